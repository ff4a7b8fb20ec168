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
    "mtf_joint": lambda: MTFEstimator(patch_size=32, joint_directions=True),
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
