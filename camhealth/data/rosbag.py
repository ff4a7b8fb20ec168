"""Robot recordings: gray camera frames and camera-state values from ROS 1 bags, ROS 2 bags and MCAP files.

Formats (pure Python, no ROS installation: the ``rosbags`` package reads them, ``rosbags-image`` knows the
image encodings):

- ROS 1 bag (``.bag``, version 2.0, indexed);
- ROS 2 bag: a rosbag2 folder (``metadata.yaml`` with ``.db3`` or ``.mcap`` storage files), or one storage
  file on its own (``.db3`` or ``.mcap``; MCAP files written by any ROS 2 tool, profile ``ros2``, CDR).

**No code from a recording is run.** A bag carries the text of its message definitions; turning that text
into (de)serialisers would generate and execute Python from the file. :class:`Recording` never does: it
decodes messages only with the standard message types that ``rosbags`` ships (ROS 1 Noetic for ``.bag``,
the latest ROS 2 distribution for the rest) and checks the recording's type hash (MD5 for ROS 1, RIHS01 for
ROS 2, when the recording stores one) against them. A topic of any other type is listed but not decoded.

Frames (:func:`image_to_gray`): ``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` to a gray
``H×W`` float32 array in [0, 1] (camhealth's image convention, ``docs/data.md``):

- ``mono8``/``8UC1``: DN/255; ``mono16``/``16UC1``: DN/(2^bit_depth − 1) with ``bit_depth`` 16 unless told
  (a camera that stores 12-bit values in 16-bit words needs ``bit_depth=12``; a value above the range is an
  error for that frame, not a silent clip);
- ``rgb8``/``bgr8``/``rgba8``/``bgra8`` and their 16-bit forms: BT.601 luma of the stored values
  (:func:`camhealth.data.io.to_gray`, float, no rounding), alpha dropped;
- ``bayer_rggb8``/``bggr``/``gbrg``/``grbg`` (8 and 16 bit): ``bayer="green"`` (default) takes the green
  sample of the top row of every 2×2 cell — a half-resolution (H/2 × W/2) green image whose pixels are raw
  sensor pixels, so the noise keeps the per-pixel statistics the sensor model (and ξ) describes;
  ``bayer="luma"`` demosaics with OpenCV (bilinear, via ``rosbags.image.convert_color``) and takes the
  BT.601 luma at full resolution — interpolation correlates and lowers the noise, which biases the noise
  estimate low (ξ towards "cleaner");
- ``CompressedImage``: JPEG or PNG decoded by OpenCV as stored (8 or 16 bit, gray or BGR(A)), then as
  above; a ``format`` such as ``"bayer_rggb8; png compressed"`` is treated as that Bayer encoding;
  ``compressedDepth`` (depth images) is refused, and so is an image whose header declares more than
  ``PIL.Image.MAX_IMAGE_PIXELS`` pixels (before it is decoded).

Any other encoding (``yuv422``, ``32FC1``, ``8UC3`` of unknown channel order, …) is refused with a message
that names it. A message that cannot be decoded (short data, corrupt JPEG, value beyond ``bit_depth``) is a
per-frame error: :class:`RecordedFrame` carries ``error`` and the iteration goes on.

Camera state (:meth:`Recording.read_state`): a numeric value from a topic — ``std_msgs`` numbers
(``Float64``, ``Int32``, … field ``data``), ``sensor_msgs/Temperature`` (``temperature``) or a field path
into any standard message (``field="a.b[0]"``). Each frame gets the latest value at or before its time:
messages with a ``header`` are compared by ``header.stamp`` with the image's header stamp, messages without
one (``std_msgs`` numbers) by the recording's log time with the image's log time. A zero (unset) header stamp is
no time: such a state message is placed at its log time, and a topic whose stamps are all zero is compared by log
time with the images' log times (a note says so, :attr:`RecordingFrames.notes`).
"""

from __future__ import annotations

import bisect
import dataclasses
import math
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
import torch

from camhealth.data._common import check_frame_range
from camhealth.data.io import to_gray

__all__ = [
    "RECORDING_SUFFIXES",
    "IMAGE_TYPES",
    "SUPPORTED_ENCODINGS",
    "BAYER_MODES",
    "RecordingError",
    "FrameDecodeError",
    "TopicSummary",
    "StateTopic",
    "StateSeries",
    "RecordedFrame",
    "RecordingFrames",
    "Recording",
    "RecordingWriter",
    "is_recording",
    "image_to_gray",
    "stamp_to_ns",
    "format_stamp",
]

#: File suffixes read as recordings (a rosbag2 folder is recognised by its ``metadata.yaml``).
RECORDING_SUFFIXES = (".bag", ".db3", ".mcap")
#: Message types read as camera frames.
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
_BAYER = ("rggb", "bggr", "gbrg", "grbg")
#: ``sensor_msgs/Image`` encodings :func:`image_to_gray` converts.
SUPPORTED_ENCODINGS: tuple[str, ...] = (
    "mono8", "mono16", "8UC1", "16UC1", "rgb8", "bgr8", "rgba8", "bgra8", "rgb16", "bgr16", "rgba16", "bgra16",
    *(f"bayer_{p}{d}" for d in (8, 16) for p in _BAYER),
)
#: How a Bayer mosaic becomes gray (see the module docstring).
BAYER_MODES = ("green", "luma")
_FIELD_PATH = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\[\d+\])?(\.[A-Za-z_][A-Za-z0-9_]*(\[\d+\])?)*$")
_NUMERIC = (int, float, np.integer, np.floating)  # (a bool is no camera reading: True would read as 1)


def _is_number(value: Any) -> bool:
    return isinstance(value, _NUMERIC) and not isinstance(value, (bool, np.bool_))


class RecordingError(ValueError):
    """A recording that cannot be read, or a topic/option that does not fit it (the message names the value)."""


class FrameDecodeError(ValueError):
    """One image message that cannot be converted to a gray frame (the message says why)."""


# ---------------------------------------------------------------------------------------------- images
def _encoding_info(encoding: str) -> tuple[str, int, np.dtype, str | None]:
    """(kind, channels, dtype, bayer pattern) of a supported encoding; ``FrameDecodeError`` otherwise.

    kind: ``"gray"``, ``"rgb"``, ``"bgr"`` or ``"bayer"``."""
    from rosbags.image.image import Format, ImageFormatError, to_cvtype

    try:
        _, fmt, typestr, nchan = to_cvtype(encoding)
    except ImageFormatError:
        fmt, typestr, nchan = None, "", 0
    dtype = np.dtype(typestr) if typestr else None
    kind = None
    if dtype in (np.dtype(np.uint8), np.dtype(np.uint16)):
        if fmt == Format.GRAY or (fmt == Format.GENERIC and nchan == 1):
            kind = "gray"
        elif fmt in (Format.RGB, Format.RGBA):
            kind = "rgb"
        elif fmt in (Format.BGR, Format.BGRA):
            kind = "bgr"
        elif fmt in (Format.BAYER_RG, Format.BAYER_BG, Format.BAYER_GB, Format.BAYER_GR):
            kind = "bayer"
    if kind is None:
        raise FrameDecodeError(
            f"image encoding {encoding!r} cannot be converted to gray; supported: {', '.join(SUPPORTED_ENCODINGS)} "
            "(and CompressedImage JPEG/PNG)"
        )
    pattern = encoding[len("bayer_"):len("bayer_") + 4] if kind == "bayer" else None
    return kind, int(nchan), dtype, pattern


def _check_bit_depth(bit_depth: int | None) -> int | None:
    if bit_depth is None:
        return None
    if isinstance(bit_depth, bool) or not isinstance(bit_depth, (int, np.integer)) or not 1 <= bit_depth <= 16:
        raise ValueError(f"bit_depth = {bit_depth!r} must be an integer in 1…16 (bits per 16-bit pixel that carry data)")
    return int(bit_depth)


def _to_unit(arr: np.ndarray, bit_depth: int | None) -> np.ndarray:
    """Integer DN → float32 in [0, 1]: 8-bit /255, 16-bit /(2^bit_depth − 1); values beyond the range are an error."""
    if arr.dtype == np.uint8:
        return arr.astype(np.float32) / np.float32(255.0)
    bits = 16 if bit_depth is None else bit_depth
    top = (1 << bits) - 1
    if bits < 16 and arr.size:
        hi = int(arr.max())
        if hi > top:
            raise FrameDecodeError(
                f"16-bit value {hi} exceeds the {bits}-bit range 0…{top} (bit depth {bits}); "
                "give the camera's real bit depth (16 if it fills the 16-bit word)"
            )
    return arr.astype(np.float32) / np.float32(top)


def _gray_from(arr: np.ndarray, kind: str, encoding: str, pattern: str | None, bit_depth: int | None,
               bayer: str) -> np.ndarray:
    if kind == "gray":
        return _to_unit(arr if arr.ndim == 2 else arr[..., 0], bit_depth)
    if kind in ("rgb", "bgr"):
        unit = _to_unit(arr, bit_depth)
        if kind == "bgr":
            unit = unit[..., [2, 1, 0]]
        return to_gray(unit).astype(np.float32, copy=False)
    # Bayer mosaic
    if arr.ndim == 3:
        arr = arr[..., 0]
    h, w = arr.shape
    if h < 2 or w < 2:
        raise FrameDecodeError(f"a {encoding} mosaic of {w}×{h} px has no complete 2×2 cell")
    if bayer == "green":
        col = 0 if pattern[0] == "g" else 1  # the green sample of the top row of each 2×2 cell
        return _to_unit(np.ascontiguousarray(arr[0:(h // 2) * 2:2, col:(w // 2) * 2:2]), bit_depth)
    from rosbags.image.image import convert_color

    _to_unit(arr, bit_depth)  # range check on the raw values
    rgb = convert_color(arr, encoding, "rgb8" if arr.dtype == np.uint8 else "rgb16")
    return to_gray(_to_unit(np.asarray(rgb), bit_depth)).astype(np.float32, copy=False)


def _raw_image(msg: Any, encoding: str, kind: str, nchan: int, dtype: np.dtype) -> np.ndarray:
    """The pixel array of a ``sensor_msgs/Image`` (rows of ``step`` bytes, padding dropped, native byte order)."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise FrameDecodeError(f"empty image ({w}×{h} px, encoding {encoding})")
    row = w * nchan * dtype.itemsize
    if step < row:
        raise FrameDecodeError(f"step {step} bytes is shorter than a row of {w} px {encoding} ({row} bytes)")
    buf = np.frombuffer(msg.data, dtype=np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data.view(np.uint8).ravel()
    need = step * (h - 1) + row
    if buf.size < need:
        raise FrameDecodeError(
            f"image data holds {buf.size} bytes but {w}×{h} px {encoding} with step {step} needs {need} (truncated message)"
        )
    if buf.size > step * h:  # ROS: len(data) = step · height; more data means height or step is wrong (a crop, else)
        allowed = f"{step * h}" if need == step * h else f"{need} (last row unpadded) to {step * h}"
        raise FrameDecodeError(
            f"image data holds {buf.size} bytes but {w}×{h} px {encoding} with step {step} is {step * h} bytes "
            f"(step × height; allowed: {allowed} bytes): height/step do not match the data"
        )
    rows = np.lib.stride_tricks.as_strided(buf, shape=(h, row), strides=(step, 1), writeable=False)
    raw = np.ascontiguousarray(rows).view(dtype)
    if dtype.itemsize > 1 and bool(msg.is_bigendian) != (sys.byteorder == "big"):
        raw = raw.byteswap()
    return raw.reshape(h, w, nchan) if nchan > 1 else raw.reshape(h, w)


def _check_compressed_size(data: np.ndarray, fmt: str) -> None:
    """Refuse a compressed image whose header (read by Pillow, which decodes nothing) declares more pixels than
    ``PIL.Image.MAX_IMAGE_PIXELS`` (read now; ``None`` = no limit), or whose header cannot be read, before OpenCV
    decodes it."""
    import io
    import warnings

    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(data.tobytes())) as im:
                width, height = im.size
    except Image.DecompressionBombError as exc:
        raise FrameDecodeError(f"CompressedImage (format {fmt!r}) is too large to decode: {exc}") from None
    except Exception:  # noqa: BLE001 - PIL.UnidentifiedImageError, a truncated header, ...
        raise FrameDecodeError(f"cannot decode CompressedImage (format {fmt!r}, {data.size} bytes): corrupt or not "
                               "JPEG/PNG") from None
    limit = Image.MAX_IMAGE_PIXELS
    if limit is not None and width * height > limit:
        raise FrameDecodeError(f"CompressedImage (format {fmt!r}) is {width}×{height} = {width * height} pixels, more "
                               f"than the limit of {limit} pixels (PIL.Image.MAX_IMAGE_PIXELS)")


def _compressed_decode(msg: Any, bit_depth: int | None, bayer: str) -> tuple[np.ndarray, int]:
    """A ``CompressedImage`` → gray, and the bits per sample of the decoded image (8 or 16)."""
    import cv2

    fmt = str(msg.format)
    if "compresseddepth" in fmt.lower().replace(" ", ""):
        raise FrameDecodeError(f"CompressedImage format {fmt!r} is a compressed depth image, not a camera image")
    data = np.frombuffer(msg.data, dtype=np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data.view(np.uint8).ravel()
    if data.size == 0:
        raise FrameDecodeError(f"CompressedImage (format {fmt!r}) holds no data")
    _check_compressed_size(data, fmt)
    try:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except (cv2.error, MemoryError) as exc:
        raise FrameDecodeError(f"cannot decode CompressedImage (format {fmt!r}, {data.size} bytes): "
                               f"{_first_line(exc)}") from None
    if img is None:
        raise FrameDecodeError(f"cannot decode CompressedImage (format {fmt!r}, {data.size} bytes): corrupt or not JPEG/PNG")
    if img.dtype not in (np.uint8, np.uint16):
        raise FrameDecodeError(f"CompressedImage (format {fmt!r}) decodes to {img.dtype} pixels; only 8 and 16 bit are read")
    bits = 8 * img.dtype.itemsize
    declared = fmt.split(";")[0].strip()
    if declared.startswith("bayer_") and img.ndim == 2:
        kind, _, _, pattern = _encoding_info(declared)
        return _gray_from(img, kind, declared, pattern, bit_depth, bayer), bits
    if img.ndim == 2 or img.shape[-1] == 1:
        return _to_unit(img.reshape(img.shape[0], img.shape[1]), bit_depth), bits
    if img.shape[-1] == 2:  # gray + alpha
        return _to_unit(np.ascontiguousarray(img[..., 0]), bit_depth), bits
    return _gray_from(img, "bgr", "bgr8", None, bit_depth, bayer), bits


def image_to_gray(msg: Any, bit_depth: int | None = None, bayer: str = "green") -> np.ndarray:
    """A ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage`` message → gray ``H×W`` float32 in [0, 1].

    ``bit_depth`` (1…16, default 16) sets the scale of 16-bit data; ``bayer`` is ``"green"`` or ``"luma"``
    (module docstring). Raises :class:`FrameDecodeError` naming the encoding or the defect."""
    return _decode(msg, bit_depth, bayer)[0]


def _decode(msg: Any, bit_depth: int | None = None, bayer: str = "green") -> tuple[np.ndarray, int]:
    """:func:`image_to_gray` and the bits per sample of the message's pixels (8 or 16: the encoding's for an
    ``Image``, the decoded image's for a ``CompressedImage``)."""
    bit_depth = _check_bit_depth(bit_depth)
    if bayer not in BAYER_MODES:
        raise ValueError(f"bayer = {bayer!r} must be one of {BAYER_MODES}")
    if hasattr(msg, "format") and not hasattr(msg, "encoding"):
        return _compressed_decode(msg, bit_depth, bayer)
    encoding = str(msg.encoding)
    kind, nchan, dtype, pattern = _encoding_info(encoding)
    gray = _gray_from(_raw_image(msg, encoding, kind, nchan, dtype), kind, encoding, pattern, bit_depth, bayer)
    return gray, 8 * dtype.itemsize


# ---------------------------------------------------------------------------------------------- stamps
def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` (``sec``, ``nanosec``) → integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def format_stamp(ns: int | None) -> str:
    """Nanoseconds as ``sec.nanosec`` (``"?"`` for ``None``)."""
    if ns is None:
        return "?"
    sign = "-" if ns < 0 else ""
    sec, nsec = divmod(abs(int(ns)), 1_000_000_000)
    return f"{sign}{sec}.{nsec:09d}"


def _header_ns(msg: Any) -> int | None:
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    return None if stamp is None else stamp_to_ns(stamp)


# ---------------------------------------------------------------------------------------------- state
def _fields(obj: Any) -> list[str]:
    return [f.name for f in dataclasses.fields(obj) if not f.name.startswith("__")] if dataclasses.is_dataclass(obj) else []


def _numeric_fields(obj: Any, prefix: str = "", depth: int = 0) -> list[str]:
    """Dotted paths of the numeric scalar fields of a decoded message (header stamps excluded)."""
    out = []
    for name in _fields(obj):
        value = getattr(obj, name)
        if _is_number(value):
            out.append(prefix + name)
        elif dataclasses.is_dataclass(value) and depth < 3 and name != "header":
            out += _numeric_fields(value, f"{prefix}{name}.", depth + 1)
    return out


def _extract(msg: Any, path: str) -> float:
    """The number at ``path`` (``a.b[0]``) of a decoded message; ``KeyError``/``TypeError`` naming the problem."""
    obj = msg
    for part in path.split("."):
        name, _, idx = part.partition("[")
        if name not in _fields(obj):
            raise KeyError(f"{type(obj).__name__.replace('__msg__', '/msg/').replace('__', '/')} has no field {name!r} "
                           f"(fields: {', '.join(_fields(obj)) or 'none'})")
        obj = getattr(obj, name)
        if idx:
            i = int(idx.rstrip("]"))
            try:
                obj = obj[i]
            except (IndexError, TypeError):
                size = len(obj) if hasattr(obj, "__len__") else 0
                raise KeyError(f"field {name!r} has {size} element(s); index [{i}] is out of range") from None
    if isinstance(obj, np.ndarray) and obj.size == 1:
        obj = obj.reshape(()).item()
    if not _is_number(obj):
        what = "bool" if isinstance(obj, (bool, np.bool_)) else type(obj).__name__
        raise TypeError(f"field {path!r} holds {what}, not a number")
    return float(obj)


@dataclass(frozen=True)
class StateTopic:
    """A camera-state value read from a recording.

    Attributes:
        key: the name the value gets in :attr:`RecordedFrame.state` (e.g. ``"gain_db"``).
        topic: the topic name.
        field: dotted field path (``"data"``, ``"temperature"``, ``"status.exposure[0]"``); ``None`` picks
            ``data`` or, for ``sensor_msgs/Temperature``, ``temperature``.
        label: how messages name the option that gave it (e.g. ``"--gain-topic"``).
    """

    key: str
    topic: str
    field: str | None = None
    label: str = ""

    @classmethod
    def parse(cls, key: str, spec: str, label: str = "") -> "StateTopic":
        """``TOPIC`` or ``TOPIC:FIELD.PATH`` (e.g. ``/camera/status:exposure_us``)."""
        topic, sep, path = str(spec).partition(":")
        topic = topic.strip()
        who = label or key
        if not topic:
            raise RecordingError(f"{who} {spec!r}: give a topic name (TOPIC or TOPIC:FIELD)")
        if sep and not _FIELD_PATH.match(path.strip()):
            raise RecordingError(f"{who} {spec!r}: field path {path!r} must look like name, name.sub or name[0]")
        return cls(key, topic, path.strip() if sep else None, label)

    def describe(self) -> str:
        return self.topic + (f":{self.field}" if self.field else "")


@dataclass
class StateSeries:
    """All values of one :class:`StateTopic`, sorted by time; :meth:`at` gives the latest at or before a time.

    ``clock`` is ``"header"`` when the messages have a header with a set (non-zero) stamp; a message whose stamp is
    zero (unset) is placed at its log time (``unstamped`` counts those), and a topic whose stamps are all zero is
    read on the ``"log"`` clock; ``notes`` says so."""

    spec: StateTopic
    msgtype: str
    field: str
    clock: str  # "header" (header.stamp) or "log" (the recording's log time)
    times: list[int]
    values: list[float]
    out_of_order: int = 0
    dropped: int = 0  # messages that could not be decoded or carry no time (NaN and ±inf readings are kept)
    unstamped: int = 0  # messages with a header whose stamp is zero (unset): their log time stands in
    notes: list[str] = field(default_factory=list)

    def at(self, t_ns: int | None) -> float | None:
        if t_ns is None or not self.times:
            return None
        i = bisect.bisect_right(self.times, t_ns) - 1
        return self.values[i] if i >= 0 else None


# ---------------------------------------------------------------------------------------------- frames
@dataclass
class RecordedFrame:
    """One image message of a recording.

    Attributes:
        index: position of the message in its topic (0-based, log-time order).
        log_time_ns: the recording's log (receive) time.
        stamp_ns: ``header.stamp`` (``None`` if the message could not be decoded or its stamp is zero, i.e. unset).
        frame_id: ``header.frame_id``.
        frame: gray ``1×H×W`` float32 tensor in [0, 1], or ``None`` with ``error`` set.
        error: why the message could not be decoded.
        state: the camera-state values in effect (latest at or before the frame), by :attr:`StateTopic.key`;
            a key is missing before its topic's first message.
        encoding: the image encoding (or CompressedImage format).
        out_of_order: the header stamp is earlier than the previous frame's.
    """

    index: int
    log_time_ns: int
    stamp_ns: int | None = None
    frame_id: str = ""
    frame: torch.Tensor | None = None
    error: str | None = None
    state: dict[str, float] = field(default_factory=dict)
    encoding: str = ""
    out_of_order: bool = False


class RecordingFrames:
    """Iterable of :class:`RecordedFrame` of one image topic (see :meth:`Recording.frames`), with counts.

    After (or during) iteration: ``decoded``, ``undecodable``, ``out_of_order`` (frames whose header stamp
    went back in time), ``unstamped`` (zero header stamps, replaced by ``None``: the log time stands in), ``first_out_of_order`` (a sentence), ``damaged`` (why reading stopped early, or
    ``None``), ``missing_state`` (frames per state key that had no value yet), ``notes``."""

    def __init__(self, recording: "Recording", topic: str, state: Sequence[StateSeries], start: int, stride: int,
                 max_frames: int | None, bit_depth: int | None, bayer: str) -> None:
        self.recording, self.topic, self.state = recording, topic, list(state)
        self.start, self.stride, self.max_frames = start, stride, max_frames
        self.bit_depth, self.bayer = bit_depth, bayer
        self.messages = recording.topics[topic].count
        self.decoded = self.undecodable = self.out_of_order = self.unstamped = 0
        self.first_out_of_order: str | None = None
        self.damaged: str | None = None
        self.missing_state = {s.spec.key: 0 for s in self.state}
        self.notes: list[str] = [note for s in self.state for note in s.notes]  # e.g. a state topic's unset stamps
        self._bit_note = bit_depth is None

    @property
    def length(self) -> int:
        n = max(0, math.ceil((self.messages - self.start) / self.stride))
        return n if self.max_frames is None else min(n, self.max_frames)

    def _convert(self, msg: Any) -> np.ndarray:
        gray, bits = _decode(msg, self.bit_depth, self.bayer)
        if self._bit_note:  # once: a 16-bit stream that never uses its top bits is probably 10/12-bit data
            self._bit_note = False
            enc = str(getattr(msg, "encoding", getattr(msg, "format", "")))
            if bits == 16:  # by the decoded samples: raw mono16/16UC1/…16, or a CompressedImage's 16-bit PNG
                hi = float(gray.max()) * 65535.0 if gray.size else 0.0
                if hi < 4096:
                    self.notes.append(
                        f"the first {enc} frame uses values up to {hi:.0f} of 65535: if the camera delivers 12-bit "
                        "(or 10-bit) data in 16-bit words, give its bit depth (--bit-depth 12), else the frames "
                        "look 16× darker than they are"
                    )
        return gray

    def __iter__(self) -> Iterator[RecordedFrame]:
        rec = self.recording
        conns = rec._image_connections(self.topic)
        previous: int | None = None
        selected = 0
        index = -1
        stream = rec._messages(conns)
        while True:
            try:
                item = next(stream)
            except StopIteration:
                return
            except Exception as exc:  # noqa: BLE001 - any reader failure on damaged data ends the stream cleanly
                self.damaged = (f"reading stopped after message {index + 1} of {self.messages} on {self.topic}: "
                                f"{_first_line(exc)} (damaged or truncated recording)")
                return
            conn, log_ns, raw = item
            index += 1
            if index < self.start or (index - self.start) % self.stride:
                continue
            if self.max_frames is not None and selected >= self.max_frames:
                return
            selected += 1
            out = RecordedFrame(index=index, log_time_ns=int(log_ns))
            try:
                msg = rec._deserialize(raw, conn.msgtype)
            except Exception as exc:  # noqa: BLE001 - the deserialiser raises several types on malformed bytes
                out.error = f"cannot decode {conn.msgtype} message: {_first_line(exc)}"
                self.undecodable += 1
                yield out
                continue
            out.stamp_ns = _header_ns(msg)
            if out.stamp_ns == 0:  # an unset stamp: the log time stands in (said once in the notes)
                out.stamp_ns = None
                self.unstamped += 1
                if self.unstamped == 1:
                    self.notes.append(f"{self.topic} has images with a zero (unset) header stamp: their log time "
                                      "stands in for it (state matching, diagnostics stamps)")
            out.frame_id = str(getattr(getattr(msg, "header", None), "frame_id", ""))
            out.encoding = str(getattr(msg, "encoding", getattr(msg, "format", "")))
            if previous is not None and out.stamp_ns is not None and out.stamp_ns < previous:
                out.out_of_order = True
                self.out_of_order += 1
                if self.first_out_of_order is None:
                    self.first_out_of_order = (f"message {index}: header stamp {format_stamp(out.stamp_ns)} s is "
                                               f"earlier than the previous frame's {format_stamp(previous)} s")
            if out.stamp_ns is not None:
                previous = out.stamp_ns if previous is None else max(previous, out.stamp_ns)
            for series in self.state:
                t = out.stamp_ns if series.clock == "header" and out.stamp_ns is not None else out.log_time_ns
                value = series.at(t)
                if value is None:
                    self.missing_state[series.spec.key] += 1
                else:
                    out.state[series.spec.key] = value
            try:
                gray = self._convert(msg)
            except FrameDecodeError as exc:
                out.error = str(exc)
                self.undecodable += 1
                yield out
                continue
            out.frame = torch.from_numpy(gray)[None]
            self.decoded += 1
            yield out


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    text = text.splitlines()[0]
    return re.sub(r"\('([^']*)',\)", r"\1", text)  # rosbags wraps some causes as "('why',)"


# ---------------------------------------------------------------------------------------------- recordings
@dataclass(frozen=True)
class TopicSummary:
    """A topic of a recording: name, message type (``None`` if its connections disagree), message count."""

    name: str
    msgtype: str | None
    count: int

    def describe(self) -> str:
        return f"{self.name} ({self.msgtype or 'mixed types'}, {self.count} message{'s' if self.count != 1 else ''})"


def is_recording(path: str | Path) -> bool:
    """True for a ``.bag``/``.db3``/``.mcap`` file or a rosbag2 folder (one with ``metadata.yaml``)."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    return p.suffix.lower() in RECORDING_SUFFIXES


def _damaged(path: Path, exc: BaseException) -> str:
    text = _first_line(exc)
    repair = ""
    low = text.lower()
    if any(w in low for w in ("index", "end magic", "footer", "malformed", "truncat", "could not read", "got only",
                              "not a database", "summary")):
        suffix = path.suffix.lower()
        tool = ("rosbag reindex" if suffix == ".bag" else "mcap recover" if suffix == ".mcap" else
                "ros2 bag reindex on its rosbag2 folder")
        repair = f"; a recording cut off by a crash or a full disk lacks its index — repair it first ({tool})"
    return f"cannot read recording {path}: {text} (damaged, truncated or not a recording{repair})"


class Recording:
    """A ROS 1 bag, a rosbag2 folder, or one ``.db3``/``.mcap`` file, opened for reading.

    Use as a context manager (or call :meth:`close`). ``topics`` maps every topic to a :class:`TopicSummary`;
    :meth:`image_topics` lists those of :data:`IMAGE_TYPES`; :meth:`frames` iterates one image topic;
    :meth:`read_state` reads a camera-state topic. Raises ``FileNotFoundError`` for a missing path and
    :class:`RecordingError` for a file that is not a readable recording (truncated, not indexed, corrupt,
    unsupported profile), with a one-line message naming the file.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"recording not found: {self.path}")
        if not is_recording(self.path):
            raise RecordingError(
                f"{self.path} is not a recording: expected a .bag, .db3 or .mcap file or a rosbag2 folder with metadata.yaml"
            )
        from rosbags.typesys import Stores, get_typestore

        self.ros1 = self.path.is_file() and self.path.suffix.lower() == ".bag"
        if self.ros1:
            from rosbags.rosbag1 import Reader

            self.format = "ROS 1 bag"
            self.typestore = get_typestore(Stores.ROS1_NOETIC)
        else:
            from rosbags.rosbag2 import Reader

            self.format = ("rosbag2 folder" if self.path.is_dir() else
                           "MCAP file" if self.path.suffix.lower() == ".mcap" else "ROS 2 SQLite3 (.db3) file")
            self.typestore = get_typestore(Stores.LATEST)
        self._reader = None
        try:
            reader = Reader(self.path)
            reader.open()
        except FileNotFoundError as exc:  # a rosbag2 folder without one of its storage files
            raise RecordingError(_damaged(self.path, exc)) from None
        except Exception as exc:  # noqa: BLE001 - readers raise ReaderError, apsw/struct/zstd errors on bad files
            raise RecordingError(_damaged(self.path, exc)) from None
        self._reader = reader
        self.connections = list(reader.connections)
        topics: dict[str, list] = {}
        for c in self.connections:
            topics.setdefault(c.topic, []).append(c)
        self.topics: dict[str, TopicSummary] = {}
        for name in sorted(topics):
            conns = topics[name]
            types = {c.msgtype for c in conns}
            self.topics[name] = TopicSummary(name, types.pop() if len(types) == 1 else None, sum(int(c.msgcount) for c in conns))

    # ------------------------------------------------------------------ basics
    def close(self) -> None:
        if self._reader is not None:
            reader, self._reader = self._reader, None
            reader.close()

    def __enter__(self) -> "Recording":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def image_topics(self) -> list[TopicSummary]:
        """Topics whose messages are ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage``."""
        return [t for t in self.topics.values() if t.msgtype in IMAGE_TYPES]

    def describe_image_topics(self) -> str:
        found = self.image_topics()
        if not found:
            others = ", ".join(t.describe() for t in self.topics.values()) or "none"
            return f"it has no sensor_msgs/Image or CompressedImage topic (topics: {others})"
        return "image topics: " + ", ".join(t.describe() for t in found)

    def _connections(self, topic: str) -> list:
        return [c for c in self.connections if c.topic == topic]

    def _check_type(self, conn: Any, what: str) -> None:
        """The connection's type must be a standard type whose definition matches the recording's hash."""
        msgtype = conn.msgtype
        if msgtype not in self.typestore.fielddefs:
            raise RecordingError(
                f"{what} has type {msgtype}, which camhealth does not decode: it reads only the standard ROS message "
                f"types that rosbags ships ({'ROS 1 Noetic' if self.ros1 else 'ROS 2'}), so that no code is generated "
                "from a recording's own message definitions"
            )
        if not self.ros1:
            fmt = getattr(conn.ext, "serialization_format", "cdr")
            if fmt != "cdr":
                raise RecordingError(f"{what} is serialised as {fmt!r}; only CDR (the ROS 2 default) is read")
        digest = str(conn.digest or "")
        if digest:
            have = self.typestore.generate_msgdef(msgtype)[1] if self.ros1 else self.typestore.hash_rihs01(msgtype)
            if have != digest:
                raise RecordingError(
                    f"{what}: the recording's definition of {msgtype} differs from the standard one (hash {digest} ≠ "
                    f"{have}); camhealth does not decode non-standard definitions"
                )

    def _deserialize(self, raw: Any, msgtype: str) -> Any:
        if self.ros1:
            return self.typestore.deserialize_ros1(raw, msgtype)
        return self.typestore.deserialize_cdr(raw, msgtype)

    def _messages(self, conns: Sequence[Any]) -> Iterator[tuple[Any, int, Any]]:
        if self._reader is None:
            raise RecordingError(f"recording {self.path} is closed")
        return iter(self._reader.messages(connections=list(conns)))

    def read(self, topic: str) -> Iterator[tuple[int, Any]]:
        """``(log time [ns], decoded message)`` of every message of ``topic`` (a standard message type)."""
        conns = self._connections(topic)
        if not conns:
            others = ", ".join(t.describe() for t in self.topics.values()) or "none"
            raise RecordingError(f"topic {topic!r} is not in recording {self.path} (topics: {others})")
        for c in conns:
            self._check_type(c, f"topic {topic!r}")
        for conn, log_ns, raw in self._messages(conns):
            yield int(log_ns), self._deserialize(raw, conn.msgtype)

    # ------------------------------------------------------------------ images
    def _image_connections(self, topic: str) -> list:
        conns = self._connections(topic)
        if not conns:
            raise RecordingError(f"topic {topic!r} is not in recording {self.path}; {self.describe_image_topics()}")
        for c in conns:
            if c.msgtype not in IMAGE_TYPES:
                raise RecordingError(
                    f"topic {topic!r} of {self.path} carries {c.msgtype}, not sensor_msgs/Image or CompressedImage; "
                    f"{self.describe_image_topics()}"
                )
            self._check_type(c, f"topic {topic!r}")
        return conns

    def frames(self, topic: str, state: Sequence[StateSeries] = (), start: int = 0, stride: int = 1,
               max_frames: int | None = None, bit_depth: int | None = None, bayer: str = "green") -> RecordingFrames:
        """Frames of an image ``topic`` (every ``stride``-th message from ``start``, at most ``max_frames``).

        The first message's encoding is checked now: an encoding that cannot be converted is a
        :class:`RecordingError` here (later messages with a bad encoding are per-frame errors)."""
        check_frame_range(start, stride, max_frames)
        bit_depth = _check_bit_depth(bit_depth)
        if bayer not in BAYER_MODES:
            raise ValueError(f"bayer = {bayer!r} must be one of {BAYER_MODES}")
        conns = self._image_connections(topic)
        stream = self._messages(conns)
        try:  # look at the first message: a stream in an encoding we cannot convert is refused up front
            first = next(stream, None)
        except Exception:  # noqa: BLE001 - damage is reported by the iteration itself
            first = None
        finally:
            close = getattr(stream, "close", None)
            if close is not None:
                close()
        if first is not None:
            try:
                msg = self._deserialize(first[2], first[0].msgtype)
            except Exception:  # noqa: BLE001 - reported per frame
                msg = None
            if msg is not None and hasattr(msg, "encoding"):
                try:
                    _encoding_info(str(msg.encoding))
                except FrameDecodeError as exc:
                    raise RecordingError(f"topic {topic!r} of {self.path}: {exc}") from None
        return RecordingFrames(self, topic, state, start, stride, max_frames, bit_depth, bayer)

    # ------------------------------------------------------------------ state
    def describe_numeric_topics(self) -> str:
        names = [t.describe() for t in self.topics.values()
                 if t.msgtype and t.msgtype in self.typestore.fielddefs and t.msgtype not in IMAGE_TYPES]
        return "topics it can read values from: " + (", ".join(names) if names else "none")

    def read_state(self, spec: StateTopic) -> StateSeries:
        """Every value of a camera-state topic, sorted by time (see the module docstring for the clock)."""
        who = f"{spec.label or spec.key} {spec.describe()}"
        conns = self._connections(spec.topic)
        if not conns:
            raise RecordingError(f"{who}: topic {spec.topic!r} is not in recording {self.path}; {self.describe_numeric_topics()}")
        for c in conns:
            if c.msgtype in IMAGE_TYPES:
                raise RecordingError(f"{who}: topic {spec.topic!r} carries images ({c.msgtype}), not a number")
            self._check_type(c, f"{who}: topic {spec.topic!r}")
        times: list[int] = []
        log_times: list[int] = []
        stamped: list[bool] = []  # the message's time is its (non-zero) header stamp
        values: list[float] = []
        path = spec.field
        clock = "log"
        first = True
        dropped = 0
        msgtype = conns[0].msgtype
        try:
            for conn, log_ns, raw in self._messages(conns):
                try:
                    msg = self._deserialize(raw, conn.msgtype)
                except Exception:  # noqa: BLE001 - a malformed state message is skipped and counted
                    dropped += 1
                    continue
                if first:
                    first = False
                    clock = "header" if _header_ns(msg) is not None else "log"
                    names = _fields(msg)
                    if path is None:
                        path = "data" if "data" in names else "temperature" if "temperature" in names else None
                    if path is None:
                        raise RecordingError(
                            f"{who}: {conn.msgtype} has no 'data' field; name one with {spec.topic}:FIELD "
                            f"(numeric fields: {', '.join(_numeric_fields(msg)) or 'none'})"
                        )
                try:
                    value = _extract(msg, path)
                except KeyError as exc:
                    raise RecordingError(f"{who}: {exc.args[0]}") from None
                except TypeError as exc:
                    raise RecordingError(
                        f"{who}: {exc.args[0]}; numeric fields of {conn.msgtype}: {', '.join(_numeric_fields(msg)) or 'none'}"
                    ) from None
                t = _header_ns(msg) if clock == "header" else int(log_ns)
                if t is None:
                    dropped += 1
                    continue
                # a non-finite reading (NaN, ±inf) is kept: the frames it governs are refused as out of range, rather
                # than scored with the previous reading or the metadata's value
                stamped.append(clock == "header" and t != 0)
                if clock == "header" and t == 0:  # an unset stamp: the log time stands in, as for images
                    t = int(log_ns)
                times.append(t)
                log_times.append(int(log_ns))
                values.append(value)
        except RecordingError:
            raise
        except Exception as exc:  # noqa: BLE001 - damage while reading the state topic
            raise RecordingError(f"{who}: {_damaged(self.path, exc)}") from None
        notes: list[str] = []
        unstamped = sum(1 for s in stamped if not s) if clock == "header" else 0
        if clock == "header" and times and unstamped == len(times):
            clock, times = "log", log_times  # every stamp unset: compared by log time with the images' log times
            notes.append(f"{who}: every header stamp is zero (unset), so its values are matched to the frames by the "
                         "recording's log time")
        elif unstamped:
            notes.append(f"{who}: {unstamped} of {len(times)} messages have a zero (unset) header stamp: their log "
                         "time stands in for it")
        out_of_order = sum(1 for a, b in zip(times, times[1:]) if b < a)
        order = sorted(range(len(times)), key=times.__getitem__)  # stable: equal times keep their recorded order
        return StateSeries(spec, msgtype, path or "data", clock, [times[i] for i in order], [values[i] for i in order],
                           out_of_order, dropped, unstamped, notes)


# ---------------------------------------------------------------------------------------------- writing
_ENCODING_OF = {(np.dtype(np.uint8), 1): "mono8", (np.dtype(np.uint16), 1): "mono16", (np.dtype(np.uint8), 3): "rgb8",
                (np.dtype(np.uint16), 3): "rgb16", (np.dtype(np.uint8), 4): "rgba8", (np.dtype(np.uint16), 4): "rgba16"}


class RecordingWriter:
    """Writes a recording with the standard message types (tests, benchmarks, turning frames into a bag).

    ``path``: ``.bag`` → ROS 1 bag; ``.mcap`` or ``.db3`` → one ROS 2 storage file of that kind; any other
    name → a rosbag2 folder with MCAP storage. Messages are written in the order given; the file is complete
    after :meth:`close` (also as a context manager). An existing ``path`` is refused."""

    def __init__(self, path: str | Path) -> None:
        import shutil
        import tempfile

        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"{self.path} exists already; not overwriting it")
        suffix = self.path.suffix.lower()
        self.ros1 = suffix == ".bag"
        self.typestore = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.LATEST)
        self._conns: dict[tuple[str, str], Any] = {}
        self._tmp: Path | None = None
        self._seq = 0
        if self.ros1:
            from rosbags.rosbag1 import Writer

            self._writer = Writer(self.path)
            self._file = self.path
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.SQLITE3 if suffix == ".db3" else StoragePlugin.MCAP
            if suffix in (".mcap", ".db3"):
                self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent))
                folder = self._tmp / "bag"
                self._file = folder / f"bag{suffix}"
            else:
                folder, self._file = self.path, self.path
            self._writer = Writer(folder, version=9, storage_plugin=plugin)
            self._rmtree = shutil.rmtree
        self._writer.open()

    def _connection(self, topic: str, msgtype: str) -> Any:
        key = (topic, msgtype)
        if key not in self._conns:
            self._conns[key] = self._writer.add_connection(topic, msgtype, typestore=self.typestore)
        return self._conns[key]

    def _header(self, stamp_ns: int, frame_id: str) -> Any:
        t = self.typestore.types
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        extra = {"seq": self._seq} if self.ros1 else {}
        self._seq += 1
        return t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id, **extra)

    def add_raw(self, topic: str, msgtype: str, data: bytes | np.ndarray, log_time_ns: int) -> None:
        """Serialised bytes as they are (e.g. a damaged message)."""
        self._writer.write(self._connection(topic, msgtype), int(log_time_ns), bytes(data))

    def add_message(self, topic: str, msg: Any, log_time_ns: int) -> None:
        """A message object of this writer's ``typestore``."""
        msgtype = msg.__msgtype__
        data = self.typestore.serialize_ros1(msg, msgtype) if self.ros1 else self.typestore.serialize_cdr(msg, msgtype)
        self.add_raw(topic, msgtype, data, log_time_ns)

    def add_image(self, topic: str, image: np.ndarray, stamp_ns: int, log_time_ns: int | None = None,
                  encoding: str | None = None, frame_id: str = "camera", step: int | None = None,
                  bigendian: bool = False) -> None:
        """A ``sensor_msgs/Image``: ``image`` H×W or H×W×C (uint8/uint16); ``encoding`` defaults to mono8/mono16/
        rgb8/rgba8/…; ``step`` > the row size pads every row; ``bigendian`` stores 16-bit data big-endian."""
        arr = np.asarray(image)
        h, w = arr.shape[:2]
        c = 1 if arr.ndim == 2 else arr.shape[2]
        enc = encoding or _ENCODING_OF.get((arr.dtype, c))
        if enc is None:
            raise ValueError(f"no default encoding for a {arr.dtype} image with {c} channel(s); give encoding=")
        if bigendian and arr.dtype.itemsize > 1:
            arr = arr.astype(arr.dtype.newbyteorder(">"))
        row = w * c * arr.dtype.itemsize
        step = row if step is None else int(step)
        rows = np.zeros((h, step), np.uint8)
        rows[:, :row] = np.ascontiguousarray(arr).view(np.uint8).reshape(h, row)
        msg = self.typestore.types["sensor_msgs/msg/Image"](
            header=self._header(stamp_ns, frame_id), height=h, width=w, encoding=enc, is_bigendian=int(bigendian),
            step=step, data=rows.reshape(-1))
        self.add_message(topic, msg, stamp_ns if log_time_ns is None else log_time_ns)

    def add_compressed(self, topic: str, data: bytes | np.ndarray, fmt: str, stamp_ns: int, log_time_ns: int | None = None,
                       frame_id: str = "camera") -> None:
        """A ``sensor_msgs/CompressedImage`` holding ``data`` (e.g. ``cv2.imencode(".png", img)[1]``)."""
        msg = self.typestore.types["sensor_msgs/msg/CompressedImage"](
            header=self._header(stamp_ns, frame_id), format=fmt, data=np.frombuffer(bytes(data), np.uint8).copy())
        self.add_message(topic, msg, stamp_ns if log_time_ns is None else log_time_ns)

    def add_number(self, topic: str, value: float, log_time_ns: int, msgtype: str = "std_msgs/msg/Float64") -> None:
        """A ``std_msgs`` number (``Float64``, ``Float32``, ``Int32``, …) in its ``data`` field."""
        cls = self.typestore.types[msgtype]
        self.add_message(topic, cls(data=value if "Float" in msgtype else int(value)), log_time_ns)

    def add_temperature(self, topic: str, celsius: float, stamp_ns: int, log_time_ns: int | None = None,
                        frame_id: str = "camera") -> None:
        """A ``sensor_msgs/Temperature`` (°C, with a header)."""
        msg = self.typestore.types["sensor_msgs/msg/Temperature"](header=self._header(stamp_ns, frame_id),
                                                                  temperature=float(celsius), variance=0.0)
        self.add_message(topic, msg, stamp_ns if log_time_ns is None else log_time_ns)

    def close(self) -> Path:
        """Finish the file; returns :attr:`path`."""
        if self._writer is None:
            return self.path
        writer, self._writer = self._writer, None
        try:
            writer.close()
            if self._tmp is not None:
                self._file.replace(self.path)
        finally:
            if self._tmp is not None:
                self._rmtree(self._tmp, ignore_errors=True)
        return self.path

    def __enter__(self) -> "RecordingWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
