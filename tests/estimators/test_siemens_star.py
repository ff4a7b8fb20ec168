"""ISO 15775 Siemens star: Coltman's CTF↔MTF series, Gaussian fit, and the measured MTF within a stated
AMAE of the analytic disk / line MTFs on the synthetic star."""

import math

import pytest
import torch

from camhealth.estimators.charts import siemens_star_chart, siemens_star_geometry
from camhealth.estimators.siemens_star import (
    coltman_coefficients,
    ctf_from_mtf,
    gaussian_ctf_fit,
    mtf_from_ctf,
    siemens_star_ctf,
    siemens_star_mtf,
)
from camhealth.metrics import amae
from camhealth.physics import NORMALIZED_FREQUENCIES, apply_psf, defocus_psf, linear_motion_psf
from camhealth.physics.mtf import disk_mtf, line_mtf

F = torch.tensor(NORMALIZED_FREQUENCIES, dtype=torch.float64) / 2.0
SIZES = torch.tensor([3.0, 7.0, 11.0], dtype=torch.float64)


@pytest.fixture(scope="module")
def star():
    return siemens_star_chart(512)


def test_coltman_coefficients():
    k, b = coltman_coefficients(15)
    assert k.tolist() == [1, 3, 5, 7, 11, 13, 15]  # 9 is not square-free
    assert (b * k).tolist() == [1, 1, -1, 1, 1, -1, -1]
    assert math.pi / 4 * float(coltman_coefficients(99)[1].sum()) == pytest.approx(1.0, abs=0.02)


def test_series_round_trip():
    """CTF from a known MTF by the square-wave series, then Eq. 3.25 gives the MTF back."""
    mtf = lambda f: torch.exp(-(f / 0.3) ** 2)  # noqa: E731
    f = torch.tensor([0.05, 0.1, 0.2, 0.3, 0.5], dtype=torch.float64)
    ctf = lambda q: ctf_from_mtf(mtf, q)  # noqa: E731
    assert torch.allclose(mtf_from_ctf(ctf, f, k_max=49), mtf(f), atol=2e-3)
    assert bool((ctf(f) > mtf(f)).all())  # a square wave keeps more contrast than a sine


def test_gaussian_fit_recovers_parameters():
    f = torch.linspace(0.05, 1.0, 60, dtype=torch.float64)
    ctf = torch.stack([torch.exp(-0.5 * ((f - 0.1) / 0.2) ** 2), torch.exp(-0.5 * (f / 0.4) ** 2)])
    mu, s = gaussian_ctf_fit(f, ctf)
    assert mu.tolist() == pytest.approx([0.1, 0.0], abs=1e-4) and s.tolist() == pytest.approx([0.2, 0.4], abs=1e-4)


def test_defocus_matches_analytic_disk_within_5_percent(star):
    img = apply_psf(star.expand(3, -1, -1, -1).contiguous(), defocus_psf(SIZES.float(), 13))
    res = siemens_star_mtf(img.double())
    analytic = torch.stack([disk_mtf(float(d), F) * torch.sinc(F) for d in SIZES]).repeat(1, 2)
    assert res.mtf.shape == (3, 16) and res.ctf_d.shape[:2] == (3, 2)
    assert float(amae(res.mtf, analytic).max()) < 5.0
    # isotropic blur: H and V agree
    assert float((res.mtf[:, :8] - res.mtf[:, 8:]).abs().max()) < 0.03


def test_linear_motion_matches_analytic_line_within_8_percent(star):
    img = apply_psf(star.expand(3, -1, -1, -1).contiguous(), linear_motion_psf(SIZES.float(), torch.zeros(3), 13))
    res = siemens_star_mtf(img)
    an = torch.stack([torch.cat([line_mtf(float(d), F) * torch.sinc(F), torch.ones(8, dtype=torch.float64)]) for d in SIZES])
    assert float(amae(res.mtf, an).max()) < 8.0
    assert bool((res.mtf[:, :8].mean(1) < res.mtf[:, 8:].mean(1)).all())  # horizontal motion: H blurrier than V


def test_ctf_geometry_and_reference_levels(star):
    fn, ctf, r = siemens_star_ctf(star)
    assert fn.max() <= 1.0 and fn.min() < 0.05
    assert torch.allclose(fn, 32 / (math.pi * r))  # Eq. 3.22
    assert float(torch.nanmean(ctf)) == pytest.approx(1.0, abs=0.02)  # sharp chart: full contrast
    fn2, ctf2, _ = siemens_star_ctf(star, levels=(0.2, 0.8))
    assert torch.allclose(ctf, ctf2, equal_nan=True)
    assert siemens_star_geometry(512) == (255.5, 255.5, 0.47 * 512)


def test_errors(star):
    with pytest.raises(ValueError, match="n_sectors"):
        siemens_star_ctf(star, n_sectors=6)
    with pytest.raises(ValueError, match="modulation"):
        siemens_star_ctf(torch.full((1, 1, 512, 512), 0.5))
    # a black image (0/0 modulation), alone or in a batch with a good chart, is refused, naming which image
    for batch in (torch.zeros(1, 1, 512, 512), torch.cat([star[:1], torch.zeros(1, 1, 512, 512)])):
        with pytest.raises(ValueError, match=r"modulation .* of image \d+ = nan"):
            siemens_star_mtf(batch)
    with pytest.raises(ValueError, match="square"):
        siemens_star_ctf(torch.rand(1, 1, 64, 80))
    with pytest.raises(ValueError, match="frequencies"):
        siemens_star_mtf(star, frequencies=[2.0])


@pytest.mark.parametrize(
    "kw,match",
    [({"n_cycles": 0}, r"n_cycles = 0 must be an int in \[4, ∞\)"), ({"n_cycles": -5}, r"n_cycles = -5 must be an int in \[4, ∞\)"),
     ({"n_cycles": 32.5}, r"n_cycles = 32.5 must be an int in \[4, ∞\)"), ({"n_cycles": True}, "n_cycles = True"),
     ({"margin": -50.0}, r"margin = -50.0 must be a finite number of px in \[0, ∞\)"),
     ({"margin": float("nan")}, r"margin = nan must be a finite")],
)
def test_bad_star_geometry_is_refused(kw, match):
    """A star geometry the measurement cannot use (n_cycles = −5 would give MTF ≡ 0, n_cycles = 0 ≈ 1) is refused,
    naming the value and the allowed range."""
    star = siemens_star_chart(256)
    with pytest.raises(ValueError, match=match):
        siemens_star_mtf(star, **kw)
    with pytest.raises(ValueError, match=match):
        siemens_star_ctf(star, **kw)


def test_sharp_chart_reads_at_most_1_after_the_aperture_correction():
    """The max − min CTF of a sharp area-rendered chart reads 1 already, so dividing by the pixel aperture would give
    up to 1.165 (f_n 0.6): the MTF is clamped to [0, 1]."""
    star = siemens_star_chart(256)
    m = siemens_star_mtf(star).mtf
    assert float(m.min()) >= 0.0 and float(m.max()) <= 1.0
    assert torch.allclose(m, torch.ones_like(m), atol=0.02)


@pytest.mark.parametrize("gain, offset, which", [(1.5, 0.0, "bright"), (2.5, 0.0, "bright"), (1.0, -0.25, "dark")])
def test_a_clipped_star_is_refused(gain, offset, which):
    """An over-exposed star (7 px defocus × gain, clipped to [0, 1]) read wrong with no warning: gain 2.5 (56 % of the
    pixels clipped) gave 9.1 % AMAE against 0.9 % unclipped. Clipped reference corners hide the chart's contrast: refused,
    naming the image and the clipped share."""
    x = (apply_psf(siemens_star_chart(512), defocus_psf(torch.tensor([7.0]), 9)) * gain + offset).clamp(0, 1)
    with pytest.raises(ValueError, match=rf"images\[0\]: the {which} reference corners are clipped \(\d+ % of their pixels"):
        siemens_star_mtf(x)


def test_clipped_rings_are_refused_even_with_the_levels_given():
    x = (apply_psf(siemens_star_chart(512), defocus_psf(torch.tensor([7.0]), 9)) * 1.5).clamp(0, 1)
    with pytest.raises(ValueError, match=r"images\[0\]: the star is clipped: \d+ of its \d+ measured rings .* more than "
                                         r"10 % of their pixels on clipped plateaus"):
        siemens_star_mtf(x, levels=(0.3, 1.2))


def test_noise_clipping_single_pixels_is_not_a_clipped_star():
    """25 DN of noise on the 0.2/0.8 levels clips ≈ 2 % of the pixels, one by one: not refused as a clipped star (it is
    read as too noisy: 25 DN is 16 % of the chart's 153-DN contrast)."""
    clean = apply_psf(siemens_star_chart(512), defocus_psf(torch.tensor([3.0]), 5))
    g = torch.Generator().manual_seed(0)
    x = (clean.expand(2, -1, -1, -1) + 25 / 255 * torch.randn(2, 1, 512, 512, generator=g)).clamp(0, 1)
    assert float(((x <= 0.5 / 255) | (x >= 1 - 0.5 / 255)).float().mean()) > 0.01
    res = siemens_star_mtf(x)
    assert all(r.startswith("noisy: σ = 2") and "% of the chart's contrast" in r for r in res.reasons)
    assert not bool(res.assessable.any()) and bool(torch.isnan(res.mtf).all())


@pytest.mark.parametrize("bad, error, match", [
    ([[0.5]], TypeError, "images must be a torch.Tensor, got list"),
    (torch.zeros(1, 1, 64, 64, dtype=torch.int64), TypeError, "images must be a floating tensor"),
    (siemens_star_chart(256) * 255.0, ValueError, r"images must lie in \[0, 1\] \(DN/255\), got values in \[51, 204\]"),
])
def test_bad_images_are_refused_before_they_are_used(bad, error, match):
    """A list reached ``images.dtype`` before the check and failed with an AttributeError."""
    with pytest.raises(error, match=match):
        siemens_star_mtf(bad)


# ------------------------------------------------------------------------------------------------ noise
def _gauss_psf(sigma_px: float, size: int = 41) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - size // 2
    g = torch.exp(-0.5 * (x / sigma_px) ** 2)
    k = g[:, None] * g[None, :]
    return (k / k.sum()).float()[None]


def _gauss_mtf(sigma_px: float) -> torch.Tensor:
    f = torch.tensor(NORMALIZED_FREQUENCIES, dtype=torch.float64)
    m = torch.exp(-0.5 * (math.pi * sigma_px * f) ** 2)  # f_n/2 cycles/px
    return torch.cat([m, m])


def test_expected_maximum_of_normal_samples_matches_closed_forms():
    from camhealth.estimators.siemens_star import _expected_max

    e = _expected_max(torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    assert e.tolist() == pytest.approx([0.0, 1 / math.sqrt(math.pi), 1.5 / math.sqrt(math.pi)], abs=1e-3)


@pytest.mark.parametrize("dn", [5.0, 10.0, 15.0])
def test_white_noise_is_taken_out_of_the_ring_contrast(star, dn):
    """A star blurred by a Gaussian of σ = 2 px read 26–35 % AMAE at 5–15 DN of white noise (the noise's extremes put a
    floor under every ring's I_max − I_min, and the fit followed it); with the noise's expected excess removed it reads
    within 4.5 %."""
    g = torch.Generator().manual_seed(1)
    blurred = apply_psf(star, _gauss_psf(2.0))
    x = (blurred.expand(2, -1, -1, -1) + dn / 255 * torch.randn(2, 1, 512, 512, generator=g)).clamp(0, 1)
    res = siemens_star_mtf(x)
    assert bool(res.assessable.all()) and res.reasons == ["", ""]
    assert res.noise_dn.tolist() == pytest.approx([dn, dn], rel=0.05)
    assert float(amae(res.mtf.double(), _gauss_mtf(2.0).expand(2, -1)).max()) < 4.5
    raw = siemens_star_mtf(x, levels=(0.2, 0.8))  # levels given: no corners read, no noise known, no correction
    assert raw.noise_dn is None and (dn < 10 or float(amae(raw.mtf.double(), _gauss_mtf(2.0).expand(2, -1)).min()) > 4.5)


def test_a_noise_free_star_is_read_as_before(star):
    """Noise-free, every ring is used and nothing is subtracted: the same MTF as with the levels given."""
    x = apply_psf(star, _gauss_psf(2.0))
    res = siemens_star_mtf(x)
    assert float(res.noise_dn[0]) < 0.5 and int(res.rings_used.min()) == res.frequencies.numel()
    torch.testing.assert_close(res.mtf, siemens_star_mtf(x, levels=(0.2, 0.8)).mtf, atol=0.01, rtol=0)


def test_noise_blurred_with_the_scene_counts_its_correlation(star):
    """Photon noise before a motion blur is correlated along the motion: fewer independent pixels compete for a ring's
    extremes, and little is subtracted. The corners' lag-1 correlation says so, and the reading stays as close to the
    noise-free one as the uncorrected reading is (white-noise excess subtracted here instead made the evaluation's
    7-px motion at 10 DN read 16 % instead of 4.4 %)."""
    from camhealth.estimators.siemens_star import _star_ctf

    g = torch.Generator().manual_seed(2)
    noisy = (star + 15 / 255 * torch.randn(1, 1, 512, 512, generator=g)).clamp(0, 1)
    psf = linear_motion_psf(torch.tensor([11.0]), torch.tensor([0.0]), 13)
    x, clean = apply_psf(noisy, psf), apply_psf(star, psf)
    c = _star_ctf(x)
    assert float(c.rho[0, 0]) > 0.8 and float(c.rho[0, 1]) < 0.1  # along rows (the motion), not along columns
    label = siemens_star_mtf(clean).mtf.double()
    err = float(amae(siemens_star_mtf(x).mtf.double(), label))
    assert err < 5.0 and err <= float(amae(siemens_star_mtf(x, levels=(0.2, 0.8)).mtf.double(), label)) + 0.5


def test_a_star_too_noisy_to_read_says_so(star):
    x = (apply_psf(star, _gauss_psf(2.0)) + 30 / 255 * torch.randn(1, 1, 512, 512, generator=torch.Generator().manual_seed(3)))
    res = siemens_star_mtf(x.clamp(0, 1).double())
    assert not bool(res.assessable[0]) and bool(torch.isnan(res.mtf).all()) and bool(torch.isnan(res.mu).all())
    assert res.reasons[0].startswith("noisy: σ = 3") and "at most 12 %" in res.reasons[0]
    assert res.mtf.dtype == torch.float64


def test_a_fit_on_a_narrow_band_of_rings_stays_a_falling_ctf():
    """A strongly blurred, noisy star keeps only its lowest frequencies; the fit there wandered to μ, s ≈ 600 (a flat
    MTF of 0.6). μ stays within the sampled frequencies and s within 4× them."""
    f = torch.linspace(0.048, 0.13, 40, dtype=torch.float64)
    ctf = torch.exp(-0.5 * ((f - 0.05) / 0.05) ** 2) + 0.03 * torch.sin(40 * f)
    mu, s = gaussian_ctf_fit(f, ctf[None], f.square()[None])
    assert float(mu) <= 0.13 and float(s) <= 4 * 0.13
