"""Small helpers shared by the image sources (not public API)."""

from __future__ import annotations

import operator
import re

__all__ = ["natural_sort_key", "check_index", "check_int", "check_whole", "check_frame_range"]

_DIGITS = re.compile(r"(\d+)")


def natural_sort_key(s: str) -> tuple:
    """Key that orders embedded numbers numerically: ``frame2`` < ``frame10`` (ties broken by the text)."""
    parts = _DIGITS.split(s)
    key = []
    for i, part in enumerate(parts):
        if i % 2:  # a run of digits
            key.append((1, int(part), part))
        else:
            key.append((0, part.lower(), part))
    return tuple(key)


def check_index(index: object, n: int, what: str) -> int:
    """Return ``index`` as a non-negative int (negative indices count from the end) or raise IndexError."""
    try:
        i = operator.index(index)  # type: ignore[arg-type]
    except TypeError:
        raise TypeError(f"{what} indices must be integers, got {type(index).__name__}") from None
    if not -n <= i < n:
        raise IndexError(f"index {i} out of range for {what} with {n} items")
    return i % n


def check_int(value: object, name: str, low: int, allow_none: bool = False) -> int | None:
    """Validate an integer parameter ``>= low`` (``None`` allowed if ``allow_none``)."""
    if value is None and allow_none:
        return None
    if isinstance(value, bool):
        raise TypeError(f"{name} must be an int, got bool")
    try:
        v = operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise TypeError(f"{name} must be an int, got {type(value).__name__}") from None
    if v < low:
        raise ValueError(f"{name} = {v} must be >= {low}")
    return v


def check_whole(value: object, name: str, low: int, high: int) -> int:
    """``value`` as an int in [low, high]: ``TypeError`` for one that is not a whole number (a bool, a float such as
    100.5, a string), ``ValueError`` for one out of the range; both name ``name``, the value and the range."""
    if isinstance(value, bool):
        raise TypeError(f"{name} = {value!r} must be an integer in [{low}, {high}], got a bool")
    try:
        v = operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise TypeError(f"{name} = {value!r} must be an integer in [{low}, {high}], got {type(value).__name__}") from None
    if not low <= v <= high:
        raise ValueError(f"{name} = {v} is out of the allowed range [{low}, {high}]")
    return v


def check_frame_range(start: object, stride: object, max_frames: object) -> None:
    """``start`` ≥ 0 and ``stride`` ≥ 1 integers, ``max_frames`` an integer ≥ 1 or ``None`` (frame sources and
    recordings); ``ValueError`` naming the value otherwise."""
    for v, name, lo in ((start, "start", 0), (stride, "stride", 1)):
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            raise ValueError(f"{name} = {v!r} must be an integer >= {lo}")
    if max_frames is not None and (isinstance(max_frames, bool) or not isinstance(max_frames, int) or max_frames < 1):
        raise ValueError(f"max_frames = {max_frames!r} must be an integer >= 1 or None")
