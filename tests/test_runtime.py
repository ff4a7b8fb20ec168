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
