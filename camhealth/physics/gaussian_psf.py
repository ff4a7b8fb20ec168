"""Gaussian defocus point spread function, pixel-area integrated in closed form, with a sub-pixel shift.

A Gaussian PSF ``p(x, y) = exp(−(x² + y²)/(2σ²)) / (2πσ²)`` models defocus of a lens whose pupil is apodised or
whose aberrations smear the disk edge (the smooth end of the defocus family; the disk of
:mod:`camhealth.physics.defocus_psf` is the sharp end). The kernel value of pixel (i, j) is the **exact** mass
of p inside the pixel square ``[j − c − 0.5, j − c + 0.5] × [i − c − 0.5, i − c + 0.5]`` around the kernel
centre c = (k − 1)/2, moved by the sub-pixel shift (dx, dy): separable, a product of two differences of
``erf``. Kernels are renormalised to sum 1 (the tails beyond the kernel are dropped). The kernel must span ±2σ
about its centre pixel, k ≥ 4σ + 1 (σ ≤ (k − 1)/4: at most 9 % of the mass dropped, whatever the shift), else
``ValueError`` — as the other generators refuse a PSF larger than their kernel; k ≥ 6σ + 1 drops < 0.6 %.

Closed form (:func:`gaussian_mtf`): the continuous MTF ``exp(−2π²σ²f²)`` (f in cycles/px); the kernel's MTF is
that times the pixel aperture's ``|sinc f|`` up to aliasing (:mod:`camhealth.physics.mtf`), whatever the shift
(a shift changes the phase of the OTF only).
"""

from __future__ import annotations

import math

import torch

from camhealth._validation import check_odd_kernel_size
from camhealth.physics._format import check_range, show_outside
from camhealth.physics._psf_common import batch_of, normalise, positive_vector, shift_vector
from camhealth.physics.defocus_psf import _out_dtype, _work_dtype
from camhealth.physics.thin_lens import _as_tensors, _finish

__all__ = ["gaussian_psf", "gaussian_mtf"]


def gaussian_psf(sigma_px: torch.Tensor, kernel_size: int, shift_px: torch.Tensor | None = None) -> torch.Tensor:
    """Pixel-integrated Gaussian kernels, one per sample.

    Args:
        sigma_px: (B,) standard deviation σ of the Gaussian in px, in [0, 64] and ≤ (k − 1)/4 (the kernel spans ±2σ:
            k ≥ 4σ + 1, else ``ValueError`` naming σ, k and the smallest k that holds it); σ = 0 is the point (delta
            kernel, moved by no shift: a point inside one pixel square lands in that pixel; a point on the pixels'
            common edge or corner, shift ±0.5, is shared by them — (0.5, 0.5) gives four taps of 0.25).
        kernel_size: odd kernel side k in px (1..255); k ≥ 6σ + 1 keeps the dropped tails below 0.6 %.
        shift_px: optional (B, 2) or (2,) sub-pixel shift (dx right, dy down) in px, each in [−0.5, 0.5].

    Returns:
        (B, k, k) kernels summing to 1; float64 if an input is float64, else float32.
    """
    k = check_odd_kernel_size(kernel_size)
    s = positive_vector(sigma_px, "sigma_px", 0.0, 64.0, "px")
    _check_fits(s, k)
    dev = s.device
    work = _work_dtype(dev)
    shift = shift_vector(shift_px, work, dev)
    b = batch_of(s, shift)
    out_dtype = _out_dtype(s, *(t for t in (shift_px,) if isinstance(t, torch.Tensor)))
    s = s.to(work).expand(b)[:, None]
    edges = torch.arange(k + 1, device=dev, dtype=work) - 0.5 * k  # pixel borders relative to the centre

    def axis(offset: torch.Tensor) -> torch.Tensor:  # (B, k) mass of the 1-D Gaussian in each pixel
        z = (edges[None, :] - offset[:, None]) / (s * math.sqrt(2.0)).clamp_min(1e-30)
        cdf = 0.5 * (1.0 + torch.erf(z))
        return cdf[:, 1:] - cdf[:, :-1]

    sh = shift.expand(b, 2)
    psf = axis(sh[:, 1])[:, :, None] * axis(sh[:, 0])[:, None, :]
    return normalise(psf).to(out_dtype)


def _check_fits(sigma: torch.Tensor, k: int) -> None:
    """``ValueError`` unless every σ fits the k-px kernel: 4σ ≤ k − 1 (the kernel spans ±2σ about its centre pixel)."""
    if sigma.numel() == 0:
        return
    top = float(sigma.max())
    limit = (k - 1) / 4.0
    if top > limit:
        need = int(math.ceil(4.0 * top + 1.0 - 1e-9))
        need += 1 - need % 2  # the smallest odd k ≥ 4σ + 1
        hint = (f"kernel_size ≥ {need}" if need <= 255 else
                "a σ of at most 63.5 px (the largest kernel, 255 px, holds no more)")
        raise ValueError(
            f"sigma_px = {show_outside(top, 0.0, limit, sigma.dtype)} px does not fit kernel_size = {k}: the kernel must "
            f"span ±2σ, σ in [0, {limit:g}] px for k = {k} (a larger σ loses more than the 9 % of the Gaussian's mass "
            f"allowed in its tails); use {hint}"
        )


def gaussian_mtf(sigma_px, f_cycles_per_px):
    """Continuous MTF of a Gaussian PSF of standard deviation σ ≥ 0 px: ``exp(−2π²σ²f²)`` (f in cycles/px). A negative
    or non-finite σ is a ``ValueError``."""
    (s, f), scal, dt, _ = _as_tensors((sigma_px, "sigma_px"), (f_cycles_per_px, "f_cycles_per_px"))
    check_range(s, "sigma_px", 0.0, math.inf, "px")
    return _finish(torch.exp(-2.0 * math.pi**2 * s.square() * f.square()), scal, dt)
