"""Aggregation: out-of-range and mistyped ``dim``, NumPy integers, an empty frame axis, more estimates than
``torch.nanquantile`` takes."""

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


def test_more_estimates_than_torch_quantile_takes_still_give_their_median():
    """torch.nanquantile refuses a row of more than 2²⁴ values ("quantile() input tensor is too large"): the median of
    a long recording's patches, pooled, raised that RuntimeError from deep inside torch."""
    n = 2**24 + 3
    x = torch.linspace(0.0, 1.0, n)
    x[::4] = float("nan")
    agg = spatial_median(x)
    kept = x[~torch.isnan(x)].double()  # (ascending already)
    m = kept.numel()
    assert int(agg.count) == m
    assert float(agg.median) == pytest.approx(0.5 * float(kept[(m - 1) // 2] + kept[m // 2]), abs=1e-7)
    assert float(agg.low) == float(kept[0]) and float(agg.high) == float(kept[-1])
    assert float(agg.spread) == pytest.approx(0.25 * 1.4826022185056018, rel=1e-4)  # MAD of a uniform: a quarter


@pytest.mark.parametrize("n", [1, 2, 3, 10, 11])
def test_the_sorted_median_of_long_rows_is_torch_quantiles(monkeypatch, n):
    """Rows longer than the limit are sorted instead: the same median (and NaN for a row without values)."""
    import camhealth.estimators.aggregation as aggregation

    w = torch.rand(4, n, generator=torch.Generator().manual_seed(n))
    w[0] = float("nan")
    w[1, 0] = float("nan")
    ref = spatial_median(w)
    monkeypatch.setattr(aggregation, "_QUANTILE_LIMIT", 0)
    got = spatial_median(w)
    for field in ("median", "spread", "low", "high", "count"):
        torch.testing.assert_close(getattr(got, field), getattr(ref, field), equal_nan=True, atol=0, rtol=0)
