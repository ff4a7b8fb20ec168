"""Export round trips (weights, pt2, onnx) give the same outputs; files that are not camhealth estimators
are refused with a clear error, and nothing but tensors is ever unpickled."""

from __future__ import annotations

import pickle
import re

import pytest
import torch

from camhealth.export import export_onnx, export_pt2, export_weights, load_module, main
from camhealth.inference import load_estimator
from camhealth.physics.metadata import CameraMetadata
from lightning_modules import MTFEstimator, NoiseLevelEstimator, NoiseSourceEstimator

MODELS = {
    "noise_source": lambda: NoiseSourceEstimator(patch_size=32, metadata_set="minimal"),
    "noise_source_none": lambda: NoiseSourceEstimator(patch_size=32, metadata_set="none"),
    "drne": lambda: NoiseLevelEstimator(patch_size=32),
    "mtf": lambda: MTFEstimator(patch_size=32),
}


def _kind(name: str) -> str:
    return "noise_source" if name.startswith("noise_source") else "mtf" if name.startswith("mtf") else name


def _perturbed(kind: str):
    torch.manual_seed(0)
    m = MODELS[kind]()
    with torch.no_grad():  # move the zero-initialised output layers off zero so outputs depend on them
        for p in m.net.parameters():
            p.add_(0.01 * torch.randn_like(p))
    return m.eval()


def _inputs(batch: int = 3):
    g = torch.Generator().manual_seed(1)
    x = torch.rand(batch, 1, 32, 32, generator=g) * 0.8 + 0.1
    x[:, :, :6] = 0.0  # black and saturated rows
    x[:, :, -4:] = 1.0
    meta = CameraMetadata.preset("ICX285", batch_size=batch, gain_db=torch.tensor([0.0, 12.0, 24.0])[:batch])
    return x, meta


@pytest.mark.parametrize("kind", sorted(MODELS))
def test_weights_round_trip_identical(kind, tmp_path):
    m = _perturbed(kind)
    path = export_weights(m, tmp_path / "w.pt", metrics={"rms_total": 0.5})
    again, desc = load_module(path)
    assert desc["kind"] == _kind(kind) and desc["metrics"] == {"rms_total": 0.5}
    inputs = m.export_inputs(3)
    with torch.no_grad():
        assert torch.equal(m.export_module()(*inputs), again.export_module()(*inputs))
    # only plain data inside: loads with weights_only=True
    torch.load(path, weights_only=True)


@pytest.mark.parametrize("fmt", ["pt2", "onnx"])
@pytest.mark.parametrize("kind", sorted(MODELS))
def test_exported_program_matches_torch(kind, fmt, tmp_path):
    m = _perturbed(kind)
    ref = load_estimator(export_weights(m, tmp_path / "w.pt"))
    path = (export_pt2 if fmt == "pt2" else export_onnx)(m, tmp_path / f"m.{fmt}")
    est = load_estimator(path)
    noise = kind.startswith("noise_source")
    assert est.backend == fmt and est.kind == _kind(kind) and est.patch_size == 32
    x, meta = _inputs(3)
    a = ref.predict(x, meta if noise else None)
    b = est.predict(x, meta if noise else None)
    for key in ("sigma", "xi", "sigma_total", "mtf"):
        if key in a:
            assert torch.allclose(a[key], b[key], rtol=1e-4, atol=1e-4), key
    # dynamic batch: a batch of 1 works too
    est.predict(x[:1], meta[:1] if noise else None)
    if kind.startswith("mtf"):  # and the flipped copies of views=4 go through the exported program as one batch
        assert torch.allclose(ref.predict(x, views=4)["mtf"], est.predict(x, views=4)["mtf"], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("fmt", ["pt2", "onnx"])
def test_exporting_a_weights_file_carries_its_mtf_error_table(fmt, tmp_path):
    """The error table measured on a weights file (``bench mtf_error --write``) travels into .pt2 and .onnx, so their
    ``mtf_std`` is the same calibrated uncertainty."""
    from camhealth.estimators.mtf_error import MTFErrorTable
    from camhealth.export import set_description_entries

    w = export_weights(_perturbed("mtf"), tmp_path / "w.pt")
    table = MTFErrorTable((0.0, 0.5, 1.0), (0.02, 0.2, 0.04), 100, "test")
    set_description_entries(w, {"mtf_error": table.to_dict()})
    path = (export_pt2 if fmt == "pt2" else export_onnx)(w, tmp_path / f"m.{fmt}")
    est, ref = load_estimator(path), load_estimator(w)
    assert est.description["mtf_error"] == table.to_dict()
    x, _ = _inputs(3)
    assert torch.allclose(est.predict(x)["mtf_std"], ref.predict(x)["mtf_std"], atol=1e-4)


def test_export_cli(tmp_path, capsys):
    src = export_weights(_perturbed("drne"), tmp_path / "w.pt")
    out = main([str(src), "--format", "pt2", "--out", str(tmp_path / "x.pt2")])
    assert out.is_file() and str(out) in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main([str(tmp_path / "missing.ckpt"), "--format", "pt2"])
    assert "no such file" in capsys.readouterr().err


class _Evil:
    def __reduce__(self):
        return (print, ("this must never run",))


def test_loader_refuses_foreign_files(tmp_path):
    plain = tmp_path / "plain.pt"
    torch.save({"weights": torch.zeros(2)}, plain)
    with pytest.raises(ValueError, match="not a camhealth checkpoint"):
        load_estimator(plain)
    evil = tmp_path / "evil.ckpt"
    evil.write_bytes(pickle.dumps({"state_dict": _Evil()}))
    with pytest.raises(ValueError, match="loads as plain tensors") as info:
        load_estimator(evil)
    assert "weights_only" not in str(info.value)  # torch's advice to load it unsafely is not passed on
    text = tmp_path / "notes.onnx"
    text.write_text("hello")
    with pytest.raises(ValueError, match="not a readable ONNX"):
        load_estimator(text)
    with pytest.raises(FileNotFoundError, match="shipped names"):
        load_estimator(tmp_path / "nothing.pt")
    with pytest.raises(ValueError, match="folder"):
        load_estimator(tmp_path)


def test_loader_refuses_unknown_class(tmp_path):
    m = _perturbed("drne")
    path = export_weights(m, tmp_path / "w.pt")
    payload = torch.load(path, weights_only=True)
    payload["description"] = payload["description"].replace("lightning_modules.drne.NoiseLevelEstimator", "os.system")
    torch.save(payload, path)
    with pytest.raises(ValueError, match="not a camhealth estimator"):
        load_estimator(path)


@pytest.mark.parametrize("edit", ["nan", "inf", "int32", "bool"])
def test_weights_that_are_not_finite_floats_are_refused_at_load_naming_the_entry(edit, tmp_path):
    """A NaN or infinite weight, or integer/bool tensors where the network holds floats (load_state_dict would cast
    them silently), is one ValueError naming the file and the state_dict entry."""
    path = export_weights(_perturbed("drne"), tmp_path / "w.pt")
    payload = torch.load(path, weights_only=True)
    state = {k: v.clone() for k, v in payload["state_dict"].items()}
    key = next(k for k, v in state.items() if v.is_floating_point() and v.numel() > 1)
    if edit in ("nan", "inf"):
        state[key].view(-1)[1] = float(edit)
        match = rf"w\.pt: state_dict entry '{key}' holds 1 NaN or infinite value\(s\)"
    else:
        state[key] = state[key].to(getattr(torch, edit))
        match = rf"w\.pt: state_dict entry '{key}' is a torch\.{edit} tensor; .* holds torch\.float32 values there"
    torch.save({**payload, "state_dict": state}, path)
    for load in (load_estimator, load_module):
        with pytest.raises(ValueError, match=match):
            load(path)


def _ort_session(path):
    import onnxruntime as ort

    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


def _hard_patches(batch: int = 6):
    x, _ = _inputs(3)
    g = torch.Generator().manual_seed(2)
    extra = torch.rand(batch - 3, 1, 32, 32, generator=g) * 0.5 + 0.25
    x = torch.cat([x, extra])
    x[3] = 0.0  # black
    x[4] = 1.0  # saturated
    return x


@pytest.mark.parametrize("kind", ["noise_source", "noise_source_none"])
def test_self_contained_noise_onnx_matches_predict(kind, tmp_path):
    """ONNX Runtime alone (raw patch in [0, 1], raw metadata in physical units) gives what predict gives."""
    m = _perturbed(kind)
    ref = load_estimator(export_weights(m, tmp_path / "w.pt"))
    path = export_onnx(m, tmp_path / "m.onnx")
    session = _ort_session(path)
    minimal = kind == "noise_source"
    assert [i.name for i in session.get_inputs()] == (["patch", "metadata"] if minimal else ["patch"])
    assert [o.name for o in session.get_outputs()] == ["sigma", "xi", "sigma_total", "assessable", "reason_code"]
    for batch in (1, 6, 37):
        x = _hard_patches(max(batch, 6))[:batch] if batch <= 6 else torch.rand(batch, 1, 32, 32, generator=torch.Generator().manual_seed(3))
        gain = torch.linspace(0.0, 24.0, batch)
        meta = CameraMetadata.preset("ICX285", batch_size=batch, gain_db=gain, exposure_s=torch.full((batch,), 0.02),
                                     temperature_c=torch.linspace(0.0, 80.0, batch))
        feeds = {"patch": x.numpy()}
        if minimal:
            feeds["metadata"] = torch.stack([meta.gain_db, meta.exposure_s, meta.temperature_c], 1).float().numpy()
        sigma, xi, total, assessable, code = (torch.from_numpy(a) for a in session.run(None, feeds))
        want = ref.predict(x, meta if minimal else None)
        assert sigma.shape == (batch, 3) and xi.shape == total.shape == assessable.shape == (batch,)
        assert (sigma >= 0).all()
        for got, key in ((sigma, "sigma"), (xi, "xi"), (total, "sigma_total")):
            assert (got - want[key]).abs().max() < 1e-3, key  # DN
        assert torch.equal(assessable, want["assessable"])
        from camhealth.export import ONNX_REASONS

        assert [ONNX_REASONS[int(c)] for c in code] == want["reason"]
    # the loader runs the same file through predict
    est = load_estimator(path)
    x = _hard_patches()
    meta = CameraMetadata.preset("ICX285", batch_size=6)
    a, b = ref.predict(x, meta if minimal else None), est.predict(x, meta if minimal else None)
    assert torch.allclose(a["sigma_total"], b["sigma_total"], atol=1e-3) and a["reason"] == b["reason"]


def test_self_contained_noise_onnx_refuses_what_predict_refuses(tmp_path):
    """The graph holds predict's refusals of a noise-source network: noise beyond the validated range (uniform
    noise of σ 97.5 DN: pixels at 30 or 225 DN at random, code 4), a patch quieter than any camera state makes (a
    constant 128 DN patch, code 5), a patch 40 % crushed black and 40 % blown out (code 6, "clipped"), and one that
    noise of 200 DN clipped at both ends (code 4: the noise is what is known)."""
    from camhealth.export import ONNX_REASONS

    m = _perturbed("noise_source_none")
    ref = load_estimator(export_weights(m, tmp_path / "w.pt"))
    session = _ort_session(export_onnx(m, tmp_path / "m.onnx"))
    g = torch.Generator().manual_seed(5)
    clipped = (128 + 5 * torch.randn(1, 32, 32, generator=g)).round().clamp(0, 255) / 255
    clipped[..., :13] = 0.0
    clipped[..., 13:26] = 1.0
    x = torch.stack([(30.0 + 195.0 * (torch.rand(1, 32, 32, generator=g) < 0.5)) / 255, torch.full((1, 32, 32), 128 / 255),
                     ((128 + 5 * torch.randn(1, 32, 32, generator=g)).round().clamp(0, 255)) / 255, clipped,
                     ((128 + 200 * torch.randn(1, 32, 32, generator=g)).round().clamp(0, 255)) / 255])
    assessable, code = (torch.from_numpy(a) for a in session.run(None, {"patch": x.numpy()})[3:])
    want = ref.predict(x)
    assert [ONNX_REASONS[int(c)] for c in code] == want["reason"] == ["noise beyond validated range",
                                                                         "less noise than the metadata allow", "",
                                                                         "clipped", "noise beyond validated range"]
    assert assessable.tolist() == [False, False, True, False, False] and code.tolist()[3] == 6


def test_self_contained_noise_onnx_flags_metadata_out_of_range(tmp_path):
    """The graph cannot raise: metadata that predict refuses (out of range, NaN) make the patch not assessable."""
    session = _ort_session(export_onnx(_perturbed("noise_source"), tmp_path / "m.onnx"))
    x = torch.rand(4, 1, 32, 32, generator=torch.Generator().manual_seed(4)) * 0.5 + 0.25
    meta = torch.tensor([[12.0, 0.01, 40.0], [30.0, 0.01, 40.0], [12.0, 0.5, 40.0], [float("nan"), 0.01, 40.0]])
    with pytest.raises(ValueError, match="gain_db"):
        load_estimator(export_weights(_perturbed("noise_source"), tmp_path / "w.pt")).predict(
            x[1:2], {"gain_db": 30.0, "exposure_s": 0.01, "temperature_c": 40.0})
    _, _, _, assessable, code = session.run(None, {"patch": x.numpy(), "metadata": meta.numpy()})
    assert assessable.tolist() == [True, False, False, False] and code.tolist() == [0, 3, 3, 3]


def test_shipped_noise_network_exports_self_contained(tmp_path):
    """The shipped Min-Meta network, exported: ONNX Runtime alone matches predict within 1e-3 DN."""
    ref = load_estimator("noise_source_min")
    session = _ort_session(export_onnx(ref.source, tmp_path / "min.onnx"))
    g = torch.Generator().manual_seed(5)
    x = (torch.rand(3, 1, 1, 1, generator=g) * 0.8 + 0.1 + torch.randn(3, 1, 128, 128, generator=g) * 0.02).clamp(0, 1)
    meta = {"gain_db": 18.0, "exposure_s": 0.05, "temperature_c": 55.0}
    sigma, xi, total, _, _ = session.run(None, {"patch": x.numpy(), "metadata": torch.tensor([[18.0, 0.05, 55.0]] * 3).numpy()})
    want = ref.predict(x, meta)
    assert (torch.from_numpy(sigma) - want["sigma"]).abs().max() < 1e-3
    assert (torch.from_numpy(xi) - want["xi"]).abs().max() < 1e-3
    assert (torch.from_numpy(total) - want["sigma_total"]).abs().max() < 1e-3


def test_a_metric_without_data_is_null_in_the_description(tmp_path):
    """The AMAE of a blur family with no test sample is NaN (no data): the weights file says null, in strict JSON."""
    import json

    def no_nan(token):
        raise ValueError(f"{token} in the description")

    path = export_weights(_perturbed("mtf"), tmp_path / "w.pt",
                          metrics={"test/amae": torch.tensor(3.5), "test/amae_nonlinear": float("nan"), "test/amae_linear": None})
    desc = json.loads(torch.load(path, weights_only=True)["description"], parse_constant=no_nan)
    assert desc["metrics"] == {"test/amae": 3.5, "test/amae_nonlinear": None, "test/amae_linear": None}
    _, again = load_module(path)
    assert again["metrics"] == desc["metrics"]
    assert json.loads(torch.load(export_weights(path, tmp_path / "again.pt"), weights_only=True)["description"],
                      parse_constant=no_nan)["metrics"] == desc["metrics"]  # exported again: still null


# ------------------------------------------------------------------ audit fixes: what a file may hold
def _edited_weights(tmp_path, name="edited.pt", top=None, **desc_changes):
    """A weights file of a small DRNE whose description (and top-level entries ``top``) are changed."""
    import json

    path = export_weights(_perturbed("drne"), tmp_path / "w.pt")
    obj = torch.load(path, weights_only=True)
    desc = json.loads(obj["description"])
    desc.update(desc_changes)
    obj.update(top or {}, description=json.dumps(desc))
    torch.save(obj, tmp_path / name)
    return tmp_path / name


@pytest.mark.parametrize("top,desc,match", [
    ({"version": 99}, {"version": 99}, r"description version = 99 is not a format version this camhealth reads \(only 1\)"),
    ({}, {"version": "1"}, r"description version = '1' is not a format version"),
    ({"version": 2}, {}, r"the weights file's version = 2 is not a format version this camhealth reads \(only 1\)"),
])
def test_a_file_of_another_format_version_is_refused_and_not_re_exported_as_version_1(tmp_path, top, desc, match):
    path = _edited_weights(tmp_path, top=top, **desc)
    for load in (load_estimator, load_module):
        with pytest.raises(ValueError, match=rf"edited\.pt: {match}"):
            load(path)
    with pytest.raises(ValueError, match=match):
        export_weights(path, tmp_path / "again.pt")
    assert not (tmp_path / "again.pt").exists()


@pytest.mark.parametrize("changes,match", [
    ({"metrics": {"test/rms_total": "abc"}}, r"description metrics\['test/rms_total'\] = 'abc' must be a finite number or null"),
    ({"metrics": {"test/rms_total": float("inf")}}, r"description metrics\['test/rms_total'\] = inf must be a finite number"),
    ({"metrics": [1, 2]}, r"description metrics must be a JSON object of numbers or null .*got list"),
    ({"params": "many"}, r"description params = 'many' must be a non-negative integer"),
    ({"params": -1}, r"description params = -1 must be a non-negative integer"),
    ({"flops_per_patch": "x"}, r"description flops_per_patch = 'x' must be a non-negative integer"),
    ({"flops_per_patch": True}, r"description flops_per_patch = True must be a non-negative integer"),
])
def test_description_metrics_params_and_flops_are_checked(tmp_path, capsys, changes, match):
    """A string metric made the model card fail with "Unknown format code 'f'" and export with "could not convert
    string to float"; a list "'list' object has no attribute 'items'"; params "many" "Cannot specify ',' with 's'".
    Each is one ValueError naming the file and the field, at load and in the export CLI."""
    path = _edited_weights(tmp_path, **changes)
    for load in (load_estimator, load_module):
        with pytest.raises(ValueError, match=rf"edited\.pt: {match}"):
            load(path)
    with pytest.raises(SystemExit):
        main([str(path), "--format", "weights", "--out", str(tmp_path / "out.pt")])
    assert re.search(match, capsys.readouterr().err)


def test_metrics_without_data_still_load(tmp_path):
    """null and NaN (an older file's metric without data) are what a metric without data may be."""
    path = _edited_weights(tmp_path, metrics={"a": None, "b": float("nan"), "c": 1, "d": 0.5})
    assert load_estimator(path).description["metrics"]["c"] == 1


def test_a_huge_integer_in_a_weights_file_description_is_named(tmp_path, capsys):
    path = export_weights(_perturbed("drne"), tmp_path / "w.pt")
    obj = torch.load(path, weights_only=True)
    obj["description"] = obj["description"].replace('"patch_size": 32', '"patch_size": ' + "9" * 5000)
    torch.save(obj, tmp_path / "bigint.pt")
    match = r"bigint\.pt: the weights file's description cannot be read: Exceeds the limit \(4300 digits\)"
    with pytest.raises(ValueError, match=match):
        load_estimator(tmp_path / "bigint.pt")
    with pytest.raises(SystemExit):
        main([str(tmp_path / "bigint.pt"), "--format", "weights", "--out", str(tmp_path / "out.pt")])
    assert re.search(match, capsys.readouterr().err)


def _deflated(src, out, extra=None):
    """``src`` re-zipped with deflate (what torch.load inflates), plus ``extra`` entries {name: bytes}."""
    import zipfile

    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zout:
        root = zin.namelist()[0].split("/", 1)[0]
        for n in zin.namelist():
            zout.writestr(n, zin.read(n))
        for name, data in (extra or {}).items():
            zout.writestr(f"{root}/{name}", data)
    return out


def test_decompression_bombs_are_refused_before_they_are_inflated(tmp_path, monkeypatch):
    """A 3.6 MB .pt2 with a 3 GiB deflated entry loaded after 56 s at 6.6 GB of memory, a 1.3 MB .pt with a 1 GiB
    tensor used 3.1 GB before its refusal. The zip directory's declared sizes are checked first (here against limits
    lowered to 1 MiB, which an entry of 2 MiB of zeros exceeds), naming the entry, its size and the limit; torch.load
    is never called on such a file."""
    import camhealth._pt2_check as check

    monkeypatch.setattr(check, "MAX_ZIP_ENTRY_BYTES", 2**20)
    monkeypatch.setattr(check, "MAX_JSON_ENTRY_BYTES", 2**20)
    m = _perturbed("drne")
    pt2 = export_pt2(m, tmp_path / "m.pt2")
    bomb = _deflated(pt2, tmp_path / "bomb.pt2", {"extra/pad.bin": bytes(2 * 2**20)})
    with pytest.raises(ValueError, match=r"bomb\.pt2: refused to load this \.pt2 archive: entry '\w+/extra/pad\.bin' "
                                         r"declares 2,097,152 bytes uncompressed \(\d[\d,]* stored\), more than the limit "
                                         r"of 1,048,576 bytes \(MAX_JSON_ENTRY_BYTES\)"):
        load_estimator(bomb)
    state = {k: v for k, v in m.net.state_dict().items()}
    torch.save({"format": "camhealth-estimator", "version": 1, "description": "{}",
                "state_dict": {**state, "pad": torch.zeros(2**19)}}, tmp_path / "raw.pt")
    bomb = _deflated(tmp_path / "raw.pt", tmp_path / "bomb.pt")
    real_load = torch.load
    monkeypatch.setattr(torch, "load", lambda *a, **k: pytest.fail("torch.load ran on a bomb"))
    with pytest.raises(ValueError, match=r"bomb\.pt: refused to load this file: entry 'raw/data/\d+' declares 2,097,152 "
                                         r"bytes uncompressed .* more than the limit of 1,048,576 bytes "
                                         r"\(MAX_ZIP_ENTRY_BYTES\)"):
        load_estimator(bomb)
    monkeypatch.setattr(torch, "load", real_load)
    monkeypatch.setattr(check, "MAX_ZIP_ENTRY_BYTES", 2**30)
    monkeypatch.setattr(check, "MAX_ZIP_TOTAL_BYTES", 2**20)
    with pytest.raises(ValueError, match=r"entries declare [\d,]+ bytes uncompressed together, more than the limit of "
                                         r"1,048,576 bytes \(MAX_ZIP_TOTAL_BYTES\)"):
        load_estimator(bomb)
    # the files camhealth writes are well within the real limits
    monkeypatch.undo()
    assert load_estimator(pt2).kind == "drne" and load_estimator(export_weights(m, tmp_path / "w.pt")).kind == "drne"


def test_the_pt2_check_reads_no_tensor_payload_and_no_extra_file(tmp_path, monkeypatch):
    """check_pt2_archive inflated every entry; it reads only the graphs, payload configs, sample inputs and the format."""
    import zipfile

    from camhealth._pt2_check import check_pt2_archive

    pt2 = export_pt2(_perturbed("drne"), tmp_path / "m.pt2")
    read = []
    real = zipfile.ZipFile.read
    monkeypatch.setattr(zipfile.ZipFile, "read", lambda self, name, pwd=None: (read.append(str(name)), real(self, name, pwd))[1])
    check_pt2_archive(pt2)
    assert read and not [n for n in read if "/data/weights/weight_" in n or "/data/constants/tensor_" in n or "/extra/" in n]


def test_files_that_are_no_weights_file_are_named_for_what_they_are(tmp_path, capsys):
    """A truncated .pt passed on miniz's wording cut at 200 characters; a .safetensors file was told to install
    safetensors; exporting a .pt2 again said "failed locating file data.pkl … likely corrupted"; a raw pickle printed
    torch's pickle-protocol warning before its refusal."""
    import pickle
    import warnings

    src = export_weights(_perturbed("drne"), tmp_path / "w.pt")
    (tmp_path / "trunc.pt").write_bytes(src.read_bytes()[: src.stat().st_size // 2])
    with pytest.raises(ValueError, match=r"trunc\.pt is truncated or corrupt: it begins as a zip archive, as torch\.save "
                                         r"writes, but its zip directory cannot be read"):
        load_estimator(tmp_path / "trunc.pt")
    (tmp_path / "w.safetensors").write_bytes(b"\x10" + bytes(7) + b'{"a": 1}')
    with pytest.raises(ValueError, match=r"w\.safetensors: camhealth does not read \.safetensors files") as info:
        load_estimator(tmp_path / "w.safetensors")
    assert "pip" not in str(info.value)
    pt2 = export_pt2(_perturbed("drne"), tmp_path / "m.pt2")
    with pytest.raises(SystemExit):
        main([str(pt2), "--format", "weights", "--out", str(tmp_path / "x.pt")])
    err = capsys.readouterr().err
    assert "m.pt2 is an exported program" in err and "give the weights file (.pt) or checkpoint (.ckpt)" in err
    import shutil

    shutil.copy(pt2, tmp_path / "renamed.pt")
    with pytest.raises(ValueError, match=r"renamed\.pt is a torch\.export archive \(\.pt2\), not a weights file"):
        load_estimator(tmp_path / "renamed.pt")
    (tmp_path / "raw.pt").write_bytes(pickle.dumps({"a": 1}, protocol=4))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(ValueError, match="loads as plain tensors"):
            load_estimator(tmp_path / "raw.pt")
    assert not [w for w in caught if "pickle protocol" in str(w.message)]
