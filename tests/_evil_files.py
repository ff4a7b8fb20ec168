"""Hostile model files for the loader tests: each one runs code (creates ``marker``) if a loader unpickles,
evaluates or imports what it holds."""

from __future__ import annotations

import io
import json
import pickle
import zipfile
from pathlib import Path

import torch


class Payload:
    """Unpickling this creates the marker file (``open(marker, "w")``)."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _pickled(marker: Path) -> bytes:
    buf = io.BytesIO()
    torch.save({"x": Payload(marker)}, buf)
    return buf.getvalue()


def _rewrite(src: Path, dst: Path, edit) -> Path:
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_STORED) as zout:
        root = zin.namelist()[0].split("/", 1)[0] + "/"
        files = {n[len(root):]: zin.read(n) for n in zin.namelist()}
        files = edit(files)
        for name, data in files.items():
            zout.writestr(root + name, data)
    return dst


def _edit_json(files: dict, name: str, fn) -> dict:
    obj = json.loads(files[name])
    fn(obj)
    files[name] = json.dumps(obj).encode()
    return files


def evil_pt2(src: Path, dst: Path, kind: str, marker: Path) -> Path:
    """A copy of the legitimate archive ``src`` with one hostile change ``kind``."""
    m = str(marker)

    def edit(files: dict) -> dict:
        if kind == "sample_inputs":  # torch retries a failed weights-only load without it
            files["data/sample_inputs/model.pt"] = _pickled(marker)
        elif kind == "pickled_weight":  # use_pickle entries are torch.load-ed with weights_only=False
            def flag(cfg):
                entry = next(iter(cfg["config"].values()))
                entry["use_pickle"] = True
                files["data/weights/" + entry["path_name"]] = _pickled(marker)
            _edit_json(files, "data/weights/model_weights_config.json", flag)
        elif kind == "legacy_weights":  # a legacy weights payload is unpickled
            files["data/weights/model.pt"] = _pickled(marker)
        elif kind == "opaque_constant":  # opaque objects go through pickle.loads
            files["data/constants/opaque_obj_0"] = pickle.dumps(Payload(marker))
            _edit_json(files, "data/constants/model_constants_config.json",
                       lambda cfg: cfg["config"].__setitem__(
                           "c", {"path_name": "opaque_obj_0", "is_param": False, "use_pickle": True, "tensor_meta": None}))
        elif kind == "sympify":  # symbolic shapes are sympy.sympify-ed, which evaluates Python
            def inject(program):
                values = program["graph_module"]["graph"]["sym_int_values"]
                key = next(iter(values))
                values[key]["as_expr"]["expr_str"] = f"__import__('builtins').open({m!r}, 'w') and Symbol('s0')"
            _edit_json(files, "models/model.json", inject)
        elif kind == "guard_code":  # guard code becomes Python source of the loaded module
            _edit_json(files, "models/model.json", lambda p: p.__setitem__("guards_code", [f"open({m!r}, 'w') is None"]))
        elif kind == "target":  # a call target resolved from torch by attribute lookup
            def retarget(program):
                node = program["graph_module"]["graph"]["nodes"][0]
                node["target"] = "torch.os.system"
            _edit_json(files, "models/model.json", retarget)
        else:
            raise ValueError(kind)
        return files

    return _rewrite(src, dst, edit)


PT2_KINDS = ["sample_inputs", "pickled_weight", "legacy_weights", "opaque_constant", "sympify", "guard_code", "target"]


def retargeted_pt2(src: Path, dst: Path, target: str) -> Path:
    """A copy of ``src`` whose first graph node calls ``target``."""

    def edit(files: dict) -> dict:
        def retarget(program):
            program["graph_module"]["graph"]["nodes"][0]["target"] = target
        return _edit_json(files, "models/model.json", retarget)

    return _rewrite(src, dst, edit)


def redescribed(src: Path, edit, out: Path) -> Path:
    """A copy of the weights file ``src`` at ``out`` whose JSON description ``edit`` (a function of the dict) changed
    in place: a tampered file that still holds only tensors."""
    payload = torch.load(src, weights_only=True)
    desc = json.loads(payload["description"])
    edit(desc)
    payload["description"] = json.dumps(desc)
    torch.save(payload, out)
    return out
