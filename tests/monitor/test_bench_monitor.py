"""``python -m camhealth.bench monitor``: registered, rows and summary lines present (tiny run, untrained
networks; no wall-clock assertions)."""

import pytest
import torch

from camhealth.bench import BENCHMARKS
from camhealth.bench.__main__ import main

def _printed(argv, capsys) -> str:
    """Run ``python -m camhealth.bench`` with ``argv`` (its ``--threads`` restored afterwards) → what it printed."""
    n = torch.get_num_threads()
    try:
        assert main(argv) == 0
    finally:
        torch.set_num_threads(n)
    return capsys.readouterr().out


TINY = ["monitor", "--untrained", "--frames", "2", "--warmup", "0", "--width", "384", "--height", "320",
        "--slow-frames", "1", "--thesis-patches", "1", "--threads", "1", "--brightness", "1.6", "--no-memory-probe"]


def test_registered():
    assert BENCHMARKS["monitor"] == "camhealth.bench.monitor"


def test_tiny_run_prints_rows_and_summary(capsys, tmp_path):
    text = _printed(TINY + ["--out", str(tmp_path / "b.md")], capsys)
    for row in ("every patch (no skipping)", "informative patches (fully monitored)", "adaptive (skip + reuse static",
                "informative patches, fp32", "thesis-size noise net, same noise patches",
                "reading the recording (.mcap)", "reading the recording (.db3)", "reading the recording (.bag)"):
        assert row in text
    for line in ("target ≤ 100 ms", "this benchmark process", "skipped as uninformative", "σ_total on informative patches",
                 "MTF AMAE", "UNTRAINED", "load average", "reading a recording adds", "of the adaptive monitor's"):
        assert line in text
    assert "CPU" in text and "noise + " in text and "thesis net / camhealth noise" in text and "bf16 − fp32" in text
    assert "| adaptive (skip + reuse static + coarse→refine) |" in (tmp_path / "b.md").read_text()


def test_static_pairs_row_on_a_still_scene(capsys):
    """``--static-pairs``: the row and its summary line; on the still dead-leaves scene (the same scene in every frame,
    a new noise realisation) the shipped estimator reads noise patches from a pair from the second frame on."""
    import re

    argv = ["monitor", "--frames", "3", "--warmup", "0", "--width", "384", "--height", "320", "--scene", "deadleaves",
            "--slow-frames", "0", "--thesis-patches", "0", "--threads", "1", "--no-memory-probe", "--static-pairs"]
    text = _printed(argv, capsys)
    assert "informative patches + static pairs" in text
    m = re.search(r"static pairs: ([0-9.]+) noise patches per frame read from a pair \(frames 2…3: ([0-9.]+)\)", text)
    assert m is not None and float(m.group(2)) > 0
    assert "against the informative patches' RMS" in text


def test_true_gain_makes_a_mismatch_every_monitor_follows(capsys):
    """``--true-gain-db``: the frames come from a sensor 12 dB above the metadata's gain; the summary gives the ξ of a
    right answer (the metadata's closed form less the realised σ, negative: the image is noisier) and each monitor's
    ξ, which follow it in sign and size on the still dead-leaves scene."""
    import re

    argv = ["monitor", "--frames", "3", "--warmup", "0", "--width", "384", "--height", "320", "--scene", "deadleaves",
            "--slow-frames", "0", "--thesis-patches", "0", "--threads", "1", "--no-memory-probe", "--static-pairs",
            "--gain-db", "6", "--true-gain-db", "18"]
    text = _printed(argv, capsys)
    m = re.search(r"metadata mismatch: the sensor's gain 18 dB, the metadata's 6 dB; .* has median ([-+0-9.]+) DN, "
                  r"ξ median: informative ([-+0-9.]+) DN, adaptive ([-+0-9.]+) DN", text)
    assert m is not None, text[-2000:]
    right, informative, adaptive = (float(v) for v in m.groups())
    assert right < -1.0
    for xi in (informative, adaptive):
        assert xi == pytest.approx(right, rel=0.25)
    pair = re.search(r"static pairs: .* ξ median ([-+0-9.]+) DN", text)
    assert pair is not None and float(pair.group(1)) == pytest.approx(right, rel=0.25)
    assert "metadata correct, truth 0" not in text


@pytest.mark.parametrize("bad", [["--frames", "0"], ["--thesis-patches", "-1"]])
def test_bad_options(bad):
    with pytest.raises(ValueError, match=bad[0]):
        main(TINY + bad)


def test_rss_probe_runs_one_monitor(model_files, tmp_path):
    import json

    from camhealth.bench.monitor import rss_probe
    from camhealth.physics import CameraMetadata

    torch.save(torch.randint(30, 220, (2, 256, 320), dtype=torch.uint8), tmp_path / "frames.pt")
    meta = {k: v[0] for k, v in CameraMetadata.preset("ICX285").to_dict().items()}
    cfg = {"frames": str(tmp_path / "frames.pt"), "noise_model": str(model_files[0]), "mtf_model": str(model_files[1]),
           "metadata": meta, "precision": "bf16", "threads": torch.get_num_threads()}
    (tmp_path / "probe.json").write_text(json.dumps(cfg))
    out = rss_probe(str(tmp_path / "probe.json"))
    assert 0 < out["start_mb"] <= out["peak_mb"]
    assert len(out["ms"]) == len(out["cpu_ms"]) == 2 and all(t > 0 for t in out["ms"])


def test_recording_times_read_every_frame(tmp_path):
    from camhealth.bench.monitor import recording_times
    from camhealth.physics import CameraMetadata

    frames = torch.randint(0, 256, (3, 40, 56), dtype=torch.uint8)
    meta = CameraMetadata.preset("ICX285", gain_db=6.0)
    for suffix in (".mcap", ".bag"):
        times = recording_times(frames, meta, tmp_path, suffix)
        assert len(times) == 3 and all(t > 0 for t in times)


MOTION = ["monitor", "--motion", "--untrained", "--frames", "3", "--warmup", "0", "--width", "640", "--height", "512",
          "--window", "2", "--noise-samples", "2", "--mtf-samples", "2", "--slow-frames", "1", "--thesis-patches", "1",
          "--threads", "1", "--no-memory-probe"]


def test_motion_run_prints_both_modes_per_stream_and_accuracy(capsys):
    text = _printed(MOTION, capsys)
    for stream in ("static", "ego-motion", "photos"):
        assert f"{stream}: sampled" in text and f"{stream}: every informative patch" in text
        assert f"accuracy, {stream}" in text
    for q in ("σ_PN", "σ_DCSN", "σ_RN", "ξ", "σ_total", "MTF̃"):
        assert q in text
    assert "thesis-size noise net, the sampled noise patches" in text and "p95" in text and "CPU" in text
    assert "2.0 of" in text  # two samples per frame and task went through the networks
    assert "defined for 1280×1024 only" in text


def test_ego_motion_crops_move_every_frame():
    from camhealth.bench.monitor_motion import ego_motion_crops

    clip = torch.rand(6, 1, 96, 128)
    out = ego_motion_crops(clip.expand(6, -1, -1, -1).contiguous() * 0 + clip[:1], (64, 80))
    assert out.shape == (6, 1, 64, 80) and float(out.min()) >= 0 and float(out.max()) <= 1
    for i in range(5):  # the same scene, a new crop every frame: consecutive frames differ
        assert float((out[i + 1] - out[i]).abs().mean()) > 1e-3


EXPOSURE = ["monitor", "--exposure-step", "--frames", "3", "--width", "384", "--height", "320", "--sensor", "EV76C661",
            "--gain-db", "6", "--exposure-s", "0.02", "--temperature-c", "30", "--threads", "1"]


def test_exposure_step_splits_a_readout_excess_only_with_the_other_exposure_time(capsys):
    """``--exposure-step``: the exposure time alternates 0.16 / 0.02 s on three cameras. Every monitor row is there; a
    matched camera reads the closed form (no error, alarm ok); with 3× the white noise, the monitors that keep the
    other exposure time's evidence read the long frames' dark current right, those that do not put a large part of
    the excess into it."""
    import re

    text = _printed(EXPOSURE, capsys)
    rows = {}
    for line in text.splitlines():
        m = re.match(r"\| (matched|hotter sensor|white noise ×3) \| (sampled|map) \| (on|off) \| ([0-9.]+) \(", line)
        if m:
            rows[m.group(1, 2, 3)] = (float(m.group(4)), line)
    assert len(rows) == 12
    for mode in ("sampled", "map"):
        assert rows[("matched", mode, "on")][0] == 0.0 and "| 0/2 / 2/2 | – / 0 | 2/2 |" in rows[("matched", mode, "on")][1]
        assert rows[("white noise ×3", mode, "on")][0] < 0.2 < 1.0 < rows[("white noise ×3", mode, "off")][0]
        assert "| 2/2 / 0/2 | 2 / 2 | 2/2 |" in rows[("white noise ×3", mode, "on")][1]  # named: readout noise
        assert rows[("white noise ×3", mode, "off")][1].endswith("| 0/2 |")  # no other exposure time drawn on
    assert "exposure alternating 160 / 20 ms (×8)" in text


@pytest.mark.parametrize("extra, message", [
    (["--exposure-ratio", "1"], r"--exposure-ratio = 1.0 must be a number > 1"),
    (["--exposure-ratio", "20"], r"exposure_s.*0.4.*\[0.001, 0.2\] s"),
    (["--frames", "2"], r"--frames must be >= 3 with --exposure-step"),
])
def test_exposure_step_refuses_bad_settings(extra, message):
    with pytest.raises(ValueError, match=message):
        main(EXPOSURE + extra)


def test_pool_sizes_reads_few_patches_worse_than_eight(capsys):
    """``--pool-sizes``: every group size has its timing row and its line; read alone, fewer of the patches that their
    whole frame reads are assessable than read in eights (the measurement behind NOISE_MIN_POOL)."""
    import re

    out = _printed(["monitor", "--pool-sizes", "--pool-draws", "1", "--gain-db", "0", "--exposure-s", "0.02",
                    "--temperature-c", "45", "--threads", "2", "--markdown"], capsys)
    for k in ("1 patch", "2 patches", "8 patches", "12 patches", "the whole frame"):
        assert f"| pooled reading of {k} |" in out
    share = {int(m.group(1)): int(m.group(2)) for m in re.finditer(r"^\| (\d+) \| (\d+) % \(", out, re.M)}
    assert set(share) == {1, 2, 4, 6, 8, 12}
    assert share[1] < share[8] and share[8] >= 90


@pytest.mark.parametrize("extra, message", [
    (["--pool-draws", "0"], r"--pool-draws must be an integer >= 1"),
    (["--pool-step-db", "-3"], r"--pool-step-db must be a finite gain step >= 0 dB"),
])
def test_pool_sizes_refuses_bad_settings(extra, message):
    with pytest.raises(ValueError, match=message):
        main(["monitor", "--pool-sizes", *extra])
