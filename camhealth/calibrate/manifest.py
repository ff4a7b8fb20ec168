"""Calibration manifests: which frames form which set, at which exposure, gain and temperature.

YAML (read with a ``yaml.SafeLoader`` that also refuses aliases: a manifest never executes code)::

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
      bit_depth: 12              # optional: significant bits of 16-bit files without an sBIT chunk
    sets:
      - {kind: bias, path: bias, exposure_s: 0.001}            # a folder of frames
      - {kind: dark, path: dark_200ms.mkv, exposure_s: 0.2}    # a lossless video (FFV1)
      - {kind: flat, path: [f1.png, f2.png, f3.png, f4.png], exposure_s: 0.01, name: L1}   # image files
      - {kind: flat, path: "flat_L2/*.tif", exposure_s: 0.02}  # a glob pattern

CSV: a header line and one row per set (``;`` separates several files or globs in ``path``)::

    kind,path,exposure_s,gain_db,temperature_c,name
    bias,bias,0.001,0,25,
    dark,dark_200ms.mkv,0.2,0,25,

Relative paths are relative to the manifest's folder; absolute paths, and relative ones that lead out of it, are
read as given (a manifest names its user's own files; nothing in it is executed). Camera fields go on the command
line with a CSV manifest (``--pixel-size-um`` …). A CSV file may start with a UTF-8 byte-order mark (as Excel saves
it); a row with more fields than the header is refused, naming the row and the extra values.

A set's path whose name follows the file-name convention (:mod:`camhealth.calibrate.frames`, e.g.
``dark_200ms_12dB_40C/``) must agree with the set's values: a kind (flat or not), exposure, gain or temperature in
the name that differs from the manifest's is an error naming both. ``path`` is a string or a list of strings.
YAML aliases (``*name``) are refused: a manifest spells its values out (``defaults`` gives values shared by sets),
so that a few hundred bytes cannot expand into gigabytes. A key given twice in one mapping (``exposure_s: 0.2,
exposure_s: 0.4``) is refused, naming the key, its lines and both values (YAML would keep the last one silently).
"""

from __future__ import annotations

import csv
import glob
import math
import os
import reprlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from camhealth.calibrate.frames import KINDS, FrameSet, _short, check_bit_depth, convention_stem, parse_set_name

__all__ = ["CAMERA_FIELDS", "OPERATING_POINT_FIELDS", "Manifest", "read_manifest"]

#: Datasheet fields a manifest's ``camera`` section may give (``sensor_type: CCD|CMOS`` or ``is_cmos``).
CAMERA_FIELDS: tuple[str, ...] = (
    "sensor_type", "is_cmos", "pixel_size_um", "pixel_clock_hz", "sense_node_gain_v_per_e", "reset_factor",
)
#: Fields of the operating point written to the output metadata.
OPERATING_POINT_FIELDS: tuple[str, ...] = ("gain_db", "exposure_s", "temperature_c")
_SET_KEYS = ("kind", "path", "exposure_s", "gain_db", "temperature_c", "name", "bit_depth")
_DEFAULT_KEYS = ("gain_db", "temperature_c", "exposure_s", "bit_depth")
_SHOW = reprlib.Repr()
_SHOW.maxlevel, _SHOW.maxlist, _SHOW.maxtuple, _SHOW.maxdict, _SHOW.maxstring, _SHOW.maxother = 2, 4, 4, 4, 60, 60


def _shown(value: Any) -> str:
    """A bounded repr of a manifest value for a message (a nested or aliased value is not expanded)."""
    text = _SHOW.repr(value)
    return text if len(text) <= 120 else text[:117] + "..."


@dataclass
class Manifest:
    """A parsed manifest: the sets, datasheet values and the operating point."""

    sets: list[FrameSet]
    camera: dict[str, Any] = field(default_factory=dict)
    operating_point: dict[str, float] = field(default_factory=dict)
    path: Path | None = None


def _readable(p: Path) -> bool:
    """Whether the process may read a file (and list a folder)."""
    return os.access(p, os.R_OK | (os.X_OK if p.is_dir() else 0))


def _expand(entry: Any, base: Path, where: str) -> tuple[list[Path], list[str]]:
    """Paths of one set's ``path`` entry (a string — ``;`` separates several — or a list of strings, globs), and the
    ones that do not exist or cannot be read (each shortened when very long). Anything else (a number, a nested list,
    a mapping) is refused with a bounded message, and so is a path the system cannot look up (too long, say), naming
    ``where`` (the manifest and the set), the path (shortened) and the reason."""
    if entry is None:
        items = []
    elif isinstance(entry, str):
        items = entry.split(";")
    elif isinstance(entry, (list, tuple)):
        bad = [i for i in entry if not isinstance(i, str)]
        if bad:
            raise ValueError(f"{where}: path items must be strings (file, folder or glob names), got {type(bad[0]).__name__} "
                             f"{_shown(bad[0])}")
        items = list(entry)
    else:
        raise ValueError(f"{where}: path must be a string or a list of strings, got {type(entry).__name__} {_shown(entry)}")
    items = [i.strip() for i in items if i.strip()]
    if not items:
        raise ValueError(f"{where}: no path given")
    found, missing = [], []
    for item in items:
        try:
            p = Path(item).expanduser()
            p = p if p.is_absolute() else base / p
            if any(ch in item for ch in "*?["):
                hits = sorted(Path(h) for h in glob.glob(str(p)))
                (found.extend(hits) if hits else missing.append(f"{_short(p)} (pattern matched nothing)"))
                missing.extend(f"{_short(h)} (not readable)" for h in hits if not _readable(h))
            elif p.exists():
                found.append(p)
                if not _readable(p):
                    missing.append(f"{_short(p)} (not readable)")
            else:
                missing.append(_short(p))
        except (OSError, RuntimeError) as exc:  # a name too long, a symlink loop, no home for "~user"
            why = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
            raise ValueError(f"{where}: path {_short(item)} cannot be used: {why}") from None
    return found, missing


def _number(value: Any, key: str, where: str) -> float:
    """A manifest value as a finite float (a number, or a string that spells one); else ``ValueError`` naming
    ``where`` (the manifest, the set), the key and the value (bounded: a 400-digit number is not echoed whole)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise ValueError(f"{where}: {key} = {_shown(value)} must be a number")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {key} = {_shown(value)} must be a number") from None
    except OverflowError:  # an integer beyond a float's range (10**400)
        v = math.inf
    if not math.isfinite(v):
        raise ValueError(f"{where}: {key} = {_shown(value)} must be a finite number")
    return v


def _name_conflicts(kind: str, values: dict[str, float], paths: list[Path], where: str) -> None:
    """Raises ``ValueError`` when a path's name follows the file-name convention and gives a kind (flat or not),
    exposure, gain or temperature other than the manifest's, naming both; names that do not follow it are skipped."""
    checked: set[str] = set()
    for p in paths:
        stems = [convention_stem(p)]
        if not p.is_dir():
            stems.append(p.parent.name)  # image files in a folder named by the convention
        for stem in stems:
            if stem in checked:
                continue
            checked.add(stem)
            try:
                info = parse_set_name(stem)
            except ValueError:
                continue
            if (info["kind"] == "flat") != (kind == "flat"):
                raise ValueError(f"{where}: kind {kind!r} contradicts the name {stem!r} ({info['kind']}) of {p}; correct the "
                                 "manifest or the name")
            clash = [f"{key} = {values[key]:g} {unit} (the name: {info[key]:g} {unit})"
                     for key, unit in (("exposure_s", "s"), ("gain_db", "dB"), ("temperature_c", "°C"))
                     if key in info and not math.isclose(info[key], values[key], rel_tol=1e-6, abs_tol=1e-9)]
            if clash:
                raise ValueError(f"{where}: {'; '.join(clash)} contradict{'s' if len(clash) == 1 else ''} the name {stem!r} of "
                                 f"{p}; correct the manifest or the name")


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
        unknown = sorted(map(str, set(row) - set(_SET_KEYS)))
        if unknown:
            raise ValueError(f"{where}: unknown key(s) {_shown(unknown)}; known: {list(_SET_KEYS)}")
        kind = row.get("kind", "")
        kind = kind.strip().lower() if isinstance(kind, str) else kind
        if kind not in KINDS:
            raise ValueError(f"{where}: kind {_shown(row.get('kind'))} must be one of {list(KINDS)}")
        values = {}
        for key in ("exposure_s", "gain_db", "temperature_c"):
            v = row.get(key)
            if v is None or (isinstance(v, str) and not v.strip()):
                v = defaults.get(key)
            if v is None:
                raise ValueError(f"{where} ({kind}): {key} is missing; give it in the set or under 'defaults'")
            values[key] = _number(v, key, where)
        bits = row.get("bit_depth")
        if bits is None or (isinstance(bits, str) and not bits.strip()):
            bits = defaults.get("bit_depth")
        if isinstance(bits, str):
            bits = _number(bits, "bit_depth", where)
        bits = check_bit_depth(bits, where)
        name = row.get("name")
        if name is not None and not isinstance(name, (str, int, float)):
            raise ValueError(f"{where}: name = {_shown(name)} must be a string")
        paths, miss = _expand(row.get("path"), base, where)
        missing.extend(f"{where} ({kind}): {m}" for m in miss)
        if not miss:
            _name_conflicts(kind, values, paths, where)
            name = str(name or "").strip()
            label = row.get("path") if isinstance(row.get("path"), str) else f"{paths[0]}" + (f" (+{len(paths) - 1} files)" if len(paths) > 1 else "")
            sets.append(FrameSet(kind, paths=paths, name=name or label, bit_depth=bits, origin=where, **values))
    if missing:
        unreadable = sum(m.endswith("(not readable)") for m in missing)
        listed = "\n  ".join(missing[:20]) + ("\n  …" if len(missing) > 20 else "")
        if unreadable == len(missing):
            raise ValueError(f"{origin} names {len(missing)} file(s)/folder(s) it cannot read (permission):\n  {listed}")
        raise FileNotFoundError(f"{origin} names {len(missing) - unreadable} missing file(s)/folder(s)"
                                + (f" and {unreadable} it cannot read" if unreadable else "") + f":\n  {listed}")
    return sets


class _AliasRefused(ValueError):
    """A manifest that uses a YAML alias, or gives a key twice in one mapping."""


def _node_text(node: Any) -> str:
    """A YAML node's value for a message: a scalar as written (bounded), else what kind of node it is."""
    import yaml

    if isinstance(node, yaml.ScalarNode):
        return _shown(node.value)
    return "a list" if isinstance(node, yaml.SequenceNode) else "a mapping"


def _manifest_loader():
    """``yaml.SafeLoader`` (no Python objects) that also refuses aliases and a key given twice in one mapping
    (:class:`_AliasRefused`)."""
    import yaml

    class ManifestLoader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            if isinstance(node, yaml.MappingNode):
                seen: dict[Any, tuple[Any, Any]] = {}
                for key_node, value_node in node.value:
                    if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == "tag:yaml.org,2002:merge":
                        continue  # (an unhashable key is refused by the constructor; a merge key may be overridden)
                    key = self.construct_object(key_node, deep=True)
                    try:
                        first = seen.get(key)
                    except TypeError:
                        continue
                    if first is not None:
                        (k1, v1) = first
                        line1, line2 = k1.start_mark.line + 1, key_node.start_mark.line + 1
                        lines = f"line {line1}" if line1 == line2 else f"lines {line1} and {line2}"
                        raise _AliasRefused(
                            f"{lines}: key {_shown(key)} is given twice in one mapping ({_node_text(v1)} and "
                            f"{_node_text(value_node)}); YAML would keep the last one silently — give each key once"
                        )
                    seen[key] = (key_node, value_node)
            return super().construct_mapping(node, deep=deep)

        def compose_node(self, parent, index):
            if self.check_event(yaml.events.AliasEvent):
                event = self.peek_event()
                raise _AliasRefused(
                    f"line {event.start_mark.line + 1}: YAML alias *{str(event.anchor)[:40]} refused; a manifest spells its "
                    "values out (give values shared by sets under 'defaults'), so that a short file cannot expand into "
                    "gigabytes"
                )
            return super().compose_node(parent, index)

    return ManifestLoader


def read_manifest(path: str | Path) -> Manifest:
    """Read a YAML (``.yaml``/``.yml``) or CSV (``.csv``) manifest (module docstring).

    Raises:
        FileNotFoundError: the manifest, or files/folders it names, do not exist (all missing ones listed, and those it
            cannot read).
        ValueError: a manifest that is not a regular file (a folder, a FIFO), files/folders it names that all exist
            but cannot be read, a path that cannot be looked up (too long), a key given twice in one YAML mapping, a
            CSV row with more fields than its header, unknown keys, a missing exposure/gain/temperature, a bad kind, a section that is not a mapping,
            a value that is not a finite number where one is needed (``gain_db: 999…9`` too), text that is not UTF-8,
            unparsable content, values nested too deeply to parse, a YAML alias, a ``path`` that is not a string or a
            list of strings, a set whose values contradict its path's name (the message names the manifest).
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"manifest not found: {p}")
    if not p.is_file():
        raise ValueError(f"manifest {p} is not a regular file (a folder, FIFO or device); give a .yaml, .yml or .csv file")
    base = p.parent
    suffix = p.suffix.lower()
    origin = f"manifest {p}"
    if suffix in (".yaml", ".yml"):
        import yaml

        try:
            data = yaml.load(p.read_text(encoding="utf-8"), Loader=_manifest_loader())
        except _AliasRefused as exc:
            raise ValueError(f"{origin}: {exc}") from None
        except RecursionError:  # the YAML composer recurses once per level of nesting
            raise ValueError(f"cannot parse {origin}: its values are nested too deeply (more levels than Python's recursion "
                             "limit allows); a manifest needs a few levels: sections, a list of sets, a set's mapping") from None
        except yaml.YAMLError as exc:
            raise ValueError(f"cannot parse {origin}: {str(exc).splitlines()[0]}") from None
        except UnicodeDecodeError as exc:
            raise ValueError(f"cannot read {origin}: not UTF-8 text ({exc.reason} at byte {exc.start}); save it as "
                             "UTF-8") from None
        except ValueError as exc:  # a value YAML's constructor cannot convert (an integer of more than 4300 digits)
            raise ValueError(f"cannot parse {origin}: {str(exc)[:200]}") from None
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
        bad = sorted(map(str, set(defaults) - set(_DEFAULT_KEYS)))
        if bad:
            raise ValueError(f"{origin}: unknown default(s) {_shown(bad)}; known: {', '.join(_DEFAULT_KEYS)}")
        for k, v in camera.items():
            if k != "sensor_type" and not (k == "is_cmos" and isinstance(v, bool)):  # is_cmos: true is a flag
                camera[k] = _number(v, k, f"{origin}, camera")
        return Manifest(_sets(rows, base, defaults, origin), camera, op, p)
    if suffix == ".csv":
        try:
            with p.open(newline="", encoding="utf-8-sig") as fh:  # (a byte-order mark, as Excel writes it, is skipped)
                reader = csv.DictReader(fh)
                if reader.fieldnames is None:
                    raise ValueError(f"{origin} is empty; expected a header line {','.join(_SET_KEYS)}")
                header = [h.strip() for h in reader.fieldnames]
                unknown = sorted(set(header) - set(_SET_KEYS))
                if unknown or "kind" not in header or "path" not in header:
                    raise ValueError(f"{origin}: header {header} must name columns from {list(_SET_KEYS)}, with kind and path")
                rows = []
                for r in reader:
                    extra = [v for v in (r.get(None) or []) if isinstance(v, str) and v.strip()]
                    if extra:
                        raise ValueError(
                            f"{origin}, set {len(rows) + 1} (line {reader.line_num}): {len(extra)} value(s) beyond the header's "
                            f"{len(header)} columns ({','.join(header)}): {_shown(extra)}; add their column to the header, or "
                            "quote a value that holds a comma"
                        )
                    rows.append({k.strip(): (v.strip() if isinstance(v, str) else v) for k, v in r.items() if k is not None and v not in (None, "")})
        except UnicodeDecodeError as exc:
            raise ValueError(f"cannot read {origin}: not UTF-8 text ({exc.reason} at byte {exc.start}); save it as "
                             "UTF-8") from None
        except csv.Error as exc:
            raise ValueError(f"cannot parse {origin}: {exc}") from None
        return Manifest(_sets(rows, base, {}, origin), {}, {}, p)
    raise ValueError(f"manifest {p} must be .yaml, .yml or .csv, got {p.suffix!r}")
