"""Synthetic test charts for the standard MTF measurements: slanted-edge square (ISO 12233) and Siemens star
(ISO 15775), rendered by pixel-area integration.

Both charts have the edge contrast C = 4 : 1 of the standards — gray levels 0.2 and 0.8 (DN/255 in
[0, 1]) — and are rendered like a camera with 100 % fill factor sees them: every pixel holds the mean of
the ideal chart over its 1×1 px area (``supersample²`` point samples per pixel). Their own MTF is
therefore the pixel aperture, ``sinc(f_x)·sinc(f_y)`` (f in cycles/px); the measurements divide it out
when asked (``aperture=True``) so that what they return is the MTF of the blur applied to the chart —
the quantity the labels of :func:`camhealth.physics.mtf_hv` describe.

* :func:`slanted_edge_chart` — a dark square rotated by ``angle_deg`` (ISO 12233: ≈ 5°) on a bright
  background; its four edges give two near-vertical (horizontal MTF) and two near-horizontal (vertical
  MTF) knife edges. :func:`slanted_edge_rois` returns the four regions of interest.
* :func:`siemens_star_chart` — a star of ``n_cycles`` black/white pairs (thesis: f_s = 32) of radius
  ``radius``; outside it the four image corners are uniform reference areas, bright in the top-left and
  bottom-right quadrant and dark in the other two, from which the measurement takes the chart's own
  contrast. At radius r the star has ``f_n = f_s / (π r)`` (Eq. 3.22; normalised to Nyquist).

Charts are deterministic and cached; they come as ``1×1×S×S`` float32 tensors (expand for a batch).
"""

from __future__ import annotations

import functools
import math
import numbers

import numpy as np
import torch

__all__ = [
    "DARK",
    "BRIGHT",
    "slanted_edge_chart",
    "slanted_edge_rois",
    "siemens_star_chart",
    "siemens_star_geometry",
]

#: Chart gray levels (edge contrast 4 : 1), intensities in [0, 1].
DARK: float = 0.2
BRIGHT: float = 0.8


def _check_size(size: object, low: int) -> int:
    """``size`` as an int ≥ ``low`` (Python's or NumPy's integers; a bool is none), else a ``TypeError``/``ValueError``."""
    if isinstance(size, (bool, np.bool_)) or not isinstance(size, numbers.Integral):
        raise TypeError(f"size must be an int, got {type(size).__name__}")
    if size < low:
        raise ValueError(f"size = {size} px is out of the allowed range [{low}, inf)")
    return int(size)


def _area_render(size: int, supersample: int, inside) -> torch.Tensor:
    """Mean of the boolean ``inside(x, y)`` (coordinates of the chart centre frame, px, y down) per pixel."""
    if isinstance(supersample, bool) or not isinstance(supersample, int) or supersample < 1:
        raise ValueError(f"supersample = {supersample!r} must be an int >= 1")
    s = supersample
    c = (size - 1) / 2.0
    sub = (torch.arange(s, dtype=torch.float64) + 0.5) / s - 0.5  # sub-pixel offsets
    coord = torch.arange(size, dtype=torch.float64) - c
    out = torch.empty(size, size, dtype=torch.float64)
    rows_per_chunk = max(1, 2_000_000 // (size * s * s))
    xs = (coord[:, None] + sub[None, :]).reshape(-1)  # (size·s,)
    for r0 in range(0, size, rows_per_chunk):  # chunks of rows only bound the memory
        r1 = min(size, r0 + rows_per_chunk)
        ys = (coord[r0:r1, None] + sub[None, :]).reshape(-1)
        val = inside(xs[None, :], ys[:, None]).to(torch.float64)  # (rows·s, size·s)
        out[r0:r1] = val.reshape(r1 - r0, s, size, s).mean(dim=(1, 3))
    return out


@functools.lru_cache(maxsize=8)
def _slanted_edge(size: int, angle_deg: float, half_side: float, supersample: int) -> torch.Tensor:
    th = math.radians(angle_deg)
    cos, sin = math.cos(th), math.sin(th)

    def inside(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        u = x * cos - y * sin  # rotate the square by θ (counter-clockwise on screen, y down)
        v = x * sin + y * cos
        return (u.abs() <= half_side) & (v.abs() <= half_side)

    sq = _area_render(size, supersample, inside)
    return (BRIGHT + (DARK - BRIGHT) * sq).float()[None, None]


def slanted_edge_chart(size: int = 256, angle_deg: float = 5.0, square_frac: float = 0.5, supersample: int = 8) -> torch.Tensor:
    """ISO 12233 style chart: a dark square (side ``square_frac·size``) rotated by ``angle_deg`` on bright.

    Returns a ``1×1×size×size`` float32 tensor with levels 0.2 (square) and 0.8 (background).
    """
    size = _check_size(size, 32)
    if not (1.0 <= abs(float(angle_deg)) <= 20.0):
        raise ValueError(f"angle_deg = {angle_deg:g}° is out of the allowed range 1°…20° (ISO 12233 asks for ≈ 5°)")
    if not (0.2 <= float(square_frac) <= 0.7):
        raise ValueError(f"square_frac = {square_frac:g} is out of the allowed range [0.2, 0.7]")
    return _slanted_edge(size, float(angle_deg), 0.5 * float(square_frac) * size, supersample).clone()


def slanted_edge_rois(size: int = 256, angle_deg: float = 5.0, square_frac: float = 0.5) -> dict[str, tuple[int, int, int, int]]:
    """Regions of interest ``(row0, row1, col0, col1)`` (end exclusive) around the four edges of
    :func:`slanted_edge_chart` with the same ``size``, ``angle_deg`` and ``square_frac``.

    ``"left"``/``"right"`` hold near-vertical edges (horizontal MTF), ``"top"``/``"bottom"`` near-horizontal
    ones (vertical MTF). Each ROI is centred where the unrotated square's edge would be and reaches
    W = min(0.6·a, room to the image border less 2 px) px across its edge (a = half side, px). Along the edge it
    covers at most the middle 70 % of the side, and less where the rotation by θ = ``angle_deg`` would bring a
    corner or an adjacent edge near: with the square's coordinate along the edge v = x·sin θ + y·cos θ (chart
    centre frame), the whole ROI keeps |v| ≤ a − W/4, i.e. every ROI pixel stays at least W/4 px from the
    adjacent edges, so the ROI holds one straight edge and nothing else. The half length along the edge is
    therefore ``min(0.7·a, (a − W/4 − (a + W)·|sin θ|)/cos θ)`` px (the 0.7·a cap is the one that holds at the
    ISO 5°); it also keeps the edge within W/2 of the ROI's centre column over all its rows.

    Raises ``ValueError`` if the chart leaves less than 8 px across or fewer than 8 rows along an edge.
    """
    size = _check_size(size, 32)
    if isinstance(angle_deg, bool) or not isinstance(angle_deg, (int, float)) or not (1.0 <= abs(float(angle_deg)) <= 30.0):
        raise ValueError(f"angle_deg = {angle_deg!r}° is out of the allowed range 1°…30° (|angle|; ISO 12233 asks for ≈ 5°)")
    if isinstance(square_frac, bool) or not isinstance(square_frac, (int, float)) or not (0.0 < float(square_frac) < 1.0):
        raise ValueError(f"square_frac = {square_frac!r} is out of the allowed range (0, 1)")
    th = math.radians(abs(float(angle_deg)))
    cos, sin = math.cos(th), math.sin(th)
    c = (size - 1) / 2.0
    a = 0.5 * float(square_frac) * size
    across = min(0.6 * a, c - a - 2.0)
    if across < 8:
        raise ValueError(f"chart of {size} px leaves only {across:.1f} px beside the square edge; use a larger size")
    # along the edge: the ROI (centre v_c = −a·sin θ, half extents W across and H along) stays within |v| ≤ a − W/4,
    # and the edge, at a·(1/cos θ − 1) + H·tan θ px from the ROI's centre column at its end rows, within W/2 of it
    along = min(0.7 * a, (a - 0.25 * across - (a + across) * sin) / cos,
                (0.5 * across - a * (1.0 / cos - 1.0)) / math.tan(th))
    if along < 3.5:
        raise ValueError(f"chart of {size} px at {float(angle_deg):g}° leaves only {2 * along:.1f} px along each edge "
                         f"clear of the corners (at least 8 rows needed); use a larger size or a smaller angle")
    lo, hi = int(round(c - along)), int(round(c + along)) + 1
    rois = {}
    for name, centre in (("left", c - a), ("right", c + a)):
        rois[name] = (lo, hi, int(round(centre - across)), int(round(centre + across)) + 1)
    for name, centre in (("top", c - a), ("bottom", c + a)):
        rois[name] = (int(round(centre - across)), int(round(centre + across)) + 1, lo, hi)
    return rois


@functools.lru_cache(maxsize=4)
def _siemens_star(size: int, n_cycles: int, radius: float, supersample: int) -> torch.Tensor:
    def inside(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        r = torch.sqrt(x * x + y * y)
        phi = torch.atan2(-y, x) % (2.0 * math.pi)
        seg = torch.floor(phi * n_cycles / math.pi).long() % 2 == 0  # 2·n_cycles segments, even = bright
        ref_bright = (x * y) > 0  # outside the star: top-left / bottom-right bright (y down)
        return torch.where(r <= radius, seg, ref_bright)

    bright = _area_render(size, supersample, inside)
    return (DARK + (BRIGHT - DARK) * bright).float()[None, None]


def siemens_star_chart(size: int = 512, n_cycles: int = 32, radius_frac: float = 0.47, supersample: int = 8) -> torch.Tensor:
    """ISO 15775 style Siemens star: ``n_cycles`` bright/dark pairs, radius ``radius_frac·size``, centred.

    Returns a ``1×1×size×size`` float32 tensor with levels 0.2 and 0.8 (see the module doc for the corners). A
    ``radius_frac`` that is not a real number (a string, a bool) raises a ``TypeError``, one outside [0.2, 0.49] (NaN
    too) a ``ValueError``, naming it.
    """
    size = _check_size(size, 64)
    if isinstance(n_cycles, bool) or not isinstance(n_cycles, int) or not (4 <= n_cycles <= 180):
        raise ValueError(f"n_cycles = {n_cycles!r} must be an int in [4, 180]")
    if isinstance(radius_frac, (bool, np.bool_)) or not isinstance(radius_frac, numbers.Real):
        raise TypeError(f"radius_frac = {radius_frac!r:.40} must be a real number in [0.2, 0.49] (star radius / size), "
                        f"got {type(radius_frac).__name__}")
    if not (0.2 <= float(radius_frac) <= 0.49):
        raise ValueError(f"radius_frac = {radius_frac:g} is out of the allowed range [0.2, 0.49]")
    return _siemens_star(size, n_cycles, float(radius_frac) * size, supersample).clone()


def siemens_star_geometry(size: int = 512, radius_frac: float = 0.47) -> tuple[float, float, float]:
    """``(centre_row, centre_col, radius)`` in px of :func:`siemens_star_chart` (pixel-centre coordinates). ``size``: an
    int ≥ 1; ``radius_frac``: a finite real number in (0, 0.5] (else a ``TypeError``/``ValueError`` naming it)."""
    size = _check_size(size, 1)
    if (isinstance(radius_frac, (bool, np.bool_)) or not isinstance(radius_frac, numbers.Real) or not math.isfinite(radius_frac)
            or not 0.0 < radius_frac <= 0.5):
        raise ValueError(f"radius_frac = {radius_frac!r:.40} must be a finite real number in (0, 0.5] (star radius / size)")
    c = (size - 1) / 2.0
    return c, c, float(radius_frac) * size
