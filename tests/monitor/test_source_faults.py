"""Monitor sources and faults: a partly decoded video frame is reported, never scored; --start past the end is an
error; 12-bit frames in 16-bit files are measured at their level and the scaling is named."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from camhealth.monitor.sources import open_source
from tests.monitor.conftest import FakeNoise
from tests.monitor.conftest import run_monitor_cli as _run

cv2 = pytest.importorskip("cv2")


def _avi(path, n=6, size=(160, 144)):
    """An MJPG clip of ``n`` textured frames; its last frame is cut short when the file is truncated."""
    g = np.random.default_rng(0)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, size)
    for k in range(n):
        frame = np.full((size[1], size[0], 3), 60 + 20 * k, np.uint8)
        frame[:, ::8] = 200
        writer.write((frame + g.integers(0, 30, frame.shape)).astype(np.uint8))
    writer.release()
    return path


def _truncated(src, dst, keep=0.97):
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * keep)])
    return dst


def test_a_partly_decoded_video_frame_is_reported_not_scored(tmp_path, models, capsys):
    clip = _truncated(_avi(tmp_path / "full.avi"), tmp_path / "cut.avi")
    items = list(open_source(clip))
    assert [i.index for i in items] == list(range(6))
    assert all(i.error is None and i.frame is not None for i in items[:5])
    assert items[5].frame is None and "frame 5" in items[5].error and "only partly decoded" in items[5].error
    whole = list(open_source(tmp_path / "full.avi"))
    assert all(i.error is None for i in whole)  # the intact clip: every frame decodes
    code, out, err = _run([str(clip), "--sensor", "ICX285", "--no-mtf", *models], capsys)
    assert code == 0, err
    lines = [json.loads(ln) for ln in out.splitlines() if ln.strip()]
    assert len(lines) == 6 and "frame_error" in lines[5] and "noise" not in lines[5]
    assert all("noise" in d for d in lines[:5])
    assert "1 unreadable" in err


def test_frame_sequence_iteration_skips_a_damaged_frame_with_a_warning(tmp_path):
    from camhealth.data import FrameSequence

    clip = _truncated(_avi(tmp_path / "full.avi"), tmp_path / "cut.avi")
    seq = FrameSequence(clip)
    with pytest.warns(UserWarning, match="frame 5 of video .* only partly decoded"):
        assert [i for _, i in seq] == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match="only partly decoded"):
        seq[5]
    seq.close()


@pytest.mark.parametrize("kind", ["image", "folder", "video"])
def test_start_past_the_end_is_an_error(tmp_path, kind, models, capsys):
    if kind == "image":
        source, n = tmp_path / "f.png", 1
        Image.fromarray(np.full((64, 64), 100, np.uint8)).save(source)
    elif kind == "folder":
        source, n = tmp_path / "frames", 3
        source.mkdir()
        for k in range(n):
            Image.fromarray(np.full((64, 64), 100, np.uint8)).save(source / f"f{k}.png")
    else:
        source, n = _avi(tmp_path / "clip.avi", n=4), 4
    with pytest.raises(ValueError, match=f"start = {n} is past the end of .*: it has {n} frame"):
        open_source(source, start=n)
    assert len(list(open_source(source, start=n - 1))) == 1
    code, out, err = _run([str(source), "--sensor", "ICX285", "--start", str(n + 5), *models], capsys)
    assert code == 2 and "past the end" in err and len(err.strip().splitlines()) == 1


def _twelve_bit_frame(path, sigma_12bit=80.0, sbit=False):
    g = np.random.default_rng(1)
    values = np.clip(np.round(2000 + g.normal(0, sigma_12bit, (256, 256))), 0, 4095).astype(np.uint16)
    Image.fromarray(values).save(path)
    if sbit:
        import struct
        import zlib

        data = path.read_bytes()
        at = 8 + 8 + 13 + 4
        chunk = b"sBIT" + bytes([12])
        path.write_bytes(data[:at] + struct.pack(">I", 1) + chunk + struct.pack(">I", zlib.crc32(chunk)) + data[at:])
    return path


@pytest.mark.parametrize("bit_depth", ["auto", 12])
def test_twelve_bit_frames_are_measured_at_their_level(tmp_path, bit_depth):
    """80 DN of 12-bit noise is ≈ 5 DN of 255: the monitor's noise estimate must see ≈ 5 DN, not 0.3 DN."""
    frame_path = _twelve_bit_frame(tmp_path / "d12.png")
    (item,) = list(open_source(frame_path, bit_depth=bit_depth))
    assert "12-bit data (÷4095" in item.scaling
    noise = FakeNoise()
    patch = item.frame[:, :128, :128].unsqueeze(0)
    sigma = float(noise.predict(patch, "ICX285")["sigma_total"][0])
    assert sigma == pytest.approx(80 / 4095 * 255, rel=0.1)
    (as16,) = list(open_source(frame_path, bit_depth=16))
    assert float(noise.predict(as16.frame[:, :128, :128].unsqueeze(0), "ICX285")["sigma_total"][0]) < 0.5


@pytest.mark.parametrize("argv,scaling", [
    ([], "16-bit file read as 12-bit data (÷4095, from the PNG's sBIT chunk)"),
    (["--bit-depth", "12"], "16-bit file read as 12-bit data (÷4095, as given)"),
    (["--bit-depth", "16"], "16-bit file read as 16-bit data (÷65535, as given)"),
])
def test_the_monitor_names_the_scaling_it_used(tmp_path, models, capsys, argv, scaling):
    frame_path = _twelve_bit_frame(tmp_path / "d12.png", sbit=True)
    out_dir = tmp_path / "out"
    code, out, err = _run([str(frame_path), "--sensor", "ICX285", "--no-mtf", "--out", str(out_dir), *argv, *models], capsys)
    assert code == 0, err
    assert f"input: {scaling} (1 frame(s))" in out
    assert json.loads((out_dir / "summary.json").read_text())["input_scaling"] == {scaling: 1}


def test_bit_depth_option_is_checked(capsys):
    with pytest.raises(SystemExit):
        from camhealth.monitor.__main__ import build_parser

        build_parser().parse_args(["x.png", "--bit-depth", "20"])
    assert "must be 'auto' or an integer 8…16, got 20" in capsys.readouterr().err


def test_a_folder_of_16_bit_frames_is_read_with_one_scale(tmp_path):
    """The monitor's folder source decides ``bit_depth="auto"`` once, from the first 16-bit frame; a darker later frame
    keeps that scale (guessed on its own it would read 4× brighter, with 4× its noise)."""
    import numpy as np
    from PIL import Image

    from camhealth.monitor.sources import open_source

    Image.fromarray(np.full((8, 8), 3000, np.uint16)).save(tmp_path / "000.png")
    Image.fromarray(np.full((8, 8), 800, np.uint16)).save(tmp_path / "001.png")
    items = list(open_source(tmp_path))
    assert [round(float(i.frame.max()) * 4095) for i in items] == [3000, 800]
    assert all("12-bit" in i.scaling for i in items)
    # the dark frame first: the later bright frame is read at the 12 bits it needs, not refused as beyond 10 bits
    (tmp_path / "b").mkdir()
    Image.fromarray(np.full((8, 8), 800, np.uint16)).save(tmp_path / "b" / "000.png")
    Image.fromarray(np.full((8, 8), 3000, np.uint16)).save(tmp_path / "b" / "001.png")
    items = list(open_source(tmp_path / "b"))
    assert [i.error for i in items] == [None, None]
    assert [round(float(items[0].frame.max()) * 1023), round(float(items[1].frame.max()) * 4095)] == [800, 3000]


def test_a_change_of_the_guessed_scale_restarts_the_aggregation_with_a_warning(tmp_path, capsys):
    """A 12-bit camera's 16-bit PNGs without sBIT: dark frames are guessed 10-bit (÷1023), bright ones 12-bit (÷4095).
    The two scales used to share one temporal window with no word said; now the change restarts it, a warning names
    both scalings and --bit-depth, and every JSON line names its frame's scaling. With --bit-depth 12: one scale."""
    g = np.random.default_rng(0)
    folder = tmp_path / "f16"
    folder.mkdir()
    for k, mean in enumerate([600, 600, 2500, 2500]):
        values = np.clip(np.round(mean + g.normal(0, 48, (256, 256))), 0, 4095).astype(np.uint16)
        Image.fromarray(values).save(folder / f"f{k}.png")
    argv = [str(folder), "--sensor", "ICX285", "--no-mtf", "--noise-model", "noise_source_full", "--no-progress",
            "--threads", "1"]
    code, out, err = _run(argv, capsys)
    assert code == 0, err
    lines = [json.loads(ln) for ln in out.splitlines() if ln.strip()]
    assert [d["input_scaling"].split(" (")[0] for d in lines] == ["16-bit file read as 10-bit data"] * 2 + \
        ["16-bit file read as 12-bit data"] * 2
    assert [d["noise"]["coverage"]["frames"] for d in lines] == [1, 2, 1, 2]
    warning = [ln for ln in err.splitlines() if ln.startswith("warning: input scaling changed")]
    assert len(warning) == 1 and f"at {folder / 'f2.png'} from '16-bit file read as 10-bit data (÷1023" in warning[0]
    assert "to '16-bit file read as 12-bit data (÷4095" in warning[0] and "pass --bit-depth N" in warning[0]
    code, out, err = _run([*argv, "--bit-depth", "12"], capsys)
    assert code == 0 and "warning" not in err, err
    lines = [json.loads(ln) for ln in out.splitlines() if ln.strip()]
    assert {d["input_scaling"] for d in lines} == {"16-bit file read as 12-bit data (÷4095, as given)"}
    assert [d["noise"]["coverage"]["frames"] for d in lines] == [1, 2, 3, 4]


def test_a_mismatch_on_a_guessed_scale_names_the_bit_depth(tmp_path, capsys):
    """A 12-bit EV76C661 whose 16-bit PNGs (no sBIT) stay below 1023 is guessed 10-bit: read 4× too bright, noise too,
    so its matched metadata read as "noisier" (the cause named: the gain). The alarm now says the scale was guessed and
    names --bit-depth; with --bit-depth 12 the same frames read "ok"."""
    import torch

    from camhealth.augment import RandomSensorNoise

    folder = tmp_path / "dark12"
    folder.mkdir()
    ramp = torch.linspace(0.02, 0.19, 256).expand(256, 256)
    scene = (ramp + 0.03 * (torch.arange(256)[:, None] // 32 % 2)).reshape(1, 1, 256, 256)
    torch.manual_seed(0)
    frames = RandomSensorNoise(metadata="EV76C661")(scene.repeat(2, 1, 1, 1))
    for k, y in enumerate(frames):
        Image.fromarray(np.round(y[0].numpy() * 4095).astype(np.uint16)).save(folder / f"f{k}.png")
    argv = [str(folder), "--sensor", "EV76C661", "--no-mtf", "--no-progress", "--threads", "1"]
    code, out, err = _run(argv, capsys)
    assert code == 0, err
    lines = [json.loads(ln) for ln in out.splitlines() if ln.strip()]
    assert all(d["input_scaling"].startswith("16-bit file read as 10-bit data (÷1023, guessed") for d in lines)
    assert [d["alarm"]["state"] for d in lines] == ["noisier", "noisier"], [d["alarm"] for d in lines]
    assert all("scale was guessed" in d["alarm"]["message"] and "--bit-depth N" in d["alarm"]["message"]
               for d in lines)
    code, out, err = _run([*argv, "--bit-depth", "12"], capsys)
    assert code == 0, err
    lines = [json.loads(ln) for ln in out.splitlines() if ln.strip()]
    assert [d["alarm"]["state"] for d in lines] == ["ok", "ok"], [d["alarm"] for d in lines]
    assert not any("guessed" in d["alarm"]["message"] for d in lines)
