"""Ring ("donut") bokeh point spread function: a uniform annulus, pixel-area integrated in closed form.

A catadioptric (mirror) lens has a central obstruction, so a defocused point images as a bright ring — the
annulus between the outer diameter d and the inner diameter ε·d (ε = obstruction ratio, 0 ≤ ε < 1). The kernel
value of a pixel is the exact area of the pixel square inside the annulus: the disk coverage of
:mod:`camhealth.physics.defocus_psf` for d minus that for ε·d, renormalised to sum 1. ε = 0 is the uniform disk.

Closed form (:func:`ring_mtf`): the OTF of a uniform annulus is the area-weighted difference of two jincs,
``(R² jinc(2πRf) − r² jinc(2πrf)) / (R² − r²)`` with jinc(z) = 2 J₁(z)/z, R = d/2, r = εd/2, f in cycles/px; the
kernel's MTF is that times the pixel aperture's ``|sinc f|`` up to aliasing.
"""

from __future__ import annotations

import math

import torch

from camhealth._validation import check_odd_kernel_size
from camhealth.physics._format import check_range
from camhealth.physics._psf_common import batch_of, normalise, positive_vector
from camhealth.physics.defocus_psf import _disk_coverage, _out_dtype, _work_dtype
from camhealth.physics.thin_lens import _as_tensors, _finish

__all__ = ["ring_psf", "ring_mtf"]


def ring_psf(diameter_px: torch.Tensor, obstruction: torch.Tensor, kernel_size: int) -> torch.Tensor:
    """Uniform-annulus kernels, one per sample.

    Args:
        diameter_px: (B,) outer diameter d in px, in [0, kernel_size].
        obstruction: (B,) inner / outer diameter ε, in [0, 0.95].
        kernel_size: odd kernel side k in px (1..255).

    Returns:
        (B, k, k) kernels summing to 1; an annulus inside the centre pixel gives the delta kernel. float64 if an
        input is float64, else float32.
    """
    k = check_odd_kernel_size(kernel_size)
    d = positive_vector(diameter_px, "diameter_px", 0.0, float(k), "px")
    eps = positive_vector(obstruction, "obstruction", 0.0, 0.95).to(d.device)
    b = batch_of(d, eps)
    work = _work_dtype(d.device)
    out_dtype = _out_dtype(d, eps)
    d = d.to(work).expand(b)
    inner = d * eps.to(work).expand(b)
    cov = (_disk_coverage(d, k) - _disk_coverage(inner, k)).clamp_min(0)
    return normalise(cov).to(out_dtype)


def ring_mtf(diameter_px, obstruction, f_cycles_per_px):
    """Continuous MTF of a uniform annulus (outer diameter d ≥ 0 px, inner εd, ε in [0, 0.95] as for
    :func:`ring_psf`): see the module docstring. Written as ``(jinc(2πRf) − ε² jinc(2πεRf)) / (1 − ε²)`` (the
    module's form with R² divided out), so d → 0 tends to 1 (a point) without a 0/0."""
    (d, eps, f), scal, dt, _ = _as_tensors((diameter_px, "diameter_px"), (obstruction, "obstruction"),
                                          (f_cycles_per_px, "f_cycles_per_px"))
    check_range(d, "diameter_px", 0.0, math.inf, "px")
    check_range(eps, "obstruction", 0.0, 0.95)

    def jinc(radius: torch.Tensor) -> torch.Tensor:
        z = 2.0 * math.pi * radius * f
        small = z.abs() < 1e-8
        zs = torch.where(small, torch.ones_like(z), z)
        return torch.where(small, torch.ones_like(z), 2.0 * torch.special.bessel_j1(zs) / zs)

    big, e2 = 0.5 * d, eps.square()
    otf = (jinc(big) - e2 * jinc(big * eps)) / (1.0 - e2)
    return _finish(otf.abs(), scal, dt)
