"""Real-time camera monitor: frames in, condition (blur, noise per source, ξ alarm) and advice out.

:class:`Monitor` runs the estimators of :mod:`camhealth.inference` patch-wise on every frame, but only where
the scene needs it (:mod:`camhealth.monitor.tiling`), in one of two modes:

- ``"sampled"`` (the default unless per-patch maps are asked for): a few informative patches per frame — flat
  ones spread over the intensities for noise (a camera-state property), ones with edges spread over the frame
  for blur — rotating over the frame across frames, the frame answer pooled over the last ``window`` frames;
  its cost does not depend on the scene or on camera motion (a moving camera); with ``adaptive`` a sampled patch
  whose content has not changed since its last estimate (and is not due for its periodic refresh) keeps that
  estimate, so a static camera sends fewer patches to the estimators once every patch has been sampled;
- ``"map"``: every informative patch (skip black/saturated/featureless/no-edge patches, reuse estimates of static
  regions, coarse lattice first and refine only where it changes), with per-patch maps;

and reports one :class:`FrameReport` per frame (a JSON line) with the coverage of each task:

- **MTF** (H and V at the 8 normalised frequencies f_n ∈ {0.05, …, 0.6}, dimensionless) on the informative
  192-px patches and the IOPC blur indicator MTF̃ (mean of H and V at f_n = 0.1);
- **noise** σ of photon shot (PN), dark-current shot (DCSN) and readout noise (RN), the residual ξ
  (Eq. 4.3: ξ = σ_Model(M) − σ_Image(M'), DN) and the total σ (√(σ_PN² + σ_DCSN² + σ_RN²), Eq. 4.2 without
  ξ), all in DN of 255, on the informative 128-px patches;
- **uncertainty by temporal median aggregation** (thesis Sec. 5.6, Eq. 5.4), map mode: every patch keeps its last
  ``window`` new values (network estimates, or interpolations from freshly estimated neighbours; a reused
  value adds no new information and is not added again); its value is their median σ̃_n and its temporal
  spread 1.4826·MAD (:func:`camhealth.estimators.aggregation.temporal_median`). The frame value is the median
  over the informative patches (the spatial median of Sec. 5.7, as in Eq. 4.4 but over the whole frame,
  :func:`~camhealth.estimators.aggregation.spatial_median`) with its spatial spread; ``temporal_spread``
  is the median of the patches' temporal spreads, ``current`` the spatial median of this frame alone.
  A change of metadata (gain, exposure, …) starts the aggregation afresh.
- **ξ alarm**: ξ̃ < −limit → the image is *noisier* than the metadata allow (wrong gain/temperature in
  the metadata, a defective sensor, or noise added downstream); ξ̃ > +limit → *cleaner* (e.g. a denoiser
  in the pipeline, or metadata that overstate gain). limit = max(``xi_threshold_dn``,
  k·1.2533·spread/√n) — the absolute threshold or k standard errors of the median, whichever is larger.
- **advice** of an :class:`camhealth.control.ExposurePolicy` (Eq. 4.5–4.8) built from IOPC files:
  α* and the new exposure/gain for σ̃ and MTF̃ at the current metadata.

Frames are gray float tensors in [0, 1] (DN/255), or arrays of 8-bit DN; colour is converted with the
BT.601 luma of :func:`camhealth.data.to_gray`. Everything runs under :func:`torch.inference_mode` with
batched network calls (``precision="bf16"`` by default, CPU autocast; ``"fp32"`` for reference).
"""

from __future__ import annotations

import collections
import inspect
import json
import math
import os
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np
import torch

from camhealth.estimators.aggregation import spatial_median, temporal_median
from camhealth.estimators.jpeg_quantisation import coded_frame
from camhealth.estimators.mtf_error import frame_uncertainty
from camhealth.estimators.physics_noise import BEYOND_VALIDATED, LESS_NOISE, LOSSY_CODEC, VALIDATED_SIGMA_DN
from camhealth.monitor.tiling import (
    ESTIMATED,
    INTERPOLATED,
    NOT_ASSESSABLE,
    REUSED,
    UNSAMPLED,
    STATUS_NAMES,
    PatchGrid,
    SelectionConfig,
    StaticRegions,
    coarse_lattice,
    grid_statistics,
    quiet_patches,
    refine_plan,
    sample_patches,
    select_patches,
    status_counts,
)
from camhealth.physics.metadata import (
    FULL_FIELDS,
    METADATA_RANGES,
    METADATA_SETS,
    MINIMAL_FIELDS,
    PRESETS,
    CameraMetadata,
    read_metadata_mapping,
)
from camhealth.physics.mtf import NORMALIZED_FREQUENCIES

__all__ = [
    "NOISE_FIELDS",
    "TASKS",
    "MODES",
    "Monitor",
    "FrameReport",
    "TaskReport",
    "as_frame",
    "load_metadata",
    "load_policy",
    "xi_alarm",
    "beyond_range_alarm",
    "banding_text",
    "defects_text",
    "new_defect_ppm",
    "DEFECT_ALARM_PPM",
    "mtf_under_banding",
    "CAUSE_GROUPS",
    "cause_text",
    "group_causes",
    "top_cause",
    "MTF_BANDING_LIMIT_DN",
    "MAX_WINDOW",
    "MAX_SAMPLES",
    "FrameSizeError",
    "InputScalingChanged",
]

#: Columns of the per-patch noise values (DN): σ per source, ξ, total.
NOISE_FIELDS: tuple[str, ...] = ("pn", "dcsn", "rn", "xi", "total")
#: The monitor's tasks and the estimator kinds each accepts.
TASKS: dict[str, tuple[str, ...]] = {"noise": ("noise_source", "drne"), "mtf": ("mtf",)}
#: Standard error of a median = √(π/2)·σ/√n for Gaussian scatter.
_MEDIAN_SE = math.sqrt(math.pi / 2.0)
_VALUE_STATUS = (ESTIMATED, INTERPOLATED, REUSED)
#: Monitor modes: ``"sampled"`` (a few patches per frame, frame-level answer), ``"map"`` (every informative
#: patch, per-patch maps) and ``"auto"`` (``"map"`` when per-patch output is asked for, else ``"sampled"``).
MODES: tuple[str, ...] = ("auto", "sampled", "map")
#: The largest ``window`` (frames of the temporal median): 200× the default 5, 100 s of a 10 frames/s stream. The
#: aggregation keeps ``window`` values of every patch, allocated at once (``window`` × patches × 16 values): a larger
#: window would take gigabytes, or fail to allocate, on a large frame, and a camera state rarely holds that long.
MAX_WINDOW = 1000
#: The largest ``noise_samples`` and ``mtf_samples`` (patches per frame in sampled mode): 32× the default 8, more than
#: the 128-px patches of a 1920×1080 frame (120; a frame with fewer informative patches samples all of them). The window keeps
#: ``window`` × samples × 16 values per task, allocated at once.
MAX_SAMPLES = 256


class FrameSizeError(ValueError):
    """A frame whose size does not fit the monitor's defect map (:meth:`Monitor.process`): that frame is refused, the
    monitor is unchanged and goes on with the next frame (the CLI writes a ``frame_error`` line for it)."""


class InputScalingChanged(UserWarning):
    """:meth:`Monitor.process` was given a frame scaled to [0, 1] differently from the frame before (``input_scaling``):
    the temporal aggregation restarted."""


# ---------------------------------------------------------------------------------------------- inputs
def _check_bit_depth(bit_depth: Any) -> int | None:
    """``bit_depth`` of :func:`as_frame`: ``None`` or an integer 8…16 (ValueError naming the value otherwise)."""
    if bit_depth is None:
        return None
    if isinstance(bit_depth, (bool, np.bool_)) or not isinstance(bit_depth, (int, np.integer)) or not 8 <= bit_depth <= 16:
        raise ValueError(f"bit_depth = {bit_depth!r} must be None or an integer 8…16: the significant bits of uint16 "
                         "frames (10, 12 or 14 for a camera that stores such data in 16-bit words; None or 16: the full "
                         "16-bit word)")
    return int(bit_depth)


def _integer_scale(dtype: str, bit_depth: int | None) -> float:
    """The divisor of an integer frame of ``dtype`` (``"uint8"``, ``"uint16"``, another integer type of 8-bit DN) for
    ``bit_depth`` (:func:`as_frame`); ValueError where ``bit_depth`` does not fit the frame's type."""
    if dtype == "uint16":
        return float(2 ** (16 if bit_depth is None else bit_depth) - 1)
    if bit_depth not in (None, 8):
        raise ValueError(f"bit_depth = {bit_depth} is for uint16 frames; this frame is {dtype}, read as 8-bit DN "
                         "(DN/255): give bit_depth=None (or 8)")
    return 255.0


def _check_bits(hi: float, bit_depth: int | None) -> None:
    """A uint16 frame's largest value ``hi`` must fit ``bit_depth`` bits (:func:`as_frame`); without ``bit_depth``, a
    frame whose values fit 14 bits or fewer gets a ``UserWarning`` (once per place it is read from, Python's default):
    a 10-, 12- or 14-bit camera's frame read as 16-bit data is 4–64× too dark, and its noise reads as texture."""
    if bit_depth is None and 0 < hi <= 2**14 - 1:
        bits = next(b for b in (10, 12, 14) if hi <= 2**b - 1)
        warnings.warn(f"uint16 frame read as 16-bit data (÷65535), but its largest value {hi:g} fits {bits} bits: if "
                      f"the camera delivers {bits} bits, pass bit_depth={bits} (read as 16-bit data the frame is "
                      f"{2 ** (16 - bits)}× too dark to judge its noise and blur)", UserWarning, stacklevel=4)
    if bit_depth is not None and bit_depth < 16 and hi > 2**bit_depth - 1:
        raise ValueError(f"uint16 frame value {hi:g} exceeds the {bit_depth}-bit range 0…{2**bit_depth - 1} "
                         f"(bit_depth = {bit_depth}); give the camera's real bit depth (None or 16 if it fills the "
                         "16-bit word)")


def as_frame(frame: Any, bit_depth: int | None = None) -> torch.Tensor:
    """A frame as a 1×1×H×W float32 tensor in [0, 1].

    Accepts a torch tensor (H×W, C×H×W or 1×C×H×W, channels first) or a NumPy array (H×W or H×W×C,
    channels last, RGB order), C ∈ {1, 2, 3, 4} (colour → BT.601 luma, alpha dropped); an array of either byte order
    (e.g. big-endian ``>u2``) is read as its values. uint8 is DN/255; uint16 is DN/(2^bit_depth − 1): ``bit_depth`` ``None`` (default) or 16 divides by 65535 (the full 16-bit word),
    10, 12 or 14 (any integer 8…16) by 1023, 4095 or 16383 — a value above that range is refused. Nothing is guessed
    here: :func:`camhealth.data.read_image` (the CLI's reader) takes the depth of a 16-bit file from its PNG
    ``sBIT`` chunk or its largest value by default, so pass the camera's ``bit_depth`` for 10-, 12- or 14-bit data in
    uint16 arrays. Other integers are 8-bit DN that must lie in [0, 255]; floats must lie in [0, 1]; ``bit_depth``
    applies to uint16 frames only (``None`` or 8 for other integers, ``None`` for floats). Raises
    ``TypeError``/``ValueError`` naming the problem.
    """
    from camhealth.data.io import to_gray

    bit_depth = _check_bit_depth(bit_depth)
    from_integers = False
    if isinstance(frame, np.ndarray):
        if frame.dtype == np.bool_ or frame.dtype.kind not in "uif":
            raise TypeError(f"frame must be a numeric array (uint8 DN or float in [0, 1]), got dtype {frame.dtype}")
        arr = frame
        if not arr.dtype.isnative:  # e.g. '>u2' (a big-endian uint16 image): the same values in this machine's order
            arr = arr.astype(arr.dtype.newbyteorder("="))
        if arr.ndim == 3 and arr.shape[-1] not in (1, 2, 3, 4) and arr.shape[0] == 1:
            arr = arr[0]
        if arr.ndim not in (2, 3):
            raise ValueError(f"frame must be H×W or H×W×C (channels last), got shape {arr.shape}")
        if arr.dtype.kind in "ui":
            scale = _integer_scale(str(arr.dtype) if arr.dtype in (np.uint8, np.uint16) else f"{arr.dtype} (8-bit DN)",
                                   bit_depth)
            hi = float(arr.max()) if arr.size else 0.0
            lo = float(arr.min()) if arr.size else 0.0
            if arr.dtype not in (np.uint8, np.uint16) and (lo < 0 or hi > 255):
                raise ValueError(f"integer frame values are 8-bit DN and must lie in [0, 255], got min {lo:g}, max {hi:g}")
            if arr.dtype == np.uint16:
                _check_bits(hi, bit_depth)
            arr = arr.astype(np.float32) / np.float32(scale)
            from_integers = True
        elif bit_depth is not None:
            raise ValueError(f"bit_depth = {bit_depth} is for uint16 frames; this frame is {arr.dtype} in [0, 1]: give "
                             "bit_depth=None")
        gray = to_gray(arr) if arr.ndim == 3 else arr
        if not from_integers:  # checked before float32, which would turn a float64 1e300 into inf
            _check_float_values(torch.from_numpy(np.ascontiguousarray(gray)))
        x = torch.from_numpy(np.ascontiguousarray(gray, dtype=np.float32))
    elif isinstance(frame, torch.Tensor):
        if frame.is_nested or frame.layout != torch.strided or frame.is_meta or frame.is_quantized:
            kind = ("a nested tensor: give one frame" if frame.is_nested else "a meta tensor, which holds no data"
                    if frame.is_meta else "a quantized tensor: .dequantize() it first" if frame.is_quantized
                    else f"a {frame.layout} tensor: .to_dense() it first")
            raise TypeError(f"frame must be a dense tensor holding its pixel values, got {kind}")
        if frame.dtype == torch.bool or frame.is_complex():
            raise TypeError(f"frame must be a real numeric tensor, got dtype {frame.dtype}")
        x = frame.detach().cpu()
        if x.ndim == 4:
            if x.shape[0] != 1:
                raise ValueError(f"process one frame at a time: got a batch of {x.shape[0]} (shape {tuple(x.shape)})")
            x = x[0]
        if not x.is_floating_point():
            names = {torch.uint8: "uint8", torch.uint16: "uint16"}
            scale = _integer_scale(names.get(x.dtype, f"{x.dtype} (8-bit DN)"), bit_depth)
            if x.dtype not in (torch.uint8, torch.uint16):  # (in range by their type; torch has no min of uint16)
                wide = x.to(torch.float64) if x.dtype in (torch.uint32, torch.uint64) else x  # (no min of those either)
                lo, hi = (float(wide.min()), float(wide.max())) if x.numel() else (0.0, 0.0)
                if lo < 0 or hi > 255:
                    raise ValueError(f"integer frame values are 8-bit DN and must lie in [0, 255], got min {lo:g}, max {hi:g}")
            x = x.float()
            if names.get(frame.dtype) == "uint16" and x.numel():
                _check_bits(float(x.max()), bit_depth)
            x = x.div_(scale)
            from_integers = True
        elif bit_depth is not None:
            raise ValueError(f"bit_depth = {bit_depth} is for uint16 frames; this frame is {x.dtype} in [0, 1]: give "
                             "bit_depth=None")
        if x.ndim == 3:
            if x.shape[0] not in (1, 2, 3, 4):
                raise ValueError(f"frame must be C×H×W with C in 1…4 (channels first), got shape {tuple(frame.shape)}")
            x = to_gray(x)[0]
        elif x.ndim != 2:
            raise ValueError(f"frame must be H×W, C×H×W or 1×C×H×W, got shape {tuple(frame.shape)}")
        if not from_integers and x.numel():  # checked before float32, which would turn a float64 1e300 into inf
            _check_float_values(x)
        x = x.float()
    else:
        raise TypeError(f"frame must be a torch.Tensor or numpy.ndarray, got {type(frame).__name__}")
    if x.numel() == 0:
        raise ValueError(f"frame is empty (shape {tuple(x.shape)})")
    if from_integers:  # DN / max: finite and in [0, 1] by construction
        return x.contiguous()[None, None]
    return x.clamp(0, 1).contiguous()[None, None]


def _check_float_values(x: torch.Tensor) -> None:
    """A float frame's values (in their own precision, before float32) must be finite and lie in [0, 1]."""
    if x.numel() == 0:
        return
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"frame holds {int((~torch.isfinite(x)).sum())} non-finite value(s) (NaN/inf)")
    lo, hi = float(x.min()), float(x.max())
    if lo < -1e-6 or hi > 1 + 1e-6:
        hint = " (looks like DN: pass a uint8 array or divide by 255)" if hi <= 255 and lo >= 0 else ""
        raise ValueError(f"float frame values must lie in [0, 1], got min {lo:g}, max {hi:g}{hint}")


def _frame_label(index: Any, source_id: Any) -> tuple[int | None, str | None]:
    """:meth:`Monitor.process`'s ``index`` (``None`` or an integer: a NumPy or 0-d torch integer becomes an ``int``) and
    ``source_id`` (``None``, a text or a path, which becomes its text), checked before the frame is read: the JSON line
    of the report holds them. ``TypeError`` naming the value otherwise."""
    if isinstance(index, torch.Tensor) and index.numel() == 1 and not index.is_floating_point() and not index.is_complex() \
            and index.dtype != torch.bool:
        index = int(index.item())
    if index is not None:
        if isinstance(index, (bool, np.bool_)) or not isinstance(index, (int, np.integer)):
            raise TypeError(f"index = {index!r} must be None or an integer (the frame's index in its source), got "
                            f"{type(index).__name__}")
        index = int(index)
    if isinstance(source_id, os.PathLike):
        source_id = os.fspath(source_id)
    if source_id is not None and not isinstance(source_id, str):
        raise TypeError(f"source_id = {source_id!r} must be None, a text or a path (the frame's file or stream name), "
                        f"got {type(source_id).__name__}")
    return index, source_id


def _python_number(value: Any) -> Any:
    """A NumPy integer or floating-point scalar as the Python ``int`` or ``float`` it holds, for the checks of a
    numeric argument; anything else (a bool, NumPy's too, which stays refused where a number is asked) as given."""
    if isinstance(value, (bool, np.bool_)):
        return value
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return float(value)
    return value


def _one_number(key: str, value: Any) -> float:
    """A per-frame metadata value as one number in physical units: an int or float, or a NumPy / torch scalar (a
    one-element array or tensor); a bool, a string or several values (a batch of camera states) are refused, and so are
    ``sensor`` and ``sensor_type``, which name the camera, not a field of a frame's state."""
    if key == "sensor":
        raise ValueError(f"per-frame metadata: sensor = {value!r} is not a per-frame field (a frame's mapping changes "
                         "fields of the monitor's camera state, a number each, e.g. gain_db, exposure_s); name the "
                         "sensor preset for the run: Monitor(sensor=…) or its metadata (--sensor or the --metadata "
                         "file on the command line), or give this frame's whole state as "
                         f"CameraMetadata.preset({value!r}, gain_db=…, exposure_s=…)")
    if key == "sensor_type":
        raise ValueError(f"per-frame metadata: sensor_type = {value!r} is not a per-frame field (a frame's mapping "
                         "changes fields of the monitor's camera state, a number each); give is_cmos (1 CMOS, 0 CCD) "
                         "for a frame, or the sensor for the run: sensor_type in the monitor's metadata (the "
                         "--metadata file on the command line) or a sensor preset, Monitor(sensor=…) (--sensor)")
    if key == "is_cmos" and isinstance(value, (bool, np.bool_)):
        return float(value)
    if value is None or isinstance(value, bool) or isinstance(value, (np.bool_, str, bytes)):
        raise ValueError(f"per-frame metadata: field {key} = {value!r} must be a number in physical units")
    if isinstance(value, (int, float)):
        return float(value)
    try:
        arr = np.asarray(value.detach().cpu() if isinstance(value, torch.Tensor) else value)
        if arr.dtype.kind == "b" and key != "is_cmos":  # a 0-d bool array or tensor is True/False, not a number
            raise ValueError
        if arr.dtype.kind in "cUS":  # (complex: its imaginary part would be dropped; text: as a plain string)
            raise ValueError
        arr = arr.astype(np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"per-frame metadata: field {key} = {value!r} must be a number in physical units") from None
    if arr.size != 1:
        raise ValueError(f"per-frame metadata: field {key} holds {arr.size} values; a frame has one camera state "
                         "(one number per field)")
    return float(arr.reshape(-1)[0])


def _input_scaling(scaling: Any) -> tuple[Any, str | None, bool]:
    """(what a change is judged by, the text the report carries, whether the scale was guessed from the frame's values)
    of :meth:`Monitor.process`'s ``input_scaling``: ``None``; an :class:`~camhealth.data.io.ImageScaling` — judged by its
    bits (the divisor 2^bits − 1: a frame read at another divisor is on another scale, however the file stored it),
    reported as its ``describe()``; or a text, judged and reported as it is."""
    if scaling is None:
        return None, None, False
    if isinstance(scaling, str):
        return ("text", scaling), scaling, False
    if hasattr(scaling, "describe") and hasattr(scaling, "bits") and hasattr(scaling, "source"):
        return ("bits", scaling.bits), scaling.describe(), scaling.source in ("largest value", "sequence")
    raise TypeError(f"input_scaling = {scaling!r} must be None, a text or a camhealth.data.io.ImageScaling, "
                    f"got {type(scaling).__name__}")


def load_metadata(
    source: CameraMetadata | Mapping[str, Any] | str | Path | None = None,
    sensor: str | None = None,
    required: str = "full",
) -> CameraMetadata | None:
    """Camera metadata (batch 1, physical units) from a file, a mapping or a preset, validated.

    Args:
        source: ``None``; a :class:`CameraMetadata`; a mapping of fields (``gain_db``, ``exposure_s``, …,
            see :data:`camhealth.physics.metadata.FULL_FIELDS`; ``sensor_type: CCD|CMOS`` for ``is_cmos``;
            ``sensor: ICX285`` names a preset that fills the missing fields); or a ``.json``/``.yaml`` file
            holding such a mapping.
        sensor: preset (``"ICX285"``, ``"EV76C661"``) that fills fields the source does not give (and the
            metadata when ``source`` is ``None``).
        required: the metadata set the estimator reads: ``"full"`` (all 11 fields must be known),
            ``"minimal"`` (gain, exposure, temperature; the other fields, which such a network does not
            read, default to the ICX285 preset) or ``"none"``.

    Returns:
        the metadata, or ``None`` if neither ``source`` nor ``sensor`` is given.

    Raises:
        FileNotFoundError / ValueError naming the file, the missing fields or the field, value and allowed
        range (:data:`camhealth.physics.metadata.METADATA_RANGES`).
    """
    return _load_metadata(source, sensor, required)[0]


def _load_metadata(
    source: CameraMetadata | Mapping[str, Any] | str | Path | None, sensor: str | None, required: str
) -> tuple[CameraMetadata | None, set[str] | None]:
    """:func:`load_metadata`, and the fields the caller gave where the ICX285 preset filled the others without anyone
    naming it (``required`` ``"none"`` or ``"minimal"``, no ``sensor``); ``None`` where every field was given or came
    from a named preset."""
    if required not in METADATA_SETS:
        raise ValueError(f"required = {required!r} must be one of {list(METADATA_SETS)}")
    if sensor is not None and str(sensor).upper() not in PRESETS:
        raise ValueError(f"unknown sensor preset {sensor!r}; known presets: {sorted(PRESETS)}")
    if isinstance(source, CameraMetadata):
        if source.batch_size != 1:
            raise ValueError(f"monitor metadata must describe one camera state (batch 1), got batch {source.batch_size}")
        return source, None
    if source is None:
        return (None if sensor is None else CameraMetadata.preset(sensor)), None
    origin = "metadata"
    if isinstance(source, (str, Path)):
        origin = f"metadata file {source}"
        data = read_metadata_mapping(Path(source))
    elif isinstance(source, Mapping):
        data = dict(source)
    else:
        raise TypeError(f"metadata must be CameraMetadata, a mapping or a .json/.yaml path, got {type(source).__name__}")
    base = data.pop("sensor", None)
    if sensor is not None:
        if base is not None and str(base).upper() != str(sensor).upper():
            raise ValueError(f"{origin} names sensor {base!r} but sensor={sensor!r} was given; use one")
        base = sensor
    if base is not None and str(base).upper() not in PRESETS:
        raise ValueError(f"{origin}: unknown sensor preset {base!r}; known presets: {sorted(PRESETS)}")
    for key, value in data.items():
        if key == "sensor_type" or (key == "is_cmos" and isinstance(value, bool)):
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{origin}: field {key} = {value!r} must be a number in physical units")
    given = set(data) | ({"is_cmos"} if "sensor_type" in data else set())
    filled = None
    if base is None:
        need = FULL_FIELDS if required == "full" else MINIMAL_FIELDS if required == "minimal" else ()
        missing = [f for f in need if f not in given]
        if missing:
            raise ValueError(
                f"{origin} is missing field(s) {missing} that the noise estimator reads ({required!r} metadata set); "
                f"add them or name a sensor preset ({sorted(PRESETS)}) that fills them"
            )
        if required != "full" and any(f not in given for f in FULL_FIELDS):
            base, filled = "ICX285", given  # fields a Min-Meta network (or none) never reads
    try:
        return CameraMetadata.from_dict(data, base=base), filled
    except (ValueError, TypeError) as exc:  # (TypeError: a sensor_type that is no string)
        raise ValueError(f"{origin}: {exc}") from None


def load_policy(
    iopc_files: Sequence[str | Path],
    exposure_limits_s: tuple[float, float] = METADATA_RANGES["exposure_s"],
    gain_limits_db: tuple[float, float] = METADATA_RANGES["gain_db"],
    weights: Sequence[float] | None = None,
) -> Any:
    """An :class:`camhealth.control.ExposurePolicy` from IOPC files (``.json``/``.npz`` written by
    ``python -m camhealth.iopc``), with the camera's exposure [s] and gain [dB] limits and optional
    application weights λ (Eq. 4.8). Raises ``ImportError`` if :mod:`camhealth.control` is not available."""
    try:
        from camhealth.control import CameraLimits, ExposurePolicy
        from camhealth.iopc import IOPC
    except ImportError as exc:
        raise ImportError(
            f"an IOPC policy needs camhealth.control and camhealth.iopc, which cannot be imported here ({exc})"
        ) from None
    files = [Path(p) for p in iopc_files]
    if not files:
        raise ValueError("load_policy needs at least one IOPC file")
    if weights is not None and len(weights) != len(files):
        raise ValueError(f"{len(weights)} weight(s) for {len(files)} IOPC file(s); give one per file")
    curves = [IOPC.load(p) for p in files]
    apps = list(zip(curves, [float(w) for w in weights])) if weights is not None else curves
    return ExposurePolicy(apps, limits=CameraLimits(tuple(exposure_limits_s), tuple(gain_limits_db)))


# ---------------------------------------------------------------------------------------------- reports
def _num(x: Any, nd: int = 4) -> Any:
    """JSON-safe rounded float (NaN/inf → None); lists recursively."""
    if isinstance(x, torch.Tensor):
        x = x.tolist()
    if isinstance(x, (list, tuple)):
        return [_num(v, nd) for v in x]
    if x is None:
        return None
    v = float(x)
    return round(v, nd) if math.isfinite(v) else None


@dataclass
class TaskReport:
    """One task's result for one frame (see :meth:`to_dict` for the JSON layout).

    Attributes:
        task: ``"noise"`` or ``"mtf"``.
        estimator: description of the estimator.
        patch: patch side [px]; grid: (rows, cols).
        assessable: at least one informative patch had a value.
        median, spread, temporal_spread, current: (K,) frame values (see the module docstring); K = 5
            (:data:`NOISE_FIELDS`, DN) or 16 (MTF H then V).
        indicator: MTF only: (median, spread) of the per-patch blur indicator MTF̃.
        uncertainty: (K,) standard error of ``median``: the larger of 1.2533·spread/√n (the standard error of a
            median of n values with Gaussian scatter ``spread``, n = ``n_values``) and 1.2533·temporal_spread/√frames
            (a pooled noise estimate gives every patch of a frame one camera state: only frames are independent).
            With an estimator that reports a per-value uncertainty (MTF ``mtf_std``; noise ``sigma_std`` and ``xi_std``):
            also at least 1.2533·estimator_std/√n, so one patch's answer is not stated exact — for the MTF
            estimator_std·√(ρ + (π/2)(1 − ρ)/n), ρ the share of the error the patches of one scene have in common (its
            error table's ``shared``; 1.2533·estimator_std/√n at ρ = 0) — or, for the noise pooled per frame (every
            patch shares the frame's posterior, so its error is common to them), estimator_std/√frames.
        indicator_uncertainty: the same for the indicator.
        estimator_std: (K,) the estimator's own per-value uncertainty, pooled over the values behind ``median`` —
            √(mean of std²) over the values that have a finite one. MTF: ``mtf_std``, each value's 1-σ uncertainty
            from the estimator's error table and its views' spread (:meth:`camhealth.inference.Estimator.predict`).
            Noise (``noise_source_full``): ``sigma_std`` for PN, DCSN and RN and ``xi_std`` for ξ and the total, the
            posterior's spread (:func:`camhealth.estimators.physics_noise.physics_noise_posterior`). NaN (JSON
            ``null``) when the estimator gives none (a network, or an MTF file without an error table at
            ``mtf_views`` 1). It is the typical error bar of one patch's value, not of ``median``.
        n_values: number of values behind ``median``, the n of its standard error (map mode: patches with a value;
            sampled mode: the distinct estimates among the window's samples — a static patch's kept estimate, reused in
            several frames, counts once).
        coverage: where the networks ran this frame (see :meth:`Monitor.process`): ``mode``, ``estimated``
            (patches sent to the network this frame and assessable), ``reused`` (patches that kept their last estimate,
            no network call), ``informative``, ``total``, ``area_fraction`` (estimated area / frame area), ``values``
            (= n_values), ``frames`` (frames behind the answer, up to the window: those that gave a value — a
            black, saturated or wholly refused frame adds none), ``patches_xy`` (sampled mode: top-left corners [px]
            of the patches estimated this frame; map mode: ``None``, the per-patch map says where).
        counts: patches per status (:data:`~camhealth.monitor.tiling.STATUS_NAMES`) and ``total``.
        refused: this frame's patches the estimator refused (status ``not_assessable``), by the reason it gave —
            e.g. ``{"textured": 3, "noise beyond validated range": 1}`` for the noise sources, ``{"no edges": 2}``
            for the MTF; empty when it refused none.
        beyond_xi: noise only: the median ξ [DN] the estimator still reports on this frame's patches refused as
            ``"noise beyond validated range"`` whose noise it read (``follows_image``; σ above
            :data:`~camhealth.estimators.physics_noise.VALIDATED_SIGMA_DN`; there the image's σ reads low, so the ξ is
            a bound: the image is at least that much noisier); ``None`` when there were none.
        banding: noise only: row and column noise (offsets shared by whole pixel rows or columns, which no metadata
            field makes; :mod:`camhealth.estimators.row_column_noise`) on this frame's assessable patches where the
            estimator reports it (``row_column_dn``) — those estimated this frame and those reused, with the evidence
            of their last estimate (as their values): ``{"row_dn", "col_dn"}`` the medians over the patches with any
            [DN] (0 for a direction none shows) and ``"patches"``; ``None`` when no patch shows any. It is part of
            σ_Total and ξ, and the alarm names it.
        defects: noise only: pixels that stand above (``hot``) or below (``dark``) all their neighbours by far more
            than the local noise (hot, stuck or dead pixels, impulses, or the scene's own points of light;
            :mod:`camhealth.estimators.defective_pixels`) on this frame's estimated patches, every one of them
            (assessable or not), and on its reused patches as their last estimate found them: ``{"hot", "dark",
            "checked"`` (pixels tested), ``"ppm"`` (per million tested),
            ``"patches"`` (with any), ``"recurring"}`` (at a pixel where an earlier frame of the run had one too: a
            defect stays where it is while the scene moves), and with a defect map (``Monitor(defect_map=...)``)
            ``"known"`` (at a pixel the map marks); ``None`` when no pixel stands out. Not part of σ_Total; the alarm
            names them from :data:`DEFECT_ALARM_PPM` on, with a map counting only the pixels it does not mark
            (:func:`new_defect_ppm`).
        cause: noise only, where this frame's assessable patches (estimated, or reused with the evidence of their last
            estimate) follow the image (their noise contradicts the metadata): which kind of cause the evidence names —
            ``{"gain", "dark_current", "readout"}``, the probabilities (summing to 1) that the gain is wrong, that the dark current is (the sensor's temperature),
            or that there is more readout-like white noise than the metadata say (the white-noise density, or noise
            beyond what any field in range explains), the mean of the estimator's ``cause`` over those patches
            (:data:`CAUSE_GROUPS`), and ``"patches"``; ``None`` where no patch follows the image. One exposure time
            names a gain; dark current and readout noise it tells apart by their physical ranges only — another
            exposure time of the camera tells them apart (``Monitor(exposure_evidence=True)``).
        note: why a task could not be assessed, if it could not.
        grid_obj, values, code: per-patch maps (not serialised unless asked).
    """

    task: str
    estimator: str
    patch: int
    grid: tuple[int, int]
    assessable: bool
    median: torch.Tensor | None = None
    spread: torch.Tensor | None = None
    temporal_spread: torch.Tensor | None = None
    current: torch.Tensor | None = None
    indicator: tuple[float, float] | None = None
    uncertainty: torch.Tensor | None = None
    indicator_uncertainty: float | None = None
    estimator_std: torch.Tensor | None = None
    n_values: int = 0
    coverage: dict[str, Any] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    refused: dict[str, int] = field(default_factory=dict)
    beyond_xi: float | None = None
    banding: dict[str, Any] | None = None
    defects: dict[str, Any] | None = None
    cause: dict[str, Any] | None = None
    note: str = ""
    grid_obj: PatchGrid | None = field(default=None, repr=False)
    values: torch.Tensor | None = field(default=None, repr=False)
    code: torch.Tensor | None = field(default=None, repr=False)

    def value(self, name: str) -> float:
        """Frame value (temporal + spatial median) of a noise field or ``"indicator"``; NaN if none."""
        if name == "indicator":
            return float("nan") if self.indicator is None else self.indicator[0]
        if self.median is None:
            return float("nan")
        return float(self.median[NOISE_FIELDS.index(name)])

    def _stats(self, sl: slice | int) -> dict[str, Any]:
        fields = [("median", self.median), ("spread", self.spread), ("temporal_spread", self.temporal_spread),
                  ("current", self.current), ("uncertainty", self.uncertainty), ("estimator_std", self.estimator_std)]
        return {key: None if t is None else _num(t[sl]) for key, t in fields}

    def to_dict(self, per_patch: bool = False) -> dict[str, Any]:
        out: dict[str, Any] = {
            "estimator": self.estimator, "patch_px": self.patch, "grid": list(self.grid), "assessable": self.assessable,
        }
        if self.task == "noise":
            out["sigma_dn"] = {name: self._stats(i) for i, name in enumerate(NOISE_FIELDS)} if self.assessable else None
        else:
            n = len(NORMALIZED_FREQUENCIES)
            if self.assessable:
                out["h"] = self._stats(slice(0, n))
                out["v"] = self._stats(slice(n, 2 * n))
                ind = self.indicator
                out["indicator"] = {"median": _num(ind[0]), "spread": _num(ind[1]),
                                    "uncertainty": _num(self.indicator_uncertainty)} if ind else None
            else:
                out["h"] = out["v"] = out["indicator"] = None
        out["patches"] = dict(self.counts)
        out["refused"] = dict(self.refused)
        if self.task == "noise":
            out["banding"] = dict(self.banding) if self.banding else None
            out["defects"] = dict(self.defects) if self.defects else None
            out["cause"] = dict(self.cause) if self.cause else None
        out["coverage"] = dict(self.coverage)
        if self.note:
            out["note"] = self.note
        if per_patch and self.grid_obj is not None and self.values is not None and self.code is not None:
            out["per_patch"] = {
                "x0": self.grid_obj.x0, "y0": self.grid_obj.y0,
                "status": [STATUS_NAMES[int(c)] for c in self.code.tolist()],
                "values": _num(self.values),
            }
        return out


@dataclass
class FrameReport:
    """Everything the monitor says about one frame; :meth:`to_json` gives the JSON line.

    Attributes:
        frame: running number of the frame in this monitor (0-based).
        index: index of the frame in its source (file order / video frame), if known.
        source_id: file or stream name, if known.
        height, width: frame size [px].
        metadata: gain [dB], exposure [s], temperature [°C] used (``None`` without metadata); where the estimators
            read no metadata and neither a preset nor a full set of fields was given, only the fields given (no
            preset fills the others).
        noise, mtf: :class:`TaskReport` (``None`` when the task is disabled).
        alarm: ξ alarm (state, ξ̃, limit, message).
        advice: policy decision, or why there is none (``None`` without a policy).
        timing_ms: convert / noise / mtf / aggregate / total [ms].
        input_scaling: how the frame's values were scaled to [0, 1] before it reached the monitor (``process``'s
            ``input_scaling``: e.g. ``"16-bit file read as 12-bit data (÷4095, as given)"``), ``None`` where not told.
    """

    frame: int
    index: int | None
    source_id: str | None
    height: int
    width: int
    metadata: dict[str, float] | None
    noise: TaskReport | None
    mtf: TaskReport | None
    alarm: dict[str, Any]
    advice: dict[str, Any] | None
    timing_ms: dict[str, float]
    per_patch: bool = False
    input_scaling: str | None = None

    @property
    def assessable(self) -> bool:
        """True if at least one task produced numbers."""
        return any(t is not None and t.assessable for t in (self.noise, self.mtf))

    def to_dict(self) -> dict[str, Any]:
        return {
            "frame": self.frame,
            "index": self.index,
            "source_id": self.source_id,
            "size": [self.width, self.height],
            "input_scaling": self.input_scaling,
            "assessable": self.assessable,
            "metadata": None if self.metadata is None else {k: _num(v, 6) for k, v in self.metadata.items()},
            "noise": None if self.noise is None else self.noise.to_dict(self.per_patch),
            "mtf": None if self.mtf is None else self.mtf.to_dict(self.per_patch),
            "alarm": self.alarm,
            "advice": self.advice,
            "timing_ms": {k: _num(v, 2) for k, v in self.timing_ms.items()},
        }

    def to_json(self) -> str:
        """One line of strict JSON (no NaN: missing numbers are ``null``)."""
        return json.dumps(self.to_dict(), ensure_ascii=False, allow_nan=False, separators=(",", ":"))


def xi_alarm(xi_dn: float, spread_dn: float, count: int, threshold_dn: float = 1.0, k: float = 3.0,
             total_dn: float | None = None, model_dn: float | None = None) -> dict[str, Any]:
    """ξ alarm for a frame value ξ̃ [DN] (Eq. 4.3: ξ = σ_Model(M) − σ_Image(M')).

    ``limit = max(threshold_dn, k·1.2533·spread/√count)``; ξ̃ < −limit → ``"noisier"`` (the image is
    noisier than the metadata allow), ξ̃ > limit → ``"cleaner"``, else ``"ok"``; NaN → ``"not_assessable"``.
    ``total_dn`` (the frame's σ_Total in the image [DN]) and ``model_dn`` (its σ_Total from the metadata [DN]; by default
    ``total_dn`` + ξ̃, which holds where every patch shares one ξ) are quoted in the message.
    """
    if not math.isfinite(xi_dn) or count < 1:
        return {"state": "not_assessable", "xi_dn": None, "limit_dn": None,
                "message": "no informative noise patch: ξ cannot be assessed"}
    se = _MEDIAN_SE * spread_dn / math.sqrt(count) if math.isfinite(spread_dn) else 0.0
    limit = max(threshold_dn, k * se)
    model = ""
    if total_dn is not None and math.isfinite(total_dn):
        meta_dn = total_dn + xi_dn if model_dn is None or not math.isfinite(model_dn) else model_dn
        model = f" (σ from the metadata ≈ {meta_dn:.2f} DN, in the image ≈ {total_dn:.2f} DN)"
    if xi_dn < -limit:
        state = "noisier"
        msg = (f"image is noisier than the metadata allow: ξ̃ = {xi_dn:+.2f} DN < −{limit:.2f} DN{model}; "
               "check gain/temperature metadata, the sensor, or noise added downstream")
    elif xi_dn > limit:
        state = "cleaner"
        msg = (f"image is cleaner than the metadata allow: ξ̃ = {xi_dn:+.2f} DN > {limit:.2f} DN{model}; "
               "check the gain metadata or a denoiser in the pipeline")
    else:
        state, msg = "ok", f"noise agrees with the metadata: |ξ̃| = {abs(xi_dn):.2f} DN ≤ {limit:.2f} DN"
    return {"state": state, "xi_dn": _num(xi_dn), "limit_dn": _num(limit), "message": msg}


def _metadata_total(noise: TaskReport) -> float | None:
    """The frame's σ_Total from the metadata [DN]: the median over this frame's patches with a value of σ_Total + ξ (per
    patch the metadata's closed form: ξ = σ_Model − σ_Image, and σ_Total is the closed form itself where ξ = 0). In a
    frame whose patches do not share one ξ (some follow the image, some keep the closed form) the frame's medians of
    σ_Total and ξ do not add up to it. ``None`` where no patch has both."""
    values = noise.values
    if values is None or values.ndim != 2 or values.shape[1] != len(NOISE_FIELDS):
        return None
    both = values[:, NOISE_FIELDS.index("total")] + values[:, NOISE_FIELDS.index("xi")]
    both = both[torch.isfinite(both)]
    return float(torch.quantile(both.double(), 0.5)) if both.numel() else None


def beyond_range_alarm(xi_dn: float, beyond: int, refused: int, threshold_dn: float = 1.0) -> dict[str, Any]:
    """ξ alarm for a frame whose noise patches were all refused, ``beyond`` of the ``refused`` ones as
    ``"noise beyond validated range"`` (σ_Total above :data:`~camhealth.estimators.physics_noise.VALIDATED_SIGMA_DN`).

    Such a patch passed every check of the evidence (flat area, texture, neighbours) and its image reads noisier
    than the validated range; the others were refused for other reasons (near 0 or 255 DN, where the clipping leaves
    no unclipped block, they say ``"no flat area"``) and do not contradict it. Beyond that range the clipping takes
    so much of the noise that the image's σ reads low (80 DN reads ≈ 68 DN), so their median ξ ``xi_dn`` [DN] is an
    upper bound on the true ξ: ξ̃ < −``threshold_dn`` says the image is *noisier* than the metadata allow — by at
    least |ξ̃| — and the alarm is raised rather than hidden as "not assessable". A ξ̃ near 0 or above (metadata that
    predict such noise themselves) cannot be told and stays ``"not_assessable"``, naming the reason.
    """
    if beyond >= 1 and math.isfinite(xi_dn) and xi_dn < -threshold_dn:
        return {"state": "noisier", "xi_dn": _num(xi_dn), "limit_dn": _num(threshold_dn),
                "message": (f"image is noisier than the metadata allow: its noise is beyond the validated "
                            f"{VALIDATED_SIGMA_DN:g} DN ({beyond} of {refused} refused patches); ξ̃ ≤ {xi_dn:+.2f} DN "
                            "(a bound: beyond the validated range σ reads low); check gain/temperature metadata, the "
                            "sensor, or noise added downstream")}
    return {"state": "not_assessable", "xi_dn": None, "limit_dn": None,
            "message": (f"noise beyond the validated {VALIDATED_SIGMA_DN:g} DN ({beyond} of {refused} refused patches) "
                        "and the metadata predict as much: ξ cannot be assessed")}


#: Row or column noise [DN] (the frame's, :attr:`TaskReport.banding`) from which the frame's MTF is not assessable:
#: the MTF network reads banding as fine detail. On the 148 clean patches of the held-out PSF generators on rendered
#: scenes (``python -m camhealth.bench robustness --task mtf --per-cell 8``, its row-noise table), on the patches it
#: calls assessable, the AMAE across the rows rises from 5.3 % to 7.9 % at 1 DN of row noise, 21.2 % at 3 DN and
#: 47.0 % at 6 DN (read sharper by 20 and 47 points), and along them from 5.5 % to 7.4 % and 9.1 %.
MTF_BANDING_LIMIT_DN = 2.0


def mtf_under_banding(mtf: TaskReport, banding: Mapping[str, Any], estimated: int | None = None) -> TaskReport:
    """The frame's MTF report, not assessable where the frame's row or column noise reaches
    :data:`MTF_BANDING_LIMIT_DN` (a copy with ``assessable=False`` and a note that names it); else ``mtf`` itself.

    ``estimated``: the noise patches whose evidence makes the frame's banding — estimated this frame (and assessable)
    or reused with the evidence of their last estimate. Banding belongs to the camera, so it shows on most of them;
    where fewer than half show it (each patch judged on its own, ``pool_noise=False``), it is a few patches' stripes
    and the MTF stands."""
    worst = max(float(banding.get("row_dn", 0.0)), float(banding.get("col_dn", 0.0)))
    if not mtf.assessable or worst < MTF_BANDING_LIMIT_DN:
        return mtf
    if estimated is not None and int(banding.get("patches", 0)) < 0.5 * estimated:
        return mtf
    which = "row" if float(banding.get("row_dn", 0.0)) >= float(banding.get("col_dn", 0.0)) else "column"
    return replace(mtf, assessable=False, note=(
        f"not assessable: {which} noise ≈ {worst:.2f} DN in this frame (banding, at least {MTF_BANDING_LIMIT_DN:g} DN): "
        "the MTF reads it as fine detail"))


#: Share of the tested pixels [per million] that stand out as defective from which the alarm names them and the ROS
#: diagnostics warn: the robustness benchmark's photographs and street frames with their right noise show 5 per
#: million on average (their own points of light and pixel-sized texture peaks), at most 95 on a frame (seeds 0 and
#: 7); one such point on eight 128-px patches is 8 per million. A sensor with 0.02 % defective pixels shows 200.
DEFECT_ALARM_PPM = 200.0
#: Frames for which the noise evidence of a camera state is kept for frames at other exposure times
#: (``exposure_evidence``): long enough to span an auto-exposure's steps, short against a sensor's warming.
EXPOSURE_MEMORY_FRAMES = 300
#: Defect positions a monitor remembers to tell recurring ones (a few MB).
DEFECT_POSITIONS = 100_000
#: Recurring defect positions the summary lists (most frames first).
DEFECT_LIST = 100
#: The fewest patches a pooled noise estimator (``pool_noise``) reads in one call. Its answer is the posterior of the
#: patches read together, and a patch read alone has only its own flat details: of the patches that are assessable
#: read with their whole frame (scikit-image's photographs, the independent sensor model, ICX285 as told and 12 dB
#: louder), 58–62 % are assessable read alone, 75–78 % in pairs, 86–90 % in fours, 97–100 % in sixes and 98–100 % in
#: eights, and of the louder camera's assessable ones 86 % see the mismatch alone, 100 % in eights
#: (``python -m camhealth.bench monitor --pool-sizes --gain-db 0 --exposure-s 0.02 --temperature-c 45``). Where fewer
#: patches need a fresh estimate (a static patch's periodic refresh, a patch that changed, a new sample, the second
#: call of coarse → refine), other informative patches of the frame are read with them, for their evidence only:
#: their own values stay as they were.
NOISE_MIN_POOL = 8


def new_defect_ppm(defects: Mapping[str, Any] | None) -> float:
    """The defective pixels of a frame (:attr:`TaskReport.defects`) that a defect map does not mark, per million
    pixels tested: what the alarm compares with :data:`DEFECT_ALARM_PPM` (without a map, all of them: ``ppm``)."""
    if not defects:
        return 0.0
    if "known" not in defects:
        return float(defects.get("ppm", 0.0))
    new = int(defects.get("hot", 0)) + int(defects.get("dark", 0)) - int(defects["known"])
    return round(1e6 * new / max(int(defects.get("checked", 0)), 1), 1)


def defects_text(defects: Mapping[str, Any]) -> str:
    """The alarm's words for a frame's defective pixels (:attr:`TaskReport.defects`)."""
    n = int(defects.get("hot", 0)) + int(defects.get("dark", 0))
    rec = int(defects.get("recurring", 0))
    known = defects.get("known")
    return (f"{n} pixels stand out from all their neighbours ({defects.get('hot', 0)} bright, {defects.get('dark', 0)} "
            f"dark; {float(defects.get('ppm', 0.0)):g} per million tested"
            + (f"; {n - int(known)} not on the defect map ({new_defect_ppm(defects):g} per million), {int(known)} on it"
               if known is not None else "")
            + (f"; {rec} at the same place as in an earlier frame" if rec else "")
            + "): hot, stuck or dead pixels or impulse noise, which no metadata field makes (or the scene's own "
            "points of light: a defect stays at its pixel while the scene moves)")


def banding_text(banding: Mapping[str, Any]) -> str:
    """The alarm's words for a frame's row and column noise (:attr:`TaskReport.banding`)."""
    parts = [f"{name} noise ≈ {float(banding[key]):.2f} DN" for name, key in (("row", "row_dn"), ("column", "col_dn"))
             if float(banding.get(key, 0.0)) > 0]
    return (" and ".join(parts) + f" on {banding.get('patches', 0)} patches: offsets shared by whole pixel "
            + ("rows and columns" if len(parts) == 2 else "rows" if banding.get("row_dn", 0) else "columns")
            + ", which no metadata field makes (banding: check the readout electronics, supply and interference)")


# ---------------------------------------------------------------------------------------------- monitor
@dataclass
class _EstimatorHandle:
    est: Any
    name: str
    kwargs: dict[str, Any]


@dataclass
class _TaskState:
    grid: PatchGrid
    k: int
    window: int
    config: SelectionConfig
    n_samples: int = 1
    values: torch.Tensor = field(init=False)
    code: torch.Tensor = field(init=False)
    history: torch.Tensor = field(init=False)
    ptr: torch.Tensor = field(init=False)
    static: StaticRegions = field(init=False)
    last_sampled: torch.Tensor = field(init=False)
    memory: torch.Tensor = field(init=False)
    samples: torch.Tensor = field(init=False)
    std: torch.Tensor = field(init=False)
    memory_std: torch.Tensor = field(init=False)
    samples_std: torch.Tensor = field(init=False)
    sample_slot: int = 0
    # this frame's refusals: reason → patches, and ξ [DN] of the patches refused as beyond the validated range
    refused: dict[str, int] = field(default_factory=dict)
    beyond_xi: list[float] = field(default_factory=list)
    # this frame's noise evidence (:meth:`gather`, from the patches with an estimate of their own this frame: fresh or
    # reused — a reused patch keeps the evidence of its last estimate, as it keeps its values)
    banding: list[tuple[float, float]] = field(default_factory=list)  # (row, column) σ [DN] of this frame's patches
    causes: list[torch.Tensor] = field(default_factory=list)  # (n, 4) the estimator's cause of the patches that follow the image
    defects: list[int] = field(default_factory=lambda: [0, 0, 0, 0])  # this frame's hot, dark, checked pixels, patches with any
    defect_xy: list[tuple[int, int]] = field(default_factory=list)  # their frame coordinates (x, y) [px]
    # each patch's noise evidence from its last estimate, kept beside its values (``values``, ``memory``)
    band: torch.Tensor = field(init=False)  # (n, 2) row, column σ [DN]; NaN where the last estimate was not assessable
    cause_p: torch.Tensor | None = None  # (n, C) the estimator's cause where the patch followed the image, else NaN
    defect_n: torch.Tensor = field(init=False)  # (n, 3) hot, dark and tested pixels
    defect_at: dict[int, list[tuple[int, int]]] = field(default_factory=dict)  # patch → its defects' (x, y) [px]
    # sampled mode: the identity of each patch's last estimate and of every sample in the window (one estimate that a
    # static patch keeps over several frames is one value of the window, not several)
    memory_id: torch.Tensor = field(init=False)
    samples_id: torch.Tensor = field(init=False)
    next_id: int = 0
    # static pairs (noise): the previous frame's patches, this frame's reference for them, and the patches read from a pair
    previous: torch.Tensor | None = None
    reference: torch.Tensor | None = None
    pairs: int = 0
    exposures: int = 0  # other exposure times whose noise evidence joined this frame's (exposure_evidence)
    # map mode: frames since the last reset that gave a value (estimated, interpolated or reused) — the frames behind
    # the answer, up to the window; a frame with no value (black, saturated, every patch refused) adds none
    frames_valued: int = 0
    # the frame counter at which each patch was last read by the estimator (for its value or as a pooled noise
    # reading's partner, NOISE_MIN_POOL), −1: never
    read_at: torch.Tensor = field(init=False)

    def __post_init__(self) -> None:
        n = self.grid.n
        self.static = StaticRegions(n, self.config)
        self.reset()

    def reset(self) -> None:
        n = self.grid.n
        self.values = torch.full((n, self.k), float("nan"))
        self.code = torch.full((n,), NOT_ASSESSABLE, dtype=torch.int8)
        self.history = torch.full((self.window, n, self.k), float("nan"))
        self.ptr = torch.zeros(n, dtype=torch.long)
        self.static.reset()
        self.last_sampled = torch.full((n,), -1, dtype=torch.long)
        self.memory = torch.full((n, self.k), float("nan"))  # sampled mode: each patch's last estimate
        self.samples = torch.full((self.window, self.n_samples, self.k), float("nan"))
        # the estimator's own per-value spread (MTF ``mtf_std``; NaN where it gives none) beside the values above
        self.std = torch.full((n, self.k), float("nan"))
        self.memory_std = torch.full((n, self.k), float("nan"))
        self.samples_std = torch.full((self.window, self.n_samples, self.k), float("nan"))
        self.memory_id = torch.full((n,), -1, dtype=torch.long)
        self.samples_id = torch.full((self.window, self.n_samples), -1, dtype=torch.long)
        self.sample_slot = 0
        self.previous = self.reference = None
        self.frames_valued = 0
        self.band = torch.full((n, 2), float("nan"))
        self.cause_p = None
        self.defect_n = torch.zeros(n, 3, dtype=torch.long)
        self.defect_at = {}
        self.read_at = torch.full((n,), -1, dtype=torch.long)

    def clear_evidence(self, index: torch.Tensor) -> None:
        """Forget the noise evidence of the patches ``index`` (re-estimated, or given an interpolated value)."""
        if index.numel() == 0:
            return
        self.band[index] = float("nan")
        if self.cause_p is not None:
            self.cause_p[index] = float("nan")
        self.defect_n[index] = 0
        for i in index.tolist():
            self.defect_at.pop(i, None)

    def gather(self, index: torch.Tensor) -> None:
        """This frame's ``banding``, ``causes``, ``defects`` and ``defect_xy`` from the evidence of the patches ``index``
        (those with an estimate of their own this frame: fresh, or reused with the evidence of their last estimate)."""
        band = self.band[index]
        shows = torch.isfinite(band).all(1) & (band > 0).any(1)
        self.banding = [tuple(b) for b in band[shows].tolist()]
        self.causes = []
        if self.cause_p is not None:
            cause = self.cause_p[index]
            cause = cause[torch.isfinite(cause).all(1)]
            if cause.numel():
                self.causes = [cause]
        d = self.defect_n[index]
        self.defects = [int(d[:, 0].sum()), int(d[:, 1].sum()), int(d[:, 2].sum()), int((d[:, :2].sum(1) > 0).sum())]
        self.defect_xy = [xy for i in index.tolist() for xy in self.defect_at.get(i, ())]

    def push_samples(self, vals: torch.Tensor, std: torch.Tensor, ids: torch.Tensor) -> None:
        """Sampled mode: this frame's assessable samples (n, K), their estimator spread (n, K) and the identities of
        their estimates (n,) replace the oldest frame of the window."""
        for buf, v, empty in ((self.samples, vals, float("nan")), (self.samples_std, std, float("nan")),
                              (self.samples_id, ids, -1)):
            row = buf[self.sample_slot]
            row.fill_(empty)
            row[: v.shape[0]] = v[: self.n_samples]
        self.sample_slot = (self.sample_slot + 1) % self.window

    def distinct_samples(self) -> torch.Tensor:
        """(window·n_samples,) bool: the samples of the window with a value, each estimate once (a reused sample is the
        estimate it repeats: counted where it first appears)."""
        flat = self.samples.reshape(-1, self.k)
        keep = torch.isfinite(flat[:, -1])
        seen: set[int] = set()
        for i, ident in enumerate(self.samples_id.reshape(-1).tolist()):
            if keep[i] and ident >= 0:
                if ident in seen:
                    keep[i] = False
                seen.add(ident)
        return keep

    def push(self, index: torch.Tensor, vals: torch.Tensor) -> None:
        """Append fresh estimates to the patches' ring buffers."""
        if index.numel() == 0:
            return
        self.history[self.ptr[index], index] = vals
        self.ptr[index] = (self.ptr[index] + 1) % self.window


def _first_rows(out: Mapping[str, Any], n: int, total: int) -> dict[str, Any]:
    """An estimator's output for ``total`` patches cut to its first ``n`` (per-patch tensors, arrays and lists; the
    frame's ``evidence`` and scalars as they are)."""
    cut: dict[str, Any] = {}
    for key, value in out.items():
        if key != "evidence" and isinstance(value, (torch.Tensor, np.ndarray)) and value.ndim and value.shape[0] == total:
            value = value[:n]
        elif isinstance(value, (list, tuple)) and len(value) == total:
            value = type(value)(value[:n])
        cut[key] = value
    return cut


def _uncertainty(spread: torch.Tensor, n: int, temporal_spread: torch.Tensor, frames: int,
                 estimator_std: torch.Tensor | None = None, shared: bool = False, error_shared: float = 0.0) -> torch.Tensor:
    """Standard error of a frame value [its unit]: the largest of 1.2533·spread/√n (scatter of the n values),
    1.2533·temporal_spread/√frames (scatter from frame to frame — the values of one frame may share one pooled
    camera-state posterior, so only the frames are independent) and, where the estimator states a per-value
    spread, estimator_std·√(ρ + (π/2)(1 − ρ)/n) (each value is itself that uncertain, and the share ρ =
    ``error_shared`` of its error variance is common to the patches of one scene — the MTF estimator's, measured with
    its error table, :func:`camhealth.estimators.mtf_error.frame_uncertainty`; 1.2533·estimator_std/√n at ρ = 0) — or,
    where the values of a frame share one posterior (``shared``: the pooled noise estimate), estimator_std/√frames
    (its error is common to them, so more patches do not shrink it)."""
    se = _MEDIAN_SE * spread / math.sqrt(max(n, 1))
    if frames > 1:
        tse = _MEDIAN_SE * torch.nan_to_num(temporal_spread.float(), nan=0.0) / math.sqrt(frames)
        se = torch.maximum(se, tse)
    if estimator_std is not None:
        floor = estimator_std.float() / math.sqrt(max(frames, 1)) if shared else frame_uncertainty(estimator_std, max(n, 1), error_shared)
        se = torch.maximum(se, torch.nan_to_num(floor, nan=0.0))
    return se


def _indicator_floor(estimator_std: torch.Tensor, n: int, error_shared: float) -> float:
    """The least standard error of the MTF indicator MTF̃ = (H + V)/2 at f_n = 0.1 that the estimator's own per-value
    uncertainty allows (:func:`_uncertainty`'s floor): (u_H + u_V)/2 — the two directions' errors taken as fully
    correlated, as one scene makes them — through :func:`~camhealth.estimators.mtf_error.frame_uncertainty`; 0 where
    the estimator states none."""
    from camhealth.physics.mtf import mtf_indicator

    u = float(mtf_indicator(estimator_std.float().reshape(1, -1))[0]) if estimator_std.numel() == 16 else float("nan")
    if not math.isfinite(u):
        return 0.0
    return float(frame_uncertainty(torch.tensor([u]), max(n, 1), error_shared)[0])


#: The run statistics of :meth:`Monitor.summary` keep the medians of at most this many recent frames (count, mean and
#: maximum cover the whole run), so a monitor that runs for days holds bounded state.
SUMMARY_RECENT_FRAMES = 10_000


class _RunStat:
    """Count, mean and maximum of a value over a whole run, and its median over the last
    :data:`SUMMARY_RECENT_FRAMES` values: bounded memory however long the run."""

    def __init__(self) -> None:
        self.count, self.total, self.max = 0, 0.0, -math.inf
        self.recent: collections.deque[float] = collections.deque(maxlen=SUMMARY_RECENT_FRAMES)

    def add(self, value: float) -> None:
        self.count += 1
        self.total += value
        self.max = max(self.max, value)
        self.recent.append(value)

    def stats(self, digits: int) -> dict[str, Any]:
        if not self.count:
            return {"median": None, "mean": None, "max": None}
        return {"median": _num(float(np.median(self.recent)), digits), "mean": _num(self.total / self.count, digits),
                "max": _num(self.max, digits)}


def _pooled_std(std: torch.Tensor, k: int) -> torch.Tensor:
    """(K,) √(mean of std²) over the rows of ``std`` (n, K) that have one; NaN where none has."""
    if std.shape[0] == 0:
        return torch.full((k,), float("nan"))
    m = torch.isfinite(std)
    cnt = m.sum(0)
    mean_sq = torch.where(m, std, torch.zeros_like(std)).pow(2).sum(0) / cnt.clamp_min(1)
    return torch.where(cnt > 0, mean_sq.sqrt(), torch.full_like(mean_sq, float("nan")))


#: The monitor's causes of a noise mismatch, each the kinds of :data:`~camhealth.estimators.physics_noise.MISMATCH_CAUSES`
#: (by index) it sums: the gain; the dark current (the sensor's temperature); readout-like white noise (the white-noise
#: density, or noise beyond what any field in range explains: both add the same exposure-independent variance).
CAUSE_GROUPS: dict[str, tuple[int, ...]] = {"gain": (0,), "dark_current": (1,), "readout": (2, 3)}
#: Words for the causes in the alarm's message, where the image is noisier than the metadata say …
CAUSE_WORDS: dict[str, str] = {"gain": "the gain", "dark_current": "dark current (the sensor hotter than told)",
                               "readout": "readout noise (white noise the metadata do not have)"}
#: … and where it is cleaner.
CAUSE_WORDS_CLEANER: dict[str, str] = {"gain": "the gain", "dark_current": "dark current (the sensor cooler than told)",
                                       "readout": "readout noise (less white noise than the metadata say, or a denoiser)"}


def group_causes(cause: Any) -> dict[str, float]:
    """The estimator's ``cause`` (the four kinds of :data:`~camhealth.estimators.physics_noise.MISMATCH_CAUSES`,
    a sequence or tensor of probabilities) summed into the monitor's causes (:data:`CAUSE_GROUPS`)."""
    c = [float(v) for v in cause]
    return {name: sum(c[i] for i in idx) for name, idx in CAUSE_GROUPS.items()}


def top_cause(cause: Mapping[str, Any]) -> str:
    """The most probable of a frame's causes (:attr:`TaskReport.cause`, or :func:`group_causes`' result)."""
    return max(CAUSE_GROUPS, key=lambda k: float(cause.get(k, 0.0)))


def cause_text(cause: Mapping[str, Any], noisier: bool = True) -> str:
    """The alarm's words for a frame's :attr:`TaskReport.cause`: the most probable cause and its probability, and the
    runner-up where it has at least a quarter; ``noisier``: the image is noisier than the metadata say (ξ < 0), else
    cleaner."""
    words = CAUSE_WORDS if noisier else CAUSE_WORDS_CLEANER
    ranked = sorted(((float(cause.get(k, 0.0)), k) for k in CAUSE_GROUPS), reverse=True)
    text = f"most likely {words[ranked[0][1]]} (P {ranked[0][0]:.2f}"
    if ranked[1][0] >= 0.25:
        text += f"; {words[ranked[1][1]]} P {ranked[1][0]:.2f}"
    return text + f", {cause.get('patches', 0)} patches)"


def _judged(noise: TaskReport) -> int:
    """The noise patches whose evidence makes a frame's ``banding`` and ``cause``: those estimated (and assessable) this
    frame and those reused with the evidence of their last estimate (``coverage`` ``estimated`` + ``reused``)."""
    return int(noise.coverage.get("estimated", 0)) + int(noise.coverage.get("reused", 0))


def _refusals(st: _TaskState) -> dict[str, Any]:
    """The ``refused``, ``beyond_xi``, ``banding``, ``defects`` and ``cause`` fields of a :class:`TaskReport` from this
    frame's task state."""
    # the true median (the mean of the two middle values for an even count), as the frame values: torch.median would
    # give the lower one (with two patches, their minimum)
    beyond = float(torch.tensor(st.beyond_xi, dtype=torch.float64).quantile(0.5)) if st.beyond_xi else None
    banding = None
    if st.banding:
        med = torch.tensor(st.banding, dtype=torch.float64).quantile(0.5, dim=0)
        banding = {"row_dn": round(float(med[0]), 3), "col_dn": round(float(med[1]), 3), "patches": len(st.banding)}
    hot, dark, checked, with_any = st.defects
    defects = None
    if hot + dark:
        defects = {"hot": hot, "dark": dark, "checked": checked, "ppm": round(1e6 * (hot + dark) / max(checked, 1), 1),
                   "patches": with_any, "recurring": 0}
    cause = None
    if st.causes:  # the mean over this frame's patches that follow the image, by physical cause
        cause = {name: round(v, 3) for name, v in group_causes(torch.cat(st.causes).double().mean(0)).items()}
        cause["patches"] = int(sum(int(t.shape[0]) for t in st.causes))
    return {"refused": dict(st.refused), "beyond_xi": beyond, "banding": banding, "defects": defects, "cause": cause}


#: Appended to the alarm message where every noise patch a frame refused was refused as textured: besides a scene that
#: is fine texture everywhere, noise that is not white does it — demosaicing, denoising, sharpening and compression
#: correlate neighbouring pixels' noise: a smooth ramp demosaiced or Gaussian-filtered (σ 0.7 px) after 2–10 DN of white
#: noise is refused as textured on every patch (``docs/monitor.md``); a JPEG's patches are named by :data:`CODEC_HINT`.
#: The alarm's note where every refused noise patch reads far less noise than the metadata's camera makes.
QUIET_HINT = ("every refused patch reads far less noise than any camera state in the metadata's ranges makes: a denoised, "
              "compressed, rescaled or rendered frame, or the metadata of a noisier camera (check gain and sensor); "
              "the metadata cannot be checked on it")
#: The alarm's note where noise patches were refused because the frame is a JPEG (``"a lossy codec changed the noise"``:
#: the noise estimator's reason, and the monitor's for patches refused as textured on a frame that shows JPEG's 8×8
#: block grid, :func:`~camhealth.estimators.jpeg_quantisation.coded_frame`).
CODEC_HINT = ("the frame is a JPEG (its 8×8 block grid is there): the codec removes noise and adds its own quantisation "
              "error, so the metadata cannot be checked on it — give frames as the sensor delivers them or losslessly "
              "coded (raw, PNG, a ROS Image topic)")
#: Appended to a "noisier" or "cleaner" alarm where the frame's scale was guessed from its largest value (a 16-bit
#: frame without an sBIT chunk and no ``--bit-depth``): a camera of more significant bits whose frames stay below the
#: guessed depth's top is read 4× (2 bits), 16× … too bright, and its noise with it.
GUESSED_SCALE_HINT = ("the frame's scale was guessed — {scale}; a camera with more significant "
                      "bits whose frames stay darker reads 4× per 2 bits too bright, and its noise with it: pass "
                      "--bit-depth N (bit_depth=N in Python), N the camera's significant bits")
TEXTURED_HINT = ("every refused patch looks textured: a scene of fine texture everywhere, or noise that is not white — "
                 "a demosaiced, denoised, sharpened or compressed frame, which camhealth's sensor noise model does not "
                 "describe (give frames as the sensor delivers them; a recording's bayer_* images: --bayer green, the default, "
                 "keeps the raw noise)")


def _reasons_text(refused: Mapping[str, int]) -> str:
    """``"8 noise beyond validated range, 2 textured"``: refusal counts, most frequent reason first."""
    return ", ".join(f"{v} {k}" for k, v in sorted(refused.items(), key=lambda kv: -kv[1]))


def _describe(est: Any) -> str:
    name = getattr(est, "name", None) or Path(str(getattr(est, "source", type(est).__name__))).stem
    kind, size, meta = getattr(est, "kind", "?"), getattr(est, "patch_size", "?"), getattr(est, "metadata_set", "none")
    return f"{name} ({kind}, {size} px, {meta} metadata)"


class Monitor:
    """Scene-adaptive patch-wise blur and noise monitor (see the module docstring).

    Args:
        noise_model: noise estimator — a shipped name or file for :func:`camhealth.inference.load_estimator`
            (kind ``noise_source`` or ``drne``), an object with the same interface, or ``None`` to skip noise.
        mtf_model: MTF estimator (kind ``mtf``), same forms, or ``None``.
        metadata: camera metadata (see :func:`load_metadata`: CameraMetadata, mapping, .json/.yaml path);
            required when the noise estimator reads metadata.
        sensor: sensor preset that fills missing metadata fields (or is the metadata).
        window: n of the temporal median (Eq. 5.4), frames (1…:data:`MAX_WINDOW`).
        mode: ``"sampled"`` — a frame-level answer from a few patches per frame (``noise_samples`` flat patches
            spread over the intensities, ``mtf_samples`` patches with edges spread over the frame, both rotating
            over the frame across frames; :func:`~camhealth.monitor.tiling.sample_patches`) pooled over the last
            ``window`` frames: cost independent of the scene and of camera motion; ``"map"`` — every informative
            patch (with ``adaptive`` reuse/interpolation), per-patch maps; ``"auto"`` (default) — ``"map"`` when
            ``per_patch`` output is asked for, else ``"sampled"``.
        noise_samples, mtf_samples: patches per frame in sampled mode (1…:data:`MAX_SAMPLES`; default 8 and 6).
        adaptive: reuse static patches and interpolate on the coarse lattice (``False``: estimate every
            informative patch of every frame).
        reuse_static, coarse_refine: the two parts of ``adaptive`` separately. A reused value enters its patch's
            temporal window as this frame's value, so the window spans the last ``window`` frames either way; a pooled
            noise reading of fewer than :data:`NOISE_MIN_POOL` patches is made up with other informative patches of
            the frame, read for their evidence only.
        skip_uninformative: ``False`` also estimates black/saturated/featureless/no-edge patches (for benchmarks;
            their results are then discarded by the estimator's own ``assessable``).
        selection: thresholds (:class:`~camhealth.monitor.tiling.SelectionConfig`).
        precision: ``"bf16"`` (CPU autocast) or ``"fp32"``.
        mtf_views: 1 (default), 2 or 4 — the MTF estimator also runs flipped copies of each patch and averages
            the estimates (:meth:`camhealth.inference.Estimator.predict` ``views``: ≈ 5 % lower AMAE for 2× the
            MTF time with 2 views); ignored by MTF estimators whose ``predict`` has no ``views``.
        pool_noise: ``True`` (default) — a noise estimator whose ``predict`` takes ``pool`` (the physics-first
            ``noise_source_full``) adds up the evidence of all of a frame's noise patches, which share one camera
            state (:func:`camhealth.estimators.physics_noise.physics_noise_posterior`); ``False`` judges every patch
            on its own (per-patch maps).
        batch_size: patches per network call.
        xi_threshold_dn, xi_sigmas: ξ alarm threshold [DN] and significance k (:func:`xi_alarm`).
        policy: an :class:`camhealth.control.ExposurePolicy` (or IOPC file path(s), :func:`load_policy`).
        per_patch: include per-patch status and values in the JSON lines.
        defect_map: the camera's known defective pixels — ``camera.maps.npz`` of ``python -m camhealth.calibrate``
            (its hot and dead pixels), a monitor run's ``--defects-out``, a ``.npy`` array, a mask image or an H×W array
            (:func:`camhealth.monitor.defect_map.load_defect_map`), the frames' size: the defects on it are counted
            as ``known`` and the alarm names only the others; ``None`` (default): every defect counts.
        warmup: on the first frame of a new size, run each network once on every batch size the frame can
            need (:func:`camhealth.inference.bucket_size` buckets up to the grid size), so that oneDNN builds its
            kernels then and not on later frames (≈ 0.5 s once for 1280×1024; the "cold first frame").
        device: where the estimators given by name or file run their networks (and ``noise_source_full`` its
            posterior): ``"cpu"`` (default), ``"cuda"`` or ``"cuda:N"``
            (:func:`camhealth.inference.load_estimator`); the frame statistics and patch selection stay on the CPU.
            Estimator objects passed in keep their own device.
        static_pairs: ``True`` — the noise estimator also reads each patch's difference from the same patch of the
            previous frame (``predict(..., reference=...)``, :mod:`camhealth.estimators.static_pair`): where the scene
            stood still, that difference holds the camera's noise and nothing of the scene, so a busy scene does not
            hide a mismatch; patches that moved are read alone, and ``coverage["static_pairs"]`` counts the patches
            read from a pair. For lossless frames only (raw, PNG/TIFF, uncompressed video or ROS ``Image``): a lossy
            codec (JPEG, H.264) re-quantises the two frames differently or copies one into the other, and on dense
            texture that passes the stillness tests. ``False`` (default): one frame at a time.
        exposure_evidence: ``True`` (default) — the physics-first noise estimator, pooled, keeps each camera state's
            latest noise evidence (``predict(..., return_evidence=True)``, from the same reading) for
            :data:`EXPOSURE_MEMORY_FRAMES` frames, and a frame whose metadata differ from a kept state's only in the
            exposure time adds it (``other_evidence``): dark-current shot noise grows with the exposure time and
            readout noise does not, so an auto-exposure's steps split an excess between them by the physics
            (:func:`camhealth.estimators.physics_noise.noise_evidence`). ``coverage["other_exposures"]`` counts the
            states that joined a frame. ``False``: each state on its own.

    The numeric arguments (``window``, ``noise_samples``, ``mtf_samples``, ``mtf_views``, ``batch_size``,
    ``xi_threshold_dn``, ``xi_sigmas``) take a Python or NumPy number (``np.int64(5)``, ``np.float32(1.0)``), kept as
    the Python ``int`` or ``float``; a bool is refused.
    """

    def __init__(
        self,
        noise_model: Any = "noise_source_full",
        mtf_model: Any = "mtf",
        metadata: Any = None,
        sensor: str | None = None,
        window: int = 5,
        mode: str = "auto",
        noise_samples: int = 8,
        mtf_samples: int = 6,
        adaptive: bool = True,
        reuse_static: bool = True,
        coarse_refine: bool = True,
        skip_uninformative: bool = True,
        selection: SelectionConfig | None = None,
        precision: str = "bf16",
        mtf_views: int = 1,
        pool_noise: bool = True,
        batch_size: int = 128,
        xi_threshold_dn: float = 1.0,
        xi_sigmas: float = 3.0,
        policy: Any = None,
        per_patch: bool = False,
        defect_map: Any = None,
        warmup: bool = True,
        device: Any = "cpu",
        static_pairs: bool = False,
        exposure_evidence: bool = True,
    ) -> None:
        window, noise_samples, mtf_samples, mtf_views, batch_size, xi_threshold_dn, xi_sigmas = map(
            _python_number, (window, noise_samples, mtf_samples, mtf_views, batch_size, xi_threshold_dn, xi_sigmas))
        if isinstance(window, bool) or not isinstance(window, int) or not 1 <= window <= MAX_WINDOW:
            raise ValueError(f"window = {window!r} must be an integer 1…{MAX_WINDOW} (frames)")
        if mode not in MODES:
            raise ValueError(f"mode = {mode!r} must be one of {list(MODES)}")
        for v, name in ((noise_samples, "noise_samples"), (mtf_samples, "mtf_samples")):
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_SAMPLES:
                raise ValueError(f"{name} = {v!r} must be an integer 1…{MAX_SAMPLES} (patches per frame)")
        if precision not in ("bf16", "fp32"):
            raise ValueError(f"precision = {precision!r} must be 'bf16' or 'fp32'")
        if mtf_views not in (1, 2, 4) or isinstance(mtf_views, bool):
            raise ValueError(f"mtf_views = {mtf_views!r} must be 1, 2 or 4")
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise ValueError(f"batch_size = {batch_size!r} must be an integer >= 1")
        for v, name in ((xi_threshold_dn, "xi_threshold_dn"), (xi_sigmas, "xi_sigmas")):
            if isinstance(v, (bool, np.bool_)) or not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} = {v!r} must be a finite number >= 0")
        for v, name in ((adaptive, "adaptive"), (reuse_static, "reuse_static"), (coarse_refine, "coarse_refine"),
                        (skip_uninformative, "skip_uninformative"), (pool_noise, "pool_noise"), (per_patch, "per_patch"),
                        (warmup, "warmup")):
            if not isinstance(v, bool):  # (bool("false") is True)
                raise TypeError(f"{name} = {v!r} must be True or False")
        if selection is not None and not isinstance(selection, SelectionConfig):
            raise TypeError(f"selection = {selection!r} must be a SelectionConfig (camhealth.monitor.SelectionConfig("
                            f"max_clipped_fraction=…, min_structure_dn=…, max_age=…)) or None, got {type(selection).__name__}")
        self.window = window
        self.mode = ("map" if per_patch else "sampled") if mode == "auto" else mode
        self.n_samples = {"noise": int(noise_samples), "mtf": int(mtf_samples)}
        self.reuse_static = bool(adaptive and reuse_static)
        self.coarse_refine = bool(adaptive and coarse_refine)
        self.skip_uninformative = bool(skip_uninformative)
        self.selection = selection or SelectionConfig()
        self.precision = precision
        self.mtf_views = int(mtf_views)
        self.batch_size = batch_size
        self.xi_threshold_dn = float(xi_threshold_dn)
        self.xi_sigmas = float(xi_sigmas)
        self.per_patch = bool(per_patch)
        self.warmup = bool(warmup)
        if not isinstance(static_pairs, bool):
            raise TypeError(f"static_pairs = {static_pairs!r} must be True or False")
        self.static_pairs = static_pairs
        if not isinstance(exposure_evidence, bool):
            raise TypeError(f"exposure_evidence = {exposure_evidence!r} must be True or False")
        self.exposure_evidence = exposure_evidence
        # (the metadata's other fields, exposure time [s]) → (frame counter, that state's latest noise evidence)
        self._exposure_cache: dict[tuple[tuple, float], tuple[int, torch.Tensor]] = {}
        self.estimators: dict[str, _EstimatorHandle] = {}
        for task, spec in (("noise", noise_model), ("mtf", mtf_model)):
            if spec is not None:
                self.estimators[task] = self._resolve(task, spec, device)
        self.pool_noise = bool(pool_noise)
        if not self.estimators:
            raise ValueError("nothing to monitor: noise_model and mtf_model are both None")
        noise = self.estimators.get("noise")
        required = getattr(noise.est, "metadata_set", "none") if noise else "none"
        self.metadata, given = _load_metadata(metadata, sensor, required if required in METADATA_SETS else "full")
        # an estimator that reads no metadata, given some fields only: those fields are reported (and a change of them
        # restarts the aggregation), but no camera state is made up from a preset nobody named (no ξ alarm on it)
        self._given: dict[str, float] | None = None
        if given is not None and required == "none" and self.metadata is not None:
            self._given = {k: float(getattr(self.metadata, k)[0]) for k in MINIMAL_FIELDS if k in given}
            self.metadata = None
        self.sensor = sensor
        if noise is not None and required != "none" and self.metadata is None:
            raise ValueError(
                f"the noise estimator {noise.name} reads {required!r} metadata: give metadata (a .json/.yaml file or "
                f"a mapping of fields) or a sensor preset ({sorted(PRESETS)})"
            )
        if isinstance(policy, (str, Path)):
            policy = load_policy([policy])
        elif isinstance(policy, (list, tuple)) and policy and isinstance(policy[0], (str, Path)):
            policy = load_policy(list(policy))
        if policy is not None:
            if not callable(getattr(policy, "decide", None)):
                raise TypeError(
                    f"policy must provide decide(...) (camhealth.control.ExposurePolicy), got {type(policy).__name__}"
                )
            if self.metadata is None:
                raise ValueError("exposure/gain advice needs the current exposure and gain: give metadata or a sensor preset")
            if "noise" not in self.estimators or "mtf" not in self.estimators:
                raise ValueError("exposure/gain advice needs both the noise and the MTF estimator")
        self.policy = policy
        self._states: dict[str, _TaskState] = {}
        self._shape: tuple[int, int] | None = None
        self._meta_key: tuple | None = None
        self._scaling: tuple[Any, str, bool] | None = None  # the last input_scaling given: _input_scaling's answer
        self._prior_cache: tuple | None = None
        self._counter = 0
        self._times = _RunStat()  # ms per frame
        self._counts: dict[str, dict[str, int]] = {t: {n: 0 for n in STATUS_NAMES} for t in self.estimators}
        self._alarms: dict[str, int] = {}
        self._banding = (_RunStat(), _RunStat())  # row, column σ [DN] of the frames that showed banding
        self._defect_frames = _RunStat()  # ppm of the frames that showed defective pixels
        self._causes: dict[str, int] = {}  # most probable noise cause → frames that named it
        self._defect_seen: dict[tuple[int, int], int] = {}  # frame position → frames it was flagged in
        self.defect_map: torch.Tensor | None = None
        if defect_map is not None:
            from camhealth.monitor.defect_map import load_defect_map

            if "noise" not in self.estimators:
                raise ValueError("defect_map is read by the noise estimator's defect check: give a noise_model")
            self.defect_map = load_defect_map(defect_map)
        self._refused: dict[str, dict[str, int]] = {t: {} for t in self.estimators}
        self._last: FrameReport | None = None

    # ------------------------------------------------------------------ set-up
    @staticmethod
    def _resolve(task: str, spec: Any, device: Any = "cpu") -> _EstimatorHandle:
        if isinstance(spec, (str, Path)):
            from camhealth.inference import load_estimator

            est = load_estimator(spec, device=device)
        else:
            est = spec
        for attr in ("kind", "patch_size", "predict"):
            if not hasattr(est, attr):
                raise TypeError(f"{task} estimator {type(est).__name__} lacks {attr!r} (see camhealth.inference.Estimator)")
        if est.kind not in TASKS[task]:
            kinds = " or ".join(TASKS[task])
            raise ValueError(f"the {task} estimator must be of kind {kinds}, got {est.kind!r} ({_describe(est)})")
        p = est.patch_size
        if isinstance(p, bool) or not isinstance(p, int) or p < 8 or p % 8:
            raise ValueError(f"{task} estimator patch_size = {p!r} must be a positive multiple of 8 px")
        try:
            params = inspect.signature(est.predict).parameters
        except (TypeError, ValueError):
            params = {}
        var_kw = any(v.kind is inspect.Parameter.VAR_KEYWORD for v in params.values())
        kwargs = {name: None for name in ("precision", "batch_size", "views") if name in params or var_kw}
        if "pool" in params:  # named, not only **kwargs: the physics-first noise estimator
            kwargs["pool"] = None
        if "reference" in params:  # a static pair's second exposure: the physics-first noise estimator
            kwargs["reference"] = None
        if "other_evidence" in params and "return_evidence" in params:  # other exposure times' evidence: the same
            kwargs["other_evidence"] = None
        return _EstimatorHandle(est, _describe(est), kwargs)

    def reset(self) -> None:
        """Forget all history (temporal aggregation, static references, other exposure times' evidence); counters and
        timing stay."""
        self._reset_aggregation()
        self._exposure_cache.clear()

    def _reset_aggregation(self) -> None:
        """A new camera state: the temporal aggregation and static references start afresh (the evidence kept per
        exposure time stays: it is about the camera, :meth:`_exposure_evidence`)."""
        for st in self._states.values():
            st.reset()

    @staticmethod
    def _exposure_key(meta: CameraMetadata) -> tuple[tuple, float]:
        """(every field but the exposure time, the exposure time [s]) of a camera state of batch 1, rounded."""
        fields = meta.to_dict()
        return (tuple((k, round(float(v[0]), 12)) for k, v in fields.items() if k != "exposure_s"),
                round(float(fields["exposure_s"][0]), 12))

    def _exposure_evidence(self, meta: CameraMetadata) -> tuple[torch.Tensor | None, int]:
        """The summed kept evidence of this camera at other exposure times (kept at most
        :data:`EXPOSURE_MEMORY_FRAMES` frames ago), and how many states it holds."""
        others, exposure = self._exposure_key(meta)
        kept = [ev for (k, e), (c, ev) in self._exposure_cache.items()
                if k == others and e != exposure and self._counter - c <= EXPOSURE_MEMORY_FRAMES]
        return (None if not kept else torch.stack(kept).sum(0)), len(kept)

    def _keep_evidence(self, meta: CameraMetadata, evidence: torch.Tensor) -> None:
        """This frame's noise evidence for its camera state (added up where the frame is read in several calls)."""
        key = self._exposure_key(meta)
        old = self._exposure_cache.get(key)
        if old is not None and old[0] == self._counter:
            evidence = old[1] + evidence
        self._exposure_cache[key] = (self._counter, evidence)
        for k in [k for k, (c, _) in self._exposure_cache.items() if self._counter - c > EXPOSURE_MEMORY_FRAMES]:
            del self._exposure_cache[k]

    def _prepare(self, h: int, w: int, source_id: str | None = None) -> None:
        if self._shape == (h, w):
            return
        if self.defect_map is not None and tuple(self.defect_map.shape) != (h, w):
            mh, mw = self.defect_map.shape
            which = "this frame" if source_id is None else f"frame {source_id}"
            raise FrameSizeError(f"the defect map is {mw}×{mh} px (W×H) but {which} is {w}×{h} px: the map must cover "
                                 "the whole frame, pixel for pixel; the frame is not scored")
        if self._shape is not None:  # another frame size: positions of the old one are not this one's pixels
            self._defect_seen.clear()
        self._shape = (h, w)
        self._states = {
            task: _TaskState(PatchGrid.fit(h, w, int(handle.est.patch_size)), 5 if task == "noise" else 16, self.window,
                             self.selection, self.n_samples[task])
            for task, handle in self.estimators.items()
        }
        if self.warmup:
            self._warm_up()

    def _warm_up(self) -> None:
        """Run every network once per padded batch size a frame of this size can send it."""
        from camhealth.inference import Estimator, bucket_size

        for task, st in self._states.items():
            handle = self.estimators[task]
            if st.grid.empty or not isinstance(handle.est, Estimator) or handle.est.backend != "torch":
                continue  # oneDNN kernels: torch-backend camhealth estimators only
            n_max = min(st.grid.n, self.batch_size, self.n_samples[task] if self.mode == "sampled" else st.grid.n)
            sizes = sorted({min(bucket_size(k), n_max) for k in range(1, n_max + 1)})
            meta = self.metadata if getattr(handle.est, "metadata_set", "none") != "none" else None
            p = st.grid.patch
            for size in sizes:
                dummy = torch.full((size, 1, p, p), 0.5)
                views = {"views": self.mtf_views} if task == "mtf" and self.mtf_views > 1 else {}
                handle.est.predict(dummy, metadata=meta, precision=self.precision, batch_size=self.batch_size, **views)

    def _frame_metadata(self, metadata: Any) -> tuple[CameraMetadata | None, dict[str, float] | None]:
        """This frame's metadata, and the fields given (gain, exposure, temperature) where the estimators read none
        and no preset or file gave the others: those are reported as they are, not completed from a preset."""
        if metadata is None:
            return self.metadata, self._given
        if isinstance(metadata, CameraMetadata):
            return load_metadata(metadata), None
        if isinstance(metadata, Mapping) and self.metadata is not None:
            unknown = [k for k in metadata if k not in FULL_FIELDS and k not in ("sensor", "sensor_type")]
            if unknown:
                raise ValueError(f"per-frame metadata: unknown metadata field(s) {sorted(unknown, key=str)}; known "
                                 f"fields: {list(FULL_FIELDS)}")
            changed = {k: _one_number(k, v) for k, v in metadata.items()}  # one camera state: a number per field
            try:
                return self.metadata.replace(**changed), None
            except (TypeError, ValueError) as exc:
                raise ValueError(f"per-frame metadata {changed}: {exc}") from None
        noise = self.estimators.get("noise")
        required = getattr(noise.est, "metadata_set", "none") if noise else "none"
        if isinstance(metadata, Mapping) and self._given is not None:  # this frame's fields over the monitor's
            metadata = {**self._given, **metadata}
        meta, given = _load_metadata(metadata, self.sensor, required)
        if given is not None and required == "none" and meta is not None:
            return None, {k: float(getattr(meta, k)[0]) for k in MINIMAL_FIELDS if k in given}
        return meta, None

    # ------------------------------------------------------------------ estimation
    def _noise_scale(self, stats: Any, meta: CameraMetadata | None) -> torch.Tensor | None:
        """(N, 5) model σ [DN] of (PN, DCSN, RN, total, total) per patch for the metadata — the closed-form
        noise model (conventions.md: σ_PN = 255·√(g·Ī/FW), σ_DCSN and σ_RN from Eq. 3.14–3.19, the same prior
        as :func:`camhealth.estimators.noise_features.physics_prior_dn`) — or ``None`` when the noise estimator
        gives no per-source σ or there is no metadata. DCSN and RN depend only on the metadata: cached."""
        if meta is None or getattr(self.estimators["noise"].est, "kind", "") != "noise_source":
            return None
        key = self._meta_key
        if self._prior_cache is None or self._prior_cache[0] != key:
            from camhealth.physics.dark_current import dark_current_shot_sigma_e
            from camhealth.physics.readout_noise import readout_sigma_e

            m64 = meta.to(dtype=torch.float64)
            dn = float(m64.dn_per_electron[0])
            self._prior_cache = (key, float(dark_current_shot_sigma_e(m64)[0]) * dn, float(readout_sigma_e(m64)[0]) * dn,
                                 float(m64.gain_factor[0] / m64.full_well_e[0]))
        _, dc, rn, g_fw = self._prior_cache
        pn = 255.0 * (stats.mean_dn.double().clamp(0, 255) / 255.0 * g_fw).sqrt()
        total = (pn.pow(2) + dc * dc + rn * rn).sqrt()
        scale = torch.stack([pn, torch.full_like(pn, dc), torch.full_like(pn, rn), total, total], 1).float()
        return scale.clamp_min(1e-3)

    def _error_shared(self, task: str) -> float:
        """The share of the estimator's per-value error variance that the patches of one scene have in common: the MTF
        estimator's error table's ``shared`` (0 without a table, and for the noise)."""
        table = getattr(self.estimators[task].est, "mtf_error", None) if task == "mtf" else None
        return float(getattr(table, "shared", 0.0) or 0.0)

    def _shared_posterior(self, task: str) -> bool:
        """Whether the values of one frame share one posterior: the noise estimate pooled per frame (``pool_noise``)."""
        return task == "noise" and bool(self.pool_noise) and "pool" in self.estimators[task].kwargs

    def _estimate(
        self, task: str, patches: torch.Tensor, index: torch.Tensor, meta: CameraMetadata | None,
        partners: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Run the estimator on ``patches[index]`` → (values (n, K), ok (n,) bool, the estimator's per-value spread
        (n, K): MTF ``mtf_std``, noise ``sigma_std`` and ``xi_std`` (ξ and the total) where the estimator returns them,
        else NaN). The reasons the estimator gave for the
        patches it refused are counted into this frame's ``refused`` of the task state, and the ξ [DN] it still
        reports for those refused as ``"noise beyond validated range"`` kept in ``beyond_xi`` (the alarm's bound).

        ``partners``: the frame's informative patches. A pooled noise reading of fewer than :data:`NOISE_MIN_POOL`
        patches reads as many of them with ``index`` as make it up — those not read this frame first (so that no
        patch's evidence is kept twice for other exposure times), the longest unread first — and returns the rows of
        ``index`` alone."""
        handle = self.estimators[task]
        st = self._states[task]
        k = 5 if task == "noise" else 16
        n = int(index.numel())
        if n == 0:
            return torch.zeros(0, k), torch.zeros(0, dtype=torch.bool), torch.zeros(0, k)
        kwargs = {}
        if "precision" in handle.kwargs:
            kwargs["precision"] = self.precision
        if "batch_size" in handle.kwargs:
            kwargs["batch_size"] = self.batch_size
        if task == "mtf" and self.mtf_views > 1 and "views" in handle.kwargs:
            kwargs["views"] = self.mtf_views
        if task == "noise" and self.pool_noise and "pool" in handle.kwargs and meta is not None and meta.batch_size == 1:
            kwargs["pool"] = True  # one camera state per frame: the frame's evidence for every patch
        if task == "noise" and st.reference is not None and "reference" in handle.kwargs:
            kwargs["reference"] = st.reference[index]  # the same patches of the previous frame (static pairs)
        call, read_twice = index, False
        if task == "noise" and kwargs.get("pool") and partners is not None and n < NOISE_MIN_POOL:
            # one pooled reading: a few patches alone have few flat details of their own, so the frame's other
            # informative patches join them for their evidence
            own = set(index.tolist())
            others = [i for i in partners.tolist() if i not in own]
            others.sort(key=lambda i: (int(st.read_at[i]) == self._counter, int(st.read_at[i]), i))
            extra = others[: NOISE_MIN_POOL - n]
            if extra:
                call = torch.cat([index, torch.tensor(extra, dtype=torch.long)])
                read_twice = any(int(st.read_at[i]) == self._counter for i in extra)
        if kwargs.get("reference") is not None:
            kwargs["reference"] = st.reference[call]
        st.read_at[call] = self._counter
        exposures = task == "noise" and self.exposure_evidence and kwargs.get("pool") and "other_evidence" in handle.kwargs
        if exposures:  # this camera's evidence at other exposure times joins; this frame's is kept for them
            kwargs["other_evidence"], st.exposures = self._exposure_evidence(meta)
            kwargs["return_evidence"] = True
        use_meta = meta if getattr(handle.est, "metadata_set", "none") != "none" else None
        out = handle.est.predict(patches[call], metadata=use_meta, **kwargs)
        if (exposures and not read_twice and out.get("evidence") is not None
                and bool(torch.as_tensor(out["evidence"]).any())):
            self._keep_evidence(meta, torch.as_tensor(out["evidence"]))
        if call is not index:
            out = _first_rows(out, n, int(call.numel()))
        if kwargs.get("reference") is not None and "static" in out:
            st.pairs += int(torch.as_tensor(out["static"]).sum())
        if task == "noise":
            if "sigma_total" not in out:
                raise ValueError(f"noise estimator {handle.name} returned no 'sigma_total' (keys {sorted(out)})")
            total = torch.as_tensor(out["sigma_total"]).float().reshape(n, 1)
            if "sigma" in out and "xi" in out:
                sigma = torch.as_tensor(out["sigma"]).float().reshape(n, 3)
                vals = torch.cat([sigma, torch.as_tensor(out["xi"]).float().reshape(n, 1), total], 1)
            else:
                vals = torch.cat([torch.full((n, 4), float("nan")), total], 1)
        else:
            if "mtf" not in out:
                raise ValueError(f"MTF estimator {handle.name} returned no 'mtf' (keys {sorted(out)})")
            vals = torch.as_tensor(out["mtf"]).float().reshape(n, 16)
        std = torch.full((n, k), float("nan"))
        if task == "mtf" and out.get("mtf_std") is not None:
            std = torch.as_tensor(out["mtf_std"]).float().reshape(n, 16).clone()
        if task == "noise" and out.get("sigma_std") is not None and out.get("xi_std") is not None:
            xi_std = torch.as_tensor(out["xi_std"]).float().reshape(n, 1)  # the posterior spread of σ_Total: ξ's and the total's
            std = torch.cat([torch.as_tensor(out["sigma_std"]).float().reshape(n, 3), xi_std, xi_std], 1)
        ok = torch.as_tensor(out.get("assessable", torch.ones(n, dtype=torch.bool))).bool().reshape(n)
        reasons = list(out.get("reason") or [""] * n)
        textured_at = [i for i in (~ok).nonzero()[:, 0].tolist() if i < len(reasons) and reasons[i] == "textured"]
        if task == "noise" and textured_at and coded_frame(patches[index[textured_at]]):
            # JPEG's blocking and quantisation error read as texture: the frame's refusals name the codec instead
            for i in textured_at:
                reasons[i] = LOSSY_CODEC
        for i in (~ok).nonzero()[:, 0].tolist():
            why = str(reasons[i]) if i < len(reasons) and reasons[i] else "no value"
            st.refused[why] = st.refused.get(why, 0) + 1
            # a bound on ξ only where the estimator read the patch's noise (followed the image): a refusal from the
            # metadata's own σ or the finest-scale check alone carries the closed form's ξ = 0, a network's its regression
            if (task == "noise" and why == BEYOND_VALIDATED and "xi" in out and out.get("follows_image") is not None
                    and bool(torch.as_tensor(out["follows_image"]).reshape(n)[i])):
                xi = float(torch.as_tensor(out["xi"]).reshape(n)[i])
                if math.isfinite(xi):
                    st.beyond_xi.append(xi)
        if task == "noise":  # each patch's evidence beside its values (kept where a later frame reuses them)
            st.clear_evidence(index)
        if task == "noise" and out.get("row_column_dn") is not None:
            band = torch.as_tensor(out["row_column_dn"]).float().reshape(n, 2)
            st.band[index[ok]] = band[ok]
        if task == "noise" and out.get("cause") is not None and out.get("follows_image") is not None:
            follows = torch.as_tensor(out["follows_image"]).bool().reshape(n) & ok
            cause = torch.as_tensor(out["cause"]).float().reshape(n, -1)
            if st.cause_p is None or st.cause_p.shape[1] != cause.shape[1]:
                st.cause_p = torch.full((st.grid.n, cause.shape[1]), float("nan"))
            st.cause_p[index[follows]] = cause[follows]
        if task == "noise" and out.get("defects") is not None:
            checked = out.get("defects_checked")  # pixels tested per patch (0 where a patch is a pattern, not tested)
            checked = (torch.as_tensor(checked).reshape(n).long() if checked is not None
                       else torch.full((n,), int(patches.shape[-2] - 2) * int(patches.shape[-1] - 2), dtype=torch.long))
            self._count_defects(st, index, torch.as_tensor(out["defects"]).reshape(n, 2), out.get("defect_mask"), checked)
        ok &= torch.isfinite(vals[:, -1])
        vals[~ok] = float("nan")
        std[~ok] = float("nan")
        return vals, ok, std

    @staticmethod
    def _count_defects(st: _TaskState, index: torch.Tensor, counts: torch.Tensor, mask: Any, checked: torch.Tensor) -> None:
        """Keeps the defective pixels the noise estimator found on the patches ``index`` of the grid (``counts`` (n, 2):
        hot, dark; ``checked`` (n,) pixels tested on each) as each patch's evidence, with their frame coordinates where
        ``mask`` (n, 1, P, P) gives them."""
        st.defect_n[index] = torch.cat([counts.long(), checked.reshape(-1, 1)], 1)
        if mask is None or not bool((counts > 0).any()):
            return
        mask = torch.as_tensor(mask)
        if tuple(mask.shape[-2:]) != (st.grid.patch, st.grid.patch):
            return
        where = (mask[:, 0] != 0).nonzero()  # (m, 3): patch, y, x
        origin = st.grid.boxes()[index][where[:, 0]]
        for p, x, y in zip(index[where[:, 0]].tolist(), (origin[:, 0] + where[:, 2]).tolist(),
                           (origin[:, 1] + where[:, 1]).tolist()):
            st.defect_at.setdefault(p, []).append((x, y))

    def _run_task(self, task: str, frame: torch.Tensor, meta: CameraMetadata | None) -> TaskReport:
        st = self._states[task]
        st.refused, st.beyond_xi, st.banding, st.causes = {}, [], [], []
        st.defects, st.defect_xy = [0, 0, 0, 0], []
        st.pairs = st.exposures = 0
        grid, cfg = st.grid, self.selection
        handle = self.estimators[task]
        base = dict(task=task, estimator=handle.name, patch=grid.patch, grid=(grid.rows, grid.cols))
        if grid.empty:
            counts = {**{n: 0 for n in STATUS_NAMES}, "total": 0}
            note = f"frame {grid.width}×{grid.height} px is smaller than one {grid.patch}-px patch: {task} not estimated"
            return TaskReport(**base, assessable=False, counts=counts, note=note, grid_obj=grid)  # (heat_map: all NaN)
        patches = grid.extract(frame)
        if task == "noise" and self.static_pairs:  # the previous frame's patches are this frame's second exposure
            same = st.previous is not None and st.previous.shape == patches.shape
            st.reference, st.previous = (st.previous if same else None), patches
        stats = grid_statistics(frame, grid)
        informative, code = select_patches(stats, task, cfg)
        if not self.skip_uninformative:
            informative = torch.ones_like(informative)
            code = torch.full_like(code, ESTIMATED)
        values = torch.full((grid.n, st.k), float("nan"))
        std = torch.full((grid.n, st.k), float("nan"))
        if self.mode == "sampled":
            scale = self._noise_scale(stats, meta) if task == "noise" else None
            quiet = None if scale is None else quiet_patches(stats, scale[:, 3])  # e.g. a noiseless overlay
            idx = sample_patches(grid, stats, informative, self.n_samples[task], task, st.last_sampled, quiet)
            reuse = torch.zeros(idx.numel(), dtype=torch.bool)
            if self.reuse_static and idx.numel():  # a sampled patch unchanged since its last estimate keeps it
                reuse = (torch.isfinite(st.memory[idx, -1]) & ~st.static.changed(stats)[idx]
                         & ~st.static.due(self._counter)[idx])
            new = idx[~reuse]
            pool_with = informative if quiet is None or not bool((informative & ~quiet).any()) else informative & ~quiet
            new_vals, new_ok, new_std = self._estimate(task, patches, new, meta, pool_with.nonzero()[:, 0])
            st.memory[new] = new_vals
            st.memory_std[new] = new_std
            st.memory_id[new] = torch.arange(st.next_id, st.next_id + new.numel())  # a new estimate each
            st.next_id += int(new.numel())
            if self.reuse_static:
                st.static.update(new[new_ok], stats, self._counter)
            vals = st.memory[idx]
            ok = torch.isfinite(vals[:, -1])
            code[informative] = UNSAMPLED
            code[idx] = ESTIMATED
            code[idx[reuse]] = REUSED
            code[idx[~ok]] = NOT_ASSESSABLE
            values[idx] = vals
            st.last_sampled[idx] = self._counter
            st.push_samples(vals[ok], st.memory_std[idx][ok], st.memory_id[idx][ok])
            st.values, st.code = values, code
            st.gather(torch.cat([new, idx[reuse]]))  # a reused sample keeps its estimate's evidence
            boxes = grid.boxes()[idx[ok & ~reuse]]  # the patches estimated (and assessable) this frame
            return self._with_pairs(task, st, self._aggregate_sampled(task, st, handle.name, int(informative.sum()), boxes,
                                                                      int(reuse.sum()), int(ok.sum())))
        if self.reuse_static:
            had = torch.isfinite(st.values).any(1) & torch.isin(st.code, torch.tensor(_VALUE_STATUS, dtype=torch.int8))
            reuse = informative & had & ~st.static.changed(stats) & ~st.static.due(self._counter)
            values[reuse] = st.values[reuse]
            std[reuse] = st.std[reuse]
            code[reuse] = REUSED
            candidates = informative & ~reuse
        else:
            candidates = informative
        first = coarse_lattice(grid, candidates, informative) if self.coarse_refine else candidates
        fresh = torch.zeros(grid.n, dtype=torch.bool)
        idx = first.nonzero()[:, 0]
        partners = informative.nonzero()[:, 0]  # a pooled noise reading's partners (NOISE_MIN_POOL)
        vals, ok, vstd = self._estimate(task, patches, idx, meta, partners)
        estimated = [idx]  # the patches estimated this frame (assessable or not)
        values[idx] = vals
        std[idx] = vstd
        code[idx[~ok]] = NOT_ASSESSABLE
        fresh[idx[ok]] = True
        interpolated = torch.zeros(grid.n, dtype=torch.bool)
        remaining = candidates & ~first
        if bool(remaining.any()):
            valid = torch.isfinite(values).any(1) & torch.isin(code, torch.tensor((ESTIMATED, REUSED), dtype=torch.int8))
            scale = self._noise_scale(stats, meta) if task == "noise" else None
            if scale is not None:  # physics-normalised: σ_s / σ_s,model(M, Ī), ξ / σ_model(M, Ī)
                clipped = stats.clipped_low + stats.clipped_high
                cues = [(stats.noise_dn / scale[:, 4], *cfg.cue_tol_noise_rel), (clipped, 0.02, 0.0)]
                interpolated, ivals = refine_plan(grid, remaining, values / scale, valid, cfg.value_tol_noise_rel, cues)
                # the total is interpolated like the sources (not re-derived as √(Σ σ_s²)): with the total head
                # of the noise-source network it is the realised total after clipping, not the quadrature sum
                ivals = ivals * scale
            elif task == "noise":
                cues = [(stats.mean_dn, cfg.cue_tol_mean_dn, 0.0), (stats.noise_dn, *cfg.cue_tol_noise)]
                interpolated, ivals = refine_plan(grid, remaining, values, valid, cfg.value_tol_noise_dn, cues)
            else:
                cues = [(stats.detail_dn, *cfg.cue_tol_detail)]
                interpolated, ivals = refine_plan(grid, remaining, values, valid, cfg.value_tol_mtf, cues)
            values[interpolated] = ivals[interpolated]
            code[interpolated] = INTERPOLATED
            if task == "noise":  # an interpolated value has no evidence of its own (nor does it, when reused later)
                st.clear_evidence(interpolated.nonzero()[:, 0])
            idx2 = (remaining & ~interpolated).nonzero()[:, 0]
            vals2, ok2, vstd2 = self._estimate(task, patches, idx2, meta, partners)
            estimated.append(idx2)
            values[idx2] = vals2
            std[idx2] = vstd2
            code[idx2[~ok2]] = NOT_ASSESSABLE
            fresh[idx2[ok2]] = True
        new_idx = (fresh | interpolated).nonzero()[:, 0]  # values computed this frame (not reused)
        if self.reuse_static:
            st.static.update(new_idx, stats, self._counter)
        # every patch with a value this frame enters its temporal window, a reused one standing for this frame (as a
        # reused sample does in sampled mode): the window spans the last `window` frames whether or not a patch was
        # re-estimated, so a still camera's change shows as soon as with every patch estimated every frame
        framed = (new_idx if not self.reuse_static
                  else (fresh | interpolated | ((code == REUSED) & torch.isfinite(values).any(1))).nonzero()[:, 0])
        st.push(framed, values[framed])
        st.values, st.code, st.std = values, code, std
        st.gather(torch.cat([*estimated, (code == REUSED).nonzero()[:, 0]]))  # a reused patch keeps its evidence
        fresh_n = int(fresh.sum())
        return self._with_pairs(task, st, self._aggregate(task, st, handle.name, int(informative.sum()), fresh_n))

    def _with_pairs(self, task: str, st: _TaskState, report: TaskReport) -> TaskReport:
        """``coverage["static_pairs"]``: this frame's noise patches read from a static pair (``static_pairs`` on);
        ``coverage["other_exposures"]``: the other exposure times whose evidence joined this frame's
        (``exposure_evidence`` on, with the physics-first noise estimator pooled)."""
        if task == "noise" and self.static_pairs:
            report.coverage["static_pairs"] = st.pairs
        if task == "noise" and self.exposure_evidence and self.pool_noise and "other_evidence" in self.estimators[task].kwargs:
            report.coverage["other_exposures"] = st.exposures
        return report

    @staticmethod
    def _coverage(mode: str, grid: PatchGrid, estimated: int, informative: int, values: int, frames: int,
                  boxes: torch.Tensor | None, reused: int = 0) -> dict[str, Any]:
        area = estimated * grid.patch * grid.patch / float(grid.height * grid.width)
        return {"mode": mode, "estimated": estimated, "reused": reused, "informative": informative, "total": grid.n,
                "area_fraction": round(area, 4), "values": values, "frames": frames,
                "patches_xy": None if boxes is None else boxes[:, :2].tolist()}

    def _aggregate_sampled(self, task: str, st: _TaskState, name: str, informative: int, boxes: torch.Tensor,
                           reused: int = 0, valued: int | None = None) -> TaskReport:
        """Frame answer of sampled mode: median of all samples of the last ``window`` frames (``boxes``: this frame's
        patches estimated and assessable; ``reused`` of this frame's samples are the earlier estimates of unchanged
        patches, each standing for its frame's sample; ``valued``: this frame's samples with a value, estimated or
        reused). Its standard error counts each estimate once: n = the distinct estimates in the window
        (``coverage["values"]``), not a kept estimate once per frame it recurs in."""
        grid = st.grid
        counts = status_counts(st.code)
        counts["total"] = grid.n
        flat = st.samples.reshape(-1, st.k)
        has = torch.isfinite(flat[:, -1])
        vals = flat[has]
        n = int(st.distinct_samples().sum())
        frames = int(torch.isfinite(st.samples[..., -1]).any(1).sum())
        coverage = self._coverage("sampled", grid, int(boxes.shape[0]), informative, n, frames, boxes, reused)
        base = dict(task=task, estimator=name, patch=grid.patch, grid=(grid.rows, grid.cols), counts=counts,
                    grid_obj=grid, values=st.values.clone(), code=st.code.clone(), coverage=coverage, **_refusals(st))
        if (int(boxes.shape[0]) if valued is None else valued) == 0:  # as in map mode: no informative patch
            skipped = {k: v for k, v in counts.items() if k in ("black", "saturated", "featureless", "no_edges", "not_assessable") and v}
            why = ", ".join(f"{v} {k}" for k, v in skipped.items()) or "no patch"
            return TaskReport(**base, assessable=False, note=f"not assessable: no informative patch ({why}"
                              + (f"; refused: {_reasons_text(st.refused)})" if st.refused else ")"))
        spatial = spatial_median(vals, dim=0)
        per_frame = torch.nanquantile(st.samples, 0.5, dim=1)  # (window, K), NaN for frames without samples
        tspread = spatial_median(per_frame, dim=0).spread
        cur = st.samples[(st.sample_slot - 1) % st.window]
        cur = cur[torch.isfinite(cur[:, -1])]
        current = spatial_median(cur, dim=0).median if cur.shape[0] else torch.full((st.k,), float("nan"))
        indicator = ind_unc = None
        if task == "mtf":
            from camhealth.physics.mtf import mtf_indicator

            ind = spatial_median(mtf_indicator(vals), dim=0)
            indicator = (float(ind.median), float(ind.spread))
            ind_unc = _MEDIAN_SE * indicator[1] / math.sqrt(n)
        if task == "mtf":
            ind_frames = spatial_median(mtf_indicator(st.samples.reshape(-1, st.k)).reshape(st.window, -1), dim=1).median
            ind_unc = max(ind_unc, _MEDIAN_SE * float(spatial_median(ind_frames, dim=0).spread) / math.sqrt(frames)) \
                if frames > 1 else ind_unc
        est_std = _pooled_std(st.samples_std.reshape(-1, st.k)[has], st.k)
        if ind_unc is not None:
            ind_unc = max(ind_unc, _indicator_floor(est_std, n, self._error_shared(task)))
        return TaskReport(**base, assessable=True, median=spatial.median, spread=spatial.spread, temporal_spread=tspread,
                          current=current, indicator=indicator,
                          uncertainty=_uncertainty(spatial.spread, n, tspread, frames, est_std, self._shared_posterior(task),
                                                  self._error_shared(task)),
                          indicator_uncertainty=ind_unc, estimator_std=est_std, n_values=n)

    def _aggregate(self, task: str, st: _TaskState, name: str, informative: int = 0, fresh: int = 0) -> TaskReport:
        grid = st.grid
        counts = status_counts(st.code)
        counts["total"] = grid.n
        has = torch.isin(st.code, torch.tensor(_VALUE_STATUS, dtype=torch.int8)) & torch.isfinite(st.values).any(1)
        n = int(has.sum())
        st.frames_valued += int(n > 0)
        frames = min(max(st.frames_valued, 1), self.window)
        coverage = self._coverage("map", grid, fresh, informative, n, frames, None, int((st.code == REUSED).sum()))
        base = dict(task=task, estimator=name, patch=grid.patch, grid=(grid.rows, grid.cols), counts=counts,
                    grid_obj=grid, values=st.values.clone(), code=st.code.clone(), coverage=coverage, **_refusals(st))
        if not bool(has.any()):
            skipped = {k: v for k, v in counts.items() if k not in ("estimated", "interpolated", "reused", "total") and v}
            why = ", ".join(f"{v} {k}" for k, v in skipped.items()) or "no patch"
            return TaskReport(**base, assessable=False, note=f"not assessable: no informative patch ({why}"
                              + (f"; refused: {_reasons_text(st.refused)})" if st.refused else ")"))
        agg = temporal_median(st.history, st.window, dim=0)  # (1, N, K)
        tm = agg.median[0]
        per_patch = torch.where(torch.isfinite(tm), tm, st.values)[has]
        spatial = spatial_median(per_patch, dim=0)
        tspread = agg.spread[0][has]
        tspread = torch.nanquantile(tspread, 0.5, dim=0) if tspread.numel() else torch.full((st.k,), float("nan"))
        current = spatial_median(st.values[has], dim=0).median
        indicator = None
        if task == "mtf":
            from camhealth.physics.mtf import mtf_indicator

            ind = spatial_median(mtf_indicator(per_patch), dim=0)
            indicator = (float(ind.median), float(ind.spread))
        se = _MEDIAN_SE / math.sqrt(n)
        est_std = _pooled_std(st.std[has], st.k)
        return TaskReport(**base, assessable=True, median=spatial.median, spread=spatial.spread,
                          temporal_spread=tspread, current=current, indicator=indicator,
                          uncertainty=_uncertainty(spatial.spread, n, tspread, frames, est_std, self._shared_posterior(task),
                                                  self._error_shared(task)),
                          indicator_uncertainty=None if indicator is None else max(
                              se * indicator[1], _indicator_floor(est_std, n, self._error_shared(task))),
                          estimator_std=est_std, n_values=n)

    # ------------------------------------------------------------------ public
    def process(self, frame: Any, metadata: Any = None, index: int | None = None, source_id: str | None = None,
                bit_depth: int | None = None, input_scaling: Any = None) -> FrameReport:
        """Monitor one frame (see :func:`as_frame` for accepted inputs) → :class:`FrameReport`.

        ``metadata``: this frame's metadata if it differs from the monitor's (CameraMetadata, a mapping of
        changed fields such as ``{"gain_db": 12}``, or a file); a change restarts the aggregation.
        ``bit_depth``: the significant bits of a uint16 frame (:func:`as_frame`): ``None`` (default) or 16 reads it as
        DN/65535, 10, 12 or 14 as DN/(2^bit_depth − 1) — nothing is guessed from the values (the CLI's image files are
        read by :func:`camhealth.data.read_image` with ``--bit-depth``, ``auto`` by default).
        ``input_scaling``: how the frame was scaled to [0, 1] before it came here — the
        :class:`~camhealth.data.io.ImageScaling` of :func:`camhealth.data.read_image_scaled` (a source item's
        ``image_scaling``) or a text (``item.scaling``); the report carries it (``input_scaling``, the ImageScaling's
        ``describe()``). A frame at another scale than the last one given (another divisor 2^bits − 1; another text)
        restarts everything, as :meth:`reset` does — its values are not comparable with the window's — with an
        :class:`InputScalingChanged` warning naming both; ``None`` (default) says nothing and changes nothing.

        ``index`` (``None`` or an integer, NumPy's and 0-d torch integers included) and ``source_id`` (``None``, a text or
        a path) label the report; anything else is a ``TypeError``, before the frame is read.

        Raises :class:`FrameSizeError` (a ``ValueError``) for a frame that does not fit the defect map, leaving the
        monitor as it was."""
        t0 = time.perf_counter()
        scale_key, scale_text, guessed = _input_scaling(input_scaling)
        index, source_id = _frame_label(index, source_id)
        with torch.inference_mode():
            x = as_frame(frame, bit_depth)
            meta, given = self._frame_metadata(metadata)
            h, w = int(x.shape[-2]), int(x.shape[-1])
            self._prepare(h, w, source_id)
            if scale_key is not None:
                if self._scaling is not None and scale_key != self._scaling[0]:
                    self.reset()  # (also the evidence kept per exposure time: it was read at the other scale)
                    self._scaling_changed(self._scaling[1], scale_text, self._scaling[2] or guessed, index, source_id)
                self._scaling = (scale_key, scale_text, guessed)
            key = None if meta is None else tuple(round(float(v[0]), 12) for v in meta.to_dict().values())
            if meta is None and given:  # fields given without a camera state (estimators that read none)
                key = tuple(sorted((k, round(v, 12)) for k, v in given.items()))
            if key != self._meta_key:
                if self._meta_key is not None:
                    self._reset_aggregation()
                self._meta_key = key
            timing = {"convert": (time.perf_counter() - t0) * 1e3}
            reports: dict[str, TaskReport] = {}
            for task in ("noise", "mtf"):
                if task in self.estimators:
                    t1 = time.perf_counter()
                    reports[task] = self._run_task(task, x, meta)
                    timing[task] = (time.perf_counter() - t1) * 1e3
            t2 = time.perf_counter()
            noise = reports.get("noise")
            if "mtf" in reports and noise is not None and noise.banding:
                reports["mtf"] = mtf_under_banding(reports["mtf"], noise.banding, _judged(noise))
            if noise is not None and noise.defects:
                xy = self._states["noise"].defect_xy
                noise.defects["recurring"] = self._recurring(xy)
                if self.defect_map is not None:
                    at = torch.tensor(xy, dtype=torch.int64).reshape(-1, 2)
                    noise.defects["known"] = int(self.defect_map[at[:, 1], at[:, 0]].sum())
            alarm = self._alarm(noise, meta)
            if guessed and alarm["state"] in ("noisier", "cleaner"):
                alarm["message"] += "; " + GUESSED_SCALE_HINT.format(scale=scale_text)
            advice = self._advice(noise, reports.get("mtf"), meta)
            timing["aggregate"] = (time.perf_counter() - t2) * 1e3
        timing["total"] = (time.perf_counter() - t0) * 1e3
        md = (given or None) if meta is None else {k: float(getattr(meta, k)[0]) for k in MINIMAL_FIELDS}
        report = FrameReport(self._counter, index, source_id, h, w, md, noise, reports.get("mtf"), alarm, advice,
                             timing, self.per_patch, scale_text)
        self._counter += 1
        self._times.add(timing["total"])
        for task, r in reports.items():
            for name in STATUS_NAMES:
                self._counts[task][name] += int(r.counts.get(name, 0))
            for why, n in r.refused.items():
                self._refused[task][why] = self._refused[task].get(why, 0) + int(n)
        self._alarms[alarm["state"]] = self._alarms.get(alarm["state"], 0) + 1
        if noise is not None and noise.banding:
            self._banding[0].add(float(noise.banding["row_dn"]))
            self._banding[1].add(float(noise.banding["col_dn"]))
        if noise is not None and noise.defects:
            self._defect_frames.add(float(noise.defects["ppm"]))
        if noise is not None and noise.cause:
            top = top_cause(noise.cause)
            self._causes[top] = self._causes.get(top, 0) + 1
        self._last = report
        return report

    @staticmethod
    def _scaling_changed(old: str, new: str, guessed: bool, index: int | None, source_id: str | None) -> None:
        """The :class:`InputScalingChanged` warning of :meth:`process` (``guessed``: either scale was guessed)."""
        where = source_id if source_id is not None else f"frame {index}" if index is not None else "this frame"
        hint = ""
        if guessed:
            hint = ("; the scale of 16-bit frames without an sBIT chunk is guessed from their largest values, which "
                    "change with the scene: pass --bit-depth N (bit_depth=N in Python), N the camera's significant "
                    "bits, to read every frame at one scale")
        warnings.warn(f"input scaling changed at {where} from {old!r} to {new!r}: the temporal aggregation restarts"
                      + hint, InputScalingChanged, stacklevel=3)

    def _recurring(self, xy: list[tuple[int, int]]) -> int:
        """How many of this frame's defect positions were flagged in an earlier frame of the run; records them (at
        most :data:`DEFECT_POSITIONS` positions are remembered)."""
        seen = self._defect_seen
        out = 0
        for p in xy:
            n = seen.get(p, 0)
            out += n > 0
            if n or len(seen) < DEFECT_POSITIONS:
                seen[p] = n + 1
        return out

    def _alarm(self, noise: TaskReport | None, meta: CameraMetadata | None) -> dict[str, Any]:
        alarm = self._xi_alarm(noise, meta)
        if noise is not None and noise.defects and new_defect_ppm(noise.defects) >= DEFECT_ALARM_PPM:
            alarm["message"] += "; " + defects_text(noise.defects)
        return alarm

    def _xi_alarm(self, noise: TaskReport | None, meta: CameraMetadata | None) -> dict[str, Any]:
        if noise is None:
            return {"state": "unavailable", "xi_dn": None, "limit_dn": None, "message": "noise monitoring is off"}
        if meta is None or getattr(self.estimators["noise"].est, "kind", "") != "noise_source":
            return {"state": "unavailable", "xi_dn": None, "limit_dn": None,
                    "message": "ξ needs a noise-source estimator with metadata"}
        if not noise.assessable or noise.median is None:
            if noise.beyond_xi is not None:
                return beyond_range_alarm(noise.beyond_xi, noise.refused.get(BEYOND_VALIDATED, 0),
                                          sum(noise.refused.values()), self.xi_threshold_dn)
            out = xi_alarm(float("nan"), float("nan"), 0)
            if noise.refused:  # say why: the estimator's reasons for the patches it refused
                out["message"] += f" (refused: {_reasons_text(noise.refused)})"
                if set(noise.refused) == {"textured"}:
                    out["message"] += "; " + TEXTURED_HINT
                elif set(noise.refused) == {LESS_NOISE}:
                    out["message"] += "; " + QUIET_HINT
                elif LOSSY_CODEC in noise.refused:
                    out["message"] += "; " + CODEC_HINT
            return out
        i = NOISE_FIELDS.index("xi")
        count = noise.n_values
        out = xi_alarm(float(noise.median[i]), float(noise.spread[i]), count, self.xi_threshold_dn, self.xi_sigmas,
                       total_dn=noise.value("total"), model_dn=_metadata_total(noise))
        if out["state"] == "noisier" and noise.banding:
            out["message"] += "; " + banding_text(noise.banding)
        elif noise.cause and out["state"] in ("noisier", "cleaner"):
            out["message"] += "; " + cause_text(noise.cause, out["state"] == "noisier")
        elif noise.cause and out["state"] == "ok" and 2 * int(noise.cause.get("patches", 0)) >= _judged(noise):
            # the frame's ξ is within the limit, but its sources depart from the metadata's (a mismatch that moves the
            # total less than the alarm waits for): say what they point to
            out["message"] += ("; the noise sources depart from the metadata's closed form: "
                               + cause_text(noise.cause, noise.value("xi") <= 0))
        return out

    def _advice(self, noise: TaskReport | None, mtf: TaskReport | None, meta: CameraMetadata | None) -> dict[str, Any] | None:
        if self.policy is None:
            return None
        if noise is None or mtf is None or not noise.assessable or not mtf.assessable or meta is None:
            return {"available": False, "reason": "blur or noise not assessable in this frame"}
        sigma = noise.value("total")
        mtf_hat = min(max(mtf.value("indicator"), 0.0), 1.0)
        src = [noise.value(n) for n in ("pn", "dcsn", "rn")]
        kwargs = {"sigma_sources": src} if all(math.isfinite(v) and v >= 0 for v in src) else {}
        try:
            d = self.policy.decide(sigma, mtf_hat, float(meta.exposure_s[0]), float(meta.gain_db[0]), **kwargs)
        except ValueError as exc:
            return {"available": False, "reason": str(exc)}
        return {
            "available": True, "alpha": _num(d.alpha), "exposure_s": _num(d.exposure_s, 6), "gain_db": _num(d.gain_db, 3),
            "expected_ap": _num(d.expected_ap), "current_ap": _num(d.current_ap), "changed": bool(d.changed),
            "explanation": d.explanation,
        }

    def run(
        self, source: Any, start: int = 0, stride: int = 1, max_frames: int | None = None, recording: Any = None,
        bit_depth: int | str = "auto",
    ) -> Iterator[tuple[Any, FrameReport | None]]:
        """Monitor every frame of ``source`` (an image, a folder of frames, a video file, ``"street"`` or a
        recording with ``recording=RecordingOptions(topic=…)``, see :func:`camhealth.monitor.sources.open_source`)
        as the CLI does: yields ``(item, report)`` per frame, with ``report = None`` for a frame that could not
        be read, a partly decoded video frame or a frame the defect map does not fit (``item.error`` says why). A
        recording's camera state (``item.metadata``) is applied per frame. ``bit_depth``: significant bits of 16-bit
        frames (``item.scaling`` names it; a change of it between frames restarts the aggregation, :meth:`process`)."""
        from camhealth.monitor.sources import open_source

        src = open_source(source, start, stride, max_frames, bit_depth=bit_depth, recording=recording)
        try:
            for item in src:
                if item.error is not None:
                    yield item, None
                    continue
                try:
                    report = self.process(item.frame, metadata=item.metadata, index=item.index,
                                          source_id=item.source_id, input_scaling=item.input_scaling())
                except FrameSizeError as exc:  # a frame the defect map does not fit: that frame only
                    item.error = str(exc)
                    yield item, None
                    continue
                yield item, report
        finally:
            close = getattr(src, "close", None)
            if close is not None:
                close()

    @property
    def frames(self) -> int:
        """Frames processed so far."""
        return self._counter

    def found_defects(self, min_frames: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
        """The run's defect map: (bool (H, W), True at the pixels flagged as defective in at least ``min_frames``
        frames; int32 (H, W), the frames each pixel was flagged in) in the frames' size. 2 (default) keeps the
        recurring ones: on a moving camera a defect stays at its pixel while the scene moves; on a static one the
        scene's own points of light recur too. At most :data:`DEFECT_POSITIONS` positions are remembered, of the frames
        of the current size (a frame of another size starts them afresh).
        ``python -m camhealth.monitor --defects-out FILE`` writes them for ``--defect-map``."""
        min_frames = _python_number(min_frames)
        if isinstance(min_frames, bool) or not isinstance(min_frames, int) or min_frames < 1:
            raise ValueError(f"min_frames = {min_frames!r} must be an integer >= 1")
        if self._shape is None:
            raise ValueError("no frame processed yet: the defect map has no size")
        h, w = self._shape
        counts = torch.zeros(h, w, dtype=torch.int32)
        if self._defect_seen:
            xy = torch.tensor(list(self._defect_seen.keys()), dtype=torch.int64)
            counts[xy[:, 1], xy[:, 0]] = torch.tensor(list(self._defect_seen.values()), dtype=torch.int32)
        if min_frames > torch.iinfo(torch.int32).max:  # no int32 count gets there (compared as int32 it would wrap)
            return torch.zeros(h, w, dtype=torch.bool), counts
        return counts >= min_frames, counts

    def _map_summary(self) -> dict[str, Any]:
        """The summary's defect-map fields (:meth:`summary`); empty without a map."""
        dmap = self.defect_map
        if dmap is None:
            return {}
        at = torch.tensor(list(self._defect_seen), dtype=torch.int64).reshape(-1, 2)
        on_map = dict(zip(self._defect_seen, dmap[at[:, 1], at[:, 0]].tolist()))
        new = sorted(((p, n) for p, n in self._defect_seen.items() if n > 1 and not on_map[p]), key=lambda kv: (-kv[1], kv[0]))
        return {"map_pixels": int(dmap.sum()), "map_pixels_flagged": sum(on_map.values()),
                "recurring_new_pixels": len(new), "recurring_new_xy": [[x, y, n] for (x, y), n in new[:DEFECT_LIST]]}

    def summary(self) -> dict[str, Any]:
        """Frames, timing (median/mean/max ms), patch counts per task and status, the patches the estimators refused
        per task and reason, alarm states, the frames whose noise named a cause (``causes``: their count and how many
        named each as the most probable — ``gain``, ``dark_current``, ``readout``; ``None`` without any; a frame's
        :attr:`TaskReport.cause`), the frames with row or column noise (``banding``: their count and the
        median and largest σ per direction [DN]; ``None`` without any), the frames with defective pixels (``defects``:
        their count, the median and largest share per million tested, ``recurring_pixels``, the frame positions
        flagged in more than one frame, and ``recurring_xy``, up to :data:`DEFECT_LIST` of them as [x, y, frames],
        most frames first: a defect map to correct or to compare with a calibration's hot pixels; with ``defect_map``
        also ``map_pixels`` (pixels the map marks), ``map_pixels_flagged`` (of those, flagged in any frame),
        ``recurring_new_pixels`` and ``recurring_new_xy`` (the recurring positions the map does not mark: defects
        new since it was made, or the scene's own points of light on a static camera); ``None`` without any), last
        values."""
        out: dict[str, Any] = {
            "frames": self._counter,
            "ms_per_frame": self._times.stats(2),
            "estimators": {task: h.name for task, h in self.estimators.items()},
            "patches": {task: dict(c) for task, c in self._counts.items()},
            "refused": {task: dict(c) for task, c in self._refused.items()},
            "alarms": dict(self._alarms),
            "banding": None if not self._banding[0].count else {
                "frames": self._banding[0].count,
                **{f"{name}_dn": {k: v for k, v in stat.stats(3).items() if k != "mean"}
                   for name, stat in (("row", self._banding[0]), ("col", self._banding[1]))}},
            "causes": None if not self._causes else {"frames": sum(self._causes.values()),
                                                     **{k: self._causes.get(k, 0) for k in CAUSE_GROUPS}},
            "defects": None if not self._defect_frames.count else {
                "frames": self._defect_frames.count,
                "ppm": {k: v for k, v in self._defect_frames.stats(1).items() if k != "mean"},
                "recurring_pixels": sum(1 for v in self._defect_seen.values() if v > 1),
                "recurring_xy": [[x, y, n] for (x, y), n in sorted(self._defect_seen.items(), key=lambda kv: (-kv[1], kv[0]))
                                 if n > 1][:DEFECT_LIST],
                **self._map_summary()},
            "mode": self.mode, "samples_per_frame": dict(self.n_samples) if self.mode == "sampled" else None,
            "precision": self.precision, "mtf_views": self.mtf_views, "pool_noise": self.pool_noise,
            "static_pairs": self.static_pairs, "exposure_evidence": self.exposure_evidence, "window": self.window,
            "adaptive": {"reuse_static": self.reuse_static, "coarse_refine": self.coarse_refine,
                         "skip_uninformative": self.skip_uninformative},
        }
        if self._last is not None:
            last = self._last.to_dict()
            out["last"] = {"noise": last["noise"], "mtf": last["mtf"], "alarm": last["alarm"], "advice": last["advice"]}
        return out
