"""Sets of calibration frames: what a set is, how it is read, and the file-name convention.

A set is N frames of one kind taken at one operating point:

* ``bias`` — shutter closed (or lens capped), the shortest exposure: read noise;
* ``dark`` — shutter closed, longer exposures (and, if the camera allows, several temperatures): dark current;
* ``flat`` — a uniform, constant light field (e.g. a diffuser over the lens, an integrating sphere) at one
  exposure or light level: photon transfer.

Frames come from a folder of images (natural file order), a video file, a list of image files, or an
in-memory array/tensor ``N×H×W`` / ``N×1×H×W`` (or a list of ``H×W`` / ``1×H×W`` frames) of real numbers in
[0, 1]. 8-bit data (k/255) held in float16 or bfloat16 are read as whole DN again (half precision moves k/255 by up
to 0.12 or 0.25 DN); other bfloat16 data are refused (8 significant bits: a rounding of up to ±0.5 DN, noise the
calibration would measure). They must be the sensor's own (raw or mono) samples:
a colour image file or video frame — one whose red, green and blue samples differ — is refused, since the gray
camhealth's BT.601 rule (:func:`camhealth.data.io.to_gray`) makes of it averages three channels' noise, which is
not one pixel's (its photon transfer gives a full well 2–3× too large). A gray image saved as RGB (its three
samples equal) is read as gray.

File-name convention (when no manifest is given): ``<kind>_<token>_<token>…``, the kind first, then in any
order ``<t>s`` / ``<t>ms`` / ``<t>us`` (exposure), ``<g>dB`` (gain, ``+6dB`` too), ``<T>C`` / ``<T>°C`` /
``<T>degC`` (sensor temperature in °C, ``-10C`` too); other tokens (e.g. ``L3`` for a light level) name the set;
a trailing frame number of an image file (``dark_100ms_12dB_40C_0007.png``) is dropped, so the image files of one
set group together. Folders and videos are named the same way (``flat_10ms_0dB_25C_L3/``,
``dark_200ms_0dB_60C.mkv``). A token shaped like an exposure, gain or temperature (a number and one of those
units) that is not a valid number, lies outside its range, or repeats a kind of token already given is an error
naming it, never a label.

Image files are read at the bit depth they declare: 8-bit files as value/255, 16-bit PNGs with an ``sBIT`` chunk
as value/(2^sBIT − 1), other 16-bit files as value/65535 unless the set's ``bit_depth`` (``--bit-depth``) says how
many of their low bits are used; a float16 image file holding 8-bit data is read as whole DN, as in-memory frames
are. Every frame of a set must have one bit depth and scaling. A video must use a lossless codec
(:data:`LOSSLESS_CODECS`): lossy ones remove the noise being measured, and are refused; so are JPEG image files
(:data:`LOSSY_IMAGE_EXTENSIONS`, or a JPEG under another name) and TIFF files with JPEG compression, for the same
reason.
"""

from __future__ import annotations

import math
import os
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from camhealth.physics.metadata import METADATA_RANGES

__all__ = [
    "KINDS", "MIN_FRAMES", "MAX_EXPOSURE_S", "TEMPERATURE_RANGE_C", "BIT_DEPTH_RANGE", "LOSSLESS_CODECS",
    "LOSSY_IMAGE_EXTENSIONS", "FrameSet", "FrameDepth", "LoadedDepth", "parse_set_name", "convention_stem",
    "sets_from_paths", "check_max_frames", "check_bit_depth", "check_video_codec", "check_image_format", "load_frames",
    "load_frames_with_depth",
]

#: Kinds of calibration sets.
KINDS: tuple[str, ...] = ("bias", "dark", "flat")
#: Frames a set needs at least (temporal variance, hot pixels, master frames); 20 are recommended.
MIN_FRAMES = 4
#: Longest exposure [s] a set may have (one hour: far beyond any calibration frame; a larger value is a slip, e.g.
#: milliseconds given as seconds, and its dark-signal prediction would overflow).
MAX_EXPOSURE_S = 3600.0

#: Sensor temperatures [°C] a set may have (the operating point written to the metadata is clipped to camhealth's
#: ``METADATA_RANGES['temperature_c']``).
TEMPERATURE_RANGE_C: tuple[float, float] = (-60.0, 150.0)
#: Significant bits a set's ``bit_depth`` may give for 16-bit image files without an ``sBIT`` chunk.
BIT_DEPTH_RANGE: tuple[int, int] = (8, 16)
#: Video codecs (FOURCC as OpenCV reports it, case-insensitive) accepted as lossless: FFV1, HuffYUV, Lagarith,
#: Ut Video, MagicYUV, PNG and uncompressed video (OpenCV reports raw video as FOURCC 0).
LOSSLESS_CODECS: dict[str, str] = {
    "ffv1": "FFV1", "hfyu": "HuffYUV", "ffvh": "HuffYUV", "huff": "HuffYUV", "lags": "Lagarith",
    "uly0": "Ut Video", "uly2": "Ut Video", "uly4": "Ut Video", "ulh0": "Ut Video", "ulh2": "Ut Video",
    "ulh4": "Ut Video", "ulrg": "Ut Video", "ulra": "Ut Video", "magy": "MagicYUV", "mpng": "PNG", "png": "PNG",
    "y800": "uncompressed gray", "grey": "uncompressed gray", "y8": "uncompressed gray", "y16": "uncompressed gray",
    "dib": "uncompressed", "rgb": "uncompressed", "raw": "uncompressed", "rawv": "uncompressed", "": "uncompressed",
}
#: Image file extensions refused as calibration frames: JPEG is lossy, like the video codecs outside
#: :data:`LOSSLESS_CODECS`.
LOSSY_IMAGE_EXTENSIONS: tuple[str, ...] = (".jpg", ".jpeg")
#: TIFF compressions (tifffile's ``COMPRESSION`` values) refused for the same reason: the JPEG family.
_LOSSY_TIFF_COMPRESSIONS: dict[int, str] = {6: "old-style JPEG", 7: "JPEG", 99: "JPEG", 33004: "lossy JPEG 2000",
                                            33007: "JPEG", 34892: "lossy JPEG"}
#: Half-precision types whose 8-bit data are restored to whole DN (:func:`_half_as_8bit`).
_HALF_NAMES: tuple[str, ...] = ("float16", "bfloat16")
_LOSSY_WHY = ("lossy compression removes part of the temporal noise a calibration measures (and adds its own block "
              "artefacts), so its read noise and full well would be wrong")

_NUMBER = r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:e[+-]?\d+)?"
_EXPOSURE = re.compile(rf"^({_NUMBER})(s|ms|us|µs)$", re.IGNORECASE)
_GAIN = re.compile(rf"^({_NUMBER})db$", re.IGNORECASE)
_TEMPERATURE = re.compile(rf"^({_NUMBER})(?:c|°c|ºc|degc)$", re.IGNORECASE)
#: A token that looks like a number with a unit: digits, signs, points, commas, exponent letters before the unit.
_SHAPED = re.compile(r"^[+-]?[\d.,]+(?:e[+-]?[\d.,]*)?\s*(ms|us|µs|s|db|degc|°c|ºc|c)$", re.IGNORECASE)
_FRAME_NUMBER = re.compile(r"^\d+$")
_UNIT_ONLY = {"s": "exposure_s", "ms": "exposure_s", "us": "exposure_s", "µs": "exposure_s", "db": "gain_db",
              "c": "temperature_c", "°c": "temperature_c", "ºc": "temperature_c", "degc": "temperature_c"}
_SPELLINGS = {
    "exposure_s": "exposure: 100ms, 0.1s, 500us",
    "gain_db": "gain: 12dB, +6dB, 0.5dB",
    "temperature_c": "temperature: 40C, 40°C, 40degC, -10C",
}


@dataclass
class FrameSet:
    """One set of calibration frames and its operating point.

    Attributes:
        kind: ``"bias"``, ``"dark"`` or ``"flat"``.
        exposure_s: exposure time [s] in (0, :data:`MAX_EXPOSURE_S`] (calibration frames may be longer than 0.2 s).
            It, the gain and the temperature are numbers: a bool (``True`` read as 1 s) is refused.
        gain_db: camera gain [dB] (the model's "digital gain": DN per electron scales with 10^(dB/20)), within
            camhealth's gain range ``METADATA_RANGES['gain_db']`` (0 … 24 dB).
        temperature_c: sensor temperature [°C].
        paths: image files, one folder of frames, or one video file (str or :class:`~pathlib.Path`; a single one
            may be given on its own); or empty when ``frames`` is given.
        frames: in-memory frames ``N×H×W`` or ``N×1×H×W`` in [0, 1] (numpy or torch; or a list of ``H×W`` /
            ``1×H×W`` frames), real numbers (complex, text and other non-numeric data are refused).
        name: label in reports and errors (default: the path or the parameters).
        bit_depth: significant bits of its 16-bit image files that have no ``sBIT`` chunk (values 0 … 2^bits − 1
            stored in the low bits, e.g. 12 for a 12-bit camera written by OpenCV), in :data:`BIT_DEPTH_RANGE`;
            ``None``: such files use the whole 16-bit range. 8-bit files, PNGs with ``sBIT`` and videos ignore it;
            for in-memory frames only 16 counts: values on the 16-bit grid (k/65535) are then 16-bit data, which the
            calibration does not take for low-bit codes divided by 65535 (``pipeline.LOW_BITS_CODES``).
        origin: where the set was given (``"manifest m.yaml, set 3"``), named in errors about reading its files.
    """

    kind: str
    exposure_s: float
    gain_db: float = 0.0
    temperature_c: float = 25.0
    paths: list[Path] = field(default_factory=list)
    frames: object | None = field(default=None, repr=False)
    name: str = ""
    bit_depth: int | None = None
    origin: str = field(default="", repr=False, compare=False)

    def __post_init__(self) -> None:
        self.paths = _path_list(self.paths, f"set {self.name or self.kind!s}")
        where = f"set {self.name or self.paths or self.kind!s}"
        if self.kind not in KINDS:
            raise ValueError(f"{where}: kind {self.kind!r} must be one of {list(KINDS)}")
        allowed = {"exposure_s": "of seconds > 0", "gain_db": "of dB in [{:g}, {:g}]".format(*METADATA_RANGES["gain_db"]),
                   "temperature_c": "of °C in [{:g}, {:g}]".format(*TEMPERATURE_RANGE_C)}
        for attr in ("exposure_s", "gain_db", "temperature_c"):
            v = getattr(self, attr)
            if isinstance(v, (bool, np.bool_)):  # True as 1 s or 1 dB is a slip, not a value
                raise ValueError(f"{where}: {attr} = {v!r} must be a number {allowed[attr]}, not a bool")
            try:
                v = float(v)
            except (TypeError, ValueError, OverflowError) as exc:
                finite = " finite" if isinstance(exc, OverflowError) else ""
                raise ValueError(f"{where}: {attr} = {_brief(v)} must be a{finite} number {allowed[attr]}") from None
            if not math.isfinite(v):
                raise ValueError(f"{where}: {attr} = {v!r} must be finite")
            setattr(self, attr, v)
        if self.exposure_s <= 0:
            raise ValueError(f"{where}: exposure_s = {self.exposure_s:g} s must be > 0")
        if self.exposure_s > MAX_EXPOSURE_S:
            raise ValueError(f"{where}: exposure_s = {self.exposure_s:g} s is outside (0, {MAX_EXPOSURE_S:g}] s (one hour at "
                             "most: milliseconds given as seconds?)")
        g_lo, g_hi = METADATA_RANGES["gain_db"]
        if not g_lo <= self.gain_db <= g_hi:
            raise ValueError(
                f"{where}: gain_db = {self.gain_db:g} dB is outside camhealth's gain range [{g_lo:g}, {g_hi:g}] dB"
            )
        t_lo, t_hi = TEMPERATURE_RANGE_C
        if not t_lo <= self.temperature_c <= t_hi:
            m_lo, m_hi = METADATA_RANGES["temperature_c"]
            raise ValueError(
                f"{where}: temperature_c = {self.temperature_c:g} °C is not a sensor temperature: it "
                f"must lie in [{t_lo:g}, {t_hi:g}] °C (the operating point written to the metadata is clipped to camhealth's "
                f"{m_lo:g} … {m_hi:g} °C)"
            )
        self.bit_depth = check_bit_depth(self.bit_depth, where)
        if not self.paths and self.frames is None:
            raise ValueError(f"set {self.name!r} ({self.kind}) has neither paths nor frames")
        if not self.name:
            self.name = (
                str(self.paths[0]) + (f" (+{len(self.paths) - 1} files)" if len(self.paths) > 1 else "")
                if self.paths else f"{self.kind} {self.exposure_s:g} s {self.gain_db:g} dB {self.temperature_c:g} °C"
            )

    @property
    def gain_factor(self) -> float:
        """Amplitude gain 10^(dB/20) [–]."""
        return 10.0 ** (self.gain_db / 20.0)

    @property
    def temperature_k(self) -> float:
        """Sensor temperature [K]."""
        return self.temperature_c + 273.15

    def describe(self) -> str:
        return f"{self.kind} set {self.name!r} ({self.exposure_s:g} s, {self.gain_db:g} dB, {self.temperature_c:g} °C)"


def _brief(value: object, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters for a message; an int too long for ``repr`` (more digits than
    ``sys.get_int_max_str_digits()``) is described instead of raising."""
    try:
        text = repr(value)
    except ValueError:
        return f"<an integer of more than {sys.get_int_max_str_digits()} digits>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _path_list(paths: object, where: str) -> list[Path]:
    """A set's ``paths`` as a list of :class:`~pathlib.Path`: one str or path-like is one path (not its characters),
    else an iterable of them; anything else raises ``ValueError`` naming ``where`` and the value."""
    if isinstance(paths, (str, os.PathLike)):
        return [Path(paths)]
    try:
        items = list(paths) if not isinstance(paths, (bytes, bytearray)) else None
    except TypeError:
        items = None
    if items is None:
        raise ValueError(f"{where}: paths = {_brief(paths, 80)} must be a path (str or Path) or a list of them")
    bad = [p for p in items if not isinstance(p, (str, os.PathLike))]
    if bad:
        raise ValueError(f"{where}: paths must be str or Path, got {type(bad[0]).__name__} {_brief(bad[0])}")
    return [Path(p) for p in items]


def parse_set_name(stem: str) -> dict:
    """Kind, exposure, gain, temperature and label from a name following the convention (module docstring).

    Returns a dict with ``kind`` and those of ``exposure_s``, ``gain_db``, ``temperature_c`` the name gives,
    plus ``label`` (the remaining tokens). Raises ``ValueError`` if the first token is not a kind, and naming the
    token and the accepted spellings for a token shaped like an exposure, gain or temperature that is not a valid
    number (``12,5dB``), lies outside its range (an exposure ≤ 0 s or above :data:`MAX_EXPOSURE_S`, a gain outside ``METADATA_RANGES['gain_db']``,
    a temperature outside :data:`TEMPERATURE_RANGE_C`), or repeats a kind of token the name already gave.
    """
    tokens = [t for t in re.split(r"[_\s]+", stem) if t]
    if not tokens or tokens[0].lower() not in KINDS:
        raise ValueError(
            f"cannot tell the kind of {stem!r}: a name must start with one of {list(KINDS)} "
            "(e.g. dark_100ms_12dB_40C), or give a manifest"
        )
    out: dict = {"kind": tokens[0].lower()}
    seen: dict[str, str] = {}
    rest = []
    g_lo, g_hi = METADATA_RANGES["gain_db"]
    t_lo, t_hi = TEMPERATURE_RANGE_C

    def refuse(tok: str, key: str, why: str) -> ValueError:
        return ValueError(f"{stem!r}: token {tok!r} {why}; accepted spellings of the {_SPELLINGS[key]} "
                          "(or give the set in a manifest)")

    for tok in tokens[1:]:
        if m := _EXPOSURE.match(tok):
            key, value = "exposure_s", float(m.group(1)) * {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6}[m.group(2).lower()]
            if not (math.isfinite(value) and 0 < value <= MAX_EXPOSURE_S):
                raise refuse(tok, key, f"gives an exposure of {value:g} s, outside (0, {MAX_EXPOSURE_S:g}] s")
        elif m := _GAIN.match(tok):
            key, value = "gain_db", float(m.group(1))
            if not g_lo <= value <= g_hi:
                raise refuse(tok, key, f"gives a gain of {value:g} dB, outside camhealth's gain range [{g_lo:g}, {g_hi:g}] dB")
        elif m := _TEMPERATURE.match(tok):
            key, value = "temperature_c", float(m.group(1))
            if not t_lo <= value <= t_hi:
                raise refuse(tok, key, f"gives a sensor temperature of {value:g} °C, outside [{t_lo:g}, {t_hi:g}] °C")
        elif m := _SHAPED.match(tok):
            unit = m.group(1).lower()
            key = "gain_db" if unit == "db" else "exposure_s" if unit.endswith("s") else "temperature_c"
            raise refuse(tok, key, f"looks like {'an exposure' if key == 'exposure_s' else 'a gain' if key == 'gain_db' else 'a temperature'} "
                                   "but is not a number with that unit")
        elif (u := _UNIT_ONLY.get(tok.lower())) and rest and re.fullmatch(_NUMBER, rest[-1], re.IGNORECASE):
            raise refuse(f"{rest[-1]} {tok}", u, "splits a number from its unit")
        else:
            rest.append(tok)
            continue
        if key in seen:
            raise ValueError(f"{stem!r}: tokens {seen[key]!r} and {tok!r} both give the {key.split('_')[0]}; a name gives each "
                             f"of exposure, gain and temperature at most once ({_SPELLINGS[key]})")
        seen[key] = tok
        out[key] = value
    out["label"] = "_".join(rest)
    return out


def _is_video(p: Path) -> bool:
    from camhealth.data.video import VIDEO_EXTENSIONS

    return p.suffix.lower() in VIDEO_EXTENSIONS


def convention_stem(path: str | Path) -> str:
    """The part of a path the file-name convention reads: a folder's name, a video's stem, or an image file's stem
    without its trailing frame number (``dark_100ms_12dB_40C_0007.png`` → ``dark_100ms_12dB_40C``)."""
    p = Path(path)
    if p.is_dir():
        return p.name
    if _is_video(p):
        return p.stem
    tokens = p.stem.split("_")
    if len(tokens) > 1 and _FRAME_NUMBER.match(tokens[-1]):
        tokens = tokens[:-1]
    return "_".join(tokens)


def sets_from_paths(paths: Sequence[str | Path], gain_db: float | None = None, temperature_c: float | None = None,
                    bit_depth: int | None = None) -> list[FrameSet]:
    """Frame sets from folders, videos and image files named by the convention (module docstring).

    Image files whose names differ only in a trailing frame number form one set. ``gain_db`` and
    ``temperature_c`` fill in a name that does not give them; a name without an exposure is an error, as is
    a missing gain or temperature with no default, a malformed, out-of-range or repeated token
    (:func:`parse_set_name`; the message names the path), and a JPEG image file (:func:`check_image_format`).
    ``bit_depth`` is every set's :attr:`FrameSet.bit_depth`.
    """
    from camhealth.data.io import IMAGE_EXTENSIONS

    groups: dict[tuple, list[Path]] = {}
    params: dict[tuple, dict] = {}
    missing = [str(p) for p in paths if not Path(p).exists()]
    if missing:
        raise FileNotFoundError(f"{len(missing)} frame path(s) not found: {', '.join(missing[:10])}" + (" …" if len(missing) > 10 else ""))
    usable = [e for e in IMAGE_EXTENSIONS if e not in LOSSY_IMAGE_EXTENSIONS]
    for raw in paths:
        p = Path(raw)
        if not (p.is_dir() or _is_video(p) or p.suffix.lower() in IMAGE_EXTENSIONS):
            raise ValueError(f"cannot use {p} as calibration frames: expected a folder, a video or an image file ({', '.join(usable)})")
        if not p.is_dir() and not _is_video(p):
            check_image_format(p)
        key_paths = [p]
        try:
            info = parse_set_name(convention_stem(p))
        except ValueError as exc:
            raise ValueError(f"{p}: {exc}") from None
        if "exposure_s" not in info:
            raise ValueError(f"{p}: the name gives no exposure time (a token like 100ms, 0.1s or 500us); rename it or use a manifest")
        for key, default in (("gain_db", gain_db), ("temperature_c", temperature_c)):
            if key not in info:
                if default is None:
                    unit = "dB" if key == "gain_db" else "C"
                    raise ValueError(f"{p}: the name gives no {key} (a token like 12{unit}) and no default was given")
                info[key] = default
        # loose image files of one set share a key; every folder and video is a set of its own
        key = (info["kind"], info["exposure_s"], info["gain_db"], info["temperature_c"], info["label"])
        if p.is_dir() or _is_video(p):
            key = key + (str(p),)
        groups.setdefault(key, []).extend(key_paths)
        params[key] = info
    sets = []
    for key, ps in groups.items():
        info = params[key]
        name = str(ps[0]) if len(ps) == 1 else f"{ps[0].parent / ('_'.join(ps[0].stem.split('_')[:-1]) or ps[0].stem)}_* ({len(ps)} files)"
        sets.append(FrameSet(info["kind"], info["exposure_s"], info["gain_db"], info["temperature_c"], paths=sorted(ps), name=name,
                             bit_depth=bit_depth))
    return sets


def check_bit_depth(bit_depth: int | None, where: str = "bit_depth") -> int | None:
    """``bit_depth`` as an int, or None; raises ``ValueError`` naming ``where``, the value and :data:`BIT_DEPTH_RANGE`
    unless it is None or a whole number of bits in that range."""
    if bit_depth is None:
        return None
    lo, hi = BIT_DEPTH_RANGE
    ok = not isinstance(bit_depth, (bool, np.bool_)) and (  # (an int is not made a float: 10**400 would overflow)
        isinstance(bit_depth, (int, np.integer)) or (isinstance(bit_depth, (float, np.floating)) and float(bit_depth).is_integer()))
    if not ok or not lo <= int(bit_depth) <= hi:
        raise ValueError(f"{where}: bit_depth = {_brief(bit_depth)} must be None (16-bit files use their whole range) or a whole "
                         f"number of significant bits in [{lo}, {hi}]")
    return int(bit_depth)


def check_max_frames(max_frames: int | None) -> None:
    """Raises ``ValueError`` unless ``max_frames`` is None (every frame) or an integer ≥ :data:`MIN_FRAMES`."""
    if max_frames is None:
        return
    if isinstance(max_frames, bool) or not isinstance(max_frames, (int, np.integer)) or max_frames < MIN_FRAMES:
        raise ValueError(f"max_frames = {max_frames!r} must be None (every frame) or an integer ≥ {MIN_FRAMES} (the frames a set needs)")


def _fourcc_text(value: float) -> str:
    code = int(value) & 0xFFFFFFFF
    return "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4)).replace("\x00", "").strip()


def check_video_codec(path: str | Path) -> str:
    """The codec of a video (its FOURCC as OpenCV reports it; "" for uncompressed video), or ``ValueError`` naming
    the file and the codec when it is not one of :data:`LOSSLESS_CODECS`: a lossy codec (MJPEG, H.264, MPEG-4, VP8/9
    …) removes part of the temporal noise a calibration measures and adds its own, so its read noise and full well
    are wrong."""
    try:
        import cv2
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("reading video files needs OpenCV: pip install 'opencv-python-headless<5'") from exc

    p = Path(path)
    cap = cv2.VideoCapture(str(p))
    try:
        if not cap.isOpened():
            raise ValueError(f"cannot open video {p}: OpenCV could not open it (corrupt or unsupported codec)")
        codec = _fourcc_text(cap.get(cv2.CAP_PROP_FOURCC))
    finally:
        cap.release()
    if codec.lower() not in LOSSLESS_CODECS:
        names = sorted(set(LOSSLESS_CODECS.values()) - {"uncompressed gray"})
        raise ValueError(
            f"video {p} uses the codec {codec!r}, which is not lossless: a lossy codec removes part of the temporal noise a "
            f"calibration measures (and adds its own), so its read noise and full well would be wrong; record the set "
            f"losslessly ({', '.join(names)}; e.g. ffmpeg -c:v ffv1 -pix_fmt gray) or as 16-bit PNG/TIFF frames"
        )
    return codec


def _short(path: object, limit: int = 120) -> str:
    """A path for a message, its middle cut out when it is longer than ``limit`` characters."""
    text = str(path)
    return text if len(text) <= limit else f"{text[: limit // 2]}…{text[-(limit // 2 - 1):]} ({len(text)} characters)"


def check_image_format(path: str | Path, where: str = "") -> None:
    """Raises ``ValueError`` naming ``where`` (e.g. the set), the file and its format when an image file is lossily
    compressed: a JPEG file (by its extension, :data:`LOSSY_IMAGE_EXTENSIONS`, or its content under another name) or
    a TIFF whose first page is JPEG-compressed — for the reason lossy video codecs are refused
    (:func:`check_video_codec`). A file that cannot be opened is left to the reader, which names it."""
    p = Path(path)
    suffix = p.suffix.lower()
    fmt = "JPEG" if suffix in LOSSY_IMAGE_EXTENSIONS else None
    if fmt is None:
        try:
            with p.open("rb") as fh:
                head = fh.read(4)
        except OSError:
            return
        if head[:3] == b"\xff\xd8\xff":
            fmt = f"JPEG (under the extension {p.suffix!r})"
        elif suffix in (".tif", ".tiff") and head[:2] in (b"II", b"MM"):
            try:
                import tifffile

                with tifffile.TiffFile(p) as tif:
                    code = int(tif.pages[0].compression)
            except Exception:  # a corrupt TIFF: the reader names it
                return
            if code in _LOSSY_TIFF_COMPRESSIONS:
                fmt = f"TIFF with {_LOSSY_TIFF_COMPRESSIONS[code]} compression"
    if fmt is not None:
        raise ValueError(
            f"{where + ': ' if where else ''}image {_short(p)} is {fmt}, which is lossy: {_LOSSY_WHY}; record the set "
            "losslessly, as PNG or uncompressed (or LZW/Deflate) TIFF frames — 16-bit where the camera offers it — or a "
            "lossless video"
        )


@dataclass(frozen=True)
class FrameDepth:
    """How a frame's integers were scaled to [0, 1]: ``file_bits`` (8 or 16; None: floating-point data),
    ``bits`` (the values were divided by 2^bits − 1; None: not scaled) and ``source`` (``"file"``: the file's own
    depth, ``"sBIT"``: the PNG's sBIT chunk, ``"given"``: the set's ``bit_depth``, ``"video"``: a video's 8-bit
    frames, ``"float"``: floating-point data, ``"float16"`` / ``"bfloat16"``: 8-bit values k/255 held in that
    half-precision type, restored to k/255 (``bits`` 8))."""

    file_bits: int | None
    bits: int | None
    source: str

    def describe(self) -> str:
        if self.source == "float":
            return "floating-point data"
        if self.source in _HALF_NAMES:
            return f"8-bit values held in {self.source}"
        if self.source == "video":
            return "8-bit video frames"
        if self.file_bits == self.bits:
            return f"{self.file_bits}-bit"
        why = {"sBIT": "its sBIT chunk", "given": "the set's bit_depth"}.get(self.source, self.source)
        return f"{self.file_bits}-bit with {self.bits} significant bits ({why})"


def _is_colour(samples: np.ndarray) -> bool:
    """Whether H×W×C samples (C ≥ 3: RGB, RGBA or BGR(A)) hold colour: the three colour samples of some pixel differ
    (alpha is not compared). A gray image saved in an RGB format has them equal."""
    return samples.ndim == 3 and samples.shape[-1] >= 3 and bool(
        (samples[..., 0] != samples[..., 1]).any() or (samples[..., 1] != samples[..., 2]).any())


def _colour_error(fs: "FrameSet", source: str) -> ValueError:
    return ValueError(
        f"{fs.describe()}: {source} is a colour image (its red, green and blue samples differ); the gray camhealth's BT.601 "
        "rule makes of it averages three channels' noise, which is not one pixel's (its photon transfer gives a full well "
        "2–3× too large); give the camera's raw or mono frames (one sample per pixel: its Mono8/Mono16 or raw Bayer "
        "output, saved as gray images or a gray video), not a demosaiced colour image"
    )


def _half_as_8bit(x: np.ndarray, dtype: str) -> np.ndarray | None:
    """``x`` (float32, holding the values of a ``dtype`` = ``"float16"``/``"bfloat16"`` array exactly) restored to
    k/255 when every value is the half-precision rounding of some k/255 (:func:`camhealth._inputs._unround_8bit`,
    the estimators' rule, over the whole array), else None."""
    import torch

    from camhealth._inputs import _unround_8bit

    t = torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)).reshape(1, -1)
    snapped = _unround_8bit(t, getattr(torch, dtype))
    if not bool(((snapped * 255.0).round() / 255.0 == snapped).all()):
        return None
    return snapped.reshape(x.shape).numpy()


def _read_frame(p: Path, bit_depth: int | None) -> tuple[np.ndarray, FrameDepth, float | None, bool]:
    """One image file as H×W float32 in [0, 1] at the depth it declares (module docstring), its :class:`FrameDepth`,
    its largest value in codes when it is a 16-bit file read at 16 bits with neither sBIT nor ``bit_depth``
    (else None), and whether it is a colour image (:func:`_is_colour`; a file with 3 or 4 samples per pixel whose
    colour samples are all equal is a gray image and read as one). A float16 file whose every value is the float16
    rounding of some k/255 holds 8-bit data: it is read as k/255 (half precision moved them by up to 0.12 DN)."""
    from camhealth.data.io import read_image_scaled, read_samples

    image, sc = read_image_scaled(p)
    colour = sc.channels >= 3 and _is_colour(read_samples(p))
    frame = image[0].numpy()
    if sc.file_bits is None:
        if not colour and read_samples(p).dtype == np.float16:
            restored = _half_as_8bit(frame, "float16")
            if restored is not None:
                return restored, FrameDepth(None, 8, "float16"), None, colour
        return frame, FrameDepth(None, None, "float"), None, colour
    if sc.file_bits == 8:
        return frame, FrameDepth(8, 8, "file"), None, colour
    if sc.source == "sBIT":
        return frame, FrameDepth(16, int(sc.bits), "sBIT"), None, colour
    want, source = (bit_depth, "given") if bit_depth is not None else (16, "file")
    if sc.max_value > 2**want - 1:
        raise ValueError(f"cannot read image {p} as {want}-bit data (the set's bit_depth): it holds values up to "
                         f"{sc.max_value:g}, more than {2**want - 1}; give the camera's bit depth, or none for 16-bit data")
    if sc.bits != want:  # "auto" guessed a depth from the largest value: the codes at the declared depth instead
        codes = frame.astype(np.float64) * (2.0**sc.bits - 1.0)
        rounded = np.rint(codes)
        if float(np.abs(codes - rounded).max(initial=0.0)) < 1e-2:  # gray: exactly what a read at ``want`` bits gives
            frame = rounded.astype(np.float32) / np.float32(2**want - 1)
        else:  # colour turned gray: read it again at that depth
            frame = read_image_scaled(p, want)[0][0].numpy()
    return frame, FrameDepth(16, want, source), (float(sc.max_value) if source == "file" else None), colour


def _video_colour_frame(p: Path, n: int) -> int | None:
    """The index of the first of a video's first ``n`` frames that is colour (:func:`_is_colour` on the BGR frame
    OpenCV decodes), or None: a gray video (or gray frames in an RGB pixel format) decodes to equal samples."""
    import cv2

    cap = cv2.VideoCapture(str(p))
    try:
        for k in range(n):
            ok, frame = cap.read()
            if not ok or frame is None:
                return None
            if _is_colour(frame):
                return k
    finally:
        cap.release()
    return None


@dataclass
class LoadedDepth:
    """The depth of a loaded set: ``depth`` (its frames' :class:`FrameDepth`; None for in-memory frames) and
    ``undeclared_max`` (the largest value, in codes of 65535, of 16-bit files read at 16 bits with neither sBIT nor
    ``bit_depth``; None when the set has none; for in-memory frames the pipeline sets their largest value in codes of
    65535, with ``undeclared_file`` "" and ``grid16`` whether they lie on the 16-bit grid one code apart)."""

    depth: FrameDepth | None = None
    undeclared_max: float | None = None
    undeclared_file: str = ""
    grid16: bool = False


def _dtype_name(value: object) -> str:
    """The element type of an array or tensor (``"float16"``, ``"uint8"``, ``"bfloat16"`` …), else the type's name."""
    dtype = getattr(value, "dtype", None)
    return str(dtype).removeprefix("torch.") if dtype is not None else type(value).__name__


def _numeric_frames(value: object, what: str, where: str) -> np.ndarray:
    """One in-memory array or tensor (a set's frames, or one frame of a list) as a float32 numpy array; complex,
    text and other non-numeric data raise ``ValueError`` naming ``where``, ``what`` (subject and verb: "its frames
    are", "frame 3 is") and the type."""
    need = ("in-memory frames must be real numbers in [0, 1] (a numpy array or torch tensor N×H×W or N×1×H×W, or a "
            "list of H×W frames)")
    if hasattr(value, "detach"):  # torch
        if value.is_complex():
            raise ValueError(f"{where}: {what} complex ({_dtype_name(value)}); {need}")
        return value.detach().cpu().float().numpy()
    if isinstance(value, (str, bytes, dict, set)) or value is None:
        raise ValueError(f"{where}: {what} a {type(value).__name__} ({_brief(value, 40)}); {need}")
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:  # a ragged nesting of lists
        raise ValueError(f"{where}: {what} not an array of one shape ({str(exc).split('.')[0]}); {need}") from None
    kind = arr.dtype.kind
    if kind == "c":
        raise ValueError(f"{where}: {what} complex ({arr.dtype}); {need}")
    if kind not in "biuf":
        try:
            if kind != "O":
                raise TypeError
            return arr.astype(np.float32)  # (an object array of numbers)
        except (TypeError, ValueError):
            raise ValueError(f"{where}: {what} not numbers (dtype {arr.dtype}, e.g. "
                             f"{_brief(arr.ravel()[0] if arr.size else arr, 40)}); {need}") from None
    return arr.astype(np.float32, copy=False)


def _in_memory_frames(fs: FrameSet) -> tuple[np.ndarray, str]:
    """A set's in-memory frames as float32 ``N×H×W`` (values checked: finite, in [0, 1]) and the type they were given
    in (:func:`_dtype_name`; a list's when every frame has the same one, else ``"mixed"``). ``ValueError`` names the
    set and what is wrong: a frame layout other than N×H×W / N×1×H×W (a list: H×W / 1×H×W frames of one size),
    complex or non-numeric data, values that are not finite or outside [0, 1] (with their count and range; integers
    are DN, to be divided by 2^bits − 1)."""
    where = fs.describe()
    x = fs.frames
    if isinstance(x, (list, tuple)):  # a list of frames: H×W or 1×H×W, one size
        types = {_dtype_name(f) for f in x}
        dtype = types.pop() if len(types) == 1 else "mixed"
        frames = [_numeric_frames(f, f"frame {i} of its list is", where) for i, f in enumerate(x)]
        odd = [(i, f.shape) for i, f in enumerate(frames) if not (f.ndim == 2 or (f.ndim == 3 and f.shape[0] == 1))]
        if odd:
            i, shape = odd[0]
            raise ValueError(f"{where}: frame {i} of its list has shape {'×'.join(map(str, shape)) or '()'}; a list of "
                             "in-memory frames holds H×W (or 1×H×W) frames")
        frames = [f[0] if f.ndim == 3 else f for f in frames]
        shapes = [f.shape for f in frames]
        sizes = {sz: shapes.count(sz) for sz in dict.fromkeys(shapes)}
        if len(sizes) > 1:
            detail = "; ".join(f"{h}×{w}: {n} frame(s)" for (h, w), n in sizes.items())
            raise ValueError(f"{where} mixes frame sizes ({detail}); every frame of a calibration must have one size")
        x = np.stack(frames) if frames else np.zeros((0, 1, 1), np.float32)
    else:
        dtype = _dtype_name(x)
        x = _numeric_frames(x, "its frames are", where)
        if x.ndim == 4 and x.shape[1] == 1:
            x = x[:, 0]
        if x.ndim == 2:
            x = x[None]
        if x.ndim != 3:
            raise ValueError(f"{where}: in-memory frames must be N×H×W or N×1×H×W, got shape {x.shape}")
    if not x.size:  # no frames, or frames of 0×0 px: the set's checks name it
        return np.ascontiguousarray(x, dtype=np.float32), dtype
    if bool(np.isfinite(x).all()):
        n_bad, lo, hi = 0, float(x.min()), float(x.max())
    else:
        finite = x[np.isfinite(x)]
        n_bad = x.size - finite.size
        lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (math.nan, math.nan)
    if n_bad or lo < 0.0 or hi > 1.0:
        got = []
        if n_bad:
            got.append(f"{n_bad} NaN or infinite value(s) of {x.size}")
        if n_bad < x.size:
            got.append(f"values from {lo:.6g} to {hi:.6g}")
        hint = ""
        if dtype in ("uint8", "int8", "uint16", "int16", "int32", "uint32", "int64", "uint64"):
            hint = (f"; {dtype} frames are integers, i.e. DN: divide them by 2^bits − 1 (x / 255 for an 8-bit camera, "
                    "x / 4095 for a 12-bit one)")
        raise ValueError(f"{where}: in-memory frame values must be finite and in [0, 1] (DN/(2^bits − 1)), got "
                         f"{' and '.join(got)}{hint}")
    return np.ascontiguousarray(x, dtype=np.float32), dtype


def load_frames(fs: FrameSet, max_frames: int | None = None) -> np.ndarray:
    """The frames of a set as float32 ``N×H×W`` in [0, 1] (:func:`load_frames_with_depth` without the depth)."""
    return load_frames_with_depth(fs, max_frames)[0]


def load_frames_with_depth(fs: FrameSet, max_frames: int | None = None) -> tuple[np.ndarray, LoadedDepth]:
    """The frames of a set as float32 ``N×H×W`` in [0, 1] (at most ``max_frames``: None or ≥ :data:`MIN_FRAMES`), and
    how they were scaled (:class:`LoadedDepth`).

    Raises ``ValueError`` naming the set for mixed frame sizes, a colour image file or video frame (naming it; module
    docstring), mixed bit depths or scalings (naming the files of each), values outside [0, 1] or unreadable files
    (naming the set, where it was given — :attr:`FrameSet.origin` — and the file), a video whose codec is not lossless
    (:func:`check_video_codec`), a JPEG image file (:func:`check_image_format`), a file with values above its set's
    ``bit_depth``, in-memory frames of another layout, complex or non-numeric (naming what they are), bfloat16 frames
    that are not 8-bit data (module docstring), and for a ``max_frames`` that is neither None nor ≥ :data:`MIN_FRAMES`.
    """
    check_max_frames(max_frames)
    if fs.frames is not None:
        x, dtype = _in_memory_frames(fs)
        loaded = LoadedDepth()
        if dtype in _HALF_NAMES and x.size:
            restored = _half_as_8bit(x, dtype)
            if restored is not None:
                x, loaded.depth = restored, FrameDepth(None, 8, dtype)
            elif dtype == "bfloat16":
                raise ValueError(
                    f"{fs.describe()}: its frames are bfloat16, which holds 8 significant bits: its values are rounded to "
                    "steps of 1 DN above 128 DN (±0.5 DN) and 0.5 DN below, a rounding noise the calibration would measure as "
                    "the camera's, and they are not 8-bit data (k/255) that could be read as whole DN; give the frames as "
                    "float32 (or float16, or an 8-bit camera's DN/255 values)"
                )
        return (x[:max_frames] if max_frames else x), loaded
    from camhealth.data.video import FrameSequence

    frames: list[np.ndarray] = []
    sources: list[str] = []
    depths: list[FrameDepth] = []
    loaded = LoadedDepth()

    def add(frame: np.ndarray, depth: FrameDepth, undeclared: float | None, colour: bool, source: str) -> None:
        if colour:  # BT.601 luma averages three channels' noise: not one sensor pixel's
            raise _colour_error(fs, source)
        frames.append(frame)
        sources.append(source)
        depths.append(depth)
        if undeclared is not None and (loaded.undeclared_max is None or undeclared > loaded.undeclared_max):
            loaded.undeclared_max, loaded.undeclared_file = undeclared, source

    where = fs.describe() + (f" ({fs.origin})" if fs.origin else "")

    def read(fp: Path) -> tuple[np.ndarray, FrameDepth, float | None, bool]:
        check_image_format(fp, where)
        try:
            return _read_frame(fp, fs.bit_depth)
        except OSError as exc:  # (a permission, a disk; FileNotFoundError: a file removed since it was listed)
            raise ValueError(f"{where}: cannot read {_short(fp)}: {exc.strerror or exc}") from None

    for p in fs.paths:
        if p.is_dir():
            try:
                seq = FrameSequence(p, max_frames=max_frames)
            except OSError as exc:
                raise ValueError(f"{where}: cannot read the folder {_short(p)}: {exc.strerror or exc}") from None
            for fp in (seq.frame_paths or [])[: seq.length]:
                add(*read(fp), str(fp))
                if max_frames and len(frames) >= max_frames:
                    break
        elif _is_video(p):
            check_video_codec(p)
            first = len(frames)
            for frame, idx in FrameSequence(p, max_frames=max_frames):
                add(frame[0].numpy(), FrameDepth(8, 8, "video"), None, False, f"{p}#{idx}")
                if max_frames and len(frames) >= max_frames:
                    break
            colour = _video_colour_frame(p, len(frames) - first)
            if colour is not None:
                raise _colour_error(fs, f"frame {colour} of video {p}")
        else:
            add(*read(p), str(p))
        if max_frames and len(frames) >= max_frames:
            break
    shapes = {f.shape for f in frames}
    if len(shapes) > 1:
        by_shape: dict[tuple, list[str]] = {}
        for f, s in zip(frames, sources):
            by_shape.setdefault(f.shape, []).append(s)
        detail = "; ".join(f"{h}×{w}: {len(v)} frame(s), e.g. {v[0]}" for (h, w), v in by_shape.items())
        raise ValueError(f"{fs.describe()} mixes frame sizes ({detail}); every frame of a calibration must have one size")
    by_depth: dict[FrameDepth, list[str]] = {}
    for d, s in zip(depths, sources):
        by_depth.setdefault(d, []).append(s)
    if len(by_depth) > 1:
        detail = "; ".join(f"{d.describe()}: {len(v)} frame(s) ({', '.join(v[:3])}{', …' if len(v) > 3 else ''})"
                           for d, v in by_depth.items())
        raise ValueError(f"{fs.describe()} mixes bit depths ({detail}); every frame of a set must have one bit depth and "
                         "scaling: its quantisation step (and the q²/12 removed from its variance) is the set's")
    loaded.depth = depths[0] if depths else None
    return (np.stack(frames).astype(np.float32) if frames else np.zeros((0, 1, 1), np.float32)), loaded
