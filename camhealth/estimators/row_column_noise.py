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

**Clipped blocks** (all four pixels within ½ DN of 0 or 255: :data:`CLIP_MARGIN_DN`) are left out: a saturated or
black area has lost the offsets and the noise together, its details are 0 and pulled every row's midmean towards 0
(5 DN of row noise over 2 DN of pixel noise read 4.65 DN with a fifth of the patch at 255 DN, 2.84 DN with 40 %; with
them left out 5.21 and 5.05 DN, 5.36 unclipped). A block row's midmean is then the middle half of its n unclipped
details (k_n and c_n for that n), a row with fewer than :data:`MIN_ROW_BLOCKS` of them is left out with the
differences it enters, and the counts behind the detection (differences, rows) are those left. A block with only
some pixels clipped is kept: leaving out every block that holds a clipped pixel selects, under noise clipped at
scattered pixels, the blocks whose noise and offsets stayed away from the bound, and cancels the offsets (2 DN of row
noise over 5 DN of pixel noise at a mean of 3 DN, 31 % of the pixels at 0: detected on 6 % of the patches instead of
99 %). A patch without a fully clipped block is read exactly as before.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch

from camhealth._order import lower_median, sorted_values
from camhealth._validation import check_finite, check_float, check_tensor
from camhealth.estimators.noise_features import _block_pixels

__all__ = ["RowColumnNoise", "row_column_noise", "debanded_details", "T_LIMIT", "MIN_BANDING_DN", "MIN_DIFFERENCES",
           "SERIAL_LIMIT", "CLIP_MARGIN_DN", "MIN_ROW_BLOCKS"]

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
#: A pixel within this many DN of 0 or 255 is clipped; a 2×2 block of four clipped pixels is left out (module
#: docstring).
CLIP_MARGIN_DN = 0.5
#: Fewest unclipped blocks (all of them on narrower patches) a block row (column) needs to enter the estimate.
MIN_ROW_BLOCKS = 8
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


@functools.lru_cache(maxsize=None)
def _midmean_constants_fast(n: int) -> tuple[float, float]:
    """(k_n, c_n) as :func:`_midmean_constants` for rows of ``n`` values, from 2¹⁴ seeded rows in NumPy (a few ms; the
    rows of a clipped patch have many different n): within about 1 % of the 2¹⁶-row values."""
    rng = np.random.default_rng(n)
    lo = n // 4
    mid = np.sort(rng.standard_normal((1 << 14, n)), axis=1)[:, lo:n - lo]
    return float(mid.var(axis=1).mean()), float(mid.mean(axis=1).var() * n)


def _block_clipped(x: torch.Tensor) -> torch.Tensor:
    """(B, ⌊H/2⌋, ⌊W/2⌋) bool: the 2×2 blocks of B×1×H×W patches whose four pixels all lie within
    :data:`CLIP_MARGIN_DN` of 0 or 255 DN (module docstring)."""
    out = None
    for q in _block_pixels(x.float()):
        c = (q.abs() <= CLIP_MARGIN_DN) | ((q - 255.0).abs() <= CLIP_MARGIN_DN)
        out = c if out is None else out & c
    return out[:, 0]


def _masked_midmean(h: torch.Tensor, keep: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_midmean` over the values ``keep`` marks, per row (…, W): the midmean and the variance of the middle half
    of the n kept values (float64; sorted in float32), and n (int64). Rows with nothing kept give 0."""
    w = h.shape[-1]
    n = keep.sum(-1)
    hs = sorted_values(torch.where(keep, h.float(), torch.full_like(h, math.inf, dtype=torch.float32)))
    lo = torch.div(n, 4, rounding_mode="floor").unsqueeze(-1)
    idx = torch.arange(w, device=h.device)
    sel = (idx >= lo) & (idx < n.unsqueeze(-1) - lo)
    cnt = sel.sum(-1).clamp_min(1).float()
    mid = torch.where(sel, hs, torch.zeros_like(hs))
    m = mid.sum(-1) / cnt
    var = (mid.square().sum(-1) / cnt - m.square()).clamp_min(0.0)
    return m.double(), var.double(), n


def _masked_lower_median(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """The lower median of the values ``valid`` marks along the last dimension (0 where none is)."""
    n = valid.sum(-1, keepdim=True)
    xs = sorted_values(torch.where(valid, x, torch.full_like(x, math.inf)))
    k = (torch.div(n + 1, 2, rounding_mode="floor") - 1).clamp_min(0)
    return torch.where(n[..., 0] > 0, xs.gather(-1, k)[..., 0], torch.zeros_like(xs[..., 0]))


def _masked_mad_var(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """:func:`_mad_var` over the values ``valid`` marks (0 where none is)."""
    med = _masked_lower_median(x, valid).unsqueeze(-1)
    return (_masked_lower_median((x - med).abs(), valid) * _MAD_TO_SD).square()


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


def _masked_serial_correlation(mid: torch.Tensor, row_ok: torch.Tensor, pool: bool) -> torch.Tensor:
    """:func:`_serial_correlation` over the block rows ``row_ok`` marks (…, B, J): the line, the clip and the mean over
    those rows, ρ_k over the pairs of them k rows apart; pooled, the mean ρ_k of the patches with two rows or more."""
    j = mid.shape[-1]
    m = row_ok.to(mid.dtype)
    cnt = m.sum(-1, keepdim=True)
    t = torch.arange(j, dtype=mid.dtype, device=mid.device)
    tm = (m * t).sum(-1, keepdim=True) / cnt.clamp_min(1.0)
    mm = (m * mid).sum(-1, keepdim=True) / cnt.clamp_min(1.0)
    tc = (t - tm) * m
    slope = (tc * (mid - mm)).sum(-1, keepdim=True) / tc.square().sum(-1, keepdim=True).clamp_min(1e-12)
    res = (mid - mm - slope * (t - tm)) * m
    lim = 3.0 * _masked_mad_var(res, row_ok).sqrt().unsqueeze(-1)
    res = torch.maximum(torch.minimum(res, lim), -lim) * m
    res = (res - res.sum(-1, keepdim=True) / cnt.clamp_min(1.0)) * m
    var = res.square().sum(-1).clamp_min(1e-12)
    rho = torch.stack([(res[..., k:] * res[..., :-k]).sum(-1) / var for k in range(1, _LAGS + 1)], -1)  # (…, B, LAGS)
    if pool:
        used = (cnt >= 2).to(mid.dtype)  # (…, B, 1)
        rho = (rho * used).sum(-2, keepdim=True) / used.sum(-2, keepdim=True).clamp_min(1.0)
    return rho.square().sum(-1)


def _masked_directions(h: torch.Tensor, keep: torch.Tensor, pool: bool) -> tuple[torch.Tensor, ...]:
    """:func:`_directions` over the blocks ``keep`` marks (D, B, J, W): each row's midmean over its kept details with
    the constants of their number, rows with fewer than :data:`MIN_ROW_BLOCKS` (all W where W is smaller) left out
    with their differences. Returns σ̂², its standard error, T, the serial correlation, the differences and the block
    rows behind them, each (D, B); 0 where no difference is left."""
    d, b, w = h.shape[0], h.shape[1], h.shape[-1]
    mid, mid_var, n = _masked_midmean(h, keep)  # (D, B, J)
    row_ok = n >= min(MIN_ROW_BLOCKS, w)
    k_tab = torch.ones(w + 1, dtype=torch.float64, device=h.device)
    c_tab = torch.ones(w + 1, dtype=torch.float64, device=h.device)
    for v in torch.unique(n[row_ok]).tolist():
        k_tab[v], c_tab[v] = _midmean_constants(w) if v == w else _midmean_constants_fast(int(v))
    k_n, c_n = k_tab[n], c_tab[n]
    per_value = c_n * (mid_var / k_n) / n.clamp_min(1).double()  # c_n·s²/n: the variance of each midmean
    delta = mid[..., 1:] - mid[..., :-1]
    nu = per_value[..., 1:] + per_value[..., :-1]
    valid = row_ok[..., 1:] & row_ok[..., :-1]
    t = torch.where(valid, delta / nu.clamp_min(1e-12).sqrt(), torch.zeros_like(delta))
    if pool:
        delta, nu, t, valid = (v.reshape(d, 1, -1) for v in (delta, nu, t, valid))
    n_diff = valid.sum(-1)  # (D, B) or (D, 1)
    var_delta = _masked_mad_var(delta, valid)
    sig2 = ((var_delta - _masked_lower_median(nu, valid)) / 4.0).clamp_min(0.0)
    se = 2.0 * 1.166 * var_delta / n_diff.clamp_min(1).double().sqrt() / 4.0
    serial = _masked_serial_correlation(mid, row_ok, pool)
    rows = row_ok.sum(-1)
    if pool:
        rows = rows.sum(-1, keepdim=True)
    some = n_diff > 0
    out = tuple(torch.where(some, v, torch.zeros_like(v)) for v in (sig2, se, _masked_mad_var(t, valid), serial))
    out = out + (n_diff, rows)
    return tuple(v.expand(d, b) for v in out) if pool else out


def row_column_noise(patches: torch.Tensor, pool: bool = False) -> RowColumnNoise:
    """Row and column noise of B×1×H×W patches in [0, 1] (H, W ≥ 8; module docstring).

    ``pool``: the patches show one camera (a frame's patches): their differences enter one estimate, the same for
    every patch. Returns :class:`RowColumnNoise` (fields (0, 2) for an empty batch).

    The patches must be a floating tensor (``TypeError`` otherwise: integer DN images, divide by 255 first) of finite
    intensities in [0, 1] (DN/255); a static pair's unclamped fold
    (:func:`~camhealth.estimators.static_pair.static_pair_image` with ``clamp=False``), whose scaled difference reaches
    1/√2 beyond either bound, is accepted as well: values outside [−1/√2, 1 + 1/√2] (DN-scale input) raise a
    ``ValueError`` naming the range found, as do NaN/inf."""
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
    n_rows = torch.tensor([[h.shape[-2] * k, v.shape[-1] * k]], device=serial.device).expand(sig2.shape)
    n_diff = torch.tensor([[(h.shape[-2] - 1) * k, (v.shape[-1] - 1) * k]], device=serial.device).expand(sig2.shape)
    clip = _block_clipped(x.detach())
    hit = clip.flatten(1).any(1)  # (B,) patches with a clipped block: read over their unclipped blocks
    if bool(hit.any()):
        sel = torch.ones_like(hit) if pool else hit  # pooled: one estimate for every patch
        keep_h, keep_v = ~clip[sel], ~clip[sel].transpose(-1, -2)
        hs, vts = h[sel], vt[sel]
        if hs.shape == vts.shape:
            m_both = _masked_directions(torch.stack([hs, vts]), torch.stack([keep_h, keep_v]), pool)
        else:
            m_both = tuple(torch.cat(p) for p in zip(_masked_directions(hs.unsqueeze(0), keep_h.unsqueeze(0), pool),
                                                     _masked_directions(vts.unsqueeze(0), keep_v.unsqueeze(0), pool)))
        sig2, se, tt, serial, n_rows, n_diff = (q.clone() for q in (sig2, se, tt, serial, n_rows, n_diff))
        for full, part in zip((sig2, se, tt, serial, n_diff, n_rows), m_both):
            full[sel] = part.t().to(full.dtype)
    white = serial <= torch.clamp(_SERIAL_CHI2 / n_rows.clamp_min(1).to(serial.dtype), min=SERIAL_LIMIT)
    enough = n_diff >= MIN_DIFFERENCES  # differences Δ_j behind the MAD, rows and columns
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
    clip = _block_clipped(x)
    rows, cols = detected[:, 0], detected[:, 1]

    def offsets(det: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:  # the midmean of each row (B', J, 1)
        mid = _midmean(det, det.shape[-1])[0]
        hit = ~keep.flatten(1).all(1)
        if bool(hit.any()):  # a patch with clipped blocks: the midmean of its unclipped details (module docstring)
            mid = torch.where(hit.view(-1, 1), _masked_midmean(det, keep)[0], mid)
        return mid.unsqueeze(-1)

    if bool(rows.any()):
        hs = hd[rows]
        d2[1, rows, 0] = (hs - offsets(hs, ~clip[rows])).square().float()
    if bool(cols.any()):
        vs = vd[cols].transpose(-1, -2)
        d2[2, cols, 0] = (vs - offsets(vs, ~clip[cols].transpose(-1, -2))).square().transpose(-1, -2).float()
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
