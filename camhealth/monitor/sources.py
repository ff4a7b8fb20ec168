"""Frame sources of the monitor CLI: one image, a folder of frames, a video file, the embedded clip, or a robot
recording (ROS 1 ``.bag``, ROS 2 ``.db3``/``.mcap``, rosbag2 folder: :mod:`camhealth.monitor.recording`).

:func:`open_source` resolves ``SOURCE`` and returns a :class:`FrameSource` whose iteration yields
:class:`SourceFrame` items in order. Reading reuses :mod:`camhealth.data` (``read_image`` for image files,
``FrameSequence`` for videos, BT.601 gray). Error policy (documented in ``docs/monitor.md``):

- a missing path, an unsupported extension, a single image that cannot be read, a folder without frame
  images, or a video OpenCV cannot open or decode: a clear ``FileNotFoundError``/``ValueError`` at
  :func:`open_source` (the CLI exits with status 2);
- one unreadable frame inside a folder, or a video frame the decoder reports damaged (partly decoded: a
  truncated last frame, a corrupt packet): the item carries ``error`` instead of a frame (the CLI writes a JSON
  line with the error, counts it and goes on; the frame is never scored);
- a video whose stream ends early (truncated file): iteration stops there, as OpenCV reports the end;
- a ``start`` past the last frame of an image, folder or video with a known frame count, or past the image
  topic's message count of a recording: ``ValueError`` at :func:`open_source`.

Integer frames are scaled by their significant bits (``bit_depth``: ``"auto"`` or 8…16, see
:func:`camhealth.data.io.read_image`); each item says which scaling it used (``scaling``).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import torch

from camhealth.data._common import check_frame_range
from camhealth.data.image_folder import list_images
from camhealth.data.io import IMAGE_EXTENSIONS, ImageScaling, first_frame_bits, read_image_scaled, read_sequence_frame
from camhealth.data.video import VIDEO_EXTENSIONS, FrameSequence

__all__ = ["SourceFrame", "FrameSource", "open_source", "STREET"]

#: SOURCE name of the embedded street clip (50 frames, 768×576).
STREET = "street"


@dataclass
class SourceFrame:
    """One item of a source: the frame (1×H×W in [0, 1]) or the error that kept it from being read, and how its
    values were scaled to [0, 1] (``scaling``: :meth:`camhealth.data.io.ImageScaling.describe`, or a recording's text;
    ``None`` for video frames, 8-bit DN/255; ``image_scaling``: the :class:`~camhealth.data.io.ImageScaling` itself, for
    image files). :meth:`input_scaling` is what :meth:`camhealth.monitor.Monitor.process` takes as ``input_scaling``.

    Items of a recording also carry ``metadata`` (the camera state of this frame: changed metadata fields,
    or ``None``), ``stamp_ns`` (image header stamp), ``log_time_ns`` and ``frame_id``."""

    index: int
    source_id: str
    frame: torch.Tensor | None = None
    error: str | None = None
    metadata: dict[str, float] | None = None
    stamp_ns: int | None = None
    log_time_ns: int | None = None
    frame_id: str = ""
    scaling: str | None = None
    image_scaling: ImageScaling | None = None

    def input_scaling(self) -> ImageScaling | str | None:
        """The frame's scaling as :meth:`camhealth.monitor.Monitor.process` takes it (``input_scaling``): the
        ``ImageScaling`` of an image file (a change is judged by its divisor, not by the text that names its largest
        value), else the text."""
        return self.image_scaling if self.image_scaling is not None else self.scaling


class FrameSource:
    """Ordered frames of an image, a folder or a video (``kind``), with ``start``/``stride``/``max_frames``."""

    def __init__(self, path: Path, kind: str, start: int = 0, stride: int = 1, max_frames: int | None = None,
                 bit_depth: int | str = "auto") -> None:
        self.path, self.kind = path, kind
        self.start, self.stride, self.max_frames = start, stride, max_frames
        self.bit_depth = bit_depth
        self._files: list[Path] = []
        self._video: FrameSequence | None = None
        if kind == "image":
            _past_end(start, 1, path)
            self._files = [path]
            # a single unreadable image is a fatal, clear error
            self._single, self._single_scaling = read_image_scaled(path, bit_depth)
        elif kind == "folder":
            files = list_images(path, recursive=False)
            if not files:
                raise ValueError(f"no frame images found in folder {path} (extensions: {', '.join(IMAGE_EXTENSIONS)})")
            _past_end(start, len(files), path)
            picked = files[start::stride]
            self._files = picked if max_frames is None else picked[:max_frames]
            self._indices = list(range(start, len(files), stride))[: len(self._files)]
        else:
            self._video = FrameSequence(path, stride=stride, max_frames=max_frames, start=start)
            if self._video.total_frames is not None:
                _past_end(start, self._video.total_frames, path)

    @property
    def length(self) -> int | None:
        """Number of frames iteration yields (``None`` if a video does not report its frame count)."""
        if self._video is not None:
            return self._video.length
        return len(self._files)

    def __iter__(self) -> Iterator[SourceFrame]:
        if self.kind == "image":
            if self._files:
                yield SourceFrame(0, str(self.path), self._single, scaling=self._single_scaling.describe(),
                                  image_scaling=self._single_scaling)
            return
        if self.kind == "folder":
            # one scale for the folder where the depth is guessed: the first frame's, or more where a frame needs it
            first = first_frame_bits(self._files[0], self.bit_depth) if self._files else None
            for idx, p in zip(self._indices, self._files):
                try:
                    frame, scaling = read_sequence_frame(p, self.bit_depth, first)
                except (OSError, ValueError) as exc:
                    yield SourceFrame(idx, str(p), None, str(exc).splitlines()[0])
                    continue
                yield SourceFrame(idx, str(p), frame, scaling=scaling.describe(), image_scaling=scaling)
            return
        assert self._video is not None
        for frame, idx, error in self._video.frames():  # a damaged (partly decoded) frame comes with its error
            yield SourceFrame(int(idx), f"{self.path}#{int(idx)}", frame, error)


#: Image suffixes of lossy codecs: a static pair of such frames is not read (``--static-pairs``).
LOSSY_IMAGE_SUFFIXES = (".jpg", ".jpeg", ".jpe", ".jfif", ".webp")


def lossy_source(source: Any) -> str | None:
    """Why the frames of ``source`` are likely lossy-compressed (a video file; JPEG or WebP images; a recording's
    ``CompressedImage`` topic whose first message is not PNG), or ``None``: ``--static-pairs`` reads two frames'
    difference as noise, which a codec's re-quantisation can imitate."""
    kind = getattr(source, "kind", None)
    if kind == "video":
        return f"{source.path.name} is a video (unless its codec is lossless, its frames are re-quantised)"
    if kind == "recording":
        return _lossy_topic(source)
    files = getattr(source, "_files", [])
    lossy = [f for f in files if f.suffix.lower() in LOSSY_IMAGE_SUFFIXES]
    if lossy:
        return f"{len(lossy)} of its {len(files)} frame file(s) are {lossy[0].suffix.lower()} images"
    return None


def _lossy_topic(source: Any) -> str | None:
    """:func:`lossy_source` of a recording: a ``sensor_msgs/CompressedImage`` topic is lossy unless its first
    message's ``format`` names PNG (``"png"``, ``"mono8; png compressed"``); raw ``Image`` topics are lossless."""
    summary = source.recording.topics.get(source.topic)
    if summary is None or not str(summary.msgtype or "").endswith("CompressedImage"):
        return None
    try:
        first = next(iter(source.recording.read(source.topic)), None)
    except Exception:  # noqa: BLE001 - a damaged first message: its format is unknown, the reader reports the damage
        first = None
    fmt = str(getattr(first[1], "format", "")) if first is not None else ""
    if "png" in fmt.lower():
        return None
    shown = f"format {fmt!r}" if fmt else "format unknown"
    return f"topic {source.topic} holds sensor_msgs/CompressedImage messages ({shown}; only PNG is lossless)"


def _past_end(start: int, n_frames: int, path: Path) -> None:
    if start >= n_frames:
        raise ValueError(f"start = {start} is past the end of {path}: it has {n_frames} frame(s), indices 0…{n_frames - 1}")


def open_source(source: str | Path, start: int = 0, stride: int = 1, max_frames: int | None = None,
                bit_depth: int | str = "auto", recording: Any = None) -> FrameSource:
    """Resolve ``source``: an image file, a folder of frames, a video file, ``"street"`` (embedded clip) or a
    recording (``.bag``/``.db3``/``.mcap`` or a rosbag2 folder; ``recording`` is its
    :class:`~camhealth.monitor.recording.RecordingOptions`, required there for the topic, refused elsewhere).

    Raises ``FileNotFoundError`` for a missing path and ``ValueError`` for an empty ``source``, an unsupported
    extension, an unreadable image, an undecodable video or a ``start`` past the last frame (messages name the file and
    the allowed kinds or frame indices); ``TypeError`` for a ``source`` that is no path. ``bit_depth``: significant
    bits of 16-bit frames (``"auto"`` or 8…16)."""
    check_frame_range(start, stride, max_frames)
    from camhealth.data.io import _check_bit_depth

    bit_depth = _check_bit_depth(bit_depth)
    if not isinstance(source, (str, os.PathLike)):
        raise TypeError(f"source = {source!r} must be a path (an image, a folder of frames, a video file, a recording) "
                        f"or '{STREET}', got {type(source).__name__}")
    if str(source) == "":  # (Path("") is the current folder: an unset shell variable would monitor it)
        raise ValueError(f"source is empty: give an image, a folder of frames, a video file, a recording (.bag .db3 .mcap) "
                         f"or '{STREET}'")
    path = Path(source)
    if not path.exists() and str(source) == STREET:
        from camhealth.data.street_sample import STREET_DIR, street_frame_paths

        street_frame_paths()
        path = STREET_DIR
    if not path.exists():
        raise FileNotFoundError(f"source not found: {source} (give an image, a folder of frames, a video file, a "
                                f"recording (.bag .db3 .mcap) or '{STREET}')")
    from camhealth.data.rosbag import is_recording

    if is_recording(path):
        from camhealth.monitor.recording import RecordingOptions, RecordingSource

        options = recording or RecordingOptions()
        if options.bit_depth is None and bit_depth != "auto":  # --bit-depth N: the data bits of 16-bit images
            options = dataclasses.replace(options, bit_depth=bit_depth)
        return RecordingSource(path, start, stride, max_frames, options)  # type: ignore[return-value]
    if recording is not None:
        raise ValueError(f"--topic and the other recording options apply to ROS recordings (.bag, .db3, .mcap or a "
                         f"rosbag2 folder), not to {path}")
    if path.is_dir():
        return FrameSource(path, "folder", start, stride, max_frames, bit_depth)
    ext = path.suffix.lower()
    if ext in IMAGE_EXTENSIONS:
        return FrameSource(path, "image", start, stride, max_frames, bit_depth)
    if ext in VIDEO_EXTENSIONS:
        return FrameSource(path, "video", start, stride, max_frames, bit_depth)
    raise ValueError(
        f"cannot monitor {path}: unsupported extension {path.suffix!r}; images: {', '.join(IMAGE_EXTENSIONS)}; "
        f"videos: {', '.join(VIDEO_EXTENSIONS)}; recordings: .bag, .db3, .mcap; or a folder of frames"
    )
