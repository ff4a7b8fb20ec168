"""PCA noise level (Chen, Zhu & Heng 2015): known σ on flat and textured patches, criterion, errors."""

import pytest
import torch

from camhealth.estimators.pca_noise import (
    MIN_SAMPLES_PER_DIMENSION,
    mean_median_noise_eigenvalue,
    patch_covariance_eigenvalues,
    pca_noise_sigma,
)
from tests.estimators.conftest import add_noise


@pytest.mark.parametrize("sigma", [2.0, 5.0, 10.0, 25.0])
def test_flat_recovers_sigma_within_5_percent(flat, sigma):
    est = pca_noise_sigma(add_noise(flat, sigma, seed=int(sigma)))
    assert est.shape == (4,) and est.dtype == torch.float32
    assert abs(float(est.mean()) - sigma) <= 0.05 * sigma + 0.1


@pytest.mark.parametrize("sigma, tol", [(5.0, 1.5), (10.0, 1.0), (25.0, 1.5)])
def test_textured_recovers_sigma(textured, sigma, tol):
    """Texture inflates small σ (the known weakness); stated tolerance 1.5 / 1.0 / 1.5 DN."""
    est = pca_noise_sigma(add_noise(textured, sigma, seed=10 + int(sigma)))
    assert abs(float(est.mean()) - sigma) <= tol


def test_returns_float_not_truncated_and_dtypes(flat):
    x = add_noise(flat.double(), 3.3, seed=1)
    e64 = pca_noise_sigma(x)
    e32 = pca_noise_sigma(x.float())
    assert e64.dtype == torch.float64 and e32.dtype == torch.float32
    assert torch.allclose(e64.float(), e32, rtol=1e-3)
    assert float(e64[0]) != round(float(e64[0]))  # a float, not an integer DN


def test_batch_independence(flat, textured):
    x = torch.cat([add_noise(flat, 5.0, 2), add_noise(textured, 15.0, 3)])
    full = pca_noise_sigma(x)
    single = torch.cat([pca_noise_sigma(x[i : i + 1]) for i in range(len(x))])
    assert torch.allclose(full, single, rtol=1e-4)


def test_constant_image_gives_zero():
    assert torch.equal(pca_noise_sigma(torch.full((2, 1, 64, 64), 0.3)), torch.zeros(2))


@pytest.mark.parametrize("size", [32, 48, 58, 59, 64, 128])
def test_too_few_sub_patches_are_refused_not_biased(size):
    """Pure noise of σ = 10 DN: σ̂ falls short by ≈ 0.7·r/n (−65 % at 32 px, n/r = 1.3, which used to be accepted).
    Sizes below MIN_SAMPLES_PER_DIMENSION · r sub-patches are refused naming n; every accepted size is within 15 %."""
    g = torch.Generator().manual_seed(size)
    x = (0.5 + torch.randn(32, 1, size, size, generator=g, dtype=torch.float64) * 10.0 / 255.0).clamp(0.0, 1.0)
    n = ((size - 8) // 3 + 1) ** 2
    if n < MIN_SAMPLES_PER_DIMENSION * 64:
        with pytest.raises(ValueError, match=rf"{size}×{size} px give only n = {n} sub-patches of 8×8 at stride 3"):
            pca_noise_sigma(x)
    else:
        assert abs(float(pca_noise_sigma(x).mean()) - 10.0) < 1.5


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
@pytest.mark.parametrize("batch", [1, 256])
def test_small_patches_name_the_stride_that_suffices(dtype, batch):
    """32 px at stride 3 is refused with the stride that gives enough sub-patches; with it σ̂ is within 10 %."""
    g = torch.Generator().manual_seed(batch)
    x = (0.5 + torch.randn(batch, 1, 32, 32, generator=g) * 10.0 / 255.0).clamp(0.0, 1.0).to(dtype)
    with pytest.raises(ValueError, match=r"n = 81 sub-patches.*stride=1 \(n = 625\)"):
        pca_noise_sigma(x)
    est = pca_noise_sigma(x, stride=1)
    assert est.shape == (batch,) and est.dtype == (torch.float64 if dtype == torch.float64 else torch.float32)
    assert abs(float(est.float().median()) - 10.0) < 1.0 + (1.5 if batch == 1 else 0.0)


def test_criterion_on_hand_made_eigenvalues():
    # noise eigenvalues 1..3 (mean 2 = median) + two signal eigenvalues: the rule stops at m = 3, τ = 2
    lam = torch.tensor([[1.0, 2.0, 3.0, 50.0, 80.0]], dtype=torch.float64)
    assert float(mean_median_noise_eigenvalue(lam)) == pytest.approx(2.0)
    # all equal: every prefix qualifies, τ = that value
    assert float(mean_median_noise_eigenvalue(torch.full((1, 6), 4.0, dtype=torch.float64))) == pytest.approx(4.0)


def test_eigenvalues_shape_and_order(flat):
    lam = patch_covariance_eigenvalues(add_noise(flat, 10.0, 4), patch_size=5, stride=2)
    assert lam.shape == (4, 25) and lam.dtype == torch.float64
    assert bool((lam[:, 1:] >= lam[:, :-1]).all())


@pytest.mark.parametrize(
    "bad, match",
    [
        (torch.rand(2, 3, 32, 32), "C = 1"),
        (torch.rand(2, 1, 32, 32) * 2, r"\[0, 1\]"),
        (torch.full((1, 1, 32, 32), float("nan")), "finite"),
        ((torch.rand(1, 1, 32, 32) * 255).to(torch.uint8), "floating"),
        (torch.rand(1, 1, 9, 9), "at least"),
    ],
)
def test_bad_input_is_rejected(bad, match):
    with pytest.raises((ValueError, TypeError), match=match):
        pca_noise_sigma(bad)


def test_bad_parameters():
    with pytest.raises(ValueError, match="patch_size"):
        pca_noise_sigma(torch.rand(1, 1, 32, 32), patch_size=1)
    with pytest.raises(TypeError, match="stride"):
        pca_noise_sigma(torch.rand(1, 1, 32, 32), stride=1.5)
