"""Ordered frame sequences: a folder of frame images or a video file, read as gray frames.

``FrameSequence`` iterates ``(frame 1×H×W float32 in [0, 1], index)`` where ``index`` is the frame's
position in the original sequence (file number in the natural sort order of the folder, or frame number
in the video), before ``start``/``stride``/``max_frames`` are applied. Colour video frames are converted
to gray with the same BT.601 luma weights as :func:`camhealth.data.to_gray`.

Video decoding uses OpenCV (``cv2.VideoCapture``, package ``opencv-python-headless``), imported only when
a video is opened, with one decoder thread so that each frame comes out of the read that decoded it. A frame
the decoder reports damage in while reading (FFmpeg's error log on the process's stderr: a truncated last frame,
a corrupt packet, concealed macroblocks) is only partly decoded: :meth:`FrameSequence.frames` yields it with the
decoder's message instead of pixels, iteration skips it with a warning, ``seq[k]`` raises ``ValueError``. (FFmpeg
must log errors — OpenCV's default; ``OPENCV_FFMPEG_LOGLEVEL`` below 16 hides them.) A frame that does not decode at
all is treated the same way where later frames decode (iteration goes on past it), and ``seq[k]`` raises
``ValueError`` naming the file and the frame where such a frame lies before frame k on the way to it (its position is
then not known). A video whose last frames are missing (a file cut short) has the length of the frames that decode,
with a warning naming the file when it is opened (:class:`FrameSequence`).
"""

from __future__ import annotations

import math
import os
import re
import sys
import tempfile
import warnings
from pathlib import Path
from typing import Iterator, Sequence, Union

import numpy as np
import torch

from camhealth.data._common import check_index, check_int
from camhealth.data.image_folder import _normalise_extensions, list_images
from camhealth.data.io import IMAGE_EXTENSIONS, first_frame_bits, read_image, read_image_scaled, read_sequence_frame, to_gray

__all__ = ["VIDEO_EXTENSIONS", "FrameSequence", "FrameSequenceSource"]

PathLike = Union[str, "os.PathLike[str]"]

# Video handles inherited through fork() (DataLoader workers) are unusable in the child and releasing them
# there can hang; they are parked here, never touched again, and a fresh handle is opened per process.
_INHERITED_CAPS: list = []

#: File extensions :class:`FrameSequence` treats as video files (case-insensitive).
VIDEO_EXTENSIONS = (".avi", ".mp4", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".wmv", ".webm", ".ogv", ".flv")


def _import_cv2():
    try:
        import cv2
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(
            "reading video files needs OpenCV: pip install 'opencv-python-headless<5'"
        ) from e
    return cv2


#: A line of FFmpeg's log: ``[mpeg4 @ 0x55d0…] ac-tex damaged at 2 6``.
_FFMPEG_LINE = re.compile(rb"^\[[A-Za-z0-9_,]+ @ 0x[0-9a-fA-F]+\] ?(.*?)\s*$", re.M)


class _DecoderLog:
    """What FFmpeg, inside OpenCV, writes to the process's stderr (file descriptor 2) during one ``read``: its
    error lines are returned, anything else is passed on to stderr."""

    def __init__(self) -> None:
        self._file = tempfile.TemporaryFile()

    def read(self, cap) -> tuple[bool, np.ndarray | None, str | None]:
        (ok, frame), message = self.call(cap.read)
        return ok, frame, message

    def call(self, fn):
        """``(fn(), FFmpeg's error lines while it ran or None)``."""
        try:
            sys.stderr.flush()
            saved = os.dup(2)
        except (OSError, ValueError):  # no usable stderr: run without the check
            return fn(), None
        os.dup2(self._file.fileno(), 2)
        try:
            result = fn()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        self._file.seek(0)
        text = self._file.read()
        self._file.seek(0)
        self._file.truncate()
        if not text:
            return result, None
        errors = [m.group(1).decode(errors="replace") for m in _FFMPEG_LINE.finditer(text)]
        rest = _FFMPEG_LINE.sub(b"", text).strip()
        if rest:
            os.write(2, rest + b"\n")
        return result, ("; ".join(e for e in errors if e) or None) if errors else None

    def close(self) -> None:
        self._file.close()


def _damaged(idx: int, path: Path, message: str) -> str:
    return f"frame {idx} of video {path} was only partly decoded (decoder: {message[:160]}); not used"


def _undecodable(idx: int, path: Path, message: str | None) -> str:
    said = f" (decoder: {message[:160]})" if message else ""
    return (f"frame {idx} of video {path} does not decode{said}; not used (the frames after it are numbered in the "
            "order they decode, lower than written where the damage took more than one frame)")


#: Reads or grabs in a row that return no frame before iteration takes the video to have ended (fewer: damaged
#: frames, skipped with a warning once a later frame decodes).
_MAX_FAILED_IN_A_ROW = 16


def _bgr_to_tensor(frame: np.ndarray) -> torch.Tensor:
    """OpenCV frame (H×W or H×W×3 BGR / H×W×4 BGRA, 8 or 16 bit) → gray float32 1×H×W in [0, 1]."""
    if frame.ndim == 3 and frame.shape[-1] >= 3:
        frame = np.concatenate([frame[..., 2::-1], frame[..., 3:]], axis=-1)  # → RGB(A)
    scale = float(np.iinfo(frame.dtype).max) if np.issubdtype(frame.dtype, np.integer) else 1.0
    gray = to_gray(frame.astype(np.float64) / scale)
    return torch.from_numpy(np.ascontiguousarray(gray, dtype=np.float32)).clamp_(0.0, 1.0).unsqueeze(0)


class FrameSequence:
    """An ordered sequence of gray frames from a folder of images or from a video file.

    Args:
        path: a folder of frame images (non-recursive; natural sort order of the file names, so
            ``frame2.png`` comes before ``frame10.png``) or a video file (one of :data:`VIDEO_EXTENSIONS`).
        stride: keep every ``stride``-th frame (>= 1).
        max_frames: stop after this many kept frames (``None``: all).
        start: index of the first frame to consider (>= 0).
        extensions: image extensions for a folder of frames.

    Iterating yields ``(frame, index)`` with ``frame`` a float32 tensor ``1×H×W`` in [0, 1] and ``index`` the
    original frame index. ``len()`` is exact for a folder; for a video it comes from the container's frame
    count (``CAP_PROP_FRAME_COUNT``), checked when the video is opened by decoding its last frame: where that
    frame cannot be decoded (a truncated file), the frames that can be are counted, the length is that count and a
    ``UserWarning`` names the file and both counts (so ``len()``, iteration and ``seq[k]`` agree); should the
    decoder still stop before the length, iteration ends with a ``UserWarning`` naming the file and the frame. If
    the container does not report a count, ``len()`` raises ``TypeError`` and :attr:`length` is ``None``.
    ``seq[k]`` returns the ``k``-th kept frame as ``(frame, index)`` (for a video by seeking, which is slower
    than iterating), or raises ``ValueError`` naming the file and the frame where it cannot: the frame is damaged,
    or a frame before it does not decode, so that its position is not known (a seek that does not land on it is
    checked and redone by counting from the first frame). Iteration skips a damaged frame or one that does not
    decode with a ``UserWarning`` naming it and goes on (:meth:`frames`).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: a folder without frame images, an unsupported file type, or a video OpenCV cannot open
            or decode (the message names the file).
    """

    def __init__(
        self,
        path: PathLike,
        stride: int = 1,
        max_frames: int | None = None,
        start: int = 0,
        extensions: Sequence[str] = IMAGE_EXTENSIONS,
        bit_depth: int | str = "auto",
    ) -> None:
        from camhealth.data.io import _check_bit_depth

        self.bit_depth = _check_bit_depth(bit_depth)
        self.path = Path(path)
        self.stride = check_int(stride, "stride", 1)
        self.max_frames = check_int(max_frames, "max_frames", 1, allow_none=True)
        self.start = check_int(start, "start", 0)
        self._cap = None
        self._cap_pid = -1
        self._cap_next = -1
        #: a damaged frame in a video that lost frames (its container declares more than decode): the frames after it
        #: have no known position (``seq[k]`` refuses them); ``None`` where no such frame was found
        self._unknown_after: int | None = None
        if not self.path.exists():
            raise FileNotFoundError(f"frame folder or video file not found: {self.path}")
        if self.path.is_dir():
            self.kind = "folder"
            exts = _normalise_extensions(extensions)
            self.frame_paths: list[Path] | None = list_images(self.path, recursive=False, extensions=exts)
            if not self.frame_paths:
                raise ValueError(
                    f"no frame images found in folder {self.path} (looked for extensions: {', '.join(exts)})"
                )
            self.total_frames: int | None = len(self.frame_paths)
        else:
            if self.path.suffix.lower() not in VIDEO_EXTENSIONS:
                raise ValueError(
                    f"cannot read {self.path} as a frame sequence: expected a folder of frames or a video file "
                    f"with one of the extensions {', '.join(VIDEO_EXTENSIONS)}"
                )
            self.kind = "video"
            self.frame_paths = None
            self.total_frames = self._probe_video()

    # -- video helpers ---------------------------------------------------------------------------
    def _open(self):
        cv2 = _import_cv2()
        # one decoder thread: with frame threading a decoder error is logged while reading a later frame
        cap = cv2.VideoCapture(str(self.path), cv2.CAP_ANY, [cv2.CAP_PROP_N_THREADS, 1])
        if not cap.isOpened():
            cap.release()
            raise ValueError(f"cannot open video {self.path}: OpenCV could not open it (corrupt or unsupported codec)")
        return cap

    def _probe_video(self) -> int | None:
        """The video's frame count: the container's, checked by decoding its last frame; where that frame cannot be
        read (a truncated file), the frames that can be, counted, with a warning (``len()`` is what iteration gives)."""
        cv2 = _import_cv2()
        cap = self._open()
        log = _DecoderLog()
        try:
            n = cap.get(cv2.CAP_PROP_FRAME_COUNT)
            ok, frame, _ = log.read(cap)
            if not ok or frame is None:
                raise ValueError(f"cannot read video {self.path}: no frame could be decoded (corrupt or empty file)")
            self.frame_shape = tuple(frame.shape[:2])
            self.fps = float(cap.get(cv2.CAP_PROP_FPS)) or None
            if not math.isfinite(n) or n < 1:
                return None
            n = int(round(n))
            if n > 1:
                log.call(lambda: cap.set(cv2.CAP_PROP_POS_FRAMES, n - 1))
                ok, frame, _ = log.read(cap)
                if not ok or frame is None:  # the last frame is missing: count the frames there are
                    cap.release()
                    cap = self._open()
                    counted = position = failed = 0  # (past a frame that does not decode, as iteration goes on)
                    first_bad = None  # the first frame the decoder reports damage in or cannot decode
                    while failed < _MAX_FAILED_IN_A_ROW:
                        ok, message = log.call(cap.grab)
                        if ok:
                            counted, failed = position + 1, 0
                        else:
                            failed += 1
                        if (not ok or message is not None) and first_bad is None:
                            first_bad = position
                        position += 1
                    if counted < n:
                        lost = first_bad is not None and first_bad < counted - 1  # frames lost in the middle
                        if lost:  # the frames after the damage may be numbered lower than written
                            self._unknown_after = first_bad
                        warnings.warn(
                            f"video {self.path}: its container declares {n} frames, but only frames 0…{counted - 1} "
                            f"({counted}) can be decoded (a truncated or damaged file?); its length is {counted}"
                            + (f"; frame {first_bad} is damaged, so the frames after it may be numbered lower than "
                               "written (random access refuses them)" if lost else ""),
                            UserWarning, stacklevel=3)
                        n = max(counted, 1)
            return n
        finally:
            cap.release()
            log.close()

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_cap"] = None  # cv2.VideoCapture cannot be pickled (DataLoader workers reopen it)
        state["_cap_pid"] = -1
        state["_cap_next"] = -1
        return state

    def close(self) -> None:
        """Release the video handle kept open by random access (``seq[k]``); iteration opens its own."""
        if self._cap is not None:
            if self._cap_pid == os.getpid():
                self._cap.release()
            else:
                _INHERITED_CAPS.append(self._cap)
            self._cap = None
            self._cap_next = -1

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass

    # -- sizes -----------------------------------------------------------------------------------
    @property
    def length(self) -> int | None:
        """Number of frames iteration yields (``None`` if the video does not report its frame count)."""
        if self.total_frames is None:
            return None
        avail = max(0, self.total_frames - self.start)
        n = -(-avail // self.stride)
        return n if self.max_frames is None else min(n, self.max_frames)

    def __len__(self) -> int:
        n = self.length
        if n is None:
            raise TypeError(f"the frame count of video {self.path} is unknown; iterate instead")
        return n

    def frame_index(self, k: int) -> int:
        """Original index of the ``k``-th kept frame."""
        return self.start + k * self.stride

    # -- access ----------------------------------------------------------------------------------
    def __iter__(self) -> Iterator[tuple[torch.Tensor, int]]:
        """``(frame, index)`` of every kept frame; a video frame the decoder reports damaged is skipped with a
        ``UserWarning`` naming it (:meth:`frames` yields it with the message instead)."""
        for frame, idx, error in self.frames():
            if error is not None:
                warnings.warn(error, UserWarning, stacklevel=2)
                continue
            yield frame, idx

    def frames(self) -> Iterator[tuple[torch.Tensor | None, int, str | None]]:
        """``(frame, index, None)`` for every kept frame, or ``(None, index, message)`` for a video frame the
        decoder reported damage in while reading it (partly decoded: concealed or missing blocks) or that does not
        decode at all while later frames do. Iteration goes on after such a frame; only
        ``_MAX_FAILED_IN_A_ROW`` (16) frames in a row that do not decode end it (with a ``UserWarning`` when that is
        before the length). Frames are numbered in the order the decoder delivers them, a frame that does not decode
        counting as one: where damage takes away more than one frame's data in one failed read, the frames after it
        are numbered lower than they were written (``seq[k]`` refuses to count past such a frame)."""
        limit = self.length if self.length is not None else self.max_frames
        if self.kind == "folder":
            assert self.frame_paths is not None
            for k in range(limit or 0):
                idx = self.frame_index(k)
                frame, _ = read_sequence_frame(self.frame_paths[idx], self.bit_depth, self._first_bits())
                yield frame, idx, None
            return
        def ended(k: int, at: int) -> None:  # fewer frames than the (checked) length: damage the probe did not see
            if self.length is not None and k < self.length:
                warnings.warn(f"video {self.path} ended at frame {at}: {k} of the {self.length} frames its length "
                              "promised were read (a truncated or damaged file?)", UserWarning, stacklevel=4)

        cap = self._open()
        log = _DecoderLog()
        # a read or grab that returns no frame is a damaged frame when a later one decodes (the kept ones among them
        # are yielded with a message then); _MAX_FAILED_IN_A_ROW of them in a row end the video
        failed = 0  # reads and grabs in a row that returned no frame
        run_start: tuple[int, int] | None = None  # (kept frames before it, frame index) of the first of them
        pending: list[tuple[int, str | None]] = []  # kept frames among them: (index, decoder message)
        try:
            for j in range(self.start):  # skip to start without converting
                if cap.grab():
                    failed, run_start = 0, None
                    continue
                failed += 1
                run_start = run_start or (0, j)
                if failed >= _MAX_FAILED_IN_A_ROW:
                    ended(*run_start)
                    return
            k = 0
            while limit is None or k < limit:
                ok, frame, message = log.read(cap)
                idx = self.frame_index(k)
                if not ok or frame is None:
                    failed += 1
                    run_start = run_start or (k, idx)
                    pending.append((idx, message))
                    if failed >= _MAX_FAILED_IN_A_ROW:
                        break
                else:
                    for p_idx, p_message in pending:  # a later frame decodes: those were damaged, not the end
                        yield None, p_idx, _undecodable(p_idx, self.path, p_message)
                    failed, run_start, pending = 0, None, []
                    if message is not None:
                        yield None, idx, _damaged(idx, self.path, message)
                    else:
                        yield _bgr_to_tensor(frame), idx, None
                k += 1
                if limit is not None and k >= limit:
                    break
                for j in range(self.stride - 1):
                    if cap.grab():
                        for p_idx, p_message in pending:
                            yield None, p_idx, _undecodable(p_idx, self.path, p_message)
                        failed, run_start, pending = 0, None, []
                        continue
                    failed += 1
                    run_start = run_start or (k, idx + 1 + j)
                    if failed >= _MAX_FAILED_IN_A_ROW:
                        break
                if failed >= _MAX_FAILED_IN_A_ROW:
                    break
            if run_start is not None:  # the last frames did not decode: the video ended there
                ended(*run_start)
        finally:
            cap.release()
            log.close()

    def _first_bits(self) -> int | None:
        """A folder's ``"auto"`` depth from its first kept frame (:func:`~camhealth.data.io.first_frame_bits`), once."""
        if not hasattr(self, "_first_bits_cache"):
            assert self.frame_paths is not None
            first = self.frame_paths[self.frame_index(0)] if (self.length or 0) > 0 else None
            self._first_bits_cache = None if first is None else first_frame_bits(first, self.bit_depth)
        return self._first_bits_cache

    def __getitem__(self, k: int) -> tuple[torch.Tensor, int]:
        n = self.length
        if n is None:
            raise TypeError(f"random access needs a known frame count; video {self.path} has none — iterate instead")
        k = check_index(k, n, f"FrameSequence({self.path})")
        idx = self.frame_index(k)
        if self.kind == "folder":
            assert self.frame_paths is not None
            return read_sequence_frame(self.frame_paths[idx], self.bit_depth, self._first_bits())[0], idx
        bad = getattr(self, "_unknown_after", None)
        if bad is not None and idx > bad:
            raise ValueError(f"cannot tell which frame is frame {idx} of video {self.path}: frame {bad} is damaged and "
                             f"the file lost frames (its container declares more than the {self.total_frames} that "
                             "decode), so the frames after it may be numbered lower than written")
        cv2 = _import_cv2()
        if self._cap is not None and self._cap_pid != os.getpid():  # inherited through fork
            self.close()
        if self._cap is None:
            self._cap = self._open()
            self._cap_pid = os.getpid()
            self._cap_next = 0
        sought = False
        if idx != self._cap_next:
            if idx > self._cap_next and idx - self._cap_next <= 64:
                self._grab_to(idx)
            else:
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, idx)
                sought = True
        ok, frame, message = self._read()
        if sought and ok and frame is not None and int(round(self._cap.get(cv2.CAP_PROP_POS_FRAMES))) != idx + 1:
            # the seek landed elsewhere (a damaged frame before idx confuses the decoder's count): count from the start
            self.close()
            self._cap = self._open()
            self._cap_pid = os.getpid()
            self._cap_next = 0
            self._grab_to(idx)
            ok, frame, message = self._read()
        if not ok or frame is None:
            self.close()
            raise ValueError(f"cannot decode frame {idx} of video {self.path}")
        self._cap_next = idx + 1
        if message is not None:
            raise ValueError(_damaged(idx, self.path, message))
        return _bgr_to_tensor(frame), idx

    def _read(self) -> tuple[bool, np.ndarray | None, str | None]:
        log = _DecoderLog()
        try:
            return log.read(self._cap)
        finally:
            log.close()

    def _grab_to(self, idx: int) -> None:
        """Advance the random-access handle from ``_cap_next`` to frame ``idx`` by grabbing the frames between; a frame
        on the way that does not decode leaves the position unknown: ``ValueError`` naming both frames and the file."""
        for j in range(self._cap_next, idx):
            if not self._cap.grab():
                self.close()
                raise ValueError(f"cannot reach frame {idx} of video {self.path}: frame {j} does not decode, so the "
                                 "frames after it cannot be counted")
            self._cap_next = j + 1

    def as_source(self, name: str | None = None) -> "FrameSequenceSource":
        """This sequence as an image source (``source[i] -> (frame, id)``) whose frames form one split group."""
        return FrameSequenceSource(self, name)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(path={str(self.path)!r}, kind={self.kind!r}, start={self.start}, "
            f"stride={self.stride}, max_frames={self.max_frames}, length={self.length})"
        )


class FrameSequenceSource(torch.utils.data.Dataset):
    """A :class:`FrameSequence` with the image-source interface: ``source[i] -> (frame 1×H×W, id)``.

    Ids are ``"<name>#<frame index, 6 digits>"`` (``name`` defaults to ``"video:<file name>"`` or
    ``"frames:<folder name>"``), so :func:`camhealth.data.split_ids` keeps all frames of the clip in one
    split (consecutive frames are nearly identical and must never straddle train/val/test).
    """

    def __init__(self, sequence: FrameSequence, name: str | None = None) -> None:
        if not isinstance(sequence, FrameSequence):
            raise TypeError(f"sequence must be a FrameSequence, got {type(sequence).__name__}")
        n = sequence.length
        if n is None:
            raise ValueError(
                f"{sequence.path}: the video does not report its frame count, so it cannot be indexed; "
                "iterate the FrameSequence instead"
            )
        self.sequence = sequence
        if name is None:
            prefix = "video" if sequence.kind == "video" else "frames"
            name = f"{prefix}:{sequence.path.name}"
        if "#" in name:
            raise ValueError(f"name must not contain '#', got {name!r}")
        self.name = name
        self.ids = [f"{name}#{sequence.frame_index(k):06d}" for k in range(n)]

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, str]:
        k = check_index(index, len(self), f"FrameSequenceSource({self.name})")
        frame, _ = self.sequence[k]
        return frame, self.ids[k]

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, n={len(self)})"
