"""Process-level settings for CPU loops that repeat the same work (the monitor, training, benchmarks).

:func:`keep_freed_memory` — on glibc, a freed block of ≥ 128 KiB (the default ``M_MMAP_THRESHOLD``, which
glibc raises adaptively only up to 32 MiB) goes back to the kernel, and the next tensor of that size is
page-faulted in afresh (~1 ms per 4–5 MB on this VM). A monitor that runs the same networks on every frame
allocates and frees the same activation buffers again and again, so this costs it a large share of its
time (measured: "every informative patch" 329 → 209 ms per 1280×1024 frame, docs/benchmarks.md). Raising
the mmap and trim thresholds keeps freed blocks in the process heap for reuse: the steady-state resident
memory becomes the peak one, which the monitor reports and keeps under 1 GB. ``python -m camhealth.fit`` calls
it too: the on-the-fly corruption of a 32×1×192×192 batch (``CameraCorruption``) took ~1 700–4 000 minor page
faults and 5–16 ms of system time per call with glibc's defaults, 0–270 faults and ~1 ms with freed memory kept
(``python -m camhealth.bench corruption`` prints the fault count; ``--default-malloc`` switches it off).

This is what ``MALLOC_MMAP_THRESHOLD_``/``MALLOC_TRIM_THRESHOLD_`` in the environment do, set from inside
the process; on other C libraries (macOS, Windows, musl) it does nothing and returns ``False``.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import numbers
import sys

__all__ = ["keep_freed_memory", "freed_memory_kept"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: glibc's largest allowed M_MMAP_THRESHOLD on 64-bit systems (4 MiB · sizeof(long)).
_MMAP_THRESHOLD_MAX = 32 * 1024 * 1024

#: The smallest value of either threshold: glibc's default mmap threshold (128 KiB). Lower ones would return more
#: freed memory to the kernel than glibc's defaults do, the opposite of what this setting is for.
_MIN_THRESHOLD = 128 * 1024
#: The largest trim threshold (``mallopt`` takes a C int).
_TRIM_THRESHOLD_MAX = 2**31 - 1

_applied: bool | None = None
#: The (mmap, trim) thresholds [bytes] the first call applied (or tried to), as clipped.
_settings: tuple[int, int] | None = None


def keep_freed_memory(mmap_threshold_bytes: int = _MMAP_THRESHOLD_MAX, trim_threshold_bytes: int = 1 << 30) -> bool:
    """Keep freed tensor memory in the process for reuse (glibc ``mallopt``); idempotent.

    Args:
        mmap_threshold_bytes: blocks at least this large are still mapped and unmapped individually
            (glibc allows at most 32 MiB on 64-bit systems; larger values are clipped to it).
        trim_threshold_bytes: free memory at the top of the heap beyond this is returned to the kernel
            (values above 2³¹ − 1, the largest ``mallopt`` takes, are clipped to it).

    Both are integers ≥ 131072 (128 KiB, glibc's default mmap threshold; bytes, not bool): anything else is a
    ``TypeError``/``ValueError`` naming the argument, raised before anything is changed, so a later valid call still
    applies the settings.

    The settings are applied once per process (they cannot be undone). A later call with the same values returns what
    the first one returned; a later call with other values changes nothing, warns (``RuntimeWarning`` naming both) and
    returns False.

    Returns:
        True if these settings were applied (glibc), False otherwise.
    """
    global _applied, _settings
    for name, value in (("mmap_threshold_bytes", mmap_threshold_bytes), ("trim_threshold_bytes", trim_threshold_bytes)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise TypeError(f"{name} = {value!r} must be an integer number of bytes, got {type(value).__name__}")
        if value < _MIN_THRESHOLD:
            raise ValueError(f"{name} = {value!r} is out of the allowed range: an integer number of bytes >= "
                             f"{_MIN_THRESHOLD} (128 KiB, glibc's default threshold)")
    settings = (int(min(mmap_threshold_bytes, _MMAP_THRESHOLD_MAX)), int(min(trim_threshold_bytes, _TRIM_THRESHOLD_MAX)))
    if _applied is not None:
        if _settings is not None and settings != _settings:
            import warnings

            warnings.warn(f"keep_freed_memory(mmap_threshold_bytes={mmap_threshold_bytes}, trim_threshold_bytes="
                          f"{trim_threshold_bytes}): not applied; this process already has mmap threshold {_settings[0]} "
                          f"and trim threshold {_settings[1]} bytes from an earlier call (they are set once)",
                          RuntimeWarning, stacklevel=2)
            return False
        return _applied
    _applied = False
    _settings = settings
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    mmap_threshold, trim_threshold = settings
    _applied = bool(mallopt(_M_MMAP_THRESHOLD, mmap_threshold)) and bool(mallopt(_M_TRIM_THRESHOLD, trim_threshold))
    return _applied


def freed_memory_kept() -> bool:
    """Whether :func:`keep_freed_memory` has changed this process's allocator settings (they cannot be undone)."""
    return bool(_applied)
