"""``python -m camhealth.demo closed-loop``: a bad option is one line naming it, its value and its range, exit status
2, before the IOPC, the frames or the detector are loaded."""

from __future__ import annotations

import pytest

from camhealth import demo
from camhealth._cli import run_cli


@pytest.fixture
def no_run(monkeypatch):
    monkeypatch.setitem(demo.DEMOS, "closed-loop", lambda options: pytest.fail("the demo ran"))
    real = demo.build_parser

    def build():
        p = real()
        demo.DEMOS["closed-loop"] = lambda options: pytest.fail("the demo ran")
        return p

    monkeypatch.setattr(demo, "build_parser", build)


@pytest.mark.parametrize("argv,message", [
    (["--decide-every", "0"], "--decide-every: must be >= 1, got 0"),
    (["--pseudo-score", "2"], "--pseudo-score must be in [0, 1], got 2.0"),
    (["--seed", "-1"], "--seed: must be >= 0, got -1"),
    (["--seed", "99999999999999999999"], "--seed: must be <= 4294967295, got 99999999999999999999 (allowed: 0 … 4294967295)"),
    (["--threads", "100000"], "--threads: must be <= "),
])
def test_bad_values_are_refused_naming_the_option(argv, message, no_run, capsys):
    assert run_cli(demo.main, "python -m camhealth.demo", ["closed-loop", *argv]) == 2
    assert message in capsys.readouterr().err


def test_out_that_is_a_file_and_iopc_that_is_a_folder_are_refused_up_front(tmp_path, no_run, capsys):
    f = tmp_path / "f.txt"
    f.write_text("x")
    for argv, message in ((["--out", str(f)], f"--out {f}"), (["--out", str(f / "sub")], "is a file"),
                          (["--iopc", str(tmp_path)], f"--iopc {tmp_path}: is a folder")):
        assert run_cli(demo.main, "python -m camhealth.demo", ["closed-loop", *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err
