"""Siemens-star MTF measurement after ISO 15775 (thesis Sec. 3.3.1.2, Eq. 3.22–3.25), batched.

A Siemens star of f_s bright/dark pairs has, on the circle of radius r around its centre, a square wave
of normalised frequency (Eq. 3.22)

    f_n = f_s / (π r)        (fraction of Nyquist; f = f_s / (2π r) cycles/px).

The measurement, for every image of a batch:

1. **Discrete CTF per radius** (Eq. 3.23). The star is cut into rings of 1 px (pixel centres, no
   interpolation) and ``n_sectors`` angular sectors. In each ring and sector
   ``CTF_D = (I_max − I_min) / (I_max + I_min)``, normalised by the chart's own modulation
   ``(I_w − I_b)/(I_w + I_b)`` measured in the uniform reference areas (median intensities; see
   :func:`~camhealth.estimators.charts.siemens_star_chart`). On a ring the stripes run radially, so a
   sector around the top or bottom of the star (tangent horizontal) measures the **horizontal** MTF and
   a sector around the left or right the **vertical** MTF; the two opposite sectors are averaged.
2. **Gaussian fit** (Eq. 3.24). A Gaussian ``CTF(f) = exp(−(f − μ)² / (2 s²))`` in f_n is fitted to the
   CTF_D samples by least squares — each ring weighted by the frequency interval it covers,
   ``|df/dr|·1 px ∝ f²``, so the sum approximates the integral over f of Eq. 3.24 — with a batched
   Levenberg–Marquardt iteration started from a log-quadratic fit.
3. **CTF → MTF** (Eq. 3.25; Coltman 1954). A square wave is a series of odd harmonics, so the
   square-wave response CTF relates to the sine-wave response MTF by
   ``MTF(f) = π/4 · Σ_k B_k · CTF(k f)`` over odd k with ``B_k = (−1)^{m + (k−1)/2} / k`` for k square-free
   with m prime factors and B_k = 0 otherwise: ``π/4 [CTF(f) + CTF(3f)/3 − CTF(5f)/5 + CTF(7f)/7 +
   CTF(11f)/11 − CTF(13f)/13 − CTF(15f)/15 + …]``. (Eq. 3.25 in the thesis prints the first terms with
   plus signs; the signs here are Coltman's, which make the series the exact inverse of
   ``CTF(f) = 4/π Σ_{k odd} (−1)^{(k−1)/2} MTF(k f)/k`` — checked in the tests.) The series runs to
   k = 99 (the fitted Gaussian extrapolates the CTF beyond the measured rings) and is divided by its
   value for CTF ≡ 1, π/4·Σ_{k ≤ 99} B_k = 1.011, so that an unblurred chart gives MTF ≡ 1. (Normalising
   by the series at f = 0 instead would inflate the MTF whenever the fit puts μ > 0, which it does to
   follow the flat top of a square-wave response, CTF_D = 1 while the stripes are wider than the blur.)

With ``aperture=True`` the pixel aperture of an area-rendered chart, sinc(f), is divided out (H and V). The MTF is
then clamped to [0, 1]: the max − min CTF of a sharp area-rendered chart already reads 1 (each ring holds pixels
wholly inside a stripe), so dividing it by sinc(f) would read above 1.
**Clipping.** ISO 15775 needs an unclipped star: in a clipped ring I_max or I_min is the clip level, not the
stripe's, and clipped reference corners hide the chart's contrast. Pixels within ½ DN of 0 or 1 are clipped; an image
whose measured reference level (a median) is clipped, or with a ring (H and V sectors) of which more than 10 % of the
pixels sit on clipped plateaus (clipped, with a 4-neighbour clipped at the same bound — noise alone rarely clips two
neighbours), raises a ``ValueError`` naming the image, the rings and the clipped share.
**Noise.** I_max − I_min of a ring picks up the noise's extremes. The noise σ is measured in the uniform reference
corners (1.4826·MAD, the rms of the dark and bright corners; with ``levels=`` no corner is read and nothing is
corrected), with its lag-1 correlation ρ along rows and columns (a blur after the noise correlates it), and a ring
and sector of n pixels counts n·(1 − ρ) independent ones. Of a fully blurred ring the range is that of the noise
alone, 2·E[max of n]·σ: the noise-only CTF. A ring whose CTF exceeds :data:`NOISE_KEEP` times that has the
extremes' excess where the stripes are resolved, 2·E[max of n/4]·σ (a crest's pixels compete for the maximum),
subtracted; below it, the noise-only CTF is subtracted in quadrature (a ring with no stripes left reads 0 and stays
in the fit). A star whose corner noise exceeds :data:`MAX_NOISE_CONTRAST` of its contrast I_w − I_b, or with fewer
than :data:`MIN_RINGS` rings above the noise in H or V, is not assessable: its MTF is NaN, with the reason. The
Gaussian fit keeps μ within the sampled frequencies and s within 4× them, so that a fit on the few low-frequency
rings a noisy, strongly blurred star keeps stays a falling CTF.
**Consistency.** A star of f_s = ``n_cycles`` cycles puts on every ring where its stripes survive the blur a component
that repeats f_s times per turn, I(φ) ≈ m + a·cos(f_s φ) + b·sin(f_s φ) (I, m, a, b in image units, DN/255). Every
1-px ring is fitted by least squares on its n pixels, with the neighbouring harmonics f_s ± 3 and f_s ± 5
(:data:`_NEIGHBOURS`) and the sub-harmonics f_s/p (p a prime factor of f_s, f_s/p ≥ 4) as further columns. A ring
*shows the star* where the component passes two tests, each at the false-alarm rate α = :data:`STAR_FALSE_ALARM` =
10⁻³ per ring:

- against the ring's residual: F = (ESS/2) / (RSS/(n − 3)) of the fit of m, a, b (ESS the sum of squares it explains
  beyond the mean, RSS the rest, image units²) exceeds t = (n − 3)/2 · (α^(−2/(n−3)) − 1), the 1 − α quantile of
  F(2, n − 3), its law for white Gaussian noise without the component (P(F > t) = (1 + 2t/(n − 3))^(−(n−3)/2)). A star
  of another period is residual here;
- against the neighbouring harmonics: the Wald statistic of (a, b) in the joint fit, β_Nᵀ V_N⁻¹ β_N / 2 (V_N its
  block of (XᵀX)⁻¹; image units²), exceeds t = J·(α^(−1/J) − 1) (18.5 for J = 4 neighbours) times the neighbours'
  β_Jᵀ V_J⁻¹ β_J / (2J): F(2, 2J) for white noise, and close to it for noise whose spectrum is smooth across ±5
  harmonics — a blur after the noise colours it, and the residual test alone would take the colour's low-frequency
  power for a star.

Both read the noise variance as at least (1/255)²/12, the 8-bit quantisation's (:data:`_QUANTISATION_VAR`). Measured
over 96 images of noise alone × 206 rings: white noise passes them on 1.1·10⁻³ and 0.8·10⁻³ of the rings, both on
1·10⁻⁴; noise blurred by a Gaussian of 2 px after it is drawn passes the residual test on 22 % of them, the neighbours'
on 1.1·10⁻³, both on 0.8·10⁻³. A star is assessable only where at least :data:`MIN_RINGS` rings show it: rings of noise
alone pass with probability ≤ α each, so 10 of R with probability ≤ C(R, 10)·α¹⁰ (3·10⁻¹⁴ for the 206 rings of a
512-px star). A strongly blurred star keeps its component on its outer, low-frequency rings only, and those suffice: no
ring is asked to show contrast. On the rings that show the star:

- **n_cycles**: a sub-harmonic f_s/p with more power than f_s (summed over those rings) means that f_s is a harmonic of
  the star's own period (a 32-cycle star read with ``n_cycles=96``; a star of f_s cycles has no component at f_s/p);
- **levels**: a blur keeps the star's mean, so the rings' mean must lie within :data:`MAX_MID_OFFSET` = 0.25 of the
  contrast I_w − I_b from the mid level (I_b + I_w)/2 (``levels=(0, 0.001)`` on the 0.2/0.8 chart: 500); and the
  component's amplitude, less 3 standard errors, must stay within :data:`MAX_FUNDAMENTAL` = 1.5 times an unblurred
  chart's, (2/π)(I_w − I_b) (a square wave's fundamental; the sharp area-rendered charts read 0.96–0.98, a sharpening
  camera may exceed 1): beyond, the levels lie closer together than the chart's.

A star that fails is not assessable, with the reason ("no star: …", "n_cycles: …", "levels: …"). The 512-px charts of
the tests, of ``python -m camhealth.bench siemens_star`` and of the evaluation (blur to 21 px, noise to 25 DN) show the
star on at least 130 of their 206 rings, their mean within 0.003 of the contrast from the mid level and their amplitude
at most 0.98 of the chart's: their outputs are those without the checks. A centre off by δ px moves J_k(f_s·δ/r) of the
component to f_s ± k: the neighbours at ±3 and ±5 keep a 512-px star read about a centre up to ≈ 10 px off assessable
(15 px off: not).

The Gaussian model is smooth and cannot follow the zeros and contrast reversals of large defocus
(|jinc| side lobes), which bounds the accuracy for large blur; see ``docs/estimators_classical.md``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
from dataclasses import dataclass
from typing import Any, Sequence, Union

import numpy as np
import torch

from camhealth._validation import check_image
from camhealth.estimators._common import check_frequencies
from camhealth.estimators.charts import siemens_star_geometry
from camhealth.physics.mtf import NORMALIZED_FREQUENCIES

__all__ = [
    "MAX_FUNDAMENTAL",
    "MAX_MID_OFFSET",
    "MAX_NOISE_CONTRAST",
    "MIN_RINGS",
    "NOISE_KEEP",
    "STAR_FALSE_ALARM",
    "SiemensStarResult",
    "coltman_coefficients",
    "ctf_from_mtf",
    "mtf_from_ctf",
    "gaussian_ctf_fit",
    "siemens_star_ctf",
    "siemens_star_mtf",
]

_K_MAX = 99

#: A ring is read where its CTF exceeds this multiple of the CTF its noise alone would give (module docstring).
NOISE_KEEP = 2.0
#: Largest noise σ, as a share of the chart's contrast I_w − I_b, whose star is read (beyond: not assessable).
MAX_NOISE_CONTRAST = 0.12
#: Fewest rings per direction (H, V) that the Gaussian fit needs above the noise.
MIN_RINGS = 10
#: False-alarm rate per ring of each of the two tests that the star's n_cycles-periodic component shows on a ring
#: (module docstring, *Consistency*): the chance that a ring of noise alone passes one of them.
STAR_FALSE_ALARM = 1e-3
#: Largest distance of the star's mean level from the mid level (I_b + I_w)/2 of the levels, as a share of their
#: contrast I_w − I_b (module docstring, *Consistency*).
MAX_MID_OFFSET = 0.25
#: Largest amplitude of the star's n_cycles-periodic component on a ring, as a multiple of an unblurred chart's,
#: (2/π)(I_w − I_b) (module docstring, *Consistency*).
MAX_FUNDAMENTAL = 1.5
#: Offsets from n_cycles of the neighbouring angular harmonics whose power estimates a ring's noise near the star's
#: (those below 1 or at a sub-harmonic n_cycles/p are left out): odd, so that neither the pixel grid (sidebands at ±4,
#: ±8, …) nor a point-symmetric blur or a tilted chart (±2, ±4, …) puts the star's own power into them, and beyond ±1,
#: where a centre off by δ px puts J₁(n_cycles·δ/r) of it (a star read about a centre up to ≈ 10 px off keeps its
#: outer rings).
_NEIGHBOURS = (-5, -3, 3, 5)
#: Least eigenvalue of a ring's XᵀX/n for its harmonics to be told apart (a ring cut short by the image border is not).
_MIN_EIGEN = 0.01
#: Variance [image units²] of 8-bit quantisation, (1/255)²/12: the least noise a ring is read with (a component below
#: the rounding of one DN cannot be told from it; it also keeps the float32 sums' rounding out of the tests).
_QUANTISATION_VAR = (1.0 / 255.0) ** 2 / 12.0
#: Slots (ring pixels and padding) of the rings' sums computed at a time: bounds their memory (float32: 2C + 1
#: values a slot per image and harmonic column).
_SLOTS = 1 << 18
#: Most basis values :class:`_RingDesign` keeps (float32: 32 MiB; a 512-px star has about 5 million, a 1024-px one
#: 20 million, computed per call instead). With the design's cache of 4 geometries, at most 128 MiB.
_CACHED_BASIS = 1 << 23
#: Share of a ring and sector's pixels that compete for its maximum (and for its minimum) where the stripes are
#: resolved: n/4, the pixels of a stripe's crest (two bright stripes per sector, each half its pixels near the top).
_EXCESS_SHARE = 0.25


@functools.lru_cache(maxsize=4)
def _coltman(k_max: int) -> tuple[tuple[int, ...], tuple[float, ...]]:
    ks, bs = [], []
    for k in range(1, k_max + 1, 2):
        n, m, p, square_free = k, 0, 3, True
        while n > 1 and p * p <= n:
            if n % p == 0:
                n //= p
                m += 1
                if n % p == 0:
                    square_free = False
                    break
            else:
                p += 2
        if not square_free:
            continue
        if n > 1:
            m += 1
        ks.append(k)
        bs.append((-1.0) ** (m + (k - 1) // 2) / k)
    return tuple(ks), tuple(bs)


def _check_k_max(k_max: Any) -> int:
    """``k_max`` as an int ≥ 1 (the series needs its first term), else a ``TypeError``/``ValueError`` naming it."""
    if isinstance(k_max, (bool, np.bool_)) or not isinstance(k_max, numbers.Integral):
        raise TypeError(f"k_max = {k_max!r} must be an int ≥ 1 (the largest odd harmonic), got {type(k_max).__name__}")
    if k_max < 1:
        raise ValueError(f"k_max = {k_max!r} must be an int ≥ 1 (the largest odd harmonic; below 1 the series has no term)")
    return int(k_max)


def coltman_coefficients(k_max: int = _K_MAX) -> tuple[torch.Tensor, torch.Tensor]:
    """Odd harmonics k ≤ k_max and Coltman's coefficients B_k of ``MTF = π/4 Σ B_k CTF(k f)`` (float64); ``k_max``
    an int ≥ 1."""
    ks, bs = _coltman(_check_k_max(k_max))
    return torch.tensor(ks, dtype=torch.float64), torch.tensor(bs, dtype=torch.float64)


def ctf_from_mtf(mtf_fn, f: torch.Tensor, k_max: int = _K_MAX) -> torch.Tensor:
    """Square-wave response of a system: ``CTF(f) = 4/π Σ_{k odd ≤ k_max} (−1)^{(k−1)/2} MTF(k f)/k``.

    ``mtf_fn`` maps a tensor of frequencies to MTF values (any unit, used consistently with ``f``); ``k_max`` an int ≥ 1.
    """
    k_max = _check_k_max(k_max)
    k = torch.arange(1, k_max + 1, 2, dtype=torch.float64, device=f.device)
    sign = torch.where(((k - 1) / 2) % 2 == 0, 1.0, -1.0)
    vals = mtf_fn(f.double()[..., None] * k)
    return 4.0 / math.pi * (sign / k * vals).sum(dim=-1)


def mtf_from_ctf(ctf_fn, f: torch.Tensor, k_max: int = _K_MAX) -> torch.Tensor:
    """Coltman's inversion (Eq. 3.25): ``MTF(f) = π/4 Σ_k B_k CTF(k f)`` for a callable CTF."""
    k, bk = coltman_coefficients(k_max)
    k, bk = k.to(f.device), bk.to(f.device)
    return math.pi / 4.0 * (bk * ctf_fn(f.double()[..., None] * k)).sum(dim=-1)


def _gauss(f: torch.Tensor, mu: torch.Tensor, log_s: torch.Tensor) -> torch.Tensor:
    return torch.exp(-0.5 * ((f - mu[..., None]) / torch.exp(log_s)[..., None]).square())


def gaussian_ctf_fit(
    f: torch.Tensor, ctf: torch.Tensor, weight: torch.Tensor | None = None, iterations: int = 60
) -> tuple[torch.Tensor, torch.Tensor]:
    """Weighted least-squares fit of ``exp(−(f − μ)²/(2 s²))`` to CTF samples (Eq. 3.24), batched.

    Args:
        f: (N,) or (…, N) frequencies; ctf: (…, N) samples (NaN = no sample); weight: like ``ctf`` or None.
            Tensors whose shapes do not broadcast to ``ctf``'s, or ``ctf`` without samples (N = 0), raise a
            ``TypeError``/``ValueError`` naming them.
        iterations: Levenberg–Marquardt iterations.

    Returns:
        μ and s (each (…)), in the unit of ``f``; NaN for a row without a sample (every value of ``ctf`` NaN or ±inf,
        or of weight 0): there is nothing to fit.
    """
    for name, value in (("f", f), ("ctf", ctf), ("weight", weight)):
        if value is not None and not isinstance(value, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if ctf.ndim == 0 or ctf.shape[-1] == 0:
        raise ValueError(f"ctf has no samples: shape {tuple(ctf.shape)} (… , N) with N ≥ 1 needed")
    for name, value in (("f", f), ("weight", weight)):
        if value is None:
            continue
        try:
            fits = value.ndim <= ctf.ndim and torch.broadcast_shapes(value.shape, ctf.shape) == ctf.shape
        except RuntimeError:  # shapes that do not broadcast at all
            fits = False
        if not fits:
            raise ValueError(f"{name} of shape {tuple(value.shape)} and ctf of shape {tuple(ctf.shape)} do not match: {name} "
                             f"must be (N,) or like ctf (… , N)")
    f = f.double().expand_as(ctf) if f.ndim == 1 else f.double()
    y = ctf.double()
    w = torch.ones_like(y) if weight is None else weight.double().expand_as(y).clone()
    valid = torch.isfinite(y)
    w = torch.where(valid, w, torch.zeros_like(w))
    y = torch.where(valid, y, torch.zeros_like(y))
    # start: log-quadratic fit ln y ≈ c0 + c1 f + c2 f² on the samples above 0.05 (weighted by y²)
    pos = (y > 0.05) & valid
    wl = torch.where(pos, w * y.square(), torch.zeros_like(w))
    ly = torch.where(pos, torch.log(y.clamp_min(1e-6)), torch.zeros_like(y))
    basis = torch.stack([torch.ones_like(f), f, f.square()], dim=-1)  # (…, N, 3)
    ata = (basis * wl[..., None]).transpose(-1, -2) @ basis + 1e-9 * torch.eye(3, dtype=f.dtype, device=f.device)
    atb = ((basis * wl[..., None]) * ly[..., None]).sum(dim=-2)
    coef = torch.linalg.solve(ata, atb)
    c2 = coef[..., 2].clamp(max=-1e-3)
    s0 = torch.sqrt(-0.5 / c2)
    mu0 = (-coef[..., 1] / (2 * c2)).clamp(-3.0 * s0, 3.0 * s0)
    fmax = torch.where(valid, f, torch.zeros_like(f)).amax(dim=-1)
    # the CTF falls from 1 at f = 0 within the sampled frequencies or beyond them: a plateau (μ) ends inside the
    # samples, and a width (s) far beyond them is a flat line. Bounding both keeps a fit on a narrow band of rings (a
    # noisy, strongly blurred star keeps only its low frequencies) from wandering off to μ, s ≫ 1 (a flat MTF)
    lo_mu, hi_mu = -4.0 * fmax, fmax
    hi_ls = torch.log((4.0 * fmax).clamp_min(1e-3))
    mu = torch.maximum(torch.minimum(torch.where(torch.isfinite(mu0), mu0, torch.zeros_like(mu0)), hi_mu), lo_mu)
    log_s = torch.minimum(torch.log(torch.where(torch.isfinite(s0), s0, fmax).clamp(1e-3, 1e3)), hi_ls)
    lam = torch.full_like(mu, 1e-2)

    def loss(m: torch.Tensor, ls: torch.Tensor) -> torch.Tensor:
        return (w * (_gauss(f, m, ls) - y).square()).sum(dim=-1)

    cur = loss(mu, log_s)
    for _ in range(iterations):  # a fixed number of batched LM steps (not a loop over samples)
        s = torch.exp(log_s)[..., None]
        g = _gauss(f, mu, log_s)
        z = (f - mu[..., None]) / s
        j_mu = g * z / s  # ∂g/∂μ
        j_ls = g * z.square()  # ∂g/∂ln s
        jac = torch.stack([j_mu, j_ls], dim=-1)  # (…, N, 2)
        r = g - y
        jtj = (jac * w[..., None]).transpose(-1, -2) @ jac
        jtr = ((jac * w[..., None]) * r[..., None]).sum(dim=-2)
        damp = jtj + lam[..., None, None] * torch.diag_embed(torch.diagonal(jtj, dim1=-2, dim2=-1) + 1e-12)
        step = torch.linalg.solve(damp, jtr)
        mu_new = torch.maximum(torch.minimum(mu - step[..., 0], hi_mu), lo_mu)
        ls_new = torch.minimum((log_s - step[..., 1]).clamp(-8.0, 8.0), hi_ls)
        new = loss(mu_new, ls_new)
        better = new < cur
        mu = torch.where(better, mu_new, mu)
        log_s = torch.where(better, ls_new, log_s)
        cur = torch.where(better, new, cur)
        lam = torch.where(better, lam * 0.3, lam * 10.0).clamp(1e-9, 1e9)
    has = (valid & (w > 0)).any(dim=-1)  # a row without a sample has no fit
    nan = torch.full_like(mu, float("nan"))
    return torch.where(has, mu, nan), torch.where(has, torch.exp(log_s), nan)


#: A pixel within half a DN (8-bit) of 0 or 1 is clipped.
CLIP_MARGIN = 0.5 / 255.0
#: Largest share of a ring's pixels (in the H and V sectors) that may sit on a clipped plateau.
MAX_CLIPPED_SHARE = 0.1


def _check_clipped_rings(img: torch.Tensor, use: torch.Tensor, ring: torch.Tensor, sector: torch.Tensor, n_rings: int,
                         n_sectors: int, n_cycles: int, r_lo: float) -> None:
    """Refuse stars whose measured rings are clipped.

    A pixel is on a clipped plateau when it and at least one of its four neighbours lie within :data:`CLIP_MARGIN`
    (½ DN) of the same bound, 0 or 1 (a stripe's clipped top or bottom; noise alone clips single pixels, rarely two
    side by side). In a ring whose stripes are clipped, I_max or I_min is the clip level rather than the stripe's, and
    CTF_D is wrong; a ring of the H and V sectors with more than :data:`MAX_CLIPPED_SHARE` of its pixels (and at least
    6) on clipped plateaus raises a ``ValueError`` naming the image, the ring and the share.

    img: (B, H, W); use: (H·W,) the ring pixels; ring, sector: their ring and sector index.
    """
    b = img.shape[0]
    hi_c, lo_c = img >= 1.0 - CLIP_MARGIN, img <= CLIP_MARGIN
    if not bool((hi_c | lo_c).any()):
        return

    def plateau(m: torch.Tensor) -> torch.Tensor:
        p = torch.nn.functional.pad(m[:, None].to(torch.uint8), (1, 1, 1, 1))[:, 0].bool()
        nbr = p[:, :-2, 1:-1] | p[:, 2:, 1:-1] | p[:, 1:-1, :-2] | p[:, 1:-1, 2:]
        return m & nbr

    flat = (plateau(hi_c) | plateau(lo_c)).reshape(b, -1)[:, use]  # (B, P) the ring pixels
    q = n_sectors // 4
    measured = (sector % q) == 0  # the H (q, 3q) and V (0, 2q) sectors
    idx = ring[measured]
    n_px = torch.zeros(n_rings, dtype=torch.float64, device=img.device).scatter_add_(0, idx, torch.ones_like(idx, dtype=torch.float64))
    n_cl = torch.zeros(b, n_rings, dtype=torch.float64, device=img.device).scatter_add_(
        1, idx.expand(b, -1), flat[:, measured].to(torch.float64))
    share = n_cl / n_px.clamp_min(1.0)
    bad = (share > MAX_CLIPPED_SHARE) & (n_cl >= 6)
    if bool(bad.any()):
        i, k = (int(v) for v in bad.nonzero()[0])
        rings = bad[i].nonzero()[:, 0]
        r0, r1 = r_lo + float(rings.min()), r_lo + float(rings.max()) + 1.0
        raise ValueError(
            f"images[{i}]: the star is clipped: {int(rings.numel())} of its {n_rings} measured rings (r = {r0:.0f}…{r1:.0f} px, "
            f"f_n = {n_cycles / (math.pi * r1):.3f}…{n_cycles / (math.pi * r0):.3f}) have more than "
            f"{100 * MAX_CLIPPED_SHARE:g} % of their pixels on clipped plateaus (within ½ DN of 0 or 1; up to "
            f"{100 * float(share[i].max()):.0f} %), where I_max or I_min is the clip level and CTF_D reads wrong; "
            f"ISO 15775 needs an unclipped star: lower the exposure or gain"
        )


@dataclass
class SiemensStarResult:
    """Result of :func:`siemens_star_mtf` for B images.

    Attributes:
        mtf: (B, 2F) ``[H×F, V×F]`` MTF at the requested normalised frequencies, in [0, 1].
        frequencies: (R,) normalised frequency of every ring (f_n = f_s / (π r)).
        ctf_d: (B, 2, R) discrete CTF (Eq. 3.23) per ring, H and V, with the noise's expected excess removed (NaN where
            a ring was not used: no pixels, or its CTF within :data:`NOISE_KEEP` × the noise-only CTF).
        mu, s: (B, 2) Gaussian parameters (in f_n) of the fitted CTF, H and V.
        noise_dn: (B,) noise σ [DN] of the reference corners (None when ``levels=`` was given: no corners read).
        rings_used: (B, 2) rings the fit used, H and V.
        assessable: (B,) False where the noise hides the stripes, where fewer than :data:`MIN_RINGS` rings lie in
            the image in both sectors of H or V, or where the image contradicts the star described (fewer than
            :data:`MIN_RINGS` rings with an ``n_cycles``-periodic component above their noise, a sub-harmonic of it
            stronger, or a mean or contrast that the levels cannot give; module docstring, *Consistency*) (``reasons``);
            ``mtf`` is NaN there.
        reasons: per image, "" or why it is not assessable.
    """

    mtf: torch.Tensor
    frequencies: torch.Tensor
    ctf_d: torch.Tensor
    mu: torch.Tensor
    s: torch.Tensor
    noise_dn: torch.Tensor | None = None
    rings_used: torch.Tensor | None = None
    assessable: torch.Tensor | None = None
    reasons: list[str] | None = None


def siemens_star_ctf(
    images: torch.Tensor,
    centre: tuple[float, float] | None = None,
    radius: float | None = None,
    n_cycles: int = 32,
    n_sectors: int = 16,
    margin: float = 24.0,
    levels: tuple[float, float] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Discrete CTF (Eq. 3.23) per 1-px ring, H and V: returns (f_n (R,), ctf_d (B, 2, R), ring radius (R,)). The
    CTF is the one measured, the noise's extremes included (:func:`siemens_star_mtf` corrects for them).

    Args:
        images: ``B×1×S×S`` images of an unclipped Siemens star in [0, 1] (DN/255; default geometry: the star of
            :func:`~camhealth.estimators.charts.siemens_star_chart` for that size). A star whose reference corners
            or measured rings are clipped raises a ``ValueError`` (module docstring).
        centre: (row, col) of the star centre, px; radius: star radius, px.
        n_cycles: f_s, the number of bright/dark pairs, an int ≥ 4 (as
            :func:`~camhealth.estimators.charts.siemens_star_chart`).
        n_sectors: angular sectors (multiple of 4); H uses the two sectors centred at 90° and 270°.
        margin: px (finite, ≥ 0) kept away from the star's rim (where the blur mixes in the reference areas) and,
            for the reference levels, from the rim and the quadrant borders.
        levels: (dark, bright) chart levels, 0 ≤ dark < bright; default: measured in the reference corners (a star
            without 16 pixels of each kind of corner beyond radius + margin is refused: pass levels=).
        A ``centre`` or ``levels`` that is not two finite real numbers, or a ``radius`` that is not a finite number
        > 0, raises a ``ValueError`` naming it.
    """
    c = _star_ctf(images, centre, radius, n_cycles, n_sectors, margin, levels)
    return c.fn, c.ctf, c.r_mean


@dataclass
class _StarCTF:
    fn: torch.Tensor  # (R,) normalised frequency per ring
    ctf: torch.Tensor  # (B, 2, R) measured CTF_D, H and V
    r_mean: torch.Tensor  # (R,) ring radius [px]
    pixels: torch.Tensor  # (2, R) pixels per ring and sector, H and V (the mean of the two sectors)
    sigma: torch.Tensor | None  # (B,) noise σ in the reference corners [image units]; None with ``levels=``
    contrast: torch.Tensor  # (B,) I_w − I_b [image units]
    rho: torch.Tensor | None = None  # (B, 2) lag-1 noise correlation along rows and columns; None with ``levels=``
    img: torch.Tensor | None = None  # (B, H·W) the images, float32 [image units]
    mid: torch.Tensor | None = None  # (B,) mid level (I_b + I_w)/2 [image units]
    geometry: tuple | None = None  # (h, w, centre row, centre col, radius, n_cycles, margin, device): the rings
    levels_given: bool = False  # the levels were passed (``levels=``), not read in the corners


def _polar(h: int, w: int, centre: tuple[float, float], dev: torch.device | str) -> tuple[torch.Tensor, ...]:
    """(dx, dy, r, φ) of every pixel centre of an h×w image about ``centre`` (row, col) [px], flattened; φ in [0, 2π),
    counter-clockwise on screen (y down)."""
    yy, xx = torch.meshgrid(torch.arange(h, device=dev, dtype=torch.float64), torch.arange(w, device=dev, dtype=torch.float64), indexing="ij")
    dx, dy = (xx - centre[1]).reshape(-1), (yy - centre[0]).reshape(-1)
    r = torch.sqrt(dx * dx + dy * dy)
    phi = torch.atan2(-dy, dx) % (2 * math.pi)
    return dx, dy, r, phi


def _two_reals(value: Any, name: str, what: str) -> tuple[float, float]:
    """``value`` as two finite real numbers (a sequence, 1-D array or tensor of two), else a ``ValueError`` naming it
    and ``what`` is allowed."""
    items = None
    if isinstance(value, (torch.Tensor, np.ndarray)):
        if value.ndim == 1 and value.shape[0] == 2:
            items = value.tolist()
    elif isinstance(value, Sequence) and not isinstance(value, (str, bytes)) and len(value) == 2:
        items = list(value)
    if items is None or not all(isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)) and math.isfinite(v)
                                for v in items):
        raise ValueError(f"{name} = {value!r:.80} must be {what}")
    return float(items[0]), float(items[1])


def _star_ctf(
    images: torch.Tensor,
    centre: tuple[float, float] | None = None,
    radius: float | None = None,
    n_cycles: int = 32,
    n_sectors: int = 16,
    margin: float = 24.0,
    levels: tuple[float, float] | None = None,
) -> _StarCTF:
    """The measurement behind :func:`siemens_star_ctf` (same arguments): the CTF per ring, the pixels per ring and
    sector, the reference corners' noise σ (robust: 1.4826·MAD, the rms of the dark and bright corners) and contrast."""
    x = check_image(images, "images", channels=1, value_range=(0.0, 1.0))
    b, _, h, w = x.shape
    if centre is not None:
        centre = _two_reals(centre, "centre", "(row, col): two finite real numbers [px]")
    if radius is not None and (isinstance(radius, (bool, np.bool_)) or not isinstance(radius, numbers.Real)
                               or not math.isfinite(radius) or radius <= 0):
        raise ValueError(f"radius = {radius!r:.80} must be a finite real number > 0 [px] (the star's radius)")
    if levels is not None:
        levels = _two_reals(levels, "levels", "(dark, bright): two finite real numbers with 0 ≤ dark < bright (the "
                                              "chart's levels in image units, DN/255)")
        if not 0.0 <= levels[0] < levels[1]:
            raise ValueError(f"levels = {levels!r} must be (dark, bright): two finite real numbers with 0 ≤ dark < bright "
                             f"(the chart's levels in image units, DN/255)")
    if centre is None or radius is None:
        if h != w:
            raise ValueError(f"the default star geometry needs a square image, got {h}×{w}; pass centre= and radius=")
        cy, cx, rad = siemens_star_geometry(h)
        centre = centre if centre is not None else (cy, cx)
        radius = radius if radius is not None else rad
    if isinstance(n_sectors, bool) or not isinstance(n_sectors, int) or n_sectors < 4 or n_sectors % 4:
        raise ValueError(f"n_sectors = {n_sectors!r} must be a multiple of 4, >= 4")
    if isinstance(n_cycles, bool) or not isinstance(n_cycles, int) or n_cycles < 4:
        raise ValueError(f"n_cycles = {n_cycles!r} must be an int in [4, ∞) (bright/dark pairs of the star)")
    if isinstance(margin, bool) or not isinstance(margin, (int, float)) or not math.isfinite(margin) or margin < 0:
        raise ValueError(f"margin = {margin!r} must be a finite number of px in [0, ∞)")
    dev = x.device
    img = x[:, 0].double().reshape(b, -1)
    dx, dy, r, phi = _polar(h, w, centre, dev)
    # reference levels from the uniform corners: bright where x·y > 0 (y down), beyond the rim + margin
    if levels is None:
        far = (r > radius + margin) & (dx.abs() > margin) & (dy.abs() > margin)
        if int(far.sum()) < 16:
            raise ValueError("the image has no reference corners beyond the star (radius + margin); pass levels=(dark, bright)")
        for what, corner in (("bright", dx * dy > 0), ("dark", dx * dy < 0)):
            n_px = int((far & corner).sum())
            if n_px < 16:  # both levels are read (a median of each): a star placed so that one kind of corner is cut off
                raise ValueError(f"no {what} reference corner beyond the star for centre = ({centre[0]!r}, {centre[1]!r}), "
                                 f"radius = {radius:g} px: {n_px} px of the {what} quadrants lie beyond radius + margin "
                                 f"({radius + margin:g} px), at least 16 needed; pass levels=(dark, bright)")
        bright_px = img[:, far & (dx * dy > 0)]
        dark_px = img[:, far & (dx * dy < 0)]
        i_w, i_b = bright_px.median(dim=1).values, dark_px.median(dim=1).values
        ref_px = ((i_w, bright_px, "bright"), (i_b, dark_px, "dark"))
        # the noise of the uniform corners, robustly (1.4826 × MAD), as the rms of the two levels' (photon noise
        # differs between them; a ring's extremes sit on both)
        mad = [1.4826 * (px - lvl[:, None]).abs().median(dim=1).values for lvl, px in ((i_w, bright_px), (i_b, dark_px))]
        sigma = torch.sqrt(0.5 * (mad[0].square() + mad[1].square()))
        # lag-1 correlation of the corners' noise along rows and columns (a blur after the noise correlates it, and
        # fewer independent pixels compete for a ring's extremes): pairs of neighbours both in one uniform corner
        bright = (dx * dy > 0).reshape(h, w)
        ref_mask = (far & (dx * dy != 0)).reshape(h, w)
        flat = torch.arange(h * w, device=dev).reshape(h, w)
        rho = []
        for first, second in ((flat[:, :-1], flat[:, 1:]), (flat[:-1, :], flat[1:, :])):
            pair = ref_mask.reshape(-1)[first] & ref_mask.reshape(-1)[second] & (bright.reshape(-1)[first] == bright.reshape(-1)[second])
            i0, i1 = first[pair], second[pair]
            lvl = torch.where(bright.reshape(-1)[i0][None], i_w[:, None], i_b[:, None])  # (B, pairs)
            a, c_ = img[:, i0] - lvl, img[:, i1] - lvl
            num = (a * c_).sum(dim=1)
            den = (0.5 * (a.square() + c_.square())).sum(dim=1).clamp_min(1e-30)
            rho.append((num / den).clamp(0.0, 0.99))
        rho_xy = torch.stack(rho, dim=1)  # (B, 2): along rows (H sectors' cells), along columns (V sectors' cells)
    else:
        i_b = torch.full((b,), float(levels[0]), dtype=torch.float64, device=dev)
        i_w = torch.full((b,), float(levels[1]), dtype=torch.float64, device=dev)
        ref_px = ()
        sigma, rho_xy = None, None
    m0 = (i_w - i_b) / (i_w + i_b)
    bad = ~(m0 > 0.05)  # NaN too: both reference levels 0 (a black image) give 0/0
    if bool(bad.any()):
        i = int(bad.nonzero()[0, 0])
        raise ValueError(f"chart modulation (I_w − I_b)/(I_w + I_b) of image {i} = {float(m0[i]):.3f} must exceed 0.05 "
                         f"(reference levels I_b = {float(i_b[i]):.3f}, I_w = {float(i_w[i]):.3f}): is this a Siemens star chart?")
    # a reference level within ½ DN of 0 or 1 is clipped (its median too: more than half its pixels are): the
    # chart's true contrast, which every CTF_D is normalised by, is then unknown
    for lvl, px, what in ref_px:
        bad = (lvl >= 1.0 - CLIP_MARGIN) | (lvl <= CLIP_MARGIN)
        if bool(bad.any()):
            i = int(bad.nonzero()[0, 0])
            share = float(((px[i] >= 1.0 - CLIP_MARGIN) | (px[i] <= CLIP_MARGIN)).double().mean())
            raise ValueError(f"images[{i}]: the {what} reference corners are clipped ({100 * share:.0f} % of their pixels "
                             f"within ½ DN of 0 or 1, median {float(lvl[i]):.4f}), so the chart's contrast is unknown; "
                             f"ISO 15775 needs an unclipped star: lower the exposure or gain (or pass levels=(dark, bright))")
    r_lo = n_cycles / math.pi  # f_n = 1 (Nyquist)
    r_hi = radius - margin
    if r_hi <= r_lo + 4:
        raise ValueError(f"star radius {radius:g} px is too small for n_cycles = {n_cycles} and margin = {margin:g} px")
    use = (r >= r_lo) & (r < r_hi)
    n_rings = int(math.floor(r_hi - r_lo))
    ring = torch.floor(r[use] - r_lo).long().clamp(max=n_rings - 1)
    width = 2 * math.pi / n_sectors
    sector = torch.round(phi[use] / width).long() % n_sectors
    cell = ring * n_sectors + sector
    vals = img[:, use]
    n_cells = n_rings * n_sectors
    idx = cell.expand(b, -1)
    i_max = torch.full((b, n_cells), -math.inf, dtype=torch.float64, device=dev).scatter_reduce(1, idx, vals, "amax")
    i_min = torch.full((b, n_cells), math.inf, dtype=torch.float64, device=dev).scatter_reduce(1, idx, vals, "amin")
    _check_clipped_rings(x[:, 0], use, ring, sector, n_rings, n_sectors, n_cycles, r_lo)
    ctf = ((i_max - i_min) / (i_max + i_min).clamp_min(1e-12)) / m0[:, None]
    ctf = torch.where(torch.isfinite(i_max) & torch.isfinite(i_min), ctf, torch.full_like(ctf, float("nan")))
    ctf = ctf.reshape(b, n_rings, n_sectors)
    q = n_sectors // 4
    ctf_h = 0.5 * (ctf[..., q] + ctf[..., 3 * q])  # sectors at 90° and 270°: tangent horizontal
    ctf_v = 0.5 * (ctf[..., 0] + ctf[..., 2 * q])  # sectors at 0° and 180°
    r_sum = torch.zeros(n_rings, dtype=torch.float64, device=dev).scatter_add_(0, ring, r[use])
    r_cnt = torch.zeros(n_rings, dtype=torch.float64, device=dev).scatter_add_(0, ring, torch.ones_like(r[use]))
    # a ring without a pixel (the star reaches beyond the image) keeps its nominal radius: its f_n stays finite, and
    # the fit, which leaves its NaN CTF out, is not spoilt by an infinite frequency
    nominal = r_lo + 0.5 + torch.arange(n_rings, dtype=torch.float64, device=dev)
    r_mean = torch.where(r_cnt > 0, r_sum / r_cnt.clamp_min(1), nominal)
    fn = n_cycles / (math.pi * r_mean)
    count = torch.zeros(n_cells, dtype=torch.float64, device=dev).scatter_add_(0, cell, torch.ones_like(r[use]))
    count = count.reshape(n_rings, n_sectors)
    pixels = torch.stack([0.5 * (count[:, q] + count[:, 3 * q]), 0.5 * (count[:, 0] + count[:, 2 * q])])
    return _StarCTF(fn, torch.stack([ctf_h, ctf_v], dim=1), r_mean, pixels, sigma, i_w - i_b, rho_xy,
                    img=x[:, 0].detach().reshape(b, -1).float(),
                    mid=0.5 * (i_w + i_b), geometry=(h, w, float(centre[0]), float(centre[1]), float(radius), n_cycles,
                                                   float(margin), str(dev)), levels_given=levels is not None)


def siemens_star_mtf(
    images: torch.Tensor,
    frequencies: Union[Sequence[float], torch.Tensor] = NORMALIZED_FREQUENCIES,
    aperture: bool = True,
    **kwargs,
) -> SiemensStarResult:
    """H/V MTF of Siemens-star images (ISO 15775 method of Sec. 3.3.1.2): ``B×1×S×S`` → (B, 2F).

    Args:
        images: star images (see :func:`siemens_star_ctf` for the geometry keywords, passed via ``kwargs``).
        frequencies: F normalised frequencies in [0, 1].
        aperture: divide out the pixel aperture sinc(f) of an area-rendered chart (default True, for the
            charts of :mod:`~camhealth.estimators.charts`); True or False (a string raises a ``TypeError``).

    Returns:
        :class:`SiemensStarResult`; ``mtf`` in [0, 1] (clamped after the aperture correction), float32 (float64 for
        float64 input). An image is not assessable (``mtf`` NaN, ``reasons`` saying why) where the noise hides the
        stripes, or where it contradicts the star that ``n_cycles``, ``centre``, ``radius`` and ``levels`` describe: no
        ``n_cycles``-periodic component above the noise on :data:`MIN_RINGS` rings ("no star: …"), a sub-harmonic of it
        stronger ("n_cycles: …"), or a mean or contrast the levels cannot give ("levels: …"; module docstring,
        *Consistency*).
    """
    if not isinstance(aperture, (bool, np.bool_)):
        raise TypeError(f"aperture = {aperture!r:.40} must be True or False, got {type(aperture).__name__}")
    x = check_image(images, "images", channels=1, value_range=(0.0, 1.0))
    out_dtype = torch.float64 if x.dtype == torch.float64 else torch.float32
    fq = check_frequencies(frequencies, x.device)
    c = _star_ctf(x, **kwargs)
    fn, ctf_d = c.fn, c.ctf
    b = ctf_d.shape[0]
    noise_dn, used, ok, reasons = None, None, torch.ones(b, dtype=torch.bool, device=x.device), [""] * b
    if c.sigma is not None:
        ctf_d, used, ok, reasons = _noise_corrected(c)
        noise_dn = 255.0 * c.sigma
    # rings measured in both sectors of a direction (the others lie beyond the image): too few leave nothing to fit
    measured = torch.isfinite(c.ctf).sum(dim=-1)  # (B, 2)
    for i in (measured.amin(dim=-1) < MIN_RINGS).nonzero()[:, 0].tolist():
        ok[i] = False
        reasons[i] = (f"only {int(measured[i].amin())} rings (H {int(measured[i, 0])}, V {int(measured[i, 1])}) lie in "
                      f"the image in both sectors of their direction; at least {MIN_RINGS} are needed (check centre= "
                      f"and radius=)")
    for i, why in _star_consistency(c, ok).items():  # a star the levels, n_cycles or the image itself contradict
        ok[i] = False
        reasons[i] = why
    weight = fn.square()  # |df/dr| per 1-px ring ∝ f²: the sum approximates ∫ … df (Eq. 3.24)
    fit_ctf = torch.where(ok[:, None, None], ctf_d, torch.ones_like(ctf_d))  # (refused images: a placeholder fit)
    mu, s = gaussian_ctf_fit(fn, fit_ctf, weight)  # (B, 2)
    unfit = ok & ~(torch.isfinite(mu) & torch.isfinite(s)).all(dim=-1)  # no NaN is ever returned as assessable
    for i in unfit.nonzero()[:, 0].tolist():
        ok[i] = False
        reasons[i] = "the Gaussian fit of the CTF found no finite solution"

    def ctf_fn(f: torch.Tensor) -> torch.Tensor:  # f (F, K) → (B, 2, F, K)
        return torch.exp(-0.5 * ((f - mu[..., None, None]) / s[..., None, None]).square())

    _, bk = coltman_coefficients()
    mtf = mtf_from_ctf(ctf_fn, fq) / (math.pi / 4.0 * float(bk.sum()))  # a CTF ≡ 1 gives MTF ≡ 1
    if aperture:
        mtf = mtf / torch.sinc(0.5 * fq).abs()
    mtf = mtf.clamp(0.0, 1.0)  # the aperture correction of a CTF that already reads 1 would exceed 1
    mtf = torch.where(ok[:, None, None], mtf, torch.full_like(mtf, float("nan")))
    nan2 = torch.full_like(mu, float("nan"))
    mu, s = torch.where(ok[:, None], mu, nan2), torch.where(ok[:, None], s, nan2)
    return SiemensStarResult(
        mtf=mtf.reshape(b, -1).to(out_dtype), frequencies=fn.to(out_dtype), ctf_d=ctf_d.to(out_dtype),
        mu=mu.to(out_dtype), s=s.to(out_dtype), noise_dn=None if noise_dn is None else noise_dn.to(out_dtype),
        rings_used=used, assessable=ok, reasons=reasons,
    )


@functools.lru_cache(maxsize=1)
def _expected_max_table() -> tuple[torch.Tensor, torch.Tensor]:
    """(log n, E[max of n independent N(0, 1)]) on 400 log-spaced n in [1, 10^5] (numerical integration, float64)."""
    z = torch.linspace(-9.0, 9.0, 3601, dtype=torch.float64)
    cdf = 0.5 * (1.0 + torch.erf(z / math.sqrt(2.0)))
    pdf = torch.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)
    log_n = torch.linspace(0.0, math.log(1e5), 400, dtype=torch.float64)
    k = log_n.exp()[:, None]
    return log_n, torch.trapezoid(z * k * cdf.pow(k - 1.0) * pdf, z, dim=-1)


def _expected_max(n: torch.Tensor) -> torch.Tensor:
    """E[max of n independent N(0, 1) samples] (0 for n = 1, ≈ 1.54 for 10, ≈ 2.51 for 100), for real n ≥ 1: linear
    in log n between the nodes of :func:`_expected_max_table` (within 1e-3 of the integral)."""
    log_n, e = (t.to(n.device) for t in _expected_max_table())
    x = n.double().clamp(1.0, 1e5).log()
    step = float(log_n[1] - log_n[0])
    i = (x / step).floor().long().clamp(0, log_n.numel() - 2)
    t = (x - log_n[i]) / step
    return e[i] * (1.0 - t) + e[i + 1] * t


def _noise_corrected(c: "_StarCTF") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[str]]:
    """CTF_D with the noise's extremes taken out, and which images can be read (module docstring, *Noise*): returns
    (ctf (B, 2, R), rings above the noise (B, 2), assessable (B,), reasons)."""
    # independent pixels of a cell: n·(1 − ρ) with ρ the noise's lag-1 correlation along the cell (H sectors' cells run
    # along rows, V sectors' along columns): n for white noise, n/L for noise averaged along the cell over L px
    n = c.pixels[None] * (1.0 - c.rho)[:, :, None]  # (B, 2, R)
    n = n.clamp_min(1.0)
    scale = (c.sigma / c.contrast)[:, None, None]  # (B, 1, 1): σ in CTF units
    floor = 2.0 * _expected_max(n) * scale  # noise-only: the range of n samples, d_n = 2 E[max of n]
    excess = 2.0 * _expected_max(_EXCESS_SHARE * n) * scale  # resolved stripes: an extreme on each stripe's n/2 pixels
    keep = torch.isfinite(c.ctf) & (c.ctf > NOISE_KEEP * floor)
    # above the noise: the extremes' excess comes off; near it, signal and noise add in quadrature (a ring whose stripes
    # are gone reads its noise's range: 0 after the correction, kept in the fit — dropping it would leave the
    # surviving noisy rings at high frequency to pull the fit up)
    ctf = torch.where(keep, c.ctf - excess, torch.sqrt((c.ctf.square() - floor.square()).clamp_min(0.0)))
    used = keep.sum(dim=-1)  # (B, 2)
    ratio = (c.sigma / c.contrast)
    ok = (ratio <= MAX_NOISE_CONTRAST) & (used.amin(dim=-1) >= MIN_RINGS)
    reasons = []
    for i in range(ratio.numel()):
        if bool(ok[i]):
            reasons.append("")
        elif float(ratio[i]) > MAX_NOISE_CONTRAST:
            reasons.append(f"noisy: σ = {255.0 * float(c.sigma[i]):.1f} DN in the reference corners is "
                           f"{100.0 * float(ratio[i]):.0f} % of the chart's contrast ({255.0 * float(c.contrast[i]):.0f} DN); "
                           f"at most {100.0 * MAX_NOISE_CONTRAST:.0f} % can be read")
        else:
            reasons.append(f"noisy: only {int(used[i].amin())} rings (H {int(used[i, 0])}, V {int(used[i, 1])}) rise above "
                           f"{NOISE_KEEP:g}× the noise's own CTF; at least {MIN_RINGS} are needed")
    return ctf, used, ok, reasons


def _primes(n: int) -> list[int]:
    """The prime factors of n ≥ 1, ascending, each once."""
    out, p = [], 2
    while p * p <= n:
        if n % p == 0:
            out.append(p)
            while n % p == 0:
                n //= p
        p += 1
    return out + ([n] if n > 1 else [])


@dataclass(frozen=True)
class _RingDesign:
    """The least-squares design of every ring's angular harmonics (geometry only, shared by a batch).

    The R rings are packed two to a row, the i-th shortest with the i-th longest, so that the rows, padded to the
    longest, hold about as many slots as the rings have pixels (a 1-px ring at radius r has ≈ 2πr). The columns
    1, cos kφ, sin kφ of a slot are computed when they are used, :data:`_SLOTS` slots at a time — and kept, in float32
    (``basis32``, one tensor per chunk), where they hold at most :data:`_CACHED_BASIS` values: a star read one chart at a
    time (the monitor's case) otherwise spent most of its check computing them."""

    ks: tuple[int, ...]  # K harmonics: n_cycles, its J neighbours (_NEIGHBOURS), then n_cycles/p (p prime, ≥ 4)
    n_nbr: int  # J
    index: torch.Tensor  # (Q, L) flattened pixel index of each row's slots (padding: pixel 0)
    phi: torch.Tensor  # (Q, L) angle φ of each slot's pixel (float64)
    half: torch.Tensor  # (Q, L) 0: the row's first ring, 1: its second, -1: padding (int8)
    rows: torch.Tensor  # (2Q,) ring of each half row (R where a half row holds none)
    count: torch.Tensor  # (R,) pixels per ring, n (float64)
    testable: torch.Tensor  # (R,) bool: n ≥ 3C and the harmonics told apart (_MIN_EIGEN)
    inv3: torch.Tensor  # (R, 3, 3) (XᵀX)⁻¹ of the columns 1, cos Nφ, sin Nφ
    inv: torch.Tensor  # (R, C, C) (XᵀX)⁻¹ of all C = 1 + 2K columns
    wald_n: torch.Tensor  # (R, 2, 2) inverse of inv's block of cos Nφ, sin Nφ
    wald_nbr: torch.Tensor  # (R, 2J, 2J) inverse of inv's block of the neighbours' columns
    basis32: tuple[torch.Tensor, ...] | None = None  # basis(lo, hi, float32) of each chunk, or None (too large to keep)

    def basis(self, lo: int, hi: int, dtype: torch.dtype) -> torch.Tensor:
        """(hi − lo, L, 2C) columns 1, cos kφ…, sin kφ… of rows lo…hi − 1: those of the row's first ring, then those of
        its second (0 on the other ring's slots and on the padding)."""
        arg = self.phi[lo:hi, :, None] * torch.tensor(self.ks, dtype=torch.float64, device=self.phi.device)
        x = torch.cat([torch.ones_like(arg[..., :1]), torch.cos(arg), torch.sin(arg)], dim=-1).to(dtype)
        half = self.half[lo:hi, :, None]
        return torch.cat([x * (half == 0), x * (half == 1)], dim=-1)

    def chunks(self) -> list[tuple[int, int]]:
        """Row ranges of about :data:`_SLOTS` slots each."""
        n_rows, length = self.index.shape
        step = max(1, _SLOTS // max(length, 1))
        return [(lo, min(lo + step, n_rows)) for lo in range(0, n_rows, step)]


@functools.lru_cache(maxsize=4)
def _ring_design(h: int, w: int, cy: float, cx: float, radius: float, n_cycles: int, margin: float, dev: str) -> _RingDesign:
    """:class:`_RingDesign` of the 1-px rings :func:`siemens_star_ctf` measures (the same rings, r_lo ≤ r < r_hi)."""
    _, _, r, phi = _polar(h, w, (cy, cx), dev)
    r_lo, r_hi = n_cycles / math.pi, radius - margin
    use = (r >= r_lo) & (r < r_hi)
    n_rings = int(math.floor(r_hi - r_lo))
    pix = use.nonzero()[:, 0]
    ring = torch.floor(r[use] - r_lo).long().clamp(max=n_rings - 1)
    subs = [n_cycles // p for p in _primes(n_cycles) if n_cycles // p >= 4]
    nbrs = [n_cycles + j for j in _NEIGHBOURS if n_cycles + j >= 1 and n_cycles + j not in subs]
    ks = (n_cycles, *nbrs, *subs)
    n_col = 1 + 2 * len(ks)
    count = torch.bincount(ring, minlength=n_rings)
    # rows: the i-th shortest ring with the i-th longest (an odd ring out alone); half rows without a ring: index R
    by_len = torch.argsort(count, stable=True).tolist()
    n_rows = (n_rings + 1) // 2
    first = by_len[:n_rows]
    second = [by_len[n_rings - 1 - q] if n_rings - 1 - q >= n_rows else n_rings for q in range(n_rows)]
    rows = torch.tensor(first + second, dtype=torch.long, device=dev)  # (2Q,)
    row_of = torch.zeros(n_rings + 1, dtype=torch.long, device=dev)
    row_of[rows] = torch.arange(2 * n_rows, device=dev) % n_rows
    half_of = torch.zeros(n_rings + 1, dtype=torch.long, device=dev)
    half_of[rows] = torch.arange(2 * n_rows, device=dev) // n_rows
    count_ext = torch.cat([count, count.new_zeros(1)])
    offset = torch.where(half_of == 1, count_ext[rows[:n_rows]][row_of], torch.zeros_like(row_of))  # after the first ring
    length = max(int((count_ext[rows[:n_rows]] + count_ext[rows[n_rows:]]).max()) if n_rings else 0, 1)
    order = torch.argsort(ring, stable=True)
    start = torch.cumsum(count, 0) - count
    ro = ring[order]
    slot = row_of[ro] * length + offset[ro] + torch.arange(ring.numel(), device=dev) - start[ro]
    index = torch.zeros(n_rows * length, dtype=torch.long, device=dev)
    index[slot] = pix[order]
    slot_phi = torch.zeros(n_rows * length, dtype=torch.float64, device=dev)
    slot_phi[slot] = phi[pix[order]]
    half = torch.full((n_rows * length,), -1, dtype=torch.int8, device=dev)
    half[slot] = half_of[ro].to(torch.int8)
    d = _RingDesign(ks, len(nbrs), index.reshape(n_rows, length), slot_phi.reshape(n_rows, length),
                    half.reshape(n_rows, length), rows, count.double(), *([None] * 5))
    # XᵀX of every ring, from its half row
    gram = torch.zeros(n_rings + 1, n_col, n_col, dtype=torch.float64, device=dev)
    for lo, hi in d.chunks():
        x = d.basis(lo, hi, torch.float64)
        for k in (0, 1):
            xk = x[..., k * n_col:(k + 1) * n_col]
            gram[rows[k * n_rows + lo:k * n_rows + hi]] = xk.transpose(1, 2) @ xk
    gram = gram[:n_rings]
    count = count.double()
    least = torch.linalg.eigvalsh(gram / count.clamp_min(1.0)[:, None, None])[:, 0]
    testable = (count >= 3 * n_col) & (least >= _MIN_EIGEN)
    eye = torch.eye(n_col, dtype=torch.float64, device=dev)
    gram = torch.where(testable[:, None, None], gram, eye)  # (a ring that is not tested: a placeholder)
    inv = torch.linalg.inv(gram)
    n_k = len(ks)
    cols3, cols_n = [0, 1, 1 + n_k], [1, 1 + n_k]
    cols_nbr = [1 + i for i in range(1, 1 + len(nbrs))] + [1 + n_k + i for i in range(1, 1 + len(nbrs))]
    inv3 = torch.linalg.inv(gram[:, cols3][:, :, cols3])
    wald_n = torch.linalg.inv(inv[:, cols_n][:, :, cols_n])
    wald_nbr = torch.linalg.inv(inv[:, cols_nbr][:, :, cols_nbr])
    n_values = d.index.numel() * 2 * n_col
    basis32 = tuple(d.basis(lo, hi, torch.float32) for lo, hi in d.chunks()) if n_values <= _CACHED_BASIS else None
    return dataclasses.replace(d, testable=testable, inv3=inv3, inv=inv, wald_n=wald_n, wald_nbr=wald_nbr,
                               basis32=basis32)


def _ring_sums(img: torch.Tensor, level: torch.Tensor, d: _RingDesign) -> tuple[torch.Tensor, torch.Tensor]:
    """Xᵀy (B, R, C) and Σ y² (B, R), float64, of every ring of y = ``img`` − ``level``: images (B, H·W) float32 less a
    level (B,) near their mean [image units] (so that float32 sums keep the rings' variance: rounding stays ≪ the 8-bit
    quantisation floor, :data:`_QUANTISATION_VAR`)."""
    b, n_col = img.shape[0], 1 + 2 * len(d.ks)
    n_rings, n_rows = d.count.numel(), d.index.shape[0]
    xty = torch.zeros(b, 2 * n_rows, n_col, dtype=torch.float64, device=img.device)  # per half row
    y2 = torch.zeros(b, 2 * n_rows, dtype=torch.float64, device=img.device)
    level = level.to(img.dtype)[:, None, None]
    for i, (lo, hi) in enumerate(d.chunks()):
        g = img.index_select(1, d.index[lo:hi].reshape(-1)).reshape(b, hi - lo, -1)  # (B, q, L)
        g -= level
        kept = d.basis32 is not None and img.dtype == torch.float32
        x = d.basis32[i] if kept else d.basis(lo, hi, img.dtype)  # (q, L, 2C)
        s = torch.einsum("bql,qlk->bqk", g, x).double()  # (B, q, 2C)
        s2 = torch.einsum("bql,qlj->bqj", g * g, x[..., ::n_col]).double()  # the columns 1 of each half: (B, q, 2)
        for k in (0, 1):
            xty[:, k * n_rows + lo:k * n_rows + hi] = s[..., k * n_col:(k + 1) * n_col]
            y2[:, k * n_rows + lo:k * n_rows + hi] = s2[..., k]
    out_xty = torch.zeros(b, n_rings + 1, n_col, dtype=torch.float64, device=img.device)
    out_y2 = torch.zeros(b, n_rings + 1, dtype=torch.float64, device=img.device)
    out_xty[:, d.rows] = xty
    out_y2[:, d.rows] = y2
    return out_xty[:, :n_rings], out_y2[:, :n_rings]


def _star_consistency(c: "_StarCTF", ok: torch.Tensor) -> dict[int, str]:
    """Why each image of ``ok`` that the star's own statistics contradict is not assessable (module docstring,
    *Consistency*): {image index: reason}; images not in ``ok`` are not examined."""
    todo = ok.nonzero()[:, 0]
    if todo.numel() == 0 or c.geometry is None:
        return {}
    d = _ring_design(*c.geometry)
    n_cycles = c.geometry[5]
    mid, contrast = c.mid[todo], c.contrast[todo]
    xty, y2 = _ring_sums(c.img if todo.numel() == c.img.shape[0] else c.img[todo], mid, d)  # y − mid: (b, R, C), (b, R)
    n = d.count
    n_k = len(d.ks)
    ysum = xty[..., 0]
    # mean + fundamental (columns 1, cos Nφ, sin Nφ): F against the ring's residual, F(2, n − 3) for white noise
    b3 = xty[..., [0, 1, 1 + n_k]]
    beta3 = torch.einsum("rij,brj->bri", d.inv3, b3)
    fitted = (beta3 * b3).sum(-1)  # bᵀ(XᵀX)⁻¹b = Σ ŷ²
    dof = (n - 3.0).clamp_min(1.0)
    rss = (y2 - fitted).clamp_min(0.0)
    ess = (fitted - ysum.square() / n.clamp_min(1.0)).clamp_min(0.0)
    noise = (rss / dof).clamp_min(_QUANTISATION_VAR)  # σ² per pixel, at least the 8-bit quantisation's
    f_res = (ess / 2.0) / noise
    t_res = dof / 2.0 * (STAR_FALSE_ALARM ** (-2.0 / dof) - 1.0)
    # every harmonic jointly: the fundamental's Wald statistic against the neighbours', F(2, 2J)
    beta = torch.einsum("rij,brj->bri", d.inv, xty)
    b_n = beta[..., [1, 1 + n_k]]
    j_nbr = d.n_nbr
    b_nbr = beta[..., [1 + i for i in range(1, 1 + j_nbr)] + [1 + n_k + i for i in range(1, 1 + j_nbr)]]
    w_n = torch.einsum("bri,rij,brj->br", b_n, d.wald_n, b_n) / 2.0
    w_nbr = torch.einsum("bri,rij,brj->br", b_nbr, d.wald_nbr, b_nbr) / b_nbr.shape[-1]
    w_nbr = w_nbr.clamp_min(_QUANTISATION_VAR)
    f_nbr = w_n / w_nbr
    t_nbr = j_nbr * (STAR_FALSE_ALARM ** (-1.0 / j_nbr) - 1.0)
    shown = d.testable & (f_res > t_res) & (f_nbr > t_nbr)  # (b, R)
    power = beta[..., 1:1 + n_k].square() + beta[..., 1 + n_k:].square()  # (b, R, K) squared amplitudes
    tested = int(d.testable.sum())
    # the levels, on the rings where the star shows: its mean, and its largest amplitude less 3 standard errors
    w = shown.double()
    shift = (ysum * w).sum(-1) / (n * w).sum(-1).clamp_min(1.0)  # the star's mean less the mid level
    mean, offset = mid + shift, shift.abs() / contrast
    amp = beta3[..., 1:].square().sum(-1).sqrt()
    se = torch.sqrt(noise * 0.5 * (d.inv3[:, 1, 1] + d.inv3[:, 2, 2]))  # (b, R) standard error of each coefficient
    reach = torch.where(shown, (amp - 3.0 * se) / (2.0 / math.pi * contrast[:, None]), torch.zeros_like(amp)).amax(-1)
    source = "levels given" if c.levels_given else "levels read in the reference corners"
    out = {}
    for j, i in enumerate(todo.tolist()):  # j: row of the examined images, i: image of the batch
        n_shown = int(shown[j].sum())
        rings = shown[j] if n_shown >= MIN_RINGS else d.testable  # where the star shows (else: every ring tested)
        sums = power[j][rings].sum(0)  # (K,) the harmonics' power summed over those rings
        ratio, m_sub = max([(float(sums[q] / sums[0]), d.ks[q]) for q in range(1 + j_nbr, n_k)], default=(0.0, 0))
        if n_shown < MIN_RINGS:
            hint = (f"; their {m_sub}-periodic component carries {ratio:.3g}× the power of the {n_cycles}-periodic one"
                    if ratio > 2.0 else "")
            out[i] = (f"no star: {n_shown} of {tested} rings show a component repeating n_cycles = {n_cycles} times per "
                      f"turn above their noise (false-alarm rate {STAR_FALSE_ALARM:g} per ring, against the ring's "
                      f"residual and against its harmonics {', '.join(str(k) for k in d.ks[1:1 + j_nbr])}){hint}; "
                      f"at least {MIN_RINGS} are needed: is this a Siemens star of {n_cycles} cycles at centre = "
                      f"({c.geometry[2]:g}, {c.geometry[3]:g}), radius = {c.geometry[4]:g} px?")
        elif ratio > 1.0:
            out[i] = (f"n_cycles: the star repeats {m_sub} times per turn, not n_cycles = {n_cycles}: on the {n_shown} "
                      f"rings where its {n_cycles}-periodic component shows, the {m_sub}-periodic one carries "
                      f"{ratio:.3g}× its power (a star of n_cycles has none at n_cycles/{n_cycles // m_sub})")
        elif float(offset[j]) > MAX_MID_OFFSET:
            out[i] = (f"levels: the star's mean, {255.0 * float(mean[j]):.1f} DN, lies {float(offset[j]):.3g}× the "
                      f"contrast I_w − I_b = {255.0 * float(contrast[j]):.1f} DN from the mid level (I_b + I_w)/2 = "
                      f"{255.0 * float(mid[j]):.1f} DN of the {source}; at most {MAX_MID_OFFSET:g} (a blur keeps the "
                      f"star's mean: the levels must be the chart's dark and bright level in image units, DN/255)")
        elif float(reach[j]) > MAX_FUNDAMENTAL:
            out[i] = (f"levels: the star's {n_cycles}-periodic component reaches {float(reach[j]):.3g}× that of an "
                      f"unblurred chart of contrast I_w − I_b = {255.0 * float(contrast[j]):.1f} DN (the {source}); at "
                      f"most {MAX_FUNDAMENTAL:g}: the star's contrast is larger than the levels say")
    return out
