"""FrameSequence on a video with a frame that does not decode: ``seq[k]`` gives frame k or an error naming it, and
iteration goes on past the damaged frame."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from camhealth.data import FrameSequence

cv2 = pytest.importorskip("cv2")


def _id_video(path, n: int, damage_at: float):
    """An MJPG AVI of ``n`` noise frames, each with its number in two flat patches, and a copy with 3 kB of bytes
    garbled at ``damage_at`` of the file (one frame or two stop decoding there)."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (160, 120), True)
    if not writer.isOpened():
        pytest.skip("OpenCV has no MJPG writer")
    rng = np.random.default_rng(0)
    for i in range(n):
        f = rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)
        f[:40, :40] = (i % 20) * 12
        f[:40, 40:80] = (i // 20) * 40
        writer.write(f)
    writer.release()
    data = bytearray(path.read_bytes())
    at = int(len(data) * damage_at)
    for k in range(at, at + 3000):
        data[k] = (data[k] * 7 + 13) & 0xFF
    damaged = path.with_name("damaged_" + path.name)
    damaged.write_bytes(bytes(data))
    return damaged


def _frame_number(frame) -> int:
    """The number written into a frame's patches (gray [0, 1] tensor 1×H×W)."""
    g = frame[0].double().numpy() * 255.0
    return int(round(g[5:35, 5:35].mean() / 12.0)) + 20 * int(round(g[5:35, 45:75].mean() / 40.0))


def _first_failed_read(path) -> int:
    """The first frame OpenCV's reads return nothing for, read one by one from the start."""
    cap = cv2.VideoCapture(str(path), cv2.CAP_ANY, [cv2.CAP_PROP_N_THREADS, 1])
    try:
        for k in range(10_000):
            if not cap.read()[0]:
                return k
    finally:
        cap.release()
    raise AssertionError("every frame decodes")


_MIXED = [12, 9, 3, 18, 15, 11, 80, 30, 10, 99, 5, 65, 13, 70, 8]  # skips ahead and back, seeks (back, > 64 ahead)


@pytest.mark.parametrize("n, damage_at, order", [
    (20, 0.45, "forward"),  # two frames' data decode as one (partly decoded): the file lost a frame
    (20, 0.45, "mixed"),
    (20, 0.6, "forward"),  # a frame does not decode, and takes the next one's data with it
    (20, 0.6, "mixed"),
    (100, 0.09, "mixed"),  # a frame does not decode; a seek behind it lands on an earlier frame
])
def test_random_access_gives_frame_k_or_an_error_naming_it(tmp_path, n, damage_at, order):
    """Damage that takes a frame away used to shift every frame after it by one (``seq[9]`` gave frame 10), silently;
    a seek could land on another frame too. Now ``seq[k]`` is frame k, or a ValueError naming the file and frame k."""
    p = _id_video(tmp_path / "ids.avi", n, damage_at)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (a container that declares more frames than decode says so)
        seq = FrameSequence(p)
    results = {}
    for k in (k for k in (range(n) if order == "forward" else _MIXED) if k < len(seq)):
        try:
            frame, idx = seq[k]
        except ValueError as e:
            assert f"frame {k} of video {p}" in str(e), str(e)
            results[k] = "refused"
        else:
            assert idx == k
            results[k] = _frame_number(frame)
    seq.close()
    wrong = {k: v for k, v in results.items() if v not in (k, "refused")}
    assert not wrong, f"seq[k] gave another frame: {wrong}"
    assert "refused" in results.values() and any(v == k for k, v in results.items()), results


@pytest.mark.parametrize("n, damage_at", [(20, 0.6), (40, 0.3), (100, 0.09)])
@pytest.mark.parametrize("stride", [1, 2, 3])
def test_iteration_goes_on_past_a_frame_that_does_not_decode(tmp_path, n, damage_at, stride):
    """Iteration ended at the first frame that did not decode ("ended at frame 8"), although the decoder gives frames
    again from the next read on. Now the frame is skipped (with a warning naming it where it is a kept frame), and the
    later frames follow to the end of the clip."""
    p = _id_video(tmp_path / "ids.avi", n, damage_at)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        seq = FrameSequence(p, stride=stride)
    first_bad = _first_failed_read(p)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = [(idx, _frame_number(frame)) for frame, idx in seq]
    messages = [str(w.message) for w in caught]
    assert not any(f"ended at frame {first_bad}:" in m for m in messages), messages
    named = [m for m in messages if f"frame {first_bad} of video {p} does not decode" in m]
    assert len(named) == (1 if first_bad % stride == 0 else 0), messages
    indices = [idx for idx, _ in got]
    assert indices == sorted(indices) and all(i % stride == 0 for i in indices) and first_bad not in indices
    assert sum(i > first_bad for i in indices) >= 2 and indices[-1] >= seq.frame_index(len(seq) - 1) - stride  # to the end
    assert all(idx == number for idx, number in got if idx < first_bad)  # (the frames before it are the written ones)
