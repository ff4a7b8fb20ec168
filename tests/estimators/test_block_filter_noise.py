"""B+F (Shin et al. 2005, 8×16 blocks): known σ on flat and textured patches, saturation, errors."""

import pytest
import torch

from camhealth.estimators.block_filter_noise import BLOCK_SIZE, adaptive_gaussian_width, block_filter_noise_sigma
from tests.estimators.conftest import add_noise


@pytest.mark.parametrize("sigma", [1.0, 5.0, 10.0, 25.0])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_flat_recovers_sigma_within_3_percent(flat, sigma, dtype):
    est = block_filter_noise_sigma(add_noise(flat.to(dtype), sigma, seed=int(sigma)))
    assert est.dtype == dtype and est.shape == (4,)
    assert abs(float(est.mean()) - sigma) <= 0.03 * sigma + 0.05


@pytest.mark.parametrize("sigma", [5.0, 10.0, 25.0])
def test_textured_recovers_sigma_within_8_percent(textured, sigma):
    est = block_filter_noise_sigma(add_noise(textured, sigma, seed=20 + int(sigma)))
    assert abs(float(est.mean()) - sigma) <= 0.08 * sigma


def test_default_block_is_the_thesis_8x16():
    assert BLOCK_SIZE == (8, 16)


def test_filter_width_grows_with_noise_and_is_bounded():
    w = adaptive_gaussian_width(torch.tensor([0.0, 5.0, 20.0, 100.0]))
    assert w.tolist() == pytest.approx([0.5, 1.0, 2.5, 3.0])


def test_saturated_blocks_are_ignored(flat):
    x = add_noise(flat, 8.0, seed=5)
    x[:, :, :64, :] = 1.0  # top half blown out: σ = 0 there would otherwise be "the most homogeneous"
    est = block_filter_noise_sigma(x)
    # the filter reaches across the saturation border into the next blocks: a little step leaks in (≤ 2 DN)
    assert 8.0 - 0.5 <= float(est.mean()) <= 8.0 + 2.0


def test_batch_independence(flat, textured):
    x = torch.cat([add_noise(flat, 3.0, 6), add_noise(textured, 12.0, 7)])
    full = block_filter_noise_sigma(x)
    single = torch.cat([block_filter_noise_sigma(x[i : i + 1]) for i in range(len(x))])
    assert torch.allclose(full, single, rtol=1e-5)


def test_constant_image_gives_zero():
    assert torch.allclose(block_filter_noise_sigma(torch.full((2, 1, 32, 32), 0.4)), torch.zeros(2))


def test_bad_arguments():
    x = torch.rand(1, 1, 32, 32)
    with pytest.raises(ValueError, match="fraction"):
        block_filter_noise_sigma(x, fraction=0.0)
    with pytest.raises(TypeError, match="block"):
        block_filter_noise_sigma(x, block=8)
    with pytest.raises(ValueError, match="at least"):
        block_filter_noise_sigma(torch.rand(1, 1, 4, 4))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        block_filter_noise_sigma(x - 0.5)
