"""Slanted edge: the ROI named when no edge is found, and the SNR of each ROI."""

import math

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
