"""Procedural dead-leaves images: the scale-invariant occlusion texture of camera test charts.

The dead-leaves (or "spilled coins") model is the texture of the ISO 19567-2 texture-loss chart and of
the Cao–Guichard–Hornung texture-acutance method: opaque disks ("leaves") of random size, position and
gray level fall on the image plane one after another and hide what lies below. With radii drawn from
the power law ``p(r) ∝ r⁻³`` on ``[r_min, r_max]`` the texture is statistically scale invariant between
the two radii (its power spectrum falls roughly as ``1/f²``, like natural images), and it has sharp
edges in every direction and at every scale: the right clean input for training blur (MTF) and noise
estimators.

Simulation (exact, not an approximation of the stationary model):

* Leaves are generated **front to back** — the first leaf generated lies on top — and a pixel takes the
  gray level of the first leaf that covers its centre. Generation stops as soon as every pixel is
  covered, so the image is fully covered and equals, in distribution, the stationary dead-leaves model
  (painting back to front "until the frame is covered" would instead leave the last, topmost layer
  biased).
* Only leaves that can touch the frame are drawn: the centre of a leaf of radius ``r`` is uniform over the
  frame dilated by ``r`` on every side (so disks centred outside the frame still occlude its borders),
  and ``r`` is drawn from the power law re-weighted by the area of that dilated frame,
  ``q(r) ∝ r⁻³ (H' + 2r)(W' + 2r)``. This is exactly the Poisson process of leaves in the whole plane,
  thinned to the ones meeting the frame; it is sampled as a mixture of three power laws (``r⁻³``, ``r⁻²``,
  ``r⁻¹``) with closed-form inverse CDFs.
* Gray levels are uniform on ``[0.5 − contrast/2, 0.5 + contrast/2]``.
* ``shading`` > 0 (at most 1): each leaf's gray level is a linear ramp ``val + g·(p − c)`` (``c`` the centre) with
  ``g`` of uniform random direction and ``|g| = shading · contrast · U(0, 1) / r`` [gray level / px, with ``r`` and
  ``p`` in the rendering grid, so the slope per output pixel does not depend on ``supersample``]: across one
  radius the level changes by at most ``shading × contrast`` (along a thin leaf, up to ``THIN_LENGTH`` times
  that). The rendered levels are clipped to [0, 1] before the supersampling average (and
  after it, as always).
* ``thin`` > 0 (at most 1): that share of the leaves are thin ellipses — wires, poles, lane markings, twigs —
  of width ``2b`` log-uniform on [:data:`THIN_WIDTH_PX`] output px, length ``2a = 2·THIN_LENGTH·r`` (``a ≥ b``) and
  uniform orientation. Their largest extent is ``THIN_LENGTH·r``, so the centres of all leaves are drawn over the
  frame dilated by ``THIN_LENGTH·r`` and ``r`` from the power law re-weighted by that area,
  ``q(r) ∝ r⁻³ (H' + 2mr)(W' + 2mr)`` with ``m = THIN_LENGTH``: the same exact thinned Poisson process (being thin,
  the width and the orientation are independent of ``r`` and the centre); leaves that then miss the frame cover no
  pixel and are culled. Bounding boxes are the exact axis-aligned boxes of the rotated ellipses (half-widths
  ``√(a²cos²θ + b²sin²θ)`` and ``√(a²sin²θ + b²cos²θ)``, at most ``a``); the hit test is the rotated ellipse
  equation (a disk is the ellipse ``a = b = r``). Natural scenes hold structures narrower than their edges are
  far apart; disks alone have none, and a patch of thin lines has more fine content than a patch of edges at the
  same blur.
* ``coverage`` < 1 (the default 1 is the model above): the leaves stop once they cover at least that share of the
  pixels (the topmost leaves of the same process) — checked after each batch of leaves (at least 16 leaves, about an
  eighth of the leaf area the share takes), so the realised share is at least the requested one and overshoots it:
  on the MTF configs' scenes (``configs/mtf_full.yaml``, 200 images) a requested 10–100 % gave 13–100 %, on average
  1–4 points more per tenth of the range on the rendering grid (up to 29 points for one image; 2–10 points more
  counted as output pixels that a leaf touches), and with large leaves on a small frame the first 16 leaves alone
  cover a quarter or more, so a share below about 0.25 is not reached there (smaller requests give the same image).
  The rest shows a background, a linear ramp between two gray levels of the leaves' range along a random direction,
  from the stream ``(seed, 3)``, rendered on the same fine grid. Natural scenes have large smooth areas (sky, road,
  walls) between their objects; a fully covered frame has none, and a network trained only on it reads a sparse
  patch's missing fine content as blur.
* Painting is vectorised: a batch of leaves is rasterised by their bounding boxes at once (leaves whose
  box holds no uncovered pixel are culled with a summed-area table first) and each pixel takes the first
  leaf of the batch that covers it; when only a few pixels remain uncovered they are tested against the
  leaves directly.
* ``supersample = s > 1`` renders at ``s×`` resolution and averages ``s×s`` blocks: anti-aliased edges
  (a plain render has staircase edges and energy above Nyquist).

Edge density (the knob): the expected edge length per pixel is ``2 E[r] / E[r²]``
≈ ``2 / (r_min · ln(r_max / r_min))`` — a smaller ``r_min`` gives a busier texture with more fine
detail; ``r_max`` sets the size of the largest flat regions.

Reproducibility: the same ``seed`` (and parameters) gives a bit-identical image with the same numpy
version (numpy's ``PCG64`` generator; no threads, no float reductions whose order could vary). The per-leaf
draws of the shading and the thin leaves (four uniforms per leaf — one unused, orientation, gradient direction and
magnitude — and with ``thin`` > 0 two more: thin or not, width) come from a second stream, seeded ``(seed, 2)``
(``DeadLeavesSource``: ``(seed, i, 2)``), used only when ``shading`` > 0 or ``thin`` > 0: the disk draws are
untouched, so with ``shading = 0`` and ``thin = 0`` the images are bit-identical to the disk-only renderer, and the
shaded leaves have the same geometry as the flat ones.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

from camhealth.data._common import check_index, check_int

__all__ = ["dead_leaves", "dead_leaves_radius_pdf", "DeadLeavesSource", "THIN_WIDTH_PX", "THIN_LENGTH"]

#: Range of the thin leaves' full width ``2b`` [output px], log-uniform: from half a pixel (a wire) to 4 px.
THIN_WIDTH_PX: tuple[float, float] = (0.5, 4.0)
#: A thin leaf of radius ``r`` is ``2·THIN_LENGTH·r`` long (its semi-major axis ``THIN_LENGTH·r``).
THIN_LENGTH = 4.0

_DIRECT_TEST_MAX = 4_000_000  # pixel×leaf tests per block in the "few pixels left" path

#: Most pixels of the rendering grid, ``H·supersample × W·supersample`` (2^28: 16384² at supersample 1, 2048² at 8;
#: the image, its coverage mask and the rasterised boxes take several bytes per pixel).
MAX_RENDER_PIXELS = 2**28


def _check_size(size: int | Sequence[int]) -> tuple[int, int]:
    given = size
    if isinstance(size, (int, np.integer)) and not isinstance(size, bool):
        size = (int(size), int(size))
    try:
        values = tuple(size)  # type: ignore[arg-type]
        h, w = (int(v) for v in values)
    except (TypeError, ValueError):
        raise ValueError(f"size must be an int or a pair (H, W) of ints, got {given!r}") from None
    if any(isinstance(v, (float, np.floating)) and float(v) != int(v) for v in values):  # (10.7 is not 10)
        raise ValueError(f"size = {given!r} must hold whole numbers of pixels (H, W), each in [1, 16384]")
    if h < 1 or w < 1 or h > 16384 or w > 16384:
        raise ValueError(f"size = {(h, w)} must have H and W in [1, 16384]")
    return h, w


def _resolve_params(
    size: int | Sequence[int], r_min: float, r_max: float | None, contrast: float, supersample: int
) -> tuple[int, int, float, float, float, int]:
    h, w = _check_size(size)
    default_r_max = r_max is None
    if r_max is None:
        r_max = 0.5 * max(h, w)
    r_min, r_max, contrast = float(r_min), float(r_max), float(contrast)
    if not math.isfinite(r_min) or r_min < 0.5:
        raise ValueError(f"r_min = {r_min:g} px must be >= 0.5 (smaller leaves cover no pixel centre)")
    if not math.isfinite(r_max) or r_max <= r_min:
        if default_r_max:
            raise ValueError(f"r_max = {r_max:g} px (default: half the larger side of the {h}×{w} px image) must be > "
                             f"r_min = {r_min:g} px: pass a smaller r_min (>= 0.5), an r_max, or a larger size")
        raise ValueError(f"r_max = {r_max:g} px must be finite and > r_min = {r_min:g} px")
    if not math.isfinite(contrast) or not 0.0 <= contrast <= 1.0:
        raise ValueError(f"contrast = {contrast:g} must be in [0, 1] (range of gray levels around 0.5)")
    s = check_int(supersample, "supersample", 1)
    if s > 8:
        raise ValueError(f"supersample = {s} must be in [1, 8]")
    if h * s * w * s > MAX_RENDER_PIXELS:
        raise ValueError(
            f"size = {(h, w)} with supersample = {s} renders {h * s}×{w * s} = {h * s * w * s} px, more than the limit "
            f"of {MAX_RENDER_PIXELS} (2^28) px: H·supersample × W·supersample must be at most that (a smaller size or "
            "supersample)"
        )
    return h, w, r_min, r_max, contrast, s  # type: ignore[return-value]


def _check_coverage(coverage: float) -> float:
    """``coverage`` as a float in (0, 1]; ``ValueError`` naming the value otherwise."""
    try:
        c = float(coverage)
    except (TypeError, ValueError):
        raise ValueError(f"coverage must be a number in (0, 1], got {coverage!r}") from None
    if not math.isfinite(c) or not 0.0 < c <= 1.0:
        raise ValueError(f"coverage = {c:g} must be in (0, 1] (share of the frame the leaves cover)")
    return c


def _gradient_background(rng3: np.random.Generator, h: int, w: int, lo: float, hi: float) -> np.ndarray:
    """``h×w`` linear ramp between two gray levels uniform on [lo, hi] along a uniformly random direction across the
    frame (the sky, a road, a wall behind the leaves)."""
    a, b, u = rng3.random(3)
    a, b, phi = lo + (hi - lo) * a, lo + (hi - lo) * b, 2.0 * math.pi * u
    c, sn = math.cos(phi), math.sin(phi)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    t = c * x + sn * y
    t = (t - t.min()) / max(float(t.max() - t.min()), 1e-12)
    return (a + (b - a) * t).astype(np.float32)


def _check_shape(shading: float, thin: float) -> tuple[float, float]:
    """``(shading, thin)`` as floats; ``ValueError`` naming the value and its allowed range otherwise."""
    try:
        shading, thin = float(shading), float(thin)
    except (TypeError, ValueError):
        raise ValueError(f"shading and thin must be numbers, got shading = {shading!r}, thin = {thin!r}") from None
    if not math.isfinite(thin) or not 0.0 <= thin <= 1.0:
        raise ValueError(f"thin = {thin:g} must be in [0, 1] (share of the leaves that are thin ellipses)")
    if not math.isfinite(shading) or not 0.0 <= shading <= 1.0:
        raise ValueError(
            f"shading = {shading:g} must be in [0, 1] (largest change of gray level across a leaf radius, × contrast)"
        )
    return shading, thin


def dead_leaves_radius_pdf(r: np.ndarray, r_min: float, r_max: float) -> np.ndarray:
    """The radius density ``p(r) = c · r⁻³`` on ``[r_min, r_max]`` (0 outside), normalised to integrate to 1."""
    r = np.asarray(r, dtype=np.float64)
    c = 2.0 / (r_min**-2 - r_max**-2)
    return np.where((r >= r_min) & (r <= r_max), c * r**-3.0, 0.0)


def _sample_leaves(
    rng: np.random.Generator,
    n: int,
    h: int,
    w: int,
    r_min: float,
    r_max: float,
    lo: float,
    hi: float,
    dilate: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``n`` leaves that may meet the frame (pixel centres 0..w-1 × 0..h-1), in front-to-back order.

    A leaf of radius ``r`` has its centre uniform over the frame dilated by ``m·r`` (``m = dilate`` >= 1: the
    largest extent of a leaf of radius ``r`` in units of ``r``; 1 for disks, ``THIN_LENGTH`` with thin leaves), and ``r``
    follows ``p(r) ∝ r⁻³`` re-weighted by that dilated area. Leaves that then miss the frame are harmless.
    """
    hp, wp = float(h - 1), float(w - 1)
    m = float(dilate)
    # q(r) ∝ r^-3 (hp + 2mr)(wp + 2mr) = hp·wp r^-3 + 2m(hp + wp) r^-2 + 4m² r^-1 on [r_min, r_max]
    w3 = hp * wp * 0.5 * (r_min**-2 - r_max**-2)
    w2 = 2.0 * (hp + wp) * (1.0 / r_min - 1.0 / r_max)
    w1 = 4.0 * math.log(r_max / r_min)
    if m != 1.0:
        w2, w1 = w2 * m, w1 * m * m
    total = w3 + w2 + w1
    u = rng.random((5, n))
    comp_u = u[0] * total
    v = u[1]
    r_pow3 = (r_min**-2 - v * (r_min**-2 - r_max**-2)) ** -0.5
    r_pow2 = 1.0 / (1.0 / r_min - v * (1.0 / r_min - 1.0 / r_max))
    r_pow1 = r_min * (r_max / r_min) ** v
    r = np.where(comp_u < w3, r_pow3, np.where(comp_u < w3 + w2, r_pow2, r_pow1))
    np.clip(r, r_min, r_max, out=r)
    d = r if m == 1.0 else m * r  # dilation of the frame for each leaf
    cx = -d + u[2] * (wp + 2.0 * d)
    cy = -d + u[3] * (hp + 2.0 * d)
    val = (lo + (hi - lo) * u[4]).astype(np.float32)
    return r, cx, cy, val


def _paint_by_boxes(
    lin_img: np.ndarray,
    uncovered: np.ndarray,
    w: int,
    r: np.ndarray,
    cx: np.ndarray,
    cy: np.ndarray,
    val: np.ndarray,
    x0: np.ndarray,
    y0: np.ndarray,
    bw: np.ndarray,
    bh: np.ndarray,
    ell: tuple[np.ndarray, ...] | None = None,
    grad: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """Rasterise the leaves' bounding boxes; each uncovered pixel takes the first leaf covering it.

    ``ell = (cos θ, sin θ, a², b²)`` per leaf makes the leaves ellipses (semi-axes ``a`` along ``θ``, ``b``
    across; ``None``: disks of radius ``r``); ``grad = (g_x, g_y)`` per leaf [gray level / px] shades them:
    a pixel ``p`` takes ``val + g·(p − c)``.
    """
    counts = bw * bh
    total = int(counts.sum())
    if total == 0:
        return
    leaf = np.repeat(np.arange(len(r), dtype=np.int64), counts)
    starts = np.cumsum(counts) - counts
    j = np.arange(total, dtype=np.int64) - starts[leaf]
    bwl = bw[leaf]
    px = x0[leaf] + j % bwl
    py = y0[leaf] + j // bwl
    dx = px - cx[leaf]
    dy = py - cy[leaf]
    lin = py * w + px
    hit = _inside(dx, dy, r, ell, leaf) & uncovered[lin]
    lin = lin[hit]
    leaf = leaf[hit]
    if lin.size == 0:
        return
    # entries are in leaf order, so the first occurrence of a pixel is its front-most leaf
    pix, first = np.unique(lin, return_index=True)
    front = leaf[first]
    if grad is None:
        lin_img[pix] = val[front]
    else:
        lin_img[pix] = val[front] + grad[0][front] * dx[hit][first] + grad[1][front] * dy[hit][first]
    uncovered[pix] = False


def _inside(
    dx: np.ndarray, dy: np.ndarray, r: np.ndarray, ell: tuple[np.ndarray, ...] | None, idx: np.ndarray | slice
) -> np.ndarray:
    """Whether the offsets ``(dx, dy)`` [px] from the centres of leaves ``idx`` lie in those leaves (edge included)."""
    if ell is None:
        return dx * dx + dy * dy <= r[idx] ** 2
    c, s, a2, b2 = (e[idx] for e in ell)
    u = dx * c + dy * s  # along the major axis
    v = dy * c - dx * s  # along the minor axis
    return u * u * b2 + v * v * a2 <= a2 * b2


def _paint_direct(
    lin_img: np.ndarray,
    uncovered: np.ndarray,
    w: int,
    r: np.ndarray,
    cx: np.ndarray,
    cy: np.ndarray,
    val: np.ndarray,
    ell: tuple[np.ndarray, ...] | None = None,
    grad: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """Few pixels left: test every uncovered pixel against every leaf (in blocks), keep the first hit.

    ``ell`` and ``grad`` as in :func:`_paint_by_boxes`."""
    pix = np.flatnonzero(uncovered)
    py = (pix // w).astype(np.float64)
    px = (pix % w).astype(np.float64)
    r2 = r * r
    block = max(1, _DIRECT_TEST_MAX // max(1, pix.size))
    for s in range(0, len(r), block):
        if pix.size == 0:
            break
        sl = slice(s, s + block)
        if ell is None:
            inside = (px[:, None] - cx[None, sl]) ** 2 + (py[:, None] - cy[None, sl]) ** 2 <= r2[None, sl]
        else:
            sub = tuple(e[None, sl] for e in ell)
            inside = _inside(px[:, None] - cx[None, sl], py[:, None] - cy[None, sl], r, sub, slice(None))
        any_hit = inside.any(axis=1)
        if not any_hit.any():
            continue
        first = inside[any_hit].argmax(axis=1) + s
        done = pix[any_hit]
        if grad is None:
            lin_img[done] = val[first]
        else:
            dx, dy = px[any_hit] - cx[first], py[any_hit] - cy[first]
            lin_img[done] = val[first] + grad[0][first] * dx + grad[1][first] * dy
        uncovered[done] = False
        keep = ~any_hit
        pix, px, py = pix[keep], px[keep], py[keep]


def _render(
    rng: np.random.Generator,
    h: int,
    w: int,
    r_min: float,
    r_max: float,
    lo: float,
    hi: float,
    slope: float = 0.0,
    rng2: np.random.Generator | None = None,
    thin: float = 0.0,
    thin_width: tuple[float, float] = (1.0, 1.0),
    coverage: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Render ``h×w`` px (radii in px of this grid) → (image, uncovered pixels) as ``h×w`` arrays. ``slope`` > 0:
    shaded leaves, the gray level changing by ``slope · U(0, 1)`` per radius ``r`` along a random direction. Their
    per-leaf draws come from ``rng2``. ``thin`` > 0: that share of the leaves are thin ellipses, semi-minor axis
    ``b`` log-uniform on ``thin_width`` [px of this grid], semi-major ``a = max(THIN_LENGTH·r, b)``. ``coverage``
    < 1: stop after the first batch of leaves that covers at least that share of the pixels; the rest stays
    uncovered. A batch holds ``max(16, N/8)`` leaves, ``N`` the number of leaves of mean area that cover the share
    (−ln(1 − coverage) frames' worth of leaf area), and the whole batch is painted before the share is checked: the
    realised share is at least ``coverage`` and overshoots it, by up to a batch's worth of leaves — at least 16, which
    with large leaves on a small frame can cover a quarter of it or more, so a small share is not reached (requests
    below it give the same image). On the MTF configs' scenes (``configs/mtf_full.yaml``, 200 images) a requested
    10–100 % gave 13–100 % of this grid's pixels (on average 1–4 points more per tenth of the range, up to 29 for one
    image)."""
    shaped = slope > 0.0 or thin > 0.0
    if shaped and rng2 is None:
        raise ValueError("shaded or thin leaves need their own random stream rng2")
    m = THIN_LENGTH if thin > 0.0 else 1.0  # largest extent of a leaf of radius r, in units of r
    n_pix = h * w
    img = np.zeros(n_pix, dtype=np.float32)
    uncovered = np.ones(n_pix, dtype=bool)
    # mean area of a leaf under p(r): π E[r²] = π c ln(r_max / r_min), c = 2 / (r_min⁻² − r_max⁻²)
    mean_area = math.pi * 2.0 / (r_min**-2 - r_max**-2) * math.log(r_max / r_min)
    frame_area = (h - 1 + 2 * m * r_min) * (w - 1 + 2 * m * r_min)
    batch = int(min(max(64, frame_area / mean_area), 1_000_000))
    if coverage < 1.0:  # a Poisson process of leaves covers 1 − exp(−N·area/frame): N for the share, in 8 steps
        batch = int(min(max(16, -math.log1p(-coverage) * frame_area / mean_area / 8.0), 1_000_000))
    n_left = n_pix
    for _ in range(10_000):
        r, cx, cy, val = _sample_leaves(rng, batch, h, w, r_min, r_max, lo, hi, m)
        ex = ey = r  # half-widths of the leaves' axis-aligned bounding boxes [px]
        ell = grad = None
        if shaped:  # the same four draws per leaf whichever option is on (v[0] is unused), two more for thin leaves
            v = rng2.random((6 if thin > 0.0 else 4, batch))  # type: ignore[union-attr]
            if thin > 0.0:
                theta = math.pi * v[1]  # orientation of the major axis
                c, sn = np.cos(theta), np.sin(theta)
                lo_w, hi_w = thin_width
                b_thin = lo_w * (hi_w / lo_w) ** v[5]
                a_thin = np.maximum(THIN_LENGTH * r, b_thin)
                is_thin = v[4] < thin
                a2 = np.where(is_thin, a_thin * a_thin, r * r)  # the others are disks: a = b = r
                b2 = np.where(is_thin, b_thin * b_thin, r * r)
                # exact half-widths of the rotated ellipse's box (<= a), padded against rounding
                ex = np.sqrt(a2 * c * c + b2 * sn * sn) + 1e-9
                ey = np.sqrt(a2 * sn * sn + b2 * c * c) + 1e-9
                ell = (c, sn, a2, b2)
            if slope > 0.0:
                g = slope * v[3] / r  # |g| [gray level / px of this grid]
                phi = 2.0 * math.pi * v[2]
                grad = (g * np.cos(phi), g * np.sin(phi))
        x0 = np.maximum(np.ceil(cx - ex), 0).astype(np.int64)
        x1 = np.minimum(np.floor(cx + ex), w - 1).astype(np.int64)
        y0 = np.maximum(np.ceil(cy - ey), 0).astype(np.int64)
        y1 = np.minimum(np.floor(cy + ey), h - 1).astype(np.int64)
        bw = np.maximum(x1 - x0 + 1, 0)
        bh = np.maximum(y1 - y0 + 1, 0)
        keep = (bw > 0) & (bh > 0)
        if n_left < n_pix:  # cull leaves whose box holds no uncovered pixel (summed-area table)
            sat = np.zeros((h + 1, w + 1), dtype=np.int64)
            np.cumsum(np.cumsum(uncovered.reshape(h, w), axis=0), axis=1, out=sat[1:, 1:])
            k = np.flatnonzero(keep)
            a, b, c, d = y0[k], y1[k] + 1, x0[k], x1[k] + 1
            holes = sat[b, d] - sat[a, d] - sat[b, c] + sat[a, c]
            keep[k[holes == 0]] = False
        k = np.flatnonzero(keep)
        r, cx, cy, val = r[k], cx[k], cy[k], val[k]
        x0, y0, bw, bh = x0[k], y0[k], bw[k], bh[k]
        if ell is not None:
            ell = tuple(e[k] for e in ell)
        if grad is not None:
            grad = (grad[0][k], grad[1][k])
        box_cost = int((bw * bh).sum())
        if n_left * len(k) <= box_cost:
            _paint_direct(img, uncovered, w, r, cx, cy, val, ell, grad)
        else:
            # bound memory: rasterise in chunks of leaves (order preserved, coverage updated in between)
            ends = np.cumsum(bw * bh)
            start = 0
            while start < len(k):
                limit = (ends[start - 1] if start else 0) + 4_000_000
                stop = max(start + 1, int(np.searchsorted(ends, limit, side="right")))
                sl = slice(start, stop)
                _paint_by_boxes(
                    img, uncovered, w, r[sl], cx[sl], cy[sl], val[sl], x0[sl], y0[sl], bw[sl], bh[sl],
                    None if ell is None else tuple(e[sl] for e in ell),
                    None if grad is None else (grad[0][sl], grad[1][sl]),
                )
                start = stop
        n_left = int(np.count_nonzero(uncovered))
        if n_left == 0 or n_left <= (1.0 - coverage) * n_pix:
            return img.reshape(h, w), uncovered.reshape(h, w)
        if coverage >= 1.0:
            batch = min(batch * 2, 1_000_000)
    raise RuntimeError("dead_leaves did not cover the frame; r_min may be too small for the image size")


def dead_leaves(
    size: int | Sequence[int] = (256, 256),
    r_min: float = 2.0,
    r_max: float | None = None,
    contrast: float = 1.0,
    seed: int = 0,
    supersample: int = 1,
    shading: float = 0.0,
    thin: float = 0.0,
    coverage: float = 1.0,
) -> torch.Tensor:
    """Render one dead-leaves image.

    Args:
        size: ``(H, W)`` in px (or one int for a square).
        r_min: smallest leaf radius in px (>= 0.5); the edge-density knob — smaller is busier.
        r_max: largest leaf radius in px (> r_min); default half the larger image side.
        contrast: width of the uniform gray-level range centred on 0.5, in [0, 1]
            (1 → levels in [0, 1]; 0.5 → [0.25, 0.75]).
        seed: integer seed; the same seed and parameters give a bit-identical image.
        supersample: render at this factor and box-average (anti-aliased edges); 1 = hard edges.
        shading: in [0, 1]; 0 = flat leaves. Otherwise each leaf's gray level is a linear ramp
            ``val + g·(p − c)`` with a random direction and ``|g| = shading · contrast · U(0, 1) / r``
            [gray level / px]: across one radius the level changes by at most ``shading · contrast``.
        thin: in [0, 1]; the share of the leaves that are thin ellipses (width log-uniform on
            :data:`THIN_WIDTH_PX` px, length ``2·THIN_LENGTH·r``, uniform orientation); 0 = none.
        coverage: in (0, 1]; 1 = the frame fully covered (the dead-leaves model). Below 1 the leaves stop after the
            first batch of leaves (at least 16 leaves a batch) that covers at least that share of the frame, so the
            realised share is at least ``coverage`` and overshoots it: on the MTF configs' scenes
            (``configs/mtf_full.yaml``, 200 images) a requested 10–100 % gave 13–100 % (on average 1–4 points more per
            tenth of the range, up to 29 for one image; 2–10 points more counted as output pixels a leaf touches),
            and a share below about 0.25 is not reached with large leaves on a small frame (the first 16 leaves cover
            more; smaller requests give the same image). The rest shows a background: a linear ramp between two gray
            levels of the leaves' range along a random direction (drawn from the seed sequence ``(seed, 3)``),
            rendered on the same fine grid, so the pixel aperture stays exact. Scenes with large smooth areas.

    Returns:
        float32 tensor ``1×H×W`` with values in ``[0.5 − contrast/2, 0.5 + contrast/2]`` ⊂ [0, 1] (with
        ``shading`` > 0: the ramps may leave that range; values are clipped to [0, 1]).
    """
    h, w, r_min, r_max, contrast, s = _resolve_params(size, r_min, r_max, contrast, supersample)
    shading, thin = _check_shape(shading, thin)
    coverage = _check_coverage(coverage)
    seed = check_int(seed, "seed", 0)
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed)))
    rng2 = np.random.Generator(np.random.PCG64(np.random.SeedSequence([seed, 2])))
    rng3 = np.random.Generator(np.random.PCG64(np.random.SeedSequence([seed, 3])))
    return _dead_leaves(rng, h, w, r_min, r_max, contrast, s, shading, rng2, thin, coverage, rng3)


def _dead_leaves(
    rng: np.random.Generator,
    h: int,
    w: int,
    r_min: float,
    r_max: float,
    contrast: float,
    s: int,
    shading: float = 0.0,
    rng2: np.random.Generator | None = None,
    thin: float = 0.0,
    coverage: float = 1.0,
    rng3: np.random.Generator | None = None,
) -> torch.Tensor:
    lo, hi = 0.5 - 0.5 * contrast, 0.5 + 0.5 * contrast
    slope = shading * contrast  # largest change of gray level across one radius
    width = (0.5 * THIN_WIDTH_PX[0] * s, 0.5 * THIN_WIDTH_PX[1] * s)  # semi-minor axis in px of the render grid
    img, uncovered = _render(rng, h * s, w * s, r_min * s, r_max * s, lo, hi, slope, rng2, thin, width, coverage)
    if uncovered.any():  # coverage < 1: the background behind the leaves, on the fine grid
        if rng3 is None:
            raise ValueError("a background (coverage < 1) needs its own random stream rng3")
        img[uncovered] = _gradient_background(rng3, h * s, w * s, lo, hi)[uncovered]
    if slope > 0.0:
        np.clip(img, 0.0, 1.0, out=img)  # a reflectance stays in [0, 1] before the pixel averages it
    if s > 1:
        img = img.reshape(h, s, w, s).astype(np.float64).mean(axis=(1, 3)).astype(np.float32)
    np.clip(img, 0.0, 1.0, out=img)
    return torch.from_numpy(np.ascontiguousarray(img)).unsqueeze(0)


class DeadLeavesSource(torch.utils.data.Dataset):
    """``n_images`` procedural dead-leaves images, rendered on demand (nothing is stored).

    Image ``i`` uses the seed sequence ``(seed, i)``: it is the same whatever ``n_images`` is and however
    the source is indexed (in any order, in any DataLoader worker). Ids are ``"deadleaves-000042"``; each
    image is its own group for :func:`camhealth.data.split_ids`.

    Args:
        n_images: number of images (>= 1).
        size: ``(H, W)`` in px, or one int.
        seed: base seed (>= 0).
        r_min, r_max, contrast, supersample, shading, thin, coverage: as in :func:`dead_leaves` (``coverage``: the
            share the leaves cover at least; the realised share overshoots it, see there).
            ``r_min`` [px], ``contrast``, ``shading``, ``thin`` and ``coverage`` may also be a ``[low, high]`` range:
            each image then draws its own value (``r_min`` log-uniform, the others uniform) from the seed sequence
            ``(seed, i, 1)``, so scenes vary in edge density, edge contrast, shading, thin structures and how much of
            the frame the leaves cover, while fixed values leave every image bit-identical to before. The per-leaf
            draws of the shading and the thin leaves come from the seed sequence ``(seed, i, 2)``, the background
            of a partly covered image from ``(seed, i, 3)``.
    """

    def __init__(
        self,
        n_images: int,
        size: int | Sequence[int] = (256, 256),
        seed: int = 0,
        r_min: float | Sequence[float] = 2.0,
        r_max: float | None = None,
        contrast: float | Sequence[float] = 1.0,
        supersample: int = 1,
        shading: float | Sequence[float] = 0.0,
        thin: float | Sequence[float] = 0.0,
        coverage: float | Sequence[float] = 1.0,
    ) -> None:
        self.n_images = check_int(n_images, "n_images", 1)
        self.seed = check_int(seed, "seed", 0)
        self.r_min_range = _range(r_min, "r_min")
        self.contrast_range = _range(contrast, "contrast")
        self.shading_range = _range(shading, "shading")
        self.thin_range = _range(thin, "thin")
        self.coverage_range = _range(coverage, "coverage")
        for c in self.coverage_range:
            _check_coverage(c)
        for sh, th in zip(self.shading_range, self.thin_range):
            _check_shape(sh, th)  # both ends valid
        for r_lo, c_lo in ((self.r_min_range[0], self.contrast_range[0]), (self.r_min_range[1], self.contrast_range[1])):
            h, w, r_lo, r_max_v, c_lo, s = _resolve_params(size, r_lo, r_max, c_lo, supersample)  # both ends valid
        self.size = (h, w)
        self.r_min, self.r_max, self.contrast, self.supersample = self.r_min_range[0], r_max_v, self.contrast_range[0], s
        self.ids = [f"deadleaves-{i:06d}" for i in range(self.n_images)]

    def image_params(self, index: int) -> tuple[float, float]:
        """``(r_min [px], contrast)`` of image ``index``: the fixed values, or its draw from the ranges."""
        return self.scene_params(index)[:2]  # type: ignore[return-value]

    def scene_params(self, index: int) -> tuple[float, float, float, float, float]:
        """``(r_min [px], contrast, shading, thin, coverage)`` of image ``index``: the fixed values, or its draws."""
        i = check_index(index, len(self), "DeadLeavesSource")
        (r_lo, r_hi), (c_lo, c_hi) = self.r_min_range, self.contrast_range
        (s_lo, s_hi), (t_lo, t_hi), (v_lo, v_hi) = self.shading_range, self.thin_range, self.coverage_range
        if r_lo == r_hi and c_lo == c_hi and s_lo == s_hi and t_lo == t_hi and v_lo == v_hi:
            return r_lo, c_lo, s_lo, t_lo, v_lo
        # the first draws are those of r_min and contrast (then shading) whatever the later ranges are; the fourth
        # (coverage) is unused by the others, so a fixed coverage leaves every image as before
        u = np.random.Generator(np.random.PCG64(np.random.SeedSequence([self.seed, i, 1]))).random(5)
        return (
            float(r_lo * (r_hi / r_lo) ** u[0]),
            float(c_lo + (c_hi - c_lo) * u[1]),
            float(s_lo + (s_hi - s_lo) * u[2]),
            float(t_lo + (t_hi - t_lo) * u[4]),
            float(v_lo + (v_hi - v_lo) * u[3]),
        )

    def __len__(self) -> int:
        return self.n_images  # type: ignore[return-value]

    def __getitem__(self, index: int) -> tuple[torch.Tensor, str]:
        i = check_index(index, len(self), "DeadLeavesSource")
        r_min, contrast, shading, thin, coverage = self.scene_params(i)
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([self.seed, i])))
        rng2 = np.random.Generator(np.random.PCG64(np.random.SeedSequence([self.seed, i, 2])))
        rng3 = np.random.Generator(np.random.PCG64(np.random.SeedSequence([self.seed, i, 3])))
        h, w = self.size
        img = _dead_leaves(rng, h, w, r_min, self.r_max, contrast, self.supersample, shading, rng2, thin, coverage,
                           rng3)
        return img, self.ids[i]

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(n_images={self.n_images}, size={self.size}, seed={self.seed}, "
            f"r_min={_fmt(self.r_min_range)}, r_max={self.r_max:g}, contrast={_fmt(self.contrast_range)}, "
            f"supersample={self.supersample}, shading={_fmt(self.shading_range)}, "
            f"thin={_fmt(self.thin_range)}, coverage={_fmt(self.coverage_range)})"
        )


def _range(v: float | Sequence[float], name: str) -> tuple[float, float]:
    """A value or a ``[low, high]`` range as ``(low, high)``; ``ValueError`` naming ``name`` otherwise."""
    if isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool):
        return float(v), float(v)
    try:
        lo, hi = (float(x) for x in v)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number or a [low, high] pair, got {v!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise ValueError(f"{name} = [{lo:g}, {hi:g}] must be finite with low <= high")
    return lo, hi


def _fmt(r: tuple[float, float]) -> str:
    return f"{r[0]:g}" if r[0] == r[1] else f"[{r[0]:g}, {r[1]:g}]"
