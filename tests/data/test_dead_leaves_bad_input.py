"""dead_leaves / DeadLeavesSource size checks: fractional sizes, renders too large to hold, the default r_max."""

from __future__ import annotations

import numpy as np
import pytest

from camhealth.data.dead_leaves import DeadLeavesSource, dead_leaves


@pytest.mark.parametrize("size, shown", [
    ((10.7, 12.2), r"\(10\.7, 12\.2\)"),
    ((64, 100.5), r"\(64, 100\.5\)"),
    ([np.float64(32.25), 32], r"32\.25"),
])
def test_a_fractional_size_is_refused_not_truncated(size, shown):
    """``size=(10.7, 12.2)`` rendered 10×12 without a word."""
    with pytest.raises(ValueError, match=rf"size = .*{shown}.* must hold whole numbers of pixels \(H, W\), each in \[1, 16384\]"):
        dead_leaves(size)
    with pytest.raises(ValueError, match=rf"size = .*{shown}.* must hold whole numbers of pixels"):
        DeadLeavesSource(2, size=size)


@pytest.mark.parametrize("size, supersample, grid", [
    (16384, 8, "131072×131072"),
    (16384, 2, "32768×32768"),
    ((4096, 8192), 4, "16384×32768"),
    (4097, 4, "16388×16388"),
])
def test_a_render_larger_than_the_limit_is_refused_before_allocating_it(size, supersample, grid):
    """Size and supersample were checked apart: ``dead_leaves(16384, supersample=8)`` tried to allocate 64 GiB."""
    match = rf"supersample = {supersample} renders {grid} = \d+ px, more than the limit of 268435456 \(2\^28\) px"
    with pytest.raises(ValueError, match=match):
        dead_leaves(size, supersample=supersample)
    with pytest.raises(ValueError, match=match):
        DeadLeavesSource(1, size=size, supersample=supersample)


@pytest.mark.parametrize("size, r_min, r_max_shown", [(1, 2.0, "0.5"), (4, 2.0, "2"), ((3, 2), 1.5, "1.5")])
def test_the_default_r_max_is_named_as_the_default(size, r_min, r_max_shown):
    """``dead_leaves(4)`` said "r_max = 2 px must be … > r_min = 2 px" though no r_max was given."""
    h, w = (size, size) if isinstance(size, int) else size
    match = (rf"r_max = {r_max_shown} px \(default: half the larger side of the {h}×{w} px image\) must be > "
             rf"r_min = {r_min:g} px")
    with pytest.raises(ValueError, match=match):
        dead_leaves(size, r_min=r_min)
    with pytest.raises(ValueError, match=match):
        DeadLeavesSource(1, size=size, r_min=r_min)
