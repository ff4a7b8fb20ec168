"""``python -m camhealth.evaluate``: metrics on hand-computed examples, ``--quick`` end to end on the embedded
data (classical methods), ``--resume``, learned rows through a fake estimator with the inference interface."""

from __future__ import annotations

import dataclasses
import json
import math
import sys

import pytest
import torch

from camhealth import evaluate as ev
from camhealth.estimators import pca_noise_sigma
from camhealth.metrics import amae, bias_std_rms, mae_hv, noise_errors
from camhealth.physics import CameraMetadata


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# ---------------------------------------------------------------------------------------------- metrics
def test_amae_by_hand():
    gt = torch.zeros(1, 16)
    est = torch.zeros(1, 16)
    est[0, :8] = torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.3])  # MAE(H) = 0.4/8 = 5 %
    est[0, 8:] = -0.02  # MAE(V) = 2 %
    assert mae_hv(est, gt)[0].tolist() == pytest.approx([5.0, 2.0])
    assert float(amae(est, gt)) == pytest.approx(3.5)
    est[0, 0] = float("nan")  # an omitted frequency: MAE(H) over the other 7 = 0.3/7
    assert float(amae(est, gt)) == pytest.approx(0.5 * (100 * 0.3 / 7 + 2.0))


def test_bias_std_rms_by_hand():
    truth = torch.tensor([10.0, 10.0, 20.0, 20.0])
    est = torch.tensor([11.0, 13.0, 19.0, 21.0])  # errors +1, +3, −1, +1: mean 1, population std √2
    r = bias_std_rms(est, truth)
    assert float(r["bias"]) == pytest.approx(1.0)
    assert float(r["std"]) == pytest.approx(math.sqrt(2.0))
    assert float(r["rms"]) == pytest.approx(math.sqrt(3.0))  # = √mean(err²) = √(12/4)
    assert int(r["n"]) == 4
    per_col = bias_std_rms(torch.stack([est, truth], 1), torch.stack([truth, truth], 1), dim=0)
    assert per_col["rms"].tolist() == pytest.approx([math.sqrt(3.0), 0.0])
    assert noise_errors(est, truth) == pytest.approx({"bias": 1.0, "std": math.sqrt(2.0), "rms": math.sqrt(3.0), "n": 4})


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
@pytest.mark.parametrize("batch", [1, 3, 5000])
def test_bias_std_rms_is_one_implementation(dtype, batch):
    """The tuple form used in training and benchmarks (lightning_modules.metrics) is camhealth.metrics's, and the
    torchmetrics accumulator gives the same numbers, in every dtype and for one sample."""
    from lightning_modules.metrics import NoiseErrorStats, bias_std_rms as tuple_form

    g = torch.Generator().manual_seed(batch)
    truth = (torch.rand(batch, 2, generator=g) * 20).to(dtype)
    est = (truth.double() + 0.7 + torch.randn(batch, 2, generator=g, dtype=torch.float64)).to(dtype)
    r = bias_std_rms(est, truth, dim=0)
    assert r["rms"].dtype == dtype and r["rms"].shape == (2,)
    b, s, q = tuple_form(est, truth)
    assert b.dtype == torch.float64
    for got, key in ((b, "bias"), (s, "std"), (q, "rms")):
        assert torch.allclose(got, r[key].double(), rtol=1e-2 if dtype in (torch.float16, torch.bfloat16) else 1e-6, atol=1e-6), key
    acc = NoiseErrorStats(["a", "b"])
    acc.update(est, truth)
    out = acc.compute()
    half = dtype in (torch.float16, torch.bfloat16)  # the accumulator subtracts in the input dtype
    assert torch.allclose(torch.stack([out["rms_a"], out["rms_b"]]).double(), q, rtol=1e-2 if half else 1e-5, atol=1e-6)
    if batch == 1:
        assert torch.equal(s, torch.zeros(2, dtype=torch.float64))


def test_bias_std_rms_refuses_what_it_cannot_reduce():
    from lightning_modules.metrics import bias_std_rms as tuple_form

    with pytest.raises(ValueError, match="truth must be finite"):
        tuple_form(torch.ones(3), torch.tensor([1.0, float("inf"), 1.0]))
    with pytest.raises(ValueError, match="estimate must be finite"):
        bias_std_rms(torch.tensor([[1.0, float("nan")]]), torch.ones(1, 2), dim=0)
    with pytest.raises(ValueError, match="overflow"):
        bias_std_rms(torch.tensor([1e200], dtype=torch.float64), torch.zeros(1, dtype=torch.float64))
    with pytest.raises(ValueError, match="at least one sample"):
        tuple_form(torch.zeros(0), torch.zeros(0))


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: amae(torch.zeros(2, 8), torch.zeros(2, 8)), r"\(\.\.\., 16\)"),
        (lambda: amae(torch.zeros(1, 16), torch.full((1, 16), float("nan"))), "target"),
        (lambda: bias_std_rms(torch.tensor([1.0, float("nan")]), torch.ones(2)), "finite"),
        (lambda: bias_std_rms(torch.zeros(3), torch.zeros(2)), "broadcast"),
        (lambda: amae(torch.zeros(1, 16, dtype=torch.long), torch.zeros(1, 16)), "floating"),
    ],
)
def test_metric_errors(call, match):
    with pytest.raises((ValueError, TypeError), match=match):
        call()


# ------------------------------------------------------------------------------------ --quick end to end
@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("evaluate_quick")
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        rc = ev.main(["--quick", "--methods", "classical", "--out", str(out), "--no-progress", "--docs", str(out / "docs" / "results.md")])
    finally:
        torch.set_num_threads(n)
    return rc, out


def test_quick_run_writes_tables_json_and_plots(quick_run):
    rc, out = quick_run
    assert rc == 0
    md = (out / "results.md").read_text()
    for title in ("like Tab. 5.1", "like Tab. 6.1", "like Tab. 5.2", "like Tab. 5.3", "Speed: every method in the same run"):
        assert title in md
    for method in ("PCA", "B+F", "wavelet", "slanted edge", "Siemens star"):
        assert f"| {method} |" in md
    assert "--quick" in md and "machine:" in md
    assert (out / "docs" / "results.md").read_text() == md
    report = json.loads((out / "results.json").read_text())
    assert {r["method"] for r in report["speed"]} == {"PCA", "B+F", "wavelet", "slanted edge", "Siemens star"}
    assert all(r["ms_per_item"] > 0 and r["items"] > 0 for r in report["speed"])
    # the standard measurement agrees with the labels: slanted edge ≤ 2 % AMAE for defocus d ≤ 11 px
    sle = report["blur"]["amae"]["slanted edge"]
    assert max(sle[f"defocus {d:g}"] for d in (3, 7, 11)) < 2.0
    assert max(v for v in report["blur"]["amae"]["slanted edge vs. exact MTF at 5°/95°"].values()) < 2.0
    # classical noise estimators on the isolated sources are in a sane range
    assert all(v < 8.0 for v in report["noise"]["isolated"]["PCA"].values())
    assert set(report["aggregation"]["PCA"]) == {"1", "2", "4", "10"}
    for png in ("error_vs_time.png", "mtf_curves.png", "noise_isolated.png", "aggregation.png"):
        assert (out / "plots" / png).stat().st_size > 1000
    assert report["config"]["noise_patches"] == ev.QUICK.noise_patches


def test_resume_reuses_every_cached_unit(quick_run, capsys):
    _, out = quick_run
    before = json.loads((out / "results.json").read_text())
    assert ev.main(["--quick", "--methods", "classical", "--out", str(out), "--no-progress", "--no-plots", "--resume"]) == 0
    after = json.loads((out / "results.json").read_text())
    assert any("reused from the cache" in n for n in after["notes"])
    assert after["blur"] == before["blur"] and after["noise"] == before["noise"]
    assert [r["ms_per_item"] for r in after["speed"]] == [r["ms_per_item"] for r in before["speed"]]


def test_cli_rejects_unknown_methods():
    with pytest.raises(SystemExit, match="unknown"):
        ev.main(["--methods", "pca,gbb", "--out", "/nonexistent"])


@pytest.fixture
def fake_run(monkeypatch):
    """``run_evaluation`` replaced by a stand-in that writes a one-line results page and records its configurations."""
    runs = []

    def run(cfg, out, methods, **kwargs):
        runs.append(cfg)
        out.mkdir(parents=True, exist_ok=True)
        (out / "results.md").write_text(f"{ev.RESULTS_TITLE}\n\nnew page\n", encoding="utf-8")
        return {"summary": [], "plots": [], "wall_s": 0.0}

    monkeypatch.setattr(ev, "run_evaluation", run)
    return runs


def test_docs_refuses_a_file_that_is_not_a_results_page_before_running(tmp_path, fake_run, capsys):
    from camhealth._cli import run_cli

    page = tmp_path / "page.md"
    text = "intro\n\n<!-- generated: python -m camhealth.evaluate --quick -->\nold\n<!-- end generated -->\n\noutro\n"
    page.write_text(text)
    rc = run_cli(ev.main, "python -m camhealth.evaluate", ["--methods", "pca", "--out", str(tmp_path / "o"), "--docs", str(page)])
    err = capsys.readouterr().err
    assert rc == 2 and f"--docs {page}" in err and "not an evaluate results page" in err
    assert page.read_text() == text and fake_run == []  # nothing overwritten, nothing evaluated


def test_docs_writes_a_new_file_and_rewrites_a_results_page_whole(tmp_path, fake_run):
    new, old = tmp_path / "docs" / "new.md", tmp_path / "results.md"
    old.write_text(f"{ev.RESULTS_TITLE}\n\nold page\n")
    for page in (new, old):
        assert ev.main(["--methods", "pca", "--out", str(tmp_path / "o"), "--docs", str(page)]) == 0
        assert page.read_text() == f"{ev.RESULTS_TITLE}\n\nnew page\n"


def test_seed_below_zero_is_refused_by_the_parser(tmp_path, fake_run, capsys):
    with pytest.raises(SystemExit) as info:
        ev.main(["--seed", "-1", "--methods", "pca", "--out", str(tmp_path / "o")])
    assert info.value.code == 2 and "argument --seed: must be >= 0, got -1" in capsys.readouterr().err
    assert fake_run == []


def test_bit_depth_reaches_the_folder_source(tmp_path, fake_run, monkeypatch):
    import camhealth.data

    assert ev.main(["--methods", "pca", "--out", str(tmp_path / "o"), "--bit-depth", "12"]) == 0
    (cfg,) = fake_run
    assert cfg.bit_depth == 12 and cfg.key() != dataclasses.replace(cfg, bit_depth="auto").key()
    asked = {}

    def build_source(spec, **kwargs):
        asked.update(kwargs, spec=spec)
        raise RuntimeError("stop")

    monkeypatch.setattr(camhealth.data, "build_source", build_source)
    with pytest.raises(RuntimeError, match="stop"):
        ev.build_cases(dataclasses.replace(cfg, source="my_frames"))
    assert asked == {"spec": "my_frames", "bit_depth": 12}


# --------------------------------------------------------------------------------- learned rows (fake)
class FakeEstimator:
    """Stands in for camhealth.inference.Estimator: same attributes and predict() contract."""

    def __init__(self, kind: str, patch_size: int, metadata_set: str = "none") -> None:
        self.kind, self.patch_size, self.metadata_set = kind, patch_size, metadata_set
        self.calls = 0

    def predict(self, patches, metadata=None):
        self.calls += 1
        assert patches.ndim == 4 and patches.shape[-1] == self.patch_size
        b = patches.shape[0]
        if self.metadata_set != "none":
            assert isinstance(metadata, CameraMetadata) and metadata.batch_size == b
        else:
            assert metadata is None
        out = {"assessable": torch.ones(b, dtype=torch.bool)}
        if self.kind == "mtf":
            out["mtf"] = torch.full((b, 16), 0.5)
            return out
        total = pca_noise_sigma(patches)
        out["sigma_total"] = total
        if self.kind == "noise_source":
            out["sigma"] = (total / math.sqrt(3.0))[:, None].expand(b, 3).clone()
            out["xi"] = torch.zeros(b)
        return out


TINY = dataclasses.replace(
    ev.QUICK, noise_patches=1, combined_patches=3, blur_patches=1, bun_patches=1, bun_sizes=(3.0,), bun_levels=(0.0, 10.0),
    agg_frames=3, agg_patches=2, agg_windows=(1, 2), charts=False,
)  # fmt: skip


def test_learned_rows_through_the_inference_interface(tmp_path):
    fakes = {"mtf": FakeEstimator("mtf", 192), "ns": FakeEstimator("noise_source", 128, "full"), "drne": FakeEstimator("drne", 128)}
    methods = [m for m in ev.classical_methods() if m.name in ("PCA", "B+F")]
    methods += [ev._wrap_learned(f"learned {k}", v) for k, v in fakes.items()]
    report = ev.run_evaluation(TINY, tmp_path, methods, progress=False, plots=False)
    assert all(f.calls > 0 for f in fakes.values())
    comb = report["noise"]["combined"]["natural"]
    assert set(comb["learned ns"]) == {"Total", "PN", "DCSN", "RN"} and set(comb["learned drne"]) == {"Total"}
    assert comb["learned drne"]["Total"] == comb["PCA"]["Total"]  # the fake runs PCA: same numbers
    assert "learned mtf" in report["blur"]["amae"] and "learned mtf + b₂ (7 px)" in report["blur_under_noise"]["blur"]
    speed = {r["method"]: r for r in report["speed"]}
    assert speed["learned mtf"]["learned"] and speed["learned mtf"]["unit"] == "patch"
    assert any(s.startswith("learned ns on dead leaves") for s in report["summary"])
    md = (tmp_path / "results.md").read_text()
    assert "| natural | learned ns |" in md


def test_learned_methods_note_when_unavailable(monkeypatch):
    notes: list[str] = []
    monkeypatch.setitem(sys.modules, "camhealth.inference", None)  # import fails
    assert ev.learned_methods(["mtf"], log=notes.append) == []
    assert "not importable" in notes[0]
    monkeypatch.delitem(sys.modules, "camhealth.inference")
    import camhealth.inference as inf

    def missing(name):
        raise FileNotFoundError(f"no weights for {name}")

    monkeypatch.setattr(inf, "load_estimator", missing)
    notes.clear()
    assert ev.learned_methods(["drne"], log=notes.append) == []
    assert "'drne' not available" in notes[0]
    with pytest.raises(FileNotFoundError):  # an explicit --checkpoint must load
        ev.learned_methods([], ["/tmp/none.pt"], log=notes.append)


def test_config_errors(tmp_path):
    with pytest.raises(ValueError, match="charts"):
        ev.run_evaluation(TINY, tmp_path, ev.classical_methods(), progress=False)
    with pytest.raises(ValueError, match="no method"):
        ev.run_evaluation(TINY, tmp_path, [], progress=False)


# ---------------------------------------------------------------------------------------------- cache faults
def _runner(tmp_path, logs):
    return ev._Runner(ev.QUICK, tmp_path / "cache", resume=True, log=logs.append, progress=False)


def test_resume_survives_a_truncated_cache_entry(tmp_path):
    """An interrupted run could leave a cut-off entry; --resume reports it, computes it again and rewrites it."""
    logs: list[str] = []
    method = ev.Method("fake", "noise", fn=lambda *a: None)
    calls: list[int] = []

    def call(batch, sl):
        calls.append(len(batch))
        return batch * 2

    inputs = torch.arange(6.0)
    first = _runner(tmp_path, logs).run("case", method, "", inputs, call, "patch")
    (entry,) = list((tmp_path / "cache").rglob("*.pt"))
    data = entry.read_bytes()
    entry.write_bytes(data[: len(data) // 2])
    again = _runner(tmp_path, logs).run("case", method, "", inputs, call, "patch")
    assert torch.equal(again, first) and len(calls) == 2
    assert any("cannot be read" in m and str(entry) in m for m in logs)
    runner = _runner(tmp_path, logs)
    assert torch.equal(runner.run("case", method, "", inputs, call, "patch"), first)
    assert runner.reused == 1 and len(calls) == 2  # the rewritten entry is whole again


def test_resume_does_not_reuse_another_files_results_under_the_same_name(tmp_path):
    """Two checkpoints named alike (the method name is the file's stem): --resume reuses a cached unit only for the same
    file (its SHA-256), so the second checkpoint is computed, not given the first one's numbers."""
    logs: list[str] = []
    calls: list[int] = []

    def call(batch, sl):
        calls.append(len(batch))
        return batch * len(calls)

    inputs = torch.arange(4.0)
    a = ev.Method("checkpoint best", "noise", fn=lambda *x: None, learned=True, identity="a" * 64)
    b = ev.Method("checkpoint best", "noise", fn=lambda *x: None, learned=True, identity="b" * 64)
    first = _runner(tmp_path, logs).run("case", a, "", inputs, call, "patch")
    runner = _runner(tmp_path, logs)
    second = runner.run("case", b, "", inputs, call, "patch")
    assert runner.reused == 0 and len(calls) == 2 and not torch.equal(first, second)
    again = _runner(tmp_path, logs)
    assert torch.equal(again.run("case", b, "", inputs, call, "patch"), second) and again.reused == 1


def test_file_identity_is_the_loaded_files_sha256(tmp_path):
    import hashlib
    from types import SimpleNamespace

    f = tmp_path / "w.pt"
    f.write_bytes(b"weights")
    assert ev._file_identity(SimpleNamespace(source=str(f))) == hashlib.sha256(b"weights").hexdigest()
    assert ev._file_identity(SimpleNamespace(source="noise_source_full")) == ""  # no file: the physics-first estimator


def test_cache_entries_are_written_atomically(tmp_path, monkeypatch):
    """A write that fails half-way leaves the previous entry intact and no temporary file behind."""
    path = tmp_path / "case" / "entry.pt"
    ev._write_cache({"config_key": "a", "out": torch.ones(3)}, path)
    real_save = torch.save

    def failing_save(obj, f, *args, **kwargs):
        real_save(obj, f, *args, **kwargs)
        f.truncate(10)
        raise KeyboardInterrupt  # the run is stopped while writing

    monkeypatch.setattr(torch, "save", failing_save)
    with pytest.raises(KeyboardInterrupt):
        ev._write_cache({"config_key": "b", "out": torch.zeros(3)}, path)
    monkeypatch.undo()
    assert [p.name for p in path.parent.iterdir()] == ["entry.pt"]
    assert torch.load(path, weights_only=True)["config_key"] == "a"


def test_blur_scenes_rendered_have_an_exact_label_and_a_bad_choice_is_refused():
    import dataclasses

    from camhealth.evaluate import QUICK, EvalConfig, _rendered_blur_scenes

    scenes = _rendered_blur_scenes(0)
    assert len(scenes) == 12 and all(scenes[i].shape == (1, 320, 320) for i in range(len(scenes)))
    assert dataclasses.replace(QUICK, blur_scenes="source").blur_scenes == "source"
    with pytest.raises(ValueError, match=r"blur_scenes = 'photos' must be 'rendered' or 'source'"):
        EvalConfig(blur_scenes="photos")


@pytest.mark.parametrize("baselines, expect", [
    ({"PCA": 10.0}, "— beats PCA;"),
    ({"PCA": 10.0, "B+F": 2.0}, "— does NOT beat PCA and B+F;"),
    ({}, "(PCA and B+F not run: no comparison)"),
])
def test_summary_names_only_the_baselines_that_ran(baselines, expect):
    comb = {"checkpoint x": {"Total": {"rms": 3.0}}, **{k: {"Total": {"rms": v}} for k, v in baselines.items()}}
    report = {"blur": {"amae": {}}, "noise": {"combined": {"deadleaves": comb}},
              "speed": [{"method": n, "ms_per_item": 1.0} for n in comb]}
    (line,) = [s for s in ev._summary(report) if s.startswith("checkpoint x")]
    assert expect in line


# ---------------------------------------------------------------------------------------------- aggregation error
def test_aggregation_error_is_the_windowed_estimate_minus_the_windowed_truth():
    """The error table is σ̃_n − σ_n as the report says (median over the window of the estimates minus that of the
    realised σ), not the window median of the per-frame differences σ̂ − σ; they differ for n ≥ 3."""
    from types import SimpleNamespace

    from camhealth.estimators.aggregation import temporal_median

    est = torch.tensor([[1.0, 5.0, 2.0], [4.0, 0.0, 3.0], [2.0, 3.0, 9.0], [8.0, 1.0, 1.0], [0.0, 7.0, 4.0]])
    truth = torch.tensor([[3.0, 1.0, 0.0], [0.0, 4.0, 6.0], [5.0, 2.0, 1.0], [1.0, 6.0, 2.0], [2.0, 0.0, 5.0]])
    t, p = est.shape
    cases = {"aggregation": {"frames": t, "per_frame": p, "total": truth.flatten()}}
    method = SimpleNamespace(name="fake", kind="noise")
    results = {("aggregation", "fake", ""): {"total": est.flatten()}}
    tab = ev._agg_table(cases, results, [method], (1, 2, 4))["fake"]
    for n in (1, 2, 4):
        want = temporal_median(est.double(), n).median - temporal_median(truth.double(), n).median
        assert tab[str(n)]["err_median"] == pytest.approx(float(want.median()), abs=1e-12), n
        assert tab[str(n)]["err_std"] == pytest.approx(float(want.std(unbiased=False)), abs=1e-12), n
    per_frame = temporal_median((est - truth).double(), 4).median
    assert tab["4"]["err_median"] != pytest.approx(float(per_frame.median()))  # the two definitions differ here
    assert tab["4"]["err_delta"] == pytest.approx(tab["1"]["err_std"] - tab["4"]["err_std"])


# ---------------------------------------------------------------------------------------------- checkpoint rows
def test_two_checkpoints_with_the_same_file_name_get_their_own_rows(tmp_path):
    """``--checkpoint a/last.pt --checkpoint b/last.pt`` (two runs' last checkpoints): both rows were named
    'checkpoint last' and the evaluation refused to start."""
    from camhealth.export import export_weights
    from lightning_modules import NoiseLevelEstimator

    torch.manual_seed(0)
    a = export_weights(NoiseLevelEstimator(patch_size=32, width=4, dilations=(1,)), tmp_path / "run0" / "last.pt")
    b = export_weights(NoiseLevelEstimator(patch_size=32, width=4, dilations=(1,)), tmp_path / "run1" / "last.pt")
    methods = ev.learned_methods([], [a, b], log=lambda s: None)
    assert [m.name for m in methods] == ["checkpoint run0/last", "checkpoint run1/last"]
    assert ev.checkpoint_labels([a, tmp_path / "best.pt"]) == ["checkpoint last", "checkpoint best"]
    assert methods[0].identity != methods[1].identity  # two files: two cache identities as well
    with pytest.raises(ValueError, match="given twice"):
        ev.checkpoint_labels([a, tmp_path / "run0" / ".." / "run0" / "last.pt"])
