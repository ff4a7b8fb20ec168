"""Export a trained estimator: ``python -m camhealth.export CKPT --format {weights,pt2,onnx} [--out PATH]``.

Formats (every file carries the same JSON description: kind, patch size, metadata set, architecture
arguments, params, FLOPs, metrics, the test data they were measured on (``evaluation``: the datamodule and the
precision of the fit's test, which ``python -m camhealth.model_card WEIGHTS --verify`` runs again) and, for an MTF
model, its error table ``mtf_error`` — read back by :func:`camhealth.load_estimator`; exporting a file again keeps
its metrics, evaluation and error table):

- ``weights`` (``.pt``): the state dict plus the description, a file that :func:`torch.load` opens with
  ``weights_only=True`` (tensors and plain containers only, no pickled code). The shipped models are these.
- ``pt2``: :func:`torch.export.export` of the bare network with a dynamic batch dimension, saved with
  :func:`torch.export.save` (description in the archive's ``extra_files``).
- ``onnx``: :func:`torch.onnx.export` (dynamo exporter), dynamic batch, description in the model's
  ``metadata_props``; runs with ONNX Runtime alone. MTF and DRNE: the bare network, input ``patch``
  (B×1×P×P in [0, 1]), output ``mtf`` (B, 16) or ``sigma_map`` (B×1×P×P, DN). Noise-source networks
  (``noise_source_min``, ``noise_source_none``) are **self-contained** (:class:`SelfContainedNoiseSource`):

  ========================  ==========  ========================================================================
  name                      shape       meaning
  ========================  ==========  ========================================================================
  in ``patch``              B×1×P×P     gray patch in [0, 1] (= DN/255), float32
  in ``metadata``           (B, k)      raw metadata in physical units, the columns of ``metadata_fields`` in the
                                        description (``minimal``: gain [dB], exposure [s], temperature [°C]);
                                        absent for ``metadata_set = none``
  out ``sigma``             (B, 3)      σ of PN, DCSN, RN [DN], ≥ 0
  out ``xi``                (B,)        ξ [DN]
  out ``sigma_total``       (B,)        √(Σ σ_s²) [DN]
  out ``assessable``        (B,)        bool
  out ``reason_code``       (B,)        int64: 0 assessable, 1 black, 2 saturated, 3 metadata outside
                                        ``METADATA_RANGES`` (or not finite), 4 noise beyond the validated range,
                                        5 less noise than any camera state in the metadata's ranges makes,
                                        6 clipped (black and saturated pixels together more than half,
                                        neither alone; 4 where the noise beyond the range clipped them)
  ========================  ==========  ========================================================================

  The metadata normalisation (``CameraMetadata.normalize``), the clamp of σ at 0, the total and the flags of
  :func:`camhealth._inputs.assess_patches` are inside the graph, so ONNX Runtime alone gives what
  :meth:`Estimator.predict` gives (within 1e-3 DN). The graph cannot raise: metadata that ``predict`` refuses give
  ``assessable = False``, ``reason_code = 3``. ``noise_source_full`` (the physics-first estimator, no network)
  is not exported: its two-pass inlier selection, per-intensity binning of Haar details and posterior over
  hypothesis grids with data-dependent branches are Python control flow, not a fixed graph.

The ``pt2`` program takes exactly the inputs of :meth:`EstimatorModule.export_inputs` (for the noise-source
network: patches and normalised metadata, which the loader computes from raw metadata with
:mod:`camhealth.physics`). TorchScript is not offered (deprecated).

A weights file or checkpoint is read back two ways: :func:`load_net` builds the bare network
(:mod:`camhealth.nets`, a plain ``torch.nn.Module``; inference, no Lightning import) and :func:`load_module` the
LightningModule that trained it (exporting to pt2/ONNX, fine-tuning). Both check the file the same way.

Noise-source files written with options that are retired (a Full-Meta hybrid network, a posterior blend, …) are
refused at load with a message that names the option and what replaced it (:func:`check_retired`).

Every file's description is checked field by field at load (:func:`_check_description`): its format ``version`` must
be :data:`FORMAT_VERSION` (a file without one is read as that version), ``metrics`` a JSON object of numbers or null,
``evaluation`` one of :data:`EVALUATION_DATAMODULES` with JSON arguments and a precision of
:data:`EVALUATION_PRECISIONS` (:func:`check_evaluation`: a file names no other class to import), ``params`` and ``flops_per_patch`` non-negative integers. A weights file or checkpoint is a zip archive whose entries'
declared sizes are checked before ``torch.load`` inflates anything (:func:`camhealth._pt2_check.zip_size_problem`), and
weights that are not finite in the network's float32 (a float64 value beyond its range) are refused at load.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import warnings
from pathlib import Path
from typing import Any, Mapping, Sequence

import torch

from camhealth._cli import add_debug_flag, config_parser, debugging, run_cli
from camhealth.nets import NETWORKS, check_patch_size, network_for

__all__ = ["CARRIED", "EVALUATION_DATAMODULES", "EVALUATION_PRECISIONS", "FORMAT_TAG", "check_evaluation", "set_description_entries", "SelfContainedNoiseSource", "ONNX_NOISE_OUTPUTS", "ONNX_REASONS", "export_weights", "export_pt2",
           "export_onnx", "load_net", "load_module", "main", "ALLOWED_CLASSES", "check_retired", "network_metadata_set"]

FORMAT_TAG = "camhealth-estimator"
#: The format version of the files camhealth writes and the only one it reads (description ``version``, and the weights
#: file's top-level ``version``).
FORMAT_VERSION = 1

#: Classes a camhealth file may name → their kind (nothing else is ever instantiated from a file): the LightningModules
#: of :data:`camhealth.nets.NETWORKS`.
ALLOWED_CLASSES: dict[str, str] = {spec.class_path: kind for kind, spec in NETWORKS.items()}


BY_PHYSICS = ("replaced by 'noise_source_full', the physics-first estimator (the closed form unless the image "
              "contradicts it; docs/estimators.md): the Full-Meta networks were worse than the closed form on data "
              "camhealth did not make (python -m camhealth.bench robustness)")
#: Retired noise-source network options → the value every file now has (older files that carry it are read as if
#: they did not); another value is refused by :func:`check_retired`.
RETIRED_OPTIONS: dict[str, Any] = {
    "physics_prior": False, "total_branch": False, "branch_inputs": "own", "nlf_statistics": False,
    "trunk_activation": "relu", "prior_clipping": False, "noise_fit_statistics": False, "mismatch_posterior": False,
    "train_only": None, "prior_anchor": "image",
}
BY_JOINT_MTF = ("replaced by the MTF network whose regressors read both directions, trained in one run by "
                "configs/mtf_full.yaml (python -m camhealth.fit --config configs/mtf_full.yaml)")
#: Retired MTF options, dropped when a file is read: ``joint_directions`` (every network now reads both directions;
#: ``False`` is refused by :func:`check_retired`, and a file whose regressor has one direction's inputs by ``_read``)
#: and ``train_only`` (a training-only option).
RETIRED_MTF_OPTIONS: tuple[str, ...] = ("joint_directions", "train_only")


def check_retired(desc: Mapping[str, Any], path: Any) -> None:
    """Refuse a description written with a retired option — a noise-source Full-Meta network or posterior blend, an
    MTF network whose regressors read one direction only — naming the option and what replaced it."""
    args = desc.get("init_args", {}) or {}
    if desc.get("kind") == "mtf":
        if args.get("joint_directions", True) is not True:
            raise ValueError(f"{path}: an MTF network whose regressors read one direction only "
                             f"(joint_directions={args['joint_directions']!r}) is retired: {BY_JOINT_MTF}")
        return
    if desc.get("kind") != "noise_source":
        return
    if args.get("metadata_set") == "full" or args.get("physics_prior"):
        raise ValueError(f"{path}: a Full-Meta noise-source network is retired: {BY_PHYSICS}")
    bad = [f"{k}={v!r}" for k, v in args.items() if k in RETIRED_OPTIONS and v not in (RETIRED_OPTIONS[k], None)]
    if desc.get("inference"):
        bad.append(f"inference settings {sorted(desc['inference'])}")
    if bad:
        raise ValueError(f"{path}: written with the retired noise-source option(s) {', '.join(bad)}: {BY_PHYSICS}")


def _class_for(class_path: str):
    if class_path not in ALLOWED_CLASSES:
        raise ValueError(f"class {class_path!r} is not a camhealth estimator; allowed: {sorted(ALLOWED_CLASSES)}")
    import importlib

    module, name = class_path.rsplit(".", 1)
    return getattr(importlib.import_module(module), name)


def _load_refusal(exc: BaseException) -> str:
    """Why ``torch.load(weights_only=True)`` refused a file, in words that do not advise loading it unsafely."""
    text = str(exc)
    blocked = re.search(r"(unsupported GLOBAL [^\s]+|Unsupported global: GLOBAL [^\s]+)", text)
    if blocked:
        return f"it holds pickled Python objects other than tensors, {blocked.group(1)}; camhealth never unpickles those"
    detail = re.search(r"(Unsupported operand [^\s]+)", text)
    lines = [ln.strip() for ln in text.splitlines() if ln.strip() and "weights_only" not in ln and "PyTorch 2.6" not in ln]
    why = detail.group(1) if detail else (_first_sentence(lines[0]) if lines else type(exc).__name__)
    return f"torch's tensors-only reader stopped: {why}"


def _first_sentence(text: str, limit: int = 200) -> str:
    """The first sentence of an error message (torch's run on with advice), at most ``limit`` characters, cut at a word."""
    head = re.split(r"(?<=[.!?])\s", text, maxsplit=1)[0].rstrip(".")
    return head if len(head) <= limit else head[:limit].rsplit(" ", 1)[0] + " …"


#: Suffixes of files that :func:`_safe_load` refuses by name, and why.
_NOT_WEIGHTS = {
    ".pt2": "an exported program (python -m camhealth.export --format pt2)",
    ".onnx": "an ONNX export (python -m camhealth.export --format onnx)",
}


def _safe_load(path: Path) -> dict:
    if path.is_dir():
        raise ValueError(f"{path} is a folder; name a checkpoint (.ckpt) or weights file (.pt) in it")
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    suffix = path.suffix.lower()
    if suffix in _NOT_WEIGHTS:
        raise ValueError(f"{path} is {_NOT_WEIGHTS[suffix]}, not a weights file or checkpoint: exports cannot be exported "
                         f"or rewritten again; give the weights file (.pt) or checkpoint (.ckpt) it was exported from "
                         f"(camhealth.load_estimator reads the {suffix} file itself)")
    if suffix == ".safetensors":
        raise ValueError(f"{path}: camhealth does not read .safetensors files; its estimators are weights files (.pt, "
                         f"python -m camhealth.export --format weights), checkpoints (.ckpt), .pt2 or .onnx exports")
    with path.open("rb") as f:
        head = f.read(8)
    if head.startswith(b"PK"):  # torch.save's zip archive: its directory checked before torch inflates anything
        _check_zip(path)
    try:
        with warnings.catch_warnings():  # (torch's note on a pickle protocol precedes the refusal that follows)
            warnings.filterwarnings("ignore", message=r".*pickle protocol", category=UserWarning)
            obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # pickle with code, not a torch file, truncated file, ...
        why = (_load_refusal(exc) if head.startswith((b"PK\x03\x04", b"\x80")) or not head
               else f"it is no torch file: neither a zip archive nor a pickle, it begins with {head!r}")
        raise ValueError(f"{path} is not a camhealth checkpoint or weights file that loads as plain tensors ({why})") from None
    if not isinstance(obj, dict):
        raise ValueError(f"{path} is not a camhealth checkpoint: it holds a {type(obj).__name__}, not a dict")
    return obj


def _check_zip(path: Path) -> None:
    """Refuse a zip archive that is truncated or corrupt, that declares more uncompressed data than a camhealth network
    needs (:func:`camhealth._pt2_check.zip_size_problem`: a decompression bomb is refused before it is inflated), or
    that is a ``torch.export`` archive (``.pt2``) under another name."""
    import zipfile

    from camhealth._pt2_check import zip_size_problem

    try:
        with zipfile.ZipFile(path) as archive:
            infos = archive.infolist()
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, ValueError, NotImplementedError) as exc:
        raise ValueError(f"{path} is truncated or corrupt: it begins as a zip archive, as torch.save writes, but its zip "
                         f"directory cannot be read ({exc}); copy or save the file again") from None
    too_large = zip_size_problem(infos)
    if too_large is not None:
        raise ValueError(f"{path}: refused to load this file: {too_large}")
    names = {i.filename.split("/", 1)[-1] for i in infos}
    if "archive_format" in names and "data.pkl" not in names:
        raise ValueError(f"{path} is a torch.export archive (.pt2), not a weights file or checkpoint: give the weights "
                         f"file (.pt) or checkpoint (.ckpt) it was exported from, or load it under its .pt2 name")


def parse_description(text: str, path: Path, label: str) -> Any:
    """The JSON ``text`` of a file's description (``label``: what it is, e.g. "the weights file's description"), or one
    ``ValueError`` naming the file: not JSON, nested deeper than Python's recursion limit, or holding a number Python
    does not read (an integer beyond ``sys.get_int_max_str_digits()`` digits)."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: {label} is not valid JSON ({exc.msg} at character {exc.pos})") from None
    except RecursionError:
        raise ValueError(f"{path}: {label} nests JSON deeper than Python's recursion limit "
                         f"({sys.getrecursionlimit()}); a camhealth description is a flat object") from None
    except ValueError as exc:  # e.g. "Exceeds the limit (4300 digits) for integer string conversion"
        raise ValueError(f"{path}: {label} cannot be read: {_first_sentence(str(exc).split(':')[0], 120)}; a camhealth "
                         f"description holds no such value") from None


def _description_and_state(obj: Mapping[str, Any], path: Path) -> tuple[dict, dict]:
    """Description + state dict of the network from a camhealth weights file or a Lightning checkpoint."""
    if obj.get("format") == FORMAT_TAG:  # weights file
        text = obj.get("description")
        if not isinstance(text, str):
            raise ValueError(f"{path}: the weights file's 'description' must be a JSON string, got {type(text).__name__}")
        desc = _check_description(parse_description(text, path, "the weights file's description"), path)
        if "version" in obj and _version_problem(obj["version"]):
            raise ValueError(f"{path}: the weights file's version = {obj['version']!r} {_version_problem(obj['version'])}")
        state = obj.get("state_dict")
        if not isinstance(state, Mapping):
            raise ValueError(f"{path}: the weights file has no 'state_dict' of tensors")
        return desc, dict(state)
    info = obj.get("camhealth")
    if isinstance(info, Mapping) and info.get("format") == FORMAT_TAG and "state_dict" in obj:
        if not isinstance(obj["state_dict"], Mapping):
            raise ValueError(f"{path}: the checkpoint's 'state_dict' is not a mapping of tensors")
        state = {k[len("net."):]: v for k, v in obj["state_dict"].items() if str(k).startswith("net.")}
        return _check_description(dict(info), path), state
    raise ValueError(
        f"{path} is not a camhealth checkpoint: expected a weights file (format {FORMAT_TAG!r}) or a Lightning "
        f"checkpoint written by a camhealth estimator (key 'camhealth'), found keys {sorted(map(str, obj))[:8]}"
    )


def _version_problem(version: Any) -> str:
    """Why ``version`` is not one this camhealth reads, or ``""``."""
    if isinstance(version, bool) or not isinstance(version, int) or version != FORMAT_VERSION:
        return (f"is not a format version this camhealth reads (only {FORMAT_VERSION}); export the network again with "
                f"this camhealth, or load it with the camhealth that wrote it")
    return ""


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _check_description(desc: Any, path: Path) -> dict:
    """The description of a file, checked field by field (one ``ValueError`` naming the field and what it must be)."""
    if not isinstance(desc, dict):
        raise ValueError(f"{path}: the description must be a JSON object, got {type(desc).__name__}")
    if "version" in desc and _version_problem(desc["version"]):
        raise ValueError(f"{path}: description version = {desc['version']!r} {_version_problem(desc['version'])}")
    class_path = desc.get("class_path")
    if class_path not in ALLOWED_CLASSES:
        raise ValueError(f"{path}: description class_path = {class_path!r} is not a camhealth estimator; allowed: {sorted(ALLOWED_CLASSES)}")
    if desc.get("kind") != ALLOWED_CLASSES[class_path]:
        raise ValueError(f"{path}: description kind = {desc.get('kind')!r} must be {ALLOWED_CLASSES[class_path]!r} for {class_path}")
    init_args = desc.get("init_args", {})
    if not isinstance(init_args, dict):
        raise ValueError(f"{path}: description init_args must be a JSON object, got {type(init_args).__name__}")
    size = desc.get("patch_size")
    if isinstance(size, bool) or not isinstance(size, int) or size < 1:
        raise ValueError(f"{path}: description patch_size = {size!r} must be a positive integer (px)")
    try:
        check_patch_size(size)
    except ValueError as exc:
        raise ValueError(f"{path}: description {exc}") from None
    if "patch_size" in init_args and init_args["patch_size"] != size:
        raise ValueError(f"{path}: description patch_size = {size!r} differs from init_args patch_size = {init_args['patch_size']!r}")
    if desc.get("metadata_set", "none") not in ("none", "minimal", "full"):
        raise ValueError(f"{path}: description metadata_set = {desc.get('metadata_set')!r} must be 'none', 'minimal' or 'full'")
    check_retired(desc, path)  # (a retired network is named as such, not as an inconsistent description)
    network_set = network_metadata_set(desc["kind"], init_args)
    if "metadata_set" in desc and desc["metadata_set"] != network_set:
        raise ValueError(f"{path}: description metadata_set = {desc['metadata_set']!r} differs from the network's "
                         f"init_args metadata_set = {network_set!r}")
    metrics = desc.get("metrics")
    if metrics is not None:
        if not isinstance(metrics, dict):
            raise ValueError(f"{path}: description metrics must be a JSON object of numbers or null (a metric without "
                             f"data), got {type(metrics).__name__}")
        for key, value in metrics.items():  # NaN: an older file's metric without data, read as null
            if value is not None and not (_is_number(value) and (math.isfinite(value) or value != value)):
                raise ValueError(f"{path}: description metrics[{str(key)[:60]!r}] = {repr(value)[:60]} must be a finite "
                                 f"number or null (a metric without data)")
    for key in ("params", "flops_per_patch"):
        value = desc.get(key)
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 0):
            raise ValueError(f"{path}: description {key} = {repr(value)[:60]} must be a non-negative integer")
    return desc


def network_metadata_set(kind: str, init_args: Mapping[str, Any]) -> Any:
    """The metadata a file's network reads: a noise-source network's ``init_args`` ``metadata_set`` (the network's
    default where the file does not give it), ``"none"`` for the other kinds."""
    if kind != "noise_source":
        return "none"
    import inspect

    default = inspect.signature(NETWORKS["noise_source"].network.__init__).parameters["metadata_set"].default
    return init_args.get("metadata_set", default)


#: dtypes a weights file's tensors may have: floats for weights, integers and bool for buffers (batch-norm counts).
_STATE_DTYPES = (torch.float16, torch.bfloat16, torch.float32, torch.float64, torch.int8, torch.uint8, torch.int16,
                 torch.int32, torch.int64, torch.bool)


def _read(source: str | Path) -> tuple[Path, dict, dict, dict]:
    """Path, checked description, init_args (retired options at their only value dropped) and state dict of a file."""
    path = Path(source)
    desc, state = _description_and_state(_safe_load(path), path)
    check_retired(desc, path)
    init_args = {k: v for k, v in dict(desc.get("init_args", {})).items() if not str(k).startswith("_")}
    retired = {"noise_source": RETIRED_OPTIONS, "mtf": RETIRED_MTF_OPTIONS}.get(str(desc.get("kind")), {})
    init_args = {k: v for k, v in init_args.items() if k not in retired}  # at their only remaining value: as if absent
    init_args.setdefault("patch_size", desc["patch_size"])  # both loaders build for the description's patch size
    try:
        network_for(desc["class_path"]).check_training_args(init_args)
    except ValueError as exc:
        raise ValueError(f"{path}: description init_args: {exc}") from None
    if desc.get("evaluation") is not None:
        check_evaluation(desc["evaluation"], f"{path}: description evaluation")
    if desc.get("kind") == "mtf" and desc.get("mtf_error") is not None:
        from camhealth.estimators.mtf_error import MTFErrorTable

        MTFErrorTable.from_dict(desc["mtf_error"], str(path))
    bad = [k for k, v in state.items() if not isinstance(v, torch.Tensor)]
    if bad:
        raise ValueError(f"{path}: state_dict entries {bad[:4]} are not tensors")
    for key, value in state.items():
        if value.layout != torch.strided or value.device.type != "cpu" or value.dtype not in _STATE_DTYPES:
            raise ValueError(f"{path}: state_dict entry {key!r} is a {value.layout} tensor of dtype {value.dtype} on "
                             f"{value.device.type!r}; weights must be dense CPU tensors of dtype "
                             f"{', '.join(str(d).replace('torch.', '') for d in _STATE_DTYPES)}")
        if (value.is_floating_point() or value.is_complex()) and not bool(torch.isfinite(value).all()):
            n = int((~torch.isfinite(value)).sum())
            raise ValueError(f"{path}: state_dict entry {key!r} holds {n} NaN or infinite value(s) of {value.numel()}; "
                             "weights must be finite")
    head = state.get("head.0.weight")
    if desc.get("kind") == "mtf" and head is not None and head.ndim == 2:
        width = int(list(init_args.get("widths", (32, 64, 96)))[-1])
        if head.shape[1] == 3 * width:  # a regressor that reads its own direction's max/mean/std only
            raise ValueError(f"{path}: an MTF network whose regressors read one direction only (regressor input "
                             f"{head.shape[1]} = 3 × {width} features, not 6 × {width}) is retired: {BY_JOINT_MTF}")
    return path, desc, init_args, state


def _check_state(expected: Mapping[str, torch.Tensor], state: Mapping[str, torch.Tensor], path: Path, class_path: str) -> None:
    """Compare a file's ``state`` with the state dict the network would have (``expected``: shapes and dtypes only,
    e.g. of a network on the meta device): a missing or unexpected entry, a tensor of another shape, or one of
    another kind than the network's (integer, bool or complex values for a floating-point parameter or buffer) is a
    ``ValueError`` naming the entry."""
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    if missing or unexpected:
        raise ValueError(f"{path}: weights do not fit {class_path} (missing {missing[:4]}, unexpected {unexpected[:4]})")
    for key, want in expected.items():
        value = state[key]
        if tuple(value.shape) != tuple(want.shape):
            raise ValueError(f"{path}: weights do not fit {class_path}: state_dict entry {key!r} has shape "
                             f"{tuple(value.shape)}, the network described by the file has {tuple(want.shape)}")
        if want.is_floating_point() and not value.is_floating_point():
            raise ValueError(f"{path}: state_dict entry {key!r} is a {value.dtype} tensor; {class_path} holds "
                             f"{want.dtype} values there (a floating-point tensor is needed)")


def _checked_network(path: Path, desc: Mapping[str, Any], init_args: Mapping[str, Any], state: Mapping[str, torch.Tensor]):
    """The network a file describes, built on the meta device (no memory, however large its arguments say it is)
    and compared with the file's tensors (:func:`_check_state`) — before anything is allocated for it."""
    class_path = desc["class_path"]
    spec = network_for(class_path)
    unknown = sorted(k for k in init_args if k not in spec.init_args)
    if unknown:
        raise ValueError(f"{path}: description init_args {unknown} are not arguments of {class_path}")
    try:
        with torch.device("meta"):
            net = spec.build(init_args)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"{path}: description init_args do not build {class_path}: {str(exc).splitlines()[0][:200]}") from None
    _check_state(net.state_dict(), state, path, class_path)
    return net


def _load_state(net: torch.nn.Module, state: Mapping[str, torch.Tensor], path: Path, class_path: str) -> None:
    """Load ``state`` into ``net`` (checked by :func:`_check_state` first; the values are copied into the network's
    tensors, in their dtype). A value finite in the file but not in the network's dtype (float64 beyond float32's
    range becomes ±inf) is a ``ValueError`` naming the entry: the network would answer every input with NaN."""
    _check_state(net.state_dict(), state, path, class_path)
    try:
        net.load_state_dict(state)
    except RuntimeError as exc:
        raise ValueError(f"{path}: weights do not fit {class_path}: {str(exc).splitlines()[-1].strip()[:200]}") from None
    for key, value in net.state_dict().items():
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            n = int((~torch.isfinite(value)).sum())
            stored = str(state[key].dtype).replace("torch.", "") if key in state else "?"
            dtype = str(value.dtype).replace("torch.", "")
            raise ValueError(f"{path}: state_dict entry {key!r} holds {n} non-finite value(s) of {value.numel()} after "
                             f"conversion to {dtype} (the file's {stored} values lie beyond {dtype}'s range); weights "
                             f"must be finite in the network's dtype")


def load_net(source: str | Path) -> tuple[torch.nn.Module, dict]:
    """The bare network of a weights file or Lightning checkpoint (a :mod:`camhealth.nets` module, eval mode, float32)
    and the file's description, without importing Lightning or the LightningModule. Only allow-listed classes are
    built and only tensors are loaded; a tampered description (bad JSON, an argument the LightningModule does not take,
    a value the network or the LightningModule refuses) is one ``ValueError`` naming the file. The network is built on
    the meta device and its shapes compared with the file's tensors before any memory is allocated for it."""
    path, desc, init_args, state = _read(source)
    net = _checked_network(path, desc, init_args, state)
    net = net.to_empty(device="cpu")  # (uninitialised: every tensor is loaded next)
    _load_state(net, state, path, desc["class_path"])
    return net.eval(), desc


def load_module(source: str | Path):
    """Rebuild the :class:`EstimatorModule` (a LightningModule: imports Lightning) of a weights file or Lightning
    checkpoint (eval mode), plus its description — for exporting and fine-tuning; inference uses :func:`load_net`.
    Only allow-listed classes are built and only tensors are loaded; a tampered description (bad JSON, an argument
    the class does not take, a value it refuses) is one ``ValueError`` naming the file. The file is checked as
    :func:`load_net` checks it (its network built on the meta device and compared with its tensors) before the
    LightningModule is built."""
    path, desc, init_args, state = _read(source)
    _checked_network(path, desc, init_args, state)
    cls = _class_for(desc.get("class_path", ""))
    import inspect

    accepted = inspect.signature(cls.__init__).parameters
    unknown = sorted(k for k in init_args if k not in accepted)
    if unknown and not any(a.kind is inspect.Parameter.VAR_KEYWORD for a in accepted.values()):
        raise ValueError(f"{path}: description init_args {unknown} are not arguments of {desc['class_path']}")
    try:
        module = cls(**init_args)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"{path}: description init_args do not build {desc['class_path']}: {str(exc).splitlines()[0][:200]}") from None
    _load_state(module.net, state, path, desc["class_path"])
    return module.eval(), desc


#: Description entries a file carries over when it is exported again (measured on the trained network, not
#: derived from the module): the MTF error table of :mod:`camhealth.estimators.mtf_error` and the test data of its
#: ``metrics`` (:func:`check_evaluation`).
CARRIED = ("mtf_error", "evaluation")

#: The datamodules a file's ``evaluation`` may name (``class_path``): the only classes built from a file's
#: description, so a file cannot make the verifier import anything else.
EVALUATION_DATAMODULES = ("datamodules.NoiseDataModule", "datamodules.BlurDataModule")
#: Lightning precisions a file's ``evaluation`` may name.
EVALUATION_PRECISIONS = ("32-true", "32", "bf16-mixed", "bf16-true", "bf16", "16-mixed", "16-true", "16", "64-true", "64")


def check_evaluation(entry: Any, where: str = "evaluation") -> dict:
    """Check a description's ``evaluation`` — ``{"data": {"class_path": one of EVALUATION_DATAMODULES,
    "init_args": {...}}, "precision": one of EVALUATION_PRECISIONS}`` and, where the fit's test read part of the
    split, ``"limit_test_batches"`` (Lightning's: batches ≥ 1 or a fraction in (0, 1]) — the test data the file's
    ``metrics`` were measured on — and return it; a ``ValueError`` names the field, its value and what is allowed."""
    if not isinstance(entry, Mapping):
        raise ValueError(f"{where} must be a JSON object with 'data' and 'precision', got {type(entry).__name__}")
    extra = sorted(set(map(str, entry)) - {"data", "precision", "limit_test_batches"})
    if extra:
        raise ValueError(f"{where} has unknown keys {extra[:4]}; allowed: ['data', 'precision', 'limit_test_batches']")
    limit = entry.get("limit_test_batches", 1.0)
    if isinstance(limit, bool) or not (isinstance(limit, int) and limit >= 1 or isinstance(limit, float) and 0 < limit <= 1):
        raise ValueError(f"{where} limit_test_batches = {repr(limit)[:40]} must be a whole number of batches ≥ 1 or a "
                         f"fraction in (0, 1]")
    data = entry.get("data")
    if not isinstance(data, Mapping) or set(map(str, data)) != {"class_path", "init_args"}:
        raise ValueError(f"{where} data must be a JSON object with exactly 'class_path' and 'init_args', got "
                         f"{repr(data)[:80]}")
    if data["class_path"] not in EVALUATION_DATAMODULES:
        raise ValueError(f"{where} data class_path = {repr(data['class_path'])[:80]} must be one of "
                         f"{list(EVALUATION_DATAMODULES)}")
    if not isinstance(data["init_args"], Mapping) or not all(isinstance(k, str) for k in data["init_args"]):
        raise ValueError(f"{where} data init_args must be a JSON object with string keys, got "
                         f"{repr(data['init_args'])[:80]}")
    if entry.get("precision") not in EVALUATION_PRECISIONS:
        raise ValueError(f"{where} precision = {repr(entry.get('precision'))[:40]} must be one of "
                         f"{list(EVALUATION_PRECISIONS)}")
    return dict(entry)


def _description(module, metrics: Mapping[str, float] | None, carried: Mapping[str, Any] | None = None) -> dict:
    desc = module.describe()
    desc.update({k: v for k, v in (carried or {}).items() if k in CARRIED})
    desc["format"] = FORMAT_TAG
    desc["version"] = FORMAT_VERSION
    desc["init_args"] = json.loads(json.dumps(desc["init_args"], default=list))
    if metrics:  # a metric without data (None, NaN: a blur family with no test sample) is null
        desc["metrics"] = {k: None if v is None or float(v) != float(v) else float(v) for k, v in metrics.items()}
    return desc


def _module_and_metrics(source, metrics):
    """(module, metrics, carried description entries) of an EstimatorModule or a file."""
    if isinstance(source, (str, Path)):
        module, desc = load_module(source)
        return module, metrics if metrics is not None else desc.get("metrics"), {k: desc[k] for k in CARRIED if k in desc}
    return source.eval(), metrics, {}


def export_weights(source, out: str | Path, metrics: Mapping[str, float] | None = None,
                   evaluation: Mapping[str, Any] | None = None) -> Path:
    """Write ``source`` (an EstimatorModule, a checkpoint or weights path) as a camhealth weights file; ``evaluation``
    (:func:`check_evaluation`) names the test data of ``metrics``."""
    module, metrics, carried = _module_and_metrics(source, metrics)
    if evaluation is not None:
        carried = {**carried, "evaluation": check_evaluation(json.loads(json.dumps(evaluation)))}
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in module.net.state_dict().items()}
    payload = {"format": FORMAT_TAG, "version": FORMAT_VERSION, "description": json.dumps(_description(module, metrics, carried)), "state_dict": state}
    torch.save(payload, out)
    return out


def set_description_entries(source: str | Path, entries: Mapping[str, Any], out: str | Path | None = None) -> Path:
    """Rewrite the weights file ``source`` (to ``out``; default in place) with the description ``entries`` set — only
    the keys of :data:`CARRIED`, JSON-serialisable — and its tensors unchanged."""
    path = Path(source)
    bad = sorted(set(map(str, entries)) - set(CARRIED))
    if bad:
        raise ValueError(f"description entries {bad} cannot be set; allowed: {list(CARRIED)}")
    obj = _safe_load(path)
    if obj.get("format") != FORMAT_TAG:
        raise ValueError(f"{path} is not a camhealth weights file (format {FORMAT_TAG!r}); export it first")
    desc, state = _description_and_state(obj, path)
    entries = json.loads(json.dumps(dict(entries)))
    if entries.get("evaluation") is not None:
        check_evaluation(entries["evaluation"], "description evaluation")
    desc.update(entries)
    payload = {"format": FORMAT_TAG, "version": obj.get("version", FORMAT_VERSION), "description": json.dumps(desc),
               "state_dict": state}
    out = Path(out) if out is not None else path
    torch.save(payload, out)
    return out


#: Largest batch an exported ``.pt2``/``.onnx`` program is exported for (the dynamic batch dimension's upper bound;
#: a ``.pt2`` program's guard refuses more, so :meth:`camhealth.inference.Estimator.predict` runs it in chunks of at
#: most this many patches).
MAX_EXPORT_BATCH = 4096


def _dynamic_batch(inputs: Sequence[torch.Tensor]):
    batch = torch.export.Dim("batch", min=1, max=MAX_EXPORT_BATCH)
    return tuple({0: batch} for _ in inputs)


def export_pt2(source, out: str | Path, metrics: Mapping[str, float] | None = None) -> Path:
    """torch.export the bare network (dynamic batch) to a ``.pt2`` archive with the description."""
    module, metrics, carried = _module_and_metrics(source, metrics)
    inputs = module.export_inputs(2)
    net = module.export_module()
    ep = torch.export.export(net, inputs, dynamic_shapes=_dynamic_batch(inputs))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    torch.export.save(ep, out, extra_files={"camhealth.json": json.dumps(_description(module, metrics, carried))})
    return out


#: Outputs of a self-contained noise-source ONNX graph, in order.
ONNX_NOISE_OUTPUTS: tuple[str, ...] = ("sigma", "xi", "sigma_total", "assessable", "reason_code")
#: ``reason_code`` of a self-contained noise-source ONNX graph → the ``reason`` of :meth:`Estimator.predict`
#: (3: metadata that ``predict`` would refuse with an error).
ONNX_REASONS: tuple[str, ...] = ("", "black", "saturated", "metadata out of range", "noise beyond validated range",
                                 "less noise than the metadata allow", "clipped")


class SelfContainedNoiseSource(torch.nn.Module):
    """A noise-source network with everything :meth:`Estimator.predict` does around it, as one graph.

    ``forward(patch, metadata)`` → ``(sigma, xi, sigma_total, assessable, reason_code)`` (see the module
    docstring for shapes and units): metadata in physical units (the ``metadata_fields`` columns) are normalised
    with ``METADATA_RANGES`` into the (B, 11) vector the network reads (zeros where the metadata set has no field),
    σ is clamped at 0, σ_total = √(Σ σ_s²), and a patch is not assessable where more than
    ``MAX_CLIPPED_FRACTION`` of its pixels lie within 0.5 DN of 0 (black, code 1) or of 255 (saturated, 2) or, neither
    alone, of either together (clipped, 6, unless the noise is beyond the validated range, 4, which clipped it:
    :func:`camhealth._inputs.assess_patches`), its metadata lie outside their range or are not finite (3), its finest-scale fluctuations exceed the validated σ
    beyond doubt (4, :func:`~camhealth.estimators.physics_noise.beyond_validated_range`) or it holds far less noise
    than any camera state makes (5, :func:`~camhealth.estimators.physics_noise.quieter_than_any_camera`).

    Args:
        net: the bare :class:`~lightning_modules.noise_source.NoiseSourceNet` (eval mode).
        metadata_set: ``"none"`` or ``"minimal"``: which raw fields ``metadata`` holds.
    """

    def __init__(self, net: torch.nn.Module, metadata_set: str) -> None:
        super().__init__()
        from camhealth.physics.metadata import FULL_FIELDS, METADATA_RANGES, METADATA_SETS

        if metadata_set not in ("none", "minimal"):
            raise ValueError(f"metadata_set = {metadata_set!r} must be 'none' or 'minimal' (noise-source networks)")
        self.net = net
        self.fields: tuple[str, ...] = METADATA_SETS[metadata_set]
        k = len(self.fields)
        low = torch.tensor([METADATA_RANGES[f][0] for f in self.fields], dtype=torch.float64)
        high = torch.tensor([METADATA_RANGES[f][1] for f in self.fields], dtype=torch.float64)
        select = torch.zeros(k, len(FULL_FIELDS), dtype=torch.float64)  # raw column j → column of FULL_FIELDS
        for j, f in enumerate(self.fields):
            select[j, FULL_FIELDS.index(f)] = 1.0
        self.register_buffer("low", low.float(), persistent=False)
        self.register_buffer("high", high.float(), persistent=False)
        self.register_buffer("select", select.float(), persistent=False)
        self.n_full = len(FULL_FIELDS)

    def forward(self, patch: torch.Tensor, metadata: torch.Tensor | None = None):
        from camhealth._inputs import MAX_CLIPPED_FRACTION

        x = patch.float()
        b = x.shape[0]
        if self.fields:
            if metadata is None:
                raise ValueError(f"this network reads metadata {list(self.fields)}; pass metadata (B, {len(self.fields)})")
            raw = metadata.float()
            norm = ((raw - self.low) / (self.high - self.low)) @ self.select
            meta_ok = ((raw >= self.low) & (raw <= self.high)).all(1)  # NaN compares False → out of range
        else:
            norm = x.new_zeros(b, self.n_full)
            meta_ok = x.new_ones(b, dtype=torch.bool)
        out = self.net(x, norm).float()
        sigma = out[:, :3].clamp_min(0.0)
        xi = out[:, 3]
        total = sigma.pow(2).sum(1).sqrt()
        flat = x.flatten(1)
        tol = 0.5 / 255.0
        at_low, at_high = flat <= tol, flat >= 1.0 - tol
        black = at_low.float().mean(1) > MAX_CLIPPED_FRACTION
        saturated = at_high.float().mean(1) > MAX_CLIPPED_FRACTION
        clipped = (at_low | at_high).float().mean(1) > MAX_CLIPPED_FRACTION
        zero = torch.zeros_like(black, dtype=torch.int64)
        from camhealth.estimators.physics_noise import beyond_validated_range, quieter_than_any_camera

        beyond = beyond_validated_range(x).to(black.device)  # the refusals predict adds for the networks
        quiet = quieter_than_any_camera(x).to(black.device)
        clipped = clipped & ~beyond  # clipped by noise beyond the validated range: that reason (assess_patches)
        reason = torch.where(black, zero + 1, torch.where(saturated, zero + 2, torch.where(clipped, zero + 6, torch.where(
            ~meta_ok, zero + 3, torch.where(beyond, zero + 4, torch.where(quiet, zero + 5, zero))))))
        return sigma, xi, total, reason == 0, reason


def _onnx_graph(module) -> tuple[torch.nn.Module, tuple[torch.Tensor, ...], list[str], list[str], dict]:
    """The module exported to ONNX, example inputs, input and output names, and what the description says of them."""
    kind = getattr(module, "kind", "")
    patch = module.export_inputs(2)[0]
    if kind != "noise_source":
        output = {"mtf": "mtf", "drne": "sigma_map"}.get(kind, "output")
        return module.export_module(), (patch,), ["patch"], [output], {"inputs": ["patch"], "outputs": [output]}
    from camhealth.physics.metadata import CameraMetadata

    wrapper = SelfContainedNoiseSource(module.export_module(), module.metadata_set).eval()
    inputs: tuple[torch.Tensor, ...] = (patch,)
    names = ["patch"]
    if wrapper.fields:
        preset = CameraMetadata.preset("ICX285", batch_size=patch.shape[0])
        inputs += (torch.stack([getattr(preset, f).float() for f in wrapper.fields], dim=1),)
        names.append("metadata")
    graph = {"inputs": names, "outputs": list(ONNX_NOISE_OUTPUTS), "self_contained": True,
             "metadata_fields": list(wrapper.fields), "reasons": list(ONNX_REASONS)}
    return wrapper, inputs, names, list(ONNX_NOISE_OUTPUTS), graph


def export_onnx(source, out: str | Path, metrics: Mapping[str, float] | None = None) -> Path:
    """ONNX export (dynamo exporter, dynamic batch, named inputs and outputs) with the description in
    ``metadata_props`` (its ``onnx_graph`` entry names the inputs and outputs); noise-source networks are exported
    self-contained (:class:`SelfContainedNoiseSource`, module docstring)."""
    import onnx

    module, metrics, carried = _module_and_metrics(source, metrics)
    net, inputs, names, outputs, graph = _onnx_graph(module)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    program = torch.onnx.export(
        net, inputs, dynamo=True, input_names=names, output_names=outputs, dynamic_shapes=_dynamic_batch(inputs),
        verbose=False,
    )
    program.save(str(out))
    model = onnx.load(str(out))
    desc = _description(module, metrics, carried)
    desc["onnx_graph"] = graph
    entry = model.metadata_props.add()
    entry.key, entry.value = "camhealth.json", json.dumps(desc)
    onnx.save(model, str(out))
    return out


def _unwritable(out: Path) -> str:
    """Why ``out`` cannot be written (creating its folder if needed), or ``""`` — checked before the export runs."""
    import os

    if out.is_dir():
        return "it is a folder"
    blocking = next((a for a in out.parents if a.exists()), None)
    if blocking is not None and not blocking.is_dir():
        return f"{blocking} is a file, not a folder"
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"its folder {out.parent} cannot be created ({exc.strerror or exc})"
    if not os.access(out.parent, os.W_OK) or (out.exists() and not os.access(out, os.W_OK)):
        return "permission denied"
    return ""


EXPORTERS = {"weights": (export_weights, ".pt"), "pt2": (export_pt2, ".pt2"), "onnx": (export_onnx, ".onnx")}


def main(argv: Sequence[str] | None = None) -> Path:
    parser = config_parser(prog="python -m camhealth.export", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", help="Lightning checkpoint (.ckpt) of a camhealth estimator, or a weights file (.pt)")
    parser.add_argument("--format", choices=sorted(EXPORTERS), default="pt2", help="output format (default pt2)")
    parser.add_argument("--out", default=None, help="output path (default: next to the checkpoint, with the format's suffix)")
    add_debug_flag(parser)
    args = parser.parse_args(argv)
    fn, suffix = EXPORTERS[args.format]
    src = Path(args.checkpoint)
    out = Path(args.out) if args.out else src.with_suffix(suffix)
    if out.resolve() == src.resolve():
        parser.error(f"--out {out} would overwrite the input; give another path")
    unwritable = _unwritable(out)
    if unwritable:
        print(f"error: --out {out} cannot be written: {unwritable}", file=sys.stderr)
        raise SystemExit(2)
    try:
        path = fn(src, out)
    except (FileNotFoundError, ValueError) as exc:
        if debugging():
            raise
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    except OSError as exc:
        if debugging():
            raise
        print(f"error: --out {out} cannot be written: {exc.strerror or exc}", file=sys.stderr)
        raise SystemExit(2) from None
    print(path)
    return path


if __name__ == "__main__":  # pragma: no cover
    sys.exit(run_cli(main, "python -m camhealth.export"))
