"""A folder of image files as an indexable image source.

Every image source in :mod:`camhealth.data` has the same interface: ``len(source)``,
``source[i] -> (image 1×H×W float32 in [0, 1], id: str)`` and ``source.ids`` (all ids, in index order,
without reading any pixels — what :func:`camhealth.data.split_ids` needs).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Sequence, Union

import torch

from camhealth.data._common import check_index, natural_sort_key
from camhealth.data.io import IMAGE_EXTENSIONS, read_image

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

    The file list is fixed at construction and sorted in natural order of the path relative to ``root``
    (deterministic on every OS). The id of an image is that relative path in POSIX form
    (``"sub/img_0002.png"``), so every image is its own group for :func:`camhealth.data.split_ids`; if the
    folder holds frames of one video, pass a ``group_key`` to the split (see ``docs/data.md``) or use
    :class:`camhealth.data.FrameSequence`.

    Raises:
        FileNotFoundError: ``root`` does not exist.
        ValueError: no image with one of ``extensions`` was found (the message names the folder and the
            extensions).
    """

    def __init__(
        self, root: PathLike, recursive: bool = True, extensions: Sequence[str] = IMAGE_EXTENSIONS
    ) -> None:
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
        return read_image(self.paths[index]), self.ids[index]

    def __repr__(self) -> str:
        return f"{type(self).__name__}(root={str(self.root)!r}, n={len(self)})"
