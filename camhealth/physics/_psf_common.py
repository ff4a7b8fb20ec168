"""Helpers shared by the PSF generators of :mod:`camhealth.physics` (argument checks, normalisation, binning)."""

from __future__ import annotations

import numbers

import torch

from camhealth._validation import check_finite
from camhealth.physics._format import check_range
from camhealth.physics.defocus_psf import _batch_vector


def batch_of(*vectors: torch.Tensor) -> int:
    """Broadcast batch size of per-sample vectors (each of size 1 or B)."""
    sizes = {v.shape[0] for v in vectors} - {1}
    if len(sizes) > 1:
        raise ValueError(f"per-sample arguments have incompatible batch sizes {sorted(sizes)} (each must be 1 or B)")
    return sizes.pop() if sizes else 1


def shift_vector(shift_px: object, work: torch.dtype, device: torch.device) -> torch.Tensor:
    """A (B, 2) sub-pixel shift (dx right, dy down) in px, each in [−0.5, 0.5]; ``None`` → (1, 2) zeros."""
    if shift_px is None:
        return torch.zeros(1, 2, dtype=work, device=device)
    if isinstance(shift_px, (list, tuple)):
        shift_px = torch.as_tensor(shift_px, dtype=torch.float64)
    if not isinstance(shift_px, torch.Tensor) or shift_px.dtype == torch.bool or shift_px.is_complex():
        raise TypeError(f"shift_px must be a real (B, 2) tensor of (dx, dy) in px, got {type(shift_px).__name__}")
    s = shift_px.reshape(1, 2) if shift_px.ndim == 1 and shift_px.numel() == 2 else shift_px
    if s.ndim != 2 or s.shape[1] != 2:
        raise ValueError(f"shift_px must have shape (B, 2) or (2,) of (dx, dy) in px, got {tuple(shift_px.shape)}")
    check_finite(s, "shift_px")
    check_range(s, "shift_px", -0.5, 0.5, "px")
    return s.to(device=device, dtype=work)


def check_generator(generator: object, name: str = "generator") -> None:
    """``TypeError`` unless ``generator`` is ``None`` or a ``torch.Generator``."""
    if generator is not None and not isinstance(generator, torch.Generator):
        raise TypeError(f"{name} must be a torch.Generator or None, got {type(generator).__name__} {generator!r:.40}")


def check_count(value: object, name: str, low: int, high: int) -> int:
    """``value`` as an int if it is an integer (Python or NumPy; a bool is none) in ``[low, high]``, else
    ``TypeError``/``ValueError`` naming it."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be an int, got {type(value).__name__}")
    value = int(value)
    if not low <= value <= high:
        raise ValueError(f"{name} = {value} is out of the allowed range [{low}, {high}]")
    return value


def normalise(psf: torch.Tensor) -> torch.Tensor:
    """Each (k, k) kernel divided by its sum (kernels with no mass become the delta kernel)."""
    total = psf.sum(dim=(-2, -1), keepdim=True)
    k = psf.shape[-1]
    delta = torch.zeros_like(psf)
    delta[:, k // 2, k // 2] = 1.0
    ok = total > 0
    return torch.where(ok, psf / torch.where(ok, total, torch.ones_like(total)), delta)


def bin_points(xy: torch.Tensor, weight: torch.Tensor, kernel_size: int) -> torch.Tensor:
    """Pixel-area integration of weighted point samples: the mass of the points in each pixel square.

    ``xy``: (B, N, 2) point positions (x right, y down) in px from the kernel centre; ``weight``: (B, N) or (N,).
    Points outside the kernel are dropped (the callers size the kernel so that none are). → (B, k, k)."""
    k = kernel_size
    b, n, _ = xy.shape
    ix = torch.floor(xy[..., 0] + 0.5 * k)
    iy = torch.floor(xy[..., 1] + 0.5 * k)
    inside = (ix >= 0) & (ix <= k - 1) & (iy >= 0) & (iy <= k - 1)
    w = weight.expand(b, n) if weight.ndim == 1 else weight
    mass = torch.where(inside, w, torch.zeros_like(w))
    idx = (iy.clamp(0, k - 1) * k + ix.clamp(0, k - 1)).long()
    out = torch.zeros(b, k * k, dtype=xy.dtype, device=xy.device)
    out.scatter_add_(1, idx, mass)
    return out.reshape(b, k, k)


def positive_vector(x: object, name: str, low: float, high: float, unit: str = "") -> torch.Tensor:
    """A per-sample 1-D tensor with every value finite and in [low, high]."""
    v = _batch_vector(x, name)
    check_range(v, name, low, high, unit)
    return v
