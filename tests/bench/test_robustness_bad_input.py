"""``python -m camhealth.bench robustness``: each ``--task`` refuses the options it does not read (the table's header
recorded them as if used) and the counts are bounded, before anything is made. Nothing is benchmarked here."""

from __future__ import annotations

import argparse

import pytest

from camhealth._cli import run_cli
from camhealth.bench import __main__ as bench_cli

PROG = "python -m camhealth.bench"


def _refused(argv, capsys) -> str:
    """The one error line of ``argv`` (exit status 2, the benchmark not started)."""
    assert run_cli(bench_cli.main, PROG, argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def _runs(argv) -> None:
    """``argv`` is accepted: the benchmark starts (the ``no_run`` fixture stops it there)."""
    with pytest.raises(pytest.fail.Exception, match="the benchmark ran"):
        bench_cli.main(argv)


@pytest.mark.parametrize("documented,extra,message", [
    (["--task", "jpeg", "--frames", "8", "--threads", "2", "--markdown"], ["--models", "drne"],
     "--models drne is not used by --task jpeg; leave it out"),
    (["--task", "jpeg", "--frames", "8", "--threads", "2", "--markdown"], ["--paired"],
     "--paired is not used by --task jpeg; leave it out"),
    (["--task", "jpeg", "--frames", "8", "--threads", "2", "--markdown"], ["--per-cell", "4"],
     "--per-cell 4 is not used by --task jpeg"),
    (["--task", "jpeg", "--frames", "8", "--threads", "2", "--markdown"], ["--mtf-sizes", "3", "5"],
     "--mtf-sizes 3 5 is not used by --task jpeg"),
    (["--task", "jpeg"], ["--models"], "--models is not used by --task jpeg"),
    (["--task", "mtf", "--per-cell", "8", "--threads", "2", "--markdown"], ["--frames", "16"],
     "--frames 16 is not used by --task mtf; leave it out"),
    (["--task", "mtf", "--per-cell", "8", "--threads", "2", "--markdown"], ["--paired"],
     "--paired is not used by --task mtf"),
    (["--frames", "16", "--threads", "2", "--paired", "--markdown"], ["--per-cell", "4"],
     "--per-cell 4 is not used by --task noise (the default task)"),
    (["--frames", "16", "--threads", "2", "--markdown"], ["--task", "noise", "--mtf-sizes", "3"],
     "--mtf-sizes 3 is not used by --task noise"),
])
def test_a_task_refuses_the_options_it_does_not_read(documented, extra, message, no_run, capsys):
    """``--task jpeg --models drne --paired`` ran the JPEG test as without them, and wrote them into its header."""
    _runs(["robustness", *documented])  # the documented command line as it is
    line = _refused(["robustness", *documented, *extra], capsys)
    assert message in line, line


def test_an_option_given_at_its_default_is_no_change(no_run):
    """Set "by the user" is away from the parser's default: ``--per-cell 8`` (its default) with ``--task jpeg`` changes
    nothing, and so is accepted; ``--per-cell 4`` is not (the test above)."""
    _runs(["robustness", "--task", "jpeg", "--per-cell", "8", "--mtf-sizes", "3", "5", "9", "15", "21"])
    with pytest.raises(ValueError, match="--per-cell 4 is not used by --task jpeg"):
        bench_cli.main(["robustness", "--task", "jpeg", "--per-cell", "4"])


def test_a_config_file_is_checked_as_the_command_line(tmp_path, no_run, capsys):
    path = tmp_path / "r.yaml"
    path.write_text("task: mtf\nframes: 12\n")
    assert "--frames 12 is not used by --task mtf" in _refused(["robustness", "--config", str(path)], capsys)


def test_run_called_directly_refuses_an_unread_option(monkeypatch):
    from camhealth.bench import robustness

    monkeypatch.setattr(robustness, "make_frames", lambda *a, **k: pytest.fail("the frames were made"))
    args = argparse.Namespace(task="jpeg", frames=2, seed=0, models=["drne"], json=None, command_line="test")
    with pytest.raises(ValueError, match="--models drne is not used by --task jpeg"):
        robustness.run(args)


@pytest.mark.parametrize("argv,message", [
    (["--frames", "65"], "argument --frames: must be <= 64, got 65 (allowed: 2 … 64)"),
    (["--frames", "1000000"], "argument --frames: must be <= 64, got 1000000 (allowed: 2 … 64)"),
    (["--frames", "1"], "argument --frames: must be >= 2, got 1 (allowed: 2 … 64)"),
    (["--task", "mtf", "--per-cell", "65"], "argument --per-cell: must be <= 64, got 65 (allowed: 1 … 64)"),
    (["--task", "mtf", "--per-cell", "300"], "argument --per-cell: must be <= 64, got 300"),
])
def test_counts_are_bounded_when_parsed(argv, message, no_run, capsys):
    """``--frames 100000`` started making 1.5 million frames (≈ 70 GB); ``--per-cell 300`` was refused naming the
    function's parameter ``per_cell``."""
    with pytest.raises(SystemExit) as info:
        bench_cli.main(["robustness", *argv])
    assert info.value.code == 2 and message in capsys.readouterr().err


@pytest.mark.parametrize("sizes,message", [
    ([str(s) for s in range(1, 12)], "--mtf-sizes 1 2 3 4 5 6 7 8 9 10 11: 11 sizes, at most 10 are allowed"),
    (["3", "40"], "--mtf-sizes 3 40 must lie in [0, 29] px (kernels are 31 px)"),
])
def test_mtf_sizes_are_bounded_before_the_run(sizes, message, no_run, capsys):
    line = _refused(["robustness", "--task", "mtf", "--mtf-sizes", *sizes], capsys)
    assert message in line, line
