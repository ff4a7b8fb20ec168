"""Formatting of offending values in error messages: short, but never printed as an allowed value.

``f"{v:g}"`` keeps six significant digits, so a value just outside its range prints as the range's end
(5.000001 px → "5 px … allowed range [0, 5] px"). :func:`show` prints the short form unless that form would read
as allowed, and then the shortest text that gives the value back exactly (in float32 for values held in float32 or
narrower, else in float64).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch

from camhealth import _validation

__all__ = ["check_range", "show", "show_outside"]


def show(value: float, allowed: Callable[[float], bool], dtype: torch.dtype | None = None) -> str:
    """``value`` as text: ``{:g}``, or its exact shortest form where ``{:g}`` would read as a value ``allowed`` accepts."""
    value = float(value)
    short = f"{value:g}"
    if not math.isfinite(value) or not allowed(float(short)):
        return short
    if dtype in (torch.float16, torch.bfloat16, torch.float32):
        return str(np.float32(value))
    return repr(value)


def show_outside(value: float, low: float, high: float, dtype: torch.dtype | None = None) -> str:
    """``value`` (outside ``[low, high]``) as text that does not read as a value inside it."""
    return show(value, lambda v: low <= v <= high, dtype)


def check_range(x: torch.Tensor, name: str, low: float, high: float, unit: str = "") -> torch.Tensor:
    """:func:`camhealth._validation.check_range` (every element finite and in ``[low, high]``, else ``ValueError``),
    with the offending value printed by :func:`show_outside` (5.000001 px is not shown as the bound 5 px)."""
    try:
        return _validation.check_range(x, name, low, high, unit)
    except ValueError:
        if not bool(torch.isfinite(x).all()):
            raise
        bad = (x < low) | (x > high)
        if not bool(bad.any()):
            raise
        first = x[bad].flatten()[0].item()
        u = f" {unit}" if unit else ""
        raise ValueError(f"{name} = {show_outside(first, low, high, x.dtype)}{u} is out of the allowed range "
                         f"[{low:g}, {high:g}]{u}") from None
