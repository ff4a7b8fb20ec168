"""B+F: blocks too small to keep σ̂ within ≈ 2 % are refused; NumPy scalars as parameters."""

import numpy as np
import pytest
import torch

from camhealth.estimators.block_filter_noise import MIN_BLOCK_AREA, block_filter_noise_sigma


def _noise(sigma_dn: float, b: int = 16, seed: int = 0, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (0.5 + sigma_dn / 255.0 * torch.randn(b, 1, 128, 128, generator=g, dtype=torch.float64)).clamp(0, 1).to(dtype)


@pytest.mark.parametrize("block", [(2, 2), (2, 4), (3, 3), (4, 4), (4, 6), (2, 15)])
def test_small_blocks_are_refused_naming_their_area(block):
    """2×2 blocks read 10 DN of white noise as 4.4 DN (−57 %), 4×4 as 8.9 DN: refused below MIN_BLOCK_AREA px."""
    with pytest.raises(ValueError, match=rf"block = \({block[0]}, {block[1]}\) px holds {block[0] * block[1]} px, fewer "
                                         rf"than the {MIN_BLOCK_AREA} px"):
        block_filter_noise_sigma(_noise(10.0, b=1), block=block)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("block", [(2, 16), (4, 8), (6, 6), (8, 16)])
@pytest.mark.parametrize("sigma", [2.0, 30.0])
def test_the_blocks_allowed_read_white_noise_within_3_percent(dtype, block, sigma):
    x = _noise(sigma, dtype=dtype, seed=int(sigma))
    assert float(block_filter_noise_sigma(x, block=block).mean()) == pytest.approx(sigma, rel=0.03)


def test_numpy_scalars_are_accepted_and_named_by_value():
    """np.float32(0.1) was refused as "fraction = 0.1 is out of the allowed range"; np.int64 block sides as non-int."""
    x = _noise(10.0, b=2)
    ref = block_filter_noise_sigma(x, block=(8, 16), fraction=0.1)
    assert torch.equal(block_filter_noise_sigma(x, block=(np.int64(8), np.int32(16)), fraction=np.float32(0.1)),
                       block_filter_noise_sigma(x, block=(8, 16), fraction=float(np.float32(0.1))))
    assert torch.equal(block_filter_noise_sigma(x, fraction=np.float64(0.1)), ref)
    with pytest.raises(ValueError, match=r"fraction = 1\.5 is out of the allowed range \(0, 1\]"):
        block_filter_noise_sigma(x, fraction=np.float32(1.5))


@pytest.mark.parametrize("fraction", ["0.1", True, None])
def test_a_fraction_that_is_not_a_number_is_a_type_error(fraction):
    with pytest.raises(TypeError, match=r"fraction must be a real number in \(0, 1\], got"):
        block_filter_noise_sigma(_noise(10.0, b=1), fraction=fraction)


@pytest.mark.parametrize("sigma0, error, message", [
    ([5.0], TypeError, r"sigma0_dn must be a torch.Tensor of noise levels σ₀ \[DN\] \(finite, ≥ 0\), got list \[5.0\]"),
    (5.0, TypeError, r"sigma0_dn must be a torch.Tensor .*got float 5.0"),
    (torch.tensor([True]), TypeError, r"sigma0_dn must hold real noise levels σ₀ \[DN\] .*got dtype torch.bool"),
    (torch.tensor([1.0, float("nan")]), ValueError, r"sigma0_dn must be finite, but 1 of 2 values are NaN/inf"),
    (torch.tensor([-2.0]), ValueError, r"sigma0_dn = -2 DN is out of the allowed range \[0, inf\] DN"),
], ids=["list", "float", "bool", "NaN", "negative"])
def test_adaptive_width_refuses_what_is_no_noise_level(sigma0, error, message):
    """A list failed on `/` inside the formula; NaN came back as a NaN width and a negative σ₀ as the narrowest filter."""
    from camhealth.estimators.block_filter_noise import adaptive_gaussian_width

    with pytest.raises(error, match=message):
        adaptive_gaussian_width(sigma0)


def test_adaptive_width_of_valid_noise_levels_is_the_formula():
    from camhealth.estimators.block_filter_noise import adaptive_gaussian_width

    for s in (torch.tensor([0.0, 5.0, 20.0, 100.0]), torch.tensor([[3.0]], dtype=torch.float64), torch.tensor([7])):
        assert torch.equal(adaptive_gaussian_width(s), (0.5 + s / 10.0).clamp(0.5, 3.0))
