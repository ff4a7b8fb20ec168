"""Rendered held-out scenes whose native MTF is known exactly: the test scenes of the MTF robustness benchmark.

Model: an ideal camera whose pixel integrates the light over its area (an exact 1-px box aperture) — the
convention of ``docs/data.md`` (*Native MTF of the sources*), under which the label of a blurred patch is the
applied kernel's MTF alone (:func:`camhealth.physics.mtf_hv`). A scene here is a continuous image L(x, y) (gray
level in [0, 1], x and y in output pixels, pixel i covering [i − ½, i + ½)); each output pixel is the mean of
s × s point samples of L at (i − ½ + (k + ½)/s), k = 0 … s − 1 — the rule of dead leaves' ``supersample``
(:func:`camhealth.data.dead_leaves.dead_leaves`) and of the charts. Against the exact area integral this has the
closed-form MTF sin(πf)/(s·sin(πf/s))/sinc(f) (f = f_n/2 cycles/px): 1.002 at f_n = 0.6 for s = 8
(:func:`camhealth.data.native_mtf.rendered_native_mtf`), so the native MTF of these scenes is 1 within 0.3 % over
the label band (f_n ≤ 0.6) and the truth of a blurred crop is the kernel's exact MTF.

Classes (:data:`CLASSES`), none of them dead leaves (the training source: occluding flat disks); ``strokes`` and
``shapes`` are drawn on a smooth linear ramp background: level a at the image's top-left corner, changing by b − a
across the image along a random direction (a, b uniform in [0.15, 0.85]). The ramp is not confined to the two
levels: depending on the direction it runs anywhere from a − |b − a| to a + |b − a| (−0.55 … 1.55 at the extremes),
and :func:`render_scenes` clamps each output pixel to [0, 1], so about one background in eight has flat black or
white areas (a translucent shape over them is clamped too). The clamp acts on the scene before any blur is applied,
so the MTF truth of a blurred crop (the kernel's MTF) is unaffected; the published tables and the shipped
``mtf_std`` calibration were made with the scenes as they are, so the ramp is kept:

- ``strokes`` — line art: straight segments, polylines and quadratic Bézier curves of widths 1–6 px (log-uniform)
  with round caps and joins, each an opaque random gray level in [0, 1]; thin features like text and drawings.
- ``shapes`` — random star-shaped polygons (3–9 vertices) and rotated ellipses, radius 6–60 px (log-uniform),
  each filled with a linear gradient (level in [0.05, 0.95] at the centre, changing by up to ±0.3 to the rim) and blended with
  opacity 0.5–1 over what is below: shading plus straight and curved edges, translucent overlaps.
- ``texture`` — random-phase power-law noise: Fourier amplitude ∝ |f|^(−β/2) (power spectrum ∝ 1/f^β), β uniform
  in [1.5, 2.5], unit-modulus random phases, synthesised by FFT on the s× fine grid (periodic), scaled on the
  fine grid to mean 0.5 and standard deviation 0.10–0.18 (25–46 DN at 8 bit), clipped to [0, 1] there, then
  block-averaged (which lowers the standard deviation a little).

Every class is seeded: scene ``i`` of class ``c`` with seed ``seed`` depends only on (seed, c, i), not on how many
scenes are asked for. These scenes belong to the benchmark only (:mod:`camhealth.bench.robustness_mtf`); no
training source uses them.
"""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["CLASSES", "SUPERSAMPLE", "render_scenes", "render_slanted_edge"]

CLASSES = ("strokes", "shapes", "texture")
#: Fine-grid factor s: each output pixel is the mean of s × s point samples (module docstring).
SUPERSAMPLE = 8
_MAX_FINE = 4096  # size · supersample (px of the fine grid per side): ≤ 64 MB per float32 fine image


def _check(size: int, supersample: int) -> tuple[int, int]:
    size, s = int(size), int(supersample)
    if not 16 <= size <= 1024:
        raise ValueError(f"size = {size} px is out of the allowed range [16, 1024]")
    if not 1 <= s <= 16:
        raise ValueError(f"supersample = {s} is out of the allowed range [1, 16]")
    if size * s > _MAX_FINE:
        raise ValueError(f"size · supersample = {size * s} px is out of the allowed range [16, {_MAX_FINE}]")
    return size, s


def _fine_coords(size: int, s: int) -> np.ndarray:
    """Positions (output-pixel units) of the fine-grid point samples along one axis: i − ½ + (k + ½)/s."""
    return ((np.arange(size * s, dtype=np.float64) + 0.5) / s - 0.5).astype(np.float32)


def _block_average(fine: np.ndarray, s: int) -> np.ndarray:
    """Mean of s × s blocks: the pixel aperture (module docstring)."""
    n = fine.shape[0] // s
    return fine.reshape(n, s, n, s).mean((1, 3), dtype=np.float64)


def _window(u: np.ndarray, lo: float, hi: float) -> slice:
    """Fine-grid indices whose sample positions lie in [lo, hi] (``u`` sorted)."""
    return slice(int(np.searchsorted(u, lo, "left")), int(np.searchsorted(u, hi, "right")))


def _gradient_background(rng: np.random.Generator, u: np.ndarray) -> np.ndarray:
    """Linear ramp along a random direction φ: level a at the top-left sample, changing by b − a across the image
    (a, b uniform in [0.15, 0.85]). The projection t spans an interval of length 1 that contains 0 (anywhere in
    [−1, 1]), so the level can leave [min(a, b), max(a, b)] and [0, 1] (a − |b − a| … a + |b − a|); it is not clipped
    here — :func:`render_scenes` clamps its output to [0, 1] (module docstring)."""
    a, b = rng.uniform(0.15, 0.85, 2)
    phi = rng.uniform(0, 2 * math.pi)
    n = float(u[-1] - u[0]) or 1.0
    t = (math.cos(phi) * (u[None, :] - u[0]) + math.sin(phi) * (u[:, None] - u[0])) / (n * (abs(math.cos(phi)) + abs(math.sin(phi))))
    return (a + (b - a) * t).astype(np.float32)


def _paint_capsule(img: np.ndarray, u: np.ndarray, p0: np.ndarray, p1: np.ndarray, half_width: float, level: float) -> None:
    """Set every fine sample within ``half_width`` px of the segment p0–p1 ((x, y), output px) to ``level``."""
    lo, hi = np.minimum(p0, p1) - half_width, np.maximum(p0, p1) + half_width
    cs, rs = _window(u, lo[0], hi[0]), _window(u, lo[1], hi[1])
    if cs.start >= cs.stop or rs.start >= rs.stop:
        return
    x, y = u[cs][None, :], u[rs][:, None]
    d = p1 - p0
    L2 = float(d @ d)
    t = np.zeros(1, np.float32) if L2 == 0 else np.clip(((x - p0[0]) * d[0] + (y - p0[1]) * d[1]) / L2, 0.0, 1.0)
    dist2 = (x - p0[0] - t * d[0]) ** 2 + (y - p0[1] - t * d[1]) ** 2
    img[rs, cs][dist2 <= half_width**2] = level


def _stroke_path(rng: np.random.Generator, size: int) -> np.ndarray:
    """Vertices (n, 2) of one stroke: a straight segment, a polyline or a quadratic Bézier curve."""
    start = rng.uniform(-0.05, 1.05, 2) * size
    length = size * math.exp(rng.uniform(math.log(0.05), math.log(0.5)))
    kind = rng.integers(3)
    if kind == 0:  # straight
        phi = rng.uniform(0, 2 * math.pi)
        return np.stack([start, start + length * np.array([math.cos(phi), math.sin(phi)])])
    if kind == 1:  # polyline: 2–5 segments with turns up to ±120°
        n = int(rng.integers(2, 6))
        phi = rng.uniform(0, 2 * math.pi) + np.cumsum(np.r_[0.0, rng.uniform(-2.1, 2.1, n - 1)])
        steps = (length / n) * np.stack([np.cos(phi), np.sin(phi)], 1)
        return np.vstack([start, start + np.cumsum(steps, 0)])
    ctrl = start + rng.uniform(-1, 1, (2, 2)) * length  # quadratic Bézier, sampled at 24 points
    t = np.linspace(0, 1, 24)[:, None]
    return (1 - t) ** 2 * start + 2 * t * (1 - t) * ctrl[0] + t**2 * ctrl[1]


def _strokes(rng: np.random.Generator, size: int, s: int) -> np.ndarray:
    u = _fine_coords(size, s)
    img = _gradient_background(rng, u)
    n = int(rng.integers(90, 151) * (size / 320) ** 2) + 1
    for _ in range(n):
        pts = _stroke_path(rng, size).astype(np.float32)
        w = math.exp(rng.uniform(0.0, math.log(6.0)))
        level = float(rng.uniform(0.0, 1.0))
        for p0, p1 in zip(pts[:-1], pts[1:]):  # a union of capsules of one level: round caps and joins
            m = max(1, int(math.ceil(float(np.hypot(*(p1 - p0))) / 12.0)))  # ≤ 12-px pieces: small windows
            for j in range(m):
                _paint_capsule(img, u, p0 + (p1 - p0) * (j / m), p0 + (p1 - p0) * ((j + 1) / m), 0.5 * w, level)
    return img


def _inside_polygon(x: np.ndarray, y: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd rule: which points (x, y) (broadcast) lie inside the closed polygon (n, 2)."""
    inside = np.zeros(np.broadcast(x, y).shape, dtype=bool)
    for (x0, y0), (x1, y1) in zip(poly, np.roll(poly, -1, 0)):
        if y0 == y1:
            continue
        cross = (y0 > y) != (y1 > y)
        xc = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
        inside ^= cross & (x < xc)
    return inside


def _paint_shape(img: np.ndarray, u: np.ndarray, inside, box: tuple[float, float, float, float], fill, alpha: float) -> None:
    cs, rs = _window(u, box[0], box[1]), _window(u, box[2], box[3])
    if cs.start >= cs.stop or rs.start >= rs.stop:
        return
    x, y = u[cs][None, :], u[rs][:, None]
    m = inside(x, y)
    sub = img[rs, cs]
    sub[m] = ((1 - alpha) * sub + alpha * np.clip(fill(x, y), 0, 1))[m]


def _shapes(rng: np.random.Generator, size: int, s: int) -> np.ndarray:
    u = _fine_coords(size, s)
    img = _gradient_background(rng, u)
    n = int(rng.integers(70, 111) * (size / 320) ** 2) + 1
    for _ in range(n):
        c = rng.uniform(-0.05, 1.05, 2) * size
        r = math.exp(rng.uniform(math.log(6.0), math.log(60.0)))
        level, delta, phi = rng.uniform(0.05, 0.95), rng.uniform(-0.3, 0.3), rng.uniform(0, 2 * math.pi)
        gx, gy = delta * math.cos(phi) / r, delta * math.sin(phi) / r
        fill = lambda x, y, c=c, level=level, gx=gx, gy=gy: level + gx * (x - c[0]) + gy * (y - c[1])  # noqa: E731
        alpha = float(rng.uniform(0.5, 1.0))
        box = (c[0] - r, c[0] + r, c[1] - r, c[1] + r)
        if rng.random() < 0.5:  # star-shaped polygon
            k = int(rng.integers(3, 10))
            ang = np.sort(rng.uniform(0, 2 * math.pi, k))
            rad = r * rng.uniform(0.45, 1.0, k)
            poly = np.stack([c[0] + rad * np.cos(ang), c[1] + rad * np.sin(ang)], 1)
            _paint_shape(img, u, lambda x, y, p=poly: _inside_polygon(x, y, p), box, fill, alpha)
        else:  # rotated ellipse, semi-axes r and r·q
            q, th = rng.uniform(0.25, 1.0), rng.uniform(0, math.pi)
            ct, st = math.cos(th), math.sin(th)
            ell = lambda x, y, c=c, r=r, q=q, ct=ct, st=st: (  # noqa: E731
                (((x - c[0]) * ct + (y - c[1]) * st) / r) ** 2 + ((-(x - c[0]) * st + (y - c[1]) * ct) / (q * r)) ** 2 <= 1.0)
            _paint_shape(img, u, ell, box, fill, alpha)
    return img


def _texture(rng: np.random.Generator, size: int, s: int) -> np.ndarray:
    n = size * s
    beta = float(rng.uniform(1.5, 2.5))
    g = torch.Generator().manual_seed(int(rng.integers(2**62)))
    # NumPy's FFT (pocketfft, float64): the same bits in every process; torch's CPU FFT (MKL) can differ in the last
    # bits from one process to the next
    w = np.fft.rfft2(torch.randn(n, n, generator=g).double().numpy())
    fy = np.fft.fftfreq(n)[:, None] * s  # cycles per output pixel
    fx = np.fft.rfftfreq(n)[None, :] * s
    f = np.sqrt(fx**2 + fy**2)
    amp = np.where(f > 0, np.maximum(f, 1e-12) ** (-beta / 2), 0.0)
    x = np.fft.irfft2(w / np.maximum(np.abs(w), 1e-30) * amp, s=(n, n))
    x = 0.5 + float(rng.uniform(0.10, 0.18)) * (x - x.mean()) / x.std(ddof=1)
    return np.clip(x, 0.0, 1.0).astype(np.float32)


_RENDER = {"strokes": _strokes, "shapes": _shapes, "texture": _texture}


def render_scenes(cls: str, n: int, size: int = 320, seed: int = 0, supersample: int = SUPERSAMPLE) -> torch.Tensor:
    """``n`` scenes of class ``cls`` (:data:`CLASSES`), rendered with an exact pixel aperture (module docstring).

    Args:
        cls: ``"strokes"``, ``"shapes"`` or ``"texture"``.
        n: number of scenes, 1 … 256.
        size: side in output px, 16 … 1024 (size · supersample ≤ 4096).
        seed: scene ``i`` depends on (seed, cls, i) only.
        supersample: fine-grid factor s (1 … 16): each pixel is the mean of s × s point samples.

    Returns:
        (n, 1, size, size) float32 gray levels, clamped to [0, 1] (a ``strokes``/``shapes`` background ramp can run
        beyond it before the clamp: module docstring).
    """
    if cls not in _RENDER:
        raise ValueError(f"cls = {cls!r} is not one of the rendered scene classes {CLASSES}")
    if not 1 <= int(n) <= 256:
        raise ValueError(f"n = {n} is out of the allowed range [1, 256]")
    size, s = _check(size, supersample)
    out = []
    for i in range(int(n)):
        rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, CLASSES.index(cls), i])
        out.append(_block_average(_RENDER[cls](rng, size, s), s))
    return torch.from_numpy(np.stack(out)[:, None].astype(np.float32)).clamp(0, 1)


def render_slanted_edge(size: int = 128, angle_deg: float = 5.0, supersample: int = SUPERSAMPLE) -> torch.Tensor:
    """A straight near-vertical edge (dark 0.2 left, bright 0.8 right, through the centre, tilted by
    ``angle_deg`` from the vertical) filled by the same polygon rule and block average as ``shapes`` → (1, 1,
    size, size) float32: the check that the rendering adds no blur (its native MTF is 1; tested)."""
    size, s = _check(size, supersample)
    if not 1.0 <= abs(float(angle_deg)) <= 20.0:
        raise ValueError(f"angle_deg = {angle_deg:g} is out of the allowed range 1°…20° (ISO 12233 asks for ≈ 5°)")
    u = _fine_coords(size, s)
    img = np.full((size * s, size * s), 0.8, np.float32)
    c, t, big = (size - 1) / 2.0, math.tan(math.radians(float(angle_deg))), 4.0 * size
    poly = np.array([[-big, -big], [c + t * (-big - c), -big], [c + t * (big - c), big], [-big, big]])
    _paint_shape(img, u, lambda x, y: _inside_polygon(x, y, poly), (-big, big, -big, big), lambda x, y: 0.2 + 0 * x, 1.0)
    return torch.from_numpy(_block_average(img, s)[None, None].astype(np.float32))
