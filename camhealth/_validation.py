"""Input checks shared by every public function.

Bad input must fail early with a message that names the offending value and the allowed range,
never as a silent NaN or a crash deep inside torch. These helpers raise ``TypeError`` for a wrong
type/dtype and ``ValueError`` for a wrong shape or value.
"""

from __future__ import annotations

import numbers
from typing import Sequence

import torch

FLOAT_DTYPES = (torch.float16, torch.bfloat16, torch.float32, torch.float64)


def check_tensor(x: object, name: str) -> torch.Tensor:
    """Raise ``TypeError`` unless ``x`` is a ``torch.Tensor``."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    return x


def check_float(x: torch.Tensor, name: str) -> torch.Tensor:
    """Raise ``TypeError`` unless ``x`` is a floating tensor (fp16, bf16, fp32 or fp64)."""
    check_tensor(x, name)
    if x.dtype not in FLOAT_DTYPES:
        raise TypeError(
            f"{name} must be a floating tensor (float16, bfloat16, float32 or float64), got dtype {x.dtype}"
            + ("; convert integer DN images with x.float() / 255" if not x.dtype.is_floating_point else "")
        )
    return x


def check_finite(x: torch.Tensor, name: str) -> torch.Tensor:
    """Raise ``ValueError`` if ``x`` holds NaN or ±inf, naming how many and the first bad value."""
    if x.numel() == 0:
        return x
    if x.is_floating_point():  # one reduction (NaN propagates into min and max) instead of a boolean mask
        lo, hi = torch.aminmax(x.detach())
        if bool(torch.isfinite(lo) & torch.isfinite(hi)):
            return x
    finite = torch.isfinite(x)
    if not bool(finite.all()):
        bad = x[~finite]
        raise ValueError(
            f"{name} must be finite, but {bad.numel()} of {x.numel()} values are NaN/inf "
            f"(first: {bad.flatten()[0].item()})"
        )
    return x


def check_image(
    x: object, name: str = "input", channels: int | None = 1, value_range: tuple[float, float] | None = None
) -> torch.Tensor:
    """Validate a Kornia-style image batch ``B×C×H×W``: a floating, finite, non-empty 4-D tensor.

    Args:
        x: candidate image batch.
        name: name used in error messages.
        channels: required channel count (camhealth images are monochrome, C = 1); ``None`` accepts any.
        value_range: ``(low, high)``: also require every value in ``[low, high]`` (camhealth images: ``(0.0, 1.0)``,
            intensities DN/255); ``None`` (default) checks no range.

    Raises ``TypeError`` for a non-tensor or a non-floating dtype, ``ValueError`` for a wrong shape or channel count,
    an empty batch, NaN/inf, or (with ``value_range``) a value outside the range, naming the offending value(s).
    """
    x = check_float(check_tensor(x, name), name)
    if x.ndim != 4:
        raise ValueError(f"{name} must have shape B×C×H×W (4 dims), got {tuple(x.shape)}")
    if channels is not None and x.shape[1] != channels:
        raise ValueError(
            f"{name} must have C = {channels} channel(s), got C = {x.shape[1]} (shape {tuple(x.shape)}); "
            "convert colour to gray first (camhealth.data.to_gray)"
        )
    if x.shape[0] == 0 or x.shape[2] == 0 or x.shape[3] == 0:
        raise ValueError(f"{name} must not be empty, got shape {tuple(x.shape)}")
    if value_range is None:
        check_finite(x, name)
    else:  # one reduction for both checks: NaN propagates into min and max, ±inf lands in one of them
        low, high = float(value_range[0]), float(value_range[1])
        lo, hi = torch.aminmax(x.detach())
        if not bool(torch.isfinite(lo) & torch.isfinite(hi)):
            check_finite(x, name)
        if lo < low or hi > high:
            hint = " (DN/255)" if (low, high) == (0.0, 1.0) else ""
            raise ValueError(f"{name} must lie in [{low:g}, {high:g}]{hint}, got values in [{lo.item():g}, {hi.item():g}]")
    return x


def check_range(x: torch.Tensor, name: str, low: float, high: float, unit: str = "") -> torch.Tensor:
    """Raise ``ValueError`` unless every element of ``x`` is finite and in ``[low, high]``."""
    check_tensor(x, name)
    check_finite(x, name)
    if x.numel() == 0:
        return x
    bad = (x < low) | (x > high)
    if bool(bad.any()):
        u = f" {unit}" if unit else ""
        first = x[bad].flatten()[0].item()
        raise ValueError(f"{name} = {first:g}{u} is out of the allowed range [{low:g}, {high:g}]{u}")
    return x


def check_batch_vector(x: object, name: str, batch: int | None = None) -> torch.Tensor:
    """Return ``x`` as a 1-D float tensor of per-sample values; check its length against ``batch``."""
    if not isinstance(x, torch.Tensor):
        x = torch.as_tensor(x, dtype=torch.get_default_dtype())
    if x.ndim == 0:
        x = x.reshape(1)
    if x.ndim != 1:
        raise ValueError(f"{name} must be a scalar or a 1-D tensor of per-sample values, got shape {tuple(x.shape)}")
    if batch is not None and x.shape[0] not in (1, batch):
        raise ValueError(f"{name} has {x.shape[0]} values but the batch has {batch} samples")
    return x


def check_odd_kernel_size(k: int, name: str = "kernel_size", low: int = 1, high: int = 255) -> int:
    """Raise unless ``k`` is an odd integer in ``[low, high]``."""
    if isinstance(k, bool) or not isinstance(k, numbers.Integral):  # (NumPy integers are Integral; np.bool_ is not)
        raise TypeError(f"{name} must be an int, got {type(k).__name__}")
    k = int(k)
    if k < low or k > high or k % 2 == 0:
        raise ValueError(f"{name} = {k} must be an odd integer in [{low}, {high}]")
    return k


def check_batch_size(batch_size: object, name: str = "batch_size") -> int:
    """``batch_size`` as an int, or ``ValueError`` unless it is an integer (not a bool) ≥ 1."""
    if isinstance(batch_size, bool) or not isinstance(batch_size, numbers.Integral) or batch_size < 1:
        raise ValueError(f"{name} = {batch_size!r} must be an integer ≥ 1")
    return int(batch_size)


def check_choice(value: str, name: str, choices: Sequence[str]) -> str:
    """Raise ``ValueError`` unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise ValueError(f"{name} = {value!r} is not one of {list(choices)}")
    return value
