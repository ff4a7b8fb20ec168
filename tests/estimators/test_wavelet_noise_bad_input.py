"""Wavelet MAD noise level on clipped and flat areas: their coefficients are left out of the median."""

import numpy as np
import pytest
import torch

from camhealth.estimators.wavelet_noise import clipped_support_db2, diagonal_detail_db2, skimage_available, wavelet_noise_sigma

BACKENDS = ["torch"] + (["skimage"] if skimage_available() else [])


def _noise(sigma_dn: float, level: float = 0.5, b: int = 1, size: int = 128, seed: int = 0,
           dtype: torch.dtype = torch.float32) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (level + sigma_dn / 255.0 * torch.randn(b, 1, size, size, generator=g, dtype=torch.float64)).clamp(0, 1).to(dtype)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("fill", [1.0, 0.0, 0.3])
@pytest.mark.parametrize("frac", [0.25, 0.4, 0.5])
def test_saturated_black_and_flat_areas_do_not_pull_sigma_down(backend, dtype, fill, frac):
    """20 DN of white noise with a quarter to a half of the image at 255 DN, 0 DN or a flat 0.3: σ̂ stays within
    3 % of the unclipped part's (it read 12.7, 6.6 and 0.6 DN with white or flat fill)."""
    n = _noise(20.0, dtype=dtype)
    ref = float(wavelet_noise_sigma(n, backend=backend))
    x = n.clone()
    x[..., : int(128 * frac)] = fill
    est = float(wavelet_noise_sigma(x, backend=backend))
    assert est == pytest.approx(ref, rel=0.03)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_noiseless_ramp_does_not_pull_sigma_down(backend, dtype):
    """Half of the image a noiseless linear ramp: its coefficients are float rounding (≈ 1e-7 in float32), not 0; it
    read 0.7 DN for 20 DN of noise."""
    n = _noise(20.0, dtype=dtype)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, 128, dtype=dtype), torch.linspace(0, 1, 128, dtype=dtype), indexing="ij")
    x = n.clone()
    x[..., :64] = 0.2 + 0.5 * xx[:, :64] + 0.1 * yy[:, :64]
    assert float(wavelet_noise_sigma(x, backend=backend)) == pytest.approx(float(wavelet_noise_sigma(n, backend=backend)),
                                                                           rel=0.03)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float16, torch.float32, torch.float64])
def test_constant_image_reads_exactly_zero(backend, dtype):
    x = torch.cat([torch.ones(1, 1, 32, 32), torch.full((1, 1, 32, 32), 0.3), torch.zeros(1, 1, 32, 32)]).to(dtype)
    est = wavelet_noise_sigma(x, backend=backend)
    assert torch.equal(est, torch.zeros(3, dtype=est.dtype))


def _noisy_ramps(dtype: torch.dtype, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    h, w = 64 + 17 * seed, 96
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h, dtype=torch.float64), torch.linspace(0, 1, w, dtype=torch.float64),
                            indexing="ij")
    sig = torch.rand(8, 1, 1, 1, generator=g, dtype=torch.float64) * 10.0 + 1.0
    return (0.2 + 0.3 * (xx + yy) + sig / 255.0 * torch.randn(8, 1, h, w, generator=g, dtype=torch.float64)).clamp(0, 1).to(dtype)


@pytest.mark.skipif(not skimage_available(), reason="PyWavelets not installed: scikit-image's estimate_sigma unavailable")
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("eight_bit", [False, True])
def test_unclipped_images_read_exactly_what_estimate_sigma_returns(dtype, seed, eight_bit):
    """Nothing is left out of an unclipped noisy ramp, 8-bit ones included (whose few tiny coefficients are isolated):
    both backends give scikit-image's number (the skimage backend bit for bit)."""
    from skimage.restoration import estimate_sigma

    x = _noisy_ramps(torch.float64, seed)
    x = ((x * 255.0).round() / 255.0 if eight_bit else x).to(dtype)
    h, w = x.shape[-2:]
    x = x[..., : h - h % 2, : w - w % 2]
    ref = np.asarray(estimate_sigma(x[:, 0].double().numpy().transpose(1, 2, 0), average_sigmas=False, channel_axis=-1))
    ref = torch.as_tensor(255.0 * ref).to(wavelet_noise_sigma(x).dtype)
    assert torch.equal(wavelet_noise_sigma(x, backend="skimage"), ref)
    # (8-bit values: a coefficient exactly 0 on one path can be float rounding on the other, and only exact zeros are
    # left out, as scikit-image does: the paths then differ by a part in 10⁴ or less)
    assert torch.allclose(wavelet_noise_sigma(x, backend="torch"), ref, rtol=1e-3 if eight_bit else 1e-6)


@pytest.mark.skipif(not skimage_available(), reason="PyWavelets not installed: scikit-image's estimate_sigma unavailable")
@pytest.mark.parametrize("sigma", [0.3, 0.5, 1.0, 5.0])
def test_low_8_bit_noise_reads_what_estimate_sigma_returns(sigma):
    """8-bit noise of 0.3–5 DN makes isolated coefficients of float rounding (0.01–1 % of them): kept, so σ̂ is
    scikit-image's (leaving out every tiny coefficient moved it by up to 3 %)."""
    from skimage.restoration import estimate_sigma

    x = (_noise(sigma, b=4, seed=int(10 * sigma), dtype=torch.float64) * 255.0).round() / 255.0
    ref = 255.0 * np.asarray(estimate_sigma(x[:, 0].numpy().transpose(1, 2, 0), average_sigmas=False, channel_axis=-1))
    assert torch.equal(wavelet_noise_sigma(x, backend="skimage"), torch.as_tensor(ref))


def test_scattered_clipping_of_strong_noise_is_kept():
    """60 DN at mid-grey clips 3.5 % of the pixels, scattered: no coefficient's support is more than half clipped, so
    nothing is left out (leaving out every one that touches a clipped pixel read −7 %)."""
    x = _noise(60.0, b=4, seed=3)
    assert float(((x <= 0.5 / 255) | (x >= 254.5 / 255)).float().mean()) > 0.02
    assert not bool(clipped_support_db2(x).any())
    d = diagonal_detail_db2(x).abs().flatten(1)
    every = torch.quantile(d, 0.5, dim=1) / 0.6744897501960817 * 255.0  # the median of every coefficient
    assert torch.allclose(wavelet_noise_sigma(x, backend="torch").double(), every, rtol=1e-6)


def test_clipped_support_marks_only_majority_clipped_coefficients():
    x = torch.full((1, 1, 32, 32), 0.5)
    x[..., :, :16] = 1.0  # columns 0…15 saturated
    m = clipped_support_db2(x)[0]
    assert bool(m[:, :7].all()) and not bool(m[:, 9:].any())
