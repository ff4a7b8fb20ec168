"""camhealth.runtime.keep_freed_memory: thresholds below glibc's 128 KiB are refused by name, and a later call with
other values says that it changes nothing."""

from __future__ import annotations

import warnings

import pytest

import camhealth.runtime as runtime


@pytest.fixture
def mallopt(monkeypatch):
    """A fresh process's state with ``mallopt`` recorded instead of called (nothing changes in this process)."""
    calls = []

    class Lib:
        def __init__(self, *args, **kwargs):
            def call(param, value):
                calls.append((param, value))
                return 1

            self.mallopt = call

    monkeypatch.setattr(runtime.ctypes, "CDLL", Lib)
    monkeypatch.setattr(runtime, "_applied", None)
    monkeypatch.setattr(runtime, "_settings", None, raising=False)
    return calls


@pytest.mark.parametrize("kwargs, name, value", [
    ({"mmap_threshold_bytes": 0}, "mmap_threshold_bytes", 0),
    ({"trim_threshold_bytes": 0}, "trim_threshold_bytes", 0),
    ({"mmap_threshold_bytes": 131071}, "mmap_threshold_bytes", 131071),
    ({"trim_threshold_bytes": 4096}, "trim_threshold_bytes", 4096),
])  # fmt: skip
def test_a_threshold_below_128_kib_is_refused_naming_it(mallopt, kwargs, name, value):
    """keep_freed_memory(0, 0) set 131072 for both, though its docstring allowed any integer >= 0."""
    with pytest.raises(ValueError, match=rf"{name} = {value} is out of the allowed range: an integer number of bytes "
                                         rf">= 131072 \(128 KiB"):
        runtime.keep_freed_memory(**kwargs)
    assert mallopt == [] and runtime.freed_memory_kept() is False


@pytest.mark.parametrize("first, second", [((1 << 20,), (8 << 20,)), ((1 << 20, 1 << 30), (1 << 20, 1 << 29)),
                                           ((), (1 << 20,))])
def test_a_later_call_with_other_values_changes_nothing_and_says_so(mallopt, first, second):
    """A second call with other values returned True ("applied") without applying them."""
    assert runtime.keep_freed_memory(*first) is True
    applied = list(mallopt)
    with pytest.warns(RuntimeWarning, match=r"not applied; this process already has mmap threshold \d+ and trim "
                                            r"threshold \d+ bytes from an earlier call"):
        assert runtime.keep_freed_memory(*second) is False
    assert mallopt == applied  # nothing set again
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert runtime.keep_freed_memory(*first) is True  # the same values again: what was applied
