"""FrameSequence over frame folders and (if OpenCV is installed) video files."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from camhealth.data import FrameSequence, build_source, split_ids


def _frames_folder(tmp_path, n=12):
    d = tmp_path / "frames"
    d.mkdir()
    for k in range(n):  # frame k has gray level 10*k; names without zero padding
        Image.fromarray(np.full((6, 8), 10 * k, np.uint8)).save(d / f"frame{k}.png")
    return d


def test_folder_natural_order_stride_and_max_frames(tmp_path):
    d = _frames_folder(tmp_path)
    seq = FrameSequence(d)
    assert len(seq) == 12
    levels = [round(f.mean().item() * 255) for f, _ in seq]
    assert levels == [10 * k for k in range(12)]  # frame2 before frame10
    assert [i for _, i in seq] == list(range(12))
    seq = FrameSequence(d, stride=5, max_frames=2, start=1)
    out = list(seq)
    assert len(seq) == 2 and [i for _, i in out] == [1, 6]
    assert out[1][0].shape == (1, 6, 8) and out[1][0].dtype == torch.float32
    frame, idx = FrameSequence(d, stride=3)[-1]
    assert idx == 9 and round(frame.mean().item() * 255) == 90


def test_folder_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing_frames"):
        FrameSequence(tmp_path / "missing_frames")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="empty"):
        FrameSequence(tmp_path / "empty")
    with pytest.raises(ValueError, match="stride"):
        FrameSequence(tmp_path, stride=0)


def _write_avi(path, n=10, size=(48, 32)):
    cv2 = pytest.importorskip("cv2")
    w, h = size
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (w, h))
    if not writer.isOpened():
        pytest.skip("OpenCV has no MJPG writer")
    for k in range(n):
        frame = np.zeros((h, w, 3), np.uint8)
        frame[..., 1] = 20 * k + 10  # green only: gray = 0.587 * G
        writer.write(frame)
    writer.release()
    return path


def test_video_frames_in_order(tmp_path):
    p = _write_avi(tmp_path / "clip.avi")
    seq = FrameSequence(p)
    assert len(seq) == 10
    frames = list(seq)
    assert [i for _, i in frames] == list(range(10))
    assert frames[0][0].shape == (1, 32, 48) and frames[0][0].dtype == torch.float32
    means = [f.mean().item() * 255 for f, _ in frames]
    assert np.allclose(means, [0.587 * (20 * k + 10) for k in range(10)], atol=3.0)
    strided = FrameSequence(p, stride=3, max_frames=3)
    assert len(strided) == 3 and [i for _, i in strided] == [0, 3, 6]
    f6, i6 = strided[2]  # random access
    assert i6 == 6 and torch.allclose(f6, frames[6][0])
    f3, _ = strided[1]  # backwards seek
    assert torch.allclose(f3, frames[3][0])
    strided.close()


def test_video_as_source_is_one_split_group(tmp_path):
    p = _write_avi(tmp_path / "run1.avi", n=6)
    src = build_source(str(p))
    assert len(src) == 6 and src.ids[0] == "video:run1.avi#000000"
    img, image_id = src[5]
    assert image_id == "video:run1.avi#000005" and img.shape == (1, 32, 48)
    for seed in range(5):
        parts = split_ids(src.ids, 0.3, 0.3, seed=seed)
        assert sorted(len(v) for v in parts.values()) == [0, 0, 6]


def test_video_errors(tmp_path):
    pytest.importorskip("cv2")
    with pytest.raises(FileNotFoundError, match="gone.avi"):
        FrameSequence(tmp_path / "gone.avi")
    bad = tmp_path / "broken.avi"
    bad.write_bytes(b"RIFF" + b"\x00" * 200)
    with pytest.raises(ValueError, match="broken.avi"):
        FrameSequence(bad)
    txt = tmp_path / "notes.txt"
    txt.write_text("x")
    with pytest.raises(ValueError, match="video file"):
        FrameSequence(txt)


def test_video_source_works_in_dataloader_workers_after_parent_access(tmp_path):
    # a capture opened in the parent must not be reused by forked workers (it would hang)
    p = _write_avi(tmp_path / "w.avi", n=4)
    src = build_source(str(p))
    src[1]  # opens a handle in this process
    loader = torch.utils.data.DataLoader(src, batch_size=2, num_workers=1, timeout=30)
    batches = list(loader)
    assert [b[1] for b in batches] == [
        ("video:w.avi#000000", "video:w.avi#000001"),
        ("video:w.avi#000002", "video:w.avi#000003"),
    ]
    assert batches[0][0].shape == (2, 1, 32, 48)


def test_a_folder_of_16_bit_frames_gets_one_scale_the_first_frames(tmp_path):
    """``bit_depth="auto"`` decides the scale once per folder (the first 16-bit frame's): a darker later frame is not
    guessed to fewer bits, which would make it read brighter and noisier than it is."""
    import warnings

    import numpy as np
    from PIL import Image

    from camhealth.data import FrameSequence

    bright = np.full((8, 8), 3000, np.uint16)  # 12 bits
    dark = np.full((8, 8), 800, np.uint16)  # would be guessed as 10 bits on its own
    Image.fromarray(bright).save(tmp_path / "000.png")
    Image.fromarray(dark).save(tmp_path / "001.png")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        frames = [f for f, _ in FrameSequence(tmp_path)]
    assert float(frames[0].max()) == pytest.approx(3000 / 4095)
    assert float(frames[1].max()) == pytest.approx(800 / 4095)
    assert float(next(iter(FrameSequence(tmp_path, bit_depth=16)))[0].max()) == pytest.approx(3000 / 65535)
    # the dark frame first: the bright one needs more bits and gets them (it was refused, and random access read it
    # otherwise than iteration did); both ways of reading agree
    dark_first = tmp_path / "dark_first"
    dark_first.mkdir()
    Image.fromarray(dark).save(dark_first / "000.png")
    Image.fromarray(bright).save(dark_first / "001.png")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        seq = FrameSequence(dark_first)
        iterated = [float(f.max()) for f, _ in seq]
        indexed = [float(seq[k][0].max()) for k in range(2)]
    assert iterated == indexed == pytest.approx([800 / 1023, 3000 / 4095])


def test_truncated_video_has_the_length_of_the_frames_that_decode(tmp_path):
    """A video cut in half: its container still declares 20 frames, 9 decode. The length is 9 (with a warning naming
    the file and both counts), so iteration, len() and the source's last item agree (len() said 20 and the
    source's items 9…19 raised in the middle of an epoch before)."""
    cv2 = pytest.importorskip("cv2")
    full = tmp_path / "full.avi"
    writer = cv2.VideoWriter(str(full), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    if not writer.isOpened():
        pytest.skip("OpenCV has no MJPG writer")
    rng = np.random.default_rng(0)
    for _ in range(20):
        writer.write(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    writer.release()
    assert len(FrameSequence(full)) == 20
    data = full.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.warns(UserWarning, match=r"cut\.avi: its container declares 20 frames, but only frames 0…(\d+) \((\d+)\)"):
        seq = FrameSequence(cut)
    n = len(seq)
    assert 1 <= n < 20
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # iteration yields exactly len() frames, without a further warning
        assert [i for _, i in seq] == list(range(n))
    src = seq.as_source()
    assert len(src) == n and src[n - 1][1] == f"video:cut.avi#{n - 1:06d}"
    seq.close()


def test_a_video_that_ends_before_its_length_warns_naming_the_frame(tmp_path, monkeypatch):
    """Should the decoder stop before the (checked) length, iteration ends with a warning naming the file and frame."""
    p = _write_avi(tmp_path / "clip.avi", n=6)
    seq = FrameSequence(p)
    seq.total_frames = 8  # as if the probe had been fooled: two frames more than decode
    with pytest.warns(UserWarning, match=r"clip\.avi ended at frame 6: 6 of the 8 frames"):
        assert [i for _, i in seq] == list(range(6))
