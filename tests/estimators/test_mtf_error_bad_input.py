"""MTF error table: negative, NaN and mistyped inputs."""

import math

import numpy as np
import pytest
import torch

from camhealth.estimators.mtf_error import (
    MTFErrorTable, fit_error_table, frame_uncertainty, mtf_uncertainty, shared_error_fraction,
)

T = MTFErrorTable((0.0, 0.5, 1.0), (0.02, 0.2, 0.04), 100)


@pytest.mark.parametrize("spread", [-1.0, -1e-3, float("inf"), float("-inf")])
def test_a_spread_that_is_not_a_standard_deviation_is_refused(spread):
    """spread = −1 gave 1.016 (squared silently)."""
    with pytest.raises(ValueError, match=r"spread must be a standard deviation \(≥ 0, or NaN where not known\), got"):
        mtf_uncertainty(torch.rand(2, 16), T, torch.full((2, 16), spread))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_nan_spread_means_not_known(dtype):
    m = torch.rand(2, 16, dtype=dtype)
    s = torch.full((2, 16), 0.1, dtype=dtype)
    s[0, 3] = float("nan")
    u = mtf_uncertainty(m, T, s)
    assert math.isnan(float(u[0, 3])) and int(torch.isnan(u).sum()) == 1


@pytest.mark.parametrize("shape", [(3, 16), (2, 8), (16, 2)])
def test_a_spread_of_another_shape_is_refused_naming_both(shape):
    with pytest.raises(ValueError, match=rf"spread \({shape[0]}, {shape[1]}\) must have the shape of mtf \(2, 16\)"):
        mtf_uncertainty(torch.rand(2, 16), T, torch.rand(*shape))
    assert mtf_uncertainty(torch.rand(2, 16), T, torch.rand(16)).shape == (2, 16)  # broadcasting to mtf is fine


@pytest.mark.parametrize("table", [{"knots": [0, 1], "rms": [0.1, 0.1]}, "mtf", 0.1])
def test_a_table_that_is_not_one_is_a_type_error(table):
    """A dict failed with "'dict' object is not callable"."""
    with pytest.raises(TypeError, match="table must be an MTFErrorTable or None, got"):
        mtf_uncertainty(torch.rand(2, 16), table)
    with pytest.raises(TypeError, match="table must be an MTFErrorTable, got"):
        shared_error_fraction([(torch.rand(3, 16), torch.rand(3, 16))], table)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_frame_uncertainty_refuses_a_negative_uncertainty(dtype):
    """−0.1 gave −0.087."""
    with pytest.raises(ValueError, match=r"estimator_std must be an uncertainty \(≥ 0, or NaN where not known\), got -0\.1"):
        frame_uncertainty(torch.tensor([-0.1], dtype=dtype), 3, 0.5)
    out = frame_uncertainty(torch.tensor([float("nan"), 0.2], dtype=dtype), 3, np.float32(0.5))
    assert math.isnan(float(out[0])) and float(out[1]) == pytest.approx(0.2 * math.sqrt(0.5 + math.pi / 4 / 3), rel=1e-6)
    with pytest.raises(TypeError, match=r"shared must be a number in \[0, 1\], got '0\.5' \(str\)"):
        frame_uncertainty(torch.tensor([0.2]), 3, "0.5")


def test_shared_error_fraction_refuses_a_nan_truth_naming_the_frame():
    """A NaN truth gave 0.0 silently."""
    good = (torch.rand(3, 16), torch.rand(3, 16))
    bad = (torch.rand(3, 16), torch.full((3, 16), float("nan")))
    with pytest.raises(ValueError, match=r"frames\[1\]: estimate and truth must be finite"):
        shared_error_fraction([good, bad], T)


def test_fit_error_table_refuses_a_float_mask_and_a_fractional_min_values():
    g = torch.Generator().manual_seed(0)
    est = torch.rand(40, 16, generator=g)
    tru = est + 0.05
    with pytest.raises(TypeError, match=r"valid must be a bool tensor .* got dtype torch\.float32"):
        fit_error_table(est, tru, torch.ones(40))
    for mv in (2.5, True, "8"):
        with pytest.raises(TypeError, match=r"min_values must be an int \(values per knot\)"):
            fit_error_table(est, tru, min_values=mv)
    assert fit_error_table(est, tru, min_values=np.int64(8)) == fit_error_table(est, tru, min_values=8)


def test_from_dict_names_the_prefix_once():
    """It said "mtf_error: mtf_error: values = 0 …"."""
    with pytest.raises(ValueError, match=r"^mtf_error: values = 0 must be a positive integer$"):
        MTFErrorTable.from_dict({"knots": [0, 1], "rms": [0.1, 0.1]})
    with pytest.raises(ValueError, match=r"^w\.pt: mtf_error: values = 0 must be a positive integer$"):
        MTFErrorTable.from_dict({"knots": [0, 1], "rms": [0.1, 0.1]}, "w.pt")


def test_numpy_scalars_are_accepted_in_a_table():
    t = MTFErrorTable((0.0, 1.0), (0.1, 0.1), np.int64(3), shared=np.float32(0.5))
    assert t.values == 3 and type(t.values) is int and t.shared == 0.5
    assert MTFErrorTable.from_dict(t.to_dict()) == t
