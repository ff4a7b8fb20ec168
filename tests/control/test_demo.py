"""``python -m camhealth.demo closed-loop`` on two street crops with a synthetic IOPC."""

import argparse
import dataclasses
import json

import pytest

from camhealth.demo import main, parse_slice
from tests.control.test_policy import BLUR_HATER
from tests.iopc.test_cli import crop_folder  # noqa: F401  (fixture)


def test_closed_loop_writes_plot_table_and_json(tmp_path, crop_folder, capsys):  # noqa: F811
    iopc_path = BLUR_HATER.save(tmp_path / "iopc.json")
    out = tmp_path / "demo"
    rc = main(["closed-loop", "--iopc", str(iopc_path), "--source", str(crop_folder), "--frames", "0:2",
               "--illumination", "60", "--motion", "1500", "--repeats", "2", "--out", str(out)])
    assert rc == 0
    assert {p.name for p in out.iterdir()} == {"closed_loop.png", "closed_loop.json", "closed_loop.md"}
    res = json.loads((out / "closed_loop.json").read_text())
    names = [r["controller"] for r in res["results"]]
    assert names == ["fixed", "auto-exposure", "IOPC policy"]
    assert all(0.0 <= r["ap"] <= 1.0 and len(r["ap_runs"]) == 2 for r in res["results"])
    assert res["decisions_per_repeat"] == [1, 1]
    iopc_traj = res["results"][2]["trajectory"]
    assert iopc_traj[0]["exposure_ms"] == pytest.approx(8.0) and iopc_traj[1]["exposure_ms"] < 8.0  # blur-hating IOPC
    assert res["decisions"][0]["explanation"].startswith("σ̂ =")
    table = (out / "closed_loop.md").read_text()
    assert "| IOPC policy |" in table and "26.1 %" in table and "| IOPC policy |" in capsys.readouterr().out


@pytest.mark.parametrize("repeats", ["0", "-1"])
def test_repeats_below_one_is_refused_by_the_parser(repeats, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:  # (before the IOPC file is looked for)
        main(["closed-loop", "--iopc", str(tmp_path / "none.json"), "--repeats", repeats])
    assert info.value.code == 2 and f"argument --repeats: must be >= 1, got {repeats}" in capsys.readouterr().err


def test_missing_iopc_and_slices(tmp_path):
    with pytest.raises(SystemExit, match="python -m camhealth.iopc"):
        main(["closed-loop", "--iopc", str(tmp_path / "none.json")])
    assert parse_slice("25:50") == slice(25, 50) and parse_slice("::2") == slice(None, None, 2)
    assert parse_slice("3") == slice(3, 4)


def test_dark_scene_runs_with_exposure_limits_the_camera_accepts(tmp_path, crop_folder):  # noqa: F811
    """In a dark scene auto-exposure asked for an exposure inside --limits-exposure (1–200 ms) but beyond what the
    camera renders at the scene's motion (253 px of blur): the demo stopped with rc 2. The controllers' longest
    exposure is now capped at 253 px / motion (25.3 ms at 10 000 px/s)."""
    iopc_path = BLUR_HATER.save(tmp_path / "iopc.json")
    out = tmp_path / "demo"
    rc = main(["closed-loop", "--iopc", str(iopc_path), "--source", str(crop_folder), "--frames", "0:2",
               "--illumination", "5", "--motion", "10000", "--out", str(out)])
    assert rc == 0
    res = json.loads((out / "closed_loop.json").read_text())
    assert res["exposure_limits_s"] == [0.001, pytest.approx(253.0 / 10000.0)]
    auto = res["results"][1]["trajectory"]
    assert auto[1]["exposure_ms"] == pytest.approx(25.3) and auto[1]["blur_px"] <= 253.0  # at the cap, not beyond
    assert "capped by the camera's motion-blur limit" in (out / "closed_loop.md").read_text()


@pytest.mark.parametrize("motion, limits", [
    (1500.0, (0.001, 253.0 / 1500.0)),  # the default scene: 168.7 ms
    (800.0, (0.001, 0.2)),  # the cap (316 ms) does not bind
    (0.0, (0.001, 0.2)),  # no motion, no blur
])
def test_exposure_limits_are_capped_by_the_motion(motion, limits):
    from camhealth.control.camera_sim import MAX_MOTION_PX
    from camhealth.demo import _exposure_limits

    args = argparse.Namespace(limits_exposure=[0.001, 0.2], motion=motion)
    t_min, t_max = _exposure_limits(args)
    assert t_min == limits[0] and t_max == pytest.approx(limits[1], rel=1e-12)
    assert motion * t_max <= MAX_MOTION_PX  # as the camera computes it: never past the limit by rounding
    with pytest.raises(SystemExit, match=r"--motion 300000 px/s: .* exposures up to 0.8433 ms, below the shortest "
                                         r"exposure --limits-exposure 1 ms"):
        _exposure_limits(argparse.Namespace(limits_exposure=[0.001, 0.2], motion=300000.0))


def _with_frames_provenance(frames, intensity=0.5):
    return dataclasses.replace(BLUR_HATER, provenance={"frames": frames, "config": {"intensity": intensity}})


def test_reference_intensity_is_the_mean_of_the_frames_as_swept():
    """--normalize-intensity rescales σ̂ by reference / mean; the reference must be what the sweep's detector saw."""
    from camhealth.demo import _reference_intensity

    # a file that records both: mean_intensity is already after the intensity scaling
    assert _reference_intensity(_with_frames_provenance({"mean_intensity": 0.2497, "source_mean_intensity": 0.4994})) == 0.2497
    # a file with mean_intensity only holds the clean frames' mean: times config.intensity, at most 1
    assert _reference_intensity(_with_frames_provenance({"mean_intensity": 0.4994})) == pytest.approx(0.2497)
    assert _reference_intensity(_with_frames_provenance({"mean_intensity": 0.6}, intensity=2.0)) == 1.0
    with pytest.raises(SystemExit, match="needs an IOPC whose provenance has frames.mean_intensity"):
        _reference_intensity(_with_frames_provenance({}))


@pytest.mark.parametrize("argv, message", [
    (["--frames", "abc"], "argument --frames: must be a frame index or a slice start:stop[:step] of integers (e.g. 25:50), "
                          "got 'abc'"),
    (["--frames", "1:2:3:4"], "argument --frames: must be a frame index or a slice"),
    (["--frames", "0:2:0"], "argument --frames: the step of a slice start:stop:step must not be 0, got '0:2:0'"),
    (["--threads", "0"], "argument --threads: must be >= 1, got 0"),
    (["--threads", "-2"], "argument --threads: must be >= 1, got -2"),
])
def test_frames_and_threads_are_checked_by_the_parser(argv, message, tmp_path, capsys):
    """``--frames abc`` failed after parsing with "invalid literal for int() with base 10: 'abc'" (no option named),
    ``--threads 0`` was silently ignored and ``--threads -2`` failed with torch's message."""
    with pytest.raises(SystemExit) as info:  # (before the IOPC file is looked for)
        main(["closed-loop", "--iopc", str(tmp_path / "none.json"), *argv])
    assert info.value.code == 2 and message in capsys.readouterr().err


def test_exposure_limits_min_above_max_is_named_as_such(tmp_path):
    """``--limits-exposure 0.2 0.001`` was reported as a motion-blur cap problem ("renders at most 253 px … below the
    shortest exposure --limits-exposure 200 ms")."""
    from camhealth.demo import _exposure_limits

    for argv, match in ((["--limits-exposure", "0.2", "0.001"], r"--limits-exposure 0.2 0.001: MIN must be <= MAX"),
                        (["--limits-gain", "24", "0"], r"--limits-gain 24 0: MIN must be <= MAX"),
                        (["--limits-gain", "0", "40"], r"--limits-gain 0 40: must lie within the camera's range \[0, 24\] dB"),
                        (["--limits-exposure", "0.0005", "0.1"],
                         r"--limits-exposure 0.0005 0.1: must lie within the camera's range \[0.001, 0.2\] s")):
        with pytest.raises(SystemExit, match=match):  # before the IOPC file is looked for
            main(["closed-loop", "--iopc", str(tmp_path / "none.json"), *argv])
    with pytest.raises(SystemExit, match=r"--limits-exposure 0.2 0.001: MIN must be <= MAX"):
        _exposure_limits(argparse.Namespace(limits_exposure=[0.2, 0.001], motion=1500.0))


def test_parse_slice_names_what_it_refuses():
    from camhealth._cli import BadValue

    assert parse_slice("-1") == slice(-1, None) and parse_slice("-2") == slice(-2, -1)
    for bad in ("abc", "1:x", "1:2:3:4", "::0", ""):
        with pytest.raises(BadValue, match=repr(bad)):
            parse_slice(bad)


def test_table_header_names_the_first_repeats_seed():
    """The header said "AP@0.5 (seed 1)" whatever --seed was (default 0)."""
    from camhealth.demo import format_table

    row = dict(controller="fixed", ap=0.5, ap_mean=0.5, ap_std=0.0, ap_runs=[0.5], n_detections=3, exposure_ms_median=8.0,
               gain_db_median=0.0, blur_px_median=12.0, sigma_dn_median=1.5, mean_intensity_median=0.4)
    for seed in (0, 7):
        config = dict(limits_exposure=[0.001, 0.2], limits_gain=[0.0, 24.0], frames="25:50", sensor="ICX285",
                      temperature=25.0, illumination=60.0, motion=1500.0, angle=0.0, exposure=0.008, gain=0.0, seed=seed)
        res = dict(config=config, exposure_limits_s=[0.001, 0.2], frames=["a"], n_gt=1, results=[row], decisions=[],
                   estimators={"noise": "physics", "mtf": "physics"})
        table = format_table(res)
        assert f"| AP@0.5 (seed {seed}) |" in table and ("seed 1)" not in table)
