"""ISO 12233 slanted-edge MTF measurement (thesis Sec. 3.3.1.1, Fig. 3.13), batched.

For a region of interest (ROI) that holds one straight, slightly slanted (≈ 5°), near-vertical knife edge,
the MTF across the edge is measured in the steps of the standard (e-SFR):

1. **Edge detection.** The derivative of every row, ``I[x+1] − I[x]`` (sign chosen so the edge is
   positive), weighted by a Hamming window, gives one edge position per row as its centroid. A straight
   line ``x_e(y) = a + b·y`` is fitted to the centroids by least squares; the centroids are then
   recomputed with the window centred on the fitted line and the line is fitted again.
2. **Projection to an oversampled ESF.** Every pixel is projected onto the edge normal,
   ``u = (x − x_e(y))·cos θ`` with θ = atan b, and the intensities are averaged in bins of
   Δ = 1/``oversample`` px (default 4× oversampling) — the edge spread function (ESF). The slant makes
   the rows sample the edge at different sub-pixel phases; only whole phase cycles of rows are used
   (``⌊⌊H·|b|⌋ / |b|⌋`` rows), so all phases count alike. Empty bins are filled by linear interpolation.
   The ESF of each ROI reaches as far along the normal as its own edge-to-border distance (less 1 px), so an
   ROI's MTF does not depend on the other ROIs of the batch; the batch shares one bin grid, and an ROI whose
   edge has less room holds its ESF at its end values beyond its reach (its LSF is 0 there).
3. **LSF.** The line spread function is the derivative of the ESF (central difference over ±Δ), times a
   Hamming window centred on its centroid that reaches the farther end of the ROI's own ESF (``window``).
   The window narrows an LSF that has not settled well inside that reach, so an ROI is refused (``ValueError``
   naming its room and the LSF's 10–90 % rise) where the ESF still changes by more than :data:`MAX_UNSETTLED`
   (1 %) of the edge step over the outer half of the reach (the mean over 50–70 % of it against the mean over its
   last 10 %, both sides) — beyond the scatter its noise allows (6 standard errors, measured on 8 blocks of rows, so
   that spatially correlated noise counts as it is). An edge whose clipped pixels (within ½ DN of 0 or 1) form a plateau that reaches
   into the transition (the LSF still above :data:`MAX_CLIPPED_LSF` of its peak next to it) is refused too: a
   clipped edge reads too sharp (ISO 12233 asks for an unclipped edge).
4. **Fourier transform.** ``MTF(f) = |Σ_i LSF_i w_i e^{−2πi f u_i}| / |Σ_i LSF_i w_i|`` evaluated *exactly*
   at the requested frequencies (a direct DFT, not FFT bins), divided by the known frequency responses of
   the central difference, ``sin(2πfΔ)/(2πfΔ)`` (the ISO 12233:2014 derivative correction), and of the
   Δ-wide binning, ``sinc(fΔ)``. A frequency whose correction would exceed :data:`MAX_CORRECTION` (10, sfrmat's cap)
   is refused: at 1× oversampling the derivative's correction reaches 0 at Nyquist (f_n above ≈ 0.85 is refused).

The result is the MTF along the edge normal, at the angle φ = atan b from the horizontal (for a 5° edge
the measured direction is 5° off the H axis — exact for isotropic blur, an approximation of the H value
for directional blur; :attr:`SlantedEdgeResult.angle_deg` says which direction was measured, in the angle
convention of :mod:`camhealth.physics.mtf`). With ``aperture=True`` the MTF of the 1 px square pixel
aperture along that direction, ``sinc(f cos φ)·sinc(f sin φ)``, is divided out — use it for charts
rendered by pixel-area integration (:mod:`camhealth.estimators.charts`), so the result is the MTF of the
blur applied to the chart, comparable to :func:`camhealth.physics.mtf_hv` labels.

**Noise** adds its own spectrum to the LSF's: it scatters the MTF of each ROI and biases it high. Each result carries
the ROI's SNR (edge step over the noise's robust standard deviation about the ESF, :attr:`SlantedEdgeResult.snr`)
and flags it below :data:`MIN_SNR` (10; :attr:`SlantedEdgeResult.low_snr`); the MTF is returned all the same.
Measured (edge 0.2/0.8, 5°, Gaussian blur σ = 1 px, 64 ROIs of 64×40 px, white noise; mean |MTF − noiseless MTF|
over the 8 frequencies, its 90th percentile): SNR 40: 0.007 (0.009), 20: 0.013 (0.019), 14: 0.017 (0.023),
10: 0.026 (0.036), 7: 0.036 (0.046), 5: 0.045 (0.066), 4: 0.060 (0.091). It scales as 1/√rows (SNR 10: 0.043 at 32
rows, 0.015 at 128) and grows with the blur (σ = 2 px: 0.032 at SNR 10, 0.065 at 5); the mean over the 64 ROIs
reads high by 0.004 (σ = 2 px: 0.022) at SNR 10 and 0.017 (0.049) at SNR 5. Below SNR ≈ 4 most ROIs are refused
(no edge found in some rows, or noise clipped into a plateau).

Frequencies are normalised to Nyquist (f_n ∈ [0, 1], f = f_n/2 cycles/px). Vertical MTF: transpose the
ROI (a near-horizontal edge); :func:`slanted_edge_mtf_hv` does that for the four edges of the
:func:`~camhealth.estimators.charts.slanted_edge_chart` and returns the (B, 16) H/V layout of the labels.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Sequence, Union

import numpy as np
import torch

from camhealth._validation import check_choice, check_image
from camhealth.estimators._common import check_frequencies
from camhealth.estimators.charts import slanted_edge_rois
from camhealth.physics.mtf import NORMALIZED_FREQUENCIES

__all__ = ["MAX_CORRECTION", "MIN_SNR", "SlantedEdgeResult", "slanted_edge_mtf", "slanted_edge_mtf_hv"]

#: The derivative and binning corrections divide the MTF by at most this factor (a frequency that needs more is refused).
MAX_CORRECTION = 10.0
#: Largest share of the edge step by which the ESF may still change over the outer half of an ROI's reach (the mean
#: over 50–70 % of it against the mean over its last 10 %, both sides together); beyond it the Hamming window, whose
#: half-width is that reach, cuts and narrows the LSF and the MTF reads too high (for a Gaussian LSF of σ px the
#: limit falls at a reach of ≈ 4.6·σ, where the window's bias is at most 3.3 % AMAE; it is ≈ 1.3 % at 6.5·σ).
MAX_UNSETTLED = 0.01
#: The noise of that share is measured on this many blocks of consecutive rows; an ROI is refused only where the
#: share exceeds :data:`MAX_UNSETTLED` by more than ``_SETTLE_Z`` of its standard errors.
_SETTLE_BLOCKS = 8
_SETTLE_Z = 6.0
#: A pixel within half a DN (8-bit) of 0 or 1 is clipped.
CLIP_MARGIN = 0.5 / 255.0
#: A clipped plateau (ESF bins with at least half their pixels clipped) may begin only where the LSF (mean over 1 px)
#: has fallen below this share of its peak; closer to the edge the clipping cuts the transition and the MTF reads high.
MAX_CLIPPED_LSF = 0.1
#: Edge step over the noise (:attr:`SlantedEdgeResult.snr`) below which :attr:`SlantedEdgeResult.low_snr` flags an
#: ROI: its noise moves the MTF by more than ≈ 0.025 (mean |ΔMTF| over the frequencies, 64 rows; module docstring).
MIN_SNR = 10.0
_MIN_SLOPE = math.tan(math.radians(1.0))
_MAX_SLOPE = math.tan(math.radians(30.0))


@dataclass
class SlantedEdgeResult:
    """Result of :func:`slanted_edge_mtf` for a batch of B ROIs.

    Attributes:
        mtf: (B, F) MTF at the requested normalised frequencies (dimensionless).
        angle_deg: (B,) direction of the edge normal = direction of the measured MTF, degrees
            (0 = horizontal, counter-clockwise positive with y down, as in :mod:`camhealth.physics.mtf`).
        positions: (N,) ESF bin centres along the normal, px (0 = the fitted edge), shared by the batch: N is set by
            the ROI with the most room on both sides of its edge.
        esf: (B, N) edge spread function (intensity, polarity as in the image); beyond an ROI's own reach it
            holds the value of the ROI's end bin.
        lsf: (B, N) line spread function (derivative of the ESF, edge made positive, before the window); 0 at an
            ROI's end bins and beyond its reach.
        snr: (B,) edge step over the noise: the ESF's outer 10 % of bins on either side apart, over the robust
            standard deviation (1.4826·MAD) of the pixels about the ESF (inf without noise).
        low_snr: (B,) bool, ``snr`` below :data:`MIN_SNR`: the noise moves this ROI's MTF by more than ≈ 0.025 (and
            biases it high; module docstring). The MTF is returned all the same.
    """

    mtf: torch.Tensor
    angle_deg: torch.Tensor
    positions: torch.Tensor
    esf: torch.Tensor
    lsf: torch.Tensor
    snr: torch.Tensor | None = None
    low_snr: torch.Tensor | None = None


def _hamming(dist: torch.Tensor, half_width: torch.Tensor | float) -> torch.Tensor:
    """Hamming window 0.54 + 0.46·cos(π·dist/half_width) on |dist| <= half_width, 0 outside."""
    z = dist / half_width
    return torch.where(z.abs() <= 1.0, 0.54 + 0.46 * torch.cos(math.pi * z), torch.zeros_like(z))


def _centroids(d: torch.Tensor, xd: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Per-row centroid of the (windowed) derivative; d (B, H, W−1), weight broadcastable. Raises if a row has no edge."""
    wd = d * weight
    mass = wd.sum(dim=-1)
    scale = wd.abs().sum(dim=-1)
    bad = (mass <= 0.05 * scale.clamp_min(1e-30)) | (scale <= 0)  # (B, H)
    if bool(bad.any()):
        i = int(bad.any(dim=-1).nonzero()[0, 0])
        raise ValueError(
            f"roi[{i}]: no edge found in {int(bad[i].sum())} of its {bad.shape[-1]} rows (the row derivative has no clear "
            f"positive peak); the ROI must hold one straight edge that crosses every row, with contrast well above the noise"
        )
    return (wd * xd).sum(dim=-1) / mass


def _fit_line(y: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Least-squares line c = a + b·y for every batch row; y (H,), c (B, H) → a, b (B,)."""
    ym = y.mean()
    cm = c.mean(dim=1)
    b = ((y - ym) * (c - cm[:, None])).sum(dim=1) / (y - ym).square().sum()
    return cm - b * ym, b


def _fill_empty(esf: torch.Tensor, count: torch.Tensor) -> torch.Tensor:
    """Linear interpolation of empty bins (count 0) from the nearest filled bins on both sides."""
    filled = count > 0
    if bool(filled.all()):
        return esf
    b, n = esf.shape
    idx = torch.arange(n, device=esf.device).expand(b, n)
    left = torch.where(filled, idx, torch.full_like(idx, -1)).cummax(dim=1).values
    right = torch.where(filled, idx, torch.full_like(idx, n)).flip(1).cummin(dim=1).values.flip(1)
    left_c = left.clamp(0, n - 1)
    right_c = right.clamp(0, n - 1)
    vl = esf.gather(1, left_c)
    vr = esf.gather(1, right_c)
    vl = torch.where(left >= 0, vl, vr)
    vr = torch.where(right < n, vr, vl)
    span = (right - left).clamp_min(1).to(esf.dtype)
    t = torch.where((left >= 0) & (right < n), (idx - left).to(esf.dtype) / span, torch.zeros_like(esf))
    return torch.where(filled, esf, vl + t * (vr - vl))


def _check_settled(img: torch.Tensor, u_px: torch.Tensor, ok: torch.Tensor, flat: torch.Tensor, esf: torch.Tensor,
                   pol: torch.Tensor, kb: torch.Tensor, half_nb: torch.Tensor, start: torch.Tensor, n_rows: torch.Tensor,
                   room: torch.Tensor, oversample: int) -> None:
    """Refuse ROIs whose ESF has not settled over the outer half of their reach (:data:`MAX_UNSETTLED`).

    On each side of the edge, with j the distance in bins from it (0 … half_nb − 1), the mean ESF over
    j ∈ [0.5, 0.7)·half_nb is compared with the mean over the last 10 % of the bins (at least one); the two
    differences, summed over both sides, are the share ``u`` of the edge step (between the two outer means) by which
    the ESF still changes there. Noise moves ``u`` too, spatially correlated noise (blurred or filtered after the
    noise) more than the bins' pixel counts suggest, so its standard error is measured: the pixels' residuals from
    the ESF (interpolated at each pixel) give the same combination of band means in :data:`_SETTLE_BLOCKS` blocks of
    consecutive rows, and the spread of those block values, over √blocks, is the standard error. An ROI is refused
    where ``u`` exceeds :data:`MAX_UNSETTLED` by more than :data:`_SETTLE_Z` standard errors.

    img, u_px, ok: (B, H, W) pixels, their distance along the normal (px) and use; flat: (B, H·W) their bin; esf:
    (B, N); pol: (B,) edge polarity; kb: (N,) bin index (0 = the first bin past the edge); half_nb: (B,) own bins per
    side; start, n_rows: (B,) the rows used; room: (B,) edge-to-border distance, px.
    """
    b, h, w = img.shape
    n = esf.shape[1]
    delta = 1.0 / oversample
    e = esf * pol[:, None]  # rising
    j = torch.where(kb >= 0, kb, -kb - 1)[None, :]  # (1, N) distance in bins from the edge
    right = (kb >= 0)[None, :]
    hn = half_nb[:, None]
    own = j < hn
    n_out = torch.clamp(torch.round(0.1 * half_nb.double()).long(), min=1)[:, None]
    inner_band = own & (j >= torch.div(hn, 2, rounding_mode="floor")) & (j < torch.ceil(0.7 * hn.double()).long())
    outer_band = own & (j >= hn - n_out)
    # band of every bin: 0 inner left, 1 outer left, 2 outer right, 3 inner right, 4 none; u = Σ coef·(band mean)
    band = torch.full((b, n), 4, dtype=torch.long, device=e.device)
    band = torch.where(inner_band & ~right, 0, band)
    band = torch.where(outer_band & ~right, 1, band)
    band = torch.where(outer_band & right, 2, band)
    band = torch.where(inner_band & right, 3, band)
    coef = torch.tensor([1.0, -1.0, 1.0, -1.0, 0.0], dtype=e.dtype, device=e.device)
    n_band = torch.zeros(b, 5, dtype=e.dtype, device=e.device).scatter_add_(1, band, torch.ones_like(e))
    m_band = torch.zeros(b, 5, dtype=e.dtype, device=e.device).scatter_add_(1, band, e) / n_band.clamp_min(1.0)
    step = m_band[:, 2] - m_band[:, 1]
    u = (m_band * coef).sum(dim=1) / step.clamp_min(1e-12)
    cand = ((u > MAX_UNSETTLED) | ~(step > 0)).nonzero()[:, 0]
    if cand.numel() == 0:  # settled everywhere (the common case): nothing to refuse, no noise to measure
        return
    # standard error, for the candidates only: residuals from the ESF (linear between bin centres), band means per
    # block of consecutive rows
    bc = cand.numel()
    esf_c, pol_c, band_c = esf[cand], pol[cand], band[cand]
    t = (u_px[cand] / delta - 0.5 + n // 2).clamp(0.0, n - 1.0).reshape(bc, -1)
    i0 = torch.floor(t).long().clamp(max=n - 2)
    wt = t - i0.to(e.dtype)
    e_px = esf_c.gather(1, i0) * (1.0 - wt) + esf_c.gather(1, i0 + 1) * wt
    res = (img[cand].reshape(bc, -1) - e_px) * pol_c[:, None]
    g_n = torch.clamp(n_rows[cand] // 2, max=_SETTLE_BLOCKS)  # (Bc,) blocks of consecutive rows
    rows = torch.arange(h, device=e.device)[None, :]
    blk = ((rows - start[cand, None]).clamp_min(0) * g_n[:, None] // n_rows[cand, None]).clamp(max=_SETTLE_BLOCKS - 1)
    pb = band_c.gather(1, flat[cand])  # band of every pixel's bin
    use = ok[cand].reshape(bc, -1) & (pb < 4)
    idx = torch.where(use, (blk[:, :, None] * 4).expand(bc, h, w).reshape(bc, -1) + pb, torch.zeros_like(pb))
    cnt = torch.zeros(bc, 4 * _SETTLE_BLOCKS, dtype=e.dtype, device=e.device).scatter_add_(1, idx, use.to(e.dtype))
    tot = torch.zeros(bc, 4 * _SETTLE_BLOCKS, dtype=e.dtype, device=e.device).scatter_add_(1, idx, res * use)
    z = ((tot / cnt.clamp_min(1.0)).reshape(bc, _SETTLE_BLOCKS, 4) * coef[:4]).sum(dim=2)  # (Bc, G) per block
    has = (cnt.reshape(bc, _SETTLE_BLOCKS, 4) > 0).all(dim=2)
    g = has.sum(dim=1).to(e.dtype)
    zm = (z * has).sum(dim=1) / g.clamp_min(1.0)
    var_z = ((z - zm[:, None]).square() * has).sum(dim=1) / (g - 1.0).clamp_min(1.0)
    se = torch.full_like(u, 0.0)
    se[cand] = torch.where(g >= 2, torch.sqrt(var_z / g), torch.full_like(g, math.inf)) / step[cand].clamp_min(1e-12)
    bad = (u - _SETTLE_Z * se > MAX_UNSETTLED) | ~(step > 0)
    if bool(bad.any()):
        i = int(bad.nonzero()[0, 0])
        z10 = (e[i] - m_band[i, 1]) / step[i].clamp_min(1e-12)
        rise = float(((z10 > 0.1) & (z10 < 0.9) & own[i]).sum()) * delta  # 10–90 % rise: a count of bins, robust
        raise ValueError(
            f"roi[{i}]: the edge has too little room for its blur: the ROI leaves {float(room[i]):.1f} px beside the edge "
            f"(along its normal) and the LSF is {rise:.1f} px wide (10–90 % edge rise), so the ESF still changes by "
            f"{100 * float(u[i]):.1f} % of the edge step over the outer half of that room (at most "
            f"{100 * MAX_UNSETTLED:g} % allowed); the LSF window would cut its tails and read the MTF too high. Use an ROI "
            f"with more room on both sides of the edge (about {max(2.0 * rise + 1.0, 5.0):.0f} px or more for this blur)"
        )


def _edge_snr(img: torch.Tensor, u_px: torch.Tensor, ok: torch.Tensor, esf: torch.Tensor, pol: torch.Tensor,
              kb: torch.Tensor, half_nb: torch.Tensor, oversample: int) -> torch.Tensor:
    """(B,) edge step over the noise: the mean ESF over the outer 10 % of each side's own bins (at least one) apart,
    over 1.4826·MAD of the used pixels' residuals from the ESF (linear between bin centres, as in
    :func:`_check_settled`); inf where the residuals are all alike (no noise)."""
    b = img.shape[0]
    n = esf.shape[1]
    delta = 1.0 / oversample
    t = (u_px / delta - 0.5 + n // 2).clamp(0.0, n - 1.0).reshape(b, -1)
    i0 = torch.floor(t).long().clamp(max=n - 2)
    wt = t - i0.to(esf.dtype)
    e_px = esf.gather(1, i0) * (1.0 - wt) + esf.gather(1, i0 + 1) * wt
    res = torch.where(ok.reshape(b, -1), img.reshape(b, -1) - e_px, torch.full_like(e_px, math.nan))
    med = res.nanmedian(dim=1, keepdim=True).values
    noise = 1.4826 * (res - med).abs().nanmedian(dim=1).values
    e = esf * pol[:, None]  # rising
    j = torch.where(kb >= 0, kb, -kb - 1)[None, :]
    hn = half_nb[:, None]
    n_out = torch.clamp(torch.round(0.1 * half_nb.double()).long(), min=1)[:, None]
    outer = (j < hn) & (j >= hn - n_out)
    right = (kb >= 0)[None, :]
    hi = (e * (outer & right)).sum(1) / (outer & right).sum(1).clamp_min(1)
    lo = (e * (outer & ~right)).sum(1) / (outer & ~right).sum(1).clamp_min(1)
    step = hi - lo
    return torch.where(noise > 0, step / noise.clamp_min(1e-300), torch.full_like(step, math.inf))


def _check_clipping(img: torch.Tensor, ok: torch.Tensor, flat: torch.Tensor, counts: torch.Tensor, e: torch.Tensor,
                    own: torch.Tensor, kb: torch.Tensor, oversample: int) -> None:
    """Refuse ROIs whose clipped plateau reaches into the edge transition (:data:`MAX_CLIPPED_LSF`).

    A pixel within :data:`CLIP_MARGIN` (½ DN) of 0 or 1 is clipped; an own ESF bin with at least half its pixels
    clipped belongs to a clipped plateau (scattered noise clipping never fills half a bin). Where such a plateau
    begins (its bin nearest the edge on either side), the LSF over the 1 px before it (ESF difference over 1 px)
    must be below :data:`MAX_CLIPPED_LSF` of the LSF's peak (the largest such 1-px difference)."""
    b, n = e.shape
    lo, hi = torch.aminmax(img)
    if bool((lo > CLIP_MARGIN) & (hi < 1.0 - CLIP_MARGIN)):  # nothing clipped (the common case): one reduction
        return
    clipped = (img <= CLIP_MARGIN) | (img >= 1.0 - CLIP_MARGIN)  # (B, H, W)
    if not bool((clipped & ok).any()):
        return
    cf = (clipped & ok).reshape(b, -1).to(e.dtype)
    n_clip = torch.zeros(b, n, device=e.device, dtype=e.dtype).scatter_add_(1, flat, cf)
    plateau = own & (counts > 0) & (n_clip >= 0.5 * counts)
    if not bool(plateau.any()):
        return
    k = oversample  # 1 px of bins
    d = torch.zeros_like(e)
    d[:, k:] = (e[:, k:] - e[:, :-k]) * oversample  # mean LSF over the px ending at each bin, per px
    d_ok = torch.zeros_like(own)
    d_ok[:, k:] = own[:, k:] & own[:, :-k]
    peak = torch.where(d_ok, d, torch.zeros_like(d)).amax(dim=1)
    prev = torch.zeros_like(plateau)
    prev[:, 1:] = plateau[:, :-1]
    nxt = torch.zeros_like(plateau)
    nxt[:, :-1] = plateau[:, 1:]
    right = (kb >= 0)[None, :]
    # right side: a plateau bin whose left neighbour is not plateau; the LSF over the 1 px before it ends at that bin
    start_r = plateau & ~prev & right & d_ok
    # left side: a plateau bin whose right neighbour is not plateau; the 1 px after it ends k bins further right
    start_l = plateau & ~nxt & ~right
    d_after = torch.zeros_like(d)
    d_after[:, :-k] = torch.where(d_ok[:, k:], d[:, k:], torch.zeros_like(d[:, k:]))
    edge_lsf = torch.maximum(torch.where(start_r, d, torch.zeros_like(d)).amax(dim=1),
                             torch.where(start_l, d_after, torch.zeros_like(d)).amax(dim=1))
    ratio = edge_lsf / peak.clamp_min(1e-12)
    bad = ratio > MAX_CLIPPED_LSF
    if bool(bad.any()):
        i = int(bad.nonzero()[0, 0])
        share = float(cf[i].sum() / ok[i].sum().clamp_min(1))
        raise ValueError(
            f"roi[{i}]: {100 * share:.0f} % of its pixels are clipped (within ½ DN of 0 or 1) and the clipped plateau "
            f"reaches into the edge transition (the LSF next to it is still {100 * float(ratio[i]):.0f} % of its peak, at "
            f"most {100 * MAX_CLIPPED_LSF:g} % allowed): a clipped edge reads too sharp, and ISO 12233 needs an unclipped "
            f"edge; lower the exposure or gain"
        )


def slanted_edge_mtf(
    roi: torch.Tensor,
    frequencies: Union[Sequence[float], torch.Tensor] = NORMALIZED_FREQUENCIES,
    oversample: int = 4,
    window: str = "hamming",
    aperture: bool = False,
) -> SlantedEdgeResult:
    """MTF across a near-vertical slanted edge (ISO 12233), for a batch of ROIs of one size.

    Args:
        roi: ``B×1×H×W`` float images in [0, 1] (DN/255) holding one straight, unclipped edge slanted by 1°…30° from the vertical
            (ISO: ≈ 5°), crossing every row, at least 5 px from the left/right ROI border (along the edge normal)
            and far enough from it that the ESF has settled over the outer half of that distance (for a Gaussian
            blur of σ px: ≳ 4.6·σ + 1 px; see step 3 of the module docstring). ROIs that break these rules are refused
            with a ``ValueError``.
        frequencies: F normalised frequencies in [0, 1] (fraction of Nyquist; f = f_n/2 cycles/px).
        oversample: ESF bins per px (ISO: 4), 1…16.
        window: LSF window, ``"hamming"`` (ISO), ``"tukey"`` (flat over the inner half, cosine taper) or
            ``"none"``.
        aperture: divide out the 1 px pixel aperture (for area-rendered synthetic charts).

    Returns:
        :class:`SlantedEdgeResult`; ``mtf`` is (B, F) float32 (float64 for float64 input).
    """
    x = check_image(roi, "roi", channels=1, value_range=(0.0, 1.0))
    check_choice(window, "window", ("hamming", "tukey", "none"))
    if (isinstance(oversample, (bool, np.bool_)) or not isinstance(oversample, numbers.Integral)
            or not (1 <= oversample <= 16)):
        raise ValueError(f"oversample = {oversample!r} must be an int in [1, 16]")
    oversample = int(oversample)
    if not isinstance(aperture, (bool, np.bool_)):  # (a string such as "no" would read as true)
        raise TypeError(f"aperture = {aperture!r:.40} must be True or False, got {type(aperture).__name__}")
    out_dtype = torch.float64 if x.dtype == torch.float64 else torch.float32
    dev = x.device
    fn = check_frequencies(frequencies, dev)
    # the derivative and binning corrections (step 4) at Δ = 1/oversample: at 1× the derivative's sinc(2fΔ) reaches 0
    # at Nyquist; a frequency that needs more than MAX_CORRECTION (sfrmat's cap) is beyond what the ESF resolves
    f_cyc, delta_px = 0.5 * fn, 1.0 / oversample
    beyond = torch.sinc(2.0 * f_cyc * delta_px) * torch.sinc(f_cyc * delta_px) < 1.0 / MAX_CORRECTION
    if bool(beyond.any()):
        raise ValueError(f"frequencies f_n = {[round(float(v), 4) for v in fn[beyond]]} are beyond what oversample = "
                         f"{oversample} resolves (the derivative and binning corrections would exceed "
                         f"{MAX_CORRECTION:g}×); use oversample ≥ 2 (ISO 12233: 4) or lower frequencies")
    img = x[:, 0].double()
    b, h, w = img.shape
    if h < 8 or w < 20:
        raise ValueError(f"roi must be at least 8 rows × 20 columns, got {h}×{w}")

    # 1. edge detection: windowed row-derivative centroids, line fit, refinement
    d = img[..., 1:] - img[..., :-1]
    pol = torch.sign(d.sum(dim=(1, 2)))
    pol = torch.where(pol == 0, torch.ones_like(pol), pol)
    d = d * pol[:, None, None]
    xd = torch.arange(w - 1, device=dev, dtype=torch.float64) + 0.5
    yy = torch.arange(h, device=dev, dtype=torch.float64)
    half = 0.5 * (w - 1)
    c = _centroids(d, xd, _hamming(xd - half, half))
    a, slope = _fit_line(yy, c)
    fit = a[:, None] + slope[:, None] * yy[None, :]
    c = _centroids(d, xd, _hamming(xd[None, None, :] - fit[:, :, None], half))
    a, slope = _fit_line(yy, c)
    bad = (slope.abs() < _MIN_SLOPE) | (slope.abs() > _MAX_SLOPE)
    if bool(bad.any()):
        ang = math.degrees(math.atan(float(slope[bad][0])))
        raise ValueError(f"edge angle = {ang:.2f}° from the vertical is out of the allowed range 1°…30° (ISO 12233: ≈ 5°)")

    # 2. whole phase cycles of rows, centred; projection onto the normal; oversampled ESF
    n_rows = torch.floor(torch.floor(h * slope.abs()) / slope.abs()).long().clamp(max=h)
    if bool((torch.floor(h * slope.abs()) < 1).any()):
        raise ValueError(f"the ROI's {h} rows do not cover one phase cycle of the edge (|slope|·H < 1); use a taller ROI or a larger angle")
    start = (h - n_rows) // 2
    row_ok = (yy[None, :] >= start[:, None]) & (yy[None, :] < (start + n_rows)[:, None])  # (B, H)
    cos_t = 1.0 / torch.sqrt(1.0 + slope.square())
    edge_x = a[:, None] + slope[:, None] * yy[None, :]  # (B, H)
    room = torch.minimum(edge_x, (w - 1) - edge_x)
    room = torch.where(row_ok, room, torch.full_like(room, math.inf)).amin(dim=1) * cos_t  # (B,)
    half_u = room - 1.0  # (B,) each ROI's own ESF half-length: its bins do not depend on the other ROIs of the batch
    short = half_u < 4.0
    if bool(short.any()):
        i = int(short.nonzero()[0, 0])
        raise ValueError(f"roi[{i}]: the edge is only {float(room[i]):.1f} px from the ROI border; centre the edge in "
                         f"the ROI (≥ 5 px each side)")
    delta = 1.0 / oversample
    half_nb = torch.floor(half_u / delta).long()  # (B,) bins each side of the edge
    nb = 2 * int(half_nb.max())
    xx = torch.arange(w, device=dev, dtype=torch.float64)
    u = (xx[None, None, :] - edge_x[:, :, None]) * cos_t[:, None, None]  # (B, H, W) px along the normal
    k = torch.floor(u / delta).long()  # bin index, 0 = the first bin past the edge
    ok = (k >= -half_nb[:, None, None]) & (k < half_nb[:, None, None]) & row_ok[:, :, None]
    flat = torch.where(ok, k + nb // 2, torch.zeros_like(k)).reshape(b, -1)
    okf = ok.reshape(b, -1).double()
    vals = img.reshape(b, -1)
    sums = torch.zeros(b, nb, device=dev, dtype=torch.float64).scatter_add_(1, flat, vals * okf)
    counts = torch.zeros(b, nb, device=dev, dtype=torch.float64).scatter_add_(1, flat, okf)
    esf = _fill_empty(sums / counts.clamp_min(1.0), counts)
    pos = (torch.arange(nb, device=dev, dtype=torch.float64) - nb // 2 + 0.5) * delta
    kb = torch.arange(nb, device=dev) - nb // 2
    own = (kb[None, :] >= -half_nb[:, None]) & (kb[None, :] < half_nb[:, None])  # (B, N) the ROI's own bins

    # 3. LSF (central difference over the ROI's own bins, 0 at and beyond its end bins), window centred on its centroid
    lsf = torch.zeros_like(esf)
    lsf[:, 1:-1] = (esf[:, 2:] - esf[:, :-2]) / (2.0 * delta)
    inner = own & torch.roll(own, 1, dims=1) & torch.roll(own, -1, dims=1)
    inner[:, [0, -1]] = False
    lsf = torch.where(inner, lsf, torch.zeros_like(lsf)) * pol[:, None]
    _check_clipping(img, ok, flat, counts, esf * pol[:, None], own, kb, oversample)
    _check_settled(img, u, ok, flat, esf, pol, kb, half_nb, start, n_rows, room, oversample)
    mass = lsf.sum(dim=1, keepdim=True)
    centre = (lsf * pos).sum(dim=1, keepdim=True) / mass
    dist = pos[None, :] - centre
    reach = torch.where(own, dist.abs(), torch.zeros_like(dist)).amax(dim=1, keepdim=True) + delta
    if window == "hamming":
        win = _hamming(dist, reach)
    elif window == "tukey":
        z = (dist.abs() / reach - 0.5).clamp_min(0.0) / 0.5
        win = 0.5 * (1.0 + torch.cos(math.pi * z.clamp_max(1.0)))
    else:
        win = torch.ones_like(dist)
    lw = lsf * win

    # 4. exact DFT at the requested frequencies, derivative and binning corrections
    f = 0.5 * fn  # cycles/px
    phase = 2.0 * math.pi * f[:, None] * pos[None, :]  # (F, N)
    re = lw @ torch.cos(phase).T
    im = lw @ torch.sin(phase).T
    mtf = torch.sqrt(re.square() + im.square()) / lw.sum(dim=1, keepdim=True).abs()
    deriv = torch.sinc(2.0 * f * delta)  # sin(2πfΔ)/(2πfΔ)
    binning = torch.sinc(f * delta)
    corr = deriv * binning  # ≥ 1/MAX_CORRECTION: checked with the arguments
    mtf = mtf / corr[None, :]
    theta = torch.atan(slope)  # normal direction, mtf.py convention
    if aperture:
        ap = torch.sinc(f[None, :] * torch.cos(theta)[:, None]) * torch.sinc(f[None, :] * torch.sin(theta)[:, None])
        mtf = mtf / ap.abs()
    snr = _edge_snr(img, u, ok, esf, pol, kb, half_nb, oversample)
    return SlantedEdgeResult(
        mtf=mtf.to(out_dtype),
        angle_deg=torch.rad2deg(theta).to(out_dtype),
        positions=pos.to(out_dtype),
        esf=esf.to(out_dtype),
        lsf=lsf.to(out_dtype),
        snr=snr.to(out_dtype),
        low_snr=snr < MIN_SNR,
    )


def slanted_edge_mtf_hv(
    charts: torch.Tensor,
    rois: dict[str, tuple[int, int, int, int]] | None = None,
    frequencies: Union[Sequence[float], torch.Tensor] = NORMALIZED_FREQUENCIES,
    aperture: bool = True,
    **kwargs,
) -> torch.Tensor:
    """H and V MTF from the four edges of slanted-edge charts: ``B×1×S×S`` → (B, 2F) = ``[H×F, V×F]``.

    H is the mean of the MTFs across the left and right (near-vertical) edges, V the mean across the top
    and bottom edges (measured on the transposed ROIs). ``rois`` defaults to
    :func:`~camhealth.estimators.charts.slanted_edge_rois` for the chart size (default chart geometry);
    ``aperture`` defaults to True (the charts of :mod:`~camhealth.estimators.charts` are area-rendered);
    further keyword arguments go to :func:`slanted_edge_mtf`.
    """
    x = check_image(charts, "charts", channels=1, value_range=(0.0, 1.0))
    if rois is None:
        if x.shape[-1] != x.shape[-2]:
            raise ValueError(f"default ROIs need a square chart, got {x.shape[-2]}×{x.shape[-1]}; pass rois=")
        rois = slanted_edge_rois(x.shape[-1])
    if not isinstance(rois, Mapping):
        raise TypeError(f"rois must be a dict of the four edges left/right/top/bottom → (row0, row1, col0, col1), got "
                        f"{type(rois).__name__}")
    missing = {"left", "right", "top", "bottom"} - set(rois)
    if missing:
        raise ValueError(f"rois must name the four edges left/right/top/bottom, missing {sorted(missing)}")
    b = x.shape[0]

    def crop(name: str) -> torch.Tensor:
        box = rois[name]
        if (isinstance(box, (str, bytes)) or not isinstance(box, Sequence) or len(box) != 4
                or not all(isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_)) for v in box)):
            raise ValueError(f"roi {name} = {box!r:.60} must be four ints (row0, row1, col0, col1) [px]")
        r0, r1, c0, c1 = (int(v) for v in box)
        if not (0 <= r0 < r1 <= x.shape[-2] and 0 <= c0 < c1 <= x.shape[-1]):
            raise ValueError(f"roi {name} = {rois[name]} lies outside the {x.shape[-2]}×{x.shape[-1]} chart")
        return x[:, :, r0:r1, c0:c1]

    def pair(first: torch.Tensor, second: torch.Tensor, transpose: bool) -> torch.Tensor:
        """The mean MTF across two edges: ROIs of one size in one call, of two sizes in two."""
        def mtf(r: torch.Tensor) -> torch.Tensor:
            return slanted_edge_mtf(r.transpose(-1, -2) if transpose else r, frequencies, aperture=aperture, **kwargs).mtf

        if first.shape == second.shape:
            m = mtf(torch.cat([first, second]))
            return 0.5 * (m[:b] + m[b:])
        return 0.5 * (mtf(first) + mtf(second))

    return torch.cat([pair(crop("left"), crop("right"), False), pair(crop("top"), crop("bottom"), True)], dim=1)
