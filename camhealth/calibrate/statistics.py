"""Statistics of one set of frames: mean level, temporal noise, clipping, master frame, hot pixels.

All values are in DN of the 8-bit scale (0…255, camhealth's convention): a frame in [0, 1] is multiplied by
255 whatever the bit depth of its file.

Two estimators of the temporal noise, chosen per set by how much of it is clipped:

* **temporal** (EMVA 1288 Release 4.0, Sec. 6: the temporal variance of each pixel over the frames,
  averaged over the pixels; fixed-pattern noise does not enter it) when at most
  :data:`CENSORED_ABOVE` of the pixels sit at the lowest or highest code. Each frame's mean is removed first
  (as EMVA's pair difference y_A − y_B − (µ_A − µ_B) does), so that a light or offset that changes from frame
  to frame does not enter the variance. The quantisation noise of the input's step q, σ_q² = q²/12 (EMVA
  1288 Eq. 13 [DN²]), is subtracted; below a raw variance of :data:`QUANTISATION_LIMITED_BELOW`·q² (σ below
  about half a step) that correction does not hold and the set is marked ``quantisation_limited``.
* **censored** (a Gaussian fitted by maximum likelihood to all values of the set, with the values at the
  lowest code treated as "at or below it" and those at the highest code as "at or above it") otherwise. A
  camera without offset clips half of its dark noise at 0 DN (thesis Sec. 3.3.2: "the intensity
  distribution of I_RN may be truncated with all negative intensity values set to zero"); the sample
  variance of such frames (Eq. 3.27) is far too small, and the censored fit recovers the latent mean and
  σ. For integer-coded input every value stands for the interval of its code (interval censoring), so the
  quantisation needs no separate correction. The thesis's own rectification (Alg. 1, ``fixHistogram``:
  mirror the histogram at its maximum x_max, bins x ≥ 2·x_max onto 2·x_max − x, and fit a normal
  distribution) gives the starting point of the fit and is reported beside it.

The censored fit pools pixels, so a fixed pattern (DSNU/PRNU) adds to its σ²; the temporal estimator is
free of it. EMVA 1288 asks for an offset high enough that the dark signal is not clipped; give a camera
that allows it such an offset and the temporal estimator is used.

The highest code is 255 DN (full scale), or the set's highest value where the values pile up there
(:func:`top_clip_level`): a pixel full well reached below the ADC's range, or 10/12-bit data in a 16-bit word
whose top code lies below 255 DN; for a flat whose every value sits at one code above 0 DN, that code (a flat
saturated at its full well). Any other set whose frames are all identical has no temporal noise and is refused.

The quantisation step is that of the code grid the values lie on (:func:`quantisation_step`): the scale the files
were read with when it is known (b-bit data read as value/(2^b − 1)), else the 16-bit grid or the grid of b = 9 … 15
bits. Pixels at 0 DN in every frame of a lit set whose other values stay off 0 DN are dead, not clipping
(:func:`stuck_at_zero`): the pipeline leaves them out of the flats' statistics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, special

__all__ = [
    "CENSORED_ABOVE",
    "PILE_UP_FRACTION",
    "QUANTISATION_LIMITED_BELOW",
    "HOT_PIXEL_SIGMAS",
    "SetStatistics",
    "quantisation_step",
    "top_clip_level",
    "mirrored_histogram_fit",
    "censored_normal_fit",
    "binned_censored_normal_fit",
    "detect_hot_pixels",
    "detect_dead_pixels",
    "DEAD_PIXEL_SIGMAS",
    "MIN_FRAME_SIDE",
    "set_statistics",
    "stuck_at_zero",
    "binned_normal_nll",
    "poisson_gaussian_cdf",
    "poisson_gaussian_group_fit",
]

#: A set whose clipped fraction (lowest + highest code) exceeds this is analysed with the censored fit.
CENSORED_ABOVE = 1e-4
#: A set with fewer than this fraction of its values strictly between its lowest and highest code is not fitted
#: (method "clipped").
MIN_UNCLIPPED_FRACTION = 0.02
#: A set's highest value below 255 DN is a clip level when at least this fraction of its values sit there (and a
#: normal distribution would have put values above it: :func:`top_clip_level`).
PILE_UP_FRACTION = 1e-3
#: A temporal set whose raw temporal variance (before the q²/12 correction) is below this many q² is
#: quantisation-limited: its σ is below ≈ 0.45 q, where q²/12 misses the quantisation noise by 10 % and more
#: depending on where the level sits between two codes (two codes alone give up to 0.25 q² whatever σ is).
QUANTISATION_LIMITED_BELOW = 0.3
#: A pixel whose master-frame level lies this many robust standard deviations above the median is hot.
HOT_PIXEL_SIGMAS = 6.0
#: A pixel whose flat-field signal lies this many robust standard deviations below the median is dead (or dim).
DEAD_PIXEL_SIGMAS = 6.0
#: Side [px] of the neighbourhood whose median a pixel's flat-field signal is compared with.
DEAD_PIXEL_WINDOW = 5
#: Smallest frame side [px] a set may have: the dead-pixel test's :data:`DEAD_PIXEL_WINDOW` × DEAD_PIXEL_WINDOW
#: neighbourhood must fit in a frame (in a smaller one the "neighbourhood" is mostly the edge pixels repeated), and the
#: spatial statistics — the median and MAD of the hot-pixel test, the variance of the fixed pattern (DSNU, PRNU: one
#: pixel has none, ``var(ddof=1)`` of it is NaN), each frame's mean removed from the temporal variance — need pixels to
#: pool. 5×5 = 25 px is a floor for validity, not for accuracy (``docs/calibration.md`` asks for ≥ 512×512 px).
MIN_FRAME_SIDE = DEAD_PIXEL_WINDOW
#: Frames are rounded to this many codes over [0, 1] to test for integer coding (16-bit resolution).
_CODES = 65535
#: Full-scale codes of b-bit data (b = 8 … 16) stored MSB-aligned in a 16-bit word: 65536 − 2^(16−b).
_FULL_SCALE_CODES = frozenset(_CODES + 1 - 2**k for k in range(9))


@dataclass
class SetStatistics:
    """Statistics of one set of N frames of H×W pixels, in DN (0…255 scale).

    Attributes:
        mean_dn: mean level µ [DN] (latent mean for the censored fit; fixed pattern averaged out).
        mean_err_dn: 1σ uncertainty of ``mean_dn`` [DN].
        var_dn2: temporal noise variance σ² [DN²].
        var_err_dn2: 1σ uncertainty of ``var_dn2`` [DN²].
        method: ``"temporal"``, ``"censored"`` (module docstring) or ``"clipped"`` (fewer than
            :data:`MIN_UNCLIPPED_FRACTION` of the values inside (0, ``upper_dn``): nothing fitted, σ² NaN).
        clipped_low, clipped_high: fraction of the values at the lowest code (0 DN) / at ``upper_dn``.
        mirrored_sigma_dn: σ of the thesis's histogram rectification (Alg. 1) [DN] (reported for comparison).
        spatial_var_dn2: variance of the fixed pattern (master frame minus its mean, with the temporal
            noise's share σ²/N removed and, for clipped sets, scaled back to the latent level) [DN²].
        step_dn: quantisation step of the input [DN] (0: continuous values).
        n_frames, height, width: frames and their size.
        n_pixels: pixels used (hot pixels excluded).
        master_dn: per-pixel mean over the frames, H×W float32 [DN].
        upper_dn: the highest code [DN]: 255, or the level the values pile up at (:func:`top_clip_level`).
        raw_var_dn2: temporal variance before the quantisation correction [DN²] (temporal method; else NaN).
        quantisation_limited: temporal method with ``raw_var_dn2`` < :data:`QUANTISATION_LIMITED_BELOW`·step²:
            ``var_dn2`` is not a measurement of σ² (the noise is below about half a code step).
    """

    mean_dn: float
    mean_err_dn: float
    var_dn2: float
    var_err_dn2: float
    method: str
    clipped_low: float
    clipped_high: float
    mirrored_sigma_dn: float
    spatial_var_dn2: float
    step_dn: float
    n_frames: int
    height: int
    width: int
    n_pixels: int
    master_dn: np.ndarray = field(repr=False)
    hist_edges_dn: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    hist_counts: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    upper_dn: float = 255.0
    raw_var_dn2: float = float("nan")
    quantisation_limited: bool = False

    @property
    def sigma_dn(self) -> float:
        """Temporal noise σ [DN]."""
        return math.sqrt(max(self.var_dn2, 0.0))


def quantisation_step(frames: np.ndarray, bits: int | None = None) -> float:
    """Quantisation step of frames in [0, 1], in DN of 255: 1.0 for 8-bit data, 255/65535 for 16-bit data,
    255·k/65535 for data on every k-th 16-bit code (10/12-bit data stored MSB-aligned in 16 bits), 255/(2^b − 1)
    for b-bit data read as value/(2^b − 1) (a PNG's ``sBIT`` chunk, 10/12-bit data in the low bits, b = 9 … 15),
    0.0 for continuous values (floats that are on none of these code grids).

    ``bits``: the scale the frames were read with (value/(2^bits − 1)), when known: its grid is tried first. Without
    it (or when the values are not on that grid), the 16-bit grid is tried, then the grids of b = 9 … 15 bits
    (every value within 0.02 codes of a code of one of them).

    The step is the spacing of the code lattice the values lie on: the greatest common divisor of the differences
    between the distinct codes strictly between 0 and the grid's top (the codes at 0 and at the top may be clipping
    levels, off the lattice), so that codes o + q·k with an offset o (a black-level pedestal added after a digital
    gain of q) give q, whatever o is. It needs at least 3 such codes; with fewer (a set of a few sparse codes), the
    greatest common divisor of the codes below the top, 0 included, is used, which needs at least 2 of them — one
    code alone, e.g. a constant frame at 128 DN, would give its own value as the step. With fewer, the step is one
    code of the grid (the finest the input can have)."""
    flat = np.asarray(frames).ravel()
    grids = [_CODES] + [2**b - 1 for b in range(9, 16)]
    if bits is not None and 2 <= int(bits) <= 16:
        grids = [2 ** int(bits) - 1] + [g for g in grids if g != 2 ** int(bits) - 1]
    for top in grids:
        if not _on_grid(flat[:4096], top) or not _on_grid(flat, top):
            continue
        unique = np.unique(np.rint(flat.astype(np.float64) * top).astype(np.int64))
        below = unique[unique < top]  # the clipped top says nothing about the step
        inner = below[below > 0]  # nor does 0, where the values are clipped at it off an offset lattice
        if inner.size >= 3:
            step = int(np.gcd.reduce(np.diff(inner)))
        elif below.size >= 2 and 0 in below:
            step = int(np.gcd.reduce(below))
        elif below.size >= 2:
            step = int(np.gcd.reduce(np.diff(below)))
        else:
            step = 1
        return 255.0 * max(step, 1) / top
    return 0.0


def _on_grid(values: np.ndarray, top: int) -> bool:
    """Whether every value·top lies within 0.02 of an integer (values on the code grid k/top)."""
    codes = values.astype(np.float64) * top
    return float(np.abs(codes - np.rint(codes)).max(initial=0.0)) <= 0.02


def top_clip_level(values_dn: np.ndarray, step_dn: float) -> float:
    """The level [DN] at which a set's values are clipped at the top: 255 DN (full scale); the set's highest value
    when it is the full-scale code of 8…16-bit data stored MSB-aligned in 16 bits (12-bit: 65520/65535·255 =
    254.94 DN); or the set's highest value where the values pile up: at least :data:`PILE_UP_FRACTION` of them
    (and ≥ 2) sit at it, while a normal distribution with the values' mean and σ would put at least 10 values —
    and at least a tenth as many as sit there — above it (above its code interval, for quantised input), where
    there are none (a pixel full well reached below the ADC's range clips so). An unclipped set's highest code holds
    that many values only where its σ is below about one step, and then a normal distribution puts next to nothing
    above it."""
    v = np.asarray(values_dn, dtype=np.float64).ravel()
    top = float(v.max())
    if top >= 255.0 - 1e-9:
        return 255.0
    if step_dn > 0 and int(round(top / 255.0 * _CODES)) in _FULL_SCALE_CODES:
        return top
    n_top = int((v >= top - 1e-9).sum())
    if n_top < max(PILE_UP_FRACTION * v.size, 2):
        return 255.0
    sd = float(v.std())
    if not sd > 0:  # one value throughout: nothing to tell a pile-up from
        return 255.0
    beyond = v.size * float(special.ndtr(-(top + step_dn / 2 - float(v.mean())) / sd))
    return top if beyond >= max(10.0, 0.1 * n_top) else 255.0


def mirrored_histogram_fit(values_dn: np.ndarray, step_dn: float, upper_dn: float = 255.0) -> tuple[float, float]:
    """Thesis Alg. 1 (``fixNoiseDistr``): histogram, its maximum x_max (excluding the clipped end bins),
    bins beyond 2·x_max (from the clipped side) mirrored at x_max, and a normal distribution fitted to
    the rectified histogram (weighted mean and standard deviation). Returns (µ, σ) [DN].

    The clipped bins themselves (values at 0 or at ``upper_dn``) are left out: their mass is what the
    mirrored bins reconstruct.
    """
    v = values_dn.ravel().astype(np.float64)
    low, high = v <= 0.0, v >= upper_dn
    inner = v[~low & ~high]
    if inner.size < 2:
        return float(v.mean()), float(v.std())
    spread = float(np.subtract(*np.percentile(inner, [75, 25])))
    width = max(step_dn, spread / 40.0, 1e-6)
    lo = 0.0
    nbins = max(int(math.ceil((inner.max() - lo) / width)) + 1, 2)
    counts, edges = np.histogram(inner, bins=nbins, range=(lo, lo + nbins * width))
    centres = 0.5 * (edges[:-1] + edges[1:])
    x_max = centres[int(np.argmax(counts))]
    xs, ws = [centres], [counts.astype(np.float64)]
    if low.any():  # reconstruct bins ≤ 0 from bins ≥ 2·x_max
        sel = centres >= 2.0 * x_max
        xs.append(2.0 * x_max - centres[sel])
        ws.append(counts[sel].astype(np.float64))
    if high.any():  # and bins ≥ upper from bins ≤ 2·x_max − upper
        sel = centres <= 2.0 * x_max - upper_dn
        xs.append(2.0 * x_max - centres[sel])
        ws.append(counts[sel].astype(np.float64))
    x, w = np.concatenate(xs), np.concatenate(ws)
    mu = float(np.average(x, weights=w))
    sigma = float(math.sqrt(max(np.average((x - mu) ** 2, weights=w), 0.0)))
    return mu, sigma


def _numeric_hessian(fun, x: np.ndarray, rel: float = 1e-4) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    n = x.size
    h = rel * np.maximum(np.abs(x), 1e-3)
    hess = np.empty((n, n))
    for i in range(n):
        for j in range(i, n):
            ei, ej = np.zeros(n), np.zeros(n)
            ei[i], ej[j] = h[i], h[j]
            val = (fun(x + ei + ej) - fun(x + ei - ej) - fun(x - ei + ej) + fun(x - ei - ej)) / (4 * h[i] * h[j])
            hess[i, j] = hess[j, i] = val
    return hess


def _covariance(nll, mu: float, sigma: float) -> np.ndarray:
    """Covariance of (µ, σ) from the inverse observed information (numeric Hessian of the NLL)."""
    hess = _numeric_hessian(lambda p: nll(p[0], p[1]), np.array([mu, sigma]))
    try:
        cov = np.linalg.inv(hess)
    except np.linalg.LinAlgError:
        return np.full((2, 2), np.nan)
    if not np.all(np.isfinite(cov)) or cov[0, 0] < 0 or cov[1, 1] < 0:
        return np.full((2, 2), np.nan)
    return cov


def censored_normal_fit(
    n_low: int, n_high: int, n_inner: int, sum_inner: float, sumsq_inner: float,
    lower: float = 0.0, upper: float = 255.0, start: tuple[float, float] | None = None,
) -> tuple[float, float, np.ndarray]:
    """Maximum-likelihood (µ, σ) of a normal distribution clipped to [lower, upper], from sufficient statistics.

    ``n_low`` values at ``lower`` (the latent value was ≤ lower), ``n_high`` at ``upper`` (≥ upper) and
    ``n_inner`` values strictly inside with sum and sum of squares. Negative log-likelihood

        −n_low·ln Φ((lower−µ)/σ) − n_high·ln Φ((µ−upper)/σ) + n_inner·ln σ + Σ(y−µ)²/(2σ²)

    minimised with its analytic gradient; the covariance of (µ, σ) is the inverse of its numeric Hessian.
    Returns (µ, σ, cov) in the units of the data.
    """
    m = float(n_inner)
    if m < 2:
        raise ValueError(f"a censored fit needs at least 2 unclipped values, got {int(m)}")
    s1, s2 = float(sum_inner), float(sumsq_inner)

    def nll(mu: float, s: float) -> float:
        if s <= 0:
            return np.inf
        a, b = (lower - mu) / s, (mu - upper) / s
        q = s2 - 2 * mu * s1 + m * mu * mu
        return float(-n_low * special.log_ndtr(a) - n_high * special.log_ndtr(b) + m * math.log(s) + q / (2 * s * s))

    def mills(x: float) -> float:  # φ(x)/Φ(x), stable
        return math.exp(-0.5 * x * x - 0.5 * math.log(2 * math.pi) - float(special.log_ndtr(x)))

    scale = 1.0 / (n_low + n_high + m)

    def f(p: np.ndarray) -> tuple[float, np.ndarray]:
        mu, s = p[0], math.exp(p[1])
        a, b = (lower - mu) / s, (mu - upper) / s
        q = s2 - 2 * mu * s1 + m * mu * mu
        la, lb = (mills(a) if n_low else 0.0), (mills(b) if n_high else 0.0)
        g_mu = n_low * la / s - n_high * lb / s + (m * mu - s1) / (s * s)
        g_ls = n_low * la * a + n_high * lb * b + m - q / (s * s)
        return nll(mu, s) * scale, np.array([g_mu, g_ls]) * scale

    if start is None:
        mean = s1 / m
        start = (mean, math.sqrt(max(s2 / m - mean * mean, 1e-12)))
    x0 = np.array([start[0], math.log(max(start[1], 1e-9))])
    res = optimize.minimize(f, x0, jac=True, method="BFGS", options={"gtol": 1e-10, "maxiter": 500})
    mu, sigma = float(res.x[0]), float(math.exp(res.x[1]))
    return mu, sigma, _covariance(nll, mu, sigma)


def binned_censored_normal_fit(
    centres: np.ndarray, counts: np.ndarray, step: float, lower: float = 0.0, upper: float = 255.0,
    start: tuple[float, float] | None = None,
) -> tuple[float, float, np.ndarray]:
    """Maximum-likelihood (µ, σ) of a normal distribution observed through a quantiser of step ``step``
    and clipped to [lower, upper]: a value at code c stands for the interval [c − step/2, c + step/2), the
    lowest code for (−∞, lower + step/2) and the highest for [upper − step/2, ∞). ``centres`` are the codes'
    values and ``counts`` how often they occur. Returns (µ, σ, cov)."""
    c = np.asarray(centres, dtype=np.float64)
    n = np.asarray(counts, dtype=np.float64)
    keep = n > 0
    c, n = c[keep], n[keep]
    if c.size < 3:
        raise ValueError(
            f"the noise is too small for the quantisation: the values fall on {c.size} code(s) only, at least 3 "
            f"are needed to fit a mean and a σ (step {step:g} DN); record the set at a higher gain or bit depth"
        )
    lo_edge = np.where(c <= lower + 1e-9, -np.inf, c - step / 2)
    hi_edge = np.where(c >= upper - 1e-9, np.inf, c + step / 2)
    total = n.sum()

    def nll(mu: float, s: float) -> float:
        if s <= 0:
            return np.inf
        a, b = (lo_edge - mu) / s, (hi_edge - mu) / s
        # P(a < Z < b), computed in the tail where it is accurate
        p = np.where(a > 0, special.ndtr(-a) - special.ndtr(-b), special.ndtr(b) - special.ndtr(a))
        return float(-(n * np.log(np.maximum(p, 1e-300))).sum())

    if start is None:
        mean = float((c * n).sum() / total)
        start = (mean, math.sqrt(max(float(((c - mean) ** 2 * n).sum() / total), step * step / 12)))
    x0 = np.array([start[0], math.log(max(start[1], 1e-6))])
    res = optimize.minimize(
        lambda p: nll(p[0], math.exp(p[1])) / total, x0, method="Nelder-Mead",
        options={"xatol": 1e-9, "fatol": 1e-13, "maxiter": 4000},
    )
    mu, sigma = float(res.x[0]), float(math.exp(res.x[1]))
    return mu, sigma, _covariance(nll, mu, sigma)


def _censored_moments(mu: float, sigma: float, lower: float, upper: float) -> tuple[float, float, float]:
    """Mean, variance of clip(X, lower, upper) for X ~ N(µ, σ²), and P(lower < X < upper)."""
    a, b = (lower - mu) / sigma, (upper - mu) / sigma
    pa, pb = special.ndtr(a), special.ndtr(b)
    da, db = math.exp(-0.5 * a * a) / math.sqrt(2 * math.pi), math.exp(-0.5 * b * b) / math.sqrt(2 * math.pi)
    p_in = pb - pa
    # E[X·1{a<Z<b}] and E[X²·1{a<Z<b}] of the truncated part
    e1 = mu * p_in + sigma * (da - db)
    e2 = (mu * mu + sigma * sigma) * p_in + 2 * mu * sigma * (da - db) + sigma * sigma * (a * da - b * db)
    mean = lower * pa + e1 + upper * (1 - pb)
    second = lower * lower * pa + e2 + upper * upper * (1 - pb)
    return float(mean), float(max(second - mean * mean, 0.0)), float(p_in)


def detect_hot_pixels(master_dn: np.ndarray, temporal_sigma_dn: float, n_frames: int, step_dn: float) -> np.ndarray:
    """Pixels whose master-frame level is more than :data:`HOT_PIXEL_SIGMAS` robust standard deviations
    above the median (robust σ: 1.4826·MAD, at least the temporal σ/√N and the quantisation step/N)."""
    med = float(np.median(master_dn))
    mad = 1.4826 * float(np.median(np.abs(master_dn - med)))
    scale = max(mad, temporal_sigma_dn / math.sqrt(max(n_frames, 1)), step_dn / max(n_frames, 1), 1e-9)
    return master_dn > med + HOT_PIXEL_SIGMAS * scale


def detect_dead_pixels(signal_dn: np.ndarray, temporal_sigma_dn: float, n_frames: int, step_dn: float,
                       exclude: np.ndarray | None = None) -> np.ndarray:
    """Pixels whose flat-field signal (master flat minus the dark level) [DN] lies more than
    :data:`DEAD_PIXEL_SIGMAS` robust standard deviations below the median of its 5×5 neighbourhood: dead pixels and
    ones whose response is far below their neighbours'. Against the local median, so that the flat's own shading
    (vignetting, uneven light) is not read as dead pixels; robust σ: 1.4826·MAD of the signal minus its local
    median, which the PRNU sets, at least the temporal σ/√N and the quantisation step/N. ``exclude`` (hot pixels)
    are neither counted in the MAD nor flagged."""
    from scipy import ndimage

    keep = np.ones(signal_dn.shape, dtype=bool) if exclude is None else ~np.asarray(exclude, dtype=bool)
    if not keep.any():
        return np.zeros(signal_dn.shape, dtype=bool)
    resid = signal_dn - ndimage.median_filter(signal_dn, size=DEAD_PIXEL_WINDOW, mode="nearest")
    vals = resid[keep]
    mad = 1.4826 * float(np.median(np.abs(vals - np.median(vals))))
    temporal = temporal_sigma_dn if math.isfinite(temporal_sigma_dn) else 0.0
    scale = max(mad, temporal / math.sqrt(max(n_frames, 1)), step_dn / max(n_frames, 1), 1e-9)
    return (resid < -DEAD_PIXEL_SIGMAS * scale) & keep


def stuck_at_zero(frames: np.ndarray, exclude: np.ndarray | None = None) -> np.ndarray:
    """Pixels (H×W bool) at 0 DN in every frame of a lit set (dead pixels: no response), when the set's other pixels
    have at most :data:`CENSORED_ABOVE` of their values at 0 DN; else none. Under that condition a pixel whose
    distribution reaches 0 DN in every one of N ≥ 2 frames is not part of the set's distribution (its chance is
    below CENSORED_ABOVE^N), so it is left out of the set's statistics instead of being counted as clipping; in a
    set whose values reach 0 DN by themselves (a dark frame of a camera without offset) nothing is left out."""
    x = np.asarray(frames)
    stuck = (x <= 0.0).all(axis=0)
    if exclude is not None:
        stuck &= ~np.asarray(exclude, dtype=bool)
    if x.shape[0] < 2 or not stuck.any():
        return np.zeros(x.shape[1:], dtype=bool)
    others = ~stuck if exclude is None else ~stuck & ~np.asarray(exclude, dtype=bool)
    if not others.any() or float((x[:, others] <= 0.0).mean()) > CENSORED_ABOVE:
        return np.zeros(x.shape[1:], dtype=bool)
    return stuck


def set_statistics(
    frames: np.ndarray, exclude: np.ndarray | None = None, step_dn: float | None = None, name: str = "the set",
    flat: bool = False,
) -> SetStatistics:
    """Statistics of a set of frames (N×H×W in [0, 1]); ``exclude`` (H×W bool) masks pixels (hot pixels); ``name``
    labels the set in errors. ``flat``: a lit set, whose values all at one code above 0 DN are saturated (a full
    well below the ADC's range; method ``"clipped"`` with every value at the top code), not a frozen image.

    Raises ``ValueError`` naming the set for fewer than 2 frames, frames smaller than :data:`MIN_FRAME_SIDE` ×
    MIN_FRAME_SIDE px (0×0 included), fewer than 2 pixels left after ``exclude``, or frames that are all identical (no
    pixel changes from frame to frame: no temporal noise to measure) unless (almost) every value is clipped.
    """
    x = np.asarray(frames, dtype=np.float32)
    if x.ndim != 3:
        raise ValueError(f"frames must be N×H×W, got shape {x.shape}")
    n, h, w = x.shape
    if n < 2:
        raise ValueError(f"{name}: a set needs at least 2 frames for its temporal noise, got {n}")
    if h < MIN_FRAME_SIDE or w < MIN_FRAME_SIDE:
        raise ValueError(
            f"{name}: its frames are {h}×{w} px; a set needs frames of at least {MIN_FRAME_SIDE}×{MIN_FRAME_SIDE} px (the "
            f"dead-pixel test's {DEAD_PIXEL_WINDOW}×{DEAD_PIXEL_WINDOW} neighbourhood, and pixels to pool for the hot-pixel "
            "test and the fixed pattern, DSNU and PRNU); record the whole sensor or a crop of at least 512×512 px"
        )
    step = quantisation_step(x) if step_dn is None else float(step_dn)
    dn = x.astype(np.float64) * 255.0
    master = dn.mean(axis=0)
    keep = np.ones((h, w), dtype=bool) if exclude is None else ~np.asarray(exclude, dtype=bool)
    if int(keep.sum()) < 2:
        raise ValueError(f"{name}: {h * w - int(keep.sum())} of its {h}×{w} pixels are excluded (hot or dead), leaving "
                         f"{int(keep.sum())}; its statistics need at least 2")
    vals = dn[:, keep]  # N × P
    n_pix = int(keep.sum())
    upper = top_clip_level(vals, step)
    if flat and float(vals.min()) == float(vals.max()) > 0.0:  # one code throughout a lit set: saturated there
        upper = float(vals.max())
    low = vals <= 0.0 + 1e-9
    high = vals >= upper - 1e-9
    n_low, n_high = int(low.sum()), int(high.sum())
    total = vals.size
    clipped = (n_low + n_high) / total
    if clipped > 1.0 - MIN_UNCLIPPED_FRACTION:  # (almost) every value at the lowest or highest code: nothing to fit
        return SetStatistics(
            mean_dn=float(vals.mean()), mean_err_dn=float("nan"), var_dn2=float("nan"), var_err_dn2=float("nan"),
            method="clipped", clipped_low=n_low / total, clipped_high=n_high / total, mirrored_sigma_dn=float("nan"),
            spatial_var_dn2=float("nan"), step_dn=step, n_frames=n, height=h, width=w, n_pixels=n_pix,
            master_dn=master.astype(np.float32), upper_dn=upper,
        )
    if not (vals != vals[:1]).any():
        lo_v, hi_v = float(vals.min()), float(vals.max())
        raise ValueError(
            f"{name}: its {n} frames are identical (no pixel changes from frame to frame"
            + (f"; every value is {lo_v:.6g} DN: a frozen image, or saturated at one code" if lo_v == hi_v else "")
            + "), so there is no temporal noise to measure; "
            "record separate frames of the sensor (not one buffer or still image repeated)"
        )
    spread = vals.std(axis=1)  # each frame's spatial σ [DN]
    blank = np.flatnonzero(spread == 0.0)
    if blank.size and float(np.median(spread)) > max(step, 0.0):  # one value throughout while the others vary
        raise ValueError(
            f"{name}: frame {int(blank[0])} of its {n} (0-based, in the set's order) holds one value throughout "
            f"({float(vals[blank[0], 0]):.6g} DN) while the others vary (median spatial σ {float(np.median(spread)):.3g} DN)"
            + (f"; so do {blank.size - 1} more" if blank.size > 1 else "")
            + ": a blank or dropped frame, whose step from the others would read as temporal noise; remove it from the set"
        )
    mir_mu, mir_sigma = mirrored_histogram_fit(vals, step, upper)
    raw, limited = float("nan"), False
    if clipped <= CENSORED_ABOVE:
        # each frame's mean removed (E[·] = σ²·(1 − 1/P), hence the factor): a changing light or offset drops out
        resid = vals - vals.mean(axis=1, keepdims=True) if n_pix > 1 else vals
        var_t = resid.var(axis=0, ddof=1) * (n_pix / (n_pix - 1) if n_pix > 1 else 1.0)
        raw = float(var_t.mean())
        var = raw - step * step / 12.0
        limited = step > 0 and raw < QUANTISATION_LIMITED_BELOW * step * step
        var_err = float(math.sqrt(2.0 / (n_pix * (n - 1)))) * max(raw, 1e-12)
        mean = float(vals.mean())
        mean_err = math.sqrt(max(var, 0.0) / total)
        spatial = float(master[keep].var(ddof=1)) - raw / n
        method = "temporal"
    else:
        start = (mir_mu, max(mir_sigma, 1e-6))
        if step > 0:
            codes = np.rint(vals / step).astype(np.int64).ravel()
            counts = np.bincount(codes - codes.min())
            centres = (np.arange(counts.size) + codes.min()) * step
            mu, sigma, cov = binned_censored_normal_fit(centres, counts, step, 0.0, upper, start)
        else:
            inner = vals[~low & ~high]
            mu, sigma, cov = censored_normal_fit(
                n_low, n_high, inner.size, float(inner.sum()), float(np.square(inner).sum()), 0.0, upper, start
            )
        var = sigma * sigma
        var_err = 2.0 * sigma * math.sqrt(cov[1, 1]) if np.isfinite(cov[1, 1]) else float("nan")
        mean, mean_err = mu, (math.sqrt(cov[0, 0]) if np.isfinite(cov[0, 0]) else float("nan"))
        _, var_clipped, p_in = _censored_moments(mu, sigma, 0.0, upper)
        spatial = (float(master[keep].var(ddof=1)) - var_clipped / n) / max(p_in, 1e-6) ** 2
        method = "censored"
    edges, counts = _histogram(vals, step, math.sqrt(max(var, 1e-12)), upper)
    return SetStatistics(
        mean_dn=mean, mean_err_dn=mean_err, var_dn2=var, var_err_dn2=var_err, method=method,
        clipped_low=n_low / total, clipped_high=n_high / total, mirrored_sigma_dn=mir_sigma,
        spatial_var_dn2=max(spatial, 0.0), step_dn=step, n_frames=n, height=h, width=w, n_pixels=n_pix,
        master_dn=master.astype(np.float32), hist_edges_dn=edges, hist_counts=counts, upper_dn=upper,
        raw_var_dn2=raw, quantisation_limited=bool(limited),
    )


def _histogram(vals: np.ndarray, step: float, sigma: float, upper: float = 255.0,
               max_bins: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """Interval histogram of all values [DN]: bin k holds the values in [e_k, e_{k+1}); the first bin starts at
    −∞ (values at 0 DN) and the last ends at +∞ (values at the highest code ``upper``) when those occur.
    Quantised data: one bin per code (whole codes merged when there would be more than ``max_bins``);
    continuous data: bins of σ/16 (at most ``max_bins``)."""
    v = vals.ravel()
    lo_v, hi_v = float(v.min()), float(v.max())
    if step > 0:
        first, last = int(round(lo_v / step)), int(round(hi_v / step))
        width = step * max(1, math.ceil((last - first + 1) / max_bins))
        start = first * step - step / 2
    else:
        width = max(sigma / 16.0, (hi_v - lo_v) / max_bins, 1e-9)
        start = lo_v
    nb = max(int(math.ceil((hi_v - start) / width + 1e-9)), 1)
    edges = start + width * np.arange(nb + 1, dtype=np.float64)
    edges[-1] = max(edges[-1], hi_v + 1e-9)
    counts, _ = np.histogram(v, bins=edges)
    if lo_v <= 1e-9:  # values at 0 DN stand for everything at or below it
        edges[0] = -np.inf
    if hi_v >= upper - 1e-9:
        edges[-1] = np.inf
    return edges, counts.astype(np.float64)


def binned_normal_nll(edges: np.ndarray, counts: np.ndarray, start: tuple[float, float]) -> float:
    """The smallest negative log-likelihood of a normal distribution (µ, σ free) for a histogram with bin ``edges``
    (the first may be −∞, the last +∞: clipped values) and ``counts``, started at ``start`` = (µ, σ): the
    Gaussian fit a model of the same histogram is compared with."""
    e = np.asarray(edges, dtype=np.float64)
    n = np.asarray(counts, dtype=np.float64)
    total = max(float(n.sum()), 1.0)

    def nll(mu: float, sd: float) -> float:
        a, b = (e[:-1] - mu) / sd, (e[1:] - mu) / sd
        p = np.where(a > 0, special.ndtr(-a) - special.ndtr(-b), special.ndtr(b) - special.ndtr(a))
        return float(-(n * np.log(np.maximum(p, 1e-300))).sum())

    x0 = np.array([float(start[0]), math.log(max(float(start[1]), 1e-6))])
    res = optimize.minimize(lambda q: nll(q[0], math.exp(q[1])) / total, x0, method="Nelder-Mead",
                            options={"xatol": 1e-9, "fatol": 1e-13, "maxiter": 4000})
    return min(nll(float(res.x[0]), math.exp(float(res.x[1]))), nll(float(x0[0]), math.exp(float(x0[1]))))


def _nll_binned(cdf, edges: np.ndarray, counts: np.ndarray) -> float:
    c = cdf(edges)
    p = np.diff(c)
    return float(-(counts * np.log(np.maximum(p, 1e-300))).sum())


def _poisson_nodes(mean_e: float, max_nodes: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """Nodes N − S [e⁻] and weights of the zero-mean dark-electron count N − S, N ~ Poisson(S), covering ±8σ.

    The nodes sit at whole electrons *relative to S* (j = …, −1, 0, 1, … with the Poisson probability continued
    to S + j, renormalised), not at whole electrons of N: the readout noise (σ_R ≫ K·1 e⁻ in practice) smears the
    lattice anyway, and this way no node crosses 0 as S changes, so the likelihood of the clipped-charge model
    stays smooth in the dark current. More than ``max_nodes`` nodes are merged in blocks at their weighted mean
    (the variance lost is ≈ (block/σ)²/12 of it: < 0.1 %).
    """
    s = max(mean_e, 0.0)
    if s <= 0:
        return np.zeros(1), np.ones(1)
    half = int(math.ceil(8 * math.sqrt(s) + 3))
    j = np.arange(-min(half, int(math.floor(s))), half + 1, dtype=np.float64)
    n = s + j
    w = np.exp(n * math.log(s) - s - special.gammaln(n + 1))
    if j.size > max_nodes:
        block = int(math.ceil(j.size / max_nodes))
        pad = (-j.size) % block
        jj = np.concatenate([j, np.zeros(pad)]).reshape(-1, block)
        ww = np.concatenate([w, np.zeros(pad)]).reshape(-1, block)
        wsum = ww.sum(1)
        j = (jj * ww).sum(1) / np.maximum(wsum, 1e-300)
        w = wsum
    w = w / w.sum()
    return j - float((j * w).sum()), w  # exactly zero-mean after the truncation


def poisson_gaussian_cdf(x: np.ndarray, offset: float, sigma_r: float, dark_e: float, k_dn_per_e: float, clip_charge: bool) -> np.ndarray:
    """CDF of a dark pixel: Y = o + c(K·(N − S)) + R with N ~ Poisson(S) dark electrons [e⁻] (their mean S removed,
    camhealth's offset-free model), R ~ N(0, σ_R²) readout noise [DN], K [DN/e⁻], and c the identity (clipped once,
    at the end) or max(·, 0) (``clip_charge``: the charge is clipped at 0 before the readout)."""
    j, w = _poisson_nodes(dark_e)
    q = k_dn_per_e * j
    if clip_charge:
        q = np.maximum(q, 0.0)
    x = np.asarray(x, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        z = (x[:, None] - offset - q[None, :]) / sigma_r
    return (special.ndtr(z) * w[None, :]).sum(1)


def poisson_gaussian_group_fit(
    histograms: list[tuple[np.ndarray, np.ndarray]], exposures_s: list[float], k_dn_per_e: float, clip_charge: bool,
    start: tuple[float, float, float],
) -> tuple[np.ndarray, np.ndarray, float]:
    """Joint maximum-likelihood fit of the dark sets of one temperature and gain to :func:`poisson_gaussian_cdf`:
    one offset o [DN], readout σ_R [DN] and dark current DC [e⁻/s] (S_i = DC·t_i) for the group, K known (from
    the photon transfer). Unlike a Gaussian fit to clipped frames it has the dark signal's Poisson skew, so the
    upper half that clipped frames show is not mistaken for a wider distribution. Returns ((o, σ_R, DC), their
    covariance, NLL)."""
    ts = np.asarray(exposures_s, dtype=np.float64)
    total = float(sum(c.sum() for _, c in histograms))

    def nll(p: np.ndarray) -> float:
        o, sr, dc = p
        if sr <= 0 or dc < 0:
            return np.inf
        return sum(_nll_binned(lambda x, t=t: poisson_gaussian_cdf(x, o, sr, dc * t, k_dn_per_e, clip_charge), e, c)
                   for (e, c), t in zip(histograms, ts))

    x0 = np.array([start[0], math.log(max(start[1], 1e-6)), math.log(max(start[2], 1e-6))])
    res = optimize.minimize(lambda q: nll(np.array([q[0], math.exp(q[1]), math.exp(q[2])])) / total, x0,
                            method="Nelder-Mead", options={"xatol": 1e-7, "fatol": 1e-12, "maxiter": 3000})
    p = np.array([res.x[0], math.exp(res.x[1]), math.exp(res.x[2])])
    try:
        cov = np.linalg.inv(_numeric_hessian(nll, p))
    except np.linalg.LinAlgError:
        cov = np.full((3, 3), np.nan)
    return p, cov, nll(p)
