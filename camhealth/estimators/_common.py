"""Input checks shared by the classical estimators (images B×1×H×W in [0, 1], σ returned in DN)."""

from __future__ import annotations

import torch

from camhealth._validation import check_image

__all__ = ["DN", "check_patches", "work_dtype"]

#: Digital numbers per unit intensity: σ [DN] = 255 · σ [intensity in [0, 1]].
DN: float = 255.0


def work_dtype(x: torch.Tensor) -> torch.dtype:
    """float64 for float64 input, else float32 (half precision is upcast)."""
    return torch.float64 if x.dtype == torch.float64 else torch.float32


def check_patches(x: object, name: str = "images", min_size: tuple[int, int] = (1, 1)) -> torch.Tensor:
    """Validate a monochrome batch ``B×1×H×W`` in [0, 1] with ``H, W`` at least ``min_size``.

    Raises ``TypeError`` for a non-tensor or a non-float dtype (integer DN images: divide by 255 first),
    ``ValueError`` for a wrong shape, NaN/inf, values outside [0, 1] or a too small patch.
    """
    x = check_image(x, name, channels=1)
    h, w = x.shape[-2:]
    if h < min_size[0] or w < min_size[1]:
        raise ValueError(f"{name} must be at least {min_size[0]}×{min_size[1]} px, got {h}×{w}")
    lo, hi = torch.aminmax(x.detach())
    if lo < 0 or hi > 1:
        raise ValueError(f"{name} must lie in [0, 1] (DN/255), got values in [{lo.item():g}, {hi.item():g}]")
    return x
