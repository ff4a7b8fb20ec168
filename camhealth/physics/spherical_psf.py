"""Defocus with spherical aberration: the geometric-optics PSF of a round pupil with a cubic ray error.

In geometric optics a ray through the normalised pupil radius ρ ∈ [0, 1] (azimuth θ) meets the image plane at
the transverse distance ``r(ρ) = R · ((1 − s)·ρ + s·ρ³)`` from the chief ray, in the direction θ: the linear term
is defocus (a uniform disk of radius R = d/2 when s = 0, thesis Eq. 3.6), the cubic one third-order spherical
aberration (Seidel), with s ∈ [−1, 1] its share of the marginal ray's error. s > 0 packs the inner rays
towards the centre (a bright core in a faint halo), s < 0 pushes them outwards (for s < −1/2 they fold back at a
caustic: a bright rim, the look of the other side of focus). The intensity is uniform over the pupil, so the PSF is
the image of the pupil's area measure under this map.

Rendered by pixel-area integration of a dense, deterministic, equal-area pupil sampling: ``n_rings`` rings
ρ² ∈ [i/n, (i + 1)/n), each with ``8·n_rings`` points spread over the ring's radii by the golden-ratio sequence and
over the azimuth evenly with a per-ring golden-angle offset (no moiré), every point
counted in the pixel square it lands in; renormalised to sum 1. s = 0 reproduces the uniform disk of
:func:`camhealth.physics.defocus_psf` up to the sampling error (≤ 1 % of the kernel mass per pixel at the
default density). Support: r ≤ 1.09 R for every s ∈ [−1, 1].
"""

from __future__ import annotations

import math

import torch

from camhealth._validation import check_odd_kernel_size
from camhealth.physics._psf_common import batch_of, bin_points, check_count, normalise, positive_vector
from camhealth.physics.defocus_psf import _out_dtype, _work_dtype

__all__ = ["spherical_psf", "MAX_REACH"]

#: Largest r(ρ)/R over ρ ∈ [0, 1] and s ∈ [−1, 1] (at s = −1, ρ = √(2/3)): 4√6/9.
MAX_REACH = 4.0 * math.sqrt(6.0) / 9.0


def spherical_psf(diameter_px: torch.Tensor, spherical: torch.Tensor, kernel_size: int, n_rings: int = 64) -> torch.Tensor:
    """Defocus-plus-spherical-aberration kernels, one per sample.

    Args:
        diameter_px: (B,) diameter d = 2R of the defocus disk in px, in [0, kernel_size / 1.09] (so the reach 1.09·d/2 stays inside).
        spherical: (B,) share s of spherical aberration in the marginal ray, in [−1, 1] (0: the uniform disk).
        kernel_size: odd kernel side k in px (1..255).
        n_rings: pupil rings sampled (8·n_rings points each), 8..512.

    Returns:
        (B, k, k) kernels summing to 1; float64 if an input is float64, else float32.
    """
    k = check_odd_kernel_size(kernel_size)
    n_rings = check_count(n_rings, "n_rings", 8, 512)  # (NumPy integers too, as kernel_size)
    d = positive_vector(diameter_px, "diameter_px", 0.0, k / 1.09, "px")
    s = positive_vector(spherical, "spherical", -1.0, 1.0).to(d.device)
    b = batch_of(d, s)
    dev = d.device
    work = _work_dtype(dev)
    out_dtype = _out_dtype(d, s)
    big_r = (0.5 * d.to(work)).expand(b)[:, None]
    sa = s.to(work).expand(b)[:, None]
    n_az = 8 * n_rings
    i = torch.arange(n_rings, device=dev, dtype=work)
    j = torch.arange(n_az, device=dev, dtype=work)
    frac = torch.remainder((j + 0.5) * (math.sqrt(5.0) - 1.0) / 2.0, 1.0)  # radial position inside the ring
    rho = torch.sqrt((i[:, None] + frac[None, :]) / n_rings).reshape(-1)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    theta = (2.0 * math.pi * (torch.arange(n_az, device=dev, dtype=work)[None, :] + 0.5) / n_az + golden * i[:, None]).reshape(-1)
    r = big_r * ((1.0 - sa) * rho[None] + sa * rho[None] ** 3)  # (B, N)
    xy = torch.stack([r * torch.cos(theta)[None], -r * torch.sin(theta)[None]], dim=-1)
    psf = bin_points(xy, torch.ones(rho.numel(), device=dev, dtype=work), k)
    return normalise(psf).to(out_dtype)
