"""``python -m camhealth.bench calibrate``: registration and every row and summary line on a tiny run. No wall-clock
assertions."""

import torch

from camhealth.bench import BENCHMARKS
from camhealth.bench.__main__ import main

TINY = ["calibrate", "--sensors", "1", "--frames", "4", "--frame-size", "24", "--patches", "2", "--threads", "1"]


def test_registered():
    assert BENCHMARKS["calibrate"] == "camhealth.bench.calibrate"


def test_cli_prints_errors_time_and_noise_rms(capsys):
    n = torch.get_num_threads()
    try:
        assert main(TINY) == 0
    finally:
        torch.set_num_threads(n)
    text = capsys.readouterr().out
    for row in ("ICX285 · form_image", "EV76C661 · sequential_clip+whole_electrons", "random 0 · form_image"):
        assert row in text
    assert text.count("FW ") >= 6 and "dark model:" in text
    assert "worst |error| full well" in text and "RMS(calibrated) − RMS(true)" in text
