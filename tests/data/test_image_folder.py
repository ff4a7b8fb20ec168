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


# ------------------------------------------------------------------ symbolic links
def _symlink(target, link):
    import os

    try:
        os.symlink(target, link)
    except (OSError, NotImplementedError):
        pytest.skip("this file system does not take symbolic links")


def test_symbolic_links_are_followed_each_file_once_and_what_is_skipped_is_named(tmp_path):
    """A file link that left the folder was read without a word and a linked sub-folder was dropped without a
    word. Links are followed (to files and folders, inside or outside the root); every file is listed once, a loop
    is skipped, a broken link named as an image is listed (reading it names it), and one warning names the links that
    lead outside, the broken link and everything skipped."""
    root, elsewhere = tmp_path / "root", tmp_path / "elsewhere"
    _save(root / "real" / "a.png", 1)
    _save(root / "real" / "b.png", 2)
    _save(elsewhere / "set" / "c.png", 3)
    _save(elsewhere / "d.png", 4)
    _symlink(elsewhere / "set", root / "setB")  # a linked sub-folder outside the root
    _symlink(elsewhere / "d.png", root / "outside.png")  # a file outside the root
    _symlink(root / "real", root / "alias")  # a second path to real/
    _symlink(root / "real" / "a.png", root / "latest.png")  # a second path to real/a.png
    _symlink(root, root / "real" / "up")  # a loop
    _symlink(tmp_path / "nowhere.png", root / "broken.png")
    with pytest.warns(UserWarning) as caught:
        src = ImageFolderSource(root)
    assert src.ids == ["broken.png", "outside.png", "real/a.png", "real/b.png", "setB/c.png"]
    assert src[4][0][0, 0, 0].item() == pytest.approx(3 / 255)
    with pytest.raises(FileNotFoundError, match=r"broken\.png: broken symbolic link \(it leads to .*nowhere\.png"):
        src[0]
    (message,) = [str(w.message) for w in caught]
    assert (f"image folder {root}: listed 1 entry named as an image that is not a regular file (reading it fails): "
            "broken.png (a broken symbolic link); ") in message
    assert "followed 2 link(s) that lead outside the folder: outside.png, setB/" in message
    assert "skipped 1 link(s) to this folder or a folder that holds it (a loop): real/up/" in message
    assert "skipped 2 second path(s) to a file or folder already listed: alias/, latest.png" in message
    assert "broken link(s)" not in message
    from camhealth.data import list_images

    with pytest.warns(UserWarning, match="outside.png"):
        assert [p.name for p in list_images(root, recursive=False)] == ["broken.png", "latest.png", "outside.png"]


def test_a_folder_of_only_a_linked_sub_folder_is_read_and_only_broken_links_are_named(tmp_path):
    """A folder holding only a symlinked sub-folder failed with 'no images found', not mentioning the link."""
    _save(tmp_path / "data" / "x.png", 7)
    root = tmp_path / "root"
    root.mkdir()
    _symlink(tmp_path / "data", root / "set")
    with pytest.warns(UserWarning, match="followed 1 link"):
        assert ImageFolderSource(root).ids == ["set/x.png"]
    empty = tmp_path / "empty"
    empty.mkdir()
    _symlink(tmp_path / "gone", empty / "frames")
    with pytest.raises(ValueError, match=r"no images found in folder .*empty.*; skipped 1 broken link\(s\): frames"):
        ImageFolderSource(empty)
