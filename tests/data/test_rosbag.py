"""camhealth.data.rosbag: frames and camera state from ROS 1 bags, ROS 2 .db3/.mcap files and rosbag2 folders
(recordings written in the test with rosbags' writers), every supported encoding, and clear errors — never a
crash, never code from the file — for unknown topics, unconvertible encodings, damaged files and bad state."""

from __future__ import annotations

import os

import cv2
import numpy as np
import pytest

from camhealth.data.io import to_gray
from camhealth.data.rosbag import (
    Recording,
    RecordingError,
    RecordingWriter,
    StateTopic,
    format_stamp,
    is_recording,
)

T0 = 1_700_000_000 * 10**9  # a realistic ROS time [ns]
MS = 10**6
FORMATS = [".bag", ".mcap", ".db3", ""]  # "" → rosbag2 folder (MCAP storage)


def _path(tmp_path, suffix, name="rec"):
    return tmp_path / (f"{name}{suffix}" if suffix else f"{name}_folder")


def _frames(path, topic="/cam/image", state=(), **kw):
    with Recording(path) as rec:
        series = [rec.read_state(s) for s in state]
        it = rec.frames(topic, series, **kw)
        return list(it), it


def _ramp(h=24, w=32, dtype=np.uint8, top=255):
    y, x = np.mgrid[0:h, 0:w]
    return ((x * 7 + y * 3) % (top + 1)).astype(dtype)


@pytest.mark.parametrize("suffix", FORMATS)
def test_roundtrip_frames_stamps_and_state(suffix, tmp_path):
    path = _path(tmp_path, suffix)
    imgs = [_ramp() + i for i in range(5)]
    with RecordingWriter(path) as w:
        for i, img in enumerate(imgs):
            t = T0 + i * 100 * MS
            if i == 2:
                w.add_number("/cam/gain", 6.0, t - 5 * MS)  # first gain value arrives before frame 2
            w.add_image("/cam/image", img, t, log_time_ns=t + 3 * MS, frame_id="cam_optical")
    assert is_recording(path)
    spec = StateTopic.parse("gain_db", "/cam/gain", "--gain-topic")
    frames, it = _frames(path, state=[spec])
    assert [f.index for f in frames] == [0, 1, 2, 3, 4] and it.decoded == 5 and it.undecodable == 0
    for i, f in enumerate(frames):
        assert f.stamp_ns == T0 + i * 100 * MS and f.log_time_ns == f.stamp_ns + 3 * MS
        assert f.frame_id == "cam_optical" and f.encoding == "mono8" and f.error is None
        assert tuple(f.frame.shape) == (1, 24, 32)
        np.testing.assert_array_equal(f.frame[0].numpy(), imgs[i].astype(np.float32) / 255)
    assert [f.state.get("gain_db") for f in frames] == [None, None, 6.0, 6.0, 6.0]
    assert it.missing_state == {"gain_db": 2}
    sub, it = _frames(path, start=1, stride=2, max_frames=5)
    assert [f.index for f in sub] == [1, 3] and it.length == 2


def test_state_matched_by_header_stamp_and_log_time(tmp_path):
    """Messages with a header (sensor_msgs/Temperature) match by header stamp, std_msgs numbers by log time;
    each frame takes the latest value at or before it."""
    path = tmp_path / "rec.mcap"
    with RecordingWriter(path) as w:
        w.add_temperature("/cam/temp", 30.0, T0 - 10 * MS, log_time_ns=T0 + 500 * MS)  # logged late, stamped early
        w.add_number("/cam/exposure_us", 5000, T0, msgtype="std_msgs/msg/Int32")
        for i in range(3):
            t = T0 + i * 100 * MS
            w.add_image("/cam/image", _ramp(), t, log_time_ns=t + 1 * MS)
            w.add_number("/cam/exposure_us", 6000 + i, t + 2 * MS, msgtype="std_msgs/msg/Int32")  # after frame i
        w.add_temperature("/cam/temp", 45.0, T0 + 150 * MS)
    specs = [StateTopic.parse("temperature_c", "/cam/temp"), StateTopic.parse("exposure_s", "/cam/exposure_us")]
    frames, _ = _frames(path, state=specs)
    assert [f.state["temperature_c"] for f in frames] == [30.0, 30.0, 45.0]  # by stamp, though logged later
    assert [f.state["exposure_s"] for f in frames] == [5000, 6000, 6001]  # the value logged at or before each frame


def test_field_paths_and_state_errors(tmp_path):
    path = tmp_path / "rec.bag"
    with RecordingWriter(path) as w:
        w.add_temperature("/cam/temp", 41.5, T0)
        w.add_image("/cam/image", _ramp(), T0 + MS)
        w.add_message("/cam/info", w.typestore.types["std_msgs/msg/String"](data="hello"), T0)
    with Recording(path) as rec:
        s = rec.read_state(StateTopic.parse("temperature_c", "/cam/temp:temperature"))
        assert (s.values, s.clock, s.field) == ([41.5], "header", "temperature")
        with pytest.raises(RecordingError, match=r"--temperature-topic /cam/temp:temprature: sensor_msgs/msg/Temperature has no field 'temprature' \(fields: header, temperature, variance\)"):
            rec.read_state(StateTopic.parse("temperature_c", "/cam/temp:temprature", "--temperature-topic"))
        with pytest.raises(RecordingError, match=r"--gain-topic /nope: topic '/nope' is not in recording.*/cam/temp \(sensor_msgs/msg/Temperature"):
            rec.read_state(StateTopic.parse("gain_db", "/nope", "--gain-topic"))
        with pytest.raises(RecordingError, match="carries images"):
            rec.read_state(StateTopic.parse("gain_db", "/cam/image"))
        with pytest.raises(RecordingError, match="holds str, not a number"):
            rec.read_state(StateTopic.parse("gain_db", "/cam/info"))
    with pytest.raises(RecordingError, match="field path"):
        StateTopic.parse("gain_db", "/cam/temp:bad path!")


@pytest.mark.parametrize("suffix", [".bag", ".mcap"])
def test_a_bool_state_topic_or_field_is_refused_naming_topic_field_and_type(suffix, tmp_path):
    """``std_msgs/Bool`` True was read as a gain of 1 dB (and an alarm stated on it): a bool is no camera reading,
    whether the topic's ``data`` or a field reached with ``TOPIC:FIELD``; numeric fields no longer list bools."""
    path = tmp_path / f"rec{suffix}"
    with RecordingWriter(path) as w:
        w.add_message("/gain", w.typestore.types["std_msgs/msg/Bool"](data=True), T0)
        w.add_image("/cam/image", _ramp(), T0 + MS)
    with Recording(path) as rec:
        with pytest.raises(RecordingError, match=r"--gain-topic /gain: field 'data' holds bool, not a number; numeric "
                                                 r"fields of std_msgs/msg/Bool: none"):
            rec.read_state(StateTopic.parse("gain_db", "/gain", "--gain-topic"))
        with pytest.raises(RecordingError, match=r"--gain-topic /gain:data: field 'data' holds bool, not a number"):
            rec.read_state(StateTopic.parse("gain_db", "/gain:data", "--gain-topic"))


@pytest.mark.parametrize("suffix", [".bag", ".mcap"])
def test_unknown_topic_lists_the_image_topics(suffix, tmp_path):
    path = tmp_path / f"rec{suffix}"
    with RecordingWriter(path) as w:
        w.add_image("/front/image_raw", _ramp(), T0)
        w.add_compressed("/rear/image/compressed", cv2.imencode(".png", _ramp())[1], "png", T0)
        w.add_number("/front/gain", 3.0, T0)
    with Recording(path) as rec:
        assert [t.name for t in rec.image_topics()] == ["/front/image_raw", "/rear/image/compressed"]
        with pytest.raises(RecordingError) as exc:
            rec.frames("/front/image")
        msg = str(exc.value)
        assert "'/front/image' is not in recording" in msg and "\n" not in msg
        assert "/front/image_raw (sensor_msgs/msg/Image, 1 message)" in msg and "/rear/image/compressed" in msg
        with pytest.raises(RecordingError, match="carries std_msgs/msg/Float64, not sensor_msgs/Image"):
            rec.frames("/front/gain")


def test_no_image_topic_says_so(tmp_path):
    path = tmp_path / "rec.mcap"
    with RecordingWriter(path) as w:
        w.add_number("/gain", 1.0, T0)
    with Recording(path) as rec, pytest.raises(RecordingError, match=r"no sensor_msgs/Image or CompressedImage topic \(topics: /gain"):
        rec.frames("/camera")


# ------------------------------------------------------------------ encodings
def _one(tmp_path, add, name="enc", **kw):
    path = tmp_path / f"{name}.mcap"
    with RecordingWriter(path) as w:
        add(w)
    frames, it = _frames(path, **kw)
    return frames, it


def test_mono16_bit_depth_endianness_and_padding(tmp_path):
    img16 = (_ramp(top=4095).astype(np.uint16) * 13) % 4096
    frames, it = _one(tmp_path, lambda w: (
        w.add_image("/cam/image", img16, T0),
        w.add_image("/cam/image", img16, T0 + MS, bigendian=True),
        w.add_image("/cam/image", img16, T0 + 2 * MS, step=32 * 2 + 10),
    ))
    for f in frames:  # default: the full 16-bit scale
        np.testing.assert_allclose(f.frame[0].numpy(), img16 / 65535.0, rtol=0, atol=1e-7)
    assert it.notes and "--bit-depth 12" in it.notes[0]  # values ≤ 4095 in a 16-bit stream: a hint, once
    frames, it = _one(tmp_path, lambda w: w.add_image("/cam/image", img16, T0), name="b12", bit_depth=12)
    np.testing.assert_allclose(frames[0].frame[0].numpy(), img16 / 4095.0, rtol=0, atol=1e-7)
    assert not it.notes
    over = img16.copy()
    over[0, 0] = 5000
    frames, it = _one(tmp_path, lambda w: w.add_image("/cam/image", over, T0), name="over", bit_depth=12)
    assert frames[0].frame is None and "16-bit value 5000 exceeds the 12-bit range 0…4095" in frames[0].error
    assert it.undecodable == 1


@pytest.mark.parametrize("encoding,order", [("rgb8", [0, 1, 2]), ("bgr8", [2, 1, 0]), ("rgba8", [0, 1, 2, 3]),
                                            ("bgra8", [2, 1, 0, 3]), ("rgb16", [0, 1, 2])])
def test_colour_is_bt601_luma(encoding, order, tmp_path):
    g = np.random.default_rng(1)
    dtype, top = (np.uint16, 65535) if encoding.endswith("16") else (np.uint8, 255)
    rgb = g.integers(0, top + 1, (20, 30, len(order)), dtype=dtype)
    stored = rgb[..., order]  # channels in the encoding's order
    frames, _ = _one(tmp_path, lambda w: w.add_image("/cam/image", stored, T0, encoding=encoding))
    np.testing.assert_allclose(frames[0].frame[0].numpy(), to_gray(rgb.astype(np.float64) / top), atol=1e-6)


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_bayer_green_takes_the_raw_green_samples(pattern, tmp_path):
    h, w = 8, 12
    value = {"r": 20, "g": 100, "b": 200}
    cell = np.array([[value[pattern[0]], value[pattern[1]]], [value[pattern[2]], value[pattern[3]]]], np.uint8)
    mosaic = np.tile(cell, (h // 2, w // 2))
    gcol = pattern.index("g") if pattern.index("g") < 2 else None
    mosaic[0::2, gcol::2] += np.arange(h // 2 * w // 2, dtype=np.uint8).reshape(h // 2, w // 2)  # mark the samples
    frames, _ = _one(tmp_path, lambda wr: wr.add_image("/cam/image", mosaic, T0, encoding=f"bayer_{pattern}8"))
    out = frames[0].frame[0].numpy()
    assert out.shape == (h // 2, w // 2)
    np.testing.assert_array_equal(out, mosaic[0::2, gcol::2] / np.float32(255))
    frames, _ = _one(tmp_path, lambda wr: wr.add_image("/cam/image", np.tile(cell, (h // 2, w // 2)), T0,
                                                      encoding=f"bayer_{pattern}8"), name="luma", bayer="luma")
    luma = frames[0].frame[0].numpy()  # demosaiced, full resolution: the luma of (R, G, B) = (20, 100, 200) inside
    assert luma.shape == (h, w)
    expect = (0.299 * 20 + 0.587 * 100 + 0.114 * 200) / 255
    assert abs(float(luma[3, 5]) - expect) < 1.5 / 255


def test_compressed_png_jpeg_bayer_and_corrupt(tmp_path):
    gray = _ramp()
    bgr = np.stack([gray, 255 - gray, gray // 2], -1).astype(np.uint8)
    bayer = np.tile(np.array([[20, 100], [100, 200]], np.uint8), (6, 8))
    frames, it = _one(tmp_path, lambda w: (
        w.add_compressed("/cam/image", cv2.imencode(".png", gray)[1], "png", T0),
        w.add_compressed("/cam/image", cv2.imencode(".png", bgr)[1], "bgr8; png compressed bgr8", T0 + 1),
        w.add_compressed("/cam/image", cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, 98])[1], "jpeg", T0 + 2),
        w.add_compressed("/cam/image", cv2.imencode(".png", bayer)[1], "bayer_rggb8; png compressed", T0 + 3),
        w.add_compressed("/cam/image", b"\xff\xd8 not a jpeg", "jpeg", T0 + 4),
        w.add_compressed("/cam/image", cv2.imencode(".png", gray.astype(np.uint16) * 16)[1], "16UC1; compressedDepth", T0 + 5),
    ))
    np.testing.assert_array_equal(frames[0].frame[0].numpy(), gray / np.float32(255))
    np.testing.assert_allclose(frames[1].frame[0].numpy(), to_gray(bgr[..., ::-1] / 255.0), atol=1e-6)
    assert float(np.abs(frames[2].frame[0].numpy() - gray / 255.0).mean()) < 2 / 255
    np.testing.assert_array_equal(frames[3].frame[0].numpy(), np.full((6, 8), 100 / np.float32(255)))
    assert frames[4].frame is None and "cannot decode CompressedImage (format 'jpeg'" in frames[4].error
    assert frames[5].frame is None and "compressed depth image" in frames[5].error
    assert (it.decoded, it.undecodable) == (4, 2)


def test_compressed_image_over_the_pixel_limit_or_that_opencv_cannot_decode_is_a_frame_error(tmp_path, monkeypatch):
    """A CompressedImage whose header declares more than PIL.Image.MAX_IMAGE_PIXELS pixels is refused before it is
    decoded, and an OpenCV error or a MemoryError while decoding is a frame error too; the next frame is read."""
    from PIL import Image

    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 24 * 32)
    big = np.zeros((25, 32), np.uint8)
    frames, it = _one(tmp_path, lambda w: (
        w.add_compressed("/cam/image", cv2.imencode(".png", big)[1], "png", T0),
        w.add_compressed("/cam/image", cv2.imencode(".png", np.dstack([big] * 3).astype(np.uint16))[1], "png", T0 + 1),
        w.add_compressed("/cam/image", cv2.imencode(".jpg", big)[1], "jpeg", T0 + 2),
        w.add_compressed("/cam/image", cv2.imencode(".png", _ramp())[1], "png", T0 + 3),
    ))
    for f, fmt in zip(frames[:3], ("png", "png", "jpeg")):
        assert f.frame is None and f"CompressedImage (format {fmt!r}) is 32×25 = 800 pixels, more than the limit of " \
                                  "768 pixels" in f.error, f.error
    assert frames[3].error is None and frames[3].frame.shape == (1, 24, 32) and (it.decoded, it.undecodable) == (1, 3)

    def failing(exc):
        def imdecode(*args):
            raise exc
        return imdecode

    png = cv2.imencode(".png", _ramp())[1]
    for exc, text in ((cv2.error("OpenCV(4) error: (-215:Assertion failed) in imdecode"), "Assertion failed"),
                      (MemoryError("out of memory"), "out of memory")):
        monkeypatch.setattr(cv2, "imdecode", failing(exc))
        frames, it = _one(tmp_path, lambda w: w.add_compressed("/cam/image", png, "png", T0), name=type(exc).__name__)
        assert frames[0].frame is None and "cannot decode CompressedImage (format 'png'" in frames[0].error
        assert text in frames[0].error and it.undecodable == 1


def test_unconvertible_encoding_is_refused_naming_it(tmp_path):
    path = tmp_path / "float.bag"
    with RecordingWriter(path) as w:
        w.add_image("/cam/image", np.zeros((4, 4, 4), np.uint8), T0, encoding="32FC1")
    with Recording(path) as rec, pytest.raises(RecordingError) as exc:
        rec.frames("/cam/image")
    assert "image encoding '32FC1' cannot be converted to gray; supported: mono8, mono16" in str(exc.value)
    # a later message in another encoding, or with too little data, is one undecodable frame
    frames, it = _one(tmp_path, lambda w: (
        w.add_image("/cam/image", _ramp(), T0),
        w.add_image("/cam/image", np.zeros((4, 8), np.uint8), T0 + 1, encoding="yuv422"),
        w.add_raw("/cam/image", "sensor_msgs/msg/Image", b"\x00\x01", T0 + 2),
        w.add_image("/cam/image", _ramp(), T0 + 3),
    ), name="mixed")
    assert [f.frame is None for f in frames] == [False, True, True, False] and it.undecodable == 2
    assert "'yuv422' cannot be converted" in frames[1].error and "cannot decode sensor_msgs/msg/Image" in frames[2].error


def test_short_image_data_is_a_frame_error(tmp_path):
    def add(w):
        msg = w.typestore.types["sensor_msgs/msg/Image"](
            header=w._header(T0, "cam"), height=10, width=10, encoding="mono8", is_bigendian=0, step=10,
            data=np.zeros(50, np.uint8))
        w.add_message("/cam/image", msg, T0)

    frames, _ = _one(tmp_path, add)
    assert "holds 50 bytes but 10×10 px mono8 with step 10 needs 100 (truncated message)" in frames[0].error


def test_out_of_order_stamps_are_counted(tmp_path):
    stamps = [0, 100, 50, 200, 150]
    frames, it = _one(tmp_path, lambda w: [w.add_image("/cam/image", _ramp(), T0 + s * MS, log_time_ns=T0 + i * 100 * MS)
                                           for i, s in enumerate(stamps)])
    assert [f.out_of_order for f in frames] == [False, False, True, False, True]
    assert it.out_of_order == 2 and f"header stamp {format_stamp(T0 + 50 * MS)} s is earlier" in it.first_out_of_order


@pytest.mark.parametrize("suffix", [".bag", ".mcap", ".db3"])
def test_truncated_recording_is_a_clear_error(suffix, tmp_path):
    path = tmp_path / f"rec{suffix}"
    with RecordingWriter(path) as w:
        for i in range(6):
            w.add_image("/cam/image", _ramp(64, 64) + i, T0 + i * MS)
    cut = tmp_path / f"cut{suffix}"
    data = path.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    try:
        with Recording(cut) as rec:  # a reader may still open what is left: then it reads what is there
            frames = list(rec.frames("/cam/image"))
            assert all(f.error is None for f in frames)
    except RecordingError as exc:
        msg = str(exc)
        assert msg.startswith(f"cannot read recording {cut}") and "truncated" in msg and "\n" not in msg
        assert "',)" not in msg
    empty = tmp_path / f"empty{suffix}"
    empty.write_bytes(b"")
    with pytest.raises(RecordingError, match="cannot read recording"):
        Recording(empty)


def test_recording_errors_for_paths(tmp_path):
    with pytest.raises(FileNotFoundError, match="recording not found"):
        Recording(tmp_path / "missing.bag")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(RecordingError, match="is not a recording"):
        Recording(tmp_path / "notes.txt")


def test_no_code_from_the_recording_runs(tmp_path, monkeypatch):
    """A recording's own message definitions are never compiled into code: a non-standard type (here with a type
    name and definition that carry Python) is listed but not decoded, and nothing from the file runs."""
    monkeypatch.delenv("CAMHEALTH_PWNED", raising=False)
    path = tmp_path / "evil.bag"
    payload = "__import__('os').environ.__setitem__('CAMHEALTH_PWNED', '1')"
    with RecordingWriter(path) as w:
        w.add_image("/cam/image", _ramp(), T0)
        conn = w._writer.add_connection("/evil", f"evil_pkg/msg/X:\n{payload}\n#", msgdef=f"int32 a\n{payload}\n",
                                        md5sum="0" * 32)
        w._writer.write(conn, T0, b"\x01\x00\x00\x00")
    with Recording(path) as rec:
        assert "/evil" in rec.topics
        frames = list(rec.frames("/cam/image"))
        assert len(frames) == 1 and frames[0].error is None
        with pytest.raises(RecordingError, match="camhealth does not decode"):
            rec.read_state(StateTopic.parse("gain_db", "/evil"))
    assert "CAMHEALTH_PWNED" not in os.environ


def test_zero_header_stamp_falls_back_to_the_log_time(tmp_path):
    frames, it = _one(tmp_path, lambda w: (w.add_image("/cam/image", _ramp(), 0, log_time_ns=T0),
                                           w.add_image("/cam/image", _ramp(), T0 + MS)))
    assert [f.stamp_ns for f in frames] == [None, T0 + MS] and it.unstamped == 1
    assert "zero (unset) header stamp" in it.notes[0]


@pytest.mark.parametrize("suffix", [".mcap", ".bag"])
def test_state_topic_with_zero_header_stamps_is_matched_by_log_time(suffix, tmp_path):
    """A driver that never sets the Temperature header stamp: each frame gets the latest value logged at or before it,
    with a note (every value was placed at time 0 before, so every frame got the recording's last value)."""
    path = tmp_path / f"zero{suffix}"
    with RecordingWriter(path) as w:
        for i in range(5):
            w.add_temperature("/cam/temp", 20.0 + 10 * i, stamp_ns=0, log_time_ns=T0 + i * 100 * MS - 1)
            w.add_image("/cam/image", _ramp(), T0 + i * 100 * MS)
    frames, it = _frames(path, state=[StateTopic.parse("temperature_c", "/cam/temp")])
    assert [f.state["temperature_c"] for f in frames] == [20.0, 30.0, 40.0, 50.0, 60.0]
    assert it.state[0].clock == "log" and it.state[0].unstamped == 5
    assert any("/cam/temp: every header stamp is zero (unset)" in n and "log time" in n for n in it.notes)


def test_state_messages_with_some_zero_stamps_use_their_log_time(tmp_path):
    """Stamped state messages keep the header clock; an unset one in between is placed at its log time (noted)."""
    path = tmp_path / "mixed.mcap"
    with RecordingWriter(path) as w:
        w.add_temperature("/cam/temp", 20.0, stamp_ns=T0 - MS, log_time_ns=T0 - MS)
        w.add_temperature("/cam/temp", 30.0, stamp_ns=0, log_time_ns=T0 + 50 * MS)  # unset: at its log time
        for i in range(3):
            w.add_image("/cam/image", _ramp(), T0 + i * 100 * MS)
        w.add_temperature("/cam/temp", 40.0, stamp_ns=T0 + 150 * MS, log_time_ns=T0 + 250 * MS)
    frames, it = _frames(path, state=[StateTopic.parse("temperature_c", "/cam/temp")])
    assert [f.state["temperature_c"] for f in frames] == [20.0, 30.0, 40.0]  # (30 was last of all at time 0 before)
    assert it.state[0].clock == "header" and it.state[0].unstamped == 1
    assert any("1 of 3 messages have a zero (unset) header stamp" in n for n in it.notes)


def test_16_bit_png_compressed_stream_gets_the_bit_depth_hint(tmp_path):
    """12-bit data in a 16-bit PNG CompressedImage ("mono16; png compressed") gets the same --bit-depth note as raw
    mono16 (the hint was chosen from the format string, which does not end in 16)."""
    img16 = (_ramp(top=4095).astype(np.uint16) * 13) % 4096
    for fmt in ("mono16; png compressed", "png"):
        frames, it = _one(tmp_path, lambda w, fmt=fmt: w.add_compressed("/cam/image", cv2.imencode(".png", img16)[1], fmt, T0),
                          name=f"c16_{fmt[:4]}")
        np.testing.assert_allclose(frames[0].frame[0].numpy(), img16 / 65535.0, rtol=0, atol=1e-7)
        assert len(it.notes) == 1 and "--bit-depth 12" in it.notes[0] and fmt in it.notes[0]
    eight = _ramp()
    _, it = _one(tmp_path, lambda w: w.add_compressed("/cam/image", cv2.imencode(".png", eight)[1], "mono8; png compressed", T0),
                 name="c8")
    assert not it.notes  # 8-bit data: no hint
