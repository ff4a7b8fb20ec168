"""``python -m camhealth.bench classical``: every row, the error next to ms/patch, registration. No wall-clock
assertions."""

import pytest
import torch

from camhealth.bench import BENCHMARKS
from camhealth.bench.__main__ import main

TINY = ["classical", "--batch", "4", "--repeats", "1", "--warmup", "0", "--charts", "1", "--threads", "1"]


def test_registered():
    assert BENCHMARKS["classical"] == "camhealth.bench.classical"


def test_cli_prints_error_and_speed_side_by_side(capsys, tmp_path):
    n = torch.get_num_threads()
    try:
        assert main(TINY + ["--out", str(tmp_path / "b.md")]) == 0
    finally:
        torch.set_num_threads(n)
    text = capsys.readouterr().out
    for row in ("PCA noise", "B+F noise", "wavelet MAD noise (torch path)", "slanted edge (ISO 12233)", "Siemens star (ISO 15775)"):
        assert row in text
    assert text.count("ms/patch · Bias") >= 3 and text.count("ms/chart · AMAE") == 2
    assert "× PCA noise" in text and "machine:" in text
    assert "| PCA noise (Chen et al. 2015) |" in (tmp_path / "b.md").read_text()


def test_bad_options():
    with pytest.raises(ValueError, match="--batch"):
        main(["classical", "--batch", "1", "--repeats", "1", "--warmup", "0"])
