"""Files from others: nothing in a model file runs code when camhealth loads it, and a tampered or unreadable file
gets one clear error that names the file and the field (and never advises loading it unsafely)."""

from __future__ import annotations

import json
import pickle

import pytest
import torch

from camhealth.export import export_pt2, export_weights, main as export_main
from camhealth.inference import load_estimator
from lightning_modules import MTFEstimator, NoiseLevelEstimator
from tests._evil_files import PT2_KINDS, Payload, evil_pt2


@pytest.fixture(scope="module")
def mtf_pt2(tmp_path_factory):
    torch.manual_seed(0)
    return export_pt2(MTFEstimator(patch_size=32), tmp_path_factory.mktemp("pt2") / "mtf.pt2")


@pytest.mark.parametrize("kind", PT2_KINDS)
def test_hostile_pt2_is_refused_before_anything_runs(kind, mtf_pt2, tmp_path):
    marker = tmp_path / "MARKER"
    evil = evil_pt2(mtf_pt2, tmp_path / "evil.pt2", kind, marker)
    with pytest.raises(ValueError, match="refused to load this .pt2 archive") as info:
        load_estimator(evil)
    assert not marker.exists()
    assert str(evil) in str(info.value) and "weights_only" not in str(info.value)


@pytest.mark.parametrize("target", [
    "torch.ops.load_library", "torch.ops.import_module.x", "torch.ops.loaded_libraries.pop", "_operator.methodcaller",
    "_operator.call", "_operator.attrgetter", "math.__loader__", "builtins.eval", "torch.ops.aten.__class__.x",
])
def test_graph_targets_other_than_operators_are_refused(target, mtf_pt2, tmp_path):
    from tests._evil_files import retargeted_pt2

    with pytest.raises(ValueError, match="which is not a PyTorch operator"):
        load_estimator(retargeted_pt2(mtf_pt2, tmp_path / "t.pt2", target))


def test_the_archives_camhealth_writes_still_load(mtf_pt2):
    est = load_estimator(mtf_pt2)
    assert est.backend == "pt2"
    assert est.predict(torch.rand(2, 1, 32, 32))["mtf"].shape == (2, 16)


def test_monitor_refuses_a_hostile_noise_model(mtf_pt2, tmp_path, capsys):
    from camhealth.monitor.__main__ import main as monitor_main
    from PIL import Image

    marker = tmp_path / "MARKER"
    evil = evil_pt2(mtf_pt2, tmp_path / "evil.pt2", "sample_inputs", marker)
    frame = tmp_path / "frame.png"
    Image.new("L", (160, 160), 120).save(frame)
    rc = monitor_main([str(frame), "--sensor", "ICX285", "--noise-model", str(evil), "--no-mtf", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and not marker.exists()
    assert "refused to load this .pt2 archive" in err and len(err.strip().splitlines()) == 1


def test_pickled_code_in_a_weights_file_never_runs_and_the_refusal_gives_no_unsafe_advice(tmp_path):
    marker = tmp_path / "MARKER"
    for name in ("evil.pt", "evil.ckpt"):
        path = tmp_path / name
        torch.save({"format": "camhealth-estimator", "state_dict": Payload(marker)}, path)
        with pytest.raises(ValueError, match="pickled Python objects other than tensors") as info:
            load_estimator(path)
        assert "weights_only" not in str(info.value) and "arbitrary code" not in str(info.value)
        assert not marker.exists()
    raw = tmp_path / "raw.ckpt"
    raw.write_bytes(pickle.dumps({"state_dict": Payload(marker)}))
    with pytest.raises(ValueError, match="not a camhealth checkpoint") as info:
        load_estimator(raw)
    assert "weights_only" not in str(info.value) and not marker.exists()


def _first_entry(payload, change):
    """Replace the weights file's first floating state-dict entry by ``change(entry)`` (another layout, dtype or device)."""
    key = next(k for k, v in payload["state_dict"].items() if v.is_floating_point())
    payload["state_dict"][key] = change(payload["state_dict"][key])


def _tampered(tmp_path, edit_description=None, edit_payload=None):
    torch.manual_seed(0)
    path = export_weights(NoiseLevelEstimator(patch_size=32), tmp_path / "w.pt")
    payload = torch.load(path, weights_only=True)
    if edit_description is not None:
        desc = json.loads(payload["description"])
        edit_description(desc)
        payload["description"] = json.dumps(desc)
    if edit_payload is not None:
        edit_payload(payload)
    torch.save(payload, path)
    return path


@pytest.mark.parametrize(
    "description,payload,match",
    [
        (None, lambda p: p.__setitem__("description", "{not json"), "description is not valid JSON"),
        (None, lambda p: p.__setitem__("description", 5), "'description' must be a JSON string"),
        (None, lambda p: p.pop("state_dict"), "no 'state_dict'"),
        (lambda d: d["init_args"].__setitem__("bogus", 1), None, r"init_args \['bogus'\] are not arguments of"),
        (lambda d: d.__setitem__("patch_size", -32), None, "patch_size = -32 must be a positive integer"),
        (lambda d: (d.__setitem__("patch_size", -32), d["init_args"].__setitem__("patch_size", -32)), None,
         "patch_size = -32 must be a positive integer"),
        (lambda d: d["init_args"].__setitem__("patch_size", 48), None, "differs from init_args patch_size = 48"),
        (lambda d: d["init_args"].__setitem__("width", -4), None, "init_args do not build"),
        (lambda d: d.__setitem__("init_args", [1, 2]), None, "init_args must be a JSON object"),
        (lambda d: d.__setitem__("metadata_set", "most"), None, "metadata_set = 'most' must be"),
        (lambda d: d.__setitem__("kind", "mtf"), None, "kind = 'mtf' must be 'drne'"),
        (None, lambda p: p["state_dict"].__setitem__(next(iter(p["state_dict"])), torch.zeros(3)), "weights do not fit"),
        (None, lambda p: p.__setitem__("description", "[" * 100_000 + "]" * 100_000), "nests JSON deeper than"),
        (lambda d: d.__setitem__("patch_size", 16 * 10**8), None, r"patch_size = 1600000000 must be a multiple of 16 px in \[16, 1024\]"),
        *[(None, (lambda p, f=f: _first_entry(p, f)), r"entry '.*' is a .* weights must be dense CPU tensors")
          for f in (lambda t: t.to_sparse(), lambda t: t.reshape(t.shape[0], -1).to_sparse_csr(),
                    lambda t: t.to(torch.float8_e4m3fn), lambda t: t.to(torch.complex64), lambda t: t.to("meta"))],
    ],
)
def test_tampered_weights_file_gets_one_clear_error_at_load(tmp_path, description, payload, match):
    path = _tampered(tmp_path, description, payload)
    with pytest.raises(ValueError, match=match) as info:
        load_estimator(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("where", ["file_as_folder", "folder"])
def test_export_to_an_unwritable_path_says_so(tmp_path, capsys, where):
    src = export_weights(NoiseLevelEstimator(patch_size=32), tmp_path / "w.pt")
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    out = blocker / "model.pt2" if where == "file_as_folder" else tmp_path
    with pytest.raises(SystemExit) as info:
        export_main([str(src), "--format", "pt2", "--out", str(out)])
    err = capsys.readouterr().err
    assert info.value.code == 2
    assert f"--out {out} cannot be written" in err and len(err.strip().splitlines()) == 1
