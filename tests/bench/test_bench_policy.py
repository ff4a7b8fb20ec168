"""``python -m camhealth.bench policy``: registration, every row and the scores on a tiny synthetic IOPC; bad input. No
wall-clock assertions."""

import re

import numpy as np
import pytest
import torch

from camhealth.bench import BENCHMARKS
from camhealth.bench.__main__ import main
from camhealth.iopc import IOPC


def _iopc(path):
    recs = []
    for s in (0.0, 1.0, 2.0, 3.0, 4.0):
        for L in (0.0, 3.0, 7.0, 15.0):
            m = 0.5 * (1.0 + abs(float(np.sinc(0.05 * L))))
            ap = float(np.clip((m - 0.5) * 2.0, 0, 1) * (1.0 - s / 5.0))
            recs.append({"index": len(recs), "key": f"L{L}_s{s}", "length_px": L, "angle_deg": 0.0,
                         "noise_level_dn": s, "sigma_tilde": s, "mtf_tilde": m, "ap": ap})
    IOPC.from_records(recs, name="synthetic").save(path)
    return path


def test_registered():
    assert BENCHMARKS["policy"] == "camhealth.bench.policy"


def test_cli_prints_loss_and_time_per_table(tmp_path, capsys):
    path = _iopc(tmp_path / "iopc.json")
    n = torch.get_num_threads()
    try:
        assert main(["policy", "--iopc", str(path), "--decisions", "40", "--repeats", "2", "--warmup", "0", "--threads", "1"]) == 0
    finally:
        torch.set_num_threads(n)
    text = capsys.readouterr().out
    for row in ("table, default resolution", "table, half the resolution", "table, twice the resolution",
                "direct objective (no table)"):
        assert row in text
    losses = [float(v) for v in re.findall(r"loss max (\S+) /", text)]
    assert len(losses) == 3 and all(0.0 <= v < 0.5 for v in losses)  # finite: no α beyond the measured σ
    assert "µs per decision" in text and "other α" in text


def test_bad_input_is_named(tmp_path):
    with pytest.raises(ValueError, match="no such file"):
        main(["policy", "--iopc", str(tmp_path / "missing.json")])
    path = _iopc(tmp_path / "iopc.json")
    with pytest.raises(ValueError, match="--decisions = 3"):
        main(["policy", "--iopc", str(path), "--decisions", "3"])
