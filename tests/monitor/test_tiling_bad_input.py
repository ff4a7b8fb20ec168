"""patch_statistics / grid_statistics / PatchGrid.extract / status_counts on bad input: NaN, values outside [0, 1],
patch sizes the statistics cannot use, batches of frames and unknown status codes are refused, naming the value."""

from __future__ import annotations

import pytest
import torch

from camhealth.monitor.tiling import (
    MAX_AGE,
    STATUS_NAMES,
    PatchGrid,
    SelectionConfig,
    grid_statistics,
    patch_statistics,
    select_patches,
    status_counts,
)


def _patches(n=2, p=128, seed=0):
    return torch.rand(n, 1, p, p, generator=torch.Generator().manual_seed(seed)) * 0.2 + 0.4


def _with(x, where, value):
    x = x.clone()
    x[where] = value
    return x


@pytest.mark.parametrize("make, match", [
    # all NaN: was "estimated" (informative) with NaN mean and noise
    (lambda x: torch.full_like(x, float("nan")), r"patches must be finite, but 32768 of 32768 values are NaN/inf"),
    (lambda x: _with(x, (1, 0, 5, 5), float("nan")), r"patches must be finite, but 1 of 32768 values are NaN/inf"),
    (lambda x: _with(x, (0, 0, 0, 0), float("inf")), r"patches must be finite, but 1 of 32768 values are NaN/inf"),
    # DN floats: every pixel counted as saturated
    (lambda x: _with(x * 0 + 0.5, (0, 0, 3, 3), 150.0), r"patches must lie in \[0, 1\] \(DN/255\), got values in "
                                                        r"\[0\.5, 150\]"),
    (lambda x: _with(x * 0 + 0.5, (1, 0, 0, 7), -2.0), r"patches must lie in \[0, 1\] \(DN/255\), got values in "
                                                       r"\[-2, 0\.5\]"),
])
def test_patch_statistics_refuses_nan_and_values_outside_the_unit_range(make, match):
    x = _patches()
    with pytest.raises(ValueError, match=match):
        patch_statistics(make(x))
    assert select_patches(patch_statistics(x), "noise")[0].tolist() == [True, True]  # valid patches as before


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.float64])
@pytest.mark.parametrize("value, match", [
    (float("nan"), r"frame must be finite, but 65536 of 65536"),
    (128.0, r"frame must lie in \[0, 1\] \(DN/255\), got values in \[128, 128\]"),
])
def test_grid_statistics_refuses_a_nan_or_dn_frame(dtype, value, match):
    """A whole NaN frame gave 4 of 4 patches informative."""
    grid = PatchGrid.fit(256, 256, 128)
    with pytest.raises(ValueError, match=match):
        grid_statistics(torch.full((1, 1, 256, 256), value, dtype=dtype), grid)
    frame = (torch.rand(1, 1, 256, 256, generator=torch.Generator().manual_seed(1)) * 0.5 + 0.25).to(dtype)
    assert len(grid_statistics(frame, grid)) == 4


@pytest.mark.parametrize("size, patch", [(300, 100), (30, 7), (64, 12), (16, 4)])
def test_grid_statistics_refuses_a_patch_that_is_not_a_multiple_of_8(size, patch):
    """PatchGrid.fit(300, 300, 100) then grid_statistics: RuntimeError: shape '[3, 12, 4, 3, 12, 4]' is invalid."""
    grid = PatchGrid.fit(size, size, patch)
    with pytest.raises(ValueError, match=rf"grid.patch = {patch} px: statistics need patches of P×P px with P a "
                                         r"positive multiple of 8"):
        grid_statistics(torch.rand(1, 1, size, size), grid)


@pytest.mark.parametrize("shape", [(2, 1, 256, 256), (1, 3, 256, 256), (4, 256, 256), (256,)])
def test_a_batch_of_frames_is_refused_by_extract_and_grid_statistics_naming_the_shape(shape):
    """A 2×1×256×256 frame: RuntimeError: shape '[256, 256]' is invalid for input of size 131072."""
    grid = PatchGrid.fit(256, 256, 128)
    frame = torch.rand(*shape)
    shown = str(tuple(shape)).replace("(", r"\(").replace(")", r"\)")
    for f in (grid.extract, lambda x: grid_statistics(x, grid)):
        with pytest.raises(ValueError, match=rf"frame has shape {shown}: expected one frame \(1×1×H×W, 1×H×W or H×W\) "
                                             r"of 256×256 px \(W×H\), not a batch"):
            f(frame)
    assert grid.extract(torch.rand(1, 256, 256)).shape == (4, 1, 128, 128)  # one frame in any of its forms


@pytest.mark.parametrize("codes, bad", [([0, 99], 99), ([len(STATUS_NAMES)], len(STATUS_NAMES)), ([-1, 2], -1)])
def test_status_counts_refuses_unknown_codes_naming_them(codes, bad):
    """A code >= len(STATUS_NAMES) was dropped without a word; a negative one gave torch's bincount error."""
    top = len(STATUS_NAMES) - 1
    with pytest.raises(ValueError, match=rf"status code {bad} is out of the allowed range \[0, {top}\]"):
        status_counts(torch.tensor(codes))
    assert status_counts(torch.tensor([0, 0, 3]))["estimated"] == 2


@pytest.mark.parametrize("age", [MAX_AGE + 1, 2**63, 10**20])
def test_selection_config_bounds_max_age(age):
    """From 2^63 frames the int64 refresh schedule wrapped (no static patch was ever reused) or did not convert."""
    with pytest.raises(ValueError, match=rf"SelectionConfig.max_age = {age} must be an integer in \[1, {MAX_AGE}\]"):
        SelectionConfig(max_age=age)
    assert SelectionConfig(max_age=MAX_AGE).max_age == MAX_AGE
