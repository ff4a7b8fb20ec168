"""PCA noise level on partly clipped images, the eigenvalue criterion's input checks and
NumPy integer parameters."""

import math

import numpy as np
import pytest
import torch

from camhealth.estimators.pca_noise import mean_median_noise_eigenvalue, patch_covariance_eigenvalues, pca_noise_sigma


def _noise(sigma_dn: float, b: int = 1, size: int = 128, seed: int = 0, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (0.5 + sigma_dn / 255.0 * torch.randn(b, 1, size, size, generator=g, dtype=torch.float64)).clamp(0, 1).to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("fill", [1.0, 0.0])
@pytest.mark.parametrize("frac", [0.25, 0.5])
def test_saturated_or_black_areas_do_not_pull_sigma_down(dtype, fill, frac):
    """20 DN of white noise with a quarter (half) of the image at 255 or 0 DN read 17.3 (14.0) DN: within 3 % now."""
    n = _noise(20.0, dtype=dtype)
    ref = float(pca_noise_sigma(n))
    x = n.clone()
    x[..., : int(128 * frac)] = fill
    assert float(pca_noise_sigma(x)) == pytest.approx(ref, rel=0.03)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_mostly_clipped_image_is_not_assessable(dtype):
    """85 % saturated leaves fewer than 5·r unclipped sub-patches: NaN, not a number 64 % low; an image saturated or
    black everywhere likewise (its eigenvalues NaN as well); a constant unclipped image still reads 0."""
    x = _noise(20.0, b=2, dtype=dtype)
    x[0, ..., : int(128 * 0.85)] = 1.0
    est = pca_noise_sigma(x)
    assert math.isnan(float(est[0])) and math.isfinite(float(est[1]))
    flat = torch.cat([torch.ones(1, 1, 64, 64), torch.zeros(1, 1, 64, 64), torch.full((1, 1, 64, 64), 0.3)]).to(dtype)
    est = pca_noise_sigma(flat)
    assert bool(est[:2].isnan().all()) and float(est[2]) == 0.0
    assert bool(patch_covariance_eigenvalues(flat[:1]).isnan().all())


def test_unclipped_images_of_a_batch_keep_their_numbers():
    x = _noise(8.0, b=6, seed=4)
    ref = pca_noise_sigma(x)
    x[0, ..., :60] = 1.0
    x[3, ..., :30, :] = 0.0
    est = pca_noise_sigma(x)
    keep = torch.tensor([1, 2, 4, 5])
    assert torch.equal(est[keep], ref[keep])


def test_scattered_clipping_keeps_every_sub_patch():
    """60 DN at mid-grey clips 3.5 % of the pixels: no sub-patch is more than half clipped, the number is the one of
    every sub-patch (their plain covariance)."""
    x = _noise(60.0, b=2, seed=5, dtype=torch.float64)
    cols = x.unfold(2, 8, 3).unfold(3, 8, 3).reshape(2, -1, 64)
    cols = cols - cols.mean(dim=1, keepdim=True)
    lam = torch.linalg.eigvalsh((cols.transpose(1, 2) @ cols) / cols.shape[1]).clamp_min(0.0)
    assert torch.allclose(patch_covariance_eigenvalues(x), lam, rtol=1e-9, atol=1e-15)


def test_numpy_integer_parameters_are_accepted():
    x = _noise(10.0, b=2)
    assert torch.equal(pca_noise_sigma(x, patch_size=np.int64(8), stride=np.int32(3)), pca_noise_sigma(x))
    with pytest.raises(TypeError, match=r"patch_size must be an int, got True \(bool\)"):
        pca_noise_sigma(x, patch_size=True)


@pytest.mark.parametrize("bad, error, match", [
    (torch.tensor([[5.0, 1.0, 1.0, 1.0]]), ValueError, r"sorted ascending .* row 0 is \[5\.0, 1\.0, 1\.0, 1\.0\]"),
    (torch.tensor([[-1.0, 0.5, 1.0]]), ValueError, r"must be >= 0 .* got -1"),
    (torch.tensor([1.0, 2.0, 3.0]), ValueError, r"shape \(B, r\) with r >= 1 .* got \(3,\)"),
    (torch.zeros(2, 0), ValueError, r"shape \(B, r\) with r >= 1 .* got \(2, 0\)"),
    (torch.tensor([[1.0, float("nan")]]), ValueError, "must be finite"),
    (torch.tensor([[True, True]]), TypeError, "real .* got dtype torch.bool"),
    ([[1.0, 2.0]], TypeError, "eigenvalues must be a torch.Tensor, got list"),
])
def test_mean_median_noise_eigenvalue_checks_its_input(bad, error, match):
    """Unsorted input gave 3.0, negative eigenvalues τ = −0.25, 1-D input "not enough values to unpack"."""
    with pytest.raises(error, match=match):
        mean_median_noise_eigenvalue(bad)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.int64])
def test_mean_median_noise_eigenvalue_on_valid_input(dtype):
    lam = torch.tensor([[1, 2, 2, 3, 40], [4, 4, 4, 4, 4]]).to(dtype)
    assert mean_median_noise_eigenvalue(lam).tolist() == pytest.approx([2.0, 4.0])
    assert mean_median_noise_eigenvalue(torch.zeros(0, 5, dtype=dtype)).shape == (0,)
