"""Sampled mode of the monitor (a moving camera): which patches are sampled, the coverage fields, the JSON lines
of the CLI, and agreement of the frame-level answer with every informative patch on a stream of known noise."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from camhealth.monitor import Monitor
from camhealth.monitor.tiling import (
    ESTIMATED,
    UNSAMPLED,
    QUIET_FRACTION,
    PatchGrid,
    grid_statistics,
    quiet_patches,
    sample_patches,
    select_patches,
)
from tests.monitor.conftest import FakeMTF, FakeNoise, noisy, run_monitor_cli


def _ramp_frame(h=512, w=768, sigma_dn=2.0, seed=0):
    """A frame whose 128-px patches have distinct mean intensities (a ramp over the patches) plus white noise."""
    g = torch.Generator().manual_seed(seed)
    grid = PatchGrid.fit(h, w, 128)
    levels = torch.linspace(30, 220, grid.n).reshape(grid.rows, grid.cols)
    clean = levels.repeat_interleave(128, 0).repeat_interleave(128, 1)
    x = clean + torch.randn(h, w, generator=g) * sigma_dn
    return (x / 255.0).clamp(0, 1)[None, None], grid


def test_noise_samples_spread_over_intensity_and_rotate():
    frame, grid = _ramp_frame()
    stats = grid_statistics(frame, grid)
    informative, _ = select_patches(stats, "noise")
    assert int(informative.sum()) == grid.n == 24
    last = torch.full((grid.n,), -1, dtype=torch.long)
    idx = sample_patches(grid, stats, informative, 4, "noise", last)
    assert idx.numel() == 4 and idx.unique().numel() == 4
    # one sample per intensity quartile: the ramp puts patches 0-5, 6-11, 12-17, 18-23 in the four strata
    assert sorted((idx // 6).tolist()) == [0, 1, 2, 3]
    seen = set(idx.tolist())
    for frame_no in range(1, 6):  # rotation: patches never sampled are preferred
        last[idx] = frame_no - 1
        idx = sample_patches(grid, stats, informative, 4, "noise", last)
        assert sorted((idx // 6).tolist()) == [0, 1, 2, 3]
        seen |= set(idx.tolist())
    assert len(seen) >= 12  # at least the flatter half of every stratum was visited


def test_mtf_samples_one_per_sector_and_only_informative():
    g = torch.Generator().manual_seed(1)
    blocks = torch.rand(1, 1, 36, 48, generator=g)  # 16-px texture everywhere: every 192-px patch informative
    frame = blocks.repeat_interleave(16, 2).repeat_interleave(16, 3)
    frame[..., :192, :] = 0.5  # top row featureless
    grid = PatchGrid.fit(576, 768, 192)
    stats = grid_statistics(frame, grid)
    informative, code = select_patches(stats, "mtf")
    assert not bool(informative[: grid.cols].any()) and bool(informative[grid.cols :].all())
    idx = sample_patches(grid, stats, informative, 4, "mtf", torch.full((grid.n,), -1, dtype=torch.long))
    assert idx.numel() == 4 and bool(informative[idx].all())
    from camhealth.monitor.tiling import _sector_ids

    assert sorted(_sector_ids(grid, 4)[idx].tolist()) == [0, 1, 2, 3]  # one per sector
    # k greater than the informative patches: all of them
    all_idx = sample_patches(grid, stats, informative, 50, "mtf", torch.full((grid.n,), -1, dtype=torch.long))
    assert all_idx.tolist() == informative.nonzero()[:, 0].tolist()


@pytest.mark.parametrize("k", [0, -1, 2.5, True])
def test_sample_patches_rejects_bad_k(k):
    frame, grid = _ramp_frame()
    stats = grid_statistics(frame, grid)
    inf, _ = select_patches(stats, "noise")
    with pytest.raises(ValueError, match="k = "):
        sample_patches(grid, stats, inf, k, "noise", torch.full((grid.n,), -1, dtype=torch.long))
    with pytest.raises(ValueError, match="must be"):
        sample_patches(grid, stats, inf[:3], 2, "noise", torch.full((grid.n,), -1, dtype=torch.long))
    with pytest.raises(ValueError, match="task"):
        sample_patches(grid, stats, inf, 2, "blur", torch.full((grid.n,), -1, dtype=torch.long))


def test_quiet_patches_are_sampled_only_where_nothing_else_is():
    """Noise: patches far quieter than the camera's closed form (a noiseless overlay) are not sampled while any other
    candidate is left — the strata are formed over the others — and a frame quiet everywhere is sampled as before."""
    frame, grid = _ramp_frame()
    frame[..., :256, :] = 128 / 255  # the top two rows of patches (12 of 24): a noiseless mid-grey overlay
    stats = grid_statistics(frame, grid)
    informative, _ = select_patches(stats, "noise")
    assert bool(informative[:12].all())  # flat and unclipped: candidates, and the flattest of all
    model = torch.full((grid.n,), 2.0)  # the camera's σ_Total [DN]
    quiet = quiet_patches(stats, model)
    assert quiet[:12].all() and not quiet[12:].any()
    assert bool((stats.noise_dn[12:] > QUIET_FRACTION * 2.0).all())
    last = torch.full((grid.n,), -1, dtype=torch.long)
    without = sample_patches(grid, stats, informative, 8, "noise", last)
    assert bool((without < 12).any())  # the old choice: overlay patches among the samples
    idx = sample_patches(grid, stats, informative, 8, "noise", last, quiet)
    assert idx.numel() == 8 and bool((idx >= 12).all())
    few = informative.clone()
    few[14:] = False  # two camera patches left: those two only, no overlay patch to outvote them
    assert sample_patches(grid, stats, few, 8, "noise", last, quiet).tolist() == [12, 13]
    everywhere = torch.ones(grid.n, dtype=torch.bool)  # quiet everywhere: sampled as without the flag
    assert torch.equal(sample_patches(grid, stats, informative, 8, "noise", last, everywhere), without)
    mtf = sample_patches(grid, stats, informative, 4, "mtf", last)  # the MTF's sampling ignores it
    assert torch.equal(sample_patches(grid, stats, informative, 4, "mtf", last, quiet), mtf)
    with pytest.raises(ValueError, match="quiet must be"):
        sample_patches(grid, stats, informative, 8, "noise", last, quiet[:3])
    with pytest.raises(ValueError, match="model_sigma_dn must be"):
        quiet_patches(stats, model[:3])


def test_a_noiseless_overlay_does_not_take_the_first_frames_samples():
    """A still camera (ICX285, its metadata right) whose frame is half a noiseless mid-grey overlay: the sampled
    monitor's noise samples go to the camera's own patches from the first frame on, and the frame is assessable
    (the overlay, the flattest patches, took every first-frame sample and the frame was refused as 'less noise than
    the metadata allow')."""
    from camhealth.bench.sensor_variants import simulate_variant
    from camhealth.physics.metadata import CameraMetadata

    meta = CameraMetadata.preset("ICX285")
    mon = Monitor(metadata=meta, mtf_model=None, mode="sampled", warmup=False)
    ramp = torch.linspace(0.25, 0.75, 640).expand(512, 640).clone().view(1, 1, 512, 640)
    for seed in range(2):
        frame = simulate_variant(ramp, meta, ("round8",), torch.Generator().manual_seed(seed))[0]
        frame[..., :256, :] = 128 / 255
        d = mon.process(frame).noise.to_dict()
        assert d["assessable"] and not d["refused"], d
        assert all(y >= 256 for _, y in d["coverage"]["patches_xy"]), d["coverage"]  # the camera's own patches
        assert abs(d["sigma_dn"]["xi"]["median"]) < 0.5, d["sigma_dn"]


@pytest.mark.parametrize("kw,match", [({"mode": "fast"}, "mode"), ({"noise_samples": 0}, "noise_samples"),
                                      ({"mtf_samples": 1.5}, "mtf_samples")])
def test_monitor_rejects_bad_mode_and_samples(kw, match):
    with pytest.raises(ValueError, match=match):
        Monitor(FakeNoise(), FakeMTF(), sensor="ICX285", **kw)


def test_auto_mode_is_sampled_unless_per_patch_maps():
    assert Monitor(FakeNoise(), FakeMTF(), sensor="ICX285").mode == "sampled"
    assert Monitor(FakeNoise(), FakeMTF(), sensor="ICX285", per_patch=True).mode == "map"
    assert Monitor(FakeNoise(), FakeMTF(), sensor="ICX285", mode="map").mode == "map"


def _moving_stream(street_frames, n, sigma_dn, size=(512, 768)):
    """A moving camera: every frame a different crop of a street frame, resized, with white noise of σ DN."""
    import kornia

    out = []
    for i in range(n):
        f = street_frames[i % len(street_frames)]
        y0, x0 = (i * 37) % 96, (i * 53) % 128
        crop = f[None, :, y0 : y0 + 480, x0 : x0 + 640]
        out.append(noisy(kornia.geometry.resize(crop, size, interpolation="bilinear")[0].clamp(0, 1), sigma_dn, seed=i))
    return out


def test_sampled_coverage_fields(street_frames):
    fn, fm = FakeNoise(), FakeMTF()
    mon = Monitor(fn, fm, sensor="ICX285", mode="sampled", noise_samples=5, mtf_samples=3, window=3)
    frames = _moving_stream(street_frames, 4, 3.0)
    for i, f in enumerate(frames):
        r = mon.process(f)
        d = json.loads(r.to_json())
        for task, k, rep in (("noise", 5, r.noise), ("mtf", 3, r.mtf)):
            cov = d[task]["coverage"]
            grid = rep.grid_obj
            est = (rep.code == ESTIMATED).nonzero()[:, 0]
            assert cov["mode"] == "sampled" and cov["total"] == grid.n
            assert cov["estimated"] == est.numel() == min(k, cov["informative"])
            assert cov["informative"] == int(((rep.code == ESTIMATED) | (rep.code == UNSAMPLED)).sum()) + d[task]["patches"]["not_assessable"]
            assert cov["patches_xy"] == grid.boxes()[est][:, :2].tolist()
            assert cov["area_fraction"] == pytest.approx(est.numel() * grid.patch**2 / (512 * 768), abs=1e-4)
            assert cov["frames"] == min(i + 1, 3) and cov["values"] == min(i + 1, 3) * k
            assert d[task]["patches"]["unsampled"] == cov["informative"] - cov["estimated"]
    assert fn.patches == 4 * 5 and fm.patches == 4 * 3  # only the samples went through the estimators


def test_sampled_agrees_with_every_patch_on_known_noise(street_frames):
    """Frame-level σ_total of sampled mode vs every informative patch, on a moving stream with σ = 4 DN white
    noise: within two combined standard errors of each other, and both near the truth."""
    sampled = Monitor(FakeNoise(), FakeMTF(), sensor="ICX285", mode="sampled", noise_samples=6, mtf_samples=4)
    full = Monitor(FakeNoise(), FakeMTF(), sensor="ICX285", mode="map", adaptive=False)
    for f in _moving_stream(street_frames, 6, 4.0):
        rs, rf = sampled.process(f), full.process(f)
    for task, get in (("noise", lambda r: (r.noise.value("total"), float(r.noise.uncertainty[-1]))),
                      ("mtf", lambda r: (r.mtf.indicator[0], r.mtf.indicator_uncertainty))):
        (vs, us), (vf, uf) = get(rs), get(rf)
        assert us > 0 and uf > 0, task
        assert abs(vs - vf) <= 2 * math.hypot(us, uf), (task, vs, us, vf, uf)
    assert rs.noise.value("total") == pytest.approx(4.0, rel=0.15)
    assert rs.noise.n_values == 5 * 6  # the window's samples


def test_sampled_physics_noise_agrees_with_every_patch_on_a_gain_mismatch(street_frames):
    """The shipped physics-first noise estimator, sensor noise at 18 dB while the metadata say 12 dB: ξ, σ_total
    and σ per source of the pooled samples agree with the pooled every-patch answer within two combined standard
    errors. With ``pool=True`` every value of a frame comes from one pooled posterior, so the stated uncertainty
    must include the frame-to-frame scatter: the spread over patches alone is ≈ 0 for σ_RN."""
    from camhealth.physics import CameraMetadata, form_image

    meta = CameraMetadata.preset("ICX285", gain_db=12.0, exposure_s=0.01, temperature_c=40.0)
    true = meta.replace(gain_db=18.0)
    g = torch.Generator().manual_seed(3)
    frames = [(form_image(f[None], true, generator=g).image[0, 0] * 255).round().to(torch.uint8)
              for f in _moving_stream(street_frames, 5, 0.0)]
    sampled = Monitor("noise_source_full", None, metadata=meta, mode="sampled", noise_samples=8)
    full = Monitor("noise_source_full", None, metadata=meta, mode="map", adaptive=False)
    for f in frames:
        rs, rf = sampled.process(f), full.process(f)
    assert rf.noise.value("xi") < -0.5  # the image is noisier than the metadata allow: a mismatch to follow
    for i, name in enumerate(("pn", "dcsn", "rn", "xi", "total")):
        vs, vf = float(rs.noise.median[i]), float(rf.noise.median[i])
        u = math.hypot(float(rs.noise.uncertainty[i]), float(rf.noise.uncertainty[i]))
        assert abs(vs - vf) <= 2 * u, (name, vs, vf, u)


def test_cli_sampled_mode_writes_json_lines_with_coverage(models, tmp_path, capsys):
    out = tmp_path / "run"
    code, _, err = run_monitor_cli(["street", "--sensor", "ICX285", "--max-frames", "3", "--mode", "sampled",
                                    "--noise-samples", "4", "--mtf-samples", "2", "--out", str(out), *models], capsys)
    assert code == 0, err
    lines = [json.loads(line) for line in (out / "monitor.jsonl").read_text().splitlines()]
    assert len(lines) == 3
    for d in lines:
        for task, k in (("noise", 4), ("mtf", 2)):
            cov = d[task]["coverage"]
            assert cov["mode"] == "sampled" and cov["estimated"] <= k and len(cov["patches_xy"]) == cov["estimated"]
            assert 0 < cov["area_fraction"] < 1
    summary = json.loads((out / "summary.json").read_text())
    assert summary["mode"] == "sampled" and summary["samples_per_frame"] == {"noise": 4, "mtf": 2}


def test_cli_auto_mode_uses_maps_for_per_patch(models, capsys):
    code, out, err = run_monitor_cli(["street", "--sensor", "ICX285", "--max-frames", "1", "--per-patch", "--no-mtf",
                                      *models], capsys)
    assert code == 0, err
    d = json.loads(out.splitlines()[0])
    assert d["noise"]["coverage"]["mode"] == "map" and d["noise"]["coverage"]["patches_xy"] is None
    assert len(d["noise"]["per_patch"]["status"]) == d["noise"]["coverage"]["total"]
    assert np.isfinite(d["noise"]["coverage"]["area_fraction"])


@pytest.mark.parametrize("value", [0.0, 1.0])
def test_sampled_black_or_white_frame_is_not_assessable_without_network_calls(value):
    fn, fm = FakeNoise(), FakeMTF()
    mon = Monitor(fn, fm, sensor="ICX285", mode="sampled")
    d = json.loads(mon.process(torch.full((512, 768), value)).to_json())
    assert d["assessable"] is False and d["noise"]["sigma_dn"] is None and d["mtf"]["indicator"] is None
    assert d["noise"]["coverage"]["estimated"] == 0 and d["noise"]["coverage"]["patches_xy"] == []
    assert fn.patches == 0 and fm.patches == 0


def test_sampled_small_frame_half_precision_and_metadata_reset(street_frames):
    fn = FakeNoise()
    mon = Monitor(fn, FakeMTF(), sensor="ICX285", mode="sampled", noise_samples=3, mtf_samples=2, window=4)
    d = json.loads(mon.process(torch.rand(100, 150)).to_json())  # smaller than one patch: documented skip
    assert d["noise"]["assessable"] is False and "smaller than one" in d["noise"]["note"]
    frames = _moving_stream(street_frames, 3, 3.0)
    for dtype in (torch.float16, torch.bfloat16, torch.float64):
        r = mon.process(frames[0].to(dtype))
        assert r.noise.assessable and r.noise.coverage["estimated"] == 3
    assert r.noise.n_values == 9  # three frames of three samples
    r = mon.process(frames[1], metadata={"gain_db": 12.0})  # a metadata change restarts the window
    assert r.noise.n_values == 3 and r.noise.coverage["frames"] == 1


def test_sampled_mode_reuses_unchanged_patches_of_a_static_camera():
    """A static scene: once a sampled patch has been estimated and has not changed, it keeps its estimate (status
    reused, no estimator call) and the frame answer is the one of a monitor that estimates every sampled patch
    again; a different scene is estimated afresh."""
    frame, _ = _ramp_frame(seed=5)
    counting = FakeNoise()
    adaptive = Monitor(counting, None, sensor="ICX285", mode="sampled", noise_samples=4)
    fresh = Monitor(FakeNoise(), None, sensor="ICX285", mode="sampled", noise_samples=4, adaptive=False)
    for _ in range(12):
        a, f = adaptive.process(frame), fresh.process(frame)
        cov = a.noise.coverage  # every sample has a value: estimated this frame, or its kept estimate
        assert cov["estimated"] + cov["reused"] == f.noise.coverage["estimated"] == 4
        assert torch.allclose(a.noise.median, f.noise.median, equal_nan=True)
        assert a.noise.n_values <= f.noise.n_values  # a kept estimate is one value, however many frames it recurs in
    assert a.noise.coverage["reused"] == a.noise.counts["reused"] > 0
    assert f.noise.coverage["reused"] == 0
    assert counting.patches < 12 * 4  # the first visit of each of the 24 patches, then reuse
    before = counting.patches
    adaptive.process(frame.flip(-1))  # another scene: every sampled patch is estimated again
    assert counting.patches - before == 4


class _EveryEstimateItsOwn(FakeNoise):
    """Every patch it estimates gets a σ of its own (1.00, 1.01, … DN in call order): a value says which estimate it is."""

    def predict(self, patches, metadata=None, precision="fp32", batch_size=256):
        out = super().predict(patches, metadata, precision, batch_size)
        total = 1.0 + 0.01 * torch.arange(self.patches - patches.shape[0], self.patches, dtype=torch.float32)
        out["sigma_total"], out["sigma"] = total, out["sigma"] * (total / out["sigma_total"])[:, None]
        return out


def test_sampled_coverage_and_window_count_each_estimate_once_on_a_static_camera():
    """A static scene in sampled mode, whose samples keep their estimates: ``coverage.estimated``, ``area_fraction`` and
    ``patches_xy`` count the patches estimated this frame only (as ``patches.estimated`` and the estimator's calls do),
    ``coverage.reused`` the kept ones; the window's median is that of its frames' samples, and its standard error counts
    the distinct estimates in it (``coverage.values``), not one kept estimate once per frame."""
    from camhealth.estimators.aggregation import spatial_median
    from camhealth.monitor.api import _MEDIAN_SE

    frame, _ = _ramp_frame(seed=5)
    fake = _EveryEstimateItsOwn()
    mon = Monitor(fake, None, sensor="ICX285", mode="sampled", noise_samples=4, window=5)
    seen: list[set[float]] = []
    samples: list[torch.Tensor] = []
    for i in range(10):
        before = fake.patches
        r = mon.process(frame)
        sent = fake.patches - before
        cov, grid = r.noise.coverage, r.noise.grid_obj
        est = (r.noise.code == ESTIMATED).nonzero()[:, 0]
        assert cov["estimated"] == r.noise.counts["estimated"] == est.numel() == sent  # (every patch assessable here)
        assert cov["reused"] == r.noise.counts["reused"] and cov["estimated"] + cov["reused"] == 4
        assert cov["patches_xy"] == grid.boxes()[est][:, :2].tolist()
        assert cov["area_fraction"] == pytest.approx(sent * 128**2 / (512 * 768), abs=1e-4)
        total = r.noise.values[:, -1]
        samples.append(total[torch.isfinite(total)])
        seen.append(set(samples[-1].tolist()))
        n = len(set().union(*seen[-5:]))  # the estimates in the window, each once
        assert cov["values"] == r.noise.n_values == n, (i, cov)
        window = spatial_median(torch.cat(samples[-5:]), dim=0)  # the answer: the samples of the window's frames
        assert float(r.noise.median[-1]) == pytest.approx(float(window.median), abs=1e-6)
        frames = min(i + 1, 5)
        per_frame = spatial_median(torch.stack([v.quantile(0.5) for v in samples[-5:]]), dim=0).spread  # (true median)
        expected = max(_MEDIAN_SE * float(window.spread) / math.sqrt(n),
                       _MEDIAN_SE * float(per_frame) / math.sqrt(frames) if frames > 1 else 0.0)
        assert float(r.noise.uncertainty[-1]) == pytest.approx(expected, rel=1e-4), i
    assert sum(len(v) for v in seen[-5:]) == 20 and r.noise.n_values < 20  # kept estimates recur in the window
    assert r.noise.coverage["reused"] > 0
