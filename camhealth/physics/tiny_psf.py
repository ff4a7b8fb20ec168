"""Tiny blur kernels: random non-negative weights on a 1–5 px support (the smallest blurs, and lens/processing
kernels of no parametric family).

:func:`sample_tiny_psf` draws, per sample, weights from the flat Dirichlet distribution (normalised
independent Exp(1) draws) on an s×s support (s = ``support_px``), placed at the kernel centre c = k//2: it covers
rows and columns c − s//2 … c − s//2 + s − 1, i.e. for odd s (s − 1)/2 pixels on each side of the centre, and
for even s s/2 pixels left of / above the centre and s/2 − 1 right of / below it (s = 4 in k = 7: columns 1…4
about the centre 3). s = 1 is the delta kernel. Kernels sum to 1 by
construction. The MTF of such a kernel has no closed form beyond its DFT (:func:`camhealth.physics.mtf_hv`).
"""

from __future__ import annotations

import torch

from camhealth._validation import check_odd_kernel_size
from camhealth.physics._psf_common import check_count, check_generator

__all__ = ["sample_tiny_psf"]


def sample_tiny_psf(batch_size: int, support_px: int, kernel_size: int, generator: torch.Generator | None = None,
                    dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """B random kernels on an s×s support (s in 1..5) inside a k×k kernel (k ≥ s, odd) → (B, k, k) summing to 1."""
    k = check_odd_kernel_size(kernel_size)
    batch_size = check_count(batch_size, "batch_size", 1, 1 << 30)  # (NumPy integers too, as kernel_size)
    support_px = check_count(support_px, "support_px", 1, 5)
    check_generator(generator)
    if support_px > k:
        raise ValueError(f"support_px = {support_px} must be ≤ kernel_size = {k}")
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"dtype must be a floating torch.dtype, got {dtype}")
    w = -torch.log1p(-torch.rand(batch_size, support_px, support_px, generator=generator, dtype=torch.float64))
    w = w / w.sum(dim=(-2, -1), keepdim=True)
    out = torch.zeros(batch_size, k, k, dtype=torch.float64)
    start = k // 2 - support_px // 2
    out[:, start:start + support_px, start:start + support_px] = w
    return out.to(dtype)
