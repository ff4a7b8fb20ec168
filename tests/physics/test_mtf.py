"""Tests for camhealth.physics.mtf (Sec. 3.3.1; 16 H/V labels at exact normalised frequencies)."""

import numpy as np
import pytest
import torch
from scipy.special import j1

from camhealth.physics.defocus_psf import defocus_psf
from camhealth.physics.motion_psf import linear_motion_psf, nonlinear_motion_psf, sample_shake_noise
from camhealth.physics.mtf import (
    NORMALIZED_FREQUENCIES,
    combine_mtf,
    disk_mtf,
    line_mtf,
    mtf_from_psf,
    mtf_hv,
    mtf_indicator,
    pixel_aperture_mtf,
)

F_CYC = np.array(NORMALIZED_FREQUENCIES) / 2.0  # cycles/px
N_ALIAS = np.arange(-4000, 4001)[:, None]


def _jinc(x):
    z = np.pi * np.asarray(x, dtype=np.float64)
    out = np.ones_like(z)
    nz = np.abs(z) > 1e-12
    out[nz] = 2.0 * j1(z[nz]) / z[nz]
    return out


def _brute_force_mtf(psf, angles_deg, f_norm):
    """numpy reference: direct DFT of one kernel at exact frequencies (uncentred coordinates)."""
    h, w = psf.shape
    yy, xx = np.mgrid[0:h, 0:w]
    out = np.zeros((len(angles_deg), len(f_norm)))
    for a, th in enumerate(np.deg2rad(angles_deg)):
        for i, fn in enumerate(f_norm):
            f = fn / 2.0
            phase = -2j * np.pi * f * (xx * np.cos(th) - yy * np.sin(th))
            out[a, i] = abs((psf * np.exp(phase)).sum()) / abs(psf.sum())
    return out


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("batch", [1, 256])
def test_matches_brute_force_dft_and_range(dtype, batch):
    g = torch.Generator().manual_seed(0)
    psf = torch.rand(batch, 9, 11, generator=g, dtype=torch.float64).to(dtype)
    angles, freqs = (0.0, 30.0, 90.0, 135.0), (0.0, 0.07, 0.1, 0.33, 0.6, 1.0)
    m = mtf_from_psf(psf, angles, freqs)
    assert m.shape == (batch, 4, 6) and m.dtype == dtype
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    for i in range(min(batch, 3)):
        ref = _brute_force_mtf(psf[i].double().numpy(), angles, freqs)
        np.testing.assert_allclose(m[i].double().numpy(), ref, atol=tol, rtol=0)
    torch.testing.assert_close(m[..., 0], torch.ones(batch, 4, dtype=dtype))  # MTF(0) = 1
    assert bool((m >= 0).all()) and bool((m <= 1 + tol).all())


def test_kernel_size_one_is_all_ones():
    m = mtf_hv(torch.full((3, 1, 1), 2.5))
    torch.testing.assert_close(m, torch.ones(3, 16))


@pytest.mark.parametrize("d", [0.5, 1.5, 3.0, 7.3, 21.0, 39.0])
def test_disk_mtf_exact_alias_sum(d):
    # The kernel is the disk integrated over 1×1 px squares, i.e. (disk ⊗ box) sampled at pixel centres.
    # Poisson summation: its DFT along x is Σ_n jinc(d(f−n))·sinc(f−n) (y-aliases vanish, sinc(m) = 0),
    # an exact identity — only the truncation of the n-sum limits the tolerance.
    m = mtf_hv(defocus_psf(torch.tensor([d], dtype=torch.float64), 41))[0].numpy()
    alias = np.abs((_jinc(d * (F_CYC - N_ALIAS)) * np.sinc(F_CYC - N_ALIAS)).sum(axis=0))
    np.testing.assert_allclose(m[:8], alias, atol=1e-6)
    np.testing.assert_allclose(m[8:], m[:8], atol=1e-12)  # isotropic: H == V


@pytest.mark.parametrize("d", [5.0, 7.0, 11.0, 15.0, 21.0, 39.0])
def test_disk_mtf_vs_jinc_times_pixel_aperture(d):
    # Kernel MTF ≈ jinc × pixel-aperture sinc (the n = 0 term of the alias sum above). The aliases
    # n = ±1 are jinc(d(1 ∓ f))·sinc(1 ∓ f) = O((π d)^-1.5 · f), small only when d is large and f low:
    # for d >= 5 px and f_n <= 0.2 they stay below 6e-3 (0.4e-3 for d = 21). Without the sinc factor
    # the error would be up to 1 − sinc(0.1) ≈ 1.6 % of the MTF.
    f_n = NORMALIZED_FREQUENCIES[:4]
    m = mtf_from_psf(defocus_psf(torch.tensor([d], dtype=torch.float64), 41), (0.0, 90.0), f_n)[0]
    f = torch.tensor(f_n, dtype=torch.float64) / 2
    expected = disk_mtf(torch.tensor(d, dtype=torch.float64), f) * pixel_aperture_mtf(f)
    torch.testing.assert_close(m, expected.expand(2, 4), atol=6e-3, rtol=0)
    np.testing.assert_allclose(expected.numpy(), np.abs(_jinc(d * f.numpy()) * np.sinc(f.numpy())), atol=1e-7)


@pytest.mark.parametrize("length", [0.5, 3.0, 4.3, 9.0, 20.0])
def test_line_mtf_horizontal(length):
    psf = linear_motion_psf(torch.tensor([length], dtype=torch.float64), torch.tensor([0.0], dtype=torch.float64), 21)
    m = mtf_hv(psf)[0].numpy()
    # H: exact alias sum of |sinc(L f)| × pixel sinc; V: the line lies in the centre row, MTF = 1.
    alias = np.abs((np.sinc(length * (F_CYC - N_ALIAS)) * np.sinc(F_CYC - N_ALIAS)).sum(axis=0))
    np.testing.assert_allclose(m[:8], alias, atol=1e-4)
    np.testing.assert_allclose(m[8:], 1.0, atol=1e-12)
    if length >= 20.0:  # aliasing ∝ 1/(π L) is small only for long lines at low frequencies
        f = torch.tensor(NORMALIZED_FREQUENCIES[:4], dtype=torch.float64) / 2
        closed = line_mtf(length, f) * pixel_aperture_mtf(f)
        np.testing.assert_allclose(m[:4], closed.numpy(), atol=3e-3)


def test_hv_swap_under_rotation():
    g = torch.Generator().manual_seed(1)
    noise = sample_shake_noise(16, generator=g, dtype=torch.float64)
    psf = nonlinear_motion_psf(torch.rand(16, generator=g, dtype=torch.float64) * 13, torch.rand(16, generator=g) * 360,
                               torch.rand(16, generator=g), noise, 15)
    m, r = mtf_hv(psf), mtf_hv(torch.rot90(psf, 1, (-2, -1)))
    torch.testing.assert_close(r[:, :8], m[:, 8:])
    torch.testing.assert_close(r[:, 8:], m[:, :8])
    length, angle = torch.full((16,), 9.0, dtype=torch.float64), torch.rand(16, generator=g, dtype=torch.float64) * 180
    a = mtf_hv(linear_motion_psf(length, angle, 11))
    b = mtf_hv(linear_motion_psf(length, angle + 90.0, 11))
    torch.testing.assert_close(b, torch.cat([a[:, 8:], a[:, :8]], dim=1), atol=1e-10, rtol=0)


def test_combine_mtf_is_mtf_of_convolution():
    disk = defocus_psf(torch.tensor([5.0], dtype=torch.float64), 9)
    line = linear_motion_psf(torch.tensor([7.0], dtype=torch.float64), torch.tensor([30.0], dtype=torch.float64), 9)
    conv = torch.nn.functional.conv2d(disk[None], line[None].flip(-1, -2), padding=8)[0]  # full convolution, 17×17
    torch.testing.assert_close(mtf_hv(conv), combine_mtf(mtf_hv(disk), mtf_hv(line)), atol=1e-12, rtol=0)
    with pytest.raises(ValueError):
        combine_mtf()


def test_closed_forms_and_indicator():
    assert disk_mtf(5.0, 0.0) == 1.0 and line_mtf(5.0, 0.0) == 1.0 and pixel_aperture_mtf(0.0) == 1.0
    assert disk_mtf(1.0, 1.2197 / 1.0) == pytest.approx(0.0, abs=1e-4)  # first jinc zero at π d f = 3.8317
    assert line_mtf(4.0, 0.25) == pytest.approx(0.0, abs=1e-12)
    labels = torch.arange(32, dtype=torch.float32).reshape(2, 16)
    torch.testing.assert_close(mtf_indicator(labels), torch.tensor([5.0, 21.0]))  # mean of indices 1 and 9
    assert mtf_indicator(mtf_hv(defocus_psf(torch.tensor([0.0]), 3))).item() == pytest.approx(1.0)


def test_bad_inputs():
    with pytest.raises(TypeError, match="psf"):
        mtf_from_psf(np.ones((1, 3, 3)))
    with pytest.raises(TypeError, match="psf"):
        mtf_from_psf(torch.ones(1, 3, 3, dtype=torch.long))
    with pytest.raises(ValueError, match="psf"):
        mtf_from_psf(torch.ones(3, 3))
    with pytest.raises(ValueError, match="non-zero sum"):
        mtf_from_psf(torch.zeros(1, 3, 3))
    with pytest.raises(ValueError, match=r"frequencies = 1.5 .*\[0, 1\]"):
        mtf_from_psf(torch.ones(1, 3, 3), frequencies=(0.1, 1.5))
    with pytest.raises(ValueError, match="nan"):
        mtf_from_psf(torch.full((1, 3, 3), float("nan")))
    with pytest.raises(ValueError, match="diameter_px = -1"):
        disk_mtf(-1.0, 0.1)
    with pytest.raises(ValueError, match="16"):
        mtf_indicator(torch.ones(2, 8))
