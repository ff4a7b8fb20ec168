"""load_defect_map / save_defect_map on bad input: a float mask image holding NaN/inf, a bfloat16 tensor, a shape
that is not (H, W), and flagged-frame counts that are not whole numbers >= 0."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from camhealth.monitor.defect_map import load_defect_map, save_defect_map

M = np.zeros((8, 8), bool)
M[1, 2] = True


@pytest.mark.parametrize("value, count", [(np.nan, 1), (np.inf, 1), (-np.inf, 2)])
def test_a_float_mask_image_with_non_finite_values_is_refused_naming_the_count(tmp_path, value, count):
    """A float32 TIFF that is 0 everywhere and NaN at one pixel read that pixel as a known defect."""
    tifffile = pytest.importorskip("tifffile")
    img = np.zeros((8, 8), np.float32)
    img[1, 2] = 1.0
    img.reshape(-1)[-count:] = value
    p = tmp_path / "mask.tif"
    tifffile.imwrite(p, img)
    with pytest.raises(ValueError, match=rf"defect map '.*mask\.tif' holds {count} non-finite value\(s\) \(NaN/inf\) "
                                         r"of 64: a mask image must be finite"):
        load_defect_map(p)
    ok = tmp_path / "ok.tif"
    tifffile.imwrite(ok, np.where(M, 0.5, 0.0).astype(np.float32))  # finite: non-zero = defective, as before
    assert load_defect_map(ok).nonzero().tolist() == [[1, 2]]


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16, torch.uint8])
def test_a_bfloat16_or_other_tensor_map_is_read(dtype):
    """A bfloat16 tensor raised TypeError: Got unsupported ScalarType BFloat16."""
    out = load_defect_map(torch.from_numpy(M).to(torch.bfloat16))
    assert out.dtype == torch.bool and out.nonzero().tolist() == [[1, 2]]
    assert load_defect_map(torch.from_numpy(M).to(dtype)).nonzero().tolist() == [[1, 2]]


@pytest.mark.parametrize("shape", [(8,), (8, 8, 1), (8, "a"), (0, 8), (8.5, 8), "ab", 8])
def test_a_shape_that_is_not_h_w_is_refused_naming_it(shape):
    """shape=(8,) raised IndexError: tuple index out of range."""
    with pytest.raises(ValueError, match=rf"shape = {re.escape(repr(shape))} must be \(H, W\): two whole numbers of "
                                         r"pixels >= 1, or None"):
        load_defect_map(M, shape=shape)
    for ok in ((8, 8), np.array([8, 8]), torch.Size([8, 8]), [8.0, 8]):
        assert load_defect_map(M, shape=ok).shape == (8, 8)


@pytest.mark.parametrize("frames, first", [
    (torch.full((8, 8), float("nan")), "nan"), (torch.full((8, 8), -1.0), "-1"), (torch.full((8, 8), 2.5), "2.5"),
    (torch.full((8, 8), 3e9), "3e+09"), (np.full((8, 8), np.inf), "inf"),
])
def test_flagged_frame_counts_that_are_not_whole_numbers_are_refused(tmp_path, frames, first):
    """NaN, negative or fractional counts were cast to int32 garbage with only a RuntimeWarning."""
    with pytest.raises(ValueError, match=rf"frames holds 64 value\(s\) that are not counts \(first: {re.escape(first)}\): "
                                         r"each must be a whole number in \[0, 2147483647\]"):
        save_defect_map(tmp_path / "d", torch.from_numpy(M), frames=frames)
    assert not (tmp_path / "d.npz").exists()
    path = save_defect_map(tmp_path / "d", torch.from_numpy(M), frames=torch.full((8, 8), 3.0))
    with np.load(path) as z:
        assert z["flagged_frames"].dtype == np.int32 and int(z["flagged_frames"].sum()) == 3 * 64
