"""``python -m camhealth.monitor RECORDING --topic …``: a small recording made here with rosbags' writers (street-clip
frames with a known added noise and a known gain topic) in every format; the monitor reads it, applies the gain
per frame (a change restarts the aggregation) and writes diagnostics that read back with the right levels and
stamps. Bad input gives one-line errors (exit 2) or counted frame errors — never a crash."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from camhealth.data.rosbag import RecordingWriter, format_stamp
from camhealth.monitor import Monitor
from camhealth.monitor.__main__ import build_parser
from camhealth.monitor.diagnostics import ERROR, KEYS, OK, WARN, frame_level, read_diagnostics
from camhealth.monitor.recording import RecordingOptions
from camhealth.monitor.sources import open_source
from tests.monitor.conftest import FakeMTF, FakeNoise, run_monitor_cli

T0 = 1_700_000_000 * 10**9
PERIOD = 100 * 10**6  # 10 frames/s
NOISE_DN = 6.0  # noise added to the street frames (realised σ ≈ 6.7 DN by the fakes' robust estimate)
BASE_DN = 6.6  # σ the fake noise model expects at 0 dB; ×2 at 6 dB
GAINS = [0.0, 0.0, 6.0, 6.0]  # gain topic value in effect for frames 0…3
TOPIC = "/camera/image_raw"


class GainAwareNoise(FakeNoise):
    """ξ = σ expected from the gain metadata (BASE_DN · 10^(gain/20)) − σ measured in the patch."""

    def predict(self, patches, metadata=None, precision="fp32", batch_size=256):
        out = super().predict(patches, metadata, precision, batch_size)
        expected = BASE_DN * 10.0 ** (float(metadata.gain_db[0]) / 20.0)
        out["xi"] = expected - out["sigma_total"]
        return out


@pytest.fixture
def fakes(monkeypatch):
    """--noise-model fake_noise / --mtf-model fake_mtf load the fast stand-ins."""
    made = {}

    def load(spec, *a, **k):
        made[str(spec)] = GainAwareNoise() if str(spec) == "fake_noise" else FakeMTF()
        return made[str(spec)]

    monkeypatch.setattr("camhealth.inference.load_estimator", load)
    return made


def _noisy(frame: torch.Tensor, seed: int) -> np.ndarray:
    g = np.random.default_rng(seed)
    return np.clip(frame[0].numpy() * 255 + g.normal(0, NOISE_DN, frame.shape[1:]), 0, 255).round().astype(np.uint8)


def write_street_recording(path, street_frames, gains=GAINS, corrupt_last=True):
    """Frames 0, 2, 3: street + σ = 6 DN; frame 1: flat gray + noise (no structure: blur not assessable); a gain
    message just before each frame whose value changes; then an undecodable image message."""
    with RecordingWriter(path) as w:
        for i, gain in enumerate(gains):
            t = T0 + i * PERIOD
            if i == 0 or gain != gains[i - 1]:
                w.add_number("/camera/gain", gain, t - 2 * 10**6)
            img = _noisy(street_frames[min(i, len(street_frames) - 1)], i)
            if i == 1:
                img = np.clip(128 + np.random.default_rng(9).normal(0, NOISE_DN, img.shape), 0, 255).round().astype(np.uint8)
            w.add_image(TOPIC, img, t, log_time_ns=t + 5 * 10**6, frame_id="camera_optical")
        if corrupt_last:
            w.add_raw(TOPIC, "sensor_msgs/msg/Image", b"\x00\x01\x00", T0 + len(gains) * PERIOD)
    return path



def _run(argv, capsys):
    return run_monitor_cli(argv, capsys, "--no-progress", "--threads", "1")


def _lines(text):
    return [json.loads(ln) for ln in text.splitlines() if ln.strip()]


@pytest.mark.parametrize("rec_suffix,diag_suffix", [(".mcap", ".mcap"), (".db3", ".bag"), (".bag", ".bag"), ("", ".mcap")])
def test_monitor_reads_recording_uses_gain_topic_and_writes_diagnostics(rec_suffix, diag_suffix, fakes, street_frames,
                                                                        tmp_path, capsys):
    rec = write_street_recording(tmp_path / (f"run{rec_suffix}" if rec_suffix else "run_bag"), street_frames)
    diag = tmp_path / f"diag{diag_suffix}"
    argv = [str(rec), "--topic", TOPIC, "--gain-topic", "/camera/gain", "--sensor", "ICX285", "--noise-model", "fake_noise",
            "--mtf-model", "fake_mtf", "--diagnostics-out", str(diag), "--out", str(tmp_path / "o")]
    code, out, err = _run(argv, capsys)
    assert code == 0, err
    lines = _lines((tmp_path / "o" / "monitor.jsonl").read_text())
    assert len(lines) == 5 and "frame_error" in lines[4] and "cannot decode sensor_msgs/msg/Image" in lines[4]["frame_error"]
    reports = lines[:4]
    assert [d["metadata"]["gain_db"] for d in reports] == GAINS  # the gain topic, per frame
    assert [d["source_id"] for d in reports] == [f"{TOPIC}@{format_stamp(T0 + i * PERIOD)}" for i in range(4)]
    for d in (reports[0], reports[2], reports[3]):
        assert abs(d["noise"]["sigma_dn"]["total"]["median"] - 6.7) < 0.8  # the known added noise
    # the gain change at frame 2 restarted the aggregation: ξ at 6 dB alone, not a median with the 0-dB values
    assert [d["alarm"]["state"] for d in reports] == ["ok", "ok", "cleaner", "cleaner"]
    assert reports[2]["noise"]["patches"]["reused"] == 0
    assert reports[1]["mtf"]["assessable"] is False and reports[1]["noise"]["assessable"] is True

    diags = read_diagnostics(diag)
    assert [d["level"] for d in diags] == [OK, WARN, ERROR, ERROR, ERROR]
    assert [d["stamp_ns"] for d in diags[:4]] == [T0 + i * PERIOD for i in range(4)]  # the image header stamps
    assert [d["log_time_ns"] for d in diags[:4]] == [T0 + i * PERIOD + 5 * 10**6 for i in range(4)]
    assert all(d["name"] == f"camhealth: {TOPIC}" for d in diags)
    assert diags[0]["frame_id"] == "camera_optical" and diags[0]["hardware_id"] == "camera_optical"
    v0, v2 = diags[0]["values"], diags[2]["values"]
    assert list(v0) == list(KEYS) and v0["level"] == "OK" and v0["alarm"] == "ok" and float(v0["gain_db"]) == 0.0
    assert v0["noise_row_dn"] == "0" and v0["noise_col_dn"] == "0"  # no row or column noise in the street clip
    assert v2["alarm"] == "cleaner" and float(v2["gain_db"]) == 6.0 and float(v2["xi_dn"]) > 3
    assert abs(float(v0["noise_total_dn"]) - reports[0]["noise"]["sigma_dn"]["total"]["median"]) < 1e-3
    assert float(v0["blur_mtf_indicator"]) == pytest.approx(reports[0]["mtf"]["indicator"]["median"], abs=1e-3)
    assert "ξ alarm: image is cleaner than the metadata allow" in diags[2]["message"]
    assert "blur not assessable" in diags[1]["message"]
    assert diags[4]["values"]["level"] == "ERROR" and "frame not assessable: cannot decode" in diags[4]["message"]
    assert diags[4]["stamp_ns"] == T0 + 4 * PERIOD  # undecodable: stamped with its log time
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["kind"] == "recording" and summary["unreadable_frames"] == 1
    assert summary["recording"]["decoded"] == 4 and summary["recording"]["undecodable"] == 1
    assert summary["recording"]["state"]["gain_db"]["messages"] == 2
    assert summary["diagnostics"]["levels"] == {"OK": 1, "WARN": 1, "ERROR": 3}
    assert "camera state gain_db: /camera/gain (std_msgs/msg/Float64, field data, dB, 2 value(s), matched by log time)" in out
    assert "5 DiagnosticArray on /diagnostics: 1 OK, 1 WARN, 3 ERROR" in out


def test_without_the_gain_topic_the_metadata_gain_holds(fakes, street_frames, tmp_path, capsys):
    rec = write_street_recording(tmp_path / "run.mcap", street_frames, corrupt_last=False)
    code, out, err = _run([str(rec), "--topic", TOPIC, "--sensor", "ICX285", "--noise-model", "fake_noise",
                           "--mtf-model", "fake_mtf"], capsys)
    assert code == 0, err
    lines = _lines(out)
    assert [d["metadata"]["gain_db"] for d in lines] == [0.0] * 4 and {d["alarm"]["state"] for d in lines} == {"ok"}


def test_state_units_and_out_of_range_values(fakes, street_frames, tmp_path, capsys):
    rec = tmp_path / "run.bag"
    with RecordingWriter(rec) as w:
        for i, (factor, exp_us, kelvin) in enumerate([(1.0, 10000, 313.15), (2.0, 20000, 303.15), (30.0, 20000, 303.15)]):
            t = T0 + i * PERIOD
            w.add_number("/cam/gain_factor", factor, t - 1)
            w.add_number("/cam/exposure_us", exp_us, t - 1, msgtype="std_msgs/msg/UInt32")
            w.add_temperature("/cam/temp", kelvin, t - 1)
            w.add_image(TOPIC, _noisy(street_frames[i], i), t)
    argv = [str(rec), "--topic", TOPIC, "--sensor", "ICX285", "--noise-model", "fake_noise", "--mtf-model", "fake_mtf",
            "--gain-topic", "/cam/gain_factor", "--gain-unit", "factor", "--exposure-topic", "/cam/exposure_us",
            "--exposure-unit", "us", "--temperature-topic", "/cam/temp:temperature", "--temperature-unit", "k"]
    code, out, err = _run(argv, capsys)
    assert code == 0, err
    a, b, c = _lines(out)
    assert a["metadata"] == {"gain_db": 0.0, "exposure_s": 0.01, "temperature_c": 40.0}
    assert b["metadata"]["gain_db"] == pytest.approx(20 * math.log10(2), abs=1e-4) and b["metadata"]["exposure_s"] == 0.02
    assert b["metadata"]["temperature_c"] == pytest.approx(30.0)
    assert "frame_error" in c and "camera state gain_db = 30 (factor) = 29.5424 dB from --gain-topic /cam/gain_factor" in c["frame_error"]
    assert "out of the allowed range [0, 24] dB" in c["frame_error"] and "--gain-unit" in c["frame_error"]
    assert "1 with camera state out of range" in err


def test_a_non_finite_state_reading_refuses_the_frames_it_governs(fakes, street_frames, tmp_path, capsys):
    """A NaN gain reading is no reading to skip: the frames it governs are not assessable and say why, whether it
    comes before the first finite value (not the metadata's gain) or after one (not the previous reading)."""
    rec = tmp_path / "run.mcap"
    with RecordingWriter(rec) as w:
        for i, gain in enumerate([float("nan"), 12.0, float("nan"), float("inf")]):
            t = T0 + i * PERIOD
            w.add_number("/cam/gain", gain, t - 1)
            w.add_image(TOPIC, _noisy(street_frames[i], i), t)
    code, out, err = _run([str(rec), "--topic", TOPIC, "--sensor", "ICX285", "--noise-model", "fake_noise",
                           "--mtf-model", "fake_mtf", "--gain-topic", "/cam/gain"], capsys)
    assert code == 0, err
    a, b, c, d = _lines(out)
    assert b["metadata"]["gain_db"] == 12.0 and "frame_error" not in b
    for line, shown in ((a, "nan"), (c, "nan"), (d, "inf")):
        assert f"camera state gain_db = {shown} dB from --gain-topic /cam/gain" in line["frame_error"]
        assert "is not a finite number; allowed: [0, 24] dB" in line["frame_error"]
    assert "3 with camera state out of range" in err and "before its first value" not in err


def test_unknown_or_missing_topic_lists_the_image_topics(fakes, street_frames, tmp_path, capsys):
    rec = write_street_recording(tmp_path / "run.bag", street_frames, corrupt_last=False)
    for extra, what in (([], "choose the camera with --topic"), (["--topic", "/camera/image"], "'/camera/image' is not in recording")):
        code, out, err = _run([str(rec), *extra, "--sensor", "ICX285", "--noise-model", "fake_noise", "--mtf-model", "fake_mtf"], capsys)
        assert code == 2 and out == "" and "Traceback" not in err
        assert what in err and f"image topics: {TOPIC} (sensor_msgs/msg/Image, 4 messages)" in err
        assert len(err.strip().splitlines()) == 1
    code, _, err = _run([str(rec), "--topic", TOPIC, "--gain-topic", "/camera/gian", "--sensor", "ICX285",
                         "--noise-model", "fake_noise", "--mtf-model", "fake_mtf"], capsys)
    assert code == 2 and "--gain-topic /camera/gian: topic '/camera/gian' is not in recording" in err
    assert "/camera/gain (std_msgs/msg/Float64, 2 messages)" in err


def test_bad_recordings_and_options_exit_2_with_one_line(fakes, street_frames, tmp_path, capsys):
    rec = write_street_recording(tmp_path / "run.mcap", street_frames, corrupt_last=False)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(rec.read_bytes()[: rec.stat().st_size // 2])
    bad_enc = tmp_path / "float.bag"
    with RecordingWriter(bad_enc) as w:
        w.add_image(TOPIC, np.zeros((8, 8, 4), np.uint8), T0, encoding="32FC1")
    models = ["--sensor", "ICX285", "--noise-model", "fake_noise", "--mtf-model", "fake_mtf"]
    cases = [
        ([str(cut), "--topic", TOPIC], "cannot read recording"),
        ([str(bad_enc), "--topic", TOPIC], "image encoding '32FC1' cannot be converted to gray"),
        (["street", "--topic", TOPIC], "apply to ROS recordings"),
        (["street", "--diagnostics-out", str(tmp_path / "d.mcap")], "--diagnostics-out needs a ROS recording"),
        ([str(rec), "--topic", TOPIC, "--diagnostics-out", str(tmp_path / "d.txt")], "must end in .mcap (ROS 2) or .bag"),
    ]
    for argv, match in cases:
        code, out, err = _run([*argv, *models], capsys)
        assert code == 2 and match in err and "Traceback" not in err, (argv, err)
        assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "d.txt").exists() and not list(tmp_path.glob(".d.*"))


def test_diagnostics_out_may_not_overwrite_the_recording(fakes, street_frames, tmp_path, capsys):
    """--diagnostics-out naming the recording it reads (as a file, or a storage file of a rosbag2 folder): exit 2
    before the run, naming the input; the recording is left as it was."""
    models = ["--sensor", "ICX285", "--noise-model", "fake_noise", "--mtf-model", "fake_mtf"]
    rec = write_street_recording(tmp_path / "run.mcap", street_frames, corrupt_last=False)
    folder = write_street_recording(tmp_path / "run_bag", street_frames, corrupt_last=False)
    (member,) = folder.glob("*.mcap")
    before = {p: p.read_bytes() for p in (rec, member, folder / "metadata.yaml")}
    for source, target, given in ((rec, rec, f"SOURCE {rec}"), (rec, tmp_path / "sub" / ".." / "run.mcap", f"SOURCE {rec}"),
                                  (folder, member, f"SOURCE {member}")):
        code, out, err = _run([str(source), "--topic", TOPIC, *models, "--diagnostics-out", str(target),
                               "--out", str(tmp_path / "o")], capsys)
        assert code == 2 and out == "" and f"--diagnostics-out {target} would overwrite the input {given}" in err, err
        assert not (tmp_path / "o").exists()  # refused before the run
    assert all(p.read_bytes() == data for p, data in before.items())


def test_a_bad_diagnostics_out_is_refused_before_the_outputs_are_opened(fakes, street_frames, tmp_path, capsys):
    """A --diagnostics-out in a missing folder (or under a file): exit 2 before the run; the monitor.jsonl of an
    earlier run in --out DIR is left as it was."""
    rec = write_street_recording(tmp_path / "run.mcap", street_frames, corrupt_last=False)
    argv = [str(rec), "--topic", TOPIC, "--sensor", "ICX285", "--noise-model", "fake_noise", "--mtf-model", "fake_mtf",
            "--out", str(tmp_path / "o")]
    code, _, err = _run(argv, capsys)
    assert code == 0, err
    earlier = (tmp_path / "o" / "monitor.jsonl").read_text()
    assert len(_lines(earlier)) == 4
    (tmp_path / "afile").write_text("x")
    for target, why in ((tmp_path / "nodir" / "d.mcap", f"folder of the diagnostics file does not exist: {tmp_path / 'nodir'}"),
                        (tmp_path / "afile" / "d.mcap", f"{tmp_path / 'afile'} is a file, not a folder"),
                        (tmp_path, "must end in .mcap")):
        code, out, err = _run([*argv, "--diagnostics-out", str(target)], capsys)
        assert (tmp_path / "o" / "monitor.jsonl").read_text() == earlier  # not truncated
        assert code == 2 and f"--diagnostics-out {target}: " in err and why in err, err
    assert not (tmp_path / "nodir").exists()


@pytest.mark.parametrize("bit_depth", [None, 12])
def test_the_summary_names_the_scaling_of_a_recordings_frames(bit_depth, fakes, tmp_path, capsys):
    """mono16 images (12-bit data in 16-bit words) and mono8 ones: the summary's ``input_scaling`` names the divisor
    the reader used — ÷65535 by default, ÷4095 with --bit-depth 12 — and ÷255 for the 8-bit frames."""
    g = np.random.default_rng(0)
    rec = tmp_path / "run.mcap"
    with RecordingWriter(rec) as w:
        for i in range(2):
            w.add_image(TOPIC, np.clip(2048 + g.normal(0, 40, (256, 256)), 0, 4095).astype(np.uint16), T0 + i * PERIOD)
        w.add_image(TOPIC, g.integers(60, 190, (256, 256), dtype=np.uint8), T0 + 2 * PERIOD)
    extra = [] if bit_depth is None else ["--bit-depth", str(bit_depth)]
    code, out, err = _run([str(rec), "--topic", TOPIC, "--sensor", "ICX285", "--noise-model", "fake_noise", "--no-mtf",
                           "--out", str(tmp_path / "o"), *extra], capsys)
    assert code == 0, err
    wide = ("mono16 (16-bit) read as 16-bit data (÷65535, the full 16-bit word)" if bit_depth is None
            else "mono16 (16-bit) read as 12-bit data (÷4095, as given)")
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["input_scaling"] == {wide: 2, "mono8: 8-bit data (÷255)": 1}
    assert f"input: {wide} (2 frame(s))" in out
    source = open_source(rec, bit_depth=bit_depth or "auto", recording=RecordingOptions(topic=TOPIC))
    try:  # the frames the monitor reads: divided by the divisor named
        first = next(iter(source))
    finally:
        source.close()
    assert first.scaling == wide
    assert float(first.frame.mean()) == pytest.approx(2048 / (65535 if bit_depth is None else 4095), rel=0.01)


def test_out_of_order_stamps_are_reported(fakes, street_frames, tmp_path, capsys):
    rec = tmp_path / "run.mcap"
    with RecordingWriter(rec) as w:
        for i, k in enumerate([0, 2, 1]):  # the third image is stamped before the second
            w.add_image(TOPIC, _noisy(street_frames[i], i), T0 + k * PERIOD, log_time_ns=T0 + i * PERIOD + 1)
    diag = tmp_path / "d.mcap"
    code, out, err = _run([str(rec), "--topic", TOPIC, "--sensor", "ICX285", "--noise-model", "fake_noise",
                           "--mtf-model", "fake_mtf", "--diagnostics-out", str(diag)], capsys)
    assert code == 0, err
    assert len(_lines(out)) == 3
    assert "warning: 1 frame(s) with a header stamp earlier than the frame before (message 2: header stamp" in err
    assert [d["stamp_ns"] for d in read_diagnostics(diag)] == [T0, T0 + 2 * PERIOD, T0 + PERIOD]  # kept as recorded


def test_monitor_run_api_applies_the_recorded_state(street_frames, tmp_path):
    rec = write_street_recording(tmp_path / "run.db3", street_frames)
    noise = GainAwareNoise()
    mon = Monitor(noise_model=noise, mtf_model=FakeMTF(), sensor="ICX285")
    got = list(mon.run(rec, recording=RecordingOptions(topic=TOPIC, gain_topic="/camera/gain")))
    assert [r.metadata["gain_db"] if r else None for _, r in got] == [*GAINS, None]
    assert got[-1][0].error and float(noise.last_metadata.gain_db[0]) == 6.0


# ------------------------------------------------------------------ levels
def _report(mon: Monitor, frame, **kw):
    return mon.process(frame, **kw)


def test_levels_for_uncertain_unavailable_and_not_assessable(street_frames):
    frame = torch.from_numpy(_noisy(street_frames[0], 0))
    # ξ beyond the 1-DN threshold but within the limit set by a wide spread over the patches → WARN (uncertain)
    mon = Monitor(noise_model=FakeNoise(xi_dn=0.0), mtf_model=FakeMTF(), sensor="ICX285", xi_sigmas=50.0)
    rep = _report(mon, frame)
    rep.alarm = {**rep.alarm, "state": "ok", "xi_dn": -1.5, "limit_dn": 4.0}
    level, msg = frame_level(rep, 1.0)
    assert level == WARN and "uncertain: |ξ̃| = 1.50 DN exceeds 1 DN but not the limit 4.00 DN" in msg
    # ξ alarm → ERROR
    mon = Monitor(noise_model=FakeNoise(xi_dn=-5.0), mtf_model=FakeMTF(), sensor="ICX285")
    assert frame_level(_report(mon, frame))[0] == ERROR
    # no noise model: ξ not checked → WARN
    mon = Monitor(noise_model=None, mtf_model=FakeMTF())
    level, msg = frame_level(_report(mon, frame))
    assert level == WARN and "ξ not checked" in msg
    # black frame: noise not assessable → ERROR
    mon = Monitor(noise_model=FakeNoise(), mtf_model=FakeMTF(), sensor="ICX285")
    level, msg = frame_level(_report(mon, torch.zeros(300, 400, dtype=torch.uint8)))
    assert level == ERROR and msg.startswith("noise not assessable")


def test_help_lists_the_recording_options(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--help"])
    text = capsys.readouterr().out
    for opt in ("--topic", "--gain-topic", "--exposure-unit", "--bit-depth", "--bayer", "--diagnostics-out", ".mcap"):
        assert opt in text


def test_damage_met_while_reading_keeps_the_frames_before_it(fakes, street_frames, tmp_path, capsys, monkeypatch):
    """A reader that fails in the middle of the image stream (simulated: the readers of rosbags detect the
    damage of a cut file when opening it) ends the stream there: the frames before it are monitored, and the
    summary and a warning line say where reading stopped."""
    from camhealth.data.rosbag import Recording

    rec = write_street_recording(tmp_path / "run.mcap", street_frames, corrupt_last=False)
    original = Recording._messages

    def failing(self, conns):
        for n, item in enumerate(original(self, conns)):
            if n == 2:
                raise OSError("chunk data ends early")
            yield item

    monkeypatch.setattr(Recording, "_messages", failing)
    code, out, err = _run([str(rec), "--topic", TOPIC, "--sensor", "ICX285", "--noise-model", "fake_noise",
                           "--mtf-model", "fake_mtf"], capsys)
    assert code == 0, err
    assert [d["index"] for d in _lines(out)] == [0, 1]
    assert (f"warning: reading stopped after message 2 of 4 on {TOPIC}: chunk data ends early (damaged or truncated "
            "recording)") in err


@pytest.mark.parametrize("fmt, lossy", [("jpeg", True), ("rgb8; jpeg compressed bgr8", True), ("png", False),
                                        ("mono8; png compressed", False), ("raw", None)])
def test_static_pairs_warn_on_a_compressed_topic_unless_png(fmt, lossy, fakes, tmp_path, capsys):
    """``--static-pairs`` on a recording: a ``CompressedImage`` topic is named as lossy unless its format is PNG
    (raw ``Image`` topics never are); the run goes on either way."""
    import cv2

    rec = tmp_path / "run.mcap"
    g = np.random.default_rng(3)
    with RecordingWriter(rec) as w:
        for i in range(2):
            img = np.clip(128 + g.normal(0, NOISE_DN, (256, 256)), 0, 255).round().astype(np.uint8)
            t = T0 + i * PERIOD
            if lossy is None:
                w.add_image(TOPIC, img, t)
            else:
                w.add_compressed(TOPIC, cv2.imencode(".jpg" if lossy else ".png", img)[1], fmt, t)
    code, out, err = _run([str(rec), "--topic", TOPIC, "--noise-model", "fake_noise", "--no-mtf", "--sensor", "ICX285",
                           "--static-pairs"], capsys)
    assert code == 0, err
    warned = f"topic {TOPIC} holds sensor_msgs/CompressedImage messages (format {fmt!r}; only PNG is lossless)"
    assert (warned in err) == bool(lossy) and err.count("warning: --static-pairs") == int(bool(lossy))


@pytest.mark.parametrize("unit", [["--exposure-unit", "ms"], ["--gain-unit", "factor"], ["--temperature-unit", "k"]])
def test_a_state_unit_without_its_topic_is_refused(unit, fakes, street_frames, tmp_path, capsys):
    """A unit option names the unit of its topic's values: without that topic it would be ignored (a forgotten
    ``--exposure-topic``), so it is a one-line error (exit 2) naming both options; RecordingOptions says the same."""
    rec = write_street_recording(tmp_path / "run.mcap", street_frames, corrupt_last=False)
    code, out, err = _run([str(rec), "--topic", TOPIC, "--sensor", "ICX285", "--noise-model", "fake_noise",
                           "--mtf-model", "fake_mtf", *unit], capsys)
    name = unit[0][2:].split("-")[0]
    assert code == 2 and out == "" and f"{unit[0]} {unit[1]} needs --{name}-topic" in err, err
    with pytest.raises(ValueError, match=f"{unit[0]} {unit[1]} needs --{name}-topic"):
        RecordingOptions(topic=TOPIC, **{f"{name}_unit": unit[1]})
    assert RecordingOptions(topic=TOPIC, **{f"{name}_unit": unit[1], f"{name}_topic": "/t"}).state_topics()


def test_a_gain_topic_without_metadata_reports_only_the_recorded_gain(fakes, street_frames, tmp_path, capsys):
    """No ``--metadata``/``--sensor`` and no noise model reading metadata: a frame's ``metadata`` and the diagnostics
    hold the recorded gain only — no exposure and temperature from a preset nobody named."""
    rec = write_street_recording(tmp_path / "run.mcap", street_frames, corrupt_last=False)
    diag = tmp_path / "d.mcap"
    code, out, err = _run([str(rec), "--topic", TOPIC, "--gain-topic", "/camera/gain", "--no-noise",
                           "--mtf-model", "fake_mtf", "--diagnostics-out", str(diag)], capsys)
    assert code == 0, err
    assert [d["metadata"] for d in _lines(out)] == [{"gain_db": g} for g in GAINS]
    values = read_diagnostics(diag)[0]["values"]
    assert float(values["gain_db"]) == 0.0 and values["exposure_s"] == values["temperature_c"] == "nan"
