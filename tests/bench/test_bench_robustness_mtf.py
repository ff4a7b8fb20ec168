"""The MTF task of ``python -m camhealth.bench robustness``: its kernels, conditions and metric (the full run is a
benchmark, not a test)."""

from __future__ import annotations

import pytest
import torch

from camhealth.bench import robustness_mtf as rm
from camhealth.bench.__main__ import parse
from camhealth.physics import mtf_hv


@pytest.mark.parametrize("gen", [g for gens in rm.FAMILIES.values() for g in gens] + list(rm.IN_DIST.values()))
@pytest.mark.parametrize("size", [3.0, 21.0])
def test_every_generator_gives_normalised_kernels_of_its_size(gen, size):
    k = rm.make_kernels(gen, size, 4, torch.Generator().manual_seed(0))
    assert k.shape == (4, rm.KERNEL, rm.KERNEL) and bool((k >= 0).all())
    torch.testing.assert_close(k.sum((1, 2)), torch.ones(4, dtype=k.dtype), atol=1e-6, rtol=0)
    m = mtf_hv(k.double())
    if gen != "tiny":  # a bigger blur is a softer blur
        small = mtf_hv(rm.make_kernels(gen, 1.0, 4, torch.Generator().manual_seed(0)).double())
        assert float(m[:, 7].mean() + m[:, 15].mean()) < float(small[:, 7].mean() + small[:, 15].mean())


def test_accelerating_line_keeps_its_length_and_moves_mass():
    uniform = rm._point_line(torch.tensor([11.0]), torch.tensor([0.0]), torch.zeros(1, 2), torch.zeros(1))
    ramp = rm._point_line(torch.tensor([11.0]), torch.tensor([0.0]), torch.zeros(1, 2), torch.ones(1))
    row = rm.KERNEL // 2
    assert int((uniform[0, row] > 0).sum()) == int((ramp[0, row] > 0).sum()) == 11
    assert float(ramp[0, row].max()) > 1.5 * float(uniform[0, row].max())  # slow start: mass piles up


def test_conditions_round_to_8_bit_and_noise_is_5_dn():
    g = torch.Generator().manual_seed(2)
    x = torch.full((4, 1, 192, 192), 0.5)
    for cond in rm.CONDITIONS:
        y = rm.degrade(x, cond, g)
        assert y.shape == x.shape and torch.equal((y * 255).round(), y * 255)
    n5 = rm.degrade(x, "noise5", g)
    assert abs(float(((n5 - 0.5) * 255).std()) - 5.0) < 0.2


def test_amae_is_the_training_metric():
    est, truth = torch.rand(5, 16), torch.rand(5, 16)
    want = 100 * (est - truth).abs().view(5, 2, 8).mean(2).mean(1)
    torch.testing.assert_close(rm._amae(est, truth).float(), want)


def test_task_switch_defaults_to_noise():
    assert parse(["robustness"]).task == "noise"
    a = parse(["robustness", "--task", "mtf", "--per-cell", "2", "--mtf-sizes", "3", "9"])
    assert a.task == "mtf" and a.per_cell == 2 and a.mtf_sizes == [3.0, 9.0]
    with pytest.raises(SystemExit):
        parse(["robustness", "--task", "blur"])



def test_chart_rois_straddle_the_rendered_squares_edges():
    """The chart is rendered at CHART_SIZE px and cropped to the patch: each ROI's edge (the 0.5 crossing of the
    profile across it) lies at its centre, with as much of the square as of the background in it."""
    from camhealth.estimators.charts import slanted_edge_chart

    chart = [("chart", slanted_edge_chart(rm.CHART_SIZE, rm.CHART_ANGLE_DEG, rm.CHART_SQUARE_FRAC)[0])]
    delta = torch.zeros(1, rm.KERNEL, rm.KERNEL, dtype=torch.float64)
    delta[0, rm.KERNEL // 2, rm.KERNEL // 2] = 1.0  # no blur: the crop itself
    x = rm.blur_patches([chart], delta, torch.Generator().manual_seed(0))[0][0, 0]
    for name, (r0, r1, c0, c1) in rm.chart_rois().items():
        roi = x[r0:r1, c0:c1]
        prof = roi.mean(0) if name in ("left", "right") else roi.mean(1)  # across the edge
        cross = torch.nonzero(torch.diff(torch.sign(prof - 0.5)) != 0).flatten()
        assert cross.numel() == 1 and abs(float(cross[0]) + 0.5 - (prof.numel() - 1) / 2) <= 1.0, name
        assert abs(float((roi < 0.5).float().mean()) - 0.5) < 0.02, name


def test_slanted_edge_reference_reads_the_chart_cells_to_their_exact_mtf(monkeypatch):
    """The benchmark's slanted-edge path (make_cells' chart cells, slanted_edge_reference) on Gaussian and linear
    motion blur, clean: within 1.5 % AMAE of the kernels' exact MTF in the directions the chart's edges measure
    (5°/95°) — the reference the table prints. (ROIs of a 192-px chart, 8 px off the rendered square's edges, read
    2.9 % at 15 px; the 0°/90° truth is 4–6 % off for linear motion.)"""
    from camhealth.physics import mtf_from_psf

    flat = [("flat", torch.full((1, 256, 256), 0.5))]
    monkeypatch.setattr(rm, "scene_sources", lambda seed: {gr: flat for gr in rm.GROUPS})  # the charts are the point
    monkeypatch.setattr(rm, "_dead_leaves", lambda n, seed: [torch.full((1, 256, 256), 0.5)])
    monkeypatch.setattr(rm, "FAMILIES", {"defocus": ("gaussian",), "linear": ("line_sampled",)})
    monkeypatch.setattr(rm, "IN_DIST", {})
    monkeypatch.setattr(rm, "CONDITIONS", ("clean",))
    kernels = []
    make = rm.make_kernels
    monkeypatch.setattr(rm, "make_kernels", lambda *a: kernels.append(make(*a)) or kernels[-1])
    _, charts = rm.make_cells(8, (9.0, 15.0), 0)
    rm.slanted_edge_reference(charts)
    assert len(charts) == len(kernels) == 4  # one chart cell per held-out generator × size × clean
    for c, k in zip(charts, kernels):
        k = k[: c.image.shape[0]]
        exact = mtf_from_psf(k, (5.0, 95.0)).reshape(k.shape[0], -1)
        err = rm._amae(c.out["edge"]["mtf"], exact)
        assert float(err.mean()) <= 1.5, (c.generator, c.size, err.tolist())
        torch.testing.assert_close(c.edge_truth, exact.float())
        pred = lambda d, cell=c: d is cell  # noqa: E731
        assert rm._agg(charts, "edge", pred, truth="edge_truth")[0] == pytest.approx(float(err.mean()))

class _FakeEstimator:
    """Reads every patch as a fixed MTF: enough to run the whole report without a network."""

    name = "fake"
    kind = "mtf"
    patch_size = 192

    def predict(self, x, views=1, **kwargs):
        n = x.shape[0]
        return {"mtf": torch.full((n, 16), 0.5), "assessable": torch.ones(n, dtype=torch.bool),
                "mtf_std": torch.full((n, 16), 0.1), "mtf_spread": torch.full((n, 16), 0.05)}


def test_tiny_benchmark_reports_every_scene_group(monkeypatch, tmp_path):
    import argparse
    import json

    import camhealth.data.native_mtf as nm
    import camhealth.inference as inf

    monkeypatch.setattr(rm, "RENDERED_PER_CLASS", 1)
    monkeypatch.setattr(rm, "FAMILIES", {"defocus": ("gaussian",), "tiny": ("tiny",)})  # one of each kind: fast
    monkeypatch.setattr(rm, "IN_DIST", {"defocus": "disk"})
    monkeypatch.setattr(rm, "CONDITIONS", ("clean", "noise5"))  # the two the chart and the tables need
    monkeypatch.setattr(inf, "load_estimator", lambda name: _FakeEstimator())
    monkeypatch.setattr(nm, "native_mtf_table", lambda: {"street": {"n": 1, "mtf_0.3": 0.9, "mtf_0.6": 0.3}})
    args = argparse.Namespace(per_cell=4, mtf_sizes=[3.0], seed=0, models=None, json=tmp_path / "r.json",
                              command_line="test")
    res = rm.run(args)
    out = json.loads((tmp_path / "r.json").read_text())
    n_cells = (sum(len(g) for g in rm.FAMILIES.values()) + len(rm.IN_DIST)) * len(rm.CONDITIONS)  # one size
    assert out["patches_per_group"] == {"rendered": 2 * n_cells, "photos": n_cells, "street": n_cells}  # R P R S
    groups = out["fake"]["families"]["defocus"]["groups"]
    assert set(groups) == set(rm.GROUPS) and all(v["n_held_out"] > 0 for v in groups.values())
    # the truth is exact per patch, so a constant 0.5 scores differently on each group's kernels but always finite
    assert all(v["held_out"] == v["held_out"] for v in groups.values())
    text = "\n".join(res.summary)
    assert "held-out generators × rendered scenes" in text and "truth ignores the scene's own blur" in text
    assert "| rendered (s = 8, closed form) |" in text
    # every patch assessable: the assessable-only columns equal the all-patch ones
    gen = out["fake"]["generators"]["gaussian"]
    assert gen["clean_assessable"] == gen["clean"] and gen["noise5_assessable"] == gen["noise5"]
    assert "| noise 5 / clean, assessable |" in text
    size = out["fake"]["sizes"]["3.0"]
    assert size["assessable"]["all"] == size["all"] and size["assessable"]["defocus"] == size["defocus"]
    # a constant 0.5 against 3-px kernels (MTF near 1 at low frequencies) reads them as more blurred: signed error < 0
    from camhealth.bench.rendered_scenes import CLASSES
    bias = [b for b in size["bias_clean"].values() if b == b]  # NaN: no clean patch of that class at one scene per class
    assert set(size["bias_clean"]) == set(CLASSES) and bias and all(b < 0 for b in bias)
    assert "| all, assessable |" in text
    # the PSF generalisation alone: held-out over training generators, both clean on the same rendered scenes
    fam = out["fake"]["families"]["defocus"]
    assert fam["clean_over_in_dist_rendered"] == pytest.approx(fam["clean"] / fam["in_dist_rendered"])
    assert fam["clean_over_in_dist_dead_leaves"] == pytest.approx(fam["clean"] / fam["in_dist_dead_leaves"])
    assert "| clean / in-dist. gen. × rendered |" in text
    # the uncertainty table: per scene group and views, the shares within u and 2u, the spread alone beside it
    unc = out["fake"]["uncertainty"]
    for gr in rm.GROUPS:
        row = unc[f"{gr}/views4"]
        assert 0 <= row["within_1std"] <= row["within_2std"] <= 1 and row["mean_std"] == pytest.approx(0.1)
        assert row["within_2spread"] <= row["within_2std"]  # 2·0.05 < 2·0.1
    assert "| rendered | 4 |" in text and "views' spread alone" in text
    # row noise after the blur: one row per level; a constant estimate reads the same error whatever the banding
    band = out["fake"]["banding"]
    assert set(band) == {str(b) for b in rm.BANDING_DN}
    assert len({round(v["across"], 9) for v in band.values()}) == 1 and all(v["assessable"] == 1.0 for v in band.values())
    assert "| row noise [DN] | AMAE across the rows (V) % |" in text
    # white noise and JPEG after the blur, paired: the same patches (so the same truths) in every row — a constant
    # estimate reads the same error in every row, per family and in all, and the ratio to the untouched patches is 1
    paired = out["fake"]["paired"]
    assert set(paired) == {"none" if k == "none" else f"{k}_{v}" for k, v in rm.PAIRED}
    for v in paired.values():
        assert set(v) >= {*rm.FAMILIES, "all", "ratio", "share_assessable"}
        assert v["ratio"]["all"] == pytest.approx(1.0) and v["share_assessable"] == 1.0
        for f in (*rm.FAMILIES, "all"):
            assert v[f]["all"] == pytest.approx(paired["none"][f]["all"]) and v[f]["assessable"] == v[f]["all"]
    assert "| after the blur | defocus | tiny | all families | ratio to none | share assessable |" in text
    assert "| white noise 5 DN |" in text and "| JPEG q 75 |" in text
    # defective pixels after the blur: one row per share, as shipped and without the repair
    defects = out["fake"]["defects"]
    assert set(defects) == {str(s) for s in rm.DEFECT_SHARES}
    assert all(set(v) == {"shipped", "unrepaired"} and v["shipped"]["assessable"] == 1.0 for v in defects.values())
    assert "| defective pixels | as shipped: all / assessable |" in text
    # per frame, what the monitor reports: a constant estimate gives the frame the same MTF as each of its patches,
    # so the frame answer's AMAE is its assessable patches' (on every family and scene class with an answer)
    frames = out["fake"]["frames"]
    assert set(frames) == {*rm.FAMILIES, *CLASSES}
    assert [frames[f]["frames"] for f in rm.FAMILIES] == [rm.FRAMES_PER_CELL] * len(rm.FAMILIES)  # one generator, one size
    assert sum(frames[c]["frames"] for c in CLASSES) == rm.FRAMES_PER_CELL * len(rm.FAMILIES)
    answered = [v for v in frames.values() if v["answered"] > 0]
    assert answered and all(v["frame"] == pytest.approx(v["patches_assessable"]) for v in answered)
    assert "| family or scene class | frames | frame answer | its assessable patches | frames with an answer |" in text
    # the slanted-edge reference: against the truth in its edges' directions and against 0°/90°
    chart = out["fake"]["chart"]["defocus/clean"]
    assert set(chart) == {"network", "edge", "edge_vs_0_90"} and all(v == v for v in chart.values())
    assert "| family | condition | network | slanted edge (truth at 5°/95°) | slanted edge against 0°/90° |" in text


@pytest.mark.parametrize("per_cell,sizes,match", [
    (0, (3.0,), r"per_cell = 0 is out of the allowed range \[1, 256\]"),
    (2, (31.0,), r"sizes = \[31.0\] must be non-empty with every size in the allowed range \[0, 29\] px"),
])
def test_make_cells_rejects_bad_arguments(per_cell, sizes, match):
    with pytest.raises(ValueError, match=match):
        rm.make_cells(per_cell, sizes, 0)


def test_scene_frames_are_seeded_8_bit_crops_of_one_scene_each():
    from camhealth.physics import defocus_psf

    scenes = [("a", torch.full((1, 640, 640), 0.25)), ("b", torch.full((1, 640, 640), 0.75))]
    k = defocus_psf(torch.tensor([5.0, 9.0, 3.0]), rm.KERNEL)
    x, labels = rm.scene_frames(scenes, k, torch.Generator().manual_seed(1))
    y, _ = rm.scene_frames(scenes, k, torch.Generator().manual_seed(1))
    side = rm.FRAME_GRID * rm.PATCH
    assert x.shape == (3, 1, side, side) and torch.equal(x, y) and set(labels) <= {"a", "b"}
    assert torch.equal((x * 255).round(), x * 255)  # 8-bit
    for img, lab in zip(x, labels):  # a flat scene stays flat: no border of the convolution entered the frame
        assert torch.allclose(img, torch.full_like(img, 0.25 if lab == "a" else 0.75), atol=0.5 / 255)
    with pytest.raises(ValueError, match=r"at least 608 px a side .*\(320, 320\) \(small\)"):
        rm.scene_frames(scenes + [("small", torch.zeros(1, 320, 320))], k, torch.Generator())
    with pytest.raises(ValueError, match="got none"):
        rm.scene_frames([], k, torch.Generator())


def test_calibration_cells_use_training_generators_on_their_own_rendered_scenes(monkeypatch):
    monkeypatch.setattr(rm, "CALIBRATION_PER_CLASS", 1)
    cells = rm.calibration_cells(2, (3.0, 9.0), 0)
    assert len(cells) == len(rm.IN_DIST) * 2 * len(rm.CONDITIONS)
    assert {c.generator for c in cells} == set(rm.IN_DIST.values()) and {c.scene for c in cells} == {"rendered"}
    from camhealth.bench.rendered_scenes import CLASSES
    assert all(c.image.shape == (2, 1, rm.PATCH, rm.PATCH) and set(c.labels) <= set(CLASSES) for c in cells)
    with pytest.raises(ValueError, match=r"per_cell = 0 is out of the allowed range \[1, 256\]"):
        rm.calibration_cells(0, (3.0,), 0)
    with pytest.raises(ValueError, match=r"sizes = \[40.0\] must be non-empty with every size in the allowed range \[0, 29\] px"):
        rm.calibration_cells(2, (40.0,), 0)


def test_mtf_error_benchmark_fits_and_writes_the_table(monkeypatch, tmp_path):
    """``bench mtf_error --write`` on an (untrained) MTF network: the table lands in the file, the estimator reads it."""
    import argparse
    import json

    from camhealth.bench import mtf_error
    from camhealth.export import export_weights
    from camhealth.inference import load_estimator
    from lightning_modules import MTFEstimator

    monkeypatch.setattr(rm, "CALIBRATION_PER_CLASS", 1)
    monkeypatch.setattr(rm, "CALIBRATION_FRAME_SCENES", 1)
    path = export_weights(MTFEstimator(), tmp_path / "m.pt")
    args = argparse.Namespace(models=[str(path)], per_cell=2, sizes=[3.0], seed=0, write=True, json=tmp_path / "e.json",
                              command_line="test", frames=2)
    res = mtf_error.run(args)
    table = json.loads((tmp_path / "e.json").read_text())["m"]["table"]
    est = load_estimator(path)
    assert est.description["mtf_error"] == table and len(table["rms"]) == len(table["knots"])
    assert 0.0 <= table["shared"] <= 1.0 and est.mtf_error.shared == table["shared"]
    assert "Shared by the patches of one scene" in "\n".join(res.summary)
    out = est.predict(torch.full((1, 1, 192, 192), 0.5) + 0.2 * (torch.rand(1, 1, 192, 192) > 0.5))
    assert torch.isfinite(out["mtf_std"]).all() and (out["mtf_std"] > 0).all()
    assert "| RMS |" in "\n".join(res.summary)
    noise = tmp_path / "n.pt"
    from lightning_modules import NoiseLevelEstimator
    export_weights(NoiseLevelEstimator(), noise)
    with pytest.raises(ValueError, match="calibrates MTF estimators"):
        mtf_error.run(argparse.Namespace(**{**vars(args), "models": [str(noise)]}))
