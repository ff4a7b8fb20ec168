"""camhealth.runtime: the allocator setting is applied once and reports whether it took effect."""

import sys

from camhealth.runtime import freed_memory_kept, keep_freed_memory


def test_keep_freed_memory_is_idempotent_and_applies_on_glibc_linux():
    first = keep_freed_memory()
    assert keep_freed_memory() is first
    assert freed_memory_kept() is first  # reports what was applied
    if sys.platform.startswith("linux"):
        import platform

        if platform.libc_ver()[0] == "glibc":
            assert first is True


def test_a_bad_argument_is_named_and_leaves_the_setting_to_a_later_call(monkeypatch):
    """``keep_freed_memory("abc")`` raised "'>' not supported between 'int' and 'str'" and switched the setting off
    for the rest of the process (every later call returned False). The arguments are checked first."""
    import pytest

    import camhealth.runtime as runtime

    monkeypatch.setattr(runtime, "_applied", None)  # as in a fresh process
    for kwargs, error, match in (
        ({"mmap_threshold_bytes": "abc"}, TypeError, r"mmap_threshold_bytes = 'abc' must be an integer number of bytes"),
        ({"mmap_threshold_bytes": float("nan")}, TypeError, r"mmap_threshold_bytes = nan must be an integer"),
        ({"trim_threshold_bytes": True}, TypeError, r"trim_threshold_bytes = True must be an integer"),
        ({"trim_threshold_bytes": 1.5e6}, TypeError, r"trim_threshold_bytes = 1500000.0 must be an integer"),
        ({"mmap_threshold_bytes": -1}, ValueError, r"mmap_threshold_bytes = -1 is out of the allowed range"),
    ):
        with pytest.raises(error, match=match):
            keep_freed_memory(**kwargs)
        assert runtime._applied is None and freed_memory_kept() is False
