"""``python -m camhealth.bench coldstart``: registration, every row and the no-Lightning line on one repeat. No
wall-clock assertions."""

import pytest
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


def _stubbed_run(monkeypatch, argv):
    """``coldstart.run`` on ``argv`` with the child processes stubbed: (result, commands started, API scripts run)."""
    import json
    from types import SimpleNamespace

    import camhealth.bench.coldstart as cs
    from camhealth.bench.__main__ import parse

    started, scripts = [], []

    def fake_run(cmd, **kw):
        scripts.append(cmd)
        out = json.dumps({"import": 0.1, "load": 0.1, "first": 0.2, "frame": 0.1, "leaked": []})
        return SimpleNamespace(returncode=0, stdout=out, stderr="")

    monkeypatch.setattr(cs, "_wall", lambda cmd: started.append(cmd) or 0.01)
    monkeypatch.setattr(cs, "_first_report", lambda cmd: started.append(cmd) or 0.02)
    monkeypatch.setattr(cs.subprocess, "run", fake_run)
    return cs.run(parse(argv)), started, scripts


@pytest.mark.parametrize("given,expected", [([], 5), (["--repeats", "20"], 20), (["--repeats", "3"], 3)])
def test_repeats_default_5_and_an_explicit_20_is_used(given, expected, monkeypatch):
    """coldstart has its own default (5); an explicit --repeats 20 was taken for the common default and ran 5."""
    result, _, scripts = _stubbed_run(monkeypatch, ["coldstart", *given])
    assert len(scripts) == expected and result.header[0].startswith(f"repeats: {expected} fresh processes per row")


def test_a_relative_source_is_the_callers_file(tmp_path, monkeypatch):
    """The child processes run in the repository root: a relative --source is made absolute first (it named a file of
    the repository, or none, before)."""
    import numpy as np
    from PIL import Image

    Image.fromarray(np.zeros((32, 40), np.uint8)).save(tmp_path / "frame.png")
    monkeypatch.chdir(tmp_path)
    result, started, scripts = _stubbed_run(monkeypatch, ["coldstart", "--repeats", "1", "--source", "frame.png"])
    cli = next(c for c in started if "camhealth.monitor" in c)
    assert cli[cli.index("camhealth.monitor") + 1] == str(tmp_path / "frame.png")
    assert repr(str(tmp_path / "frame.png")) in scripts[0][-1]  # the API script reads the same file
    assert f"source {str(tmp_path / 'frame.png')!r}" in result.header[0]


def test_a_missing_source_is_refused_when_parsed(tmp_path, monkeypatch, capsys):
    from camhealth.bench.__main__ import parse

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as info:
        parse(["coldstart", "--source", "nope.png"])
    assert info.value.code == 2 and "argument --source: no such image file: nope.png" in capsys.readouterr().err
    assert parse(["coldstart"]).source == "street"
