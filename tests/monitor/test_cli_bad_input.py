"""``python -m camhealth.monitor`` on bad input: a recording frame whose time the ``--diagnostics-out`` file cannot hold
is a ``frame_error`` line naming the stamp and the range (and an ERROR status at its log time), and the run goes on."""

from __future__ import annotations

import json

import numpy as np
import pytest

from camhealth.data.rosbag import RecordingWriter
from camhealth.monitor.diagnostics import ERROR, read_diagnostics
from tests.monitor.conftest import FakeMTF, FakeNoise, run_monitor_cli

T0 = 1_700_000_000 * 10**9
PERIOD = 100 * 10**6
TOPIC = "/cam"


@pytest.fixture
def fakes(monkeypatch):
    """--noise-model fake_noise / --mtf-model fake_mtf load the fast stand-ins."""
    monkeypatch.setattr("camhealth.inference.load_estimator",
                        lambda spec, *a, **k: FakeNoise() if str(spec) == "fake_noise" else FakeMTF())


def _image(w: RecordingWriter, img: np.ndarray, sec: int, nanosec: int, log_time_ns: int) -> None:
    """A mono8 Image whose header stamp is (sec, nanosec) as given (nanosec may exceed 10^9, as a driver may write it)."""
    t = w.typestore.types
    header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id="cam")
    msg = t["sensor_msgs/msg/Image"](header=header, height=img.shape[0], width=img.shape[1], encoding="mono8",
                                     is_bigendian=0, step=img.shape[1], data=img.reshape(-1))
    w.add_message(TOPIC, msg, log_time_ns)


def _recording(path, stamps, log_times=None):
    rng = np.random.default_rng(0)
    with RecordingWriter(path) as w:
        for i, (sec, nanosec) in enumerate(stamps):
            log = T0 + i * PERIOD if log_times is None else log_times[i]
            _image(w, rng.integers(0, 256, (256, 256), dtype=np.uint8), sec, nanosec, log)
    return path


def _run(tmp_path, rec, diag, capsys):
    argv = [str(rec), "--topic", TOPIC, "--sensor", "ICX285", "--noise-model", "fake_noise", "--mtf-model", "fake_mtf",
            "--diagnostics-out", str(diag), "--out", str(tmp_path / "o"), "--no-progress", "--threads", "1"]
    code, out, err = run_monitor_cli(argv, capsys)
    lines = [json.loads(ln) for ln in (tmp_path / "o" / "monitor.jsonl").read_text().splitlines()]
    return code, err, lines


SEC0 = T0 // 10**9


@pytest.mark.parametrize("suffix, bad, shown", [
    (".mcap", (2**31 - 1, 4_000_000_000), r"stamp_ns = 2147483651000000000 (2147483651 s) is out of the range of a "
                                          r"ROS 2 .mcap header stamp: [-2147483648, 2147483647] s"),
    (".bag", (2**31 - 1, 4_000_000_000), r"stamp_ns = 2147483651000000000 (2147483651 s) is out of the range of a "
                                         r"ROS 1 .bag header stamp: [0, 2147483647] s"),
    (".bag", (-5, 0), "stamp_ns = -5000000000 (-5 s) is out of the range of a ROS 1 .bag header stamp: [0, 2147483647] s"),
], ids=["mcap-beyond-2^31-s", "bag-beyond-2^31-s", "bag-before-0-s"])
def test_a_stamp_the_diagnostics_file_cannot_hold_is_a_frame_error_and_the_run_goes_on(fakes, tmp_path, capsys, suffix,
                                                                                        bad, shown):
    """A header stamp beyond 2^31 s (or before 0 s in a .bag) on one frame stopped the whole run with exit 2."""
    rec = _recording(tmp_path / "run.mcap", [(SEC0, 0), bad, (SEC0, 2 * PERIOD)])
    diag = tmp_path / f"diag{suffix}"
    code, err, lines = _run(tmp_path, rec, diag, capsys)
    assert code == 0, err
    assert len(lines) == 3 and "frame_error" not in lines[0] and "frame_error" not in lines[2]
    assert lines[1]["index"] == 1 and "assessable" not in lines[1]
    assert lines[1]["frame_error"] == f"--diagnostics-out {diag} cannot hold the time of this frame: {shown}" + (
        " (int32 seconds)" if suffix == ".mcap" else " (uint32 seconds, written as int32)")
    diags = read_diagnostics(diag)
    assert [d["stamp_ns"] for d in diags] == [T0, T0 + PERIOD, T0 + 2 * PERIOD]  # the refused frame at its log time
    assert diags[1]["level"] == ERROR and diags[1]["message"].startswith("frame not assessable: --diagnostics-out")
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["frames"] == 2 and summary["unreadable_frames"] == 1
    assert summary["diagnostics"]["messages"] == 3


def test_a_log_time_beyond_a_ros1_bag_is_a_frame_error_without_a_message(fakes, tmp_path, capsys):
    """A frame logged after 2^32 s cannot be written to a .bag at all: its frame_error line says so; the run goes on."""
    late = 2**32 * 10**9
    rec = _recording(tmp_path / "run.mcap", [(SEC0, 0), (SEC0, PERIOD), (SEC0, 2 * PERIOD)],
                     log_times=[T0, T0 + PERIOD, late])
    diag = tmp_path / "diag.bag"
    code, err, lines = _run(tmp_path, rec, diag, capsys)
    assert code == 0, err
    assert len(lines) == 3 and "frame_error" in lines[2] and "frame_error" not in lines[1]
    assert lines[2]["frame_error"] == (f"--diagnostics-out {diag} cannot hold the time of this frame: log_time_ns = "
                                       f"{late} is out of the range of a ROS 1 .bag log time: [0, 4294967295999999999] ns; "
                                       "no --diagnostics-out message for it")
    assert [d["stamp_ns"] for d in read_diagnostics(diag)] == [T0, T0 + PERIOD]


def test_an_undecodable_frame_at_a_time_the_file_cannot_hold_does_not_stop_the_run(fakes, tmp_path, capsys):
    """An undecodable image message (no header stamp) logged after 2^31 s: its ERROR status has no stamp an .mcap
    holds; its frame_error line says so and the run goes on."""
    rng = np.random.default_rng(1)
    late = 2**31 * 10**9 + 7
    with RecordingWriter(tmp_path / "run.mcap") as w:
        _image(w, rng.integers(0, 256, (256, 256), dtype=np.uint8), SEC0, 0, T0)
        w.add_raw(TOPIC, "sensor_msgs/msg/Image", b"\x00\x01\x00", late)
    diag = tmp_path / "diag.mcap"
    code, err, lines = _run(tmp_path, tmp_path / "run.mcap", diag, capsys)
    assert code == 0, err
    assert len(lines) == 2 and "cannot decode" in lines[1]["frame_error"]
    assert (f"; no --diagnostics-out message for it: stamp_ns = {late} (2147483648 s) is out of the range of a ROS 2 "
            ".mcap header stamp" in lines[1]["frame_error"])
    assert [d["stamp_ns"] for d in read_diagnostics(diag)] == [T0]


@pytest.mark.parametrize("flag, value, allowed", [
    ("--max-age", str(10**20), "1…2147483647"),  # OverflowError: int too big to convert (no option named)
    ("--max-age", str(2**63), "1…2147483647"),  # wrapped in the refresh schedule: no static patch was ever reused
    ("--max-age", "0", "1…2147483647"),
    ("--threads", str(2**31), None),  # torch: "Overflow when unpacking long" (no option named)
    ("--threads", "0", None),
])
def test_max_age_and_threads_have_a_maximum(flag, value, allowed, capsys):
    from camhealth.monitor.__main__ import MAX_AGE, THREADS_MAX, build_parser

    allowed = allowed or f"1…{THREADS_MAX}"
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args(["street", flag, value])
    assert info.value.code == 2 and f"argument {flag}: must be an integer {allowed}, got {value}" in capsys.readouterr().err
    top = MAX_AGE if flag == "--max-age" else THREADS_MAX
    assert getattr(build_parser().parse_args(["street", flag, str(top)]), flag[2:].replace("-", "_")) == top


def test_defects_min_frames_beyond_an_int32_count_writes_an_empty_map(tmp_path, capsys):
    """--defects-min-frames 2147483648 wrote a map with every pixel defective (the int32 counts were compared with a
    value that wrapped to −2^31); 10^20 stopped the run with OverflowError after the frames were scored."""
    import cv2

    from tests.monitor.test_defect_map import _defect_frame

    frame, _ = _defect_frame()
    png = tmp_path / "f.png"
    cv2.imwrite(str(png), (frame.numpy() * 255).round().astype(np.uint8))
    for n in (2**31, 10**20):
        out_map = tmp_path / f"found{n}.npz"
        argv = [str(png), "--sensor", "ICX285", "--no-mtf", "--noise-model", "noise_source_full", "--mode", "map",
                "--defects-out", str(out_map), "--defects-min-frames", str(n), "--no-progress", "--threads", "1"]
        code, out, err = run_monitor_cli(argv, capsys)
        assert code == 0, err
        assert f"defect map: {out_map} (0 pixels flagged in at least {n} frames)" in out + err
        with np.load(out_map) as z:
            assert not z["defective_pixels"].any() and int(z["flagged_frames"].max()) == 1
