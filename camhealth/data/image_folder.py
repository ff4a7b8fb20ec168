"""A folder of image files as an indexable image source.

Every image source in :mod:`camhealth.data` has the same interface: ``len(source)``,
``source[i] -> (image 1×H×W float32 in [0, 1], id: str)`` and ``source.ids`` (all ids, in index order,
without reading any pixels — what :func:`camhealth.data.split_ids` needs).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Iterable, Sequence, Union

import torch

from camhealth.data._common import check_index, natural_sort_key
from camhealth.data.io import IMAGE_EXTENSIONS, _check_bit_depth, read_image_scaled

__all__ = ["natural_sort_key", "list_images", "ImageFolderSource"]

PathLike = Union[str, "os.PathLike[str]"]


def _normalise_extensions(extensions: Iterable[str]) -> tuple[str, ...]:
    if isinstance(extensions, str):
        extensions = [extensions]
    exts = []
    for e in extensions:
        if not isinstance(e, str) or not e.strip("."):
            raise ValueError(f"extensions must be non-empty strings like '.png', got {e!r}")
        e = e.lower()
        exts.append(e if e.startswith(".") else "." + e)
    if not exts:
        raise ValueError("extensions must not be empty")
    unsupported = [e for e in exts if e not in IMAGE_EXTENSIONS]
    if unsupported:
        raise ValueError(f"unsupported image extension(s) {unsupported}; allowed: {', '.join(IMAGE_EXTENSIONS)}")
    return tuple(dict.fromkeys(exts))


def list_images(root: PathLike, recursive: bool = True, extensions: Sequence[str] = IMAGE_EXTENSIONS) -> list[Path]:
    """Image files under ``root`` (hidden files skipped), in natural order of their relative path."""
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"image folder not found: {root}")
    if not root.is_dir():
        raise NotADirectoryError(f"not a folder: {root}")
    exts = _normalise_extensions(extensions)
    it = root.rglob("*") if recursive else root.iterdir()
    files = [
        p
        for p in it
        if p.suffix.lower() in exts
        and not any(part.startswith(".") for part in p.relative_to(root).parts)
        and p.is_file()
    ]
    files.sort(key=lambda p: natural_sort_key(p.relative_to(root).as_posix()))
    return files


class ImageFolderSource(torch.utils.data.Dataset):
    """All image files in a folder (and, by default, its sub-folders).

    Args:
        root: the folder.
        recursive: also look in sub-folders.
        extensions: file extensions to include (case-insensitive), a subset of
            :data:`camhealth.data.IMAGE_EXTENSIONS`.
        bit_depth: significant bits of the folder's files, 1…16 (every file is read as DN / (2^bit_depth − 1); a file
            holding a larger value, or 8-bit data under a bit_depth above 8, raises when it is read), or ``"auto"``
            (default): each file on its own as :func:`camhealth.data.read_image` reads it — the PNG's ``sBIT`` chunk,
            else a guess from the file's largest value, with a ``UserWarning`` naming this argument. Give the camera's
            depth (e.g. 12) for 16-bit files without an ``sBIT`` chunk: a guess reads a dark frame brighter than a
            bright one of the same camera.

    The file list is fixed at construction and sorted in natural order of the path relative to ``root``
    (deterministic on every OS). The id of an image is that relative path in POSIX form
    (``"sub/img_0002.png"``), so every image is its own group for :func:`camhealth.data.split_ids`; if the
    folder holds frames of one video, pass a ``group_key`` to the split (see ``docs/data.md``) or use
    :class:`camhealth.data.FrameSequence`.

    Raises:
        FileNotFoundError: ``root`` does not exist.
        ValueError: no image with one of ``extensions`` was found (the message names the folder and the
            extensions); ``bit_depth`` is neither ``"auto"`` nor an integer in [1, 16].
    """

    def __init__(
        self,
        root: PathLike,
        recursive: bool = True,
        extensions: Sequence[str] = IMAGE_EXTENSIONS,
        bit_depth: int | str = "auto",
    ) -> None:
        self.bit_depth = _check_bit_depth(bit_depth)
        self.root = Path(root)
        self.recursive = bool(recursive)
        self.extensions = _normalise_extensions(extensions)
        self.paths = list_images(self.root, self.recursive, self.extensions)
        if not self.paths:
            where = "or its sub-folders " if self.recursive else ""
            raise ValueError(
                f"no images found in folder {self.root} {where}(looked for extensions: {', '.join(self.extensions)})"
            )
        self.ids = [p.relative_to(self.root).as_posix() for p in self.paths]

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, str]:
        index = check_index(index, len(self), f"ImageFolderSource({self.root})")
        image, scaling = read_image_scaled(self.paths[index], self.bit_depth)
        if scaling.source == "largest value":
            warnings.warn(f"{self.paths[index]}: {scaling.describe()}; pass bit_depth=16 (ImageFolderSource, build_source; "
                          "--bit-depth 16 on the command line) to scale by 65535, or the camera's bit depth",
                          UserWarning, stacklevel=2)
        return image, self.ids[index]

    def __repr__(self) -> str:
        depth = "" if self.bit_depth == "auto" else f", bit_depth={self.bit_depth}"
        return f"{type(self).__name__}(root={str(self.root)!r}, n={len(self)}{depth})"
