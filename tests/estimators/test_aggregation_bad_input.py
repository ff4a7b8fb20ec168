"""Aggregation: out-of-range and mistyped ``dim``, NumPy integers, an empty frame axis."""

import numpy as np
import pytest
import torch

from camhealth.estimators.aggregation import spatial_median, temporal_median, uncertainty_by_window

E = torch.arange(50.0).view(10, 5)  # (T = 10 frames, P = 5 patches)


@pytest.mark.parametrize("call", [
    lambda d: temporal_median(E, 3, dim=d),
    lambda d: spatial_median(E, dim=d),
    lambda d: spatial_median(E, dim=(0, d)),
    lambda d: uncertainty_by_window(E, dim=d),
])
@pytest.mark.parametrize("dim", [2, 5, -3, 7])
def test_out_of_range_dim_is_refused_not_wrapped(call, dim):
    """dim = 5 on a 2-D tensor wrapped to 1 and aggregated the patches instead of the frames."""
    with pytest.raises(ValueError, match=rf"dim = {dim} is out of range for a 2-D tensor \(allowed \[-2, 1\]\)"):
        call(dim)


@pytest.mark.parametrize("call, match", [
    (lambda: temporal_median(E, 3, dim="x"), r"dim must be an int \(an axis\), got 'x' \(str\)"),
    (lambda: temporal_median(E, 3, dim=1.0), r"dim must be an int \(an axis\), got 1\.0 \(float\)"),
    (lambda: temporal_median(E, 3, dim=True), r"dim must be an int \(an axis\), got True \(bool\)"),
    (lambda: spatial_median(E, dim=1.0), r"dim must be an int or a sequence of ints \(axes\), got 1\.0 \(float\)"),
    (lambda: spatial_median(E, dim="ab"), r"dim must be an int or a sequence of ints \(axes\), got 'ab' \(str\)"),
    (lambda: spatial_median(E, dim=(0, 1.5)), r"dim must be an int \(an axis\), got 1\.5 \(float\)"),
    (lambda: uncertainty_by_window(E, dim="0"), r"dim must be an int \(an axis\), got '0' \(str\)"),
])
def test_mistyped_dim_is_a_type_error_naming_it(call, match):
    with pytest.raises(TypeError, match=match):
        call()


def test_in_range_and_negative_dims_still_work():
    assert temporal_median(E, 3, dim=-2).median.shape == (8, 5)
    assert temporal_median(E.t(), 3, dim=1).median.shape == (5, 8)
    assert torch.equal(spatial_median(E, dim=-1).median, spatial_median(E, dim=1).median)
    assert uncertainty_by_window(E, windows=(2,), dim=-2)[2]["n_values"] == 9 * 5


def test_numpy_integers_are_accepted_as_ints():
    ref = temporal_median(E, 3, stride=2, dim=0)
    agg = temporal_median(E, np.int64(3), stride=np.int32(2), dim=np.int64(0))
    assert torch.equal(agg.median, ref.median)
    assert torch.equal(spatial_median(E, dim=np.int64(1)).median, spatial_median(E, dim=1).median)
    assert uncertainty_by_window(E, windows=(np.int64(2),))[2]["n_values"] == 9 * 5


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_an_empty_frame_axis_says_no_frames(dtype):
    """It said "window = 1 is out of the allowed range [1, 0]"."""
    with pytest.raises(ValueError, match=r"estimates have no frames along dim 0 \(shape \(0, 3\)\)"):
        temporal_median(torch.zeros(0, 3, dtype=dtype), 1)
    with pytest.raises(ValueError, match="no frames"):
        uncertainty_by_window(torch.zeros(0, 3, dtype=dtype))
