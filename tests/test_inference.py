"""`camhealth.load_estimator(...).predict`: input conventions, metadata handling, flags, precision."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from camhealth import load_estimator
from camhealth.export import export_weights
from camhealth.inference import assess_patches, shipped_models
from camhealth.physics.metadata import CameraMetadata
from lightning_modules import MTFEstimator, NoiseSourceEstimator


@pytest.fixture(scope="module")
def noise_est(tmp_path_factory):
    torch.manual_seed(0)
    m = NoiseSourceEstimator(patch_size=32, metadata_set="minimal")
    with torch.no_grad():
        for p in m.net.parameters():
            p.add_(0.01 * torch.randn_like(p))
    return load_estimator(export_weights(m, tmp_path_factory.mktemp("w") / "ns.pt"))


@pytest.fixture(scope="module")
def min_est(tmp_path_factory):
    m = NoiseSourceEstimator(patch_size=32, metadata_set="minimal")
    return load_estimator(export_weights(m, tmp_path_factory.mktemp("w") / "min.pt"))


def _patches(batch=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(batch, 1, 32, 32, generator=g) * 0.6 + 0.2


@pytest.mark.parametrize("batch", [1, 3])
def test_outputs_and_shapes(noise_est, batch):
    out = noise_est.predict(_patches(batch), "ICX285")
    assert out["sigma"].shape == (batch, 3) and out["xi"].shape == (batch,) and out["sigma_total"].shape == (batch,)
    assert out["assessable"].dtype == torch.bool and len(out["reason"]) == batch
    assert torch.allclose(out["sigma_total"], out["sigma"].pow(2).sum(1).sqrt(), rtol=1e-5)  # Eq. 4.2


def test_dn_uint8_float_and_numpy_inputs_agree(noise_est):
    x = (_patches(2) * 255).round()
    ref = noise_est.predict(x / 255, "ICX285")["sigma"]
    u8 = noise_est.predict(x.to(torch.uint8).numpy(), "ICX285")["sigma"]
    dn = noise_est.predict(x, "ICX285", input_range="dn")["sigma"]
    assert torch.allclose(ref, u8, atol=1e-5) and torch.allclose(ref, dn, atol=1e-5)
    hw = noise_est.predict(x[0, 0].to(torch.uint8), "ICX285")["sigma"]  # H×W
    assert torch.allclose(hw, ref[:1], atol=1e-5)


def test_bad_inputs_get_clear_errors(noise_est):
    x = _patches(2)
    with pytest.raises(ValueError, match="looks like DN"):
        noise_est.predict(x * 255, "ICX285")
    nan = x.clone()
    nan[0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        noise_est.predict(nan, "ICX285")
    with pytest.raises(ValueError, match="32×32"):
        noise_est.predict(torch.rand(2, 1, 40, 40), "ICX285")
    with pytest.raises(ValueError, match="B×1×H×W"):
        noise_est.predict(torch.rand(2, 3, 32, 32), "ICX285")
    with pytest.raises(TypeError, match="numeric"):
        noise_est.predict(np.array([["a"]]), "ICX285")
    with pytest.raises(ValueError, match="pass metadata"):
        noise_est.predict(x)
    with pytest.raises(ValueError, match="in DN must lie in"):
        noise_est.predict(x * 400, "ICX285", input_range="dn")


@pytest.mark.parametrize("field,value", [("gain_db", 30.0), ("temperature_c", -5.0), ("full_well_e", 1000.0)])
def test_metadata_out_of_range_names_field(noise_est, field, value):
    with pytest.raises(ValueError, match=field):
        noise_est.predict(_patches(1), {field: value}, base_preset="ICX285")
    with pytest.raises(ValueError, match=field):  # an empty batch checks its metadata too
        noise_est.predict(_patches(1)[:0], {field: value}, base_preset="ICX285")


@pytest.mark.parametrize("name", ["noise_source_full", "noise_source_min"])
def test_an_empty_batch_checks_the_shipped_noise_models_metadata(name):
    est = load_estimator(name)
    empty = torch.zeros(0, 1, est.patch_size, est.patch_size)
    assert est.predict(empty, "ICX285")["sigma"].shape == (0, 3)
    with pytest.raises(ValueError, match=r"gain_db.*= 99 dB is out of the allowed range \[0, 24\]"):
        est.predict(empty, {"gain_db": 99.0}, base_preset="ICX285")
    with pytest.raises(ValueError, match="unknown sensor preset 'NOPE'"):
        est.predict(empty, "NOPE")
    with pytest.raises(TypeError, match="metadata must be"):
        est.predict(empty, 3)


def test_metadata_batch_and_dict(noise_est, min_est):
    x = _patches(3)
    meta = CameraMetadata.preset("EV76C661", batch_size=3, gain_db=torch.tensor([0.0, 12.0, 24.0]))
    full = noise_est.predict(x, meta)
    one = noise_est.predict(x[1:2], meta[1:2])
    assert torch.allclose(full["sigma"][1:2], one["sigma"], atol=1e-5)
    with pytest.raises(ValueError, match="batch size 2"):
        noise_est.predict(x, meta[:2])
    # Min-Meta: gain/exposure/temperature suffice
    out = min_est.predict(x, {"gain_db": 6.0, "exposure_s": 0.01, "temperature_c": 30.0})
    assert torch.isfinite(out["sigma"]).all()


@pytest.mark.parametrize("metadata,missing", [({}, "'gain_db', 'exposure_s', 'temperature_c'"),
                                              ({"gain_db": 12.0}, "'exposure_s', 'temperature_c'"),
                                              ({"gain_db": 12.0, "exposure_s": 0.2}, "'temperature_c'")])
def test_min_meta_refuses_a_dict_without_the_fields_it_reads(min_est, metadata, missing):
    """A Min-Meta network reads gain, exposure and temperature: a dict that lacks one of them (and no base_preset)
    is a ValueError naming the missing fields, for a full and an empty batch alike — not ICX285's operating point
    (0 dB, 10 ms, 25 °C) in their place."""
    x = _patches(2)
    with pytest.raises(ValueError, match=rf"lacks \[{missing}\].*base_preset="):
        min_est.predict(x, metadata)
    with pytest.raises(ValueError, match=rf"lacks \[{missing}\]"):
        min_est.predict(x[:0], metadata)
    # with base_preset= the preset gives them, as documented (ICX285: 0 dB, 10 ms, 25 °C)
    given = min_est.predict(x, metadata, base_preset="ICX285")["sigma"]
    full = {"gain_db": 0.0, "exposure_s": 0.01, "temperature_c": 25.0, **metadata}
    assert torch.allclose(given, min_est.predict(x, full)["sigma"], atol=1e-6)


@pytest.mark.parametrize("fill,reason", [(0.0, "black"), (1.0, "saturated")])
def test_black_and_saturated_are_finite_and_flagged(noise_est, fill, reason):
    out = noise_est.predict(torch.full((2, 1, 32, 32), fill), "ICX285")
    assert torch.isfinite(out["sigma"]).all() and torch.isfinite(out["xi"]).all()
    assert not out["assessable"].any() and out["reason"] == [reason, reason]


def test_featureless_only_for_mtf():
    flat = torch.full((1, 1, 16, 16), 0.5)
    assert assess_patches(flat, "mtf")[1] == ["featureless"]
    assert assess_patches(flat, "noise_source")[1] == [""]


def test_fp32_and_bf16_agree(noise_est, tmp_path):
    """bf16 autocast inference stays within 5 % + 0.1 DN of fp32 (noise) and 0.03 of MTF."""
    x = _patches(4, seed=3)
    a = noise_est.predict(x, "ICX285", precision="fp32")["sigma"]
    b = noise_est.predict(x, "ICX285", precision="bf16")["sigma"]
    assert torch.allclose(a, b, rtol=0.05, atol=0.1)
    mtf = load_estimator(export_weights(MTFEstimator(patch_size=32), tmp_path / "mtf.pt"))
    y = torch.rand(4, 1, 32, 32)
    assert torch.allclose(mtf.predict(y, precision="fp32")["mtf"], mtf.predict(y, precision="bf16")["mtf"], atol=0.03)
    with pytest.raises(ValueError, match="precision"):
        mtf.predict(y, precision="fp16")


@pytest.mark.parametrize("batch", [1, 256])
def test_large_and_single_batches(noise_est, batch):
    x = torch.rand(batch, 1, 32, 32)
    out = noise_est.predict(x, "ICX285", batch_size=100)
    assert out["sigma"].shape == (batch, 3) and torch.isfinite(out["sigma"]).all()


def test_shipped_models_load_by_name():
    shipped = shipped_models()
    for name in shipped:
        est = load_estimator(name)
        assert est.kind in ("mtf", "drne", "noise_source")
        assert "metrics" in est.description  # every shipped model carries its held-out metrics


def test_model_card_timing_uses_all_threads_and_restores_them(min_est, monkeypatch):
    """The card's ms/patch come from torch.utils.benchmark.Timer at this process's thread count (not Timer's
    default of 1), and the thread count is as before afterwards."""
    from torch.utils import benchmark

    from camhealth.model_card import _time_predict

    seen = []
    real = benchmark.Timer.__init__

    def spy(self, *args, **kwargs):
        seen.append(kwargs.get("num_threads"))
        real(self, *args, **kwargs)

    monkeypatch.setattr(benchmark.Timer, "__init__", spy)
    threads = torch.get_num_threads()
    t = _time_predict(min_est, batch=2, min_run_time_s=0.01)
    assert set(t) == {"fp32", "bf16"} and all(np.isfinite(v) and v > 0 for v in t.values())
    assert seen == [threads, threads] and torch.get_num_threads() == threads

def test_bucket_sizes():
    from camhealth.inference import bucket_size

    assert [bucket_size(n) for n in (1, 4, 5, 31, 32, 33, 80, 129)] == [4, 4, 8, 32, 32, 48, 80, 144]
    with pytest.raises(ValueError):
        bucket_size(0)


def test_padding_to_a_bucket_does_not_change_results(noise_est):
    """Batches are padded to bucket sizes: every patch's estimate is the one it gets alone (fp32)."""
    x = _patches(7, seed=3)
    meta = CameraMetadata.preset("ICX285", batch_size=7, gain_db=torch.linspace(0, 24, 7).tolist())
    together = noise_est.predict(x, meta)
    for i in (0, 6):
        alone = noise_est.predict(x[i : i + 1], meta[i])
        assert torch.allclose(alone["sigma"], together["sigma"][i : i + 1], atol=1e-5)
        assert torch.allclose(alone["xi"], together["xi"][i : i + 1], atol=1e-5)


@pytest.mark.parametrize("views", [2, 4])
def test_mtf_views_average_the_flipped_copies(tmp_path, views):
    torch.manual_seed(0)
    mtf = load_estimator(export_weights(MTFEstimator(patch_size=32), tmp_path / "mtf.pt"))
    y = torch.rand(3, 1, 32, 32)
    flips = [(-2, -1)] if views == 2 else [(-1,), (-2,), (-2, -1)]
    expected = torch.stack([mtf.predict(y)["mtf"]] + [mtf.predict(y.flip(d))["mtf"] for d in flips]).mean(0)
    out = mtf.predict(y, views=views)
    assert out["mtf"].shape == (3, 16) and torch.allclose(out["mtf"], expected, atol=1e-6)
    assert out["assessable"].shape == (3,) and len(out["reason"]) == 3
    assert not torch.allclose(out["mtf"], mtf.predict(y)["mtf"])  # the flipped copies do add estimates


def test_views_are_checked(noise_est, tmp_path):
    mtf = load_estimator(export_weights(MTFEstimator(patch_size=32), tmp_path / "mtf.pt"))
    with pytest.raises(ValueError, match="views = 3 must be 1, 2 or 4"):
        mtf.predict(torch.rand(1, 1, 32, 32), views=3)
    with pytest.raises(ValueError, match="views = 2 averages flipped copies of MTF patches"):
        noise_est.predict(_patches(1), "ICX285", views=2)


@pytest.mark.parametrize("bad", [0, 2.5, "4", True, None])
def test_batch_size_is_checked(noise_est, bad):
    """A float or string batch size failed inside the chunking with a message that did not name the argument."""
    from camhealth.estimators.physics_noise import PhysicsNoiseEstimator

    for est in (noise_est, PhysicsNoiseEstimator()):
        with pytest.raises(ValueError, match=rf"batch_size = {re.escape(repr(bad))} must be an integer ≥ 1"):
            est.predict(_patches(1), "ICX285", batch_size=bad)
    assert noise_est.predict(_patches(2), "ICX285", batch_size=np.int64(1))["sigma"].shape == (2, 3)


@pytest.mark.parametrize("fill,reason", [(0.0, "black"), (1.0, "saturated"), (0.5, "featureless")])
def test_mtf_views_keep_the_flags_of_hard_patches(tmp_path, fill, reason):
    mtf = load_estimator(export_weights(MTFEstimator(patch_size=32), tmp_path / "mtf.pt"))
    x = torch.cat([torch.full((1, 1, 32, 32), fill), _edges(1, 32)])
    out = mtf.predict(x, views=4, precision="bf16")
    assert torch.isfinite(out["mtf"]).all() and out["mtf"].shape == (2, 16)
    assert out["reason"] == [reason, ""] and out["assessable"].tolist() == [False, True]


def _write_description(path, **changes):
    """A camhealth weights file of a fresh Min-Meta network whose description is edited (an older file's)."""
    import json

    export_weights(NoiseSourceEstimator(patch_size=32, metadata_set="minimal"), path)
    obj = torch.load(path, weights_only=True)
    desc = json.loads(obj["description"])
    for key, value in changes.items():
        if key == "inference":
            desc["inference"] = value
        else:
            desc["init_args"][key] = value
    obj["description"] = json.dumps(desc)
    torch.save(obj, path)
    return path


def test_retired_models_and_options_are_refused_with_what_replaced_them(tmp_path):
    for name in ("noise_source_full_gain", "noise_source_full_meta", "noise_source_full_pure"):
        with pytest.raises(ValueError, match="retired: replaced by 'noise_source_full', the physics-first estimator"):
            load_estimator(name)
    with pytest.raises(ValueError, match="renamed 'noise_source_full'"):
        load_estimator("noise_source_physics")
    cases = [
        ({"metadata_set": "full", "physics_prior": True}, "a Full-Meta noise-source network is retired"),
        ({"mismatch_posterior": True}, "retired noise-source option\\(s\\) mismatch_posterior=True"),
        ({"trunk_activation": "leaky_relu"}, "trunk_activation='leaky_relu'"),
        ({"inference": {"posterior_blend": {"weight": 0.7}}}, "inference settings \\['posterior_blend'\\]"),
    ]
    for i, (changes, msg) in enumerate(cases):
        path = _write_description(tmp_path / f"old{i}.pt", **changes)
        with pytest.raises(ValueError, match=msg):
            load_estimator(path)
    # an older Min-Meta file that names retired options at their only remaining value loads as before
    old = _write_description(tmp_path / "older.pt", physics_prior=False, total_branch=False, branch_inputs="own")
    assert load_estimator(old).metadata_set == "minimal"


def test_noise_source_full_is_the_physics_first_estimator():
    from camhealth.estimators.physics_noise import PhysicsNoiseEstimator

    est = load_estimator("noise_source_full")
    assert isinstance(est, PhysicsNoiseEstimator) and est.metadata_set == "full" and est.description["params"] == 0
    assert "noise_source_full" not in shipped_models()  # no weights file


def test_flat_noisy_patches_are_never_assessable_for_mtf():
    """Flat grey patches at any level with white noise σ ≤ 20 DN (8-bit rounded): featureless, although the pixel
    std is up to 20 DN; the noise-corrected structure contrast is what is compared with 2 DN."""
    g = torch.Generator().manual_seed(11)
    for sigma in (1.0, 3.0, 5.0, 10.0, 20.0):
        for level in (0.15, 0.5, 0.85):
            x = (level + sigma / 255.0 * torch.randn(64, 1, 192, 192, generator=g)).clamp(0, 1)
            x = (x * 255).round() / 255
            ok, reason = assess_patches(x, "mtf")
            assert not ok.any() and set(reason) == {"featureless"}, (sigma, level)
            assert assess_patches(x, "noise_source")[0].all()


def test_structure_survives_noise():
    """The structure contrast of a 4 DN sine of 32-px period under 20 DN of noise matches the sine's std 4/√2 DN (it
    is not featureless); a sine has no edges, a square wave under the same noise has."""
    from camhealth._inputs import structure_contrast_dn

    g = torch.Generator().manual_seed(12)
    xx = torch.arange(192, dtype=torch.float64)
    scene = 0.5 + 4.0 / 255.0 * torch.sin(2 * torch.pi * xx / 32)[None, None, None, :].expand(16, 1, 192, 192)
    x = (scene + 20.0 / 255.0 * torch.randn(16, 1, 192, 192, generator=g, dtype=torch.float64)).float()
    s, noise = structure_contrast_dn(x)
    assert torch.allclose(noise, torch.full_like(noise, 20.0), rtol=0.05)
    # block means of a 32-px sine keep sinc(8/32)·(4/√2) ≈ 2.55 DN of it
    assert torch.allclose(s, torch.full_like(s, 4.0 / 2**0.5 * float(torch.sinc(torch.tensor(8 / 32)))), atol=0.6)
    # a single sine has no edges: its contrast and its blur cannot be told apart
    ok, reason = assess_patches(x, "mtf")
    assert not ok.any() and set(reason) == {"no edges"}
    # a square wave of the same period with ±20 DN steps keeps its edges under the same noise
    square = 0.5 + 20.0 / 255.0 * torch.sign(torch.sin(2 * torch.pi * (xx + 0.5) / 32))[None, None, None, :].expand(16, 1, 192, 192)
    y = (square + 20.0 / 255.0 * torch.randn(16, 1, 192, 192, generator=g, dtype=torch.float64)).float()
    assert assess_patches(y, "mtf")[0].all()


def test_mtf_std_is_the_spread_over_views_without_an_error_table(tmp_path):
    mtf = load_estimator(export_weights(MTFEstimator(patch_size=32), tmp_path / "mtf.pt"))
    x = _textured(3, 32)
    one = mtf.predict(x)
    assert one["mtf_std"].shape == (3, 16) and torch.isnan(one["mtf_std"]).all() and torch.isnan(one["mtf_spread"]).all()
    four = mtf.predict(x, views=4)
    flips = torch.stack([mtf.predict(v)["mtf"] for v in (x, x.flip(-1), x.flip(-2), x.flip(-2, -1))])
    assert torch.allclose(four["mtf_spread"], flips.std(0), atol=1e-5)
    assert torch.equal(four["mtf_std"], four["mtf_spread"])
    assert (four["mtf_std"] >= 0).all() and torch.isfinite(four["mtf_std"]).all()
    assert mtf.predict(x[:0], views=2)["mtf_std"].shape == (0, 16)
    assert mtf.predict(x[:0], views=2)["mtf_spread"].shape == (0, 16)


def test_mtf_std_reads_the_files_error_table_and_export_keeps_it(tmp_path):
    """With an error table in the file, mtf_std = √(r(Ĥ)² + spread²) — finite with one view too — and exporting the
    file again carries the table; a malformed table is refused naming the file."""
    from camhealth.estimators.mtf_error import MTFErrorTable
    from camhealth.export import set_description_entries

    path = export_weights(MTFEstimator(patch_size=32), tmp_path / "mtf.pt")
    table = MTFErrorTable((0.0, 0.5, 1.0), (0.02, 0.2, 0.04), 100, "test")
    set_description_entries(path, {"mtf_error": table.to_dict()})
    mtf = load_estimator(path)
    x = _textured(3, 32)
    one, four = mtf.predict(x), mtf.predict(x, views=4)
    torch.testing.assert_close(one["mtf_std"], table(one["mtf"]))
    torch.testing.assert_close(four["mtf_std"], (table(four["mtf"]) ** 2 + four["mtf_spread"] ** 2).sqrt())
    again = load_estimator(export_weights(path, tmp_path / "again.pt"))
    assert again.description["mtf_error"] == table.to_dict()
    torch.testing.assert_close(again.predict(x)["mtf_std"], one["mtf_std"])
    with pytest.raises(ValueError, match=r"cannot be set; allowed: \['mtf_error', 'evaluation'\]"):
        set_description_entries(path, {"metrics": {}})
    set_description_entries(path, {"mtf_error": {**table.to_dict(), "rms": [0.1, 0.1, 2.0]}}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match=r"bad.pt: mtf_error: rms .* allowed range \[0, 1\]"):
        load_estimator(tmp_path / "bad.pt")


def _edges(n: int, size: int, seed: int = 2) -> torch.Tensor:
    """Random 4-px blocks of random gray (edges between them), well above the featureless threshold."""
    import torch.nn.functional as F

    g = torch.Generator().manual_seed(seed)
    return F.interpolate(0.1 + 0.8 * torch.rand(n, 1, size // 4, size // 4, generator=g), size=size, mode="nearest")


def _textured(n: int, size: int, seed: int = 2) -> torch.Tensor:
    """Smooth random texture (blurred noise), well above the featureless threshold."""
    import torch.nn.functional as F

    g = torch.Generator().manual_seed(seed)
    x = F.avg_pool2d(torch.rand(n, 1, size + 3, size + 3, generator=g), 4, stride=1)
    return ((x - x.amin((2, 3), keepdim=True)) / (x.amax((2, 3), keepdim=True) - x.amin((2, 3), keepdim=True))).clamp(0, 1)


def test_mtf_reads_patches_with_their_defective_pixels_repaired():
    """The shipped MTF estimator on blurred rectangles with 0.3 % hot and dead pixels answers as on the same patches
    without them (mean |ΔH| ≤ 0.005 per patch), and says how many it replaced; with the repair switched off the
    impulses move the answer visibly (up to ~0.02)."""
    import torch.nn.functional as F

    from camhealth.bench.robustness import add_defects
    from camhealth.bench.robustness_mtf import swapped_global
    from camhealth.estimators.defective_pixels import defective_pixels

    g = torch.Generator().manual_seed(0)
    x = torch.full((8, 1, 192, 192), 0.3)
    for i in range(8):
        for _ in range(12):
            y0, x0 = torch.randint(0, 170, (2,), generator=g).tolist()
            h, w = torch.randint(8, 60, (2,), generator=g).tolist()
            x[i, 0, y0:y0 + h, x0:x0 + w] = torch.rand(1, generator=g).item()
    k = torch.exp(-0.5 * torch.arange(-4.0, 5.0) ** 2)
    k = k / k.sum()
    x = F.conv2d(F.conv2d(F.pad(x, (4, 4, 4, 4), mode="replicate"), k.view(1, 1, 1, 9)), k.view(1, 1, 9, 1))
    x = (x * 255 + 2 * torch.randn(x.shape, generator=g)).clamp(0, 255).round() / 255
    bad, truth = add_defects(x, 0.003, 1)
    est = load_estimator("mtf")
    clean, repaired = est.predict(x), est.predict(bad)
    assert clean["assessable"].all() and (clean["defects"] == 0).all()
    assert (repaired["defects"].sum(1) >= 0.7 * (truth != 0).flatten(1).sum(1)).all()  # offsets from 10 DN: not all seen
    assert ((repaired["mtf"] - clean["mtf"]).abs().mean(1) <= 0.005).all()
    with swapped_global(type(est).predict, "repair_defective_pixels", lambda p, n=None: (p, defective_pixels(p, n))):
        raw = est.predict(bad)
    assert ((raw["mtf"] - clean["mtf"]).abs().mean(1).max() > 0.01)
    assert est.predict(torch.zeros(0, 1, 192, 192))["defects"].shape == (0, 2)


# ------------------------------------------------------------------ device
def test_device_names_are_checked():
    from camhealth.inference import check_device

    assert check_device(None) == check_device("cpu") == check_device(torch.device("cpu")) == torch.device("cpu")
    with pytest.raises(ValueError, match=r"device = 'gpu' is not a device name; allowed: 'cpu', 'cuda' or 'cuda:N'"):
        check_device("gpu")
    with pytest.raises(ValueError, match=r"device = 'meta'.*allowed are 'cpu', 'cuda' or 'cuda:N'"):
        check_device("meta")
    with pytest.raises(TypeError, match="device must be a str or torch.device, got int"):
        check_device(0)
    if torch.cuda.is_available():
        with pytest.raises(ValueError, match=r"CUDA device index 99 is out of the allowed range \[0, "):
            check_device("cuda:99")
    else:
        with pytest.raises(ValueError, match=r"device = 'cuda': this machine has no CUDA device"):
            load_estimator("mtf", device="cuda")
    for suffix in (".pt2", ".onnx"):  # refused before the file is read: those backends run on the CPU
        with pytest.raises(ValueError, match=rf"{suffix} file, which runs on the CPU only"):
            load_estimator(f"model{suffix}", device="cuda")


def _scene_patches(size: int, batch: int, seed: int) -> torch.Tensor:
    """Edges, shading and noise: patches every estimator reads as assessable, and a flat and a black one."""
    g = torch.Generator().manual_seed(seed)
    x = torch.linspace(0.2, 0.8, size).view(1, 1, 1, size).expand(batch, 1, size, size).clone()
    x[..., size // 3:, size // 2:] += 0.15
    x[-2] = 0.5
    x[-1] = 0.0
    return (x + 0.01 * torch.randn(x.shape, generator=g)).clamp(0, 1)


@pytest.mark.parametrize("name", ["mtf", "drne", "noise_source_min", "noise_source_full"])
def test_predict_on_each_device_gives_the_cpu_answer(device, name):
    """With ``device=`` the network (``noise_source_full``: the posterior) runs there and the outputs come back on the
    CPU: the same flags as on the CPU and values within float32 convolution rounding (TF32 on a GPU)."""
    est = load_estimator(name, device=device)
    assert est.device.type == device.type
    x = _scene_patches(est.patch_size, 5, seed=1)
    meta = None if est.metadata_set == "none" else CameraMetadata.preset("ICX285", gain_db=12.0)
    ref = load_estimator(name).predict(x, metadata=meta)
    for inputs in (x, x.to(device)):  # CPU or device tensors alike
        out = est.predict(inputs, metadata=meta)
        assert out["reason"] == ref["reason"]
        for key, want in ref.items():
            if isinstance(want, torch.Tensor):
                got = out[key]
                assert got.device.type == "cpu" and got.dtype == want.dtype and got.shape == want.shape, key
                if want.is_floating_point():
                    scale = 1.0 if name == "mtf" else 255.0
                    assert torch.allclose(got, want, rtol=2e-3, atol=2e-3 * scale, equal_nan=True), key
                else:
                    assert torch.equal(got, want), key
    if name == "mtf":
        with torch.no_grad():
            assert est.predict(x, precision="bf16")["mtf"].device.type == "cpu"


@pytest.fixture(scope="module")
def exported_pt2(tmp_path_factory):
    """A .pt2 export of an MTF network (patch 32) and its camhealth.json description."""
    import json
    import zipfile

    from camhealth.export import export_pt2

    path = export_pt2(MTFEstimator(patch_size=32), tmp_path_factory.mktemp("pt2") / "mtf.pt2")
    with zipfile.ZipFile(path) as zf:
        (name,) = [n for n in zf.namelist() if n.endswith("extra/camhealth.json")]
        return path, json.loads(zf.read(name))


def _with_description(fmt, exported_pt2, text, out):
    """``out``: a .pt2 (the export with its camhealth.json replaced) or an .onnx (a small graph with an MTF network's
    inputs and outputs) holding ``text``."""
    import zipfile

    if fmt == "pt2":
        with zipfile.ZipFile(exported_pt2[0]) as zin, zipfile.ZipFile(out, "w") as zout:
            for n in zin.namelist():
                zout.writestr(n, text.encode() if n.endswith("extra/camhealth.json") else zin.read(n))
        return out
    import onnx
    from onnx import TensorProto, helper

    # the signature of an MTF graph: patch (B, 1, 32, 32) → mtf (B, 16), the 8×8 block means
    x = helper.make_tensor_value_info("patch", TensorProto.FLOAT, ["b", 1, 32, 32])
    y = helper.make_tensor_value_info("mtf", TensorProto.FLOAT, ["b", 16])
    nodes = [helper.make_node("AveragePool", ["patch"], ["pooled"], kernel_shape=[8, 8], strides=[8, 8]),
             helper.make_node("Flatten", ["pooled"], ["mtf"], axis=1)]
    model = helper.make_model(helper.make_graph(nodes, "g", [x], [y]), opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    entry = model.metadata_props.add()
    entry.key, entry.value = "camhealth.json", text
    onnx.save(model, out)
    return out


@pytest.mark.parametrize("fmt", ["pt2", "onnx"])
def test_exported_descriptions_are_checked_like_a_weights_files(fmt, exported_pt2, tmp_path):
    """The camhealth.json of a .pt2 or .onnx file: malformed JSON, not an object, a bad patch_size, metadata_set or
    onnx_graph is one ValueError naming the file and the field, as for a .pt file."""
    import json

    good = exported_pt2[1]
    est = load_estimator(_with_description(fmt, exported_pt2, json.dumps(good), tmp_path / f"ok.{fmt}"))
    assert est.kind == "mtf" and est.patch_size == 32
    cases = [
        ("{x", "the camhealth.json description is not valid JSON"),
        ("[1]", "the description must be a JSON object, got list"),
        (json.dumps({**good, "patch_size": -5}), "description patch_size = -5 must be a positive integer"),
        (json.dumps({**good, "patch_size": "abc"}), "description patch_size = 'abc' must be a positive integer"),
        (json.dumps({k: v for k, v in good.items() if k != "patch_size"}), "description patch_size = None must be"),
        (json.dumps({**good, "metadata_set": "bogus"}), "description metadata_set = 'bogus' must be 'none', 'minimal'"),
        (json.dumps({**good, "onnx_graph": [1]}), "description onnx_graph must be a JSON object, got list"),
    ]
    for text, match in cases[:3] if fmt == "pt2" else cases:  # (the same check; a .pt2 takes longer to open)
        path = _with_description(fmt, exported_pt2, text, tmp_path / f"bad.{fmt}")
        with pytest.raises(ValueError, match=rf"bad\.{fmt}: {match}"):
            load_estimator(path)


def _redescribed(src, edit, out):
    from tests._evil_files import redescribed

    return redescribed(src, edit, out)


@pytest.mark.parametrize(
    "make,edit,stated,network",
    [
        (lambda: NoiseSourceEstimator(patch_size=32, metadata_set="minimal"), lambda d: d.update(metadata_set="none"),
         "none", "minimal"),
        (lambda: NoiseSourceEstimator(patch_size=32, metadata_set="none"), lambda d: d.update(metadata_set="minimal"),
         "minimal", "none"),
        # a file whose init_args do not give it: the network's default (minimal)
        (lambda: NoiseSourceEstimator(patch_size=32, metadata_set="minimal"),
         lambda d: (d.update(metadata_set="none"), d["init_args"].pop("metadata_set")), "none", "minimal"),
        (lambda: MTFEstimator(patch_size=32), lambda d: d.update(metadata_set="minimal"), "minimal", "none"),
    ],
)
def test_a_description_metadata_set_other_than_the_networks_is_refused(tmp_path, make, edit, stated, network):
    """A Min-Meta network whose description said ``none`` ran without metadata (zeros fed to its metadata inputs) and
    answered wrong; the description's metadata_set must be what the network's init_args build."""
    from camhealth.export import load_module

    path = _redescribed(export_weights(make(), tmp_path / "w.pt"), edit, tmp_path / "edited.pt")
    for load in (load_estimator, load_module):
        with pytest.raises(ValueError, match=rf"edited\.pt: description metadata_set = '{stated}' differs from the "
                                             rf"network's init_args metadata_set = '{network}'"):
            load(path)


def test_the_estimators_metadata_set_is_the_networks(tmp_path):
    """A description without the top-level field: the estimator reads what the network reads (init_args)."""
    path = _redescribed(export_weights(NoiseSourceEstimator(patch_size=32, metadata_set="minimal"), tmp_path / "w.pt"),
                        lambda d: d.pop("metadata_set"), tmp_path / "edited.pt")
    est = load_estimator(path)
    assert est.metadata_set == "minimal"
    with pytest.raises(ValueError, match="reads 'minimal' metadata: pass metadata="):
        est.predict(_patches(2))


@pytest.mark.parametrize("size", [18, 100, 8])
def test_a_description_patch_size_that_is_not_a_multiple_of_16_is_refused(tmp_path, size):
    from camhealth.export import load_module

    def edit(d):
        d["patch_size"] = size
        d["init_args"].pop("patch_size")

    path = _redescribed(export_weights(MTFEstimator(patch_size=32), tmp_path / "w.pt"), edit, tmp_path / "edited.pt")
    for load in (load_estimator, load_module):
        with pytest.raises(ValueError, match=rf"edited\.pt: description patch_size = {size} must be a positive multiple of 16 px"):
            load(path)


def test_both_loaders_read_the_description_patch_size(tmp_path):
    """init_args without patch_size: the inference estimator and the LightningModule take the description's."""
    from camhealth.export import load_module

    def edit(d):
        d["patch_size"] = 48
        d["init_args"].pop("patch_size")

    path = _redescribed(export_weights(MTFEstimator(patch_size=32), tmp_path / "w.pt"), edit, tmp_path / "edited.pt")
    module, _ = load_module(path)
    assert load_estimator(path).patch_size == module.patch_size == 48


def test_pt2_predicts_batches_beyond_its_exported_batch_bound(tmp_path):
    """A .pt2 program's batch dimension ends at MAX_EXPORT_BATCH (4096): ``predict(batch_size=8192)`` runs it in
    chunks no larger (its guard assertion refused 4100 patches) and answers as the weights file does."""
    from camhealth.export import MAX_EXPORT_BATCH, export_pt2
    from lightning_modules import NoiseLevelEstimator

    torch.manual_seed(0)
    module = NoiseLevelEstimator(patch_size=16, width=4, dilations=(1,))
    weights = load_estimator(export_weights(module, tmp_path / "d.pt"))
    pt2 = load_estimator(export_pt2(module, tmp_path / "d.pt2"))
    x = torch.rand(MAX_EXPORT_BATCH + 4, 1, 16, 16, generator=torch.Generator().manual_seed(1))
    out = pt2.predict(x, batch_size=2 * MAX_EXPORT_BATCH)
    assert out["sigma_total"].shape == (MAX_EXPORT_BATCH + 4,)
    ref = weights.predict(x, batch_size=2 * MAX_EXPORT_BATCH)
    assert torch.allclose(out["sigma_total"], ref["sigma_total"], atol=1e-4)


def _relabel_onnx(src, edit, out):
    """A copy of the .onnx file ``src`` whose camhealth.json description ``edit`` changed in place."""
    import json

    import onnx

    model = onnx.load(str(src))
    for prop in model.metadata_props:
        if prop.key == "camhealth.json":
            desc = json.loads(prop.value)
            edit(desc)
            prop.value = json.dumps(desc)
    onnx.save(model, str(out))
    return out


def _as_drne(desc):
    desc.update(kind="drne", class_path="lightning_modules.drne.NoiseLevelEstimator", init_args={"patch_size": 32},
                onnx_graph={"inputs": ["patch"], "outputs": ["sigma_map"]})


@pytest.mark.parametrize("fmt", ["pt2", "onnx"])
def test_an_exported_graph_that_is_not_the_described_estimator_is_refused(fmt, exported_pt2, tmp_path):
    """An MTF graph whose description says ``kind: drne`` loaded and returned the RMS of 16 MTF values as σ [DN]:
    the graph's inputs and outputs are checked against the description's kind and patch size at load time."""
    import json

    if fmt == "pt2":
        desc = dict(exported_pt2[1])
        _as_drne(desc)
        desc.pop("onnx_graph")
        path = _with_description("pt2", exported_pt2, json.dumps(desc), tmp_path / "as_drne.pt2")
    else:
        from camhealth.export import export_onnx

        src = export_onnx(MTFEstimator(patch_size=32), tmp_path / "mtf.onnx")
        assert load_estimator(src).kind == "mtf"
        path = _relabel_onnx(src, _as_drne, tmp_path / "as_drne.onnx")
    with pytest.raises(ValueError, match=rf"as_drne\.{fmt}: the graph's inputs .* and outputs \(\w*\[B, 16\]\) do not "
                                         r"match a 'drne' estimator of patch size 32"):
        load_estimator(path)


def test_onnx_metadata_fields_must_be_the_networks_fields(tmp_path):
    """``onnx_graph.metadata_fields`` of a self-contained noise-source graph: a string or other fields are refused
    at load (not an AttributeError at predict time)."""
    from camhealth.export import export_onnx

    src = export_onnx(NoiseSourceEstimator(patch_size=32, metadata_set="minimal"), tmp_path / "ns.onnx")
    assert load_estimator(src).predict(_patches(2), "ICX285")["sigma"].shape == (2, 3)
    for bad in ("gain", ["gain_db"], ["exposure_s", "gain_db", "temperature_c"]):
        def edit(desc, bad=bad):
            desc["onnx_graph"]["metadata_fields"] = bad

        path = _relabel_onnx(src, edit, tmp_path / "bad.onnx")
        with pytest.raises(ValueError, match=r"bad\.onnx: description onnx_graph metadata_fields = .* must be "
                                             r"\['gain_db', 'exposure_s', 'temperature_c'\]"):
            load_estimator(path)


@pytest.mark.parametrize("name", ["noise_source_min", "noise_source_none"])
def test_noise_source_networks_refuse_what_they_cannot_vouch_for_and_state_no_uncertainty(name):
    """Uniform noise of σ 73.6 DN (beyond the validated 64 DN beyond doubt) and a noiseless 128 DN patch (less than any
    camera in range makes: photon noise alone is ≥ 0.57 DN there) were assessable, with σ_Total 76 and 0.5 DN and
    ξ ≈ 0 whatever the metadata. They are refused with the physics-first estimator's reasons; a patch of 50 DN of
    Gaussian noise is read. ``xi_std`` is NaN: the networks state no uncertainty of their ξ."""
    from camhealth.estimators.physics_noise import BEYOND_VALIDATED, LESS_NOISE

    net = load_estimator(name)
    g = torch.Generator().manual_seed(0)
    x = torch.stack([(torch.rand(1, 128, 128, generator=g) * 255).round() / 255, torch.full((1, 128, 128), 0.5),
                     ((128 + 50 * torch.randn(1, 128, 128, generator=g)).clamp(0, 255).round()) / 255])
    for md, base in (({"gain_db": 6.0, "exposure_s": 0.01, "temperature_c": 25.0}, "ICX285"),
                     ({"gain_db": 24.0, "exposure_s": 0.2, "temperature_c": 80.0}, "EV76C661")):
        out = net.predict(x, md if net.metadata_set != "none" else None, base_preset=base)
        assert out["reason"] == [BEYOND_VALIDATED, LESS_NOISE, ""] and out["assessable"].tolist() == [False, False, True]
        assert out["xi_std"].shape == (3,) and torch.isnan(out["xi_std"]).all()
        assert torch.isfinite(out["xi"]).all() and torch.isfinite(out["sigma"]).all()
    empty = net.predict(torch.zeros(0, 1, 128, 128), {"gain_db": 6.0, "exposure_s": 0.01, "temperature_c": 25.0}
                        if net.metadata_set != "none" else None)
    assert empty["xi_std"].shape == (0,)
    # never a camera in range: ICX285 at 0 dB and the quietest camera the ranges allow (0.16 DN at 10 DN, 0.57 DN at
    # 128 DN), made 8-bit; nor a noiseless patch below 98 DN, where rounding may remove a quiet camera's noise altogether
    from camhealth.bench.sensor_variants import simulate_variant

    quiet = dict(gain_db=0.0, exposure_s=0.001, temperature_c=0.0, dark_fom_na_per_cm2=0.0, full_well_e=100000.0,
                 pixel_clock_hz=8e6, sense_node_gain_v_per_e=5e-6, reset_factor=0.0, pixel_size_um=0.9,
                 white_noise_v_per_rthz=1e-9)
    levels = torch.tensor([20.0, 60.0, 100.0, 128.0, 240.0]).view(-1, 1, 1, 1).expand(-1, 1, 128, 128) / 255
    md = {"gain_db": 0.0, "exposure_s": 0.001, "temperature_c": 0.0}
    for meta in (CameraMetadata.preset("ICX285", gain_db=0.0), CameraMetadata.preset("ICX285", **quiet)):
        noisy, _ = simulate_variant(levels.contiguous(), meta, ("round8",), torch.Generator().manual_seed(2))
        assert net.predict(noisy, md if net.metadata_set != "none" else None, base_preset="ICX285")["reason"] == [""] * 5
    flat = torch.tensor([20.0, 60.0, 97.0]).view(-1, 1, 1, 1).expand(-1, 1, 128, 128) / 255
    assert net.predict(flat.contiguous(), md if net.metadata_set != "none" else None, base_preset="ICX285")["reason"] == [""] * 3



# ------------------------------------------------------------------ audit fixes: refusals and checks
def test_mostly_clipped_patches_are_not_assessable_for_any_shipped_network():
    """45 % crushed black + 45 % blown out, 10 DN of noise: DRNE and the noise-source networks read 0.8 DN and called
    it assessable; the MTF read an 84 %-clipped blur (Gaussian σ 3 px) as sharp, "assessable" at 3.7 of its mtf_std
    off. Now "clipped" — the outputs themselves unchanged."""
    g = torch.Generator().manual_seed(1)
    mean = torch.full((3, 1, 128, 128), 127.5)
    mean[..., :57] = -60.0
    mean[..., 57:114] = 320.0
    x = ((mean + 10 * torch.randn(3, 1, 128, 128, generator=g)) / 255).clamp(0, 1)
    for name, meta in (("drne", None), ("noise_source_none", None), ("noise_source_min", "ICX285")):
        out = load_estimator(name).predict(x, meta)
        assert out["reason"] == ["clipped"] * 3 and not out["assessable"].any(), name
    import torch.nn.functional as F

    yy, xx = torch.meshgrid(torch.arange(192), torch.arange(192), indexing="ij")
    sq = ((((xx + 0.37 * yy) % 64) < 32) ^ (((yy + 0.21 * xx) % 64) < 32)).float()[None, None].repeat(2, 1, 1, 1)
    k = torch.exp(-torch.arange(-12, 13).float() ** 2 / 18)
    k = k / k.sum()
    b = F.conv2d(F.conv2d(F.pad(sq, (12,) * 4, mode="reflect"), k.view(1, 1, 1, -1)), k.view(1, 1, -1, 1))
    nz = 2 / 255 * torch.randn(b.shape, generator=g)
    mtf = load_estimator("mtf")
    assert mtf.predict((0.3 + 0.4 * b + nz).clamp(0, 1))["reason"] == ["", ""]
    assert mtf.predict((-1 + 3 * b + nz).clamp(0, 1))["reason"] == ["clipped", "clipped"]


def test_drne_refuses_noise_beyond_the_validated_range_as_every_noise_estimator_does():
    """DRNE read 120 DN of noise as 92 DN and 200 DN as 107 DN, assessable; the noise-source networks and the
    physics-first estimator refuse them (beyond_validated_range). DRNE now does too; 30 DN is read as before."""
    from camhealth.estimators.physics_noise import BEYOND_VALIDATED

    g = torch.Generator().manual_seed(1)
    drne, other = load_estimator("drne"), load_estimator("noise_source_none")
    for sigma, want in ((30.0, ""), (120.0, BEYOND_VALIDATED), (200.0, BEYOND_VALIDATED)):
        x = (0.5 + sigma / 255 * torch.randn(2, 1, 128, 128, generator=g)).clamp(0, 1)
        out = drne.predict(x)
        assert out["reason"] == [want] * 2 and out["assessable"].tolist() == [not want] * 2, sigma
        assert other.predict(x)["reason"] == out["reason"]
        assert torch.isfinite(out["sigma_total"]).all()


@pytest.mark.parametrize("name", ["drne", "mtf", "noise_source_none"])
def test_metadata_given_to_an_estimator_that_reads_none_is_checked(name):
    """``metadata=`` given to an estimator that reads none was dropped unchecked: a −5 s exposure, a mistyped preset, a
    missing file or a number passed. It is checked as for the networks that read it (full and empty batches), and
    valid metadata change nothing."""
    est = load_estimator(name)
    p = est.patch_size
    x = (0.5 + 5 / 255 * torch.randn(2, 1, p, p, generator=torch.Generator().manual_seed(0))).clamp(0, 1)
    for patches in (x, x[:0]):
        with pytest.raises(ValueError, match=r"gain_db.*= 1000 dB is out of the allowed range"):
            est.predict(patches, {"gain_db": 1000, "exposure_s": -5})
        with pytest.raises(ValueError, match="unknown sensor preset 'NOPE'"):
            est.predict(patches, "NOPE")
        with pytest.raises(FileNotFoundError, match="nonexistent.yaml"):
            est.predict(patches, "/nonexistent.yaml")
        with pytest.raises(TypeError, match="metadata must be"):
            est.predict(patches, 12345)
    with pytest.raises(ValueError, match="batch size 3"):
        est.predict(x, CameraMetadata.preset("ICX285", batch_size=3))
    ref = est.predict(x)
    for meta in ("ICX285", {"gain_db": 12.0}, CameraMetadata.preset("EV76C661", batch_size=2)):
        out = est.predict(x, meta)
        for key, value in ref.items():
            if isinstance(value, list):
                assert out[key] == value, key
            else:  # bit for bit (NaN where the estimator states no uncertainty)
                torch.testing.assert_close(out[key], value, rtol=0, atol=0, equal_nan=True)


@pytest.mark.parametrize("bad", [True, 1.0, 2.0, "2", np.bool_(True)])
def test_views_must_be_an_integer(tmp_path, bad):
    """``views=True`` (and 1.0) were accepted as 1 (``True in (1, 2, 4)``)."""
    mtf = load_estimator(export_weights(MTFEstimator(patch_size=32), tmp_path / "mtf.pt"))
    with pytest.raises(ValueError, match=rf"views = {re.escape(repr(bad))} must be 1, 2 or 4 \(an integer\)"):
        mtf.predict(torch.rand(1, 1, 32, 32), views=bad)
    y = torch.rand(2, 1, 32, 32)
    assert torch.equal(mtf.predict(y, views=np.int64(2))["mtf"], mtf.predict(y, views=2)["mtf"])


@pytest.mark.parametrize("bad", [None, 5, b"mtf", ["mtf"]])
def test_load_estimator_names_the_shipped_models_for_what_is_no_name_or_path(bad):
    with pytest.raises(TypeError, match=r"must be a shipped model's name \(a str: \['drne', 'mtf', 'noise_source_full'"):
        load_estimator(bad)


def test_load_estimator_takes_any_path_like(tmp_path):
    import os

    class P(os.PathLike):
        def __init__(self, p):
            self.p = p

        def __fspath__(self):
            return str(self.p)

    path = export_weights(MTFEstimator(patch_size=32), tmp_path / "mtf.pt")
    assert load_estimator(P(path)).kind == "mtf"


def test_weights_finite_in_the_file_but_not_in_float32_are_refused_at_load(tmp_path):
    """float64 weights × 1e300 are finite in the file and ±inf in the float32 network: the file loaded and predict then
    blamed the input ("please report this input"). Refused at load, naming the file, the entry and the conversion."""
    from camhealth.export import load_module

    path = export_weights(MTFEstimator(patch_size=32), tmp_path / "w.pt")
    obj = torch.load(path, weights_only=True)
    obj["state_dict"] = {k: v.double() * 1e300 if v.is_floating_point() else v for k, v in obj["state_dict"].items()}
    torch.save(obj, tmp_path / "big.pt")
    for load in (load_estimator, load_module):
        with pytest.raises(ValueError, match=r"big\.pt: state_dict entry '[\w.]+' holds \d+ non-finite value\(s\) of \d+ "
                                             r"after conversion to float32 \(the file's float64 values"):
            load(tmp_path / "big.pt")
    # float64 weights within float32's range load and answer as the float32 file does
    obj["state_dict"] = {k: v / 1e300 for k, v in obj["state_dict"].items()}
    torch.save(obj, tmp_path / "f64.pt")
    y = torch.rand(2, 1, 32, 32)
    torch.testing.assert_close(load_estimator(tmp_path / "f64.pt").predict(y)["mtf"], load_estimator(path).predict(y)["mtf"])


def test_a_non_finite_weight_in_an_exported_program_is_refused_at_load(exported_pt2, tmp_path):
    """A NaN weight payload in a .pt2 loaded, and predict said "produced non-finite outputs; please report this input"."""
    import zipfile

    import numpy as np

    out = tmp_path / "nan.pt2"
    with zipfile.ZipFile(exported_pt2[0]) as zin, zipfile.ZipFile(out, "w") as zout:
        for n in zin.namelist():
            data = zin.read(n)
            zout.writestr(n, np.full(len(data) // 4, np.nan, np.float32).tobytes() if n.endswith("weights/weight_0") else data)
    with pytest.raises(ValueError, match=r"nan\.pt2: the exported program's weight '[\w.]+' holds \d+ NaN or infinite"):
        load_estimator(out)


def _small_onnx(out, text, scale):
    """An .onnx graph with an MTF network's signature whose output is scaled by the initializer ``scale``."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    x = helper.make_tensor_value_info("patch", TensorProto.FLOAT, ["b", 1, 32, 32])
    y = helper.make_tensor_value_info("mtf", TensorProto.FLOAT, ["b", 16])
    nodes = [helper.make_node("AveragePool", ["patch"], ["pooled"], kernel_shape=[8, 8], strides=[8, 8]),
             helper.make_node("Flatten", ["pooled"], ["flat"], axis=1),
             helper.make_node("Mul", ["flat", "scale"], ["mtf"])]
    init = numpy_helper.from_array(np.full((1, 16), scale, np.float32), "scale")
    model = helper.make_model(helper.make_graph(nodes, "g", [x], [y], [init]), opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    entry = model.metadata_props.add()
    entry.key, entry.value = "camhealth.json", text
    onnx.save(model, out)
    return out


def test_a_non_finite_onnx_initializer_is_refused_at_load(exported_pt2, tmp_path):
    import json

    text = json.dumps(exported_pt2[1])
    assert load_estimator(_small_onnx(tmp_path / "ok.onnx", text, 0.5)).kind == "mtf"
    with pytest.raises(ValueError, match=r"nan\.onnx: the ONNX initializer 'scale' holds 16 NaN or infinite value\(s\) of 16"):
        load_estimator(_small_onnx(tmp_path / "nan.onnx", text, float("nan")))


@pytest.mark.parametrize("fmt", ["pt2", "onnx"])
def test_exported_descriptions_of_another_version_deep_or_with_huge_numbers_are_refused(fmt, exported_pt2, tmp_path):
    """A description of format version 42 loaded; one nested 50 000 deep raised a bare RecursionError, one with a
    5 000-digit patch size "Exceeds the limit (4300 digits)" without the file's name; metrics and params were never
    checked. Each is one ValueError naming the file."""
    import json

    good = exported_pt2[1]
    assert good["version"] == 1
    cases = [
        (json.dumps({**good, "version": 42}), r"description version = 42 is not a format version this camhealth reads "
                                              r"\(only 1\)"),
        ("[" * 50000 + "]" * 50000, "the camhealth.json description nests JSON deeper than Python's recursion limit"),
        (json.dumps(good).replace('"patch_size": 32', '"patch_size": ' + "9" * 5000),
         r"the camhealth.json description cannot be read: Exceeds the limit \(4300 digits\)"),
        (json.dumps({**good, "metrics": [1, 2]}), "description metrics must be a JSON object of numbers or null"),
        (json.dumps({**good, "params": "many"}), "description params = 'many' must be a non-negative integer"),
    ]
    for text, match in cases:
        path = _with_description(fmt, exported_pt2, text, tmp_path / f"bad.{fmt}")
        with pytest.raises(ValueError, match=rf"bad\.{fmt}: {match}"):
            load_estimator(path)


def test_a_deep_graph_in_an_exported_program_is_refused_naming_the_entry(exported_pt2, tmp_path):
    import zipfile

    out = tmp_path / "deep.pt2"
    with zipfile.ZipFile(exported_pt2[0]) as zin, zipfile.ZipFile(out, "w") as zout:
        for n in zin.namelist():
            data = zin.read(n)
            if n.endswith("models/model.json"):
                data = data[:-1] + b',"x":' + b"[" * 50000 + b"]" * 50000 + b"}"
            zout.writestr(n, data)
    with pytest.raises(ValueError, match=r"deep\.pt2: refused to load this \.pt2 archive: models/model\.json nests JSON "
                                         r"deeper than Python's recursion limit"):
        load_estimator(out)


def test_predict_says_the_weights_may_be_at_fault_when_outputs_are_not_finite(tmp_path, monkeypatch):
    """Non-finite outputs from finite input are the network's arithmetic: the message names the weights file as a
    possible cause instead of asking only for the input."""
    est = load_estimator(export_weights(MTFEstimator(patch_size=32), tmp_path / "mtf.pt"))
    monkeypatch.setattr(est, "_run", lambda *x, **kw: torch.full((x[0].shape[0], 16), float("inf")))
    with pytest.raises(FloatingPointError, match=r"produced 32 non-finite output value\(s\) of 32 from finite input.*"
                                                 r"mtf\.pt\) were finite when loaded"):
        est.predict(torch.rand(2, 1, 32, 32))
