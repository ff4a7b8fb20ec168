"""Input checks shared by the classical estimators (images B×1×H×W in [0, 1], σ returned in DN)."""

from __future__ import annotations

import torch

from camhealth._validation import check_image, check_range

__all__ = ["DN", "check_frequencies", "check_patches", "work_dtype"]

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


def check_frequencies(frequencies: object, device: torch.device | str | None = None) -> torch.Tensor:
    """``frequencies`` (a number, sequence, array or tensor of normalised frequencies) as a 1-D float64 tensor, each
    finite and in [0, 1] (× Nyquist); a ``TypeError`` for what holds no real numbers (a string, a bool or complex
    tensor), a ``ValueError`` naming a value out of range."""
    if isinstance(frequencies, (str, bytes)) or (isinstance(frequencies, torch.Tensor)
                                                 and (frequencies.dtype == torch.bool or frequencies.is_complex())):
        raise TypeError(f"frequencies must be real numbers in [0, 1] (× Nyquist), got {frequencies!r:.60}")
    try:
        fn = torch.as_tensor(frequencies, dtype=torch.float64, device=device).reshape(-1)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"frequencies must be real numbers in [0, 1] (× Nyquist), got {type(frequencies).__name__} "
                        f"{frequencies!r:.60}") from None
    return check_range(fn, "frequencies", 0.0, 1.0, "× Nyquist")
