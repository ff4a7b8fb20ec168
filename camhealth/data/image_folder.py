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


class _Listing:
    """The image files under a folder and what the listing left out (:func:`_scan`)."""

    def __init__(self) -> None:
        #: (relative POSIX path, path, real path, the file is a link, a folder on its path is a link)
        self.files: list[tuple[str, Path, str, bool, bool]] = []
        self.outside: list[str] = []  # links whose target lies outside the root (followed)
        self.repeated: list[str] = []  # second paths to a file or folder already listed (skipped)
        self.loops: list[str] = []  # links to the folder itself or a folder that holds it (skipped)
        self.broken: list[str] = []  # links without an extension to nothing (skipped; perhaps a folder's)
        self.unreadable: list[str] = []  # folders that cannot be listed (skipped)
        #: entries named as images that are no regular file (listed: reading them raises): (relative path, what it is)
        self.not_files: list[tuple[str, str]] = []

    def notes(self) -> str:
        """The links and folders named for the user, or ``""``."""
        def some(names: list[str]) -> str:
            return ", ".join(names[:5]) + (f" … ({len(names)} in all)" if len(names) > 5 else "")

        parts = []
        if self.not_files:
            one = len(self.not_files) == 1
            parts.append(f"listed {len(self.not_files)} "
                         + ("entry named as an image that is not a regular file (reading it fails): " if one else
                            "entries named as images that are not regular files (reading them fails): ")
                         + some([f"{rel} ({what})" for rel, what in self.not_files]))
        if self.outside:
            parts.append(f"followed {len(self.outside)} link(s) that lead outside the folder: {some(self.outside)}")
        if self.loops:
            parts.append(f"skipped {len(self.loops)} link(s) to this folder or a folder that holds it (a loop): "
                         f"{some(self.loops)}")
        if self.repeated:
            parts.append(f"skipped {len(self.repeated)} second path(s) to a file or folder already listed: "
                         f"{some(self.repeated)}")
        if self.broken:
            parts.append(f"skipped {len(self.broken)} broken link(s): {some(self.broken)}")
        if self.unreadable:
            parts.append(f"skipped {len(self.unreadable)} folder(s) that cannot be listed: {some(self.unreadable)}")
        return "; ".join(parts)


def _scan(root: Path, recursive: bool, exts: tuple[str, ...]) -> _Listing:
    """Walk ``root`` (see :func:`list_images` for the rules): the folders themselves first, then the folders that links
    lead to, each real folder once, so a file keeps its path without links where it has one."""
    out = _Listing()
    root_real = os.path.realpath(root)
    walked = {root_real}
    pending: list[tuple[Path, str, bool]] = [(root, "", False)]  # (folder, its relative path + "/", via a link)
    links: list[tuple[Path, str]] = []  # links to folders, walked after every plain folder

    def outside(real: str) -> bool:
        return not (real == root_real or real.startswith(root_real.rstrip(os.sep) + os.sep))

    while pending or links:
        if pending:
            folder, prefix, via_link = pending.pop()
        else:
            link, rel = links.pop(0)
            real = os.path.realpath(link)
            if real == root_real or root_real.startswith(real.rstrip(os.sep) + os.sep):
                out.loops.append(rel + "/")
                continue
            if real in walked:
                out.repeated.append(rel + "/")
                continue
            walked.add(real)
            if outside(real):
                out.outside.append(rel + "/")
            folder, prefix, via_link = link, rel + "/", True
        try:
            entries = sorted(os.scandir(folder), key=lambda e: natural_sort_key(e.name))
        except OSError:
            out.unreadable.append(prefix or ".")
            continue
        subfolders = []
        for entry in entries:
            if entry.name.startswith("."):
                continue
            rel = prefix + entry.name
            path = folder / entry.name
            try:
                is_link = entry.is_symlink()  # (does not follow the link)
            except OSError:
                is_link = False
            try:
                is_dir, is_file = entry.is_dir(), entry.is_file()  # (both follow links)
            except OSError:  # e.g. a link that leads to itself (ELOOP): a link to nothing, see below
                is_dir, is_file = False, False
            image_name = os.path.splitext(entry.name)[1].lower() in exts
            if is_dir and not recursive and image_name:  # e.g. a folder frame_0003.png among a sequence's frames
                out.files.append((rel, path, os.path.realpath(path), is_link, via_link))
                out.not_files.append((rel, "a folder"))
            elif is_dir:
                if not recursive:
                    continue
                if is_link:
                    links.append((path, rel))
                else:
                    real = os.path.realpath(path)
                    if real in walked:  # (reached again inside a linked folder)
                        out.repeated.append(rel + "/")
                    else:
                        walked.add(real)
                        subfolders.append((path, rel + "/", via_link))
            elif is_file:
                if not image_name:
                    continue
                real = os.path.realpath(path)
                if is_link and outside(real):
                    out.outside.append(rel)
                out.files.append((rel, path, real, is_link, via_link))
            elif image_name:  # a link to nothing, a FIFO, a socket or a device (never opened here): listed, so that
                # reading it names the entry and why instead of the frame vanishing from a sequence
                if is_link and not os.path.exists(path):  # (a link that leads back to itself too)
                    # one entry per link: its own folder's real path and its name (its target does not exist)
                    out.files.append((rel, path, os.path.join(os.path.realpath(folder), entry.name), False, via_link))
                    out.not_files.append((rel, "a broken symbolic link"))
                else:
                    real = os.path.realpath(path)
                    if is_link and outside(real):
                        out.outside.append(rel)
                    out.files.append((rel, path, real, is_link, via_link))
                    out.not_files.append((rel, "not a regular file: a FIFO, socket or device"))
            elif is_link and not os.path.splitext(entry.name)[1]:  # (a folder's link, perhaps)
                out.broken.append(rel)
        pending.extend(reversed(subfolders))
    # each file once: where several paths lead to one file, a path that is not itself a link wins, then one through no
    # linked folder, then the first in natural order
    best: dict[str, tuple[str, Path, str, bool, bool]] = {}
    for item in sorted(out.files, key=lambda f: (f[3], f[4], natural_sort_key(f[0]))):
        if item[2] in best:
            out.repeated.append(item[0])
        else:
            best[item[2]] = item
    out.files = sorted(best.values(), key=lambda f: natural_sort_key(f[0]))
    listed = {item[0] for item in out.files}
    out.not_files = sorted((n for n in out.not_files if n[0] in listed), key=lambda n: natural_sort_key(n[0]))
    return out


def list_images(root: PathLike, recursive: bool = True, extensions: Sequence[str] = IMAGE_EXTENSIONS) -> list[Path]:
    """Image files under ``root`` (hidden files and folders skipped), in natural order of their relative path.

    Symbolic links are followed, to files and (with ``recursive``) to folders, also where they lead outside ``root``;
    each file and folder is listed once: a second path to one already listed (a link to it, or to a folder holding
    it) is skipped, keeping a path that is not itself a link, then one through no linked folder. A link to ``root``
    or to a folder that holds it (a loop) and a link without an extension to nothing (also one that leads back to
    itself, directly or through other links) are skipped. An entry named with one of ``extensions`` that is no
    regular file — a link to nothing (``frame_0003.png`` whose target is gone, or a loop of links), a FIFO, a socket,
    a device or, without ``recursive``, a folder — is listed (never opened here): reading it raises an error naming
    the path and why (:func:`camhealth.data.read_image`), so that a frame does not vanish from a sequence. Links that
    lead outside ``root``, such entries and everything skipped but hidden files are named in one ``UserWarning``.
    """
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"image folder not found: {root}")
    if not root.is_dir():
        raise NotADirectoryError(f"not a folder: {root}")
    listing = _scan(root, bool(recursive), _normalise_extensions(extensions))
    notes = listing.notes()
    if notes:
        warnings.warn(f"image folder {root}: {notes}", UserWarning, stacklevel=2)
    return [item[1] for item in listing.files]


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
    (deterministic on every OS); symbolic links to files and folders are followed, each file listed once
    (:func:`list_images`); an entry named as an image that is no regular file (a link to nothing, a FIFO, a device) is
    listed too, and reading it raises an error naming it and why. The id of an image is that relative path in POSIX form
    (``"sub/img_0002.png"``), so every image is its own group for :func:`camhealth.data.split_ids`; if the
    folder holds frames of one video, pass a ``group_key`` to the split (see ``docs/data.md``) or use
    :class:`camhealth.data.FrameSequence`.

    Raises:
        FileNotFoundError: ``root`` does not exist.
        ValueError: no image with one of ``extensions`` was found (the message names the folder, the
            extensions and any links skipped); ``bit_depth`` is neither ``"auto"`` nor an integer in [1, 16].
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
        if not self.root.exists():
            raise FileNotFoundError(f"image folder not found: {self.root}")
        if not self.root.is_dir():
            raise NotADirectoryError(f"not a folder: {self.root}")
        listing = _scan(self.root, self.recursive, self.extensions)
        notes = listing.notes()
        if not listing.files:
            where = "or its sub-folders " if self.recursive else ""
            raise ValueError(
                f"no images found in folder {self.root} {where}(looked for extensions: {', '.join(self.extensions)})"
                + (f"; {notes}" if notes else "")
            )
        if notes:
            warnings.warn(f"image folder {self.root}: {notes}", UserWarning, stacklevel=2)
        self.paths = [item[1] for item in listing.files]
        self.ids = [item[0] for item in listing.files]

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
