"""Blur under noise: shapes and types of divide_out_prefilter and prefilter."""

import numpy as np
import pytest
import torch

from camhealth.estimators.blur_under_noise import divide_out_prefilter, estimate_blur_under_noise, prefilter, prefilter_mtf


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(2, 8), (3, 17), (16, 2)])
def test_an_overall_mtf_of_another_shape_is_refused_naming_both(dtype, shape):
    """(2, 8) against the (16,) prefilter MTF failed with a raw broadcast RuntimeError."""
    with pytest.raises(ValueError, match=rf"b2_mtf \(16,\) must broadcast to the shape of overall \({shape[0]}, {shape[1]}\)"):
        divide_out_prefilter(torch.rand(*shape, dtype=dtype), prefilter_mtf())


@pytest.mark.parametrize("epsilon", ["0.1", True, None, torch.tensor(0.1)])
def test_an_epsilon_that_is_not_a_number_is_a_type_error(epsilon):
    with pytest.raises(TypeError, match=r"epsilon must be a real number in \[0, 1\), got"):
        divide_out_prefilter(torch.rand(2, 16), prefilter_mtf(), epsilon=epsilon)


def test_epsilon_is_checked_before_the_estimator_runs():
    calls = []

    def est(x):
        calls.append(1)
        return torch.rand(x.shape[0], 16)

    with pytest.raises(ValueError, match=r"epsilon = 1\.5 is out of the allowed range \[0, 1\)"):
        estimate_blur_under_noise(torch.rand(2, 1, 32, 32), est, epsilon=1.5)
    assert not calls


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_numpy_scalars_are_accepted(dtype):
    x = torch.rand(2, 1, 32, 32, dtype=dtype)
    assert torch.equal(prefilter(x, np.float64(7.0)), prefilter(x, 7.0))
    assert torch.equal(prefilter(x, np.int64(5)), prefilter(x, 5.0))
    o = torch.rand(3, 16, dtype=dtype)
    a, b = divide_out_prefilter(o, prefilter_mtf(), np.float32(0.05)), divide_out_prefilter(o, prefilter_mtf(), float(np.float32(0.05)))
    assert torch.equal(a[1], b[1]) and torch.equal(torch.nan_to_num(a[0]), torch.nan_to_num(b[0]))


@pytest.mark.parametrize("d2", [torch.tensor(7.0), "7", True])
def test_a_diameter_that_is_not_a_number_is_a_type_error(d2):
    """torch.tensor(7.) was reported as "d2 = tensor(7.) is out of the allowed range"."""
    with pytest.raises(TypeError, match=r"prefilter diameter d2 must be a real number \(px\), got"):
        prefilter(torch.rand(1, 1, 16, 16), d2)
