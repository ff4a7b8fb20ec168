"""Export round trips (weights, pt2, onnx) give the same outputs; files that are not camhealth estimators
are refused with a clear error, and nothing but tensors is ever unpickled."""

from __future__ import annotations

import pickle

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
    """The graph holds predict's two refusals of a noise-source network: noise beyond the validated range (uniform
    noise of σ 97.5 DN: pixels at 30 or 225 DN at random, code 4) and a patch quieter than any camera state makes (a
    constant 128 DN patch, code 5)."""
    from camhealth.export import ONNX_REASONS

    m = _perturbed("noise_source_none")
    ref = load_estimator(export_weights(m, tmp_path / "w.pt"))
    session = _ort_session(export_onnx(m, tmp_path / "m.onnx"))
    g = torch.Generator().manual_seed(5)
    x = torch.stack([(30.0 + 195.0 * (torch.rand(1, 32, 32, generator=g) < 0.5)) / 255, torch.full((1, 32, 32), 128 / 255),
                     ((128 + 5 * torch.randn(1, 32, 32, generator=g)).round().clamp(0, 255)) / 255])
    assessable, code = (torch.from_numpy(a) for a in session.run(None, {"patch": x.numpy()})[3:])
    want = ref.predict(x)
    assert [ONNX_REASONS[int(c)] for c in code] == want["reason"] == ["noise beyond validated range",
                                                                         "less noise than the metadata allow", ""]
    assert assessable.tolist() == [False, False, True]


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
