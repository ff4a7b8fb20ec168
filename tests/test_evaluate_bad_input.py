"""python -m camhealth.evaluate on bad input: configurations, output folders and checkpoints refused before any data
is built, each error naming the value; estimates a method cannot give; the summary's pass/fail line with kernels
without a value."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from skimage.io import imsave

from camhealth import evaluate as ev

TINY = dataclasses.replace(
    ev.QUICK, noise_patches=1, combined_patches=2, blur_patches=0, bun_patches=0, bun_sizes=(3.0,), bun_levels=(0.0,),
    agg_frames=3, agg_patches=1, agg_windows=(1, 2), deadleaves=False, charts=False,
)  # fmt: skip


def _folder(path, value=None, n=3, size=256):
    path.mkdir(parents=True)
    rng = np.random.default_rng(1)
    for i in range(n):
        img = np.full((size, size), value, np.uint8) if value is not None else (rng.random((size, size)) * 200 + 20).astype(np.uint8)
        imsave(path / f"f{i}.png", img, check_contrast=False)
    return path


def _bf():
    return [m for m in ev.classical_methods() if m.name == "B+F"]


@pytest.mark.parametrize("field, value, match", [
    ("batch", 0, r"batch = 0 must be an integer >= 1"),
    ("batch", True, r"batch = True must be an integer >= 1"),
    ("noise_patches", 0, r"noise_patches = 0 must be an integer >= 1"),
    ("combined_patches", 0, r"combined_patches = 0 must be an integer >= 1"),
    ("agg_patches", 0, r"agg_patches = 0 must be an integer >= 1"),
    ("blur_patches", -2, r"blur_patches = -2 must be an integer >= 0 \(0: no patches\)"),
    ("bun_patches", 1.5, r"bun_patches = 1\.5 must be an integer >= 0"),
    ("agg_frames", 1, r"agg_frames = 1 must be an integer >= 2"),
    ("seed", -1, r"seed = -1 must be an integer >= 0"),
    ("agg_windows", (0,), r"agg_windows = \(0,\) must be a non-empty list of window sizes: integers >= 1"),
    ("agg_windows", (), r"agg_windows = \(\) must be a non-empty list of window sizes"),
    ("bun_levels", (-5.0,), r"bun_levels = \(-5\.0,\) must be a non-empty list of noise levels σ >= 0"),
    ("bun_levels", (float("nan"),), r"bun_levels = \(nan,\) must be a non-empty list of noise levels"),
    ("bun_sizes", (1000.0,), r"bun_sizes = \(1000\.0,\) must be a non-empty list of blur sizes in \[0, 23\] px"),
    ("deadleaves", "yes", r"deadleaves = 'yes' must be True or False"),
])  # fmt: skip
def test_config_values_are_refused_when_the_config_is_built(field, value, match):
    """batch = 0 failed as "range() arg 3 must not be zero" and noise_patches = 0 as "stack expects a non-empty
    TensorList", after every case was built; the others were accepted."""
    with pytest.raises(ValueError, match=match):
        dataclasses.replace(ev.QUICK, **{field: value})


@pytest.mark.parametrize("where", ["same", "inside", "containing"])
def test_out_in_or_around_a_folder_source_is_refused_before_anything_is_built(where, tmp_path):
    """With --out inside the --source folder a second run read the first run's plots as 4 more benchmark images."""
    top = tmp_path / "top"
    src = _folder(top / "imgs")
    out = {"same": src, "inside": src / "evaluation", "containing": top}[where]
    words = {"same": "is the source folder", "inside": "is inside the source folder", "containing": "contains the source folder"}
    cfg = dataclasses.replace(TINY, source=str(src))
    with pytest.raises(ValueError, match=rf"out {out} {words[where]} {src}"):
        ev.run_evaluation(cfg, out, _bf(), progress=False, plots=True, log=lambda s: None)
    assert not (out / "results.json").exists() and not (out / "cache").exists()


def test_the_command_refuses_out_inside_the_source_folder_before_running(tmp_path, monkeypatch):
    src = _folder(tmp_path / "imgs")
    runs = []
    monkeypatch.setattr(ev, "run_evaluation", lambda *a, **k: runs.append(a))
    with pytest.raises(ValueError, match=rf"--out {src / 'evaluation'} is inside the source folder {src}"):
        ev.main(["--source", str(src), "--out", str(src / "evaluation"), "--methods", "bf", "--quick"])
    assert runs == []


def test_estimates_a_method_cannot_give_are_left_out_and_counted(tmp_path):
    """PCA answers NaN on flat black patches: the whole run stopped at the tables with "estimate must be finite for
    Bias/Std/RMS", naming neither the method nor the case."""
    src = _folder(tmp_path / "black", value=0)
    pca = [m for m in ev.classical_methods() if m.name == "PCA"]
    report = ev.run_evaluation(dataclasses.replace(TINY, source=str(src)), tmp_path / "out", pca, progress=False,
                               plots=False, log=lambda s: None)
    total = report["noise"]["combined"]["natural"]["PCA"]["Total"]
    assert total["n"] == 0 and total["excluded"] == 2 and math.isnan(total["rms"])
    assert any(n.startswith("PCA on noise_combined_natural (total): 2 of 2 estimates are not finite") for n in report["notes"])
    assert "> PCA on noise_combined_natural (total): 2 of 2 estimates" in (tmp_path / "out" / "results.md").read_text()


@pytest.mark.parametrize("kind, size, limit", [("mtf", 256, 192), ("drne", 160, 128)])
def test_a_checkpoint_reading_larger_patches_than_the_benchmark_has_is_refused_naming_the_file(kind, size, limit, tmp_path):
    """An MTF estimator of 256 px failed with "patches of 192 px are smaller than the 256 px the estimator reads" once
    every case was built, naming no file."""
    from camhealth.export import export_weights
    from lightning_modules import MTFEstimator, NoiseLevelEstimator

    module = MTFEstimator(size, (4, 4, 4), (4,)) if kind == "mtf" else NoiseLevelEstimator(size, width=4, dilations=(1,))
    path = export_weights(module, tmp_path / f"{kind}{size}.pt")
    what = "an MTF" if kind == "mtf" else "a noise"
    with pytest.raises(ValueError, match=rf"--checkpoint {path}: {what} estimator of patch_size = {size} px; the "
                                         rf"benchmark's .* patches are {limit} px"):
        ev.learned_methods((), [path], log=lambda s: None)


def test_a_learned_method_reading_larger_patches_is_refused_before_data_is_built(tmp_path):
    class Big:
        kind, patch_size, metadata_set = "mtf", 256, "none"

    method = ev._wrap_learned("checkpoint big", Big())
    with pytest.raises(ValueError, match=r"method 'checkpoint big': an MTF estimator of patch_size = 256 px; the "
                                         r"benchmark's MTF patches are 192 px"):
        ev.run_evaluation(TINY, tmp_path / "out", [method], progress=False, log=lambda s: None)
    assert not (tmp_path / "out").exists()


def _report(defocus, exact=None):
    amae = {"slanted edge": {f"defocus {d:g}": v for d, v in zip(ev.BLUR_SIZES_PX, defocus)}}
    if exact is not None:
        amae["slanted edge vs. exact MTF at 5°/95°"] = exact
    return {"blur": {"amae": amae}, "noise": {"combined": {}}, "speed": []}


@pytest.mark.parametrize("values, worst, missing", [
    ([1.0, math.nan, 1.5, 9.0, 9.0], "1.50", 1),
    ([math.nan, 1.0, 1.5, 9.0, 9.0], "1.50", 1),
    ([1.0, 1.5, math.nan, 9.0, 9.0], "1.50", 1),
    ([math.nan, math.nan, math.nan, 9.0, 9.0], "–", 3),
])  # fmt: skip
def test_the_target_line_is_not_met_wherever_a_kernel_without_a_value_sits(values, worst, missing):
    """[1.0, nan, 1.5] read "met"; the same values with the NaN first read "nan % … NOT met"."""
    line = ev._summary(_report(values))[0]
    assert line == (f"slanted edge vs labels, defocus d ≤ 11 px: max AMAE {worst} % (target ≤ 2 %: NOT met "
                    f"({missing} kernel{'' if missing == 1 else 's'} without a value))")


def test_the_exact_mtf_line_with_no_value_at_all_is_said_so():
    """max() of an empty list raised "max() arg is an empty sequence"."""
    lines = ev._summary(_report([1.0, 1.0, 1.5, 9.0, 9.0], {"defocus 3": math.nan, "linear 3": math.nan}))
    assert lines[0].endswith("(target ≤ 2 %: met)")
    assert lines[1] == ("slanted edge vs exact kernel MTF in the measured direction: no value for any of the 2 kernels "
                        "(the slanted edge measured none)")
