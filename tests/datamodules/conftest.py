"""Tiny on-disk image folders for the DataModule tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image


def textured(size: int, seed: int, scale: float = 0.25, offset: float = 0.5) -> np.ndarray:
    """A smooth random texture in [0, 1] (no clipping), H = W = size."""
    rng = np.random.default_rng(seed)
    small = rng.random((size // 8 + 2, size // 8 + 2))
    img = np.kron(small, np.ones((8, 8)))[:size, :size]
    img = img + 0.3 * rng.random((size, size))
    img = (img - img.min()) / (img.max() - img.min())
    return offset + scale * (2 * img - 1)


def save_png(path: Path, arr: np.ndarray, bits: int = 8) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    dtype = np.uint8 if bits == 8 else np.uint16
    top = 255 if bits == 8 else 65535
    Image.fromarray(np.round(np.clip(arr, 0, 1) * top).astype(dtype)).save(path)
    return path


@pytest.fixture
def image_folder(tmp_path: Path) -> Path:
    """10 textured 8-bit 64×64 PNGs img00.png … img09.png (seed 0 split 0.3/0.3: val 4, test 1)."""
    root = tmp_path / "images"
    for i in range(10):
        save_png(root / f"img{i:02d}.png", textured(64, i))
    return root


SMALL = dict(patch_size=32, batch_size=4, patches_per_image=2, val_patches_per_image=2, val_fraction=0.3, test_fraction=0.3)
