"""Check a ``.pt2`` archive (:func:`torch.export.save`) before :func:`torch.export.load` opens it.

torch's loader unpickles some entries without ``weights_only`` (weights or constants flagged ``use_pickle``,
custom and opaque objects, legacy ``.pt`` payloads, and the sample inputs when a weights-only load of them
fails), loads AOTInductor shared libraries, evaluates symbolic-shape strings with ``sympy.sympify`` and resolves
graph targets by attribute lookup from ``torch``. A file from someone else could run code through any of them.
:func:`check_pt2_archive` reads the archive as a zip and JSON only (no unpickling, nothing imported) and refuses
it unless every entry is one that :func:`camhealth.export.export_pt2` writes:

- raw tensor payloads (``data/weights/weight_N``, ``data/constants/tensor_N``) described by JSON configs with
  ``use_pickle: false``; no custom or opaque objects, no AOTInductor/ExecuTorch/MTIA data, no legacy ``.pt``;
- sample inputs that load with ``torch.load(weights_only=True)`` (so torch never falls back to a full unpickle);
- graphs whose call targets are PyTorch operators (``torch.ops.<namespace>.<op>[.<overload>]``, not the
  library loaders of ``torch.ops``) or the arithmetic builtins torch's verifier allows, whose guard code only compares input sizes, and whose symbolic shapes are sympy expressions of numbers, quoted symbol names
  and the arithmetic functions torch serialises (no attribute access, no other names);
- entries whose declared uncompressed sizes (the zip directory's, read before anything is inflated) stay within
  :data:`MAX_ZIP_ENTRY_BYTES` each, :data:`MAX_JSON_ENTRY_BYTES` for the JSON entries and :data:`MAX_ZIP_TOTAL_BYTES`
  together (:func:`zip_size_problem`; a few MB of deflated zeros would otherwise inflate to gigabytes). Only the
  entries it inspects are read (graphs, payload configs, sample inputs); tensor payloads and ``extra/`` files are not.

What stays is torch's own deserialiser running on plain data. It is not designed for hostile input: prefer
weights files (``.pt``) for files from others (``docs/reliability.md``).
"""

from __future__ import annotations

import io
import json
import re
import tokenize
import zipfile
from pathlib import Path
from typing import Any, Iterator

__all__ = ["check_pt2_archive", "zip_size_problem", "MAX_ZIP_ENTRY_BYTES", "MAX_ZIP_TOTAL_BYTES", "MAX_JSON_ENTRY_BYTES"]

#: Largest declared uncompressed size of one entry of a zip archive camhealth opens (``.pt``, ``.ckpt``, ``.pt2``)
#: [bytes]. The largest shipped network holds 2.2 MB of weights; a network this size (64 M float32 values) is far
#: beyond anything camhealth trains, so a larger entry is a decompression bomb or not a camhealth file.
MAX_ZIP_ENTRY_BYTES = 256 * 2**20
#: Largest declared uncompressed size of all entries of such an archive together [bytes].
MAX_ZIP_TOTAL_BYTES = 512 * 2**20
#: Largest declared uncompressed size of a JSON entry of a ``.pt2`` archive (graph, payload config, description)
#: [bytes]; camhealth's graphs are 0.1–0.5 MB.
MAX_JSON_ENTRY_BYTES = 16 * 2**20

_FIXED = {"archive_format", "archive_version", "byteorder", ".data/version", ".data/serialization_id"}
_ALLOWED = [
    re.compile(r"extra/[A-Za-z0-9_.\-]+"),
    re.compile(r"models/(?P<model>[A-Za-z0-9_]+)\.json"),
    re.compile(r"data/weights/[A-Za-z0-9_]+_weights_config\.json"),
    re.compile(r"data/weights/weight_\d+"),
    re.compile(r"data/constants/[A-Za-z0-9_]+_constants_config\.json"),
    re.compile(r"data/constants/tensor_\d+"),
    re.compile(r"data/sample_inputs/[A-Za-z0-9_]+\.pt"),
]
_PAYLOAD_NAME = re.compile(r"(weight|tensor)_\d+")
_SEGMENT = re.compile(r"[A-Za-z0-9_]+")
#: The Python builtins torch.export's verifier lets a graph call (``_operator.*``, ``math.*``), and the attributes of
#: ``torch.ops`` that are not operator namespaces (they load libraries and import modules).
_OPERATOR_BUILTINS = frozenset(
    "getitem add mul sub truediv ge le gt lt eq ne floordiv mod and_ or_ not_ pow neg abs lshift rshift".split()
)
_MATH_BUILTINS = frozenset({"ceil", "floor", "trunc"})
_OPS_ATTRIBUTES = frozenset({"import_module", "load_library", "loaded_libraries"})
#: Names a serialised symbolic shape may call: sympy's arithmetic, logic and number classes, and the functions
#: torch.export's deserialiser provides (``torch.utils._sympy.functions``).
_SYMPY_NAMES = frozenset(
    "Symbol Dummy Integer Rational Float Mul Add Pow Max Min Mod Abs floor ceiling sign Eq Ne Lt Le Gt Ge "
    "Equality Unequality StrictLessThan StrictGreaterThan LessThan GreaterThan And Or Not Xor Piecewise ExprCondPair "
    "BooleanTrue BooleanFalse true false True False oo zoo nan Infinity NegativeInfinity One Zero NegativeOne Half "
    "FloorDiv ModularIndexing Where PythonMod CleanDiv CeilToInt FloorToInt CeilDiv LShift RShift PowByNatural "
    "FloatPow FloatTrueDiv IntTrueDiv IsNonOverlappingAndDenseIndicator TruncToFloat TruncToInt RoundToInt "
    "RoundDecimal ToFloat Identity".split()
)
_SYMPY_OPS = frozenset({"(", ")", ",", "=", "+", "-", "*", "/", "**", "%", "<", ">", "<=", ">=", "==", "!=", "&", "|", "~"})
#: Guard code torch.export writes for a dynamic batch: comparisons of input sizes, e.g. ``L['image'].size()[0] ==
#: L['prior'].size()[0]`` (it becomes Python source of the loaded module, so nothing else is let through).
_SIZE_TERM = r"(?:L\['[A-Za-z_][A-Za-z0-9_]*'\]\.size\(\)\[\d+\]|\d+)"
_GUARD = re.compile(rf"{_SIZE_TERM}(?:\s*(?:==|!=|<=|>=|<|>|\+|-|\*|//|%)\s*{_SIZE_TERM})*")
_QUOTED_NAME = re.compile(r"""(['"])[A-Za-z_][A-Za-z0-9_]*\1""")
_SYMBOL_NAME = re.compile(r"[a-z]+[0-9]+")


def _refuse(path: Path, why: str) -> ValueError:
    return ValueError(f"{path}: refused to load this .pt2 archive: {why} (camhealth loads only the plain tensors and "
                      f"operator graphs that camhealth.export writes; a weights file, .pt, is the safe format)")


def zip_size_problem(infos: list[zipfile.ZipInfo], json_entries: frozenset[str] | set[str] = frozenset()) -> str | None:
    """Why the entries ``infos`` of a zip archive are too large to read, from the sizes its directory declares (nothing
    is inflated), or ``None``: an entry above :data:`MAX_ZIP_ENTRY_BYTES` (one named in ``json_entries`` above
    :data:`MAX_JSON_ENTRY_BYTES`), or all of them together above :data:`MAX_ZIP_TOTAL_BYTES`. The message names the
    entry, its declared size and the limit."""
    total = 0
    for info in infos:
        limit, name = ((MAX_JSON_ENTRY_BYTES, "MAX_JSON_ENTRY_BYTES") if info.filename in json_entries
                       else (MAX_ZIP_ENTRY_BYTES, "MAX_ZIP_ENTRY_BYTES"))
        if info.file_size > limit:
            return (f"entry {info.filename[:80]!r} declares {info.file_size:,} bytes uncompressed ({info.compress_size:,} "
                    f"stored), more than the limit of {limit:,} bytes ({name}); a camhealth network's file holds a few MB")
        total += info.file_size
    if total > MAX_ZIP_TOTAL_BYTES:
        return (f"its {len(infos)} entries declare {total:,} bytes uncompressed together, more than the limit of "
                f"{MAX_ZIP_TOTAL_BYTES:,} bytes (MAX_ZIP_TOTAL_BYTES); a camhealth network's file holds a few MB")
    return None


def _json(path: Path, name: str, text: bytes) -> Any:
    """``text`` parsed as JSON, or the archive refused naming the entry (not JSON, nested deeper than Python's recursion
    limit, an integer of more digits than Python converts)."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise _refuse(path, f"{name} is not JSON ({exc})") from None
    except UnicodeDecodeError as exc:
        raise _refuse(path, f"{name} is not JSON text ({exc.reason} at byte {exc.start})") from None
    except RecursionError:
        raise _refuse(path, f"{name} nests JSON deeper than Python's recursion limit") from None
    except ValueError as exc:  # an integer beyond sys.get_int_max_str_digits
        raise _refuse(path, f"{name} is not JSON that can be read ({str(exc).splitlines()[0][:120]})") from None


def _walk(obj: Any, key: str = "") -> Iterator[tuple[str, Any]]:
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _walk(v, str(k))
    elif isinstance(obj, list):
        for v in obj:
            yield from _walk(v, key)
    else:
        yield key, obj


def _check_target(target: str) -> bool:
    """Whether ``target`` names a PyTorch operator (``torch.ops.<namespace>.<op>[.<overload>]``) or one of the few
    Python builtins the verifier allows."""
    parts = target.split(".")
    if any(not _SEGMENT.fullmatch(p) or p.startswith("__") for p in parts):
        return False
    if parts[0] == "_operator":
        return len(parts) == 2 and parts[1] in _OPERATOR_BUILTINS
    if parts[0] == "math":
        return len(parts) == 2 and parts[1] in _MATH_BUILTINS
    return (parts[:2] == ["torch", "ops"] and len(parts) in (4, 5) and parts[2] not in _OPS_ATTRIBUTES
            and not parts[2].startswith("_"))


def _check_expression(expr: str) -> str | None:
    """``None`` if ``expr`` is a plain sympy expression (see the module docstring), else the offending token."""
    try:
        tokens = list(tokenize.generate_tokens(io.StringIO(expr).readline))
    except (tokenize.TokenError, IndentationError, SyntaxError):
        return expr[:40]
    for i, tok in enumerate(tokens):
        if tok.type in (tokenize.NEWLINE, tokenize.NL, tokenize.ENDMARKER):
            continue
        if tok.type == tokenize.NUMBER:
            continue
        if tok.type == tokenize.STRING and _QUOTED_NAME.fullmatch(tok.string):
            continue
        if tok.type == tokenize.OP and tok.string in _SYMPY_OPS:
            continue
        if tok.type == tokenize.NAME:
            after = tokens[i + 1].string if i + 1 < len(tokens) else ""
            if tok.string in _SYMPY_NAMES or _SYMBOL_NAME.fullmatch(tok.string):
                continue
            if after == "=" and tok.string.isidentifier() and tok.string.islower() and not tok.string.startswith("_"):
                continue  # an assumption keyword: positive=True, integer=True, ...
        return tok.string
    return None


def _check_graph(path: Path, name: str, text: bytes) -> None:
    program = _json(path, name, text)
    if not isinstance(program, dict):
        raise _refuse(path, f"{name} is not an exported program")
    guards = program.get("guards_code") or []
    if not isinstance(guards, list):
        raise _refuse(path, f"{name} has guard code that is not a list")
    for guard in guards:
        if not isinstance(guard, str) or not _GUARD.fullmatch(guard):
            raise _refuse(path, f"{name} has guard code {str(guard)[:80]!r} (Python that torch would run) beyond input-size "
                                f"comparisons")
    try:
        _check_walk(path, name, program)
    except RecursionError:  # (json.loads nests no deeper than this walk recurses, but a walk frame is larger)
        raise _refuse(path, f"{name} nests JSON deeper than Python's recursion limit") from None
    graph = program.get("graph_module", {}).get("graph", {}) if isinstance(program.get("graph_module"), dict) else {}
    if isinstance(graph, dict) and graph.get("custom_obj_values"):
        raise _refuse(path, f"{name} holds custom objects")


def _check_walk(path: Path, name: str, program: Any) -> None:
    for key, value in _walk(program):
        if key in ("target", "as_operator") and isinstance(value, str) and not _check_target(value):
            raise _refuse(path, f"{name} calls {value[:80]!r}, which is not a PyTorch operator")
        if key == "expr_str" and isinstance(value, str):
            bad = _check_expression(value)
            if bad is not None:
                raise _refuse(path, f"{name} has a symbolic shape {value[:80]!r} with {bad!r}, which is not plain arithmetic")


def _check_payload_config(path: Path, name: str, text: bytes) -> None:
    config = _json(path, name, text)
    entries = config.get("config") if isinstance(config, dict) else None
    if not isinstance(entries, dict):
        raise _refuse(path, f"{name} is not a payload config")
    for fqn, meta in entries.items():
        if not isinstance(meta, dict) or meta.get("use_pickle") is not False:
            raise _refuse(path, f"{name}: entry {str(fqn)[:60]!r} is pickled")
        if not _PAYLOAD_NAME.fullmatch(str(meta.get("path_name", ""))):
            raise _refuse(path, f"{name}: entry {str(fqn)[:60]!r} points at {str(meta.get('path_name'))[:60]!r}")


def check_pt2_archive(path: str | Path) -> None:
    """Raise ``ValueError`` naming the reason unless ``path`` is a ``.pt2`` archive that holds nothing but what
    :func:`camhealth.export.export_pt2` writes (module docstring). Reads the file; never unpickles or imports."""
    path = Path(path)
    if not zipfile.is_zipfile(path):
        raise ValueError(f"{path} is not a readable torch.export archive (not a zip file)")
    try:
        with zipfile.ZipFile(path) as archive:
            infos = [i for i in archive.infolist() if not i.filename.endswith("/")]
            roots = {i.filename.split("/", 1)[0] for i in infos}
            if len(roots) != 1 or any("/" not in i.filename for i in infos):
                raise _refuse(path, f"entries lie in {len(roots)} top-level folders, not one")
            root = roots.pop() + "/"
            names = [i.filename[len(root):] for i in infos]
            for name in names:
                if ".." in name.split("/") or name.startswith("/"):
                    raise _refuse(path, f"entry {name[:80]!r} leaves the archive")
                if name not in _FIXED and not any(p.fullmatch(name) for p in _ALLOWED):
                    raise _refuse(path, f"entry {name[:80]!r} is none that camhealth.export writes")
            # sizes from the zip directory, before anything is inflated (torch.export.load reads every payload)
            json_entries = {root + n for n in names if n.endswith(".json") or n.startswith("extra/")}
            too_large = zip_size_problem(infos, json_entries)
            if too_large is not None:
                raise _refuse(path, too_large)
            if "archive_format" not in names or archive.read(root + "archive_format").strip() != b"pt2":
                raise _refuse(path, "no archive_format 'pt2' entry")
            import torch

            for name in names:  # only what is inspected is read: not the tensor payloads, not extra/
                if name.startswith("models/"):
                    _check_graph(path, name, archive.read(root + name))
                elif name.endswith("_config.json"):
                    _check_payload_config(path, name, archive.read(root + name))
                elif name.startswith("data/sample_inputs/"):
                    try:
                        torch.load(io.BytesIO(archive.read(root + name)), map_location="cpu", weights_only=True)
                    except Exception:
                        raise _refuse(path, f"{name} holds more than tensors") from None
    except zipfile.BadZipFile as exc:
        raise ValueError(f"{path} is not a readable torch.export archive ({exc})") from None
