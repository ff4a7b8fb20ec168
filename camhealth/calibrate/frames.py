"""Sets of calibration frames: what a set is, how it is read, and the file-name convention.

A set is N frames of one kind taken at one operating point:

* ``bias`` — shutter closed (or lens capped), the shortest exposure: read noise;
* ``dark`` — shutter closed, longer exposures (and, if the camera allows, several temperatures): dark current;
* ``flat`` — a uniform, constant light field (e.g. a diffuser over the lens, an integrating sphere) at one
  exposure or light level: photon transfer.

Frames come from a folder of images (natural file order), a video file, a list of image files, or an
in-memory array/tensor ``N×H×W`` / ``N×1×H×W`` in [0, 1]. Colour input is converted to gray by
camhealth's BT.601 rule (:func:`camhealth.data.io.to_gray`), exactly as everywhere else in camhealth.

File-name convention (when no manifest is given): ``<kind>_<token>_<token>…``, the kind first, then in any
order ``<t>s`` / ``<t>ms`` / ``<t>us`` (exposure), ``<g>dB`` (gain), ``<T>C`` (sensor temperature in °C);
other tokens (e.g. ``L3`` for a light level) name the set; a trailing frame number of an image file
(``dark_100ms_12dB_40C_0007.png``) is dropped, so the image files of one set group together. Folders and
videos are named the same way (``flat_10ms_0dB_25C_L3/``, ``dark_200ms_0dB_60C.mp4``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from camhealth.physics.metadata import METADATA_RANGES

__all__ = ["KINDS", "MIN_FRAMES", "FrameSet", "parse_set_name", "sets_from_paths", "check_max_frames", "load_frames"]

#: Kinds of calibration sets.
KINDS: tuple[str, ...] = ("bias", "dark", "flat")
#: Frames a set needs at least (temporal variance, hot pixels, master frames); 20 are recommended.
MIN_FRAMES = 4

_EXPOSURE = re.compile(r"^(\d+(?:\.\d+)?(?:e-?\d+)?)(s|ms|us)$", re.IGNORECASE)
_GAIN = re.compile(r"^(\d+(?:\.\d+)?)db$", re.IGNORECASE)
_TEMPERATURE = re.compile(r"^(-?\d+(?:\.\d+)?)c$", re.IGNORECASE)
_FRAME_NUMBER = re.compile(r"^\d+$")


@dataclass
class FrameSet:
    """One set of calibration frames and its operating point.

    Attributes:
        kind: ``"bias"``, ``"dark"`` or ``"flat"``.
        exposure_s: exposure time [s] (any positive value; calibration frames may be longer than 0.2 s).
        gain_db: camera gain [dB] (the model's "digital gain": DN per electron scales with 10^(dB/20)), within
            camhealth's gain range ``METADATA_RANGES['gain_db']`` (0 … 24 dB).
        temperature_c: sensor temperature [°C].
        paths: image files, one folder of frames, or one video file; or empty when ``frames`` is given.
        frames: in-memory frames ``N×H×W`` or ``N×1×H×W`` in [0, 1] (numpy or torch).
        name: label in reports and errors (default: the path or the parameters).
    """

    kind: str
    exposure_s: float
    gain_db: float = 0.0
    temperature_c: float = 25.0
    paths: list[Path] = field(default_factory=list)
    frames: object | None = field(default=None, repr=False)
    name: str = ""

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"set {self.name or self.paths!s}: kind {self.kind!r} must be one of {list(KINDS)}")
        for attr in ("exposure_s", "gain_db", "temperature_c"):
            v = getattr(self, attr)
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise ValueError(f"set {self.name or self.paths!s}: {attr} = {v!r} must be a number") from None
            if not math.isfinite(v):
                raise ValueError(f"set {self.name or self.paths!s}: {attr} = {v!r} must be finite")
            setattr(self, attr, v)
        if self.exposure_s <= 0:
            raise ValueError(f"set {self.name or self.paths!s}: exposure_s = {self.exposure_s:g} s must be > 0")
        g_lo, g_hi = METADATA_RANGES["gain_db"]
        if not g_lo <= self.gain_db <= g_hi:
            raise ValueError(
                f"set {self.name or self.paths!s}: gain_db = {self.gain_db:g} dB is outside camhealth's gain range [{g_lo:g}, {g_hi:g}] dB"
            )
        if not -60.0 <= self.temperature_c <= 150.0:
            raise ValueError(f"set {self.name or self.paths!s}: temperature_c = {self.temperature_c:g} °C is not a sensor temperature")
        self.paths = [Path(p) for p in self.paths]
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


def parse_set_name(stem: str) -> dict:
    """Kind, exposure, gain, temperature and label from a name following the convention (module docstring).

    Returns a dict with ``kind`` and those of ``exposure_s``, ``gain_db``, ``temperature_c`` the name gives,
    plus ``label`` (the remaining tokens). Raises ``ValueError`` if the first token is not a kind.
    """
    tokens = [t for t in re.split(r"[_\s]+", stem) if t]
    if not tokens or tokens[0].lower() not in KINDS:
        raise ValueError(
            f"cannot tell the kind of {stem!r}: a name must start with one of {list(KINDS)} "
            "(e.g. dark_100ms_12dB_40C), or give a manifest"
        )
    out: dict = {"kind": tokens[0].lower()}
    rest = []
    for tok in tokens[1:]:
        if m := _EXPOSURE.match(tok):
            out["exposure_s"] = float(m.group(1)) * {"s": 1.0, "ms": 1e-3, "us": 1e-6}[m.group(2).lower()]
        elif m := _GAIN.match(tok):
            out["gain_db"] = float(m.group(1))
        elif m := _TEMPERATURE.match(tok):
            out["temperature_c"] = float(m.group(1))
        else:
            rest.append(tok)
    out["label"] = "_".join(rest)
    return out


def _is_video(p: Path) -> bool:
    from camhealth.data.video import VIDEO_EXTENSIONS

    return p.suffix.lower() in VIDEO_EXTENSIONS


def sets_from_paths(paths: Sequence[str | Path], gain_db: float | None = None, temperature_c: float | None = None) -> list[FrameSet]:
    """Frame sets from folders, videos and image files named by the convention (module docstring).

    Image files whose names differ only in a trailing frame number form one set. ``gain_db`` and
    ``temperature_c`` fill in a name that does not give them; a name without an exposure is an error, as is
    a missing gain or temperature with no default.
    """
    from camhealth.data.io import IMAGE_EXTENSIONS

    groups: dict[tuple, list[Path]] = {}
    params: dict[tuple, dict] = {}
    missing = [str(p) for p in paths if not Path(p).exists()]
    if missing:
        raise FileNotFoundError(f"{len(missing)} frame path(s) not found: {', '.join(missing[:10])}" + (" …" if len(missing) > 10 else ""))
    for raw in paths:
        p = Path(raw)
        if p.is_dir() or _is_video(p):
            stem, key_paths = p.name if p.is_dir() else p.stem, [p]
        elif p.suffix.lower() in IMAGE_EXTENSIONS:
            tokens = p.stem.split("_")
            if len(tokens) > 1 and _FRAME_NUMBER.match(tokens[-1]):
                tokens = tokens[:-1]
            stem, key_paths = "_".join(tokens), [p]
        else:
            raise ValueError(f"cannot use {p} as calibration frames: expected a folder, a video or an image file ({', '.join(IMAGE_EXTENSIONS)})")
        info = parse_set_name(stem)
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
        sets.append(FrameSet(info["kind"], info["exposure_s"], info["gain_db"], info["temperature_c"], paths=sorted(ps), name=name))
    return sets


def _file_bits(path: Path) -> int | str:
    """The scale of an image file's integers for a calibration: the PNG's ``sBIT`` bits where it has them, else the
    file's own (8 or 16) — never a guess from the frame's content, which would scale a dark frame and a flat frame of
    one camera differently. ``"auto"`` for floating-point files (read as [0, 1])."""
    from camhealth.data.io import read_image_scaled

    _, scaling = read_image_scaled(path)
    if scaling.file_bits is None:
        return "auto"
    return scaling.bits if scaling.source == "sBIT" else scaling.file_bits


def check_max_frames(max_frames: int | None) -> None:
    """Raises ``ValueError`` unless ``max_frames`` is None (every frame) or an integer ≥ :data:`MIN_FRAMES`."""
    if max_frames is None:
        return
    if isinstance(max_frames, bool) or not isinstance(max_frames, (int, np.integer)) or max_frames < MIN_FRAMES:
        raise ValueError(f"max_frames = {max_frames!r} must be None (every frame) or an integer ≥ {MIN_FRAMES} (the frames a set needs)")


def load_frames(fs: FrameSet, max_frames: int | None = None) -> np.ndarray:
    """The frames of a set as float32 ``N×H×W`` in [0, 1] (at most ``max_frames``: None or ≥ :data:`MIN_FRAMES`).

    Raises ``ValueError`` naming the set for mixed frame sizes, values outside [0, 1] or unreadable files, and for
    a ``max_frames`` that is neither None nor ≥ :data:`MIN_FRAMES`.
    """
    check_max_frames(max_frames)
    if fs.frames is not None:
        x = fs.frames
        if hasattr(x, "detach"):
            x = x.detach().cpu().float().numpy()
        if isinstance(x, (list, tuple)):  # a list of frames: one size, or the error names the set and the sizes
            shapes = [tuple(np.shape(f.detach().cpu() if hasattr(f, "detach") else f))[-2:] for f in x]
            sizes = {sz: shapes.count(sz) for sz in dict.fromkeys(shapes)}
            if len(sizes) > 1:
                detail = "; ".join(f"{h}×{w}: {n} frame(s)" for (h, w), n in sizes.items())
                raise ValueError(f"{fs.describe()} mixes frame sizes ({detail}); every frame of a calibration must have one size")
            x = [f.detach().cpu().float().numpy() if hasattr(f, "detach") else f for f in x]
        x = np.asarray(x, dtype=np.float32)
        if x.ndim == 4 and x.shape[1] == 1:
            x = x[:, 0]
        if x.ndim == 2:
            x = x[None]
        if x.ndim != 3:
            raise ValueError(f"{fs.describe()}: in-memory frames must be N×H×W or N×1×H×W, got shape {x.shape}")
        if not np.isfinite(x).all() or x.min(initial=0.0) < 0 or x.max(initial=0.0) > 1:
            raise ValueError(f"{fs.describe()}: frame values must be finite and in [0, 1] (DN/255)")
        return x[:max_frames] if max_frames else x
    from camhealth.data.io import read_image_scaled
    from camhealth.data.video import FrameSequence

    frames: list[np.ndarray] = []
    sources: list[str] = []
    for p in fs.paths:
        if p.is_dir() or _is_video(p):
            seq = FrameSequence(p, max_frames=max_frames)
            bits = _file_bits(seq.frame_paths[0]) if seq.kind == "folder" and seq.frame_paths else "auto"
            for frame, idx in FrameSequence(p, max_frames=max_frames, bit_depth=bits):
                frames.append(frame[0].numpy())
                sources.append(f"{p}#{idx}")
                if max_frames and len(frames) >= max_frames:
                    break
        else:
            image, _ = read_image_scaled(p, _file_bits(p))
            frames.append(image[0].numpy())
            sources.append(str(p))
        if max_frames and len(frames) >= max_frames:
            break
    shapes = {f.shape for f in frames}
    if len(shapes) > 1:
        by_shape: dict[tuple, list[str]] = {}
        for f, s in zip(frames, sources):
            by_shape.setdefault(f.shape, []).append(s)
        detail = "; ".join(f"{h}×{w}: {len(v)} frame(s), e.g. {v[0]}" for (h, w), v in by_shape.items())
        raise ValueError(f"{fs.describe()} mixes frame sizes ({detail}); every frame of a calibration must have one size")
    return np.stack(frames).astype(np.float32) if frames else np.zeros((0, 1, 1), np.float32)
