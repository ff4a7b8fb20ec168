"""The noise task of ``python -m camhealth.bench robustness``: its two scene scales, the frames that record them and
the tables per scale (the full run is a benchmark, not a test)."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
import torch

from camhealth.bench import robustness as rb
from camhealth.physics import CameraMetadata


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)  # many tiny tensors: more threads only contend
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def frames():
    return rb.make_frames(2, seed=0)  # one frame of each scale per condition


def test_scenes_are_the_originals_and_their_3x_area_downsampling():
    from camhealth.data.skimage_photos import SKIMAGE_PHOTOS, load_skimage_photo

    scenes = rb._scenes()
    assert set(scenes) == set(rb.SCENE_SCALES) == {"full", "3x"} and rb.SCENE_DOWNSAMPLE == 3
    photos = [load_skimage_photo(n) for n in SKIMAGE_PHOTOS]
    # full resolution: every photograph (none is shorter than 128 px) and the 10 street frames, untouched
    assert len(scenes["full"]) == len(photos) + 10
    assert all(torch.equal(s, p) for s, p in zip(scenes["full"], photos))
    assert tuple(scenes["full"][-1].shape) == (1, 576, 768)
    # 3×: the photographs at least 384 px on their short side, each the mean of 3×3 pixels
    kept = [p for p in photos if min(p.shape[-2:]) >= 3 * rb.PATCH]
    assert len(scenes["3x"]) == len(kept) + 10 and len(kept) < len(photos)
    p = kept[0]
    torch.testing.assert_close(scenes["3x"][0][0, 0, 0], p[0, :3, :3].mean())
    assert tuple(scenes["3x"][-1].shape) == (1, 192, 256)
    assert all(min(s.shape[-2:]) >= rb.PATCH for ss in scenes.values() for s in ss)


def test_every_frame_records_its_scale_and_both_scales_appear_in_every_condition(frames):
    assert len(frames) == 2 * len(rb.CONDITIONS)
    for cond in rb.CONDITIONS:
        assert [f.scale for f in frames if f.condition == cond] == ["full", "3x"]
    assert all(f.clean.shape == (16, 1, rb.PATCH, rb.PATCH) for f in frames)
    # the 3× scale packs a 384-px field into a patch: its scene floor is the higher one (seed 0: 0.8 vs 2.0 DN at
    # 16 frames per condition)
    floor = {s: np.nanmedian([f.scene_floor for f in frames if f.scale == s]) for s in rb.SCENE_SCALES}
    assert floor["full"] < floor["3x"]


def test_odd_frame_counts_give_the_first_scale_the_extra_frame(monkeypatch):
    flat = torch.full((1, 160, 160), 0.5)
    monkeypatch.setattr(rb, "_scenes", lambda: {"full": [flat], "3x": [flat.clone()]})
    monkeypatch.setattr(rb, "CONDITIONS", ("reference", "gain"))
    out = rb.make_frames(3, seed=1)
    assert len(out) == 6
    for cond in rb.CONDITIONS:
        assert [f.scale for f in out if f.condition == cond] == ["full", "3x", "full"]


@pytest.mark.parametrize("n", [2, 3])
def test_paired_frames_put_one_set_of_frames_under_every_condition(monkeypatch, n):
    """--paired: every condition's j-th frame has the same scene crop, told camera and random-number seed, so two
    conditions differ only by what they name (the matched variants' frames and a mismatch's image as told are the
    reference's own frames); unpaired, the conditions take turns through the scenes and draw their own cameras."""
    scenes = {sc: [torch.full((1, 160, 160), v) for v in (0.2, 0.4, 0.6, 0.8)] for sc in rb.SCENE_SCALES}
    monkeypatch.setattr(rb, "_scenes", lambda: scenes)
    monkeypatch.setattr(rb, "CONDITIONS", ("reference", "round8", "gain", "white_noise"))
    out = rb.make_frames(n, seed=3, paired=True)
    by = {c: [f for f in out if f.condition == c] for c in rb.CONDITIONS}
    ref = by["reference"]
    assert [f.scale for f in ref] == ["full", "3x", "full"][:n]
    for cond, fs in by.items():
        for f, r in zip(fs, ref):
            assert torch.equal(f.clean, r.clean) and f.seed == r.seed and f.scale == r.scale
            assert float(f.told.gain_db) == float(r.told.gain_db)
    # the gain frames' image as told is the reference frame itself: only the altered field differs
    for g, r in zip(by["gain"], ref):
        assert g.overrides is not None and 6.0 <= g.overrides["gain_db"] - float(r.told.gain_db) <= 12.0
        torch.testing.assert_close(g.total + g.xi, r.total)
    # another seed pairs other scenes (an offset drawn per seed) and the design is reproducible
    again = rb.make_frames(n, seed=3, paired=True)
    assert all(torch.equal(a.noisy, b.noisy) for a, b in zip(out, again))
    unpaired = rb.make_frames(n, seed=3)
    u = [f for f in unpaired if f.condition == "reference"], [f for f in unpaired if f.condition == "round8"]
    assert not torch.equal(u[0][0].clean, u[1][0].clean)  # unpaired: the next condition takes the next scenes


def test_score_has_pooled_and_per_scale_groups(frames):
    res = rb.score(rb._ClosedForm(), frames)
    assert set(res["scales"]) == set(rb.SCENE_SCALES)
    n_matched = sum(16 for f in frames if f.condition in rb.MATCHED)
    assert res["groups"]["matched"]["n"] == n_matched
    assert sum(res["scales"][s]["groups"]["matched"]["n"] for s in rb.SCENE_SCALES) == n_matched
    for s in rb.SCENE_SCALES:
        part = res["scales"][s]
        assert part["frames"] == sum(f.scale == s for f in frames)
        assert set(part["groups"]) == set(res["groups"])
        for key in ("auc_patch", "auc_frame", "auc_frame_quiet", "auc_frame_busy", "strong_total_rel_p90", "assessable"):
            assert key in part
        # the closed form is exact where the metadata are right, at either scale
        assert part["groups"]["matched"]["total"][2] < 0.1
        assert part["auc_patch"] != part["auc_patch"] or part["auc_patch"] == pytest.approx(0.5)


def test_report_prints_floors_and_tables_per_scale(frames, monkeypatch, tmp_path):
    monkeypatch.setattr(rb, "make_frames", lambda n, seed=0, paired=False: frames)
    args = argparse.Namespace(task="noise", frames=2, seed=0, models=[], json=tmp_path / "r.json", command_line="test")
    res = rb.run(args)
    header = "\n".join(res.header)
    n_full = sum(f.scale == "full" for f in frames)
    assert n_full == len(rb.CONDITIONS)  # two frames per condition, one per scale
    assert f"full resolution ({n_full} frames): scenes' own fine-scale σ" in header
    assert f"3× area-downsampled ({len(frames) - n_full} frames): scenes' own fine-scale σ" in header and "quartiles" in header
    text = "\n".join(res.summary)
    n = 16 * len(rb.MATCHED)  # matched patches per scale
    for label, matched in (("pooled", 2 * n), ("full resolution", n), ("3× area-downsampled", n)):
        assert f"| closed_form | {label} | matched ({matched}) |" in text  # per-source table
        assert f"| closed_form | {label} | 0.500 |" in text or f"| closed_form | {label} | nan |" in text  # detection
        assert f"{label}: " in text  # visible/matched counts
        assert f"| closed_form | {label} | banding (" in text  # row and column noise: per-source table
        assert f"| closed_form | {label} | " in text.split("Row and column noise")[1]  # and its own table
        assert f"| closed_form | {label} | defects (" in text  # defective pixels: per-source table
        assert f"| closed_form | {label} | nan % | nan % |" in text.split("Defective pixels")[1]  # it says where none
    out = json.loads((tmp_path / "r.json").read_text())
    assert set(out["closed_form"]["scales"]) == {"full", "3x"}


class _Refuses:
    """The closed form, but it says "I can't tell" on the first 4 patches of every frame."""

    kind, metadata_set, name = "noise_source", "full", "refuses"

    def predict(self, noisy, meta):
        out = rb._ClosedForm().predict(noisy, meta)
        ok = torch.ones(noisy.shape[0], dtype=torch.bool)
        ok[:4] = False
        return {**out, "assessable": ok}


def test_strong_noise_is_also_scored_on_the_patches_called_assessable(frames):
    res = rb.score(_Refuses(), frames)
    assert res["strong_assessable"] == pytest.approx(12 / 16)
    # the closed form never sees the extra noise: ξ = 0 has the wrong sign on every strong patch, vouched for or not
    assert res["strong_xi_sign_right"] == 0.0 and res["strong_xi_sign_right_assessable"] == 0.0
    assert res["strong_total_rel_p90_assessable"] > 0.5
    strong = [f for f in frames if f.condition == "strong"]
    rel = torch.cat([(rb._ClosedForm().predict(f.noisy, f.told)["sigma_total"] / f.total - 1).abs()[4:] for f in strong])
    assert res["strong_total_rel_p90_assessable"] == pytest.approx(float(rel.quantile(0.9)), rel=1e-5)


def test_evidence_breaks_ties_of_xi_with_the_mismatch_probability_and_the_decision_is_counted():
    """ξ̂ = 0 (closed form kept) on all matched and half the mismatched patches: |ξ̂| ties them, the estimator's
    p_match still ranks them; the declared mismatches (|ξ̂| visible) are half the visible ones and no matched one."""
    from types import SimpleNamespace

    def frame(xi_true: float) -> SimpleNamespace:
        return SimpleNamespace(xi=torch.full((16,), xi_true), total=torch.full((16,), 10.0), sigma=torch.ones(16, 3),
                               scene_floor=0.0)

    sig, tot = torch.ones(16, 3), torch.full((16,), 10.0)
    matched = (sig, tot, torch.zeros(16), frame(0.0), torch.ones(16, dtype=torch.bool), torch.full((16,), 0.9))
    xi_hat = torch.cat([torch.zeros(8), torch.full((8,), -3.0)])
    pm = torch.cat([torch.full((8,), 0.3), torch.full((8,), 0.1)])
    mismatched = (sig, tot, xi_hat, frame(-3.0), torch.ones(16, dtype=torch.bool), pm)
    rows = {c: [] for c in rb.CONDITIONS}
    rows[rb.MATCHED[0]] = [matched, matched]
    rows[rb.MISMATCH[0]] = [mismatched, mismatched]
    res = rb._aggregate(rows)
    assert res["auc_patch"] == pytest.approx(0.75)  # half the positives tie with every negative
    assert res["auc_patch_evidence"] == pytest.approx(1.0)
    assert res["declared_tpr_patch"] == pytest.approx(0.5) and res["declared_fpr_patch"] == 0.0
    # without p_match (a network) the evidence is |ξ̂| alone
    rows[rb.MATCHED[0]] = [matched[:5] + (None,)] * 2
    rows[rb.MISMATCH[0]] = [mismatched[:5] + (None,)] * 2
    assert rb._aggregate(rows)["auc_patch_evidence"] == pytest.approx(0.75)


def test_per_source_uncertainty_coverage_is_counted_where_the_estimator_reports_one():
    """Errors of 0.1 / 0.3 / 1.0 DN against u = 0.2 DN: within u 100 / 0 / 0 %, within 2u 100 / 100 / 0 %; an
    estimator without ``sigma_std`` (a network) gets no coverage entry."""
    from types import SimpleNamespace

    truth = SimpleNamespace(xi=torch.zeros(16), total=torch.full((16,), 3.0), sigma=torch.ones(16, 3), scene_floor=0.0)
    sig = torch.ones(16, 3) + torch.tensor([0.1, 0.3, 1.0])
    row = (sig, torch.full((16,), 3.0), torch.zeros(16), truth, torch.ones(16, dtype=torch.bool), torch.ones(16),
           torch.full((16, 3), 0.2))
    rows = {c: [] for c in rb.CONDITIONS}
    rows[rb.MATCHED[0]] = [row]
    g = rb._aggregate(rows)["groups"]["matched"]
    assert g["within_u"] == pytest.approx((1.0, 0.0, 0.0)) and g["within_2u"] == pytest.approx((1.0, 1.0, 0.0))
    assert g["median_u"] == pytest.approx((0.2, 0.2, 0.2))
    rows[rb.MATCHED[0]] = [row[:6] + (None,)]
    assert "within_u" not in rb._aggregate(rows)["groups"]["matched"]


@pytest.mark.parametrize("kind", ["rows", "columns", "both"])
def test_add_banding_adds_offsets_per_row_or_column(kind):
    """The benchmark's row and column noise: per-row (per-column) offsets of the asked σ, constant along the row
    (column), clipped, and rounded to whole DN only where the input was 8-bit."""
    x = torch.full((4, 1, 128, 128), 100.0 / 255.0)
    out = rb.add_banding(x, 5.0, kind, seed=3)
    d = (out - x)[:, 0].double() * 255.0
    assert torch.allclose(out * 255.0, (out * 255.0).round(), atol=1e-3)  # 8-bit in, 8-bit out
    if kind == "rows":
        assert (d.std(2) < 1e-6).all() and d[:, :, 0].std() == pytest.approx(5.0, rel=0.15)
    elif kind == "columns":
        assert (d.std(1) < 1e-6).all() and d[:, 0, :].std() == pytest.approx(5.0, rel=0.15)
    else:
        assert d.flatten(1).std(1).mean() == pytest.approx(5.0 * 2**0.5, rel=0.2)
    smooth = torch.full((1, 1, 16, 16), 0.3001)
    assert not torch.allclose(rb.add_banding(smooth, 1.0, "rows", 0) * 255, (rb.add_banding(smooth, 1.0, "rows", 0) * 255).round())
    assert rb.add_banding(torch.ones(1, 1, 16, 16), 40.0, "both", 1).max() <= 1.0


def test_add_defects_offsets_single_pixels_and_records_them():
    """The benchmark's defective pixels: about the asked share of the pixels, each moved by 10–200 DN up (+1 in the
    truth) or down (−1), the others untouched; clipped, and 8-bit in, 8-bit out."""
    x = torch.full((8, 1, 128, 128), 100.0 / 255.0)
    out, truth = rb.add_defects(x, 0.01, seed=4)
    d = (out - x)[:, 0].double() * 255.0
    hit = truth[:, 0] != 0
    assert hit.float().mean() == pytest.approx(0.01, rel=0.1)
    assert (d[~hit] == 0).all() and torch.allclose(out * 255.0, (out * 255.0).round(), atol=1e-3)
    lo, hi = rb.DEFECT_OFFSET_DN
    up, down = truth[:, 0] > 0, truth[:, 0] < 0
    assert (d[up] >= lo - 0.5).all() and (d[up] <= 155.01).all()  # clipped at 255 DN
    assert (d[down] <= -(lo - 0.5)).all() and (d[down] >= -100.01).all()  # clipped at 0 DN
    assert 0.4 < up.sum() / hit.sum() < 0.6


def test_defect_scores_count_found_wrong_and_elsewhere():
    """Recall, precision and the per-frame ratio on the defects frames, flagged pixels per million on the others."""
    x = torch.full((16, 1, 128, 128), 0.5)
    _, truth = rb.add_defects(x, 0.001, seed=1)
    told = CameraMetadata.preset("ICX285")
    fr = rb.Frame("defects", x, x, told, torch.zeros(16, 3), torch.ones(16), torch.zeros(16), "full", 0.5, truth)
    other = rb.Frame("reference", x, x, told, torch.zeros(16, 3), torch.ones(16), torch.zeros(16), "full", 0.5)
    found = truth.clone()
    idx = (truth[..., 1:-1, 1:-1] != 0).nonzero()[0]
    found[idx[0], 0, idx[2] + 1, idx[3] + 1] = 0  # one injected defect missed
    wrong = torch.zeros_like(truth)
    wrong[0, 0, 64, 64] = 1  # one pixel flagged where nothing was injected
    z = torch.zeros(16)
    rows = {c: [] for c in rb.CONDITIONS}
    rows["defects"] = [(torch.zeros(16, 3), torch.ones(16), z, fr, z.bool(), None, None, found)]
    rows["reference"] = [(torch.zeros(16, 3), torch.ones(16), z, other, z.bool(), None, None, wrong)]
    res = rb._defect_scores(rows)
    n = int((truth[..., 1:-1, 1:-1] != 0).sum())
    assert res["defects_recall"] == pytest.approx((n - 1) / n)
    assert res["defects_precision"] == 1.0 and res["defects_count_ratio"] == pytest.approx((n - 1) / n)
    assert res["defects_false_ppm"] == pytest.approx(1e6 / (16 * 126 * 126))
    assert res["defects_noisier_frames"] == 0.0
    rows["reference"] = [rows["reference"][0][:7] + (None,)]
    assert all(v != v for v in rb._defect_scores(rows).values())  # no mask from the estimator: NaN


def test_every_frame_has_a_second_exposure_of_the_same_scene_and_camera(frames):
    """A static camera's next frame: the same clean scene and camera state, its own random numbers (so its noise is
    as strong and independent), the same defects at the same pixels, the same JPEG quality."""
    for f in frames:
        assert f.second is not None and f.second.shape == f.noisy.shape and not torch.equal(f.second, f.noisy)
        n1, n2 = (f.noisy - f.clean).flatten(1) * 255, (f.second - f.clean).flatten(1) * 255
        if f.condition != "defects":
            assert torch.allclose(n2.std(1), n1.std(1), rtol=0.25, atol=0.3), f.condition
        if f.condition not in ("defects", *rb.LOSSY):  # (the codec's own error on the scene is common to both)
            assert abs(float(torch.corrcoef(torch.stack([n1.flatten(), n2.flatten()]))[0, 1])) < 0.2, f.condition
    d = next(f for f in frames if f.condition == "defects")
    hit = d.defects != 0
    assert ((d.second - d.noisy).abs()[hit] * 255 < (d.noisy - d.clean).abs()[hit] * 255).float().mean() > 0.5


def test_the_static_pair_row_reads_lossless_frames_as_pairs_and_jpeg_ones_alone(frames):
    from camhealth.estimators.physics_noise import PhysicsNoiseEstimator

    pair = PhysicsNoiseEstimator(settings={"pool": True}, source=f"noise_source_full {rb.STATIC_PAIR_LABEL}")
    ref = next(f for f in frames if f.condition == "reference")
    jpeg = next(f for f in frames if f.condition in rb.LOSSY)
    assert "static" in rb._predict(pair, ref)[0] and "static" not in rb._predict(pair, jpeg)[0]
    lines = rb.static_pair_lines(pair, frames, seed=0)
    text = "\n".join(lines)
    for label in rb.SCALE_LABELS.values():
        assert f"| {label} | " in text
    assert "JPEG as a pair" in text and "scene moved" in text


def test_every_frame_records_how_it_was_made(frames):
    """Variants, the real camera's fields and the seed: what another exposure of the same camera needs."""
    by = {f.condition: f for f in frames}
    assert by["all_variants"].variants == tuple(rb.VARIANTS) and by["reference"].variants == ()
    assert by["reference"].overrides is None and set(by["temperature"].overrides) == {"temperature_c"}
    assert by["temperature"].overrides["temperature_c"] >= float(by["temperature"].told.temperature_c) + 15.0
    again, _ = rb.simulate_variant(by["gain"].clean, by["gain"].told, by["gain"].variants,
                                   torch.Generator().manual_seed(by["gain"].seed), by["gain"].overrides)
    assert torch.equal(again, by["gain"].noisy)  # the frame, made again from what it records


def test_other_exposure_lines_score_each_estimator_alone_and_with_the_other_exposure(frames):
    from camhealth.estimators.physics_noise import PhysicsNoiseEstimator

    ests = [PhysicsNoiseEstimator(settings={"pool": True}, source="noise_source_full (pooled per frame)"),
            PhysicsNoiseEstimator(settings={"pool": True}, source=f"noise_source_full {rb.STATIC_PAIR_LABEL}")]
    text = "\n".join(rb.other_exposure_lines(ests, frames))
    for name in (e.name for e in ests):
        assert f"| {name} | this exposure | 0.0" in text  # matched: the closed form, ~0 DN
        assert f"| {name} | + the other exposure time" in text
    assert rb.other_exposure_lines([rb._ClosedForm()], frames) == []  # nothing to read it with


def _pairwise_auc(score, label) -> float:
    """The AUC by hand: over every (positive, negative) pair, 1 where the positive scores higher, ½ on a tie."""
    pos = [s for s, y in zip(score, label) if y]
    neg = [s for s, y in zip(score, label) if not y]
    return sum(1.0 if p > n else 0.5 if p == n else 0.0 for p in pos for n in neg) / (len(pos) * len(neg))


@pytest.mark.parametrize("score, label, expect", [
    ([0.1, 0.4, 0.35, 0.8], [0, 0, 1, 1], 0.75),
    ([0, 0, 0, 0, 0, 2.0, 0.7], [0, 0, 0, 1, 1, 1, 1], 0.75),  # ties at ξ̂ = 0 count ½
    ([0.0] * 6, [0, 0, 0, 1, 1, 1], 0.5),
    ([38.0, 40.0, 45.0, 39.0], [0, 1, 1, 0], 1.0),  # scores far above 1 (a sigmoid would tie them at 1.0)
    ([60.0, 40.0, 45.0, 40.0, 37.5], [0, 1, 1, 0, 1], 1.5 / 6),  # 40 ties 40 (½), 45 beats 40 (1), the rest lose
    ([1e-6 * 0.2, 1e-6 * 0.9, 50.0, 1e-6 * 0.5], [0, 1, 1, 0], 1.0),  # the evidence's tie-break
])
def test_auc_is_the_mann_whitney_statistic_with_ties_counted_half(score, label, expect):
    got = rb._auc(torch.tensor(score, dtype=torch.float64), torch.tensor(label, dtype=torch.bool))
    assert got == pytest.approx(expect, abs=1e-12) and got == pytest.approx(_pairwise_auc(score, label), abs=1e-12)


def test_auc_agrees_with_pairs_on_random_tied_scores_and_refuses_nan():
    gen = torch.Generator().manual_seed(0)
    score = torch.randint(0, 12, (300,), generator=gen).double() * 7.5  # many ties, up to 82.5
    label = torch.rand(300, generator=gen) < 0.3
    assert rb._auc(score, label) == pytest.approx(_pairwise_auc(score.tolist(), label.tolist()), abs=1e-12)
    assert rb._auc(torch.tensor([1.0, 2.0]), torch.tensor([True, True])) != rb._auc(torch.tensor([1.0, 2.0]), torch.tensor([True, True]))
    assert np.isnan(rb._auc(torch.tensor([1.0, 2.0]), torch.tensor([False, False])))
    with pytest.raises(ValueError, match="NaN"):
        rb._auc(torch.tensor([0.1, float("nan"), 0.3]), torch.tensor([False, False, True]))


class _TotalOnly:
    """A total-σ baseline (as drne): σ_Total only, no sources and no ξ."""

    kind, metadata_set, name = "drne", "none", "total_only"

    def predict(self, noisy):
        return {"sigma_total": torch.full((noisy.shape[0],), 5.0)}


def test_an_estimator_without_xi_gets_dashes_not_a_xi_of_zero(frames, monkeypatch):
    res = rb.score(_TotalOnly(), frames)
    assert res["reports_xi"] is False and rb.score(rb._ClosedForm(), frames)["reports_xi"] is True
    for part in (res, *res["scales"].values()):
        assert all(part[k] != part[k] for k in rb.XI_KEYS)  # NaN, not the 0.5 / 0 % of an imputed ξ̂ = 0
        assert all(g["xi_rms"] != g["xi_rms"] for g in part["groups"].values())
        assert part["strong_total_rel_median"] == part["strong_total_rel_median"]  # σ_Total is still scored
    monkeypatch.setattr(rb, "make_frames", lambda n, seed=0, paired=False: frames)
    monkeypatch.setattr(rb, "_estimators", lambda names: [rb._ClosedForm(), _TotalOnly()])
    args = argparse.Namespace(task="noise", frames=2, seed=0, models=[], json=None, command_line="test")
    text = "\n".join(rb.run(args).summary)
    for label in ("pooled", "full resolution", "3× area-downsampled"):
        assert f"| total_only | {label} | matched (" in text and f"| closed_form | {label} | 0.500 |" in text
        detection = text.split("Detection of a visible mismatch")[1].split("Detection by the estimator's evidence")[0]
        assert f"| total_only | {label} | – | – | – | – | " in detection
        assert "% | – | " in detection.split(f"| total_only | {label} |")[1].split("\n")[0]  # ξ sign right
        assert f"| total_only | {label} | – | – | – | – |" in text.split("Detection by the estimator's evidence")[1]
        banding = text.split("Row and column noise")[1].split("Defective pixels")[0]
        assert f"| total_only | {label} | " in banding and "| – | – |" in banding.split(f"| total_only | {label} |")[1].split("\n")[0]
    rows = [line for line in text.splitlines() if line.startswith("| total_only | pooled | ") and "(" in line.split("|")[3]]
    assert rows and all(line.endswith("| – |") for line in rows)  # ξ RMS


def test_header_gives_the_strong_frames_targets_and_realised_range_per_scale(frames):
    lines = rb.strong_range_lines(frames)
    assert len(lines) == len(rb.SCENE_SCALES)
    for scale, line in zip(rb.SCENE_SCALES, lines):
        strong = [f for f in frames if f.condition == "strong" and f.scale == scale]
        assert all(10.0 <= f.target <= 60.0 for f in strong)
        real = torch.cat([f.total for f in strong])
        assert line.startswith(f"strong noise, {rb.SCALE_LABELS[scale]} ({len(strong)} frames, {real.numel()} patches)")
        assert f"realised σ_Total after clipping (the truth) {float(real.min()):.1f}–{float(real.max()):.1f} DN" in line
        assert float(real.max()) <= max(f.target for f in strong) + 1.0  # clipping only lowers it
    assert all(f.target != f.target for f in frames if f.condition != "strong")
