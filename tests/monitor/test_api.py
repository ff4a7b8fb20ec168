"""Monitor API: frames in, FrameReport/JSON out; skips, reuse, aggregation, ξ alarm, advice, clear errors."""

import json
import math
import warnings

import numpy as np
import pytest
import torch

from camhealth.monitor import Monitor, as_frame, load_metadata, xi_alarm
from camhealth.monitor.api import CAUSE_WORDS, cause_text
from camhealth.monitor.diagnostics import OK, key_values
from camhealth.physics import CameraMetadata
from tests.monitor.conftest import FakeMTF, FakeNoise, noisy


def _strict(line: str) -> dict:
    def bad(x):
        raise ValueError(f"non-strict JSON constant {x}")

    return json.loads(line, parse_constant=bad)


# ------------------------------------------------------------------ frames
@pytest.mark.parametrize("kind", ["uint8", "uint16", "float32", "float64", "rgb_uint8", "torch_chw", "torch_1chw", "torch_uint8"])
def test_as_frame_accepts(kind):
    g = np.random.default_rng(0)
    base = g.random((40, 60))
    x = {
        "uint8": (base * 255).round().astype(np.uint8),
        "uint16": (base * 65535).round().astype(np.uint16),
        "float32": base.astype(np.float32),
        "float64": base,
        "rgb_uint8": np.repeat((base * 255).round().astype(np.uint8)[..., None], 3, axis=2),
        "torch_chw": torch.from_numpy(base).float()[None].repeat(3, 1, 1),
        "torch_1chw": torch.from_numpy(base).float()[None, None],
        "torch_uint8": torch.from_numpy((base * 255).round().astype(np.uint8)),
    }[kind]
    f = as_frame(x)
    assert f.shape == (1, 1, 40, 60) and f.dtype == torch.float32
    assert torch.allclose(f[0, 0], torch.from_numpy(base).float(), atol=0.5 / 255 + 1e-6)


@pytest.mark.parametrize("x,err,match", [
    (np.full((8, 8), np.nan, dtype=np.float32), ValueError, "non-finite"),
    (np.full((8, 8), 3.0, dtype=np.float32), ValueError, r"\[0, 1\].*DN"),
    (np.full((8, 8), 300, dtype=np.int32), ValueError, "8-bit DN"),
    (np.zeros((8, 8), dtype=bool), TypeError, "numeric"),
    (np.zeros((2, 3, 8, 8), dtype=np.uint8), ValueError, "H×W"),
    (torch.zeros(2, 1, 8, 8), ValueError, "one frame at a time"),
    (torch.zeros(0, 8), ValueError, "empty"),
    ([[0.5]], TypeError, "torch.Tensor or numpy"),
])
def test_as_frame_rejects(x, err, match):
    with pytest.raises(err, match=match):
        as_frame(x)


# ------------------------------------------------------------------ metadata
def test_load_metadata_forms(tmp_path):
    full = CameraMetadata.preset("ICX285", gain_db=6.0).to_dict()
    full = {k: v[0] for k, v in full.items()}
    m = load_metadata(full)
    assert float(m.gain_db[0]) == 6.0 and m.batch_size == 1
    (tmp_path / "m.json").write_text(json.dumps(full))
    assert float(load_metadata(tmp_path / "m.json").gain_db[0]) == 6.0
    (tmp_path / "m.yaml").write_text("sensor: EV76C661\ngain_db: 18\nexposure_s: 0.02\n")
    m = load_metadata(tmp_path / "m.yaml")
    assert float(m.gain_db[0]) == 18.0 and float(m.is_cmos[0]) == 1.0
    assert float(load_metadata(None, "ICX285").gain_db[0]) == 0.0
    assert load_metadata(None) is None
    m = load_metadata({"gain_db": 3.0, "exposure_s": 0.01, "temperature_c": 30.0}, required="minimal")
    assert float(m.gain_db[0]) == 3.0  # other fields are not read by a Min-Meta network


@pytest.mark.parametrize("data,required,match", [
    ({"gain_db": 3.0}, "full", r"missing field\(s\) \['exposure_s'"),
    ({"gain_db": 3.0}, "minimal", r"missing field\(s\) \['exposure_s', 'temperature_c'\]"),
    ({"sensor": "ICX285", "gain_db": 40.0}, "full", r"gain_db\[0\] = 40 dB is out of the allowed range \[0, 24\] dB"),
    ({"sensor": "ICX285", "exposure_s": 5}, "full", r"exposure_s.*\[0.001, 0.2\] s"),
    ({"sensor": "ICX285", "gain": 3.0}, "full", "unknown metadata field"),
    ({"sensor": "ICX285", "gain_db": "high"}, "full", "must be a number"),
    ({"sensor": "NOPE"}, "full", "unknown sensor preset"),
])
def test_load_metadata_errors(data, required, match):
    with pytest.raises(ValueError, match=match):
        load_metadata(data, required=required)


def test_load_metadata_file_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        load_metadata(tmp_path / "missing.yaml")
    (tmp_path / "bad.json").write_text("{gain_db: ")
    with pytest.raises(ValueError, match="cannot parse"):
        load_metadata(tmp_path / "bad.json")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(ValueError, match="mapping"):
        load_metadata(tmp_path / "list.yaml")
    (tmp_path / "m.txt").write_text("gain_db: 1")
    with pytest.raises(ValueError, match=".json, .yaml"):
        load_metadata(tmp_path / "m.txt")
    (tmp_path / "m.png").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")  # binary: refused by its suffix, not decoded
    with pytest.raises(ValueError, match=r"m.png must be .json, .yaml or .yml, got '.png'"):
        load_metadata(tmp_path / "m.png")
    (tmp_path / "latin1.yaml").write_bytes("sensor: ICX285\ntemperature_c: 40 # 40 °C\n".encode("latin-1"))
    with pytest.raises(ValueError, match=r"latin1.yaml is not UTF-8 text: byte 0xb0 at position \d+"):
        load_metadata(tmp_path / "latin1.yaml")


# ------------------------------------------------------------------ monitor behaviour
def _monitor(noise=None, mtf=None, **kw):
    kw.setdefault("sensor", "ICX285")
    kw.setdefault("mode", "map")  # the per-patch behaviour these tests check; sampled mode: test_sampled.py
    return Monitor(noise_model=noise if noise is not None else FakeNoise(), mtf_model=mtf if mtf is not None else FakeMTF(), **kw)


def test_report_on_street_frames(street_frames):
    mon = _monitor(precision="fp32")
    for i, f in enumerate(street_frames[:2]):
        r = mon.process(noisy(f, 3.0, seed=i), index=i, source_id="street")
        d = _strict(r.to_json())
        assert d["frame"] == i and d["size"] == [768, 576] and d["assessable"]
        n, m = d["noise"], d["mtf"]
        assert n["grid"] == [4, 6] and m["grid"] == [3, 4]
        assert sum(v for k, v in n["patches"].items() if k != "total") == n["patches"]["total"] == 24
        for name in ("pn", "dcsn", "rn", "xi", "total"):
            assert set(n["sigma_dn"][name]) == {"median", "spread", "temporal_spread", "current", "uncertainty", "estimator_std"}
            assert n["sigma_dn"][name]["estimator_std"] is None  # the fake states no uncertainty of its own
        assert n["sigma_dn"]["total"]["median"] == pytest.approx(3.0, rel=0.35)  # fake = robust σ of the patch
        assert len(m["h"]["median"]) == 8 and len(m["v"]["median"]) == 8 and 0 < m["indicator"]["median"] <= 1
        assert d["alarm"]["state"] == "ok" and d["advice"] is None
        assert d["metadata"] == {"gain_db": 0.0, "exposure_s": 0.01, "temperature_c": 25.0}
        assert set(d["timing_ms"]) == {"convert", "noise", "mtf", "aggregate", "total"}
    s = mon.summary()
    assert s["frames"] == 2 and s["alarms"] == {"ok": 2} and s["patches"]["noise"]["estimated"] > 0


@pytest.mark.parametrize("value", [0.0, 1.0])
@pytest.mark.parametrize("dtype", ["uint8", "float32"])
def test_black_and_white_frames_are_not_assessable(value, dtype):
    fn, fm = FakeNoise(), FakeMTF()
    mon = _monitor(fn, fm)
    x = np.full((576, 768), value, dtype=np.float32)
    if dtype == "uint8":
        x = (x * 255).astype(np.uint8)
    d = _strict(mon.process(x).to_json())
    assert d["assessable"] is False
    assert d["noise"]["assessable"] is False and d["noise"]["sigma_dn"] is None
    assert d["mtf"]["assessable"] is False and d["mtf"]["h"] is None and d["mtf"]["indicator"] is None
    reason = "black" if value == 0 else "saturated"
    assert d["noise"]["patches"][reason] == 24 and d["mtf"]["patches"][reason] == 12
    assert reason in d["noise"]["note"]
    assert d["alarm"]["state"] == "not_assessable"
    assert fn.patches == 0 and fm.patches == 0  # nothing was sent to a network


def test_frame_smaller_than_one_patch_is_a_documented_skip():
    mon = _monitor()
    d = _strict(mon.process(torch.rand(100, 150)).to_json())
    assert d["assessable"] is False and d["noise"]["grid"] == [0, 1] and d["mtf"]["grid"] == [0, 0]
    assert "smaller than one 128-px patch" in d["noise"]["note"] and "192-px" in d["mtf"]["note"]
    # noise fits, MTF does not
    d = _strict(mon.process(noisy(torch.full((1, 150, 170), 0.5), 3.0, seed=0)).to_json())
    assert d["noise"]["assessable"] and not d["mtf"]["assessable"]


def test_skips_are_counted_and_featureless_only_for_blur(street_frames):
    fn, fm = FakeNoise(), FakeMTF()
    mon = _monitor(fn, fm, adaptive=False)
    x = noisy(street_frames[0], 2.0, seed=0).clone()
    x[..., :, :384] = 0.0  # left half black
    x[..., 384:, 384:] = 0.45  # flat bottom-right: two MTF patches (192 px), noise added below
    x = noisy(x, 2.0, seed=1)
    x[..., :, :384] = 0.0
    d = mon.process(x).to_dict()
    assert d["noise"]["patches"]["black"] == 12 and d["mtf"]["patches"]["black"] == 6
    assert d["mtf"]["patches"]["featureless"] == 2 and d["noise"]["patches"]["featureless"] == 0
    informative = d["noise"]["patches"]["estimated"]
    assert fn.patches == informative == 12
    assert fm.patches == d["mtf"]["patches"]["estimated"]


def test_static_regions_are_reused_and_refreshed(street_frames):
    fn = FakeNoise()
    mon = _monitor(fn, FakeMTF(), selection=None)
    scene = street_frames[0]
    mon.process(noisy(scene, 3.0, seed=0))
    first = fn.patches
    assert first == 24 - mon._last.noise.counts["interpolated"]
    r = mon.process(noisy(scene, 3.0, seed=1))  # same scene, new noise realisation
    c = r.noise.counts
    assert c["reused"] >= 18 and fn.patches - first == c["estimated"] <= 6
    assert c["estimated"] + c["interpolated"] + c["reused"] == 24
    # a change of metadata restarts everything
    r = mon.process(noisy(scene, 3.0, seed=2), metadata={"gain_db": 12.0})
    assert r.noise.counts["reused"] == 0 and r.metadata["gain_db"] == 12.0
    assert float(fn.last_metadata.gain_db[0]) == 12.0


def test_run_over_a_source(tmp_path):
    import cv2

    folder = tmp_path / "frames"
    folder.mkdir()
    g = np.random.default_rng(0)
    assert cv2.imwrite(str(folder / "f1.png"), g.integers(30, 220, (200, 260), dtype=np.uint8))
    (folder / "f2.png").write_bytes(b"broken")
    mon = _monitor(FakeNoise(), None)
    out = list(mon.run(folder))
    assert [item.index for item, _ in out] == [0, 1]
    assert out[0][1].noise.assessable and out[1][1] is None and "cannot read image" in out[1][0].error
    assert mon.frames == 1


def test_not_adaptive_estimates_every_informative_patch(street_frames):
    fn = FakeNoise()
    mon = _monitor(fn, FakeMTF(), adaptive=False)
    for i in range(2):
        r = mon.process(noisy(street_frames[0], 3.0, seed=i))
        assert r.noise.counts["estimated"] == 24 and r.noise.counts["reused"] == 0
    assert fn.patches == 48


def test_no_skipping_sends_black_patches_to_the_estimator():
    fn = FakeNoise()
    mon = _monitor(fn, FakeMTF(), skip_uninformative=False, adaptive=False)
    d = mon.process(np.zeros((300, 300), np.uint8)).to_dict()
    assert fn.patches == 4 and d["noise"]["patches"]["not_assessable"] == 4 and not d["noise"]["assessable"]


def test_temporal_median_ignores_an_outlier_frame():
    # the fake returns σ_total 2, 2, 9, 2, 2 … per call: the window-3 median stays 2, the spread shows it
    fn = FakeNoise(values=[2.0, 2.0, 9.0, 2.0, 2.0])
    mon = _monitor(fn, FakeMTF(), adaptive=False, window=3)
    x = noisy(torch.full((1, 256, 256), 0.5), 3.0, seed=0)
    out = [mon.process(x).noise for _ in range(4)]
    assert out[2].value("total") == pytest.approx(2.0) and out[2].current[4] == pytest.approx(9.0)
    assert float(out[2].temporal_spread[4]) == pytest.approx(0.0)  # MAD of (2, 2, 9) is 0
    assert out[3].value("total") == pytest.approx(2.0)
    assert out[1].value("total") == pytest.approx(2.0)


@pytest.mark.parametrize("xi,state", [(0.0, "ok"), (-3.0, "noisier"), (3.0, "cleaner")])
def test_xi_alarm_states(street_frames, xi, state):
    mon = _monitor(FakeNoise(xi_dn=xi), FakeMTF())
    d = mon.process(noisy(street_frames[0], 3.0, seed=0)).to_dict()
    assert d["alarm"]["state"] == state and d["alarm"]["xi_dn"] == pytest.approx(xi)
    if state != "ok":
        assert ("noisier" if xi < 0 else "cleaner") in d["alarm"]["message"]


@pytest.mark.parametrize("source,hinted", [("largest value", True), ("sequence", True), ("given", False), ("sBIT", False)])
@pytest.mark.parametrize("xi", [-3.0, 3.0, 0.0])
def test_a_mismatch_on_a_guessed_scale_names_the_bit_depth(street_frames, source, hinted, xi):
    """A 12-bit camera whose frames stay below 1023 is read as 10-bit data (÷1023) when the depth is guessed: 4× too
    bright, its noise too. A "noisier" or "cleaner" alarm on a guessed scale says so and names --bit-depth; a declared
    scale (given, sBIT) or an "ok" frame says nothing of it."""
    from camhealth.data.io import ImageScaling
    from camhealth.monitor.api import GUESSED_SCALE_HINT

    mon = _monitor(FakeNoise(xi_dn=xi), FakeMTF())
    scaling = ImageScaling(16, 10, source, 811.0)
    d = mon.process(noisy(street_frames[0], 3.0, seed=0), input_scaling=scaling).to_dict()
    expected = "ok" if xi == 0 else "noisier" if xi < 0 else "cleaner"
    assert d["alarm"]["state"] == expected
    hint = GUESSED_SCALE_HINT.format(scale=scaling.describe())
    assert (hint in d["alarm"]["message"]) == (hinted and xi != 0), d["alarm"]["message"]
    if hinted and xi != 0:
        assert "--bit-depth N" in d["alarm"]["message"] and "÷1023" in d["alarm"]["message"]


def test_xi_alarm_function():
    assert xi_alarm(-2.0, 0.1, 20)["state"] == "noisier"
    assert xi_alarm(-2.0, 10.0, 20)["state"] == "ok"  # not significant: 3 standard errors ≈ 8.4 DN
    assert xi_alarm(0.5, 0.1, 20, threshold_dn=1.0)["state"] == "ok"
    a = xi_alarm(float("nan"), float("nan"), 0)
    assert a["state"] == "not_assessable" and a["xi_dn"] is None


def test_drne_kind_gives_total_only(street_frames):
    class FakeDRNE(FakeNoise):
        kind = "drne"
        metadata_set = "none"

        def predict(self, patches, metadata=None, **kw):
            out = super().predict(patches, metadata, **kw)
            return {"sigma_total": out["sigma_total"], "assessable": out["assessable"]}

    mon = Monitor(FakeDRNE(), FakeMTF())  # no metadata needed
    d = _strict(mon.process(noisy(street_frames[0], 3.0, seed=0)).to_json())
    s = d["noise"]["sigma_dn"]
    assert s["total"]["median"] > 0 and s["pn"]["median"] is None and s["xi"]["median"] is None
    assert d["alarm"]["state"] == "unavailable"


def noise_sensitive_iopc(tmp_path):
    """An IOPC file whose AP falls with σ only (horizontal motion: MTF̃ = (1 + |sinc(0.05 L)|)/2)."""
    from camhealth.iopc import IOPC

    recs = []
    for s in (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0):
        for length in (0.0, 3.0, 7.0, 11.0, 15.0, 21.0):
            m = 0.5 * (1.0 + abs(float(np.sinc(0.05 * length))))
            recs.append({"index": len(recs), "key": f"L{length}_s{s}", "length_px": length, "angle_deg": 0.0,
                         "noise_level_dn": s, "sigma_tilde": s, "mtf_tilde": m, "ap": 1.0 - s / 30.0})
    return IOPC.from_records(recs, name="noise-sensitive").save(tmp_path / "iopc.json")


def test_advice_from_an_iopc_policy(street_frames, tmp_path):
    from camhealth.iopc import IOPC

    path = noise_sensitive_iopc(tmp_path)
    assert isinstance(IOPC.load(path), IOPC)
    mon = _monitor(policy=path, metadata={"gain_db": 18.0}, sensor="ICX285")
    d = _strict(mon.process(noisy(street_frames[0], 6.0, seed=0)).to_json())
    a = d["advice"]
    assert a["available"] and a["alpha"] < 1 and a["gain_db"] < 18.0 and a["exposure_s"] > 0.01  # less gain, longer exposure
    assert "IOPC" in a["explanation"]
    d = _strict(mon.process(np.zeros((576, 768), np.uint8)).to_json())
    assert d["advice"] == {"available": False, "reason": "blur or noise not assessable in this frame"}


def test_monitor_errors(model_files):
    ns, mtf = model_files
    with pytest.raises(ValueError, match="reads 'minimal' metadata"):
        Monitor(ns, mtf)
    with pytest.raises(ValueError, match="kind noise_source or drne"):
        Monitor(mtf, None, sensor="ICX285")
    with pytest.raises(ValueError, match="kind mtf"):
        Monitor(None, FakeNoise())
    with pytest.raises(ValueError, match="nothing to monitor"):
        Monitor(None, None)
    with pytest.raises(ValueError, match="window"):
        Monitor(FakeNoise(), None, sensor="ICX285", window=0)
    with pytest.raises(ValueError, match="precision"):
        Monitor(FakeNoise(), None, sensor="ICX285", precision="fp16")
    with pytest.raises(ValueError, match="mtf_views = 3 must be 1, 2 or 4"):
        Monitor(FakeNoise(), None, sensor="ICX285", mtf_views=3)
    with pytest.raises(FileNotFoundError, match="shipped names"):
        Monitor("no_such_model", None, sensor="ICX285")
    with pytest.raises(ValueError, match="device = 'tpu' is not a device name"):
        Monitor("noise_source_full", None, sensor="ICX285", device="tpu")
    class BlindNoise(FakeNoise):
        metadata_set = "none"

    class Policy:
        def decide(self, *args, **kwargs):
            raise AssertionError("not reached")

    with pytest.raises(ValueError, match="needs the current exposure"):
        Monitor(BlindNoise(), FakeMTF(), policy=Policy())
    with pytest.raises(TypeError, match="decide"):
        Monitor(FakeNoise(), FakeMTF(), sensor="ICX285", policy=object())
    mon = Monitor(FakeNoise(), None, sensor="ICX285")
    with pytest.raises(ValueError, match="per-frame metadata"):
        mon.process(torch.rand(128, 128), metadata={"gain_db": 99.0})


@pytest.mark.parametrize("precision", ["bf16", "fp32"])
def test_real_exported_models(model_files, street_frames, precision):
    """The monitor drives the real Estimator (untrained weights: behaviour only) end to end."""
    ns, mtf = model_files
    mon = Monitor(ns, mtf, sensor="ICX285", precision=precision, per_patch=True)
    d = _strict(mon.process(noisy(street_frames[0], 3.0, seed=0)).to_json())
    assert d["noise"]["assessable"] and d["mtf"]["assessable"]
    assert d["noise"]["estimator"].startswith("ns (noise_source, 128 px, minimal")
    assert all(math.isfinite(v) for v in d["mtf"]["h"]["median"])
    pp = d["noise"]["per_patch"]
    assert len(pp["status"]) == 24 and len(pp["values"]) == 24 and len(pp["values"][0]) == 5


def test_policy_option_errors_clearly_without_camhealth_control(monkeypatch, tmp_path):
    import sys

    from camhealth.monitor import load_policy

    monkeypatch.setitem(sys.modules, "camhealth.control", None)  # as if the package were not importable
    with pytest.raises(ImportError, match="needs camhealth.control"):
        load_policy([tmp_path / "iopc.json"])


def test_warm_up_runs_every_bucket_once_before_the_first_frame(model_files, monkeypatch):
    from camhealth.inference import Estimator, bucket_size

    ns, mtf = model_files
    sizes = []
    orig = Estimator.predict
    monkeypatch.setattr(Estimator, "predict", lambda self, x, *a, **k: sizes.append((self.kind, x.shape[0])) or orig(self, x, *a, **k))
    mon = Monitor(ns, mtf, sensor="ICX285", mode="map")  # 384×576 frame: 3×4 noise patches, 2×3 MTF patches
    mon.process(torch.full((384, 576), 0.5))
    # warm-up first: each network once per bucket size up to its grid (12 noise, 6 MTF patches), then the frame
    assert sizes[:5] == [("noise_source", 4), ("noise_source", 8), ("noise_source", 12), ("mtf", 4), ("mtf", 6)]
    assert {min(bucket_size(n), 12) for n in range(1, 13)} == {4, 8, 12}
    sizes.clear()
    Monitor(ns, mtf, sensor="ICX285", mode="map", warmup=False).process(torch.full((384, 576), 0.5))
    assert len(sizes) <= 4  # only the frame's own network calls


def test_mtf_views_reach_the_mtf_estimator_and_its_warm_up(model_files, street_frames, monkeypatch):
    """``mtf_views=2``: every MTF call (warm-up included) asks for 2 views, the noise estimator is called as
    before, and only the MTF result changes."""
    from camhealth.inference import Estimator

    ns, mtf = model_files
    calls = []
    orig = Estimator.predict
    monkeypatch.setattr(Estimator, "predict", lambda self, x, *a, **k: calls.append((self.kind, k.get("views"))) or orig(self, x, *a, **k))
    frame = noisy(street_frames[0], 3.0, seed=0)
    mon = Monitor(ns, mtf, sensor="ICX285", mtf_views=2, per_patch=True, adaptive=False)
    d = _strict(mon.process(frame).to_json())
    assert {v for kind, v in calls if kind == "mtf"} == {2} and {v for kind, v in calls if kind != "mtf"} == {None}
    assert d["mtf"]["assessable"]
    one = _strict(Monitor(ns, mtf, sensor="ICX285", per_patch=True, adaptive=False).process(frame).to_json())
    assert d["mtf"]["h"]["median"] != one["mtf"]["h"]["median"]  # the views do change the estimate
    assert d["noise"]["per_patch"]["values"] == one["noise"]["per_patch"]["values"]  # and only the MTF
    assert mon.summary()["mtf_views"] == 2


def test_physics_noise_pools_a_frame_and_catches_40_dn_of_unexplained_noise(monkeypatch):
    """The default noise model (physics-first ``noise_source_full``) gets ``pool=True`` (one camera state per frame);
    a flat grey frame with 40 DN of white noise at ICX285 24 dB / 80 °C — a few DN by the metadata — raises the
    "noisier" alarm with ξ < 0; ``pool_noise=False`` judges every patch on its own and says the same."""
    from camhealth.estimators.physics_noise import PhysicsNoiseEstimator

    calls = []
    orig = PhysicsNoiseEstimator.predict
    monkeypatch.setattr(PhysicsNoiseEstimator, "predict",
                        lambda self, x, *a, pool=False, **k: calls.append(pool) or orig(self, x, *a, pool=pool, **k))
    meta = {"gain_db": 24.0, "exposure_s": 0.05, "temperature_c": 80.0}
    frame = (0.5 + 40.0 / 255.0 * torch.randn(384, 512, generator=torch.Generator().manual_seed(0))).clamp(0, 1)
    for pool in (True, False):
        calls.clear()
        mon = Monitor("noise_source_full", None, sensor="ICX285", metadata=meta, pool_noise=pool, warmup=False, adaptive=False)
        d = _strict(mon.process(frame).to_json())
        assert calls and set(calls) == {pool}
        assert d["alarm"]["state"] == "noisier", d["alarm"]
        assert d["noise"]["sigma_dn"]["xi"]["median"] < -25.0  # ξ̃ [DN]: the metadata explain a few DN of the ~40
        assert mon.summary()["pool_noise"] is pool


@pytest.mark.parametrize("mode", ["sampled", "map"])
def test_physics_noise_uncertainty_reaches_the_report(mode):
    """``noise_source_full`` states its own uncertainty (``sigma_std``, ``xi_std``): the report carries it as
    ``estimator_std`` for every noise field, and pooled (every patch shares the frame's posterior, so its error is
    common to them) each frame value's ``uncertainty`` is at least that; per patch it may shrink with the patches."""
    from camhealth.monitor import NOISE_FIELDS

    meta = {"gain_db": 24.0, "exposure_s": 0.05, "temperature_c": 80.0}
    frame = (0.5 + 12.0 / 255.0 * torch.randn(384, 512, generator=torch.Generator().manual_seed(1))).clamp(0, 1)
    for pool in (True, False):
        mon = Monitor("noise_source_full", None, sensor="ICX285", metadata=meta, mode=mode, pool_noise=pool, warmup=False,
                      adaptive=False)
        d = _strict(mon.process(frame).to_json())["noise"]["sigma_dn"]
        for name in NOISE_FIELDS:
            est, unc = d[name]["estimator_std"], d[name]["uncertainty"]
            assert est is not None and est >= 0.0, (name, d[name])
            if pool:
                assert unc >= est - 1e-6, (name, d[name])
        assert d["xi"]["estimator_std"] > 0.0 and d["xi"]["estimator_std"] == d["total"]["estimator_std"]


@pytest.mark.parametrize("noise", ["gaussian", "uniform"])
@pytest.mark.parametrize("mode", ["sampled", "map"])
def test_noise_beyond_the_validated_range_raises_noisier_not_silence(mode, noise):
    """A frame with 80 DN of white noise (or uniform noise over 0…255 DN, σ 73.6 DN, which the clipped-Gaussian model
    alone reads as ≈ 52 DN) where the metadata say a few DN: the physics-first estimator refuses its patches as
    "noise beyond validated range" (σ above 64 DN, where its σ reads low), and the monitor still raises "noisier"
    with that ξ̃ as a bound, instead of "not assessable"; the refusals are counted in the report."""
    from camhealth.estimators.physics_noise import BEYOND_VALIDATED, VALIDATED_SIGMA_DN

    g = torch.Generator().manual_seed(3)
    ramp = torch.linspace(60.0, 200.0, 512).view(1, 512).expand(384, 512) / 255.0
    if noise == "gaussian":
        frame = ((ramp + 80.0 / 255.0 * torch.randn(384, 512, generator=g)).clamp(0, 1) * 255).round() / 255
    else:
        frame = (torch.rand(384, 512, generator=g) * 255).round() / 255
    mon = Monitor("noise_source_full", None, sensor="ICX285", mode=mode, warmup=False, adaptive=False)
    d = _strict(mon.process(frame).to_json())
    assert not d["noise"]["assessable"]
    refused = d["noise"]["refused"]
    assert refused.get(BEYOND_VALIDATED, 0) >= 1 and sum(refused.values()) == d["noise"]["patches"]["not_assessable"]
    assert BEYOND_VALIDATED in d["noise"]["note"]
    a = d["alarm"]
    assert a["state"] == "noisier", a
    assert a["xi_dn"] < -VALIDATED_SIGMA_DN + 20.0  # the metadata explain ~2 DN; the image reads ≥ 60 DN (a bound)
    assert "bound" in a["message"] and f"{VALIDATED_SIGMA_DN:g} DN" in a["message"]


def test_beyond_range_alarm_rules():
    """noisier only with a beyond-range patch and ξ̃ below −threshold; otherwise not assessable, saying why."""
    from camhealth.monitor import beyond_range_alarm

    a = beyond_range_alarm(-40.0, 2, 8, 1.0)
    assert a["state"] == "noisier" and a["xi_dn"] == -40.0 and a["limit_dn"] == 1.0 and "2 of 8" in a["message"]
    for xi, beyond in ((-0.5, 3), (0.0, 3), (12.0, 3), (float("nan"), 3), (-40.0, 0)):
        b = beyond_range_alarm(xi, beyond, 8, 1.0)
        assert b["state"] == "not_assessable" and b["xi_dn"] is None and "cannot be assessed" in b["message"], (xi, beyond)


def test_refused_patches_are_counted_and_named_when_nothing_is_assessable():
    """An estimator that refuses every patch with a reason: the report counts the reasons, the note and the alarm
    message name them (not a bare "no informative patch")."""

    class Refusing(FakeNoise):
        def predict(self, patches, metadata=None, precision="fp32", batch_size=256):
            out = super().predict(patches, metadata, precision, batch_size)
            b = patches.shape[0]
            out["assessable"] = torch.zeros(b, dtype=torch.bool)
            out["reason"] = ["textured" if i % 2 else "no flat area" for i in range(b)]
            return out

    frame = (0.5 + 3.0 / 255.0 * torch.randn(384, 512, generator=torch.Generator().manual_seed(0))).clamp(0, 1)
    for mode in ("sampled", "map"):
        mon = Monitor(Refusing(), None, sensor="ICX285", mode=mode, warmup=False, adaptive=False)
        d = _strict(mon.process(frame).to_json())
        refused = d["noise"]["refused"]
        assert set(refused) == {"textured", "no flat area"} and sum(refused.values()) == d["noise"]["patches"]["not_assessable"] > 0
        assert "textured" in d["noise"]["note"] and "no flat area" in d["noise"]["note"]
        assert d["alarm"]["state"] == "not_assessable" and "textured" in d["alarm"]["message"]
        # the next frame counts its own refusals, not a running total; the summary adds them up over the run
        d2 = _strict(mon.process(frame).to_json())
        assert sum(d2["noise"]["refused"].values()) == d2["noise"]["patches"]["not_assessable"]
        total = mon.summary()["refused"]["noise"]
        assert total == {k: refused.get(k, 0) + d2["noise"]["refused"].get(k, 0) for k in set(refused) | set(d2["noise"]["refused"])}
    ok = _strict(Monitor(FakeNoise(), None, sensor="ICX285", warmup=False).process(frame).to_json())
    assert ok["noise"]["refused"] == {}


class _MTFWithStd(FakeMTF):
    """FakeMTF that also states a per-value spread ``mtf_std`` (as ``Estimator.predict(views=2|4)`` does): ``std``
    for every patch, or per call from ``stds``."""

    def __init__(self, std=None, stds=None):
        super().__init__()
        self.std, self.stds = std, stds

    def predict(self, patches, metadata=None, precision="fp32", batch_size=256):
        out = super().predict(patches, metadata, precision, batch_size)
        b = patches.shape[0]
        if self.stds is not None:
            s = torch.as_tensor(self.stds[: b], dtype=torch.float32)[:, None].expand(b, 16)
        else:
            s = torch.full((b, 16), float("nan") if self.std is None else float(self.std))
        out["mtf_std"] = s
        return out


@pytest.mark.parametrize("mode", ["map", "sampled"])
def test_mtf_estimator_std_is_pooled_and_bounds_the_uncertainty(street_frames, mode):
    """The estimator's per-patch ``mtf_std`` reaches the frame report as ``estimator_std`` (√ mean of squares over the
    values behind the median), in the JSON line beside median/spread, and the stated ``uncertainty`` is never below
    1.2533·estimator_std/√n; without a per-patch spread (views 1: NaN) the field is null and the uncertainty is the
    one from the scatter alone."""
    frame = noisy(street_frames[0], 2.0, seed=0)
    kw = dict(sensor="ICX285", mode=mode, adaptive=False, warmup=False)
    rep = Monitor(None, _MTFWithStd(std=0.2), **kw).process(frame).mtf
    assert rep.assessable and rep.n_values >= 2
    assert torch.allclose(rep.estimator_std, torch.full((16,), 0.2))
    floor = 1.2533 * 0.2 / math.sqrt(rep.n_values)
    assert bool((rep.uncertainty >= floor - 1e-6).all())
    d = json.loads(rep_json := Monitor(None, _MTFWithStd(std=0.2), **kw).process(frame).to_json())["mtf"]
    assert "NaN" not in rep_json
    assert d["h"]["estimator_std"] == [0.2] * 8 and d["v"]["estimator_std"] == [0.2] * 8
    assert min(d["h"]["uncertainty"]) >= round(floor, 4) - 1e-4
    # the indicator MTF̃ = (H + V)/2 at f_n 0.1 has the same floor (its two parts' u averaged): patches that happen to
    # agree do not make it exact
    assert rep.indicator_uncertainty >= floor - 1e-6

    plain = Monitor(None, _MTFWithStd(std=None), **kw).process(frame).mtf  # views 1: no per-patch spread
    assert bool(torch.isnan(plain.estimator_std).all())
    d0 = json.loads(Monitor(None, _MTFWithStd(std=None), **kw).process(frame).to_json())["mtf"]
    assert d0["h"]["estimator_std"] == [None] * 8
    assert torch.equal(plain.median, rep.median) and bool((plain.uncertainty < floor).any())  # the floor did act

    # pooled as √(mean std²): patches with 0.1 and 0.3 alternate → √((0.01 + 0.09) / 2) when they come in equal numbers
    n = rep.n_values
    stds = [0.1 if i % 2 == 0 else 0.3 for i in range(64)]
    mixed = Monitor(None, _MTFWithStd(stds=stds), **kw).process(frame).mtf
    per = torch.tensor(stds[:n] if mode == "sampled" else stds[: mixed.n_values])
    assert torch.allclose(mixed.estimator_std, per.pow(2).mean().sqrt().expand(16), atol=1e-5)


@pytest.mark.parametrize("mode", ["map", "sampled"])
def test_mtf_uncertainty_keeps_the_part_of_the_error_a_scenes_patches_share(street_frames, mode):
    """An MTF estimator whose error table says the patches of one scene share ρ of their error variance (the shipped
    file's ``mtf_error.shared``): the frame's uncertainty is at least estimator_std·√(ρ + (π/2)(1 − ρ)/n), so more
    patches do not make a shared bias look small; without ``shared`` (ρ = 0) the floor is 1.2533·estimator_std/√n."""
    from camhealth.estimators.mtf_error import MTFErrorTable
    from camhealth.inference import load_estimator

    frame = noisy(street_frames[0], 2.0, seed=0)
    kw = dict(sensor="ICX285", mode=mode, adaptive=False, warmup=False)
    est = _MTFWithStd(std=0.2)
    est.mtf_error = MTFErrorTable((0.0, 1.0), (0.2, 0.2), 10, "test", 0.68)
    rep = Monitor(None, est, **kw).process(frame).mtf
    n = rep.n_values
    assert n >= 2 and bool((rep.uncertainty >= 0.2 * math.sqrt(0.68 + (math.pi / 2) * 0.32 / n) - 1e-6).all())
    alone = Monitor(None, _MTFWithStd(std=0.2), **kw).process(frame).mtf  # no table: independent errors
    assert bool((alone.uncertainty < 0.2 * math.sqrt(0.68)).any()) and torch.equal(alone.median, rep.median)
    assert load_estimator("mtf").mtf_error.shared > 0.5  # the shipped file carries its measured ρ


def test_noise_estimator_without_its_own_uncertainty_reports_a_null_estimator_std(street_frames):
    d = json.loads(Monitor(FakeNoise(), None, sensor="ICX285", warmup=False).process(street_frames[0]).to_json())
    assert d["noise"]["sigma_dn"]["total"]["estimator_std"] is None


def test_real_mtf_estimator_views_give_an_estimator_std(model_files, street_frames):
    """With the exported MTF network and ``mtf_views=2`` the frame carries a finite, non-negative estimator_std;
    with views 1 it is null."""
    ns, mtf = model_files
    frame = noisy(street_frames[0], 3.0, seed=0)
    two = json.loads(Monitor(None, mtf, mtf_views=2, warmup=False).process(frame).to_json())["mtf"]
    one = json.loads(Monitor(None, mtf, warmup=False).process(frame).to_json())["mtf"]
    assert all(v is not None and v >= 0 for v in two["h"]["estimator_std"] + two["v"]["estimator_std"])
    assert one["h"]["estimator_std"] == [None] * 8


@pytest.mark.parametrize("kind", ["rows", "columns"])
@pytest.mark.parametrize("mode", ["sampled", "map"])
def test_row_or_column_noise_raises_noisier_and_names_it(mode, kind, monkeypatch):
    """A ramp frame with the camera's own noise plus 8 DN of offsets per pixel row (or column): the texture check alone
    reads the banding as texture and would refuse every patch; the banding is taken out of the checks, counted in
    σ_Total and ξ, and the alarm says "noisier" and names it. The same frame without banding stays "ok"."""
    from camhealth.bench.sensor_variants import simulate_variant
    from camhealth.monitor.diagnostics import frame_level, key_values
    from camhealth.physics import CameraMetadata

    meta = CameraMetadata.preset("ICX285")
    ramp = torch.linspace(60.0, 200.0, 512).view(1, 1, 1, 512).expand(1, 1, 384, 512) / 255.0
    noisy, _ = simulate_variant(ramp.contiguous(), meta, ("round8",), torch.Generator().manual_seed(4))
    g = torch.Generator().manual_seed(5)
    shape = (384, 1) if kind == "rows" else (1, 512)
    banded = ((noisy[0, 0] + 8.0 / 255.0 * torch.randn(shape, generator=g)).clamp(0, 1) * 255).round() / 255
    for frame, banding in ((noisy[0, 0], False), (banded, True)):
        mon = Monitor("noise_source_full", None, sensor="ICX285", mode=mode, warmup=False, adaptive=False)
        report = mon.process(frame)
        d = _strict(report.to_json())
        diag = dict(key_values(report, frame_level(report)[0]))
        assert d["noise"]["assessable"], d["noise"]
        if not banding:
            assert d["alarm"]["state"] == "ok" and d["noise"]["banding"] is None, d["alarm"]
            assert diag["noise_row_dn"] == "0" and diag["noise_col_dn"] == "0"
            assert mon.summary()["banding"] is None
            continue
        band = d["noise"]["banding"]
        key, other = ("row_dn", "col_dn") if kind == "rows" else ("col_dn", "row_dn")
        assert 6.5 < band[key] < 9.5 and band[other] == 0.0, band
        a = d["alarm"]
        assert a["state"] == "noisier", a
        assert a["xi_dn"] < -4.0
        assert f"{kind[:-1] if kind == 'rows' else 'column'} noise ≈" in a["message"] and "banding" in a["message"]
        assert float(diag[f"noise_{key[:3]}_dn"]) == pytest.approx(band[key], abs=1e-3)  # the ROS diagnostics carry it
        assert diag["level"] == "ERROR" and float(diag["noise_total_dn"]) > 7.0
        summary = mon.summary()["banding"]  # the run's frames with banding
        assert summary["frames"] == 1 and summary[key]["median"] == pytest.approx(band[key], abs=1e-3)
        assert summary[key]["max"] == summary[key]["median"] and summary[other]["max"] == 0.0
        # with the banding never detected, the texture check refuses the patches: the monitor could not tell
        import camhealth.estimators.row_column_noise as rcn

        monkeypatch.setattr(rcn, "T_LIMIT", float("inf"))
        mon = Monitor("noise_source_full", None, sensor="ICX285", mode=mode, warmup=False, adaptive=False)
        d = _strict(mon.process(frame).to_json())
        assert not d["noise"]["assessable"] and d["noise"]["refused"].get("textured", 0) >= 1, d["noise"]
        assert d["alarm"]["state"] == "not_assessable"


def test_mtf_is_not_assessable_under_banding_from_the_limit_on():
    """The MTF network reads row and column noise as fine detail: a frame whose noise report shows banding of
    MTF_BANDING_LIMIT_DN or more gets its MTF refused with a note that names it; below, or without banding, the
    report is returned as it is."""
    from camhealth.monitor import MTF_BANDING_LIMIT_DN, TaskReport, mtf_under_banding

    mtf = TaskReport(task="mtf", estimator="mtf", patch=192, grid=(2, 3), assessable=True,
                     median=torch.full((16,), 0.5), indicator=(0.6, 0.05))
    below = {"row_dn": MTF_BANDING_LIMIT_DN - 0.1, "col_dn": 0.0, "patches": 8}
    assert mtf_under_banding(mtf, below) is mtf
    for band, which in (({"row_dn": 0.0, "col_dn": MTF_BANDING_LIMIT_DN, "patches": 8}, "column"),
                        ({"row_dn": 6.5, "col_dn": 1.0, "patches": 8}, "row")):
        out = mtf_under_banding(mtf, band)
        assert out is not mtf and not out.assessable and mtf.assessable
        assert f"{which} noise ≈" in out.note and "banding" in out.note
        d = out.to_dict()
        assert d["h"] is None and d["v"] is None and d["indicator"] is None
    # judged patch by patch, banding on 3 of 8 patches is their stripes, not the camera's: the MTF stands
    few = {"row_dn": 6.5, "col_dn": 0.0, "patches": 3}
    assert mtf_under_banding(mtf, few, estimated=8) is mtf
    assert not mtf_under_banding(mtf, {**few, "patches": 4}, estimated=8).assessable
    not_assessable = TaskReport(task="mtf", estimator="mtf", patch=192, grid=(2, 3), assessable=False, note="n")
    assert mtf_under_banding(not_assessable, {"row_dn": 9.0, "col_dn": 0.0, "patches": 8}) is not_assessable


class _BandedNoise(FakeNoise):
    """A noise estimator that finds 3 DN of row noise, a readout-like cause and one hot pixel (at (5, 7) of the patch)
    on every patch it estimates, and ξ = −5 DN (the image noisier than the metadata allow)."""

    def __init__(self) -> None:
        super().__init__(xi_dn=-5.0)

    def predict(self, patches, metadata=None, precision="fp32", batch_size=256):
        out = super().predict(patches, metadata, precision, batch_size)
        n, p = patches.shape[0], patches.shape[-1]
        mask = torch.zeros(n, 1, p, p, dtype=torch.int8)
        mask[:, 0, 7, 5] = 1
        return {**out, "row_column_dn": torch.tensor([[3.0, 0.0]]).repeat(n, 1),
                "cause": torch.tensor([[0.1, 0.0, 0.8, 0.1]]).repeat(n, 1), "follows_image": torch.ones(n, dtype=torch.bool),
                "defects": torch.tensor([[1, 0]]).repeat(n, 1), "defects_checked": torch.full((n,), (p - 2) ** 2),
                "defect_mask": mask}


@pytest.mark.parametrize("mode", ["sampled", "map"])
def test_reused_patches_keep_the_banding_cause_and_defects_of_their_estimate(mode, street_frames):
    """A static camera whose noise patches show row noise, a cause and a hot pixel each: from the frames on where the
    patches keep their estimates (reused, no estimator call) the frame keeps their banding, cause and defects — the MTF
    stays not assessable under the banding, the alarm keeps naming it, the diagnostics carry it — as on the first
    frame, where they were estimated."""
    from camhealth.monitor.diagnostics import frame_level, key_values

    fake = _BandedNoise()
    mon = Monitor(fake, FakeMTF(), sensor="ICX285", mode=mode, coarse_refine=False, noise_samples=4, window=3)
    frame = noisy(street_frames[0], 3.0, seed=0)
    first = None
    for i in range(6):
        before = fake.patches
        r = mon.process(frame)
        d = _strict(r.to_json())
        n = d["noise"]
        judged = n["coverage"]["estimated"] + n["coverage"]["reused"]
        assert judged > 0 and fake.patches - before == n["patches"]["estimated"] + n["patches"]["not_assessable"]
        assert n["banding"] == {"row_dn": 3.0, "col_dn": 0.0, "patches": judged}, (i, n["coverage"])
        assert n["cause"] == {"gain": 0.1, "dark_current": 0.0, "readout": 0.9, "patches": judged}
        assert n["defects"]["hot"] == judged and n["defects"]["checked"] == judged * 126 * 126
        if mode == "map":  # the same patches every frame: every hot pixel where it was
            assert n["defects"]["recurring"] == (0 if i == 0 else judged)
        assert d["mtf"]["assessable"] is False and "row noise ≈ 3.00 DN" in d["mtf"]["note"]
        assert d["alarm"]["state"] == "noisier" and "row noise ≈ 3.00 DN" in d["alarm"]["message"]
        assert dict(key_values(r, frame_level(r)[0]))["noise_row_dn"] == "3"
        if first is None:
            first = (n["banding"], n["cause"], n["defects"]["ppm"], d["alarm"]["message"])
        elif mode == "map":  # the same patches every frame: the same frame verdict, estimated or kept
            assert (n["banding"], n["cause"], n["defects"]["ppm"], d["alarm"]["message"]) == first
    assert n["coverage"]["reused"] > 0 and n["coverage"]["estimated"] < judged  # the last frames kept their estimates
    assert mon.summary()["banding"]["frames"] == 6


@pytest.mark.parametrize("mode", ["sampled", "map"])
def test_defective_pixels_are_counted_named_and_recur(mode):
    """A ramp frame with the camera's own noise and 0.5 % of its pixels hot or dead: the noise report counts them
    (``defects``), the alarm names them (its state stays the ξ verdict: the defects are not σ), the ROS diagnostics
    warn and carry the share; the same frame again shows them at the same pixels (``recurring``), which the summary
    counts. The frame without defects reports none and stays OK."""
    from camhealth.bench.sensor_variants import simulate_variant
    from camhealth.monitor import DEFECT_ALARM_PPM
    from camhealth.monitor.diagnostics import WARN, OK, frame_level, key_values
    from camhealth.physics import CameraMetadata

    meta = CameraMetadata.preset("ICX285")
    ramp = torch.linspace(60.0, 200.0, 512).view(1, 1, 1, 512).expand(1, 1, 384, 512) / 255.0
    noisy, _ = simulate_variant(ramp.contiguous(), meta, ("round8",), torch.Generator().manual_seed(4))
    g = torch.Generator().manual_seed(6)
    hit = torch.rand(noisy.shape, generator=g) < 0.005
    sign = torch.where(torch.rand(noisy.shape, generator=g) < 0.5, 1.0, -1.0)
    bad = ((noisy * 255 + hit * sign * (40 + 100 * torch.rand(noisy.shape, generator=g))).clamp(0, 255).round() / 255)[0, 0]
    mon = Monitor("noise_source_full", None, sensor="ICX285", mode=mode, warmup=False, adaptive=False)
    clean = mon.process(noisy[0, 0])
    assert clean.noise.defects is None and clean.alarm["state"] == "ok"
    assert frame_level(clean)[0] == OK and dict(key_values(clean, OK))["noise_defect_ppm"] == "0"
    first = mon.process(bad)
    d = _strict(first.to_json())
    df = d["noise"]["defects"]
    assert df["hot"] > 0 and df["dark"] > 0 and df["recurring"] == 0
    assert 0.8 * 5000 <= df["ppm"] <= 5000 * 1.05 and df["ppm"] >= DEFECT_ALARM_PPM
    assert df["checked"] == d["noise"]["coverage"]["estimated"] * 126 * 126
    assert d["alarm"]["state"] == "ok" and "stand out from all their neighbours" in d["alarm"]["message"]
    level, message = frame_level(first)
    assert level == WARN and message.startswith("defective pixels")
    assert float(dict(key_values(first, level))["noise_defect_ppm"]) == pytest.approx(df["ppm"], rel=1e-3)  # 4 digits
    second = _strict(mon.process(bad).to_json())
    again = second["noise"]["defects"]
    assert again["recurring"] == again["hot"] + again["dark"] > 0  # the same frame: every defect where it was
    assert f"{again['recurring']} at the same place as in an earlier frame" in second["alarm"]["message"]
    s = mon.summary()["defects"]
    assert s["frames"] == 2 and s["recurring_pixels"] >= again["recurring"] > 0
    xy = s["recurring_xy"]  # where: [x, y, frames] in frame pixels, each a pixel the frame really has moved
    assert 0 < len(xy) <= 100 and all(n == 2 for _, _, n in xy)
    assert all(hit[0, 0, y, x] for x, y, _ in xy)
    assert s["ppm"]["max"] >= s["ppm"]["median"] >= DEFECT_ALARM_PPM


@pytest.mark.parametrize("process", ["demosaic", "gauss"])
def test_noise_that_is_not_white_is_refused_with_a_hint_at_its_cause(process):
    """A smooth ramp with 5 DN of white noise, then demosaiced (OpenCV bilinear, to gray) or Gaussian-filtered: the
    noise of neighbouring pixels is correlated, every noise patch is refused as textured, and the alarm message says
    what besides texture does that; on the raw ramp the noise is read and there is no hint."""
    import cv2

    from camhealth.monitor.api import TEXTURED_HINT

    rng = np.random.default_rng(0)
    ramp = np.tile(np.linspace(40, 210, 640), (512, 1))
    raw = np.clip(ramp + 5 * rng.standard_normal(ramp.shape), 0, 255).round().astype(np.uint8)
    if process == "demosaic":
        img = cv2.cvtColor(cv2.cvtColor(raw, cv2.COLOR_BayerBG2BGR), cv2.COLOR_BGR2GRAY)
    else:
        img = cv2.GaussianBlur(raw, (0, 0), 0.7)
    mon = Monitor("noise_source_full", None, sensor="ICX285", warmup=False)
    r = mon.process(img)
    assert not r.noise.assessable and set(r.noise.refused) == {"textured"}
    assert r.alarm["state"] == "not_assessable" and TEXTURED_HINT in r.alarm["message"]
    ok = Monitor("noise_source_full", None, sensor="ICX285", warmup=False).process(raw)
    assert ok.noise.assessable and TEXTURED_HINT not in ok.alarm["message"]


@pytest.mark.parametrize("quality", [75, 95])
def test_a_jpeg_frame_is_refused_as_coded_with_a_hint(quality):
    """The same ramp with 3 DN of white noise, coded as a JPEG. At quality 75 the estimator refuses the pooled patches
    as textured (the codec's blocking reads as texture) and the monitor finds JPEG's 8×8 block grid on them; at 95 the
    pooled posterior would be followed and the estimator names the codec itself. Either way the refused noise patches
    name the codec and the alarm says why the metadata cannot be checked on it."""
    import functools

    import cv2

    from camhealth.estimators.physics_noise import LOSSY_CODEC
    from camhealth.monitor.api import CODEC_HINT, TEXTURED_HINT

    rng = np.random.default_rng(0)
    raw = np.clip(np.tile(np.linspace(40, 210, 640), (512, 1)) + 3 * rng.standard_normal((512, 640)), 0, 255)
    ok, buf = cv2.imencode(".jpg", raw.round().astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, quality])
    img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    mon = Monitor("noise_source_full", None, sensor="ICX285", warmup=False)
    est = mon.estimators["noise"].est
    own = est.predict  # what the estimator itself says, before the monitor's relabel
    said: list[str] = []

    @functools.wraps(own)  # (the monitor reads predict's signature: pool=, reference=)
    def spy(*args, **kwargs):
        out = own(*args, **kwargs)
        said.extend(out["reason"])
        return out

    est.predict = spy
    r = mon.process(img)
    assert set(said) == ({"textured"} if quality == 75 else {LOSSY_CODEC})
    assert not r.noise.assessable and set(r.noise.refused) == {LOSSY_CODEC}
    assert r.alarm["state"] == "not_assessable" and CODEC_HINT in r.alarm["message"]
    assert TEXTURED_HINT not in r.alarm["message"]


def test_the_estimators_run_on_the_monitors_device(device, street_frames):
    """``device=`` puts the named estimators' networks (and the noise posterior) there; the frame's answer is the
    CPU's: the same patches and alarm, σ and MTF within float32 convolution rounding (TF32 on a GPU)."""
    frame = noisy(street_frames[0], 3.0, seed=0)
    reports = []
    for dev in ("cpu", device):
        mon = Monitor("noise_source_full", "mtf", sensor="ICX285", mode="map", precision="fp32", device=dev)
        assert all(h.est.device.type == torch.device(dev).type for h in mon.estimators.values())
        reports.append(_strict(mon.process(frame).to_json()))
    ref, got = reports
    assert got["alarm"] == ref["alarm"]
    assert got["noise"]["patches"] == ref["noise"]["patches"] and got["mtf"]["patches"] == ref["mtf"]["patches"]
    for name in ("pn", "dcsn", "rn", "xi", "total"):
        assert got["noise"]["sigma_dn"][name]["median"] == pytest.approx(ref["noise"]["sigma_dn"][name]["median"], abs=1e-3)
    for d in ("h", "v"):
        assert got["mtf"][d]["median"] == pytest.approx(ref["mtf"][d]["median"], abs=2e-3)


def _busy_frame(h: int = 384, w: int = 512, seed: int = 0) -> torch.Tensor:
    """A busy static scene: random-phase 1/f² texture (30 DN of contrast) over sharp-edged blocks, 0.2…0.8."""
    g = torch.Generator().manual_seed(seed)
    wn = torch.fft.rfft2(torch.randn(h, w, generator=g).double())
    f = torch.sqrt(torch.fft.fftfreq(h).view(-1, 1) ** 2 + torch.fft.rfftfreq(w).view(1, -1) ** 2)
    x = torch.fft.irfft2(wn / wn.abs().clamp_min(1e-30) * torch.where(f > 0, 1.0 / f.clamp_min(1e-9), 0.0), s=(h, w))
    x = (x - x.mean()) / x.std()
    blocks = torch.nn.functional.interpolate((torch.rand(1, 1, h // 16, w // 16, generator=g) > 0.5).double(), scale_factor=16.0)[0, 0]
    return (0.5 + 30.0 / 255.0 * x + 0.15 * (blocks - 0.5)).clamp(0.2, 0.8).float()


@pytest.mark.parametrize("mode", ["map", "sampled"])
def test_static_pairs_find_a_mismatch_a_busy_scene_hides_from_one_frame(mode):
    """A static camera 3 DN noisier than its metadata, on a busy scene: one frame at a time no patch has a flat area
    to read the noise from (not assessable); with ``static_pairs`` the second frame on is read against the previous
    one, every patch, and raises "noisier". When the camera moves between the frames, no pair is read."""
    from camhealth.bench.sensor_variants import simulate_variant
    from camhealth.physics import CameraMetadata

    meta = {"gain_db": 6.0, "exposure_s": 0.02, "temperature_c": 30.0}
    cam = CameraMetadata.preset("ICX285", **meta)
    clean = _busy_frame()[None, None]
    frames = [simulate_variant(clean, cam, (), torch.Generator().manual_seed(i), extra_read_noise_dn=3.0)[0][0, 0] for i in range(3)]
    states = {}
    for pairs in (False, True):
        mon = Monitor("noise_source_full", None, sensor="ICX285", metadata=meta, mode=mode, adaptive=False, warmup=False,
                      static_pairs=pairs)
        reports = [_strict(mon.process(f).to_json()) for f in frames]
        states[pairs] = [r["alarm"]["state"] for r in reports]
        assert mon.summary()["static_pairs"] is pairs
        if pairs:
            assert reports[0]["noise"]["coverage"]["static_pairs"] == 0  # nothing to pair the first frame with
            assert all(r["noise"]["coverage"]["static_pairs"] > 0 for r in reports[1:])
        else:
            assert "static_pairs" not in reports[1]["noise"]["coverage"]
    assert states[False] == ["not_assessable"] * 3
    assert states[True] == ["not_assessable", "noisier", "noisier"]
    moved = Monitor("noise_source_full", None, sensor="ICX285", metadata=meta, mode=mode, adaptive=False, warmup=False,
                    static_pairs=True)
    for i, f in enumerate(frames):  # the camera pans 1 px per frame
        r = _strict(moved.process(torch.roll(f, i, -1)).to_json())
    assert r["noise"]["coverage"]["static_pairs"] == 0 and r["alarm"]["state"] == "not_assessable"


def test_static_pairs_must_be_a_bool():
    with pytest.raises(TypeError, match="static_pairs = 'yes' must be True or False"):
        Monitor("noise_source_full", None, sensor="ICX285", static_pairs="yes")


@pytest.mark.parametrize("mode", ["map", "sampled"])
def test_an_auto_exposures_steps_split_dark_current_from_readout_noise(mode):
    """A CMOS camera with 3× the white noise its metadata say, its exposure alternating 0.2 s / 0.02 s: one state at a
    time, the 0.2-s frames give the excess to dark current (DCSN 2.8× the truth); with the other exposure time's
    evidence kept (the default) each source is within 5 % from the third frame on. A frame of another gain adds
    nothing: only the exposure time may differ."""
    from camhealth.bench.sensor_variants import simulate_variant

    told = {"gain_db": 6.0, "exposure_s": 0.2, "temperature_c": 30.0}
    long = CameraMetadata.preset("EV76C661", **told)
    h, w = 384, 512
    clean = torch.linspace(0.1, 0.8, w).view(1, 1, 1, w).expand(1, 1, h, w).contiguous()
    real = {"white_noise_v_per_rthz": float(long.white_noise_v_per_rthz) * 3.0}
    seq = []
    for i in range(4):
        cam = long.replace(exposure_s=torch.tensor([0.02 if i % 2 else 0.2], dtype=torch.float64))
        x, truth = simulate_variant(clean, cam, (), torch.Generator().manual_seed(i), real)
        seq.append((x[0, 0], {"exposure_s": float(cam.exposure_s)}, truth.mean(0)))
    got = {}
    for kept in (False, True):
        mon = Monitor("noise_source_full", None, sensor="EV76C661", metadata=told, mode=mode, adaptive=False, warmup=False,
                      exposure_evidence=kept)
        reports = [_strict(mon.process(x, md).to_json()) for x, md, _ in seq]
        got[kept] = [[r["noise"]["sigma_dn"][k]["median"] for k in ("pn", "dcsn", "rn")] for r in reports]
        assert mon.summary()["exposure_evidence"] is kept
        assert all(r["alarm"]["state"] == "noisier" for r in reports)
        if kept:
            assert [r["noise"]["coverage"]["other_exposures"] for r in reports] == [0, 1, 1, 1]
        else:
            assert "other_exposures" not in reports[0]["noise"]["coverage"]
    truth = seq[2][2]
    assert got[False][2][1] > 2.0 * float(truth[1])  # one state: the excess partly in DCSN
    for i in (2, 3):
        assert torch.allclose(torch.tensor(got[True][i]), seq[i][2].float(), rtol=0.05), (got[True][i], seq[i][2])
    other_gain = Monitor("noise_source_full", None, sensor="EV76C661", metadata=told, mode=mode, adaptive=False, warmup=False)
    other_gain.process(seq[1][0], {"exposure_s": 0.02, "gain_db": 12.0})
    r = _strict(other_gain.process(seq[2][0], seq[2][1]).to_json())
    assert r["noise"]["coverage"]["other_exposures"] == 0


@pytest.mark.parametrize("mode", ["map", "sampled"])
def test_the_report_names_the_cause_of_a_mismatch(mode):
    """What the evidence points to, in the JSON (``noise.cause``) and in the alarm's message: a camera with 3× the white
    noise is "noisier", most likely readout noise; a sensor 25 K hotter than told, its exposure alternating 0.2 / 0.02
    s, moves the short frames' σ_Total by less than the alarm's limit — "ok", but its sources are followed and named
    (dark current); a matched camera has no cause."""
    from camhealth.bench.sensor_variants import simulate_variant

    told = {"gain_db": 6.0, "exposure_s": 0.2, "temperature_c": 30.0}
    long = CameraMetadata.preset("EV76C661", **told)
    h, w = 256, 384
    clean = torch.linspace(0.1, 0.8, w).view(1, 1, 1, w).expand(1, 1, h, w).contiguous()
    cameras = {"readout": {"white_noise_v_per_rthz": float(long.white_noise_v_per_rthz) * 3.0},
               "dark_current": {"temperature_c": 55.0}, None: None}
    for cause, real in cameras.items():
        mon = Monitor("noise_source_full", None, sensor="EV76C661", metadata=told, mode=mode, adaptive=False, warmup=False)
        for i in range(4):
            cam = long.replace(exposure_s=torch.tensor([0.02 if i % 2 else 0.2], dtype=torch.float64))
            x, _ = simulate_variant(clean, cam, (), torch.Generator().manual_seed(i), real)
            report = mon.process(x[0, 0], {"exposure_s": float(cam.exposure_s)})
            r = _strict(report.to_json())
        got = r["noise"]["cause"]  # the last frame: 0.02 s, the other exposure time's evidence kept
        diag = dict(key_values(report, OK))
        causes = mon.summary()["causes"]  # the run's frames that named a cause, by the most probable one
        if cause is None:
            assert got is None and r["alarm"]["state"] == "ok" and "most likely" not in r["alarm"]["message"]
            assert diag["noise_cause"] == "" and diag["noise_cause_p"] == "nan" and causes is None
            continue
        assert causes[cause] >= 2 and causes["frames"] == sum(v for k, v in causes.items() if k != "frames")
        assert set(causes) == {"frames", "gain", "dark_current", "readout"}  # every cause, 0 where none named it
        assert diag["noise_cause"] == cause and float(diag["noise_cause_p"]) > 0.9
        assert set(got) == {"gain", "dark_current", "readout", "patches"} and got["patches"] > 0
        assert abs(got["gain"] + got["dark_current"] + got["readout"] - 1.0) < 1e-2
        assert got[cause] > 0.9, got
        assert "most likely " + CAUSE_WORDS[cause] in r["alarm"]["message"]
        assert r["alarm"]["state"] == ("noisier" if cause == "readout" else "ok"), r["alarm"]


def test_a_cleaner_image_names_its_cause_in_the_words_of_less_noise():
    """The gain is 8 dB below the told one: the image is "cleaner", and the message names the gain."""
    from camhealth.bench.sensor_variants import simulate_variant

    told = {"gain_db": 12.0, "exposure_s": 0.05, "temperature_c": 30.0}
    clean = torch.linspace(0.1, 0.8, 384).view(1, 1, 1, 384).expand(1, 1, 256, 384).contiguous()
    x, _ = simulate_variant(clean, CameraMetadata.preset("ICX285", **told), (), torch.Generator().manual_seed(0), {"gain_db": 4.0})
    mon = Monitor("noise_source_full", None, sensor="ICX285", metadata=told, mode="map", adaptive=False, warmup=False)
    r = _strict(mon.process(x[0, 0]).to_json())
    assert r["alarm"]["state"] == "cleaner" and r["noise"]["cause"]["gain"] > 0.9
    assert r["alarm"]["message"].endswith(f"; most likely the gain (P 1.00, {r['noise']['cause']['patches']} patches)")


def test_the_estimators_four_kinds_group_into_the_monitors_three_causes():
    from camhealth.monitor.api import group_causes, top_cause

    got = group_causes(torch.tensor([0.1, 0.2, 0.3, 0.4]))  # gain, temperature, white-noise density, beyond
    assert got == pytest.approx({"gain": 0.1, "dark_current": 0.2, "readout": 0.7})
    assert top_cause(got) == "readout" and top_cause({"gain": 0.6, "dark_current": 0.4}) == "gain"


def test_cause_text_names_the_runner_up_where_it_has_a_quarter():
    assert cause_text({"gain": 0.9, "dark_current": 0.06, "readout": 0.04, "patches": 12}) == "most likely the gain (P 0.90, 12 patches)"
    both = cause_text({"gain": 0.0, "dark_current": 0.55, "readout": 0.45, "patches": 3})
    assert both.startswith("most likely dark current (the sensor hotter") and "readout noise (white noise the metadata do not have) P 0.45" in both
    cleaner = cause_text({"gain": 0.0, "dark_current": 0.2, "readout": 0.8, "patches": 3}, noisier=False)
    assert cleaner.startswith("most likely readout noise (less white noise than the metadata say, or a denoiser) (P 0.80")


def test_exposure_evidence_must_be_a_bool_and_reset_forgets_it():
    with pytest.raises(TypeError, match="exposure_evidence = 1 must be True or False"):
        Monitor("noise_source_full", None, sensor="ICX285", exposure_evidence=1)
    mon = Monitor("noise_source_full", None, sensor="ICX285", warmup=False)
    frame = (0.5 + 0.01 * torch.randn(256, 256, generator=torch.Generator().manual_seed(0))).clamp(0, 1)
    mon.process(frame, {"exposure_s": 0.01})
    assert len(mon._exposure_cache) == 1
    mon.process(frame, {"exposure_s": 0.02})  # a new exposure time: its evidence joins the kept one
    assert len(mon._exposure_cache) == 2
    mon.reset()
    assert not mon._exposure_cache



@pytest.mark.parametrize("mode", ["map", "sampled"])
def test_the_frames_behind_an_answer_start_afresh_with_the_aggregation(street_frames, mode):
    """After a metadata change (or reset) the answer stands on that one frame: ``coverage.frames`` is 1, as for a fresh
    monitor, and so is the uncertainty (map mode counted the frames of the whole run: 5, an uncertainty √5 too small)."""
    frame = noisy(street_frames[0], 3.0, seed=0)
    mon = _monitor(noise="noise_source_full", mtf=None, mode=mode, warmup=False, adaptive=False)
    for _ in range(6):
        mon.process(frame)
    changed = mon.process(frame, {"gain_db": 12.0}).noise
    fresh = _monitor(noise="noise_source_full", mtf=None, mode=mode, warmup=False, adaptive=False,
                     metadata={"gain_db": 12.0}).process(frame).noise
    assert changed.coverage["frames"] == fresh.coverage["frames"] == 1
    assert torch.allclose(changed.uncertainty, fresh.uncertainty, equal_nan=True)
    mon.reset()
    assert mon.process(frame, {"gain_db": 12.0}).noise.coverage["frames"] == 1


@pytest.mark.parametrize("value, match", [
    (np.array([12.0, 24.0]), "gain_db holds 2 values; a frame has one camera state"),
    (torch.tensor([12.0, 24.0]), "gain_db holds 2 values"),
    (True, r"gain_db = True must be a number"),
    ("12", r"gain_db = '12' must be a number"),
])
def test_per_frame_metadata_is_one_number_per_field(street_frames, value, match):
    """A per-frame array became a batch of camera states: a wrong answer on a 2-patch frame, a deep crash elsewhere."""
    mon = _monitor(noise="noise_source_full", mtf=None, warmup=False)
    with pytest.raises(ValueError, match=match):
        mon.process(street_frames[0], {"gain_db": value})
    one = mon.process(street_frames[0], {"gain_db": np.float32(12.0), "exposure_s": torch.tensor(0.01)})
    assert one.metadata["gain_db"] == 12.0 and one.metadata["exposure_s"] == pytest.approx(0.01)


def test_a_torch_uint16_frame_is_read_as_dn_over_65535():
    x = torch.full((64, 80), 65535, dtype=torch.uint16)
    assert float(as_frame(x).max()) == 1.0 and as_frame(torch.zeros(8, 8, dtype=torch.uint32)).shape == (1, 1, 8, 8)
    with pytest.raises(ValueError, match="must lie in \\[0, 255\\], got min 300"):
        as_frame(torch.full((8, 8), 300, dtype=torch.uint32))


@pytest.mark.parametrize("bits", [10, 12, 14])
def test_a_uint16_frame_of_fewer_bits_is_read_with_its_bit_depth(bits, tmp_path):
    """12-bit (or 10-, 14-bit) data in uint16: ``bit_depth`` divides by 2^bits − 1 — the frame the CLI reads from the
    same data in a PNG with ``--bit-depth``; without it (or 16) DN/65535 as before, for NumPy arrays and torch tensors
    alike; ``process`` takes it too."""
    import cv2

    from camhealth.data.io import read_image

    g = np.random.default_rng(0)
    top = 2**bits - 1
    arr = np.clip(top / 2 + g.normal(0, top / 100, (256, 384)), 0, top).astype(np.uint16)
    arr[0, 0] = top
    assert cv2.imwrite(str(tmp_path / "f.png"), arr)
    cli = read_image(tmp_path / "f.png", bit_depth=bits)
    for x in (arr, torch.from_numpy(arr.astype(np.int32)).to(torch.uint16)):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # a frame read with its bit depth, or as 16-bit data told so: no warning
            f = as_frame(x, bit_depth=bits)
            sixteen = as_frame(x, bit_depth=16)
        assert torch.allclose(f[0, 0], cli.reshape(f.shape[-2:]), atol=1e-6) and float(f.max()) == 1.0
        # without bit_depth, DN/65535 as before, and a warning that names the bits the values fit
        with pytest.warns(UserWarning, match=rf"largest value {top} fits {bits} bits: .* pass bit_depth={bits} "
                                             rf"\(read as 16-bit data the frame is {2 ** (16 - bits)}× too dark"):
            default = as_frame(x)
        assert torch.equal(default, sixteen) and float(default.max()) == pytest.approx(top / 65535)
    mon = Monitor(FakeNoise(), None, sensor="ICX285", mode="map")
    assert mon.process(arr, bit_depth=bits).noise.value("total") == pytest.approx(
        mon.process((cli[0] * 255).round().to(torch.uint8).numpy()).noise.value("total"), rel=0.1)


@pytest.mark.parametrize("x,bit_depth,match", [
    (np.full((8, 8), 4096, np.uint16), 12, r"uint16 frame value 4096 exceeds the 12-bit range 0…4095 \(bit_depth = 12\)"),
    (torch.full((8, 8), 1024, dtype=torch.int32).to(torch.uint16), 10, "value 1024 exceeds the 10-bit range 0…1023"),
    (np.zeros((8, 8), np.uint16), 7, r"bit_depth = 7 must be None or an integer 8…16"),
    (np.zeros((8, 8), np.uint16), 17, r"bit_depth = 17 must be None or an integer 8…16"),
    (np.zeros((8, 8), np.uint16), 12.0, r"bit_depth = 12.0 must be None or an integer"),
    (np.zeros((8, 8), np.uint8), 12, "bit_depth = 12 is for uint16 frames; this frame is uint8"),
    (np.zeros((8, 8), np.float32), 12, "bit_depth = 12 is for uint16 frames; this frame is float32"),
    (torch.zeros(8, 8), 10, "bit_depth = 10 is for uint16 frames; this frame is torch.float32"),
])
def test_a_bit_depth_that_does_not_fit_the_frame_is_refused(x, bit_depth, match):
    with pytest.raises(ValueError, match=match):
        as_frame(x, bit_depth=bit_depth)
    with pytest.raises(ValueError, match=match):
        Monitor(FakeNoise(), None, sensor="ICX285").process(x, bit_depth=bit_depth)


def test_the_run_summary_holds_bounded_state(monkeypatch):
    """A monitor that runs for days keeps count, mean and maximum of the whole run and the median of the last
    SUMMARY_RECENT_FRAMES frames (the per-frame lists grew by one entry per frame)."""
    import camhealth.monitor.api as api

    monkeypatch.setattr(api, "SUMMARY_RECENT_FRAMES", 5)
    stat = api._RunStat()
    for v in range(1, 21):
        stat.add(float(v))
    assert len(stat.recent) == 5 and stat.stats(2) == {"median": 18.0, "mean": 10.5, "max": 20.0}
    assert api._RunStat().stats(1) == {"median": None, "mean": None, "max": None}
    mon = _monitor(warmup=False)
    for i in range(8):
        mon.process(torch.rand(64, 64, generator=torch.Generator().manual_seed(i)))
    assert len(mon._times.recent) == 5 and mon.summary()["ms_per_frame"]["max"] >= mon.summary()["ms_per_frame"]["median"]


def test_load_metadata_sensor_type_that_is_not_a_string_names_the_file(tmp_path):
    f = tmp_path / "cam.yaml"
    f.write_text("sensor: ICX285\nsensor_type: 5\n")
    with pytest.raises(ValueError, match=rf"metadata file {f}: camera metadata sensor_type must be 'CCD' or 'CMOS', got int 5"):
        load_metadata(str(f))


def test_a_frame_far_quieter_than_its_metadata_says_so():
    """A flat 0.3-DN frame for an ICX285 (≈ 1.5 DN at mid grey): no camera state in range explains it, so its noise
    patches are refused as quieter than the metadata allow and the alarm says what that may be."""
    from camhealth.estimators.physics_noise import LESS_NOISE
    from camhealth.monitor.api import QUIET_HINT

    rng = np.random.default_rng(0)
    img = np.clip(np.tile(np.linspace(60, 190, 640), (512, 1)) + 0.3 * rng.standard_normal((512, 640)), 0, 255)
    r = Monitor("noise_source_full", None, sensor="ICX285", warmup=False).process(img.round().astype(np.uint8))
    assert not r.noise.assessable and set(r.noise.refused) == {LESS_NOISE}
    assert r.alarm["state"] == "not_assessable" and QUIET_HINT in r.alarm["message"]


def test_as_frame_reads_big_endian_uint16_as_uint16():
    """A big-endian uint16 array (``>u2``: ``np.frombuffer`` of a ROS Image with ``is_bigendian``, a 16-bit PGM or FITS
    reader) is uint16: DN/65535, or DN/(2^bit_depth − 1) — not 8-bit DN (200 would read 257× too bright)."""
    native = as_frame(np.full((8, 8), 200, "<u2"), bit_depth=16)
    big = as_frame(np.full((8, 8), 200, ">u2"), bit_depth=16)
    assert torch.equal(big, native) and float(big[0, 0, 0, 0]) == pytest.approx(200 / 65535)
    assert float(as_frame(np.full((8, 8), 4000, ">u2"), bit_depth=12).mean()) == pytest.approx(4000 / 4095)
    with pytest.raises(ValueError, match="5000 exceeds the 12-bit range"):
        as_frame(np.full((8, 8), 5000, ">u2"), bit_depth=12)


def test_map_mode_frames_count_only_frames_that_gave_a_value():
    """Black frames give no value: they are not among the ``coverage.frames`` behind the answer, and do not shrink the
    pooled noise estimator's uncertainty floor (estimator_std/√frames) of the first real frame after them."""
    rng = np.random.default_rng(0)
    grey = np.clip(np.round(rng.normal(100, 12, (128, 256))), 0, 255).astype(np.uint8)  # two noise patches
    black = np.zeros((128, 256), np.uint8)
    reports = []
    for frames in ([grey], [black] * 4 + [grey]):
        mon = Monitor("noise_source_full", None, sensor="ICX285", mode="map", warmup=False)
        for f in frames:
            r = mon.process(f)
        reports.append(r.noise)
    alone, after = reports
    assert after.assessable and after.coverage["frames"] == alone.coverage["frames"] == 1
    from camhealth.monitor import NOISE_FIELDS

    xi = NOISE_FIELDS.index("xi")
    assert float(after.uncertainty[xi]) == pytest.approx(float(alone.uncertainty[xi]), rel=1e-6)
    assert float(after.uncertainty[xi]) >= float(after.estimator_std[xi]) - 1e-6


class _TwoBanded(FakeNoise):
    """Every patch assessable; row noise 1.6 DN on the first patch, 2.6 DN on the second (median 2.1 DN)."""

    def predict(self, patches, metadata=None, **kw):
        out = super().predict(patches, metadata)
        n = patches.shape[0]
        out["assessable"] = torch.ones(n, dtype=torch.bool)
        out["row_column_dn"] = torch.tensor([[1.6, 0.0], [2.6, 0.0]])[:n]
        return out


class _TwoBeyond(FakeNoise):
    """Every patch refused as beyond the validated range, with ξ −1.5 and −0.3 DN (median −0.9 DN)."""

    def predict(self, patches, metadata=None, **kw):
        from camhealth.estimators.physics_noise import BEYOND_VALIDATED

        out = super().predict(patches, metadata)
        n = patches.shape[0]
        out["assessable"] = torch.zeros(n, dtype=torch.bool)
        out["reason"] = [BEYOND_VALIDATED] * n
        out["xi"] = torch.tensor([-1.5, -0.3])[:n]
        out["follows_image"] = torch.ones(n, dtype=torch.bool)  # read from the image: their ξ is a bound
        return out


def test_banding_and_beyond_range_xi_are_true_medians_over_an_even_count_of_patches():
    """Two noise patches: the frame's banding and beyond-range ξ are the mean of the two (the median), not the lower
    one — 2.1 DN of row noise reaches MTF_BANDING_LIMIT_DN (2 DN), and ξ −0.9 DN is within the 1-DN threshold."""
    from camhealth.monitor import MTF_BANDING_LIMIT_DN

    g = torch.Generator().manual_seed(0)
    x = torch.linspace(0, 1, 256)[None, :].expand(192, 256)
    frame = (0.2 + 0.6 * ((x * 12).floor() % 2) + torch.randn(192, 256, generator=g) * 2 / 255).clamp(0, 1)
    r = Monitor(_TwoBanded(), FakeMTF(), sensor="ICX285", mode="map", adaptive=False, warmup=False).process(frame)
    assert r.noise.banding["patches"] == 2 and r.noise.banding["row_dn"] == pytest.approx(2.1)
    assert r.noise.banding["row_dn"] >= MTF_BANDING_LIMIT_DN and r.mtf.assessable is False
    r = Monitor(_TwoBeyond(), FakeMTF(), sensor="ICX285", mode="map", adaptive=False, warmup=False).process(frame)
    assert r.noise.beyond_xi == pytest.approx(-0.9)
    assert r.alarm["state"] == "not_assessable", r.alarm


class _BeyondUnread(_TwoBeyond):
    """Refused as beyond the validated range without a reading (the closed form's ξ = 0, ``follows_image`` False)."""

    def predict(self, patches, metadata=None, **kw):
        out = super().predict(patches, metadata)
        out["xi"] = torch.zeros(patches.shape[0])
        out["follows_image"] = torch.zeros(patches.shape[0], dtype=torch.bool)
        return out


def test_beyond_range_patches_without_a_reading_give_no_bound():
    """Patches refused as beyond the validated range whose noise was not read (clipped nearly everywhere: the
    finest-scale check alone) carry no ξ bound: the frame is not assessable with that reason named, not "the
    metadata predict as much"."""
    from camhealth.estimators.physics_noise import BEYOND_VALIDATED

    x = torch.linspace(0, 1, 256)[None, :].expand(192, 256)
    frame = noisy(0.2 + 0.6 * ((x * 12).floor() % 2), 2.0, 0)
    r = Monitor(_BeyondUnread(), FakeMTF(), sensor="ICX285", mode="map", adaptive=False, warmup=False).process(frame)
    assert r.noise.beyond_xi is None
    assert r.alarm["state"] == "not_assessable" and BEYOND_VALIDATED in r.alarm["message"], r.alarm
    assert "predict as much" not in r.alarm["message"]


class _NoMetadataNoiseSource(FakeNoise):
    metadata_set = "none"


def test_fields_given_without_a_preset_are_reported_as_given_not_completed_from_one():
    """Estimators that read no metadata, no sensor and no full set of fields: a frame's ``metadata`` holds the fields
    given (no exposure and temperature from the ICX285 preset that nobody named), ``None`` without any, a change of
    them restarts the aggregation, and ξ is not checked against made-up values."""
    x = torch.linspace(0, 1, 512)[None, None, :].expand(1, 384, 512)
    frame = noisy(0.2 + 0.6 * ((x * 24).floor() % 2), 2.0, 0)  # stripes: edges for the MTF
    mon = Monitor(None, FakeMTF(), mode="map", warmup=False)
    assert mon.process(frame).metadata is None
    r = mon.process(frame, metadata={"gain_db": 12})
    assert r.metadata == {"gain_db": 12.0}
    assert _strict(r.to_json())["metadata"] == {"gain_db": 12.0}
    kv = dict(key_values(r, OK))
    assert kv["gain_db"] == "12" and kv["exposure_s"] == kv["temperature_c"] == "nan"
    assert mon.process(frame, metadata={"gain_db": 12}).mtf.coverage["frames"] == 3
    assert mon.process(frame, metadata={"gain_db": 13}).mtf.coverage["frames"] == 1  # a change restarts it
    mon = Monitor(_NoMetadataNoiseSource(), None, metadata={"gain_db": 6.0}, warmup=False)
    r = mon.process(frame)
    assert r.metadata == {"gain_db": 6.0} and r.alarm["state"] == "unavailable"
    assert mon.process(frame, metadata={"temperature_c": 40}).metadata == {"gain_db": 6.0, "temperature_c": 40.0}
    # a named preset or a full set still gives the whole camera state
    full = mon.process(frame, metadata={"sensor": "ICX285", "gain_db": 6.0}).metadata
    assert set(full) == {"gain_db", "exposure_s", "temperature_c"}


class PooledFakeNoise(FakeNoise):
    """A pooled noise estimator stand-in: records the size of every call and refuses a call of fewer than
    ``min_pool`` patches as ``"no flat area"`` (a few patches have few flat details of their own)."""

    def __init__(self, min_pool: int = 4) -> None:
        super().__init__()
        self.min_pool = min_pool
        self.sizes: list[int] = []

    def predict(self, patches, metadata=None, precision="fp32", batch_size=256, pool=False):
        out = super().predict(patches, metadata, precision, batch_size)
        b = patches.shape[0]
        self.sizes.append(b)
        out["tag"] = torch.arange(b)  # which row of the call a patch's output came from
        if pool and b < self.min_pool:
            out["assessable"] = torch.zeros(b, dtype=torch.bool)
            out["reason"] = ["no flat area"] * b
        return out


@pytest.mark.parametrize("mode", ["map", "sampled"])
def test_a_pooled_noise_reading_of_few_patches_is_made_up_with_the_frames_others(mode, street_frames):
    from camhealth.monitor.api import NOISE_MIN_POOL

    fn = PooledFakeNoise(min_pool=NOISE_MIN_POOL)
    mon = _monitor(fn, None, mode=mode, window=3)
    scene = street_frames[0]
    few = 0
    for i in range(20):  # a still camera: each frame re-estimates only the patches due for their refresh
        calls = len(fn.sizes)
        r = mon.process(noisy(scene, 3.0, seed=i))
        assert r.noise.refused == {} and r.noise.counts["not_assessable"] == 0, (i, r.noise.refused)
        few += 0 < r.noise.coverage["estimated"] < NOISE_MIN_POOL and len(fn.sizes) > calls
    # every call read at least NOISE_MIN_POOL patches (the frame has more informative ones), though frames re-estimated
    # fewer: the others joined for their evidence only
    assert few > 0 and min(fn.sizes) >= NOISE_MIN_POOL


def test_a_pooled_reading_made_up_with_partners_keeps_the_partners_values(street_frames):
    from camhealth.monitor.api import REUSED, _first_rows

    fn = PooledFakeNoise(min_pool=1)
    mon = _monitor(fn, None, window=3)
    scene = street_frames[0]
    mon.process(noisy(scene, 3.0, seed=0))
    before = mon._states["noise"].values.clone()
    r = mon.process(noisy(scene, 3.0, seed=1))  # the same scene: most patches reused, a few due
    reused = mon._states["noise"].code == REUSED
    assert int(reused.sum()) > 0 and r.noise.counts["estimated"] < 8
    assert torch.equal(mon._states["noise"].values[reused], before[reused])
    # the helper cuts every per-patch output to the patches asked for, and leaves the frame's evidence and scalars
    out = {"sigma": torch.zeros(5, 3), "reason": ["", "a", "", "", ""], "evidence": torch.ones(5, 7), "n": 3,
           "mask": np.zeros((5, 1, 4, 4))}
    cut = _first_rows(out, 2, 5)
    assert cut["sigma"].shape == (2, 3) and cut["reason"] == ["", "a"] and cut["evidence"].shape == (5, 7)
    assert cut["n"] == 3 and cut["mask"].shape == (2, 1, 4, 4)


def test_a_still_cameras_gain_step_shows_with_reused_patches_as_without():
    """Map mode on a still camera: reused values enter the temporal window as the frame's values, so a gain step the
    metadata do not know (ICX285 at 12 dB, told 0 dB) raises the alarm, and its return clears it, in the same frames as
    when every patch is estimated every frame."""
    from camhealth.data import build_source
    from camhealth.physics import form_image

    photo, _ = build_source("skimage")[0]
    clean = photo[None, :, :384, :384]
    told = CameraMetadata.preset("ICX285", gain_db=0.0, exposure_s=0.02, temperature_c=45.0)
    states = {}
    for reuse in (True, False):
        mon = Monitor(noise_model="noise_source_full", mtf_model=None, metadata=told, window=3, mode="map",
                      reuse_static=reuse)
        g = torch.Generator().manual_seed(0)
        seq = []
        for t in range(12):
            cam = told.replace(gain_db=12.0 if 4 <= t < 8 else 0.0)
            shot = (form_image(clean, cam, generator=g).image[0, 0] * 255).round().to(torch.uint8)
            r = mon.process(shot)
            assert "no flat area" not in r.noise.refused, (reuse, t, r.noise.refused)
            seq.append(r.alarm["state"])
        states[reuse] = seq
    assert states[True] == states[False]
    assert states[True][:4] == ["ok"] * 4 and "noisier" in states[True][4:8] and states[True][-1] == "ok"


def test_the_alarm_quotes_the_metadatas_sigma_from_each_patch():
    """σ from the metadata in the alarm's message is the median over the patches of σ_Total + ξ (each patch's closed
    form), not the frame's median σ_Total plus its median ξ, which differ where the patches do not share one ξ."""
    from types import SimpleNamespace

    from camhealth.monitor.api import NOISE_FIELDS, _metadata_total

    # three patches: closed forms 2, 5 and 8 DN, read 3, 11 and 10 DN (ξ −1, −6, −2)
    values = torch.full((4, len(NOISE_FIELDS)), float("nan"))
    values[:3, NOISE_FIELDS.index("total")] = torch.tensor([3.0, 11.0, 10.0])
    values[:3, NOISE_FIELDS.index("xi")] = torch.tensor([-1.0, -6.0, -2.0])
    model = _metadata_total(SimpleNamespace(values=values))
    assert model == pytest.approx(5.0)  # the frame's medians would say 10 − 2 = 8
    msg = xi_alarm(-2.0, 0.1, 3, total_dn=10.0, model_dn=model)["message"]
    assert "σ from the metadata ≈ 5.00 DN, in the image ≈ 10.00 DN" in msg
    assert "≈ 8.00 DN" in xi_alarm(-2.0, 0.1, 3, total_dn=10.0)["message"]  # one shared ξ: total + ξ
    assert _metadata_total(SimpleNamespace(values=torch.full((2, 5), float("nan")))) is None


# ------------------------------------------------------------------ bad input (camhealth.monitor)
def _flat_frame(seed=0, size=(256, 384)):
    g = np.random.default_rng(seed)
    return np.clip(120 + g.normal(0, 3, size), 0, 255).astype(np.uint8)


def test_a_change_of_input_scaling_restarts_the_aggregation_with_a_warning():
    """A folder's 16-bit frames whose depth is guessed from their largest values (10 bits on dark frames, 12 on bright
    ones) were pooled in one window at two scales (σ 4× off). A change of the divisor restarts the aggregation, as a
    change of metadata does, with a warning naming both scalings; every JSON line names its frame's scaling."""
    from camhealth.data.io import ImageScaling
    from camhealth.monitor.api import InputScalingChanged

    mon = _monitor(FakeNoise(), None, adaptive=False)
    ten = [ImageScaling(16, 10, "largest value", v) for v in (811.0, 793.0)]
    twelve = [ImageScaling(16, 12, "largest value", v) for v in (2712.0, 2720.0)]
    frame = _flat_frame()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the same divisor (another largest value) is no change: no warning
        reports = [mon.process(frame, input_scaling=s) for s in ten]
    assert [r.noise.coverage["frames"] for r in reports] == [1, 2]
    line = _strict(reports[0].to_json())
    assert line["input_scaling"] == "16-bit file read as 10-bit data (÷1023, guessed from the largest value 811)"
    with pytest.warns(InputScalingChanged, match=r"from '16-bit file read as 10-bit data \(÷1023.*' to '16-bit file read "
                                                 r"as 12-bit data \(÷4095.*': the temporal aggregation restarts.*--bit-depth"):
        changed = mon.process(frame, index=2, source_id="f2.png", input_scaling=twelve[0])
    assert changed.noise.coverage["frames"] == 1 and changed.input_scaling.startswith("16-bit file read as 12-bit")
    assert mon.process(frame, input_scaling=twelve[1]).noise.coverage["frames"] == 2
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = mon.process(frame)  # no scaling given: nothing said, nothing restarted
    assert r.noise.coverage["frames"] == 3 and r.input_scaling is None and _strict(r.to_json())["input_scaling"] is None
    with pytest.warns(InputScalingChanged, match="mono8: 8-bit data"):  # a text (a recording's) is judged as it is
        mon.process(frame, input_scaling="mono8: 8-bit data (÷255)")
    with pytest.raises(TypeError, match="input_scaling = 12 must be None, a text or"):
        mon.process(frame, input_scaling=12)


@pytest.mark.parametrize("kwargs, error, match", [
    ({"xi_sigmas": True}, ValueError, r"xi_sigmas = True must be a finite number >= 0"),
    ({"xi_threshold_dn": np.True_}, ValueError, r"xi_threshold_dn = (np\.)?True_? must be a finite number >= 0"),
    ({"per_patch": "false"}, TypeError, r"per_patch = 'false' must be True or False"),
    ({"adaptive": "no"}, TypeError, r"adaptive = 'no' must be True or False"),
    ({"pool_noise": 0}, TypeError, r"pool_noise = 0 must be True or False"),
    ({"reuse_static": None}, TypeError, r"reuse_static = None must be True or False"),
    ({"window": 1001}, ValueError, r"window = 1001 must be an integer 1…1000 \(frames\)"),
    ({"window": 2**40}, ValueError, r"window = 1099511627776 must be an integer 1…1000"),
    ({"noise_samples": 257}, ValueError, r"noise_samples = 257 must be an integer 1…256 \(patches per frame\)"),
    ({"mtf_samples": 10**9}, ValueError, r"mtf_samples = 1000000000 must be an integer 1…256"),
    ({"selection": {"max_age": 3}}, TypeError, r"selection = \{'max_age': 3\} must be a SelectionConfig.*got dict"),
])
def test_monitor_options_of_the_wrong_kind_or_beyond_their_range_are_refused(kwargs, error, match):
    """``Monitor(xi_sigmas=True)`` was 1σ, ``per_patch="false"`` was True (``bool()``), ``window=2**40`` a torch
    allocation error, ``selection={...}`` an AttributeError deep in the tiling: each is refused naming the value."""
    with pytest.raises(error, match=match):
        _monitor(FakeNoise(), FakeMTF(), **kwargs)


def test_the_largest_window_and_samples_are_accepted():
    from camhealth.monitor.api import MAX_SAMPLES, MAX_WINDOW

    mon = _monitor(FakeNoise(), None, mode="sampled", window=MAX_WINDOW, noise_samples=MAX_SAMPLES, warmup=False)
    assert mon.process(_flat_frame()).noise.assessable


@pytest.mark.parametrize("value, match", [
    (np.array(True), r"gain_db = array\(True\) must be a number"),
    (torch.tensor(True), r"gain_db = tensor\(True\) must be a number"),
    (None, r"gain_db = None must be a number"),
])
def test_per_frame_metadata_that_is_a_bool_array_or_none_is_refused(value, match):
    """A 0-d bool array or tensor became gain 1 dB (and an alarm stated on it); None became "gain_db = nan"."""
    mon = _monitor(FakeNoise(), None)
    with pytest.raises(ValueError, match=match):
        mon.process(_flat_frame(), {"gain_db": value})
    assert mon.process(_flat_frame(), {"is_cmos": np.array(True)}).metadata is not None  # is_cmos is a bool field


def test_per_frame_metadata_with_an_unknown_field_lists_the_known_ones():
    mon = _monitor(FakeNoise(), None)
    with pytest.raises(ValueError, match=r"per-frame metadata: unknown metadata field\(s\) \['bogus'\]; known fields: "
                                         r"\['gain_db', 'exposure_s'"):
        mon.process(_flat_frame(), {"bogus": 1, "gain_db": 3.0})


@pytest.mark.parametrize("x", [np.full((8, 8), 1e300), torch.full((8, 8), 1e300, dtype=torch.float64),
                               np.full((8, 8, 3), -1e300)])
def test_a_huge_finite_float_frame_is_out_of_range_not_non_finite(x):
    """A float64 frame of 1e300 overflowed to inf in float32 (a RuntimeWarning, then "non-finite"): it is finite and
    outside [0, 1], and says so."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match=r"float frame values must lie in \[0, 1\], got min -?1e\+300"):
            as_frame(x)
