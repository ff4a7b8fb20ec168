"""camhealth.data.rosbag: a sensor_msgs/Image whose data is longer than step × height (ROS: len(data) = step ·
height) is a per-frame error naming both sizes, not a silently cropped frame."""

from __future__ import annotations

import numpy as np
import pytest

from camhealth.data.rosbag import Recording, RecordingWriter

T0 = 1_700_000_000 * 10**9
TOPIC = "/cam/image"
ROWS = (np.arange(64 * 96) % 251).astype(np.uint8).reshape(64, 96)


def _image(w, height, width, step, data, t, encoding="mono8"):
    return w.typestore.types["sensor_msgs/msg/Image"](
        header=w._header(t, "cam"), height=height, width=width, encoding=encoding, is_bigendian=0, step=step,
        data=np.frombuffer(bytes(data), np.uint8).copy())


@pytest.mark.parametrize("suffix", [".mcap", ".bag"])
@pytest.mark.parametrize("height, width, step, enc, data, message", [
    # height says 32 rows, the data hold 64: half the image was dropped
    (32, 96, 96, "mono8", ROWS.tobytes(),
     "image data holds 6144 bytes but 96×32 px mono8 with step 96 is 3072 bytes (step × height; allowed: 3072 bytes)"),
    # trailing junk after the last row
    (64, 96, 96, "mono8", ROWS.tobytes() + b"\0" * 5000,
     "image data holds 11144 bytes but 96×64 px mono8 with step 96 is 6144 bytes (step × height; allowed: 6144 bytes)"),
    # a padded step whose data run past step × height
    (32, 48, 96, "mono8", ROWS.tobytes()[:3082],
     "image data holds 3082 bytes but 48×32 px mono8 with step 96 is 3072 bytes (step × height; allowed: 3024 (last "
     "row unpadded) to 3072 bytes)"),
    # 16-bit rows: 32 rows of 2 · 48 bytes, data for 64
    (32, 48, 96, "mono16", ROWS.tobytes(),
     "image data holds 6144 bytes but 48×32 px mono16 with step 96 is 3072 bytes (step × height; allowed: 3072 bytes)"),
])
def test_image_data_longer_than_step_times_height_is_a_frame_error(tmp_path, suffix, height, width, step, enc, data,
                                                                    message):
    path = tmp_path / f"rec{suffix}"
    with RecordingWriter(path) as w:
        w.add_image(TOPIC, ROWS, T0)
        w.add_message(TOPIC, _image(w, height, width, step, data, T0 + 1, enc), T0 + 1)
        # the last row without its padding (step · (h − 1) + row bytes) is still read, as before
        w.add_message(TOPIC, _image(w, 64, 48, 96, ROWS.tobytes()[: 96 * 63 + 48], T0 + 2), T0 + 2)
    with Recording(path) as rec:
        it = rec.frames(TOPIC)
        frames = list(it)
    assert [f.frame is None for f in frames] == [False, True, False] and it.undecodable == 1
    assert frames[1].error == message + ": height/step do not match the data"
    assert frames[2].frame.shape == (1, 64, 48)
    np.testing.assert_allclose(frames[2].frame[0].numpy(), ROWS[:, :48] / 255.0, atol=1e-6)
