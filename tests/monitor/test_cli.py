"""``python -m camhealth.monitor``: JSON lines on the embedded street clip, --help, and clear errors (exit 2) or
documented skips — never a crash — for bad sources, videos, metadata and frames."""

import argparse
import json
import re

import numpy as np
import pytest

from camhealth.monitor.__main__ import build_parser
from tests.monitor.conftest import run_monitor_cli as _run


def _lines(text: str) -> list[dict]:
    def bad(x):
        raise ValueError(f"non-strict JSON constant {x}")

    return [json.loads(ln, parse_constant=bad) for ln in text.splitlines() if ln.strip()]


def _png(path, array):
    import cv2

    assert cv2.imwrite(str(path), array)
    return path


def test_help_explains_every_option(capsys):
    parser = build_parser()
    with pytest.raises(SystemExit) as exc:
        parser.parse_args(["--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    hidden = {opt for action in parser._actions if action.help == argparse.SUPPRESS for opt in action.option_strings}
    assert hidden <= {"--print_shtab"}  # jsonargparse's hidden stub that only says it is no longer supported
    for action in parser._actions:
        if action.help == argparse.SUPPRESS:
            continue
        for opt in action.option_strings:
            assert opt in text, opt
        assert action.help, action.dest  # every option has an explanation
    for word in ("SOURCE", "street", "JSON", "gain_db", "ξ", "IOPC", "noisier", "--config", "--print_config"):
        assert word in text


def test_street_clip_writes_valid_json_lines(models, tmp_path, capsys):
    argv = ["street", "--sensor", "ICX285", "--max-frames", "2", "--out", str(tmp_path / "o"), "--overlay", *models]
    code, out, err = _run(argv, capsys)
    assert code == 0, err
    lines = _lines((tmp_path / "o" / "monitor.jsonl").read_text())
    assert [d["index"] for d in lines] == [0, 1]
    for d in lines:
        assert d["assessable"] and d["noise"]["grid"] == [4, 6] and d["mtf"]["grid"] == [3, 4]
        assert d["noise"]["sigma_dn"]["total"]["median"] >= 0 and d["alarm"]["state"] in ("ok", "noisier", "cleaner")
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["frames"] == 2 and summary["unreadable_frames"] == 0 and summary["kind"] == "folder"
    assert len(list((tmp_path / "o" / "overlays").glob("*.png"))) == 2
    assert "2 frame(s)" in out and "median" in out


def test_json_lines_go_to_stdout_without_out(models, capsys):
    argv = ["street", "--sensor", "ICX285", "--max-frames", "1", "--stride", "10", "--start", "5", "--no-mtf", *models]
    code, out, err = _run(argv, capsys)
    assert code == 0, err
    (d,) = _lines(out)
    assert d["index"] == 5 and d["mtf"] is None and "1 frame(s)" in err


def test_folder_with_an_unreadable_frame_skips_it(models, tmp_path, capsys):
    folder = tmp_path / "frames"
    folder.mkdir()
    g = np.random.default_rng(0)
    _png(folder / "f001.png", g.integers(40, 200, (256, 256), dtype=np.uint8))
    (folder / "f002.png").write_bytes(b"not a png at all")
    _png(folder / "f003.png", g.integers(40, 200, (256, 256), dtype=np.uint8))
    code, out, err = _run([str(folder), "--sensor", "ICX285", "--no-mtf", *models], capsys)
    assert code == 0, err
    lines = _lines(out)
    assert len(lines) == 3 and "frame_error" in lines[1] and "f002.png" in lines[1]["source_id"]
    assert lines[0]["noise"]["assessable"] and lines[2]["noise"]["assessable"]
    assert "1 unreadable" in err


def test_black_white_and_tiny_frames(models, tmp_path, capsys):
    folder = tmp_path / "frames"
    folder.mkdir()
    _png(folder / "a_black.png", np.zeros((300, 400), np.uint8))
    _png(folder / "b_white.png", np.full((300, 400), 255, np.uint8))
    _png(folder / "c_tiny.png", np.full((60, 90), 128, np.uint8))
    code, out, err = _run([str(folder), "--sensor", "ICX285", *models], capsys)
    assert code == 0, err
    black, white, tiny = _lines(out)
    for d, reason in ((black, "black"), (white, "saturated")):
        assert d["assessable"] is False and d["noise"]["sigma_dn"] is None and d["mtf"]["h"] is None
        assert d["noise"]["patches"][reason] == d["noise"]["patches"]["total"] == 6
        assert d["alarm"]["state"] == "not_assessable"
    assert tiny["assessable"] is False and "smaller than one 128-px patch" in tiny["noise"]["note"]


def test_video_file(models, tmp_path, capsys):
    import cv2

    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (256, 256))
    if not writer.isOpened():
        pytest.skip("OpenCV cannot write MJPG here")
    g = np.random.default_rng(1)
    base = g.integers(40, 200, (256, 256), dtype=np.uint8)
    for _ in range(3):
        writer.write(np.repeat(base[..., None], 3, axis=2))
    writer.release()
    code, out, err = _run([str(path), "--sensor", "ICX285", "--no-mtf", "--mode", "map", *models], capsys)
    assert code == 0, err
    lines = _lines(out)
    assert [d["index"] for d in lines] == [0, 1, 2] and lines[0]["source_id"].endswith("clip.avi#0")
    assert lines[2]["noise"]["patches"]["reused"] >= 1  # a static video reuses its patches


@pytest.mark.parametrize("setup,match", [
    (lambda p: str(p / "missing.png"), "source not found"),
    (lambda p: (p / "broken.png").write_bytes(b"garbage") and str(p / "broken.png"), "cannot read image"),
    (lambda p: (p / "broken.mp4").write_bytes(b"\x00" * 2048) and str(p / "broken.mp4"), "video"),
    (lambda p: (p / "notes.txt").write_text("hi") and str(p / "notes.txt"), "unsupported extension"),
    (lambda p: (p / "empty").mkdir() or str(p / "empty"), "no frame images"),
])
def test_bad_sources_exit_2_with_a_message(setup, match, models, tmp_path, capsys):
    code, out, err = _run([setup(tmp_path), "--sensor", "ICX285", *models], capsys)
    assert code == 2 and out == ""
    assert "error:" in err and match in err and "Traceback" not in err


@pytest.mark.parametrize("content,match", [
    ("gain_db: 6\nexposure_s: 0.01\n", r"missing field\(s\) \['temperature_c'\]"),
    ("sensor: ICX285\ngain_db: 30\n", r"gain_db\[0\] = 30 dB is out of the allowed range \[0, 24\] dB"),
    ("sensor: ICX285\ntemperature_c: -20\n", r"temperature_c.*\[0, 80\]"),
    ("sensor: ICX285\ngain_db: [1, 2\n", "cannot parse"),
])
def test_bad_metadata_exit_2_naming_the_field(content, match, models, tmp_path, capsys):
    meta = tmp_path / "meta.yaml"
    meta.write_text(content)
    code, _, err = _run(["street", "--metadata", str(meta), "--max-frames", "1", *models], capsys)
    assert code == 2 and "error:" in err
    assert re.search(match, err), err


def test_metadata_overrides_and_option_errors(models, tmp_path, capsys):
    argv = ["street", "--sensor", "EV76C661", "--set", "gain_db=18", "--max-frames", "1", "--no-mtf", *models]
    code, out, err = _run(argv, capsys)
    assert code == 0, err
    assert _lines(out)[0]["metadata"]["gain_db"] == 18.0
    code, _, err = _run(["street", "--max-frames", "1", *models], capsys)
    assert code == 2 and "reads 'minimal' metadata" in err
    code, _, err = _run(["street", "--sensor", "ICX285", "--overlay", *models], capsys)
    assert code == 2 and "--overlay needs --out" in err
    code, _, err = _run(["street", "--sensor", "ICX285", "--iopc", str(tmp_path / "nope.json"), *models], capsys)
    assert code == 2 and "IOPC file not found" in err
    code, _, err = _run(["street", "--sensor", "ICX285", "--max-frames", "1", "--device", "gpu0", *models], capsys)
    assert code == 2 and "device = 'gpu0' is not a device name; allowed: 'cpu', 'cuda' or 'cuda:N'" in err
    with pytest.raises(SystemExit):
        build_parser().parse_args(["street", "--set", "gain=3"])



def test_default_threads_is_two_or_the_cores_available(monkeypatch):
    import os

    from camhealth.monitor.__main__ import build_parser, default_threads

    assert build_parser().parse_args(["street"]).threads is None
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0}, raising=False)
    assert default_threads() == 1
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
    assert default_threads() == 2


def test_defect_map_counts_known_defects_and_refuses_another_size(tmp_path, capsys):
    """--defect-map camera.maps.npz: the frame's defects on the map are counted as known (JSON lines and summary);
    --defects-out writes the run's flagged pixels as a map that --defect-map reads; a map of another size than the
    frames stops with exit 2 naming both sizes."""
    from tests.monitor.test_defect_map import _defect_frame

    frame, hit = _defect_frame()
    png = _png(tmp_path / "frame.png", (frame.numpy() * 255).round().astype(np.uint8))
    maps = tmp_path / "camera.maps.npz"
    np.savez_compressed(maps, hot_pixels=hit.numpy(), dsnu_dn=np.zeros(hit.shape))
    argv = [str(png), "--sensor", "ICX285", "--no-mtf", "--noise-model", "noise_source_full", "--no-progress",
            "--threads", "1", "--defect-map", str(maps), "--out", str(tmp_path / "run")]
    code, out, err = _run(argv, capsys)
    assert code == 0, err
    line = _lines((tmp_path / "run" / "monitor.jsonl").read_text())[0]
    d = line["noise"]["defects"]
    assert d["known"] == d["hot"] + d["dark"] > 0 and "stand out" not in line["alarm"]["message"]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())["defects"]
    assert summary["map_pixels"] == int(hit.sum()) and summary["map_pixels_flagged"] == d["known"]
    # the run's own map: the pixels flagged in at least one frame, written and read back
    out_map = tmp_path / "found.npz"
    code, out, err = _run([str(png), "--sensor", "ICX285", "--no-mtf", "--noise-model", "noise_source_full",
                           "--no-progress", "--threads", "1", "--defects-out", str(out_map), "--defects-min-frames", "1"],
                          capsys)
    assert code == 0, err
    assert f"defect map: {out_map}" in out + err
    from camhealth.monitor.defect_map import load_defect_map

    found = load_defect_map(out_map, shape=tuple(hit.shape))
    assert int(found.sum()) == d["hot"] + d["dark"] and bool(hit[found].all())
    np.savez_compressed(maps, hot_pixels=hit.numpy()[:, :-8])
    code, _, err = _run(argv, capsys)  # the one frame refused: nothing scored, exit 2
    assert code == 2 and "no frame of" in err and f"defect map is 504×384 px (W×H) but frame {png} is 512×384 px" in err, err


def test_a_frame_of_another_size_than_the_defect_map_is_a_frame_error_and_the_run_goes_on(tmp_path, capsys):
    """A folder whose second frame is not the --defect-map's size: that frame gets a ``frame_error`` line naming the file
    and both sizes; the frames before and after it are scored and summary.json is written (the run used to stop there,
    exit 2, with monitor.jsonl half written, no summary and no file named)."""
    g = np.random.default_rng(0)
    folder = tmp_path / "frames"
    folder.mkdir()
    for name, (h, w) in (("a", (256, 320)), ("b", (200, 300)), ("c", (256, 320))):
        _png(folder / f"{name}.png", np.clip(120 + g.normal(0, 3, (h, w)), 0, 255).astype(np.uint8))
    dmap = tmp_path / "map.npy"
    np.save(dmap, np.zeros((256, 320), bool))
    code, out, err = _run([str(folder), "--sensor", "ICX285", "--no-mtf", "--noise-model", "noise_source_full",
                           "--no-progress", "--threads", "1", "--defect-map", str(dmap), "--out", str(tmp_path / "o")],
                          capsys)
    assert code == 0, err
    lines = _lines((tmp_path / "o" / "monitor.jsonl").read_text())
    assert [("frame_error" in d, d["index"]) for d in lines] == [(False, 0), (True, 1), (False, 2)]
    assert lines[1]["frame_error"].startswith(f"the defect map is 320×256 px (W×H) but frame {folder / 'b.png'} is "
                                              "300×200 px")
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["frames"] == 2 and summary["unreadable_frames"] == 1 and "1 unreadable" in out


def test_static_pairs_on_a_folder_of_lossless_frames(tmp_path, capsys):
    """``--static-pairs``: PNG frames of a still scene, each with its own noise; from the second frame on the noise
    patches are read against the previous frame (``coverage.static_pairs``; ``--no-adaptive``: every patch is
    estimated on every frame, where static reuse would keep the first frame's estimates until they are due)."""
    folder = tmp_path / "frames"
    folder.mkdir()
    g = np.random.default_rng(0)
    scene = g.integers(60, 190, (8, 8)).repeat(32, 0).repeat(32, 1).astype(float)
    for i in range(3):
        _png(folder / f"f{i:03d}.png", np.clip(scene + 3.0 * g.standard_normal(scene.shape), 0, 255).round().astype(np.uint8))
    code, out, err = _run([str(folder), "--sensor", "ICX285", "--no-mtf", "--mode", "map", "--no-adaptive", "--static-pairs"], capsys)
    assert code == 0, err
    lines = _lines(out)
    assert [d["noise"]["coverage"]["static_pairs"] for d in lines][0] == 0
    assert all(d["noise"]["coverage"]["static_pairs"] > 0 for d in lines[1:])
    code, out, _ = _run([str(folder), "--sensor", "ICX285", "--no-mtf", "--mode", "map"], capsys)
    assert "static_pairs" not in _lines(out)[1]["noise"]["coverage"]


def test_the_run_summary_counts_the_frames_that_named_a_cause(tmp_path, capsys):
    """Frames of a smooth ramp with 8 DN of white noise, read as an ICX285 whose metadata predict about 1 DN: every
    frame is "noisier" and names readout noise; the printed summary and summary.json count them."""
    folder = tmp_path / "frames"
    folder.mkdir()
    g = np.random.default_rng(1)
    ramp = np.tile(np.linspace(40.0, 200.0, 384), (256, 1))
    for i in range(2):
        _png(folder / f"f{i}.png", np.clip(ramp + 8.0 * g.standard_normal(ramp.shape), 0, 255).round().astype(np.uint8))
    code, out, err = _run([str(folder), "--sensor", "ICX285", "--no-mtf", "--mode", "map", "--out", str(tmp_path / "run")], capsys)
    assert code == 0, err
    lines = _lines((tmp_path / "run" / "monitor.jsonl").read_text())
    assert len(lines) == 2 and all(d["alarm"]["state"] == "noisier" and d["noise"]["cause"]["readout"] > 0.9 for d in lines)
    assert "noise departs from the metadata in 2 frame(s); most probable cause: readout 2" in out
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["causes"] == {"frames": 2, "gain": 0, "dark_current": 0, "readout": 2}


def test_static_pairs_warn_on_lossy_frames(tmp_path, capsys):
    """JPEG frames (or a video) with ``--static-pairs``: the run goes on and says, once, that pairs are for lossless
    frames; PNG frames get no warning."""
    g = np.random.default_rng(1)
    for ext in ("jpg", "png"):
        folder = tmp_path / ext
        folder.mkdir()
        for i in range(2):
            _png(folder / f"f{i}.{ext}", g.integers(60, 190, (256, 256), dtype=np.uint8))
        code, out, err = _run([str(folder), "--sensor", "ICX285", "--no-mtf", "--static-pairs"], capsys)
        assert code == 0, err
        warned = "warning: --static-pairs reads pairs of lossless frames, and 2 of its 2 frame file(s) are .jpg images"
        assert (warned in err) == (ext == "jpg") and err.count("warning: --static-pairs") == (ext == "jpg")


def test_no_frame_scored_at_all_exits_2_after_writing_the_frame_errors(models, tmp_path, capsys):
    """A folder whose every frame is unreadable is an error (as a single unreadable image is), not a run that exits 0;
    the frame errors and summary.json are still written."""
    folder = tmp_path / "frames"
    folder.mkdir()
    for name in ("f001.png", "f002.png"):
        (folder / name).write_bytes(b"not a png at all")
    code, out, err = _run([str(folder), "--sensor", "ICX285", "--no-mtf", "--out", str(tmp_path / "o"), *models], capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert f"no frame of {folder} could be scored: all 2 unreadable or refused (first: " in lines[0] and "f001.png" in lines[0]
    assert len(_lines((tmp_path / "o" / "monitor.jsonl").read_text())) == 2
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["unreadable_frames"] == 2
    code, out, err = _run([str(folder), "--sensor", "ICX285", "--no-mtf", *models], capsys)  # JSON lines on stdout
    assert code == 2 and all("frame_error" in d for d in _lines(out)) and len(err.strip().splitlines()) == 1


def _defect_run(tmp_path, models, *extra):
    g = np.random.default_rng(0)
    png = _png(tmp_path / "frame.png", g.integers(40, 200, (256, 256), dtype=np.uint8))
    return [str(png), "--sensor", "ICX285", "--no-mtf", "--defects-min-frames", "1", *models, *extra]


def test_defects_out_is_checked_before_the_run(models, tmp_path, capsys):
    (tmp_path / "adir").mkdir()
    (tmp_path / "afile").write_text("x")
    for target, message in ((tmp_path / "adir", f"{tmp_path / 'adir'} is a folder"),
                            (tmp_path / "afile" / "map.npz", f"{tmp_path / 'afile'} is a file, not a folder")):
        argv = _defect_run(tmp_path, models, "--defects-out", str(target), "--out", str(tmp_path / "o"))
        code, out, err = _run(argv, capsys)
        assert code == 2 and out == "" and f"--defects-out {target}: " in err and message in err, err
        assert not (tmp_path / "o").exists()  # refused before the run
    assert not (tmp_path / "adir.npz").exists()


def test_defects_out_folder_is_created_and_npz_appended(models, tmp_path, capsys):
    target = tmp_path / "new" / "sub" / "found"
    code, out, err = _run(_defect_run(tmp_path, models, "--defects-out", str(target)), capsys)
    assert code == 0, err
    assert (tmp_path / "new" / "sub" / "found.npz").is_file() and f"defect map: {target}.npz" in err


def test_summary_is_written_when_the_defect_map_cannot_be_written(models, tmp_path, capsys, monkeypatch):
    import camhealth.monitor.defect_map as defect_map

    def disk_full(path, *a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(defect_map, "save_defect_map", disk_full)
    target = tmp_path / "found.npz"
    code, out, err = _run(_defect_run(tmp_path, models, "--defects-out", str(target), "--out", str(tmp_path / "o")), capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert f"--defects-out {target}: the defect map could not be written: " in lines[0] and "No space left" in lines[0]
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["frames"] == 1 and "No space left" in summary["defects_out"]["error"]
    assert len(_lines((tmp_path / "o" / "monitor.jsonl").read_text())) == 1


@pytest.mark.parametrize("value", ["0", "-1", "inf"])
def test_sigma_max_dn_must_be_positive(value, capsys):
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args(["street", "--sigma-max-dn", value])
    assert info.value.code == 2 and f"argument --sigma-max-dn: must be a finite number > 0, got {value}" in capsys.readouterr().err


def test_defects_out_may_not_overwrite_an_input(models, tmp_path, capsys):
    """--defects-out naming the --defect-map it reads (also as the name .npz is appended to), or another input file,
    is refused before the run, naming both; the input is left as it was."""
    argv = _defect_run(tmp_path, models)
    maps = tmp_path / "camera.maps.npz"
    np.savez(maps, hot_pixels=np.zeros((256, 256), bool), master_dark_dn=np.ones((256, 256), np.float32))
    policy = tmp_path / "policy.npz"
    policy.write_bytes(b"an IOPC file")
    for extra, target, given in ((["--defect-map", str(maps)], maps, f"--defect-map {maps}"),
                                 (["--defect-map", str(maps)], tmp_path / "sub" / ".." / "camera.maps", f"--defect-map {maps}"),
                                 (["--iopc", str(policy)], policy, f"--iopc {policy}")):
        code, out, err = _run([*argv, *extra, "--defects-out", str(target), "--out", str(tmp_path / "o")], capsys)
        assert code == 2 and out == "" and "would overwrite the input " + given in err, err
        assert not (tmp_path / "o").exists()  # refused before the run
    assert set(np.load(maps).files) == {"hot_pixels", "master_dark_dn"} and policy.read_bytes() == b"an IOPC file"


def test_a_file_name_that_is_not_utf8_is_written_with_escapes(models, tmp_path, capsys):
    """A frame whose file name is not UTF-8 (bytes Python holds as surrogates) is scored, and its id is written to
    monitor.jsonl and summary.json (UTF-8) with \\xNN escapes; so is an unreadable one's."""
    import os

    folder = tmp_path / "frames"
    folder.mkdir()
    good, bad = os.fsencode(folder) + b"/caf\xe9.png", os.fsencode(folder) + b"/z\xff.png"
    try:
        _png(folder / "tmp.png", np.random.default_rng(0).integers(40, 200, (256, 256), dtype=np.uint8))
        os.rename(folder / "tmp.png", good)
        with open(bad, "wb") as f:
            f.write(b"not a png at all")
    except (OSError, UnicodeError):
        pytest.skip("the file system does not take file names that are not UTF-8")
    code, out, err = _run([str(folder), "--sensor", "ICX285", "--no-mtf", *models, "--out", str(tmp_path / "o")], capsys)
    assert code == 0, err
    scored, unreadable = _lines((tmp_path / "o" / "monitor.jsonl").read_text(encoding="utf-8"))
    assert scored["source_id"].endswith("caf\\xe9.png") and scored["noise"]["assessable"]
    assert unreadable["source_id"].endswith("z\\xff.png") and "frame_error" in unreadable
    summary = json.loads((tmp_path / "o" / "summary.json").read_text(encoding="utf-8"))
    assert summary["unreadable_frames"] == 1 and "z\\xff.png" in summary["unreadable"][0]


def test_overlays_may_not_overwrite_a_source_frame(models, tmp_path, capsys):
    """SOURCE a frame under DIR/overlays/ named as an overlay (or a folder of such frames, or DIR/overlays holding a link
    to the frame) with --out DIR --overlay: refused before the run (exit 2, naming the input); the frame is left as
    it was, and nothing else is written."""
    import os

    overlays = tmp_path / "run" / "overlays"
    overlays.mkdir(parents=True)
    frame = _png(overlays / "frame_000000.png", np.random.default_rng(0).integers(60, 180, (256, 384), dtype=np.uint8))
    original = frame.read_bytes()
    elsewhere = _png(tmp_path / "elsewhere.png", np.random.default_rng(1).integers(60, 180, (256, 384), dtype=np.uint8))
    other = tmp_path / "other"
    (other / "overlays").mkdir(parents=True)
    os.symlink(elsewhere, other / "overlays" / "frame_000000.png")
    for source, out, given in ((frame, tmp_path / "run", f"SOURCE {frame}"), (overlays, tmp_path / "run", f"SOURCE {frame}"),
                               (elsewhere, other, f"SOURCE {elsewhere}")):
        code, stdout, err = _run([str(source), "--sensor", "ICX285", "--no-mtf", "--out", str(out), "--overlay", *models],
                                 capsys)
        assert code == 2 and stdout == "" and f"over the input {given}" in err and "--overlay" in err, err
        assert not (out / "monitor.jsonl").exists() and not (out / "summary.json").exists()
    assert frame.read_bytes() == original and os.path.islink(other / "overlays" / "frame_000000.png")
    code, _, err = _run([str(frame), "--sensor", "ICX285", "--no-mtf", "--out", str(tmp_path / "new"), "--overlay", *models],
                        capsys)
    assert code == 0 and (tmp_path / "new" / "overlays" / "frame_000000.png").is_file(), err


def test_out_may_not_overwrite_the_config_file(models, tmp_path, capsys):
    """--out DIR whose summary.json is the --config file the options came from: refused before the run, naming both
    (it was overwritten by the run's summary)."""
    cfg = tmp_path / "summary.json"
    cfg.write_text('{"sensor": "ICX285", "no_mtf": true}')
    png = _png(tmp_path / "frame.png", np.random.default_rng(0).integers(40, 200, (256, 256), dtype=np.uint8))
    code, out, err = _run([str(png), "--config", str(cfg), "--out", str(tmp_path), *models], capsys)
    assert code == 2 and out == "" and f"--out {tmp_path} would overwrite the input --config {cfg}" in err, err
    assert cfg.read_text() == '{"sensor": "ICX285", "no_mtf": true}' and not (tmp_path / "monitor.jsonl").exists()
    code, _, err = _run([str(png), "--config", str(cfg), "--out", str(tmp_path / "o"), *models], capsys)
    assert code == 0, err  # another folder: the config file is read as before


@pytest.mark.parametrize("content,key,shown", [
    ("xi_sigmas: true", "xi_sigmas", "True"),
    ("xi_threshold_dn: true", "xi_threshold_dn", "True"),
    ("max_clipped: true", "max_clipped", "True"),
    ("min_structure_dn: false", "min_structure_dn", "False"),
    ("gain_limits: [true, 12]", "gain_limits", "True"),
])
def test_true_in_a_config_file_is_no_number(content, key, shown, tmp_path, capsys):
    """A config file's ``xi_sigmas: true`` was read as 1.0 (k from 3σ to 1σ: false alarms) and ``max_clipped: true`` as
    1.0 (clipped patches never skipped): refused, exit 2, naming the key and the value."""
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(f"sensor: ICX285\n{content}\n")
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args(["street", "--config", str(cfg)])
    err = capsys.readouterr().err
    assert info.value.code == 2 and f'"{key}"' in err and f"must be a number, got {shown}" in err, err


@pytest.mark.parametrize("flag,value,allowed", [
    ("--window", "1001", "1…1000"),
    ("--window", "1099511627776", "1…1000"),
    ("--noise-samples", "257", "1…256"),
    ("--mtf-samples", "100000", "1…256"),
    ("--noise-samples", "0", "1…256"),
])
def test_window_and_samples_have_a_documented_maximum(flag, value, allowed, capsys):
    """--window 2**40 crashed with a torch allocation error (the window is allocated at once): now a range error."""
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args(["street", flag, value])
    assert info.value.code == 2 and f"argument {flag}: must be an integer {allowed}, got {value}" in capsys.readouterr().err
    assert build_parser().parse_args(["street", flag, allowed.split("…")[1]]) is not None  # the maximum itself is fine


def test_out_may_not_overwrite_an_input(models, tmp_path, capsys):
    """--out DIR whose summary.json is the --metadata file it reads: refused before the run, naming both."""
    meta = tmp_path / "summary.json"
    meta.write_text('{"sensor": "ICX285"}')
    png = _png(tmp_path / "frame.png", np.random.default_rng(0).integers(40, 200, (256, 256), dtype=np.uint8))
    code, out, err = _run([str(png), "--metadata", str(meta), "--no-mtf", "--out", str(tmp_path), *models], capsys)
    assert code == 2 and out == "" and f"--out {tmp_path} would overwrite the input --metadata {meta}" in err, err
    assert meta.read_text() == '{"sensor": "ICX285"}' and not (tmp_path / "monitor.jsonl").exists()


@pytest.mark.parametrize("flag,values,allowed", [
    ("--exposure-limits", ["0.2", "0.001"], "[0.001, 0.2] s"),   # LO > HI
    ("--exposure-limits", ["0.001", "5"], "[0.001, 0.2] s"),     # beyond the metadata range
    ("--exposure-limits", ["0", "0.1"], "[0.001, 0.2] s"),
    ("--gain-limits", ["30", "-5"], "[0, 24] dB"),
    ("--gain-limits", ["0", "30"], "[0, 24] dB"),
])
def test_exposure_and_gain_limits_are_checked_with_or_without_iopc(flag, values, allowed, models, tmp_path, capsys):
    """--exposure-limits / --gain-limits LO HI: LO <= HI, both within the metadata ranges (the advice's exposure and
    gain are metadata the monitor must accept); otherwise exit 2 before the run, naming the flag, the values and the
    allowed range — also without --iopc."""
    from camhealth.physics.metadata import METADATA_RANGES

    assert METADATA_RANGES["exposure_s"] == (0.001, 0.2) and METADATA_RANGES["gain_db"] == (0.0, 24.0)
    code, out, err = _run(_defect_run(tmp_path, models, flag, *values, "--out", str(tmp_path / "o")), capsys)
    shown = " ".join(f"{float(v):g}" for v in values)
    assert code == 2 and out == "" and f"{flag} {shown}: " in err and allowed in err and "LO <= HI" in err, err
    assert not (tmp_path / "o").exists()


def test_exposure_and_gain_limits_within_the_ranges_are_accepted(models, tmp_path, capsys):
    code, _, err = _run(_defect_run(tmp_path, models, "--exposure-limits", "0.001", "0.2", "--gain-limits", "6", "6"), capsys)
    assert code == 0, err
