"""Defocus point spread function: an anti-aliased uniform disk (thesis Eq. 3.6, diameter from Eq. 3.7).

The continuous PSF is a uniform disk of diameter d px centred on the kernel centre (Eq. 3.6). The
discrete kernel value of a pixel is the **exact area** of the pixel square covered by the disk (pixel-area
integration, i.e. the continuous PSF convolved with the 1×1 px box of the pixel aperture, then sampled at
the pixel centres), normalised so that each kernel sums to 1. The area is computed in closed form, so the
kernel changes continuously with d (no staircase for sub-pixel diameters), and is fully vectorised over
the batch.

Pixel (i, j) of a k×k kernel covers the square ``[j − 0.5, j + 0.5] × [i − 0.5, i + 0.5]`` around the
centre ``c = (k − 1)/2``. A disk with d <= 1 px lies inside the centre pixel and yields the delta kernel
(as does d = 0).
"""

from __future__ import annotations

import math
from typing import Sequence, Union

import torch

from camhealth._validation import check_batch_vector, check_odd_kernel_size
from camhealth.physics._format import check_range

__all__ = ["defocus_psf", "default_kernel_size"]


def _batch_vector(x: object, name: str, batch: int | None = None) -> torch.Tensor:
    """Per-sample values as a 1-D real tensor (TypeError for non-numeric input, ValueError for bad shape)."""
    if isinstance(x, bool) or not isinstance(x, (int, float, torch.Tensor, list, tuple)):
        raise TypeError(f"{name} must be a torch.Tensor of per-sample values (or a number), got {type(x).__name__}")
    if isinstance(x, (list, tuple)):
        try:
            x = torch.as_tensor(x, dtype=torch.float64)
        except (TypeError, ValueError, RuntimeError) as err:
            raise TypeError(f"{name} must hold real numbers, got {x!r}") from err
    if isinstance(x, torch.Tensor) and (x.dtype == torch.bool or x.is_complex()):
        raise TypeError(f"{name} must be a real-valued tensor, got dtype {x.dtype}")
    return check_batch_vector(x, name, batch)


def _out_dtype(*tensors: torch.Tensor) -> torch.dtype:
    """float64 if any input tensor is float64, else float32."""
    return torch.float64 if any(t.dtype == torch.float64 for t in tensors) else torch.float32


def _work_dtype(device: torch.device) -> torch.dtype:
    """Internal computation dtype: float64 (float32 on MPS, which has no float64)."""
    return torch.float32 if device.type == "mps" else torch.float64


def _disk_quadrant_area(x: torch.Tensor, y: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Signed area of ``disk(0, r) ∩ [0, x] × [0, y]`` (signed: sign(x)·sign(y)·area for |x|, |y|).

    For x, y >= 0 (clamped to r): with t* = sqrt(r² − y²) the abscissa where the circle reaches height y,
    ``Q = y · min(x, t*) + S(x) − S(min(x, t*))`` where ``S(t) = ∫_0^t sqrt(r² − u²) du
    = (t·sqrt(r² − t²) + r²·asin(t/r)) / 2``.
    """
    sgn = torch.sign(x) * torch.sign(y)
    r_safe = r.clamp_min(1e-30)
    ax = torch.minimum(x.abs(), r)
    ay = torch.minimum(y.abs(), r)
    t_star = (r * r - ay * ay).clamp_min(0).sqrt()
    xm = torch.minimum(ax, t_star)

    def s(t: torch.Tensor) -> torch.Tensor:
        return 0.5 * (t * (r * r - t * t).clamp_min(0).sqrt() + r * r * torch.asin((t / r_safe).clamp(-1, 1)))

    return sgn * (ay * xm + s(ax) - s(xm))


def _disk_coverage(diameter_px: torch.Tensor, kernel_size: int) -> torch.Tensor:
    """Unnormalised pixel-area coverage (px²) of disks of diameter ``diameter_px`` (B,) → (B, k, k).

    Sums to π·d²/4 when the disk fits into the kernel (d <= k). Computed in the dtype of ``diameter_px``.
    """
    k = kernel_size
    r = (0.5 * diameter_px)[:, None, None]  # (B,1,1)
    edges = torch.arange(k + 1, device=diameter_px.device, dtype=diameter_px.dtype) - 0.5 * k  # grid lines
    q = _disk_quadrant_area(edges[None, None, :], edges[None, :, None], r)  # (B, k+1, k+1): [y-edge, x-edge]
    # Inclusion–exclusion over the four pixel corners.
    area = q[:, 1:, 1:] - q[:, 1:, :-1] - q[:, :-1, 1:] + q[:, :-1, :-1]
    # Remove cancellation dust: pixels whose square does not reach the disk are exactly 0, none negative.
    centres = torch.arange(k, device=diameter_px.device, dtype=diameter_px.dtype) - 0.5 * (k - 1)
    gap = (centres.abs() - 0.5).clamp_min(0)  # distance from the kernel centre to the pixel square, per axis
    reaches = (gap[None, :, None] ** 2 + gap[None, None, :] ** 2) < r * r
    return torch.where(reaches, area.clamp_min(0), torch.zeros_like(area))


def _delta(batch: int, kernel_size: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    out = torch.zeros(batch, kernel_size, kernel_size, dtype=dtype, device=device)
    c = kernel_size // 2
    out[:, c, c] = 1.0
    return out


def defocus_psf(diameter_px: torch.Tensor, kernel_size: int) -> torch.Tensor:
    """Anti-aliased uniform-disk defocus kernels (Eq. 3.6), one per sample.

    Args:
        diameter_px: (B,) disk diameters d in px (circle of confusion, Eq. 3.7 / pixel pitch), each in
            ``[0, kernel_size]``; a scalar or a Python number is treated as B = 1.
        kernel_size: odd kernel side k in px (1..255); see :func:`default_kernel_size`.

    Returns:
        (B, k, k) kernels, each summing to 1: value = area of the pixel covered by the disk / disk area.
        d <= 1 px (the whole disk inside the centre pixel, including d = 0) gives the delta kernel.
        dtype float64 if ``diameter_px`` is float64, else float32; on ``diameter_px``'s device.

    Raises:
        TypeError: ``diameter_px`` not numeric, or ``kernel_size`` not an int.
        ValueError: d non-finite, d < 0 or d > kernel_size, or kernel_size even / out of range.
    """
    k = check_odd_kernel_size(kernel_size)
    d = _batch_vector(diameter_px, "diameter_px")
    check_range(d, "diameter_px", 0.0, float(k), "px")
    out_dtype = _out_dtype(d)
    work = _work_dtype(d.device)
    d = d.to(work)
    cov = _disk_coverage(d, k)
    total = cov.sum(dim=(-2, -1), keepdim=True)
    ok = total > 0
    psf = torch.where(ok, cov / torch.where(ok, total, torch.ones_like(total)), _delta(d.shape[0], k, work, d.device))
    psf = psf / psf.sum(dim=(-2, -1), keepdim=True)
    return psf.to(out_dtype)


def default_kernel_size(max_diameter_px: Union[float, int, torch.Tensor, Sequence[float]]) -> int:
    """Smallest odd kernel size (px) that holds a disk of diameter ``max_diameter_px`` plus a 2 px margin.

    ``k = smallest odd integer >= d + 2`` (1 px free on each side), e.g. d = 21 → 23, d = 39 → 41,
    d = 0 → 3. For a tensor/sequence the maximum diameter is used.

    Raises:
        TypeError: non-numeric input. ValueError: negative/non-finite diameter or k > 255.
    """
    d = _batch_vector(max_diameter_px, "max_diameter_px")
    check_range(d, "max_diameter_px", 0.0, 253.0, "px")
    if d.numel() == 0:
        raise ValueError("max_diameter_px must hold at least one value, got an empty tensor")
    k = int(math.ceil(float(d.max().item()) + 2.0 - 1e-9))
    return k if k % 2 == 1 else k + 1
