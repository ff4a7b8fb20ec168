"""JPEG grid: the types of coded_frame's sample and noise_jitter_ratio's σ."""

import numpy as np
import pytest
import torch

from camhealth.estimators.jpeg_quantisation import coded_frame, noise_jitter_ratio


def _patches(dtype: torch.dtype = torch.float32) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    x = (0.5 + 3.0 / 255.0 * torch.randn(6, 1, 64, 64, generator=g, dtype=torch.float64)).clamp(0, 1)
    return ((x * 255.0).round() / 255.0).to(dtype)


@pytest.mark.parametrize("sample", [2.5, True, "4", None])
def test_a_sample_that_is_not_an_int_is_a_type_error(sample):
    """2.5 and True failed deep inside torch.linspace."""
    with pytest.raises(TypeError, match=r"sample must be an int \(patches to read\), got"):
        coded_frame(_patches(), sample)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_numpy_integer_sample_is_accepted(dtype):
    x = _patches(dtype)
    assert coded_frame(x, np.int64(3)) == coded_frame(x, 3)
    with pytest.raises(ValueError, match=r"sample = 0 is out of the allowed range \[1, inf\)"):
        coded_frame(x, np.int64(0))


@pytest.mark.parametrize("sigma", ["1", True, None, {"s": 1.0}, torch.tensor([True])])
def test_a_sigma_that_is_not_a_number_is_a_type_error(sigma):
    """"1" failed with "new(): invalid data type 'str'"."""
    with pytest.raises(TypeError, match=r"sigma_dn must be a real number or a real tensor \[DN\]"):
        noise_jitter_ratio(sigma)


def test_real_sigmas_of_every_kind_are_accepted():
    ref = noise_jitter_ratio(0.5)
    for s in (np.float32(0.5), np.float64(0.5), torch.tensor(0.5), [0.5]):
        assert torch.allclose(noise_jitter_ratio(s).reshape(-1), ref.reshape(-1))
    assert noise_jitter_ratio(1).item() == pytest.approx(1.254, abs=0.01)
