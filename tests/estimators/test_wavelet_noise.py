"""Wavelet MAD noise level: known σ, the torch path equals scikit-image's (when PyWavelets is installed)."""

import warnings

import numpy as np
import pytest
import torch

from camhealth.estimators.wavelet_noise import DB2_DEC_HI, diagonal_detail_db2, skimage_available, wavelet_noise_sigma
from tests.estimators.conftest import add_noise


@pytest.mark.parametrize("sigma", [2.0, 5.0, 10.0, 25.0])
def test_flat_recovers_sigma_within_4_percent(flat, sigma):
    est = wavelet_noise_sigma(add_noise(flat, sigma, seed=int(sigma)))
    assert est.shape == (4,) and est.dtype == torch.float32
    assert abs(float(est.mean()) - sigma) <= 0.04 * sigma + 0.05


@pytest.mark.parametrize("sigma, tol", [(5.0, 0.8), (10.0, 0.8), (25.0, 1.0)])
def test_textured_recovers_sigma(textured, sigma, tol):
    est = wavelet_noise_sigma(add_noise(textured, sigma, seed=30 + int(sigma)))
    assert abs(float(est.mean()) - sigma) <= tol


def test_db2_filter_is_orthonormal_high_pass():
    h = np.array(DB2_DEC_HI)
    assert h.sum() == pytest.approx(0.0, abs=1e-12)  # kills constants
    assert (h**2).sum() == pytest.approx(1.0)  # unit norm: white noise keeps its σ in the sub-band
    assert (np.arange(4) * h).sum() == pytest.approx(0.0, abs=1e-12)  # two vanishing moments: kills ramps


def test_detail_band_shape_and_ramp_invariance():
    yy, xx = torch.meshgrid(torch.arange(21.0, dtype=torch.float64), torch.arange(30.0, dtype=torch.float64), indexing="ij")
    ramp = (0.2 + 0.01 * xx + 0.005 * yy)[None, None]
    d = diagonal_detail_db2(ramp)
    assert d.shape == (1, 12, 16)
    assert float(d[:, 1:-1, 1:-1].abs().max()) < 1e-14  # interior of a linear ramp: no detail


def test_returns_dn_floats(flat):
    x = add_noise(flat.double(), 7.3, seed=8)
    est = wavelet_noise_sigma(x, backend="torch")
    assert est.dtype == torch.float64 and float(est[0]) != round(float(est[0]))


@pytest.mark.skipif(not skimage_available(), reason="PyWavelets not installed: scikit-image's estimate_sigma unavailable")
def test_torch_path_equals_skimage(textured):
    x = add_noise(textured.double(), 9.0, seed=9)
    assert torch.allclose(wavelet_noise_sigma(x, backend="torch"), wavelet_noise_sigma(x, backend="skimage"), rtol=1e-10)


@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_constant_images_read_zero_not_nan(backend):
    x = torch.cat([torch.zeros(1, 1, 64, 64), torch.ones(1, 1, 64, 64), torch.full((1, 1, 64, 64), 0.5)])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # and without NumPy's "mean of empty slice"
        est = wavelet_noise_sigma(x, backend=backend)
    assert bool(torch.isfinite(est).all()) and torch.allclose(est, torch.zeros(3), atol=1e-20)  # (rounding: ~1e-30)


def test_backend_errors(flat):
    with pytest.raises(ValueError, match="backend"):
        wavelet_noise_sigma(flat, backend="pywt")
    if not skimage_available():
        with pytest.raises(ImportError, match="PyWavelets"):
            wavelet_noise_sigma(flat, backend="skimage")


def test_an_odd_side_is_cropped_and_small_images_are_refused():
    """Symmetric extension biases the MAD of small and odd-sized images low (33 px: −11 %): an odd side is cropped by
    one pixel, and images under MIN_SIZE px are refused naming the size."""
    from camhealth.estimators.wavelet_noise import MIN_SIZE

    g = torch.Generator().manual_seed(0)
    x = (0.5 + 10.0 / 255.0 * torch.randn(64, 1, 33, 33, generator=g)).clamp(0, 1)
    assert torch.equal(wavelet_noise_sigma(x, backend="torch"), wavelet_noise_sigma(x[..., :32, :32], backend="torch"))
    assert float(wavelet_noise_sigma(x, backend="torch").mean()) == pytest.approx(10.0, rel=0.06)
    with pytest.raises(ValueError, match=rf"images must be at least {MIN_SIZE}×{MIN_SIZE} px, got 15×15"):
        wavelet_noise_sigma(x[..., :15, :15])
