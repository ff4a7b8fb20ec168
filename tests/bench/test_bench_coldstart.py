"""``python -m camhealth.bench coldstart``: registration, every row and the no-Lightning line on one repeat. No
wall-clock assertions."""

import torch

from camhealth.bench import BENCHMARKS
from camhealth.bench.__main__ import main
from camhealth.inference import WEIGHTS_DIR


def test_registered():
    assert BENCHMARKS["coldstart"] == "camhealth.bench.coldstart"


def test_cli_prints_every_phase_and_no_lightning(capsys):
    frame = WEIGHTS_DIR.parent / "data" / "street" / "vtest_0100.png"
    n = torch.get_num_threads()
    try:
        assert main(["coldstart", "--repeats", "1", "--threads", "1", "--source", str(frame),
                     "--noise-model", "noise_source_min"]) == 0
    finally:
        torch.set_num_threads(n)
    text = capsys.readouterr().out
    for row in ("python -c pass", "import camhealth.monitor", "CLI → first report", "API: import", "API: load estimators",
                "API: first frame", "API: frame, kernels built", "API: kernel warm-up"):
        assert row in text
    assert "imported by the API process: none" in text
    assert "to the first report excluding the warm-up" in text and "noise_source_min" in text
