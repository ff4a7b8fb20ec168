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
