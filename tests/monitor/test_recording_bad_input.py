"""RecordingSource / open_source: a start at or past the image topic's message count is refused when the source is
opened (as for images, folders and videos), not found out after an empty run."""

from __future__ import annotations

import numpy as np
import pytest

from camhealth.data.rosbag import RecordingWriter
from camhealth.monitor.recording import RecordingOptions, RecordingSource
from camhealth.monitor.sources import open_source

T0 = 1_700_000_000 * 10**9
TOPIC = "/camera/image_raw"


def _recording(path, n=4):
    with RecordingWriter(path) as w:
        for i in range(n):
            w.add_image(TOPIC, np.full((16, 24), 10 * i, np.uint8), T0 + i * 10**8)
        w.add_image("/other/image", np.zeros((8, 8), np.uint8), T0)  # another topic's messages do not count
    return path


@pytest.mark.parametrize("suffix", [".mcap", ".bag", ".db3"])
@pytest.mark.parametrize("start", [4, 5, 100])
def test_start_past_the_last_message_is_refused_when_opened(tmp_path, suffix, start):
    """start=100 on a 4-message topic yielded 0 frames without a word (the CLI then wrote an empty diagnostics
    file before it noticed)."""
    path = _recording(tmp_path / f"rec{suffix}")
    match = rf"start = {start} is past the end of .*rec\{suffix}: it has 4 frame\(s\), indices 0…3"
    with pytest.raises(ValueError, match=match):
        RecordingSource(path, start=start, options=RecordingOptions(topic=TOPIC))
    with pytest.raises(ValueError, match=match):
        open_source(path, start=start, recording=RecordingOptions(topic=TOPIC))
    # the last frame is still a valid start
    src = RecordingSource(path, start=3, options=RecordingOptions(topic=TOPIC))
    try:
        assert src.length == 1 and [item.index for item in src] == [3]
    finally:
        src.close()
