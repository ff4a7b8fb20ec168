"""``python -m camhealth.bench siemens_star``: registration, both timed rows, the worst-case line and the AMAE table
with a cell per kernel and level. No wall-clock assertions."""

import re

import torch

from camhealth.bench import BENCHMARKS
from camhealth.bench.__main__ import main


def test_registered():
    assert BENCHMARKS["siemens_star"] == "camhealth.bench.siemens_star"


def test_cli_prints_error_beside_time_with_and_without_the_correction(capsys):
    n = torch.get_num_threads()
    try:
        assert main(["siemens_star", "--images", "1", "--repeats", "1", "--warmup", "0", "--threads", "1", "--markdown"]) == 0
    finally:
        torch.set_num_threads(n)
    text = capsys.readouterr().out
    assert "Siemens star, noise corrected (default)" in text and "Siemens star, raw CTF (levels= given)" in text
    assert "worst single-chart AMAE at 0–15 DN" in text
    rows = [line for line in text.splitlines() if re.match(r"\| (Gaussian|hexagon|shake) ", line)]
    assert len(rows) == 9 and all(line.count(" / ") == 6 for line in rows)
    assert all(line.split("|")[-2].strip().startswith("– /") for line in rows)  # 25 DN: 16 % of the contrast, refused
