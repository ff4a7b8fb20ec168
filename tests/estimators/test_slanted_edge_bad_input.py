"""Slanted edge: the ROI named when no edge is found, the SNR of each ROI, the aperture flag, a NumPy integer
oversample, frequencies that are no numbers and the ROIs of slanted_edge_mtf_hv."""

import math
import re

import numpy as np
import pytest
import torch

from camhealth.estimators.slanted_edge import MIN_SNR, slanted_edge_mtf


def _edge(b: int = 1, h: int = 64, w: int = 40, lo: float = 0.2, hi: float = 0.8, blur: float = 1.0,
          noise_dn: float = 0.0, seed: int = 0, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    t = math.tan(math.radians(5.0))
    dist = (xx - (w - 1) / 2 - t * (yy - (h - 1) / 2)) * math.cos(math.radians(5.0))
    img = (lo + (hi - lo) * 0.5 * (1 + torch.erf(dist / (blur * math.sqrt(2)))))[None, None].expand(b, 1, h, w).clone()
    if noise_dn:
        g = torch.Generator().manual_seed(seed)
        img = img + noise_dn / 255.0 * torch.randn(img.shape, generator=g, dtype=torch.float64)
    return img.clamp(0, 1).to(dtype)


@pytest.mark.parametrize("where", [0, 2])
def test_an_roi_without_an_edge_is_named(where):
    """"no edge found in some rows of the ROI" did not say which ROI of the batch."""
    x = _edge(3)
    g = torch.Generator().manual_seed(1)
    x[where] = (0.5 + 5.0 / 255.0 * torch.randn(1, 64, 40, generator=g)).clamp(0, 1)
    with pytest.raises(ValueError, match=rf"roi\[{where}\]: no edge found in \d+ of its 64 rows"):
        slanted_edge_mtf(x)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("snr", [5.0, 10.0, 20.0, 40.0])
def test_the_snr_is_the_edge_step_over_the_noise(dtype, snr):
    """Edge 0.2/0.8 (153 DN) under white noise of 153/SNR DN: the median SNR read is within 10 %, and ROIs below
    MIN_SNR are flagged (the noise moves their MTF by more than ≈ 0.025)."""
    r = slanted_edge_mtf(_edge(32, noise_dn=153.0 / snr, seed=int(snr), dtype=dtype))
    assert r.snr.shape == (32,) and r.snr.dtype == (torch.float64 if dtype == torch.float64 else torch.float32)
    assert float(r.snr.median()) == pytest.approx(snr, rel=0.1)
    flagged = float(r.low_snr.float().mean())
    if snr < 0.8 * MIN_SNR:
        assert flagged == 1.0
    elif snr > 1.5 * MIN_SNR:
        assert flagged == 0.0


def test_a_noiseless_edge_has_infinite_snr_and_is_not_flagged():
    r = slanted_edge_mtf(_edge(2))
    assert bool(torch.isinf(r.snr).all()) and not r.low_snr.any()


@pytest.mark.parametrize("aperture", ["no", "False", 0, 1.0, None])
def test_aperture_must_be_a_bool(aperture):
    """A string such as "no" read as true and divided the pixel aperture out (as siemens_star_mtf refuses it)."""
    from camhealth.estimators.charts import slanted_edge_chart
    from camhealth.estimators.slanted_edge import slanted_edge_mtf_hv

    with pytest.raises(TypeError, match=rf"aperture = {re.escape(repr(aperture))} must be True or False"):
        slanted_edge_mtf(_edge(), aperture=aperture)
    with pytest.raises(TypeError, match=r"aperture = .* must be True or False"):
        slanted_edge_mtf_hv(slanted_edge_chart(128), aperture=aperture)


def test_a_numpy_integer_oversample_is_an_int():
    """np.int64(4) was refused as "oversample = 4 must be an int in [1, 16]"."""
    roi = _edge(noise_dn=2.0)
    torch.testing.assert_close(slanted_edge_mtf(roi, oversample=np.int64(4)).mtf, slanted_edge_mtf(roi, oversample=4).mtf,
                               atol=0, rtol=0)
    with pytest.raises(ValueError, match=r"oversample = .*17.* must be an int in \[1, 16\]"):
        slanted_edge_mtf(roi, oversample=np.int64(17))


@pytest.mark.parametrize("frequencies", ["abc", [0.1, "x"], None, torch.tensor([True])])
def test_frequencies_that_are_not_real_numbers_are_a_type_error(frequencies):
    with pytest.raises(TypeError, match=r"frequencies must be real numbers in \[0, 1\] \(× Nyquist\), got"):
        slanted_edge_mtf(_edge(), frequencies=frequencies)


def test_hv_rois_of_two_sizes_give_the_mean_of_each_edge():
    """Left and right (or top and bottom) ROIs of different heights raised torch's "Sizes of tensors must match"."""
    from camhealth.estimators.charts import slanted_edge_chart, slanted_edge_rois
    from camhealth.estimators.slanted_edge import slanted_edge_mtf_hv

    g = torch.Generator().manual_seed(3)
    chart = (slanted_edge_chart(256) + 2.0 / 255 * torch.randn(2, 1, 256, 256, generator=g)).clamp(0, 1)
    rois = slanted_edge_rois(256)
    r0, r1, c0, c1 = rois["left"]
    t0, t1, u0, u1 = rois["bottom"]
    uneven = {**rois, "left": (r0 + 2, r1 - 1, c0, c1), "bottom": (t0, t1, u0 + 3, u1)}
    got = slanted_edge_mtf_hv(chart, rois=uneven)

    def mtf(box, transpose):
        a, b, c, d = box
        roi = chart[:, :, a:b, c:d]
        return slanted_edge_mtf(roi.transpose(-1, -2) if transpose else roi, aperture=True).mtf

    h = 0.5 * (mtf(uneven["left"], False) + mtf(uneven["right"], False))
    v = 0.5 * (mtf(uneven["top"], True) + mtf(uneven["bottom"], True))
    torch.testing.assert_close(got, torch.cat([h, v], dim=1), atol=1e-6, rtol=0)


@pytest.mark.parametrize("box, error, message", [
    ((83.5, 173, 25, 103), ValueError, r"roi left = \(83\.5, 173, 25, 103\) must be four ints \(row0, row1, col0, col1\)"),
    ((83, 173), ValueError, r"roi left = \(83, 173\) must be four ints"),
    ("abcd", ValueError, r"roi left = 'abcd' must be four ints"),
], ids=["float", "two", "str"])
def test_hv_rois_that_are_not_four_ints_are_named(box, error, message):
    from camhealth.estimators.charts import slanted_edge_chart, slanted_edge_rois
    from camhealth.estimators.slanted_edge import slanted_edge_mtf_hv

    with pytest.raises(error, match=message):
        slanted_edge_mtf_hv(slanted_edge_chart(256), rois={**slanted_edge_rois(256), "left": box})


def test_hv_rois_that_are_no_mapping_are_a_type_error():
    from camhealth.estimators.charts import slanted_edge_chart
    from camhealth.estimators.slanted_edge import slanted_edge_mtf_hv

    with pytest.raises(TypeError, match=r"rois must be a dict of the four edges left/right/top/bottom .* got list"):
        slanted_edge_mtf_hv(slanted_edge_chart(256), rois=["left", "right", "top", "bottom"])
