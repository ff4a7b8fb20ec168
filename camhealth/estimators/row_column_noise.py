"""Row and column noise (banding): offsets shared by a whole pixel row or column, from one patch.

Model: I(y, x) = S(y, x) + r_y + c_x + n(y, x) [DN], with r_y ~ N(0, σ_row²) drawn once per pixel row, c_x ~ N(0,
σ_col²) once per pixel column, n the pixel noise (conventions.md) and S the scene. Row noise is a common CMOS defect
(a readout line whose reference or supply fluctuates from row to row, interference); none of the sensor model's
sources (photon shot, dark-current shot, readout noise) has it, so the metadata never predict it.

In the 2×2 Haar details of block (j, i) — horizontal h = (I₀₀ + I₀₁ − I₁₀ − I₁₁)/2, vertical v = (I₀₀ − I₀₁ + I₁₀ −
I₁₁)/2, diagonal d = (I₀₀ − I₀₁ − I₁₀ + I₁₁)/2 — the row offsets add r_{2j} − r_{2j+1} to the h of every block of
block row j, the column offsets c_{2i} − c_{2i+1} to the v of every block of block column i, and neither reaches d
(both cancel). The noise-level function of :mod:`camhealth.estimators.physics_noise` reads d, so it is blind to
banding; its texture check (h and v energy over d's) reads banding as texture.

**Estimate** (rows; columns alike on v). Per block row the mean of the middle half of its W sorted details, H̃_j
(the midmean: a scene's sparse edges do not move it, and unlike a median it is not stuck to the half-DN steps of
8-bit data), and their spread s_j² = the variance of that middle half / k_W (k_W: its share of a Gaussian's variance,
0.149 at W = 64). Adjacent differences Δ_j = H̃_{j+1} − H̃_j cancel a smooth vertical shading (a ramp puts the same
h into every block). Under the model

    Δ_j = (r_{2j+2} − r_{2j+3}) − (r_{2j} − r_{2j+1}) + e_j,   Var Δ_j = 4·σ_row² + ν_j,   ν_j = c_W·(s_j² + s_{j+1}²)/W

(the midmean of W Gaussian details has the variance c_W·s²/W, c_W = 1.19), so σ̂_row² = (MAD²(Δ) − median_j ν_j)/4 with
MAD² = (1.4826·median|Δ − median Δ|)². Its significance is T = MAD²(Δ_j/√ν_j): 1 for pixel noise alone whatever
the scene's spread along each row (each Δ is standardised by its own rows' spread), larger with banding. Pooled (the
patches of one frame share one camera), the Δ of all patches enter one MAD.

**Detected** where at least :data:`MIN_DIFFERENCES` differences Δ_j enter the estimate, T exceeds :data:`T_LIMIT`, σ̂
exceeds :data:`MIN_BANDING_DN` and the offsets look independent from row to row (:attr:`RowColumnNoise.serial`).
Fewer differences leave the MAD too loose for the limit (white noise on 16-px patches, 7 differences: T above it on
3 % of patches), so a patch under 34 px tall (wide) reports no row (column) noise alone; pooled, the differences of
all the frame's patches count. The scene can imitate banding: structure coherent along whole rows
(horizontal edges across the patch, stripes) gives the same Δ. On the robustness benchmark's clean scenes with
matched noise (``python -m camhealth.bench robustness``) T reaches 12.6 on single patches of photographs and 4.0
pooled over a frame. Such structure is mostly not independent from row to row (a stripe pattern, periodic or
smooth), which :attr:`RowColumnNoise.serial` tests; what passes — random stripes, which one patch cannot tell from
banding (2.8 % of the benchmark's full-resolution patches without banding, 0.4 % at 3×) — rarely moves σ_Total
visibly, and a patch whose banding came from its scene is mostly still textured once the band is taken out and is
refused. :func:`debanded_details` removes the detected offsets from the details the noise fits use.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch

from camhealth._order import lower_median, sorted_values
from camhealth._validation import check_finite, check_float, check_tensor
from camhealth.estimators.noise_features import _block_pixels

__all__ = ["RowColumnNoise", "row_column_noise", "debanded_details", "T_LIMIT", "MIN_BANDING_DN", "MIN_DIFFERENCES",
           "SERIAL_LIMIT"]

#: Significance T above which row or column noise counts as detected. Pixel noise alone: T ≈ 1, 99th percentile
#: 2.0–2.2 over 128-px patches of white noise (float or 8-bit), the largest of 512 2.7. Clean scenes with their right
#: noise (the robustness benchmark): up to 4.0 pooled over a frame (the street clip 3.2–3.8: 0.5 DN of row structure
#: of its own camera), 12.6 on single patches of photographs.
T_LIMIT = 6.0
#: Smallest σ_row or σ_col [DN] reported as banding.
MIN_BANDING_DN = 0.5
#: Fewest adjacent differences Δ_j (block rows − 1 per patch, summed over the patches when pooled) for which banding is
#: reported in that direction: T_LIMIT holds for the MAD of at least this many (white noise: T above it on 0.02 % of
#: 34-px patches, 16 differences; on 3 % of 16-px ones, 7).
MIN_DIFFERENCES = 16
#: Largest Σ ρ_k² (lags 1…4) of the block rows' values that still counts as offsets drawn independently per row (an
#: RMS correlation of 0.16 per lag): a scene's stripes, periodic or smooth, are correlated from row to row.
SERIAL_LIMIT = 0.1
_LAGS = 4
_SERIAL_CHI2 = 18.47  # χ²₄ at 99.9 %
# 1.4826 = 1/Φ⁻¹(¾): the MAD of a normal sample times it is its standard deviation
_MAD_TO_SD = 1.4826


#: The values :func:`row_column_noise` accepts: intensities in [0, 1], and a static pair's unclamped fold, whose scaled
#: difference (I₁ − I₂)/√2 reaches 1/√2 beyond either bound.
_LOWEST, _HIGHEST = -1.0 / math.sqrt(2.0), 1.0 + 1.0 / math.sqrt(2.0)

@dataclass
class RowColumnNoise:
    """Row and column noise of B patches (each field (B, 2): rows, columns; float64).

    Attributes:
        sigma_dn: σ̂_row, σ̂_col [DN] (≥ 0; 0 where the details show none).
        var_se_dn2: standard error of σ̂² [DN²] (the MAD-based variance of n differences: 2·1.166·MAD²/√n).
        significance: T (1 for pixel noise alone).
        serial: Σ ρ_k² over lags 1…4 of the block rows' (columns') values: ≈ 4/J for offsets independent from row to
            row, large for a scene's periodic or smooth structure.
        detected: at least :data:`MIN_DIFFERENCES` differences behind the estimate, T > :data:`T_LIMIT`, σ̂ >
            :data:`MIN_BANDING_DN` and the offsets independent from row to row (``serial`` within max(χ²₄ at 99.9 % /
            n, :data:`SERIAL_LIMIT`), n the block rows behind it) (bool).
    """

    sigma_dn: torch.Tensor
    var_se_dn2: torch.Tensor
    significance: torch.Tensor
    serial: torch.Tensor
    detected: torch.Tensor


def _mad_var(x: torch.Tensor) -> torch.Tensor:
    """(1.4826·median|x − median x|)² along the last dimension."""
    med = lower_median(x).unsqueeze(-1)
    return (lower_median((x - med).abs()) * _MAD_TO_SD).square()


def _signed_details(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Horizontal and vertical Haar details [DN] of B×1×H×W patches in [0, 1], each (B, h, w) float32."""
    p00, p01, p10, p11 = (p[:, 0] for p in _block_pixels(x.float()))
    return (p00 + p01 - p10 - p11) / 2.0, (p00 - p01 + p10 - p11) / 2.0


@functools.lru_cache(maxsize=8)
def _midmean_constants(w: int) -> tuple[float, float]:
    """(k_W, c_W) for rows of ``w`` Gaussian values: the share of σ² in the variance of the middle half, and
    W·Var(midmean)/σ² (Monte Carlo, 2¹⁶ seeded rows drawn 2¹² at a time, so it needs no more than a few MB;
    asymptotically 0.143 and 1.195)."""
    g = torch.Generator().manual_seed(0)
    lo = w // 4
    share, means = [], []
    for _ in range(16):
        mid = torch.randn(1 << 12, w, generator=g, dtype=torch.float64).sort(-1).values[:, lo:w - lo]
        share.append(mid.var(-1, unbiased=False).mean())
        means.append(mid.mean(-1))
    return float(torch.stack(share).mean()), float(torch.cat(means).var() * w)


def _midmean(h: torch.Tensor, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Midmean along the last dimension and the variance of the middle half (float64; sorted in float32)."""
    lo = w // 4
    mid = sorted_values(h.float())[..., lo:w - lo]
    m = mid.mean(-1)
    return m.double(), (mid.square().mean(-1) - m.square()).clamp_min(0.0).double()


def _directions(h: torch.Tensor, pool: bool) -> tuple[torch.Tensor, ...]:
    """σ̂² [DN²], its standard error, T and the serial correlation, each (D, B), for details h (D, B, J, W) whose
    rows j carry the offsets (module docstring); D directions at once (rows, and columns transposed)."""
    d, b, w = h.shape[0], h.shape[1], h.shape[-1]
    k_w, c_w = _midmean_constants(w)
    mid, mid_var = _midmean(h, w)  # (D, B, J): H̃_j and the variance of the middle half
    s2 = mid_var / k_w
    delta = mid[..., 1:] - mid[..., :-1]
    nu = c_w * (s2[..., 1:] + s2[..., :-1]) / w
    t = delta / nu.clamp_min(1e-12).sqrt()
    if pool:
        delta, nu, t = (v.reshape(d, 1, -1) for v in (delta, nu, t))
    n = delta.shape[-1]
    var_delta = _mad_var(delta)
    sig2 = ((var_delta - lower_median(nu)) / 4.0).clamp_min(0.0)
    se = 2.0 * 1.166 * var_delta / math.sqrt(max(n, 1)) / 4.0
    out = (sig2, se, _mad_var(t), _serial_correlation(mid, pool))
    return tuple(v.expand(d, b) for v in out) if pool else out


def _serial_correlation(mid: torch.Tensor, pool: bool) -> torch.Tensor:
    """Σ_{k=1..LAGS} ρ_k² of the block-row values H̃_j (…, B, J) after a straight line in j is taken out (a ramp or a
    smooth shading) and values beyond 3 robust σ are clipped (a scene's edges): ≈ LAGS/J for offsets drawn
    independently per row, large for a scene's periodic or smooth structure along the rows. Pooled, the ρ_k of the
    patches (dimension −2) are averaged (the sum then ≈ LAGS/(B·J))."""
    j = mid.shape[-1]
    t = torch.arange(j, dtype=mid.dtype, device=mid.device) - (j - 1) / 2.0
    slope = (mid * t).sum(-1, keepdim=True) / t.square().sum()
    res = mid - mid.mean(-1, keepdim=True) - slope * t
    lim = 3.0 * _mad_var(res).sqrt().unsqueeze(-1)
    res = torch.maximum(torch.minimum(res, lim), -lim)
    res = res - res.mean(-1, keepdim=True)
    var = res.square().sum(-1).clamp_min(1e-12)
    rho = torch.stack([(res[..., k:] * res[..., :-k]).sum(-1) / var for k in range(1, _LAGS + 1)], -1)  # (…, B, LAGS)
    if pool:
        rho = rho.mean(-2, keepdim=True)
    return rho.square().sum(-1)


def row_column_noise(patches: torch.Tensor, pool: bool = False) -> RowColumnNoise:
    """Row and column noise of B×1×H×W patches in [0, 1] (H, W ≥ 8; module docstring).

    ``pool``: the patches show one camera (a frame's patches): their differences enter one estimate, the same for
    every patch. Returns :class:`RowColumnNoise` (fields (0, 2) for an empty batch).

    The patches must be a floating tensor (``TypeError`` otherwise: integer DN images, divide by 255 first) of finite
    intensities in [0, 1] (DN/255); a static pair's unclamped fold
    (:func:`~camhealth.estimators.static_pair.static_pair_image` with ``clamp=False``), whose scaled difference reaches
    1/√2 beyond either bound, is accepted as well: values outside [−1/√2, 1 + 1/√2] (DN-scale input) raise a
    ``ValueError`` naming the range found, as do NaN/inf."""
    if not isinstance(pool, bool):  # (a string such as "no" would read as true)
        raise TypeError(f"pool = {pool!r} must be a bool (True: the patches show one camera)")
    x = check_float(check_tensor(patches, "patches"), "patches")
    if x.ndim != 4 or x.shape[1] != 1 or min(x.shape[-2:]) < 8:
        raise ValueError(f"row_column_noise needs B×1×H×W patches with H, W ≥ 8, got {tuple(x.shape)}")
    if x.shape[0] == 0:
        z = torch.zeros(0, 2, dtype=torch.float64, device=x.device)
        return RowColumnNoise(z, z.clone(), z.clone(), z.clone(), torch.zeros(0, 2, dtype=torch.bool, device=x.device))
    lo, hi = torch.aminmax(x.detach())
    if not bool(torch.isfinite(lo) & torch.isfinite(hi)):
        check_finite(x, "patches")
    if lo < _LOWEST or hi > _HIGHEST:
        raise ValueError(f"patches must lie in [0, 1] (DN/255; a static pair's unclamped fold in [{_LOWEST:.3f}, "
                         f"{_HIGHEST:.3f}]), got values in [{lo.item():g}, {hi.item():g}]")
    h, v = _signed_details(x.detach())
    vt = v.transpose(-1, -2)
    if h.shape == vt.shape:  # square patches: both directions in one call
        both = _directions(torch.stack([h, vt]), pool)
    else:
        both = tuple(torch.cat(p) for p in zip(_directions(h.unsqueeze(0), pool), _directions(vt.unsqueeze(0), pool)))
    sig2, se, tt, serial = (q.t() for q in both)  # each (B, 2): rows, columns
    k = h.shape[0] if pool else 1
    n = (h.shape[-2] * k, v.shape[-1] * k)
    white = serial <= torch.tensor([max(_SERIAL_CHI2 / m, SERIAL_LIMIT) for m in n], dtype=serial.dtype, device=serial.device)
    enough = torch.tensor([(h.shape[-2] - 1) * k >= MIN_DIFFERENCES, (v.shape[-1] - 1) * k >= MIN_DIFFERENCES],
                          device=serial.device)  # differences Δ_j behind the MAD, rows and columns
    sigma = sig2.sqrt().contiguous()
    detected = (tt > T_LIMIT) & (sigma > MIN_BANDING_DN) & white & enough
    return RowColumnNoise(sigma, se.contiguous(), tt.contiguous(), serial.contiguous(), detected)


def debanded_details(x: torch.Tensor, m: torch.Tensor, d2: torch.Tensor, g2: torch.Tensor, detected: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """The squared details d² (3, B, 1, h, w) and the block-mean gradients g² (B, 1, h, w) of
    :func:`camhealth.estimators.noise_features.block_details`, with the offsets of the detected rows and columns
    (``detected`` (B, 2) bool) taken out: h − H̃_j and v − Ṽ_i (the band is the same in every block of a block row or
    column), and the vertical (horizontal) central difference of block means less its median along the block row
    (column), which carries (r_{2j+2} + r_{2j+3} − r_{2j−2} − r_{2j−1})/2 for all blocks alike. Patches with
    nothing detected keep their values; the diagonal detail never carries banding."""
    if not bool(detected.any()):
        return d2, g2
    d2, g2 = d2.clone(), g2.clone()
    hd, vd = _signed_details(x)
    rows, cols = detected[:, 0], detected[:, 1]
    if bool(rows.any()):
        hs = hd[rows]
        d2[1, rows, 0] = (hs - _midmean(hs, hs.shape[-1])[0].unsqueeze(-1)).square().float()
    if bool(cols.any()):
        vs = vd[cols].transpose(-1, -2)
        d2[2, cols, 0] = (vs - _midmean(vs, vs.shape[-1])[0].unsqueeze(-1)).square().transpose(-1, -2).float()
    mm = m[:, 0].float()
    gv = torch.zeros_like(mm)
    gh = torch.zeros_like(mm)
    gv[:, 1:-1, :] = mm[:, 2:, :] - mm[:, :-2, :]
    gh[:, :, 1:-1] = mm[:, :, 2:] - mm[:, :, :-2]
    gv = torch.where(rows.view(-1, 1, 1), gv - gv.median(-1, keepdim=True).values, gv)
    gh = torch.where(cols.view(-1, 1, 1), gh - gh.median(-2, keepdim=True).values, gh)
    gv[:, 0, :] = 0.0
    gv[:, -1, :] = 0.0
    gh[:, :, 0] = 0.0
    gh[:, :, -1] = 0.0
    any_band = (rows | cols).view(-1, 1, 1, 1)
    return d2, torch.where(any_band, (gv.square() + gh.square()).unsqueeze(1), g2)
