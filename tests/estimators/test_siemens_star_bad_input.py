"""The Siemens-star measurement and its charts on arguments they used to crash on or read silently: the star's
geometry, the chart levels, the aperture flag, the Gaussian fit without samples, Coltman's series without terms,
NumPy integer sizes, a star reaching beyond the image and frequencies that are no numbers."""

import math
import re

import numpy as np
import pytest
import torch

from camhealth.estimators.charts import siemens_star_chart, siemens_star_geometry, slanted_edge_chart
from camhealth.estimators.siemens_star import (
    coltman_coefficients, ctf_from_mtf, gaussian_ctf_fit, mtf_from_ctf, siemens_star_ctf, siemens_star_mtf,
)


@pytest.fixture(scope="module")
def star():
    return siemens_star_chart(256)


@pytest.mark.parametrize("centre", ["a", "ab", (1.0,), (1.0, 2.0, 3.0), (float("nan"), 128.0), (128.0, float("inf")),
                                    (True, 128.0), 128.0, ("127.5", "127.5")])
@pytest.mark.parametrize("fn", [siemens_star_mtf, siemens_star_ctf])
def test_a_centre_that_is_not_two_finite_numbers_is_refused(star, fn, centre):
    with pytest.raises(ValueError, match=r"centre = .* must be \(row, col\): two finite real numbers"):
        fn(star, centre=centre, radius=100.0)


@pytest.mark.parametrize("radius", ["a", 0.0, -5.0, float("nan"), float("inf"), True])
def test_a_radius_that_is_not_a_positive_finite_number_is_refused(star, radius):
    with pytest.raises(ValueError, match=rf"radius = {radius!r} must be a finite real number > 0"):
        siemens_star_mtf(star, centre=(127.5, 127.5), radius=radius)


@pytest.mark.parametrize("levels", [(0.2, 0.5, 0.8), (0.5,), 0.5, "ab", (0.8, 0.2), (0.5, 0.5), (-0.2, 5.0),
                                    (0.2, float("nan")), (False, True)])
@pytest.mark.parametrize("fn", [siemens_star_mtf, siemens_star_ctf])
def test_levels_that_are_not_a_dark_and_a_brighter_level_are_refused(star, fn, levels):
    """Three levels used to drop the third silently (CTF_D 1.40 on every ring), one or a number raised an IndexError
    or TypeError, and a negative or inverted pair was read as given."""
    with pytest.raises(ValueError, match=r"levels = .* must be \(dark, bright\): two finite real numbers with "
                                         r"0 ≤ dark < bright"):
        fn(star, levels=levels)


@pytest.mark.parametrize("centre, radius, corner", [((600.0, 600.0), 200.0, "dark"), ((-300.0, 600.0), 200.0, "bright")])
def test_a_star_without_a_reference_corner_of_each_level_is_refused(star, centre, radius, corner):
    """Enough far pixels, but all in one kind of quadrant: a ValueError naming the missing corner and the geometry,
    not an IndexError from the median of no pixels."""
    with pytest.raises(ValueError, match=rf"no {corner} reference corner beyond the star for centre = "
                                         rf"\({centre[0]!r}, {centre[1]!r}\), radius = {radius:g}.*pass levels="):
        siemens_star_mtf(star, centre=centre, radius=radius)


@pytest.mark.parametrize("aperture", ["no", "False", 0, 1.0, None])
def test_aperture_must_be_a_bool(star, aperture):
    with pytest.raises(TypeError, match=rf"aperture = {aperture!r} must be True or False"):
        siemens_star_mtf(star, aperture=aperture)


@pytest.mark.parametrize("batch", [(), (3,), (2, 2)])
def test_gaussian_fit_of_a_row_without_samples_is_nan(batch):
    """A row whose samples are all NaN (no sample) gets μ = s = NaN, not a confident μ = 0, s = 0.001; the rows with
    samples are fitted as alone."""
    f = torch.linspace(0.1, 1.0, 12, dtype=torch.float64)
    good = torch.exp(-0.5 * ((f - 0.1) / 0.3).square())
    ctf = good.expand(*batch, 12).clone()
    ctf.view(-1, 12)[0] = float("nan")
    mu, s = gaussian_ctf_fit(f, ctf)
    assert mu.shape == batch and s.shape == batch
    assert math.isnan(float(mu.reshape(-1)[0])) and math.isnan(float(s.reshape(-1)[0]))
    alone_mu, alone_s = gaussian_ctf_fit(f, good)
    torch.testing.assert_close(mu.reshape(-1)[1:], alone_mu.expand(mu.numel() - 1), rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(s.reshape(-1)[1:], alone_s.expand(s.numel() - 1), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("f, ctf, weight, message", [
    (torch.zeros(0), torch.zeros(2, 0), None, r"ctf has no samples: shape \(2, 0\)"),
    (torch.linspace(0, 1, 5), torch.ones(2, 3), None, r"f of shape \(5,\) and ctf of shape \(2, 3\)"),
    (torch.linspace(0, 1, 5), torch.ones(5), torch.ones(4), r"weight of shape \(4,\) and ctf of shape \(5,\)"),
    ([0.1, 0.2], torch.ones(2), None, r"f must be a torch.Tensor, got list"),
], ids=["no samples", "f and ctf lengths", "weight length", "f a list"])
def test_gaussian_fit_refuses_samples_it_cannot_fit(f, ctf, weight, message):
    with pytest.raises((TypeError, ValueError), match=message):
        gaussian_ctf_fit(f, ctf, weight)


@pytest.mark.parametrize("k_max", [0, -5, 2.5, True, "99"])
def test_coltman_series_without_terms_is_refused(k_max):
    """k_max below 1 gave empty coefficients and an MTF of 0 without a word."""
    with pytest.raises((TypeError, ValueError), match=rf"k_max = {k_max!r} must be an int ≥ 1"):
        coltman_coefficients(k_max)
    with pytest.raises((TypeError, ValueError), match=rf"k_max = {k_max!r} must be an int ≥ 1"):
        mtf_from_ctf(lambda f: torch.ones_like(f), torch.tensor([0.1]), k_max=k_max)
    with pytest.raises((TypeError, ValueError), match=rf"k_max = {k_max!r} must be an int ≥ 1"):
        ctf_from_mtf(lambda f: torch.ones_like(f), torch.tensor([0.1]), k_max=k_max)


@pytest.mark.parametrize("size", [np.int64(64), np.int32(128)])
def test_charts_take_numpy_integer_sizes(size):
    assert torch.equal(slanted_edge_chart(size), slanted_edge_chart(int(size)))
    assert torch.equal(siemens_star_chart(size), siemens_star_chart(int(size)))
    assert siemens_star_geometry(size) == siemens_star_geometry(int(size))


@pytest.mark.parametrize("size, error, message", [
    ("a", TypeError, r"size must be an int, got str"),
    (64.0, TypeError, r"size must be an int, got float"),
    (0, ValueError, r"size = 0 px is out of the allowed range \[1, inf\)"),
])
def test_star_geometry_checks_its_size(size, error, message):
    """siemens_star_geometry("a") raised a bare TypeError from its arithmetic."""
    with pytest.raises(error, match=message):
        siemens_star_geometry(size)


@pytest.mark.parametrize("radius_frac", ["a", 0.0, 0.6, float("nan"), True])
def test_star_geometry_checks_its_radius_fraction(radius_frac):
    with pytest.raises(ValueError, match=rf"radius_frac = {radius_frac!r} .*\(0, 0.5\]"):
        siemens_star_geometry(256, radius_frac)


@pytest.mark.parametrize("levels", [None, (0.2, 0.8)], ids=["corners", "levels"])
def test_a_star_whose_rings_lie_outside_the_image_is_not_assessable(levels):
    """A star centred above the image (the lower part of a chart cropped off the frame): no ring lies in the image in
    both of its H or V sectors. With the levels given its MTF was NaN and yet assessable, and its rings without a pixel
    had f_n = ∞; without them the reason blamed the noise."""
    chart = siemens_star_chart(512)[..., 300:, :]  # the centre, row 255.5, is 44.5 px above the crop
    res = siemens_star_mtf(chart, centre=(-44.5, 255.5), radius=240.64, levels=levels)
    assert not bool(res.assessable[0]) and torch.isnan(res.mtf).all()
    assert re.fullmatch(r"only 0 rings \(H 0, V 0\) lie in the image in both sectors of their direction; at least 10 "
                        r"are needed \(check centre= and radius=\)", res.reasons[0])
    assert torch.isfinite(res.frequencies).all()


def test_a_star_cut_by_the_image_border_is_read_from_the_rings_inside():
    """The star's top cut off by the frame: the rings that lie in the image are read, as with the whole star."""
    star = siemens_star_chart(512)
    whole = siemens_star_mtf(star, levels=(0.2, 0.8))
    cut = siemens_star_mtf(star[..., 100:, :], centre=(155.5, 255.5), radius=240.64, levels=(0.2, 0.8))
    assert bool(cut.assessable[0]) and torch.isfinite(cut.mtf).all()
    torch.testing.assert_close(cut.mtf, whole.mtf, atol=0.01, rtol=0)


@pytest.mark.parametrize("frequencies", ["abc", [0.1, "x"], None, torch.tensor([True])])
def test_frequencies_that_are_not_real_numbers_are_a_type_error(star, frequencies):
    """A string raised torch's "new(): invalid data type 'str'"; a bool tensor was read as 0 and 1 × Nyquist."""
    with pytest.raises(TypeError, match=r"frequencies must be real numbers in \[0, 1\] \(× Nyquist\), got"):
        siemens_star_mtf(star, frequencies=frequencies)


@pytest.mark.parametrize("radius_frac, error, message", [
    ("0.4", TypeError, r"radius_frac = '0.4' must be a real number in \[0.2, 0.49\] \(star radius / size\), got str"),
    (True, TypeError, r"radius_frac = True must be a real number in \[0.2, 0.49\] .*got bool"),
    (None, TypeError, r"radius_frac = None must be a real number in \[0.2, 0.49\] .*got NoneType"),
    (float("nan"), ValueError, r"radius_frac = nan is out of the allowed range \[0.2, 0.49\]"),
    (0.6, ValueError, r"radius_frac = 0.6 is out of the allowed range \[0.2, 0.49\]"),
], ids=["str", "bool", "None", "NaN", "0.6"])
def test_star_chart_checks_its_radius_fraction(radius_frac, error, message):
    """radius_frac="0.4" rendered the chart (float() of the string); True was read as 1 and refused as out of range."""
    with pytest.raises(error, match=message):
        siemens_star_chart(256, radius_frac=radius_frac)


def test_star_chart_takes_real_radius_fractions_as_before():
    ref = siemens_star_chart(256, radius_frac=0.4)
    assert torch.equal(siemens_star_chart(256, radius_frac=np.float64(0.4)), ref)
    assert torch.equal(siemens_star_chart(256, radius_frac=np.float32(0.25)), siemens_star_chart(256, radius_frac=float(np.float32(0.25))))


# ---------------------------------------------------------------------------------- consistency of the star
def _blurred_star(psf: torch.Tensor, noise_dn: float = 0.0, n: int = 1, seed: int = 0) -> torch.Tensor:
    from camhealth.physics import apply_psf

    g = torch.Generator().manual_seed(seed)
    clean = apply_psf(siemens_star_chart(512), psf.float())
    return (clean.expand(n, -1, -1, -1) + noise_dn / 255.0 * torch.randn(n, 1, 512, 512, generator=g)).clamp(0, 1)


def _gaussian(sigma_px: float) -> torch.Tensor:
    from camhealth.physics import gaussian_psf

    return gaussian_psf(torch.tensor([sigma_px]), 25)


def test_pure_noise_with_the_levels_given_is_no_star():
    """White noise of 30 DN and no star, read with the chart's levels, came back assessable with an MTF of 0.66; no ring
    holds a 32-periodic component above its noise."""
    g = torch.Generator().manual_seed(0)
    noise = (0.5 + 30 / 255 * torch.randn(3, 1, 512, 512, generator=g)).clamp(0, 1)
    res = siemens_star_mtf(noise, levels=(0.2, 0.8))
    assert not bool(res.assessable.any()) and bool(torch.isnan(res.mtf).all()) and bool(torch.isnan(res.mu).all())
    for reason in res.reasons:
        assert re.fullmatch(r"no star: [0-9] of 206 rings show a component repeating n_cycles = 32 times per turn above "
                            r"their noise \(false-alarm rate 0.001 per ring, against the ring's residual and against its "
                            r"harmonics 27, 29, 35, 37\); at least 10 are needed: is this a Siemens star of 32 cycles at "
                            r"centre = \(255.5, 255.5\), radius = 240.64 px\?", reason)


@pytest.mark.parametrize("image", ["flat", "gradient", "blurred noise", "checkerboard"])
def test_images_without_a_star_are_not_read_as_one(image):
    """Without a star, with the levels given (nothing else to refuse them): a flat image read MTF ≈ 0, assessable. Noise
    blurred after it is drawn has most of its power at low frequencies: the neighbouring harmonics keep it from reading
    as a star where the ring's residual alone would not (with noise of that colour it passes there on ≈ 20 % of the
    rings)."""
    from camhealth.physics import apply_psf

    yy, xx = torch.meshgrid(torch.arange(512.0), torch.arange(512.0), indexing="ij")
    g = torch.Generator().manual_seed(4)
    x = {"flat": torch.full((1, 1, 512, 512), 0.45),
         "gradient": (0.2 + 0.6 * xx / 511).expand(1, 1, -1, -1),
         "blurred noise": apply_psf((0.5 + 60 / 255 * torch.randn(2, 1, 512, 512, generator=g)).clamp(0, 1),
                                    _gaussian(2.0).float().expand(2, -1, -1)),
         "checkerboard": (0.2 + 0.6 * ((yy // 16 + xx // 16) % 2)).expand(1, 1, -1, -1)}[image]
    res = siemens_star_mtf(x.contiguous(), levels=(0.2, 0.8))
    assert not bool(res.assessable.any()) and bool(torch.isnan(res.mtf).all())
    assert all(r.startswith("no star: ") for r in res.reasons)


@pytest.mark.parametrize("levels, match", [
    ((0.0, 0.001), r"levels: the star's mean, 127.5 DN, lies 500× the contrast I_w − I_b = 0.3 DN from the mid level "
                   r"\(I_b \+ I_w\)/2 = 0.1 DN of the levels given; at most 0.25"),
    ((51.0, 204.0), r"levels: the star's mean, 127.5 DN, lies 0.83× the contrast"),
    ((0.1, 0.4), r"levels: the star's mean, 127.5 DN, lies 0.834× the contrast I_w − I_b = 76.5 DN"),
    ((0.45, 0.55), r"levels: the star's 32-periodic component reaches 5.\d\d× that of an unblurred chart of contrast "
                   r"I_w − I_b = 25.5 DN \(the levels given\); at most 1.5: the star's contrast is larger"),
], ids=["(0, 0.001)", "DN", "(0.1, 0.4)", "(0.45, 0.55)"])
def test_levels_the_star_contradicts_are_refused(levels, match):
    """levels=(0, 0.001) on the 0.2/0.8 chart read an MTF of 0.24 (0.64 unblurred) as assessable: a blur keeps the
    star's mean, 127.5 DN here, which such levels cannot give; levels closer together than the chart's read its contrast
    as more than an unblurred chart can have (and the MTF ≡ 1)."""
    res = siemens_star_mtf(_blurred_star(_gaussian(2.0)), levels=levels)
    assert not bool(res.assessable[0]) and bool(torch.isnan(res.mtf).all())
    assert re.match(match, res.reasons[0]), res.reasons[0]


@pytest.mark.parametrize("levels", [None, (0.2, 0.8)], ids=["corners", "levels"])
@pytest.mark.parametrize("n_cycles, match", [
    (96, r"n_cycles: the star repeats 32 times per turn, not n_cycles = 96: on the \d+ rings where its 96-periodic "
         r"component shows, the 32-periodic one carries \d+\.?\d*× its power \(a star of n_cycles has none at "
         r"n_cycles/3\)"),
    (64, r"no star: 0 of \d+ rings show a component repeating n_cycles = 64 times .*; their 32-periodic component "
         r"carries .*× the power of the 64-periodic one; at least 10 are needed"),
    (40, r"no star: 0 of 203 rings show a component repeating n_cycles = 40 times"),
    (16, r"no star: 0 of \d+ rings show a component repeating n_cycles = 16 times"),
])
def test_a_wrong_number_of_cycles_is_refused(n_cycles, match, levels):
    """A 32-cycle star read with n_cycles = 96 (its third harmonic) read an MTF of 0.81 as assessable, 40 read 0.46:
    the rings then repeat 32 times per turn, not n_cycles."""
    res = siemens_star_mtf(_blurred_star(_gaussian(2.0)), n_cycles=n_cycles, levels=levels)
    assert not bool(res.assessable[0]) and bool(torch.isnan(res.mtf).all())
    assert re.match(match, res.reasons[0]), res.reasons[0]


def _without_checks(monkeypatch, x, **kw):
    import camhealth.estimators.siemens_star as ss

    with monkeypatch.context() as m:
        m.setattr(ss, "_star_consistency", lambda c, ok: {})
        return siemens_star_mtf(x, **kw)


@pytest.mark.parametrize("case", ["hexagon 15 px, 25 DN, levels", "shake 15 px, 25 DN, levels", "Gaussian 2 px, 15 DN",
                                  "shake 21 px", "defocus 21 px, 15 DN", "centre 8 px off"])
def test_stars_blurred_far_and_noisy_read_as_without_the_checks(monkeypatch, case):
    """Strong blur leaves the star's component on the outer rings only, and noise hides it on some: those rings suffice.
    Every output is what the measurement gives without the consistency checks, bit for bit."""
    from camhealth.physics import defocus_psf
    from camhealth.physics.motion_psf import nonlinear_motion_psf, sample_shake_noise
    from camhealth.physics.polygon_psf import polygon_psf

    shake = lambda d: nonlinear_motion_psf(torch.tensor([d]), torch.tensor([30.0]), torch.tensor([0.7]),  # noqa: E731
                                           sample_shake_noise(1, 64, generator=torch.Generator().manual_seed(7)), 31)
    hexagon = lambda d: polygon_psf(torch.tensor([d]), 6, 31, rotation_deg=15.0)  # noqa: E731
    x, kw = {
        "hexagon 15 px, 25 DN, levels": lambda: (_blurred_star(hexagon(15.0), 25.0, 2), {"levels": (0.2, 0.8)}),
        "shake 15 px, 25 DN, levels": lambda: (_blurred_star(shake(15.0), 25.0, 2), {"levels": (0.2, 0.8)}),
        "Gaussian 2 px, 15 DN": lambda: (_blurred_star(_gaussian(2.0), 15.0, 2), {}),
        "shake 21 px": lambda: (_blurred_star(shake(21.0)), {}),
        "defocus 21 px, 15 DN": lambda: (_blurred_star(defocus_psf(torch.tensor([21.0]), 23), 15.0, 2), {}),
        "centre 8 px off": lambda: (_blurred_star(_gaussian(1.0)), {"centre": (263.5, 255.5), "radius": 240.64}),
    }[case]()
    res = siemens_star_mtf(x, **kw)
    ref = _without_checks(monkeypatch, x, **kw)
    assert bool(res.assessable.all()) and res.reasons == [""] * len(x)
    for name in ("mtf", "frequencies", "ctf_d", "mu", "s", "noise_dn", "rings_used", "assessable"):
        mine, theirs = getattr(res, name), getattr(ref, name)
        assert (mine is None and theirs is None) or torch.equal(mine, theirs), name


def test_a_refused_star_leaves_the_others_of_its_batch_as_they_are():
    star = _blurred_star(_gaussian(2.0))
    alone = siemens_star_mtf(star, levels=(0.2, 0.8))
    batch = siemens_star_mtf(torch.cat([star, torch.full_like(star, 0.5), star]), levels=(0.2, 0.8))
    assert batch.assessable.tolist() == [True, False, True] and batch.reasons[1].startswith("no star: ")
    assert torch.equal(batch.mtf[0], alone.mtf[0]) and torch.equal(batch.mtf[2], alone.mtf[0])


def test_noise_alone_seldom_shows_on_a_ring():
    """Each of the two tests passes a ring of white noise with probability 10⁻³, and a ring shows the star only where
    both pass: over 8 images × 206 rings of 5–60 DN noise no image comes near the 10 rings a star needs."""
    import camhealth.estimators.siemens_star as ss

    g = torch.Generator().manual_seed(11)
    sigma = torch.tensor([5.0, 10, 20, 30, 40, 50, 60, 60]).view(-1, 1, 1, 1)
    x = (0.5 + sigma / 255 * torch.randn(8, 1, 512, 512, generator=g)).clamp(0, 1)
    reasons = ss._star_consistency(ss._star_ctf(x, levels=(0.2, 0.8)), torch.ones(8, dtype=torch.bool))
    shown = [int(re.match(r"no star: (\d+) of 206", r).group(1)) for r in reasons.values()]
    assert len(shown) == 8 and max(shown) <= 2
