"""The committed street sample: consecutive gray frames of OpenCV's ``vtest.avi`` street clip.

The frames live in ``camhealth/data/street/`` as lossless 8-bit gray PNGs named
``vtest_<frame number>.png`` (frame numbers of the original clip); provenance, licence and the exact
extraction are in ``camhealth/data/street/README.md``. :func:`extract_street_frames` is the script that
made them (it needs the original ``vtest.avi``; nothing is downloaded at run time).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Union

import numpy as np
import torch

from camhealth.data._common import check_index, check_int
from camhealth.data.io import read_image, to_gray
from camhealth.data.video import FrameSequence

__all__ = ["STREET_DIR", "STREET_CLIP", "street_frame_paths", "StreetSampleSource", "street_sequence",
           "extract_street_frames"]

PathLike = Union[str, "os.PathLike[str]"]

#: Folder of the committed frames (package data).
STREET_DIR = Path(__file__).resolve().parent / "street"
#: Clip name used in ids: ``"street:vtest#000100"`` — the split group is ``"street:vtest"``.
STREET_CLIP = "street:vtest"

_FRAME_RE = re.compile(r"^vtest_(\d+)\.png$")


def street_frame_paths() -> list[Path]:
    """Paths of the committed street frames, in frame order."""
    if not STREET_DIR.is_dir():
        raise FileNotFoundError(
            f"street sample folder not found: {STREET_DIR} (is the package installed with its package data?)"
        )
    paths = [p for p in STREET_DIR.iterdir() if _FRAME_RE.match(p.name)]
    if not paths:
        raise FileNotFoundError(f"no street frames (vtest_<n>.png) found in {STREET_DIR}")
    return sorted(paths, key=lambda p: int(_FRAME_RE.match(p.name).group(1)))  # type: ignore[union-attr]


class StreetSampleSource(torch.utils.data.Dataset):
    """The street frames as individual images: ``source[i] -> (frame 1×H×W float32, id)``.

    Ids are ``"street:vtest#<original frame number, 6 digits>"``; all frames share the split group
    ``"street:vtest"`` so temporally correlated frames never straddle train/val/test.

    Args:
        stride: keep every ``stride``-th committed frame (>= 1).
        max_frames: keep at most this many (``None``: all).
    """

    def __init__(self, stride: int = 1, max_frames: int | None = None) -> None:
        stride = check_int(stride, "stride", 1)
        max_frames = check_int(max_frames, "max_frames", 1, allow_none=True)
        paths = street_frame_paths()[::stride]
        self.paths = paths if max_frames is None else paths[:max_frames]
        self.frame_numbers = [int(_FRAME_RE.match(p.name).group(1)) for p in self.paths]  # type: ignore[union-attr]
        self.ids = [f"{STREET_CLIP}#{n:06d}" for n in self.frame_numbers]

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, str]:
        i = check_index(index, len(self), "StreetSampleSource")
        return read_image(self.paths[i]), self.ids[i]

    def __repr__(self) -> str:
        return f"{type(self).__name__}(n={len(self)}, frames {self.frame_numbers[0]}..{self.frame_numbers[-1]})"


def street_sequence(stride: int = 1, max_frames: int | None = None) -> FrameSequence:
    """The committed street frames as a :class:`FrameSequence` (index = position in the sample, 0-based)."""
    street_frame_paths()  # clear error if the package data are missing
    return FrameSequence(STREET_DIR, stride=stride, max_frames=max_frames, extensions=(".png",))


def extract_street_frames(video: PathLike, out_dir: PathLike, first: int = 100, count: int = 50) -> list[Path]:
    """Re-create the street sample from ``vtest.avi`` (maintenance script, not used at run time).

    Decodes the clip sequentially with OpenCV, keeps frames ``first .. first + count − 1``, converts BGR to
    gray with BT.601 luma in floating point (:func:`camhealth.data.to_gray`), rounds to the nearest 8-bit
    DN and writes ``vtest_<frame>.png`` (lossless, Pillow ``optimize=True``).
    """
    import cv2
    from PIL import Image

    first = check_int(first, "first", 0)
    count = check_int(count, "count", 1)
    video, out_dir = Path(video), Path(out_dir)
    if not video.is_file():
        raise FileNotFoundError(f"video file not found: {video}")
    cap = cv2.VideoCapture(str(video))
    if not cap.isOpened():
        raise ValueError(f"cannot open video {video}")
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    try:
        idx = 0
        while idx < first + count:
            ok, frame = cap.read()
            if not ok:
                raise ValueError(f"{video} ended at frame {idx}, before frame {first + count - 1}")
            if idx >= first:
                rgb = frame[..., ::-1].astype(np.float64)
                gray = np.clip(np.rint(to_gray(rgb)), 0, 255).astype(np.uint8)
                path = out_dir / f"vtest_{idx:04d}.png"
                Image.fromarray(gray).save(path, optimize=True)
                written.append(path)
            idx += 1
    finally:
        cap.release()
    return written
