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
