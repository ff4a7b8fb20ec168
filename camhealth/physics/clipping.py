"""Clipping (saturation) of noisy pixels and what it does to each noise source's σ — in closed form.

The ADC clips y = x + n to [0, 255] DN (conventions.md; the last step of Fig. 3.7 before quantisation). The
labels of :func:`~camhealth.physics.image_formation.form_image` attribute the clipped noise y − x to the
sources by one factor per pixel, f = (y − x)/n, so source k keeps n_k·f. This module gives the expected
per-source and total standard deviations of a patch after clipping, for a known clean image x and per-pixel
source variances σ_k²(x) [DN²], treating the total noise n = Σ n_k as Gaussian N(0, σ²), σ² = Σ σ_k²
(the sources are independent and, at the counts where clipping matters, near-normal).

Per pixel, with l = (0 − x)/σ, h = (255 − x)/σ and the clipped noise y = clamp(n, −x, 255 − x):

    E[y]/σ   = φ(l) − φ(h) + l·Φ(l) + h·Q(h)
    E[y²]/σ² = Φ(h) − Φ(l) − h·φ(h) + l·φ(l) + l²·Φ(l) + h²·Q(h)
    E[f²]    = Φ(h) − Φ(l) + |l|·φ(l) − l²·Φ(l) + h·φ(h) − h²·Q(h)

(Q = 1 − Φ; the tail terms of E[f²] come from ∫ φ(u)/u² du = −φ(u)/u − Φ(u)). Since n_k = β_k·n + e_k with
β_k = σ_k²/σ² and e_k independent of n (jointly Gaussian),

    E[n_k·f]     = β_k·E[y]
    E[(n_k·f)²]  = β_k²·E[y²] + σ_k²·(1 − β_k)·E[f²].

The patch's σ per source is then √(mean E[(n_k f)²] − (mean E[n_k f])²) over its pixels, the label's
definition (standard deviation over the patch) up to the sampling noise of one realisation. Checks: far
from the bounds every moment is that of n (f = 1); at x = 0 exactly, E[(n_k f)²] = σ_k²/2 for every source.

A source's σ after clipping may exceed the total's. y = clamp(n, −x, 255 − x) spans at most 255 DN, so on a flat
scene σ_y ≤ 127.5 DN; n_k·f = n_k·y/n is not so confined (|n_k| > |n| where the other sources cancel part of n_k),
and the shares are negatively correlated: with e_k = n_k − β_k·n, E[e_j·e_k] = −σ_j²σ_k²/σ² for j ≠ k, so
E[(n_j f)(n_k f)] = β_jβ_k·E[y²] − (σ_j²σ_k²/σ²)·E[f²] can be negative and the shares' variances add up to more than
the total's. Under strong clipping a source's σ then exceeds the clipped total and 127.5 DN (x = 128 DN, σ_k = 8.9,
300 and 425 DN: 5.2, 147 and 163 DN against a total of 119 DN; Monte Carlo of the rule gives the same). That is the
attribution rule, not an error of these moments; clamping a source at the total would no longer describe the labels.

:func:`estimate_clean_dn` recovers the clean intensity near the bounds from a noisy, clipped image: the
3×3 mean of the observed values estimates E[clamp(x + n)], which is inverted for x (bisection; the censored
mean is increasing in x). Away from the bounds the 3×3 mean is the estimate. All functions are pure, batched
over B and computed in float64.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from camhealth._validation import check_finite, check_tensor
from camhealth.physics._format import check_range

__all__ = ["censored_noise_moments", "clipped_sigma_dn", "censored_mean_dn", "estimate_clean_dn", "FULL_SCALE_DN"]

#: Upper clipping bound [DN] of the 8-bit output (the lower bound is 0 DN).
FULL_SCALE_DN = 255.0
_SQRT2 = math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
#: Pixels whose 3×3 mean lies this many σ (of the largest noise at any intensity) from a bound are treated as
#: unaffected by clipping: P(|n| > 6σ) < 2e-9.
_NEAR_SIGMAS = 6.0
#: Newton steps of :func:`estimate_clean_dn` stop once no pixel moved by more than this [DN] in the last step (float32:
#: 255 DN is resolved to 1.5e-5 DN).
_NEWTON_TOL_DN = 1e-4


def _phi(u: torch.Tensor) -> torch.Tensor:
    return torch.exp(-0.5 * u * u) * _INV_SQRT_2PI


def _cdf(u: torch.Tensor) -> torch.Tensor:
    return 0.5 * torch.special.erfc(-u / _SQRT2)


def censored_noise_moments(
    x: torch.Tensor, var: torch.Tensor, dtype: torch.dtype = torch.float64,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """E[y], E[y²] and E[f²] of the clipped noise y = clamp(n, −x, 255 − x), n ~ N(0, var), f = y/n.

    Args:
        x: clean intensities [DN], any shape. E[y] and E[y²] hold for any x; E[f²] needs x in [0, 255] (clean
            images are; outside, f = y/n is unbounded near n = 0 and E[f²] diverges) and is returned clamped to
            [0, 1].
        var: total noise variance [DN²], broadcastable to ``x``; 0 gives y = 0 where 0 < x < 255 (f = 1).
        dtype: floating dtype of the computation (float64 by default; float32 is ≈ 2× faster and good to ≈ 1e-6).

    Returns:
        (E[y] [DN], E[y²] [DN²], E[f²]) in the broadcast shape and ``dtype``.
    """
    check_finite(check_tensor(x, "x"), "x")
    _check_variance(var, "var")
    x, var = torch.broadcast_tensors(x.to(dtype), var.to(dtype))
    s = var.clamp_min(0).sqrt()
    zero = s <= 0
    s_safe = torch.where(zero, torch.ones_like(s), s)
    lo, hi = -x / s_safe, (FULL_SCALE_DN - x) / s_safe
    p_lo, q_hi = _cdf(lo), 0.5 * torch.special.erfc(hi / _SQRT2)
    d_lo, d_hi = _phi(lo), _phi(hi)
    inside = (1.0 - q_hi - p_lo).clamp_min(0)
    ey = s * (d_lo - d_hi + lo * p_lo + hi * q_hi)
    ey2 = var * (inside - hi * d_hi + lo * d_lo + lo * lo * p_lo + hi * hi * q_hi)
    ef2 = inside - lo * d_lo - lo * lo * p_lo + hi * d_hi - hi * hi * q_hi
    # zero noise: nothing to clip inside the range; at or beyond a bound a pixel is clipped (y = bound − x)
    inside0 = (x > 0) & (x < FULL_SCALE_DN)
    y0 = torch.where(inside0, torch.zeros_like(x), (x.clamp(0, FULL_SCALE_DN) - x))
    ey = torch.where(zero, y0, ey)
    ey2 = torch.where(zero, y0 * y0, ey2.clamp_min(0))
    ef2 = torch.where(zero, inside0.to(dtype), ef2.clamp(0, 1))
    return ey, ey2, ef2


def clipped_sigma_dn(
    clean_dn: torch.Tensor, variances: list[torch.Tensor], dtype: torch.dtype = torch.float64,
) -> torch.Tensor:
    """Expected σ [DN] of every source and of the total after clipping to [0, 255] DN, per patch.

    Args:
        clean_dn: B×C×H×W (or B×N) clean intensities [DN].
        variances: per-source noise variances [DN²] before clipping, each with one value, one per sample or
            one per pixel (per pixel for photon noise, per sample for signal-independent sources).
        dtype: floating dtype of the per-pixel arithmetic (float64 by default; the camhealth estimators use
            float32, ≈ 2× faster); the sums over the patch are always float64.

    Returns:
        (B, S + 1) float64: the σ of each of the S sources' attributed noise, then of the realised total.
        Only pixels within 6 σ of a bound are evaluated with the censored moments; the others contribute
        their unclipped variance (exact to < 2e-9 relative).
    """
    if not variances:
        raise ValueError("clipped_sigma_dn needs at least one source variance")
    check_finite(check_tensor(clean_dn, "clean_dn"), "clean_dn")
    if clean_dn.ndim < 2:
        raise ValueError(f"clean_dn must be B×C×H×W or B×N, got shape {tuple(clean_dn.shape)}")
    x = clean_dn.to(dtype).flatten(1)
    b, n = x.shape
    vs, per_sample = [], []  # per-sample sources also keep their (B, 1) value
    for k, v in enumerate(variances):
        v = _check_variance(torch.as_tensor(v, device=x.device), f"variance {k}").to(dtype)
        if v.numel() == b * n:
            vs.append(v.reshape(b, n))
            per_sample.append(None)
        elif v.numel() in (1, b):
            vs.append(v.reshape(-1, 1).expand(b, n))
            per_sample.append(v.reshape(-1, 1).expand(b, 1))
        else:
            raise ValueError(
                f"variance {k} has {v.numel()} values; expected 1, one per sample ({b}) or one per pixel ({b * n})"
            )
    var = vs[0].clone()
    for v in vs[1:]:
        var = var + v
    s = var.clamp_min(0).sqrt()
    near = (x < _NEAR_SIGMAS * s) | (x > FULL_SCALE_DN - _NEAR_SIGMAS * s)
    # unclipped pixels: E[n_k f] = 0, E[(n_k f)²] = σ_k², total likewise (a per-sample σ_k² times the count of such
    # pixels: the same float64 sum, exactly, without a pass over the pixels)
    f64 = torch.float64
    far = n - near.sum(1, dtype=f64)
    first = [torch.zeros(b, dtype=f64, device=x.device) for _ in range(len(vs) + 1)]
    second = [torch.where(near, 0.0, v).sum(1, dtype=f64) if c is None else c.to(f64).flatten() * far
              for v, c in zip(vs, per_sample)] + [torch.where(near, 0.0, var).sum(1, dtype=f64)]
    if bool(near.any()):
        rows, cols = near.nonzero(as_tuple=True)
        xv, vv = x[rows, cols], var[rows, cols]
        ey, ey2, ef2 = censored_noise_moments(xv, vv, dtype)
        safe = torch.where(vv > 0, vv, torch.ones_like(vv))
        for k, v in enumerate(vs):
            vk = v[rows, cols]
            beta = torch.where(vv > 0, vk / safe, torch.zeros_like(vk))
            first[k] = first[k].index_add(0, rows, (beta * ey).to(f64))
            second[k] = second[k].index_add(0, rows, (beta * beta * ey2 + vk * (1.0 - beta) * ef2).to(f64))
        first[-1] = first[-1].index_add(0, rows, ey.to(f64))
        second[-1] = second[-1].index_add(0, rows, ey2.to(f64))
    out = [(m2 / n - (m1 / n) ** 2).clamp_min(0).sqrt() for m1, m2 in zip(first, second)]
    return torch.stack(out, 1)


def censored_mean_dn(x: torch.Tensor, var: torch.Tensor) -> torch.Tensor:
    """E[clamp(x + n, 0, 255)] [DN] for n ~ N(0, var) > 0: the mean of a clipped noisy pixel of clean value x
    (the E[y] of :func:`censored_noise_moments`, in the input's floating dtype)."""
    return _censored_mean_and_slope(x, var, torch.zeros_like(x))[0]


def _censored_mean_and_slope(x: torch.Tensor, var: torch.Tensor, dvar_dx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """E[clamp(x + n, 0, 255)] and its derivative in x when var depends on x with slope ``dvar_dx``:
    ∂/∂x = P(inside) and ∂/∂σ = φ(l) − φ(h), so d/dx = P(inside) + (φ(l) − φ(h))·dvar_dx / (2σ)."""
    s = var.clamp_min(1e-30).sqrt()
    lo, hi = -x / s, (FULL_SCALE_DN - x) / s
    p_lo, q_hi, d_lo, d_hi = _cdf(lo), 0.5 * torch.special.erfc(hi / _SQRT2), _phi(lo), _phi(hi)
    mean = x + s * (d_lo - d_hi + lo * p_lo + hi * q_hi)
    slope = (1.0 - p_lo - q_hi).clamp_min(0) + (d_lo - d_hi) * dvar_dx / (2.0 * s)
    return mean, slope


def estimate_clean_dn(
    image_dn: torch.Tensor, slope: torch.Tensor, offset: torch.Tensor, window: int = 3, iterations: int = 8,
    dtype: torch.dtype = torch.float64,
) -> torch.Tensor:
    """Clean intensities [DN] of B×1×H×W noisy, clipped images, for the noise model var(x) = slope·x + offset.

    The ``window``×``window`` mean m of the observed image (replicate borders) estimates the censored mean
    E[clamp(x + n, 0, 255)]. Where m lies within 6 σ of a bound it is inverted for x by bisection — the
    censored mean is increasing in x and |m − x| ≤ E|n| < σ(255), which brackets x; at most ``iterations`` steps of
    Newton's method, safeguarded by bisection of the bracket (8 resolve < 1e-4 DN where it matters), ending early
    once no pixel moves by more than 1e-4 DN; a mean at or beyond the censored mean of a clean level at a bound is
    that bound, without steps — elsewhere x = m. The result is clamped to
    [0, 255] DN, the range of clean images, in ``dtype`` (the inversion itself runs in float32: the 3×3 mean
    is uncertain by σ/3 anyway).

    Args:
        image_dn: B×1×H×W observed intensities [DN].
        slope: (B,) photon-noise variance per DN of signal [DN²/DN] (255·g/FW).
        offset: (B,) signal-independent variance [DN²] (σ_DCSN² + σ_RN²).
    """
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window = {window} must be an odd number ≥ 1")
    check_finite(check_tensor(image_dn, "image_dn"), "image_dn")
    if image_dn.ndim != 4:
        raise ValueError(f"image_dn must be B×1×H×W, got shape {tuple(image_dn.shape)}")
    b = image_dn.shape[0]
    for name, v in (("slope", slope), ("offset", offset)):
        _check_variance(check_tensor(v, name), name)
        if v.numel() != b:
            raise ValueError(f"{name} must hold one value per sample ({b}), got {v.numel()}")
    img = image_dn.to(dtype)
    m = _box_mean(img, window // 2)
    a = slope.to(dtype).reshape(b, 1, 1, 1).clamp_min(0)
    c = offset.to(dtype).reshape(b, 1, 1, 1).clamp_min(1e-12)
    k = _NEAR_SIGMAS
    # the band where clipping moves the mean: x < k·σ(x) near 0 DN (σ² = a·x + c ⇒ x < k²a/2 + √(k⁴a²/4 + k²c)),
    # x > 255 − k·σ(255) near full scale
    low_band = 0.5 * k * k * a + (0.25 * k**4 * a * a + k * k * c).sqrt()
    high_band = FULL_SCALE_DN - k * (a * FULL_SCALE_DN + c).sqrt()
    low, high = m < low_band, m > high_band
    near = low | high
    x = m
    if bool(near.any()):
        idx = near.nonzero(as_tuple=True)
        # float32 suffices here: the 3×3 mean itself is uncertain by σ/3
        target, aa, cc = m[idx].float(), a.flatten()[idx[0]].float(), c.flatten()[idx[0]].float()
        # the censored mean increases with x: a mean at or below its value at x = 0 (above it at 255 DN) is a clean
        # level at the bound, which the result is clamped to anyway; only the others are solved for
        f0 = _censored_mean_and_slope(torch.zeros_like(target), cc, torch.zeros_like(target))[0]
        f255 = _censored_mean_and_slope(torch.full_like(target, FULL_SCALE_DN), aa * FULL_SCALE_DN + cc, torch.zeros_like(target))[0]
        at_bound = torch.where(target <= f0, 0.0, FULL_SCALE_DN)
        solve = (target > f0) & (target < f255)
        pix, target, aa, cc, at_bound = solve.nonzero(as_tuple=True)[0], target[solve], aa[solve], cc[solve], at_bound[~solve]
        # |m − x| = |E[y]| ≤ E|n| < σ(x) ≤ σ(255): x ∈ [m − σ(255), m + σ(255)]
        span = (aa * FULL_SCALE_DN + cc).sqrt()
        lo, hi = target - span, target + span
        # safeguarded Newton: a Newton step where it stays inside the bracket, bisection otherwise
        xv = target.clone()
        for _ in range(iterations if pix.numel() else 0):
            f, df = _censored_mean_and_slope(xv, aa * xv.clamp(0, FULL_SCALE_DN) + cc, aa * ((xv > 0) & (xv < FULL_SCALE_DN)))
            below = f < target
            lo, hi = torch.where(below, xv, lo), torch.where(below, hi, xv)
            step = xv + (target - f) / df.clamp_min(1e-12)
            moved = xv
            # a converged pixel's step is itself, one end of its bracket: it stays (a strict test would bisect it
            # away from the root again)
            xv = torch.where((step >= lo) & (step <= hi), step, 0.5 * (lo + hi))
            if float((xv - moved).abs().max()) < _NEWTON_TOL_DN:  # converged everywhere
                break
        values = torch.empty(solve.shape, dtype=dtype, device=m.device)
        values[pix] = xv.to(dtype)
        values[~solve] = at_bound.to(dtype)
        x = m.index_put(idx, values)
    return x.clamp(0, FULL_SCALE_DN)


def _box_mean(x: torch.Tensor, r: int) -> torch.Tensor:
    """(2r+1)×(2r+1) mean of B×C×H×W with replicate borders, separably from shifted slices (the same values
    as ``avg_pool2d`` of the replicate-padded image, several times faster on the CPU)."""
    if r == 0:
        return x.clone()
    p = F.pad(x, (r, r, r, r), mode="replicate")
    k = 2 * r + 1
    h, w = x.shape[-2], x.shape[-1]
    rows = sum(p[..., :, j:j + w] for j in range(k))
    return sum(rows[..., i:i + h, :] for i in range(k)) / (k * k)


def _check_variance(v: torch.Tensor, name: str) -> torch.Tensor:
    """Variances [DN²] (or slopes [DN²/DN]) must be finite and ≥ 0."""
    return check_range(v, name, 0.0, float("inf"), "DN²")
