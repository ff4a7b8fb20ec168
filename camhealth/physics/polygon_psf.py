"""Polygonal-aperture defocus point spread function: a uniform regular polygon (an iris of n straight blades).

A defocused lens images each point as the shape of its aperture stop, scaled to the circle of confusion
(thesis Eq. 3.6–3.7 for a round stop). An iris of n straight blades makes a regular n-gon: here the polygon is
inscribed in the circle of diameter d px (circumradius R = d/2), rotated by ``rotation_deg`` (counter-clockwise
with y down, as in :mod:`camhealth.physics.motion_psf`; 0° puts a vertex on the +x axis), and moved by an optional
sub-pixel shift. The kernel value of a pixel is the area of the pixel square covered by the polygon, by
supersampling each pixel on an s×s grid of sub-pixel centres (s = ``supersample``; error of the covered area
≤ the boundary length × 1/s px per kernel, → 0 as s grows), renormalised to sum 1.

Closed forms: the area of the polygon is ``n R² sin(2π/n) / 2``; as n → ∞ the kernel tends to the uniform disk
of :func:`camhealth.physics.defocus_psf` (and its MTF to the jinc of :func:`camhealth.physics.mtf.disk_mtf`).
"""

from __future__ import annotations

import math

import torch

from camhealth._validation import check_odd_kernel_size
from camhealth.physics._psf_common import batch_of, check_count, normalise, positive_vector, shift_vector
from camhealth.physics.defocus_psf import _batch_vector, _out_dtype, _work_dtype

__all__ = ["polygon_psf", "polygon_area_px2"]


def polygon_area_px2(diameter_px, n_blades: int) -> torch.Tensor:
    """Area (px²) of the regular n-gon inscribed in the circle of diameter d: ``n (d/2)² sin(2π/n) / 2``."""
    d = torch.as_tensor(diameter_px, dtype=torch.float64)
    return 0.5 * n_blades * (0.5 * d) ** 2 * math.sin(2.0 * math.pi / n_blades)


def polygon_psf(
    diameter_px: torch.Tensor,
    n_blades: int,
    kernel_size: int,
    rotation_deg: torch.Tensor | float = 0.0,
    shift_px: torch.Tensor | None = None,
    supersample: int = 8,
) -> torch.Tensor:
    """Uniform regular-polygon defocus kernels, one per sample.

    Args:
        diameter_px: (B,) diameter d of the circumscribed circle in px, in [0, kernel_size − 1].
        n_blades: number of polygon sides (iris blades), 3..16.
        kernel_size: odd kernel side k in px (1..255).
        rotation_deg: (B,) rotation of the polygon in degrees (any finite value).
        shift_px: optional (B, 2) or (2,) sub-pixel shift (dx right, dy down) in px, each in [−0.5, 0.5].
        supersample: sub-pixel samples per pixel side, 2..32.

    Returns:
        (B, k, k) kernels summing to 1 (a polygon smaller than the sampling grid gives the delta kernel);
        float64 if an input is float64, else float32.
    """
    k = check_odd_kernel_size(kernel_size)
    n_blades = check_count(n_blades, "n_blades", 3, 16)  # (NumPy integers too, as kernel_size)
    supersample = check_count(supersample, "supersample", 2, 32)
    d = positive_vector(diameter_px, "diameter_px", 0.0, float(k - 1), "px")
    dev = d.device
    rot = _batch_vector(rotation_deg, "rotation_deg").to(dev)
    work = _work_dtype(dev)
    shift = shift_vector(shift_px, work, dev)
    b = batch_of(d, rot, shift)
    out_dtype = _out_dtype(d, rot, *(t for t in (shift_px,) if isinstance(t, torch.Tensor)))
    if not bool(torch.isfinite(rot).all()):
        raise ValueError("rotation_deg must be finite")
    r = (0.5 * d.to(work)).expand(b)
    alpha = torch.deg2rad(rot.to(work)).expand(b)
    s = supersample
    sub = (torch.arange(k * s, device=dev, dtype=work) + 0.5) / s - 0.5 * k  # sub-pixel centres
    yy, xx = torch.meshgrid(sub, sub, indexing="ij")
    sh = shift.expand(b, 2)
    x = xx[None] - sh[:, 0, None, None]
    y = -(yy[None] - sh[:, 1, None, None])  # y up for the angle convention
    j = torch.arange(n_blades, device=dev, dtype=work)
    normal = alpha[:, None] + math.pi / n_blades + 2.0 * math.pi * j[None] / n_blades  # (B, n) side normals
    apothem = (r * math.cos(math.pi / n_blades))[:, None, None]
    inside = torch.ones(b, k * s, k * s, dtype=torch.bool, device=dev)
    for i in range(n_blades):
        c, sn = torch.cos(normal[:, i])[:, None, None], torch.sin(normal[:, i])[:, None, None]
        inside &= x * c + y * sn <= apothem
    cov = inside.to(work).reshape(b, k, s, k, s).mean((2, 4))
    return normalise(cov).to(out_dtype)
