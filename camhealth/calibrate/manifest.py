"""Calibration manifests: which frames form which set, at which exposure, gain and temperature.

YAML (read with ``yaml.safe_load``: a manifest never executes code)::

    camera:                      # optional datasheet values (CameraMetadata fields)
      sensor_type: CMOS          # CCD | CMOS
      pixel_size_um: 5.3
      pixel_clock_hz: 90.0e6
      sense_node_gain_v_per_e: 5.0e-6
      reset_factor: 0.0          # optional; fitted from the dark sets when they span ≥ 2 temperatures (CMOS)
    operating_point:             # optional: gain_db, exposure_s, temperature_c written to the output YAML
      gain_db: 6
      exposure_s: 0.02
      temperature_c: 35
    defaults:                    # optional: values of sets that do not give them
      gain_db: 0
      temperature_c: 25
    sets:
      - {kind: bias, path: bias, exposure_s: 0.001}            # a folder of frames
      - {kind: dark, path: dark_200ms.mp4, exposure_s: 0.2}    # a video
      - {kind: flat, path: [f1.png, f2.png, f3.png, f4.png], exposure_s: 0.01, name: L1}   # image files
      - {kind: flat, path: "flat_L2/*.tif", exposure_s: 0.02}  # a glob pattern

CSV: a header line and one row per set (``;`` separates several files or globs in ``path``)::

    kind,path,exposure_s,gain_db,temperature_c,name
    bias,bias,0.001,0,25,
    dark,dark_200ms.mp4,0.2,0,25,

Relative paths are relative to the manifest's folder. Camera fields go on the command line with a CSV
manifest (``--pixel-size-um`` …).
"""

from __future__ import annotations

import csv
import glob
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from camhealth.calibrate.frames import KINDS, FrameSet

__all__ = ["CAMERA_FIELDS", "OPERATING_POINT_FIELDS", "Manifest", "read_manifest"]

#: Datasheet fields a manifest's ``camera`` section may give (``sensor_type: CCD|CMOS`` or ``is_cmos``).
CAMERA_FIELDS: tuple[str, ...] = (
    "sensor_type", "is_cmos", "pixel_size_um", "pixel_clock_hz", "sense_node_gain_v_per_e", "reset_factor",
)
#: Fields of the operating point written to the output metadata.
OPERATING_POINT_FIELDS: tuple[str, ...] = ("gain_db", "exposure_s", "temperature_c")
_SET_KEYS = ("kind", "path", "exposure_s", "gain_db", "temperature_c", "name")


@dataclass
class Manifest:
    """A parsed manifest: the sets, datasheet values and the operating point."""

    sets: list[FrameSet]
    camera: dict[str, Any] = field(default_factory=dict)
    operating_point: dict[str, float] = field(default_factory=dict)
    path: Path | None = None


def _expand(entry: Any, base: Path, where: str) -> tuple[list[Path], list[str]]:
    """Paths of one set's ``path`` entry (string, list, globs), and the ones that do not exist."""
    items = entry if isinstance(entry, (list, tuple)) else str(entry).split(";") if entry is not None else []
    items = [str(i).strip() for i in items if str(i).strip()]
    if not items:
        raise ValueError(f"{where}: no path given")
    found, missing = [], []
    for item in items:
        p = Path(item).expanduser()
        p = p if p.is_absolute() else base / p
        if any(ch in item for ch in "*?["):
            hits = sorted(Path(h) for h in glob.glob(str(p)))
            (found.extend(hits) if hits else missing.append(f"{p} (pattern matched nothing)"))
        elif p.exists():
            found.append(p)
        else:
            missing.append(str(p))
    return found, missing


def _number(value: Any, key: str, where: str) -> float:
    if isinstance(value, bool):
        raise ValueError(f"{where}: {key} = {value!r} must be a number")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {key} = {value!r} must be a number") from None


def _section(data: dict, name: str, origin: str) -> dict[str, Any]:
    """A YAML manifest's optional section ``name`` (a mapping of field: value; absent or empty: ``{}``)."""
    value = data.get(name)
    if value is None:
        return {}
    if not isinstance(value, dict):
        shown = repr(value) if len(repr(value)) <= 60 else repr(value)[:57] + "..."
        raise ValueError(f"{origin}: section {name!r} must be a mapping of field: value, got {type(value).__name__} "
                         f"{shown}")
    return dict(value)


def _sets(rows: list[dict], base: Path, defaults: dict, origin: str) -> list[FrameSet]:
    sets, missing = [], []
    for i, row in enumerate(rows):
        where = f"{origin}, set {i + 1}"
        if not isinstance(row, dict):
            raise ValueError(f"{where}: each set must be a mapping with keys {list(_SET_KEYS)}, got {type(row).__name__}")
        unknown = sorted(set(row) - set(_SET_KEYS))
        if unknown:
            raise ValueError(f"{where}: unknown key(s) {unknown}; known: {list(_SET_KEYS)}")
        kind = str(row.get("kind", "")).strip().lower()
        if kind not in KINDS:
            raise ValueError(f"{where}: kind {row.get('kind')!r} must be one of {list(KINDS)}")
        values = {}
        for key in ("exposure_s", "gain_db", "temperature_c"):
            v = row.get(key)
            if v is None or (isinstance(v, str) and not v.strip()):
                v = defaults.get(key)
            if v is None:
                raise ValueError(f"{where} ({kind}): {key} is missing; give it in the set or under 'defaults'")
            values[key] = _number(v, key, where)
        paths, miss = _expand(row.get("path"), base, where)
        missing.extend(f"{where} ({kind}): {m}" for m in miss)
        if not miss:
            name = str(row.get("name") or "").strip()
            sets.append(FrameSet(kind, paths=paths, name=name or str(row.get("path")), **values))
    if missing:
        raise FileNotFoundError(
            f"{origin} names {len(missing)} missing file(s)/folder(s):\n  " + "\n  ".join(missing[:20])
            + ("\n  …" if len(missing) > 20 else "")
        )
    return sets


def read_manifest(path: str | Path) -> Manifest:
    """Read a YAML (``.yaml``/``.yml``) or CSV (``.csv``) manifest (module docstring).

    Raises:
        FileNotFoundError: the manifest, or files/folders it names, do not exist (all missing ones listed).
        ValueError: unknown keys, a missing exposure/gain/temperature, a bad kind, a section that is not a mapping,
            text that is not UTF-8, unparsable content (the message names the manifest).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"manifest not found: {p}")
    base = p.parent
    suffix = p.suffix.lower()
    origin = f"manifest {p}"
    if suffix in (".yaml", ".yml"):
        import yaml

        try:
            data = yaml.safe_load(p.read_text(encoding="utf-8"))
        except yaml.YAMLError as exc:
            raise ValueError(f"cannot parse {origin}: {str(exc).splitlines()[0]}") from None
        except UnicodeDecodeError as exc:
            raise ValueError(f"cannot read {origin}: not UTF-8 text ({exc.reason} at byte {exc.start}); save it as "
                             "UTF-8") from None
        if not isinstance(data, dict) or "sets" not in data:
            raise ValueError(f"{origin} must be a mapping with a 'sets' list (and optional camera, operating_point, defaults)")
        unknown = sorted(set(data) - {"sets", "camera", "operating_point", "defaults"})
        if unknown:
            raise ValueError(f"{origin}: unknown section(s) {unknown}; known: sets, camera, operating_point, defaults")
        rows = data.get("sets") or []
        if not isinstance(rows, list):
            raise ValueError(f"{origin}: 'sets' must be a list of sets")
        camera = _section(data, "camera", origin)
        bad = sorted(set(camera) - set(CAMERA_FIELDS))
        if bad:
            raise ValueError(f"{origin}: unknown camera field(s) {bad}; known: {list(CAMERA_FIELDS)}")
        op = _section(data, "operating_point", origin)
        bad = sorted(set(op) - set(OPERATING_POINT_FIELDS))
        if bad:
            raise ValueError(f"{origin}: unknown operating_point field(s) {bad}; known: {list(OPERATING_POINT_FIELDS)}")
        op = {k: _number(v, k, f"{origin}, operating_point") for k, v in op.items()}
        defaults = _section(data, "defaults", origin)
        bad = sorted(set(defaults) - {"gain_db", "temperature_c", "exposure_s"})
        if bad:
            raise ValueError(f"{origin}: unknown default(s) {bad}; known: gain_db, temperature_c, exposure_s")
        for k, v in camera.items():
            if k != "sensor_type":
                camera[k] = _number(v, k, f"{origin}, camera")
        return Manifest(_sets(rows, base, defaults, origin), camera, op, p)
    if suffix == ".csv":
        try:
            with p.open(newline="", encoding="utf-8") as fh:
                reader = csv.DictReader(fh)
                if reader.fieldnames is None:
                    raise ValueError(f"{origin} is empty; expected a header line {','.join(_SET_KEYS)}")
                header = [h.strip() for h in reader.fieldnames]
                unknown = sorted(set(header) - set(_SET_KEYS))
                if unknown or "kind" not in header or "path" not in header:
                    raise ValueError(f"{origin}: header {header} must name columns from {list(_SET_KEYS)}, with kind and path")
                rows = [{k.strip(): (v.strip() if isinstance(v, str) else v) for k, v in r.items() if k is not None and v not in (None, "")} for r in reader]
        except UnicodeDecodeError as exc:
            raise ValueError(f"cannot read {origin}: not UTF-8 text ({exc.reason} at byte {exc.start}); save it as "
                             "UTF-8") from None
        except csv.Error as exc:
            raise ValueError(f"cannot parse {origin}: {exc}") from None
        return Manifest(_sets(rows, base, {}, origin), {}, {}, p)
    raise ValueError(f"manifest {p} must be .yaml, .yml or .csv, got {p.suffix!r}")
