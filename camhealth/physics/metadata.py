"""Camera metadata of the Konnik & Welsh (2014) sensor-noise model, batched.

The 11 variable parameters of thesis Table 4.1 (ranges in ``conventions.md``) are stored as one value
per sample (1-D tensors of length B), so a batch of images can come from a batch of different cameras
and operating points. The fixed parameters of Table B.1 live in :class:`SensorConstants`.

Units are in the field names: ``gain_db`` [dB], ``exposure_s`` [s], ``temperature_c`` [°C],
``dark_fom_na_per_cm2`` [nA/cm² at 300 K], ``full_well_e`` [e⁻], ``pixel_clock_hz`` [Hz],
``sense_node_gain_v_per_e`` [V/e⁻], ``reset_factor`` [–], ``pixel_size_um`` [µm], ``is_cmos`` [bool],
``white_noise_v_per_rthz`` [V/√Hz].
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
import torch

from camhealth._validation import check_choice
from camhealth.physics._format import show, show_outside

__all__ = [
    "CameraMetadata",
    "SensorConstants",
    "SENSOR_CONSTANT_RANGES",
    "METADATA_RANGES",
    "MINIMAL_FIELDS",
    "FULL_FIELDS",
    "PRESETS",
    "db_to_factor",
    "factor_to_db",
    "celsius_to_kelvin",
    "kelvin_to_celsius",
]

#: Allowed range (inclusive) of every variable parameter, thesis Table 4.1. Used to validate and to
#: normalise network inputs to [0, 1].
METADATA_RANGES: dict[str, tuple[float, float]] = {
    "gain_db": (0.0, 24.0),
    "exposure_s": (0.001, 0.2),
    "temperature_c": (0.0, 80.0),
    "dark_fom_na_per_cm2": (0.0, 1.0),
    "full_well_e": (2_000.0, 100_000.0),
    "pixel_clock_hz": (8e6, 150e6),
    "sense_node_gain_v_per_e": (1e-6, 5e-6),
    "reset_factor": (0.0, 1.0),
    "pixel_size_um": (0.9, 10.0),
    "is_cmos": (0.0, 1.0),
    "white_noise_v_per_rthz": (1e-9, 60e-9),
}

UNITS: dict[str, str] = {
    "gain_db": "dB",
    "exposure_s": "s",
    "temperature_c": "°C",
    "dark_fom_na_per_cm2": "nA/cm²",
    "full_well_e": "e⁻",
    "pixel_clock_hz": "Hz",
    "sense_node_gain_v_per_e": "V/e⁻",
    "reset_factor": "",
    "pixel_size_um": "µm",
    "is_cmos": "",
    "white_noise_v_per_rthz": "V/√Hz",
}

#: File types :meth:`CameraMetadata.from_file` reads.
METADATA_FILE_SUFFIXES: tuple[str, ...] = (".yaml", ".yml", ".json")

#: The "Min-Meta" set: what any camera driver reports.
MINIMAL_FIELDS: tuple[str, ...] = ("gain_db", "exposure_s", "temperature_c")
#: The "Full-Meta" set: all 11 variable parameters, in Table 4.1 order.
FULL_FIELDS: tuple[str, ...] = tuple(METADATA_RANGES)
METADATA_SETS: dict[str, tuple[str, ...]] = {"none": (), "minimal": MINIMAL_FIELDS, "full": FULL_FIELDS}


def db_to_factor(gain_db: torch.Tensor | float) -> torch.Tensor:
    """Amplitude gain factor from decibels: g = 10^(dB/20) (0 dB → 1, 24 dB → 15.85)."""
    return torch.pow(10.0, torch.as_tensor(gain_db) / 20.0)


def factor_to_db(gain_factor: torch.Tensor | float) -> torch.Tensor:
    """Decibels from an amplitude gain factor: dB = 20·log10(g)."""
    return 20.0 * torch.log10(torch.as_tensor(gain_factor))


def celsius_to_kelvin(t_c: torch.Tensor | float) -> torch.Tensor:
    """Temperature in kelvin from °C."""
    return torch.as_tensor(t_c) + 273.15


def kelvin_to_celsius(t_k: torch.Tensor | float) -> torch.Tensor:
    """Temperature in °C from kelvin."""
    return torch.as_tensor(t_k) - 273.15


#: Allowed range (inclusive) and unit of every fixed sensor constant (:class:`SensorConstants`). Generous: the
#: defaults (conventions.md) lie well inside; the ends keep every formula finite and meaningful (a time or gain of 0
#: divides by 0 in Eq. 3.17, a negative corner frequency makes the 1/f noise power negative and σ NaN, an RTN
#: current of 1 mA a read noise of 10⁶ DN).
SENSOR_CONSTANT_RANGES: dict[str, tuple[float, float, str]] = {
    "offset_dn": (0.0, 255.0, "DN"),
    "cds_gain": (0.01, 10.0, ""),
    "cds_sample_time_s": (1e-9, 1e-4, "s"),
    "cds_time_factor": (0.01, 100.0, ""),
    "flicker_corner_hz": (0.0, 1e9, "Hz"),
    "rtn_current_a": (0.0, 1e-6, "A"),
    "rtn_time_factor": (1e-3, 1e3, ""),
    "source_follower_gain": (0.01, 10.0, "V/V"),
    "reference_voltage_v": (0.1, 100.0, "V"),
}


def check_sensor_constant(name: str, value: Any, where: str | None = None) -> float:
    """``value`` of the sensor constant ``name`` as a float, or ``TypeError`` (not a real number, or a bool) /
    ``ValueError`` (NaN, ±inf or outside :data:`SENSOR_CONSTANT_RANGES`) naming ``where`` (default
    ``SensorConstants.<name>``), the value and the allowed range."""
    low, high, unit = SENSOR_CONSTANT_RANGES[name]
    where = f"SensorConstants.{name}" if where is None else where
    u = f" {unit}" if unit else ""
    if isinstance(value, torch.Tensor) and value.ndim == 0 and value.dtype != torch.bool and not value.is_complex():
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{where} must be a real number{f' in {unit}' if unit else ''}, got {type(value).__name__} "
                        f"{value!r:.60}")
    try:
        v = float(value)
    except OverflowError:  # a Python int beyond float's range
        raise ValueError(f"{where} = {str(value)[:24]}… is out of the allowed range [{low:g}, {high:g}]{u}") from None
    if not (low <= v <= high):  # (NaN fails both comparisons)
        raise ValueError(f"{where} = {show_outside(v, low, high)}{u} is out of the allowed range [{low:g}, {high:g}]{u}")
    return v


@dataclass(frozen=True)
class SensorConstants:
    """Fixed metadata of the noise model (thesis Table B.1, conventions.md).

    Every field is checked on construction (:data:`SENSOR_CONSTANT_RANGES`): a real number (not a bool), finite and
    inside its range, else ``TypeError``/``ValueError`` naming the field, the value and the range. Values are stored
    as Python floats.

    Attributes:
        offset_dn: camera offset [DN], 0…255.
        cds_gain: gain left over from correlated double sampling [–], 0.01…10.
        cds_sample_time_s: CDS sample-to-sample time t_s [s], 1e-9…1e-4.
        cds_time_factor: τ_D = cds_time_factor · t_s, the CDS dominant time constant [–], 0.01…100.
        flicker_corner_hz: flicker (1/f) noise corner frequency f_c [Hz], 0…1e9.
        rtn_current_a: random-telegraph source-follower current modulation ΔI [A] (CMOS only), 0…1e-6.
        rtn_time_factor: τ_RTN = rtn_time_factor · τ_D [–], 1e-3…1e3.
        source_follower_gain: A_SF [V/V], 0.01…10.
        reference_voltage_v: sense-node reference voltage [V], 0.1…100: the conventions' fixed 5 V for every preset
            (informative: no camhealth.physics function reads it, the ADC maps the full well to 255 DN; the
            EV76C661's own 3.3 V would change nothing here, and one set of constants keeps presets
            concatenable into one batch — give ``SensorConstants(reference_voltage_v=3.3)`` to carry it).
    """

    offset_dn: float = 0.0
    cds_gain: float = 1.0
    cds_sample_time_s: float = 1e-6
    cds_time_factor: float = 0.5
    flicker_corner_hz: float = 1e6
    rtn_current_a: float = 1e-8
    rtn_time_factor: float = 0.1
    source_follower_gain: float = 1.0
    reference_voltage_v: float = 5.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            object.__setattr__(self, f.name, check_sensor_constant(f.name, getattr(self, f.name)))

    @property
    def cds_time_constant_s(self) -> float:
        """τ_D [s]."""
        return self.cds_time_factor * self.cds_sample_time_s

    @property
    def rtn_time_constant_s(self) -> float:
        """τ_RTN [s]."""
        return self.rtn_time_factor * self.cds_time_constant_s


def _as_vector(name: str, value: Any) -> torch.Tensor:
    if isinstance(value, bool):
        if name != "is_cmos":  # a flag is the one field a bool may give; True as 1 dB or 1 s is a slip, not a value
            raise TypeError(f"camera metadata {name} must be a number in {UNITS.get(name, '')}, got bool {value!r}")
        value = float(value)
    if isinstance(value, int):  # a Python int of any size (10**30 overflows torch's int64): its float, range-checked later
        try:
            value = float(value)
        except OverflowError:  # beyond float's range (10**400): out of every field's range
            low, high = METADATA_RANGES.get(name, (-math.inf, math.inf))
            unit = UNITS.get(name, "")
            u = f" {unit}" if unit else ""
            raise ValueError(f"camera metadata {name} = {str(value)[:24]}… is out of the allowed range "
                             f"[{low:g}, {high:g}]{u}") from None
    if not isinstance(value, torch.Tensor):
        unit = UNITS.get(name, "")
        expected = f"a number{f' in {unit}' if unit else ''} or a 1-D sequence/tensor of per-sample numbers"
        if value is None or isinstance(value, (str, bytes)):
            raise TypeError(f"camera metadata {name} must be {expected}, got {type(value).__name__} {value!r}")
        try:
            value = torch.as_tensor(value)
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(f"camera metadata {name} must be {expected}, got {type(value).__name__} {value!r:.60}") from None
    t = value
    if t.is_complex():
        raise TypeError(f"camera metadata {name} must hold real numbers, got dtype {t.dtype}")
    if t.dtype == torch.bool and name != "is_cmos":  # (as for a Python bool: True as 1 dB or 1 s is a slip)
        raise TypeError(f"camera metadata {name} must hold numbers in {UNITS.get(name, '')}, got a bool tensor")
    if not t.is_floating_point():
        t = t.to(torch.float32)
    if t.ndim == 0:
        t = t.reshape(1)
    if t.ndim != 1:
        raise ValueError(f"metadata field {name} must be a scalar or a 1-D per-sample tensor, got shape {tuple(t.shape)}")
    return t


class _DuplicateKey(ValueError):
    """A key given twice in one mapping of a metadata file (the parsers would keep the last one silently)."""


def _unique_json_object(pairs: list[tuple[str, Any]]) -> dict:
    """``json.loads``' ``object_pairs_hook``: the object, or :class:`_DuplicateKey` naming a key given twice."""
    out: dict = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKey(f"field {key} is given twice ({out[key]!r} and {value!r})")
        out[key] = value
    return out


@functools.lru_cache(maxsize=None)
def _unique_key_loader() -> Any:
    """``yaml.SafeLoader`` (no Python objects) that refuses a key given twice in one mapping (:class:`_DuplicateKey`,
    naming the key and its lines); keys a merge (``<<: *anchor``) brings in may be overridden, as YAML says."""
    import yaml

    class UniqueKeyLoader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            if isinstance(node, yaml.MappingNode):
                seen: dict[Any, int] = {}
                for key_node, _ in node.value:
                    if key_node.tag == "tag:yaml.org,2002:merge":
                        continue
                    key = self.construct_object(key_node, deep=False)
                    line = key_node.start_mark.line + 1
                    try:
                        if key in seen:
                            where = f"on line {line}" if seen[key] == line else f"lines {seen[key]} and {line}"
                            raise _DuplicateKey(f"field {key} is given twice ({where})")
                        seen[key] = line
                    except TypeError:  # an unhashable key: the constructor reports it
                        continue
            return super().construct_mapping(node, deep=deep)

    return UniqueKeyLoader


def read_metadata_mapping(path: Any) -> dict:
    """The mapping of a ``.yaml``/``.yml``/``.json`` metadata file (``yaml.safe_load``/``json``: a file never executes
    code). Raises ``FileNotFoundError``, or ``ValueError`` naming the file: another suffix, text that is not UTF-8,
    text that does not parse, a field given twice (the parsers would keep the last one), or content that is not a
    mapping."""
    from pathlib import Path

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"metadata file not found: {p}")
    suffix = p.suffix.lower()
    if suffix not in METADATA_FILE_SUFFIXES:
        raise ValueError(f"metadata file {p} must be .json, .yaml or .yml, got {p.suffix!r}")
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"metadata file {p} is not UTF-8 text: byte 0x{exc.object[exc.start]:02x} at position "
                         f"{exc.start} (save it as UTF-8)") from None
    try:
        if suffix == ".json":
            import json

            data = json.loads(text, object_pairs_hook=_unique_json_object)
        else:
            import yaml

            data = yaml.load(text, Loader=_unique_key_loader())
    except _DuplicateKey as exc:
        raise ValueError(f"metadata file {p}: {exc}; give each field once") from None
    except Exception as exc:  # json.JSONDecodeError, yaml.YAMLError
        raise ValueError(f"cannot parse metadata file {p}: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise ValueError(f"metadata file {p} must hold a mapping of field: value, got {type(data).__name__}")
    return data


def _normalise_metadata_mapping(data: Mapping[str, Any]) -> dict[str, Any]:
    """A mapping of metadata field → value(s) with ``sensor_type: CCD|CMOS`` turned into ``is_cmos`` (0/1), as
    :meth:`CameraMetadata.from_dict`, :meth:`CameraMetadata.sample` (``fixed=``) and the corruption modules
    (``metadata=``) read it. Raises ``TypeError``/``ValueError`` on a ``sensor_type`` that is not ``"CCD"`` or
    ``"CMOS"``, one that contradicts ``is_cmos``, or an unknown key (listing the known fields)."""
    if not isinstance(data, Mapping):
        raise TypeError(f"metadata must be a mapping of field: value, got {type(data).__name__}")
    data = dict(data)
    if "sensor_type" in data:
        raw = data.pop("sensor_type")
        if not isinstance(raw, str):
            raise TypeError(f"camera metadata sensor_type must be 'CCD' or 'CMOS', got {type(raw).__name__} {raw!r}")
        st = raw.upper()
        check_choice(st, "sensor_type", ("CCD", "CMOS"))
        is_cmos = 1.0 if st == "CMOS" else 0.0
        if "is_cmos" in data:
            given = _as_vector("is_cmos", data["is_cmos"])
            if not bool((given == is_cmos).all()):
                raise ValueError(
                    f"camera metadata sensor_type = {raw!r} contradicts is_cmos = {data['is_cmos']!r} "
                    f"(CMOS is is_cmos = 1, CCD is 0); give one of them"
                )
        data["is_cmos"] = is_cmos
    unknown = set(data) - set(FULL_FIELDS)
    if unknown:
        hint = ""
        if "sensor" in unknown:  # a preset's name, as a metadata file's sensor: key gives it
            hint = (f"; sensor = {data['sensor']!r} names a preset, not a field: start from it with "
                    f"CameraMetadata.preset({data['sensor']!r}, …) or from_dict(…, base={data['sensor']!r})")
        raise ValueError(f"unknown metadata field(s) {sorted(unknown, key=str)}; known fields: {list(FULL_FIELDS)}"
                         + hint)
    return data


@dataclass
class CameraMetadata:
    """Batched camera metadata: one value per sample for each of the 11 variable parameters.

    Construct from scalars or 1-D tensors (broadcast to the common batch size), from a preset
    (:meth:`preset`), by random sampling (:meth:`sample`), or from a dict (:meth:`from_dict`). Every
    instance is validated on construction: a non-finite or out-of-range value raises ``ValueError``
    naming the field, the value and the allowed range (``METADATA_RANGES``).

    Attributes:
        gain_db: camera gain [dB], 0…24 (factor 10^(dB/20) = 1…15.85).
        exposure_s: exposure time [s], 0.001…0.2.
        temperature_c: sensor temperature [°C], 0…80.
        dark_fom_na_per_cm2: dark-current figure of merit D_FM [nA/cm² at 300 K], 0…1.
        full_well_e: full-well capacity [e⁻], 2 000…100 000. The ADC maps the full well to 255 DN.
        pixel_clock_hz: pixel clock / readout frequency [Hz], 8e6…150e6.
        sense_node_gain_v_per_e: sense-node conversion gain A_SN [V/e⁻], 1e-6…5e-6.
        reset_factor: fraction of the kTC reset noise left after CDS [–], 0 (removed)…1 (CMOS only).
        pixel_size_um: pixel pitch d_p [µm], 0.9…10.
        is_cmos: sensor type, 1.0 = CMOS, 0.0 = CCD.
        white_noise_v_per_rthz: source-follower thermal white noise W [V/√Hz], 1e-9…60e-9.
        constants: fixed metadata (Table B.1).
    """

    gain_db: torch.Tensor
    exposure_s: torch.Tensor
    temperature_c: torch.Tensor
    dark_fom_na_per_cm2: torch.Tensor
    full_well_e: torch.Tensor
    pixel_clock_hz: torch.Tensor
    sense_node_gain_v_per_e: torch.Tensor
    reset_factor: torch.Tensor
    pixel_size_um: torch.Tensor
    is_cmos: torch.Tensor
    white_noise_v_per_rthz: torch.Tensor
    constants: SensorConstants = field(default_factory=SensorConstants)

    def __post_init__(self) -> None:
        vecs = {name: _as_vector(name, getattr(self, name)) for name in FULL_FIELDS}
        sizes = {v.shape[0] for v in vecs.values()}
        batch = max(sizes)
        if not sizes <= {1, batch}:
            detail = ", ".join(f"{k}: {v.shape[0]}" for k, v in vecs.items())
            raise ValueError(f"metadata fields have incompatible batch sizes ({detail})")
        device = next((v.device for v in vecs.values() if v.device.type != "cpu"), torch.device("cpu"))
        dtype = torch.float64 if any(v.dtype == torch.float64 for v in vecs.values()) else torch.float32
        for name, v in vecs.items():
            w = v.to(device=device, dtype=dtype)
            if v.dtype in (torch.float16, torch.bfloat16):
                # a range end given in half precision is rounded by up to 2^-9 (bf16) or 2^-12 (fp16) of its value:
                # 0.2 s in bf16 is 0.2002 s. Values within two rounding steps outside the range are the range end.
                low, high = METADATA_RANGES[name]
                eps = 2.0 * torch.finfo(v.dtype).eps  # two rounding steps of that end's own value
                w = torch.where((w < low) & (w >= low - eps * abs(low)), torch.full_like(w, low), w)
                w = torch.where((w > high) & (w <= high + eps * abs(high)), torch.full_like(w, high), w)
            object.__setattr__(self, name, w.expand(batch).contiguous())
        self.validate()

    # ------------------------------------------------------------------ validation / conversion
    def validate(self) -> "CameraMetadata":
        """Raise ``ValueError`` naming the field, the sample, the value and the range on a bad value."""
        for name in FULL_FIELDS:
            v = getattr(self, name)
            low, high = METADATA_RANGES[name]
            # A relative slack of 1e-6 of each range end absorbs float32 rounding of that end (0.2 s stored in
            # float32 is 0.2000000030 in float64) without admitting physically different values. An end at 0 is
            # exact in every dtype and gets none: a negative D_FM or reset factor is refused (σ would be NaN).
            lo_ok, hi_ok = low - 1e-6 * abs(low), high + 1e-6 * abs(high)
            bad = ~torch.isfinite(v) | (v < lo_ok) | (v > hi_ok)
            if name == "is_cmos":
                bad = bad | ((v != 0) & (v != 1))
            if bool(bad.any()):
                i = int(torch.nonzero(bad)[0, 0])
                unit = UNITS[name]
                u = f" {unit}" if unit else ""
                allowed = (lambda x: x in (0.0, 1.0)) if name == "is_cmos" else (lambda x: lo_ok <= x <= hi_ok)
                raise ValueError(
                    f"camera metadata {name}[{i}] = {show(v[i].item(), allowed, v.dtype)}{u} is out of the allowed range "
                    f"[{low:g}, {high:g}]{u}" + (" (0 = CCD, 1 = CMOS)" if name == "is_cmos" else "")
                )
        return self

    @property
    def batch_size(self) -> int:
        return int(self.gain_db.shape[0])

    @property
    def device(self) -> torch.device:
        return self.gain_db.device

    @property
    def dtype(self) -> torch.dtype:
        return self.gain_db.dtype

    def __len__(self) -> int:
        return self.batch_size

    @property
    def gain_factor(self) -> torch.Tensor:
        """Amplitude gain g = 10^(gain_db/20) [–], shape (B,)."""
        return db_to_factor(self.gain_db)

    @property
    def temperature_k(self) -> torch.Tensor:
        """Sensor temperature T [K], shape (B,)."""
        return celsius_to_kelvin(self.temperature_c)

    @property
    def dn_per_electron(self) -> torch.Tensor:
        """Output DN per electron after gain, g·255/FW [DN/e⁻], shape (B,)."""
        return self.gain_factor * 255.0 / self.full_well_e

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "CameraMetadata":
        """Copy to another device and/or floating dtype (float32 or float64 recommended)."""
        kw = {n: getattr(self, n).to(device=device, dtype=dtype) for n in FULL_FIELDS}
        return CameraMetadata(**kw, constants=self.constants)

    def replace(self, **changes: Any) -> "CameraMetadata":
        """New metadata with some fields changed (validated), e.g. ``meta.replace(gain_db=12.0)``."""
        return dataclasses.replace(self, **changes)

    def __getitem__(self, index: int | slice | torch.Tensor | Sequence[int]) -> "CameraMetadata":
        """Select samples, e.g. ``meta[3]``, ``meta[:4]`` or ``meta[mask]``."""
        if isinstance(index, int) and not isinstance(index, bool):
            if not -self.batch_size <= index < self.batch_size:
                raise IndexError(f"metadata index {index} is out of range for batch size {self.batch_size}")
            index = index % self.batch_size
            index = slice(index, index + 1)
        kw = {n: getattr(self, n)[index] for n in FULL_FIELDS}
        return CameraMetadata(**kw, constants=self.constants)

    def expand(self, batch_size: int) -> "CameraMetadata":
        """Repeat a single-sample metadata to ``batch_size`` samples (an integer ≥ 0; 0 gives an empty batch)."""
        batch_size = _check_batch_size(batch_size, "batch_size", low=0)
        if self.batch_size == batch_size:
            return self
        if self.batch_size != 1:
            raise ValueError(f"cannot expand metadata of batch size {self.batch_size} to {batch_size}; only 1 → B")
        kw = {n: getattr(self, n).expand(batch_size) for n in FULL_FIELDS}
        return CameraMetadata(**kw, constants=self.constants)

    @staticmethod
    def cat(items: Sequence["CameraMetadata"]) -> "CameraMetadata":
        """Concatenate metadata batches (constants must agree)."""
        if not items:
            raise ValueError("CameraMetadata.cat needs at least one item")
        consts = items[0].constants
        for j, m in enumerate(items):
            if m.constants != consts:
                diff = ", ".join(f"{f.name} = {getattr(m.constants, f.name)!r} vs {getattr(consts, f.name)!r}"
                                 for f in dataclasses.fields(SensorConstants)
                                 if getattr(m.constants, f.name) != getattr(consts, f.name))
                raise ValueError(f"cannot concatenate metadata with different fixed SensorConstants: item {j} has {diff} "
                                 "(item 0); a batch has one set of constants")
        kw = {n: torch.cat([getattr(m, n) for m in items]) for n in FULL_FIELDS}
        return CameraMetadata(**kw, constants=consts)

    def to_dict(self) -> dict[str, list[float]]:
        """Plain dict of lists (JSON/YAML friendly); inverse of :meth:`from_dict`."""
        return {n: getattr(self, n).tolist() for n in FULL_FIELDS}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], base: "CameraMetadata | str | None" = None) -> "CameraMetadata":
        """Build from a mapping of field → value(s). Missing fields come from ``base`` (a preset name or
        metadata); unknown keys raise ``ValueError`` listing the known ones. ``sensor_type: CCD|CMOS`` is
        accepted for ``is_cmos``."""
        data = _normalise_metadata_mapping(data)
        if base is None:
            missing = [n for n in FULL_FIELDS if n not in data]
            if missing:
                raise ValueError(f"metadata is missing field(s) {missing}; give them or a base preset")
            return cls(**data)
        if isinstance(base, str):
            base = cls.preset(base)
        return base.replace(**data) if data else base

    # ------------------------------------------------------------------ network normalisation
    def normalize(self, fields: str | Sequence[str] = "full") -> torch.Tensor:
        """Map the selected fields linearly to [0, 1] with ``METADATA_RANGES``; shape (B, n).

        ``fields`` is ``"none"``, ``"minimal"`` (gain, exposure, temperature), ``"full"`` (all 11) or an
        explicit list of field names. Gain is normalised in dB.
        """
        names = _field_names(fields)
        if not names:
            return self.gain_db.new_zeros(self.batch_size, 0)
        cols = []
        for n in names:
            low, high = METADATA_RANGES[n]
            cols.append((getattr(self, n) - low) / (high - low))
        return torch.stack(cols, dim=1)

    @classmethod
    def denormalize(
        cls, values: torch.Tensor, fields: str | Sequence[str] = "full", base: "CameraMetadata | str | None" = None
    ) -> "CameraMetadata":
        """Inverse of :meth:`normalize`: (B, n) in [0, 1] → metadata; fields not given come from ``base``."""
        names = _field_names(fields)
        if values.ndim != 2 or values.shape[1] != len(names):
            raise ValueError(f"expected normalised metadata of shape (B, {len(names)}) for {names}, got {tuple(values.shape)}")
        # physical units in float32 at least: fp16 cannot hold a 28.64 MHz pixel clock (it is inf there), nor bf16
        # a 5e-6 V/e⁻ sense-node gain to the range's precision
        values = values.to(torch.promote_types(values.dtype, torch.float32)) if values.is_floating_point() else values.float()
        data = {}
        for j, n in enumerate(names):
            low, high = METADATA_RANGES[n]
            data[n] = values[:, j] * (high - low) + low
        if "is_cmos" in data:
            data["is_cmos"] = data["is_cmos"].round()
        b = values.shape[0]
        if base is not None:
            base = cls.preset(base) if isinstance(base, str) else base
            base = base.expand(b) if base.batch_size == 1 else base
            base = base.to(device=values.device, dtype=values.dtype)
        return cls.from_dict(data, base=base)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_file(cls, path: Any) -> "CameraMetadata":
        """Metadata (batch 1) from a ``.yaml``/``.yml``/``.json`` file holding a mapping of field: value in physical
        units — e.g. the ``camera.yaml`` that ``python -m camhealth.calibrate`` writes. ``sensor_type: CCD|CMOS``
        is accepted for ``is_cmos`` and ``sensor: <preset>`` fills fields the file does not give; all 11 fields
        are needed otherwise. Read with ``yaml.safe_load``/``json`` (a file never executes code).

        Raises ``FileNotFoundError`` or ``ValueError`` naming the file and what is wrong with it.
        """
        p = path
        data = read_metadata_mapping(p)
        base = data.pop("sensor", None)
        for key, value in data.items():
            if key != "sensor_type" and (isinstance(value, bool) or not isinstance(value, (int, float))):
                raise ValueError(f"metadata file {p}: field {key} = {value!r} must be a number in physical units")
        try:
            return cls.from_dict(data, base=str(base) if base is not None else None)
        except (TypeError, ValueError) as exc:  # (TypeError: a sensor_type that is not a string)
            raise ValueError(f"metadata file {p}: {exc}") from None

    @classmethod
    def lookup(cls, name_or_path: Any) -> "CameraMetadata":
        """A preset by name (``"ICX285"``, ``"EV76C661"``) or the metadata of a ``.yaml``/``.yml``/``.json`` file
        (:meth:`from_file`)."""
        text = str(name_or_path)
        if text.lower().endswith(METADATA_FILE_SUFFIXES):
            return cls.from_file(text)
        return cls.preset(text)

    @classmethod
    def preset(cls, name: str, batch_size: int = 1, **operating_point: Any) -> "CameraMetadata":
        """Metadata of a known sensor (``"ICX285"`` CCD or ``"EV76C661"`` CMOS) at an operating point.

        ``operating_point`` overrides any field, typically ``gain_db``, ``exposure_s`` and
        ``temperature_c`` (defaults 0 dB, 0.01 s, 25 °C). The fixed constants are :class:`SensorConstants`' defaults
        (conventions.md's fixed metadata), the same for every preset, so presets concatenate into one batch.
        """
        if not isinstance(name, str):
            raise ValueError(f"sensor preset {name!r} is not a name; known presets: {sorted(PRESETS)}")
        batch_size = _check_batch_size(batch_size, low=0)
        key = name.upper()
        if key not in PRESETS:
            raise ValueError(f"unknown sensor preset {name!r}; known presets: {sorted(PRESETS)}")
        data = {"gain_db": 0.0, "exposure_s": 0.01, "temperature_c": 25.0, **PRESETS[key], **operating_point}
        unknown = set(data) - set(FULL_FIELDS)
        if unknown:
            raise ValueError(f"unknown metadata field(s) {sorted(unknown)}; known fields: {list(FULL_FIELDS)}")
        meta = cls(**data, constants=SensorConstants())
        return meta.expand(batch_size) if meta.batch_size == 1 else meta

    @classmethod
    def sample(
        cls,
        batch_size: int,
        generator: torch.Generator | None = None,
        ranges: Mapping[str, tuple[float, float]] | None = None,
        fixed: "CameraMetadata | str | Mapping[str, Any] | None" = None,
        device: torch.device | str | None = None,
        gain_uniform_in: str = "factor",
    ) -> "CameraMetadata":
        """Draw ``batch_size`` random cameras/operating points uniformly from ``ranges``.

        Args:
            batch_size: number of samples B.
            generator: torch generator for reproducibility (CPU generator; values moved to ``device``).
            ranges: per-field (low, high) overriding ``METADATA_RANGES`` (each must lie inside it).
                ``is_cmos`` takes (0, 0) (CCD), (1, 1) (CMOS) or (0, 1) (a fair coin); any other range is a
                ``ValueError``.
            fixed: fields held fixed instead of sampled: a preset name or metadata file path
                (:meth:`lookup`), metadata of batch 1 or B (its :class:`SensorConstants` are kept), or a dict read
                as :meth:`from_dict` reads one (``sensor_type: CCD|CMOS`` accepted, an unknown key is a
                ``ValueError``); only fields *not* named in ``ranges`` are taken from it.
            gain_uniform_in: ``"factor"`` (the thesis: uniform in the linear gain factor, converted to dB)
                or ``"db"``.
        """
        check_choice(gain_uniform_in, "gain_uniform_in", ("factor", "db"))
        batch_size = _check_batch_size(batch_size)
        if ranges is not None and not isinstance(ranges, Mapping):
            raise TypeError(f"ranges must be a mapping of field: (low, high), e.g. {{'gain_db': (0.0, 24.0)}}, got "
                            f"{type(ranges).__name__} {ranges!r:.60}")
        rng = dict(METADATA_RANGES)
        for n, value in (ranges or {}).items():
            if n not in METADATA_RANGES:
                raise ValueError(f"unknown metadata field {n!r} in ranges; known fields: {list(FULL_FIELDS)}")
            lo, hi = _range_pair(value, n)
            glo, ghi = METADATA_RANGES[n]
            if not (glo <= lo <= hi <= ghi):
                ok = lambda x, y: glo <= x <= y <= ghi  # noqa: E731
                shown = (f"{lo:g}", f"{hi:g}") if not ok(float(f"{lo:g}"), float(f"{hi:g}")) else (repr(lo), repr(hi))
                raise ValueError(f"range for {n} = ({shown[0]}, {shown[1]}) must satisfy {glo:g} ≤ low ≤ high ≤ {ghi:g}")
            if n == "is_cmos" and (float(lo), float(hi)) not in ((0.0, 0.0), (1.0, 1.0), (0.0, 1.0)):
                raise ValueError(f"range for is_cmos = ({lo:g}, {hi:g}) must be (0, 0) (CCD only), (1, 1) (CMOS only) "
                                 "or (0, 1) (either, a fair coin)")
            rng[n] = (float(lo), float(hi))
        # Fields taken from ``fixed`` (all of a preset/metadata, the keys of a dict), unless sampled
        # explicitly through ``ranges``.
        fixed_values: dict[str, Any] = {}
        constants = SensorConstants()
        if isinstance(fixed, str):
            fixed = cls.lookup(fixed)
        if isinstance(fixed, CameraMetadata):
            fm = fixed.expand(batch_size) if fixed.batch_size == 1 else fixed
            fixed_values = {n: getattr(fm, n).float().cpu() for n in FULL_FIELDS}
            constants = fixed.constants
        elif isinstance(fixed, Mapping):
            fixed_values = _normalise_metadata_mapping(fixed)
        elif fixed is not None:
            raise TypeError(f"fixed must be a preset name, CameraMetadata or dict, got {type(fixed).__name__}")
        for n in ranges or {}:
            fixed_values.pop(n, None)
        u = torch.rand(batch_size, len(FULL_FIELDS), generator=generator, dtype=torch.float64)
        data: dict[str, Any] = {}
        for j, n in enumerate(FULL_FIELDS):
            lo, hi = rng[n]
            if n == "is_cmos":
                v = (u[:, j] < 0.5).double() if lo != hi else torch.full((batch_size,), lo, dtype=torch.float64)
            elif n == "gain_db" and gain_uniform_in == "factor":
                flo, fhi = 10 ** (lo / 20), 10 ** (hi / 20)
                v = (20 * torch.log10(flo + u[:, j] * (fhi - flo))).clamp(lo, hi)
            else:
                v = lo + u[:, j] * (hi - lo)
            data[n] = v.float()
        data.update(fixed_values)
        meta = cls(**data, constants=constants)
        return meta.to(device=device) if device is not None else meta


def _check_batch_size(batch_size: Any, name: str = "batch_size", low: int = 1) -> int:
    """``batch_size`` as an int: ``TypeError`` unless it is an integer (a bool is none), ``ValueError`` below ``low``."""
    if isinstance(batch_size, torch.Tensor) and batch_size.ndim == 0 and not batch_size.is_floating_point() \
            and not batch_size.is_complex() and batch_size.dtype != torch.bool:
        batch_size = int(batch_size)
    if isinstance(batch_size, bool) or not isinstance(batch_size, numbers.Integral):
        raise TypeError(f"{name} must be an integer ≥ {low}, got {type(batch_size).__name__} {batch_size!r:.40}")
    if batch_size < low:
        raise ValueError(f"{name} = {batch_size} must be an integer ≥ {low}")
    return int(batch_size)


def _range_pair(value: Any, name: str) -> tuple[float, float]:
    """A sampling range of ``ranges``: a (low, high) pair of real numbers (or one number: (v, v)) as floats, else
    ``TypeError``/``ValueError`` naming the field (a bool or a string is no number)."""
    def number(v: Any) -> float:
        if isinstance(v, torch.Tensor) and v.ndim == 0 and v.dtype != torch.bool and not v.is_complex():
            v = v.item()
        if isinstance(v, bool) or not isinstance(v, numbers.Real):
            raise TypeError(f"range for {name} must be a (low, high) pair of numbers, got {value!r:.60} "
                            f"({type(v).__name__} {v!r:.20} is no number)")
        try:
            f = float(v)
        except OverflowError:
            f = math.inf if v > 0 else -math.inf
        if math.isnan(f):
            raise ValueError(f"range for {name} = {value!r:.60} must hold finite numbers")
        return f

    if isinstance(value, np.ndarray):
        value = value.tolist()  # (a 0-d array gives its number)
    if isinstance(value, torch.Tensor):
        value = value.item() if value.ndim == 0 and value.dtype != torch.bool else list(value) if value.ndim == 1 else value
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        v = number(value)
        return v, v
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        raise TypeError(f"range for {name} must be a (low, high) pair of numbers, got {type(value).__name__} {value!r:.60}")
    if len(value) != 2:
        raise ValueError(f"range for {name} must be a (low, high) pair, got {len(value)} values {value!r:.60}")
    return number(value[0]), number(value[1])


def _field_names(fields: str | Sequence[str]) -> tuple[str, ...]:
    if isinstance(fields, str):
        check_choice(fields, "metadata set", tuple(METADATA_SETS))
        return METADATA_SETS[fields]
    names = tuple(fields)
    unknown = [n for n in names if n not in METADATA_RANGES]
    if unknown:
        raise ValueError(f"unknown metadata field(s) {unknown}; known fields: {list(FULL_FIELDS)}")
    return names


#: Sensor presets (thesis App. A.2 and the authors' measured values, conventions.md). The sense-node
#: gain of the EV76C661 is not published; 5 µV/e⁻ with the kTC residue 0 reproduces its measured read
#: noise of ≈ 24 e⁻ through the source-follower model (see tests/physics/test_readout_noise.py).
PRESETS: dict[str, dict[str, float]] = {
    "ICX285": {
        "pixel_size_um": 6.45,
        "full_well_e": 14_000.0,
        "dark_fom_na_per_cm2": 0.00889,
        "pixel_clock_hz": 28.64e6,
        "white_noise_v_per_rthz": 30.8e-9,
        "sense_node_gain_v_per_e": 5e-6,
        "reset_factor": 0.0,
        "is_cmos": 0.0,
    },
    "EV76C661": {
        "pixel_size_um": 5.3,
        "full_well_e": 8_400.0,
        "dark_fom_na_per_cm2": 0.957,
        "pixel_clock_hz": 90e6,
        "white_noise_v_per_rthz": 59e-9,
        "sense_node_gain_v_per_e": 5e-6,
        "reset_factor": 0.0,
        "is_cmos": 1.0,
    },
}

# Physical constants (CODATA).
BOLTZMANN_EV_PER_K = 8.617343e-5  # k [eV/K], as in the dark-current law (conventions.md)
BOLTZMANN_J_PER_K = 1.380649e-23  # k [J/K]
ELEMENTARY_CHARGE_C = 1.602176634e-19  # q [C]
