"""ImageFolderSource: deterministic listing, ids, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from camhealth.data import ImageFolderSource, natural_sort_key


def _save(path, value, size=(4, 5)):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full(size, value, np.uint8)).save(path)


def test_listing_is_sorted_recursive_and_ids_are_relative_paths(tmp_path):
    _save(tmp_path / "b" / "img10.png", 10)
    _save(tmp_path / "b" / "img2.png", 2)
    _save(tmp_path / "a.jpg", 1)
    (tmp_path / "notes.txt").write_text("not an image")
    _save(tmp_path / ".hidden" / "x.png", 99)
    src = ImageFolderSource(tmp_path)
    assert src.ids == ["a.jpg", "b/img2.png", "b/img10.png"]
    assert len(src) == 3
    img, image_id = src[2]
    assert image_id == "b/img10.png" and img.shape == (1, 4, 5) and img.dtype == torch.float32
    assert img[0, 0, 0].item() == pytest.approx(10 / 255)
    assert src[-1][1] == "b/img10.png"
    with pytest.raises(IndexError):
        src[3]
    assert ImageFolderSource(tmp_path, recursive=False).ids == ["a.jpg"]
    assert ImageFolderSource(tmp_path, extensions=["PNG"]).ids == ["b/img2.png", "b/img10.png"]


def test_missing_folder_names_it(tmp_path):
    with pytest.raises(FileNotFoundError, match="no_such_dir"):
        ImageFolderSource(tmp_path / "no_such_dir")


def test_empty_folder_names_folder_and_extensions(tmp_path):
    (tmp_path / "readme.txt").write_text("x")
    with pytest.raises(ValueError) as e:
        ImageFolderSource(tmp_path)
    msg = str(e.value)
    assert str(tmp_path) in msg and ".png" in msg and ".jpg" in msg


def test_bad_extension_argument():
    with pytest.raises(ValueError, match="allowed"):
        ImageFolderSource(".", extensions=[".gif"])


def test_natural_sort_key():
    names = ["frame10.png", "frame2.png", "Frame1.png", "frame02.png", "frame1.png"]
    assert sorted(names, key=natural_sort_key)[:2] == ["Frame1.png", "frame1.png"]
    assert sorted(names, key=natural_sort_key)[-1] == "frame10.png"


def _save16(path, top):
    arr = np.full((4, 5), 500, np.uint16)  # DN 500, and the file's largest value in one pixel
    arr[0, 0] = top
    Image.fromarray(arr).save(path)


def test_bit_depth_reads_every_file_at_one_scale(tmp_path):
    """A 12-bit camera's dark and bright frames in 16-bit PNGs without sBIT: bit_depth=12 reads DN 500 as 500/4095 in
    both; "auto" guesses per file and its warning names the argument to pass."""
    import warnings

    _save16(tmp_path / "dark.png", 1000)
    _save16(tmp_path / "bright.png", 4000)
    src = ImageFolderSource(tmp_path, bit_depth=12)
    assert [src[i][0][0, 1, 1].item() for i in range(2)] == [pytest.approx(500 / 4095)] * 2
    assert "bit_depth=12" in repr(src)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        dark = ImageFolderSource(tmp_path)[src.ids.index("dark.png")][0]
    assert dark[0, 1, 1].item() == pytest.approx(500 / 1023)
    assert [str(w.message) for w in caught] == [
        f"{tmp_path / 'dark.png'}: 16-bit file read as 10-bit data (÷1023, guessed from the largest value 1000); pass "
        "bit_depth=16 (ImageFolderSource, build_source; --bit-depth 16 on the command line) to scale by 65535, or the "
        "camera's bit depth"]
    with pytest.raises(ValueError, match=r"holds values up to 4000 \(more than 1023\)"):
        ImageFolderSource(tmp_path, bit_depth=10)[src.ids.index("bright.png")]
    with pytest.raises(ValueError, match="bit_depth = 20 must be 'auto' or an integer"):
        ImageFolderSource(tmp_path, bit_depth=20)
