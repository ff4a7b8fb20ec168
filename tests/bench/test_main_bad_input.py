"""``python -m camhealth.bench``: output files, the seed, the thread count and monitor's mode options are refused
before the benchmark runs, with one line naming the option, its value and its range. Nothing is benchmarked here."""

from __future__ import annotations

import pytest

from camhealth._cli import run_cli
from camhealth.bench import __main__ as bench_cli

TINY = ["data", "--batch", "2", "--size", "32", "--repeats", "1", "--warmup", "0"]


def _err(capsys) -> list[str]:
    return capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize("option", ["--out", "--json"])
def test_an_output_file_that_is_a_folder_or_under_a_file_is_refused_before_the_run(option, tmp_path, no_run, capsys):
    argv = ["mtf_error"] if option == "--json" else TINY
    assert run_cli(bench_cli.main, "python -m camhealth.bench", argv + [option, str(tmp_path)]) == 2
    err = _err(capsys)
    assert len(err) == 1 and f"{option} {tmp_path}" in err[0] and "is a folder" in err[0], err
    (tmp_path / "f.txt").write_text("x")
    assert run_cli(bench_cli.main, "python -m camhealth.bench", argv + [option, str(tmp_path / "f.txt" / "t.md")]) == 2
    err = _err(capsys)
    assert len(err) == 1 and option in err[0] and "is a file" in err[0], err


def test_a_missing_folder_of_json_is_made_before_the_run(tmp_path, no_run):
    target = tmp_path / "new" / "deeper" / "r.json"
    with pytest.raises(pytest.fail.Exception, match="the benchmark ran"):
        bench_cli.main(["mtf_error", "--json", str(target)])
    assert target.parent.is_dir() and not target.exists()


@pytest.mark.parametrize("option,value,message", [
    ("--seed", "-1", "must be ≥ 0, got -1 (allowed: 0 … 4294967295)"),
    ("--seed", "99999999999999999999", "must be ≤ 4294967295"),
    ("--threads", "100000", "must be ≤"),
    ("--batch", "100000000", "must be ≤ 4096"),
])
def test_seed_and_counts_are_bounded(option, value, message, no_run, capsys):
    with pytest.raises(SystemExit) as info:
        bench_cli.main(TINY + [option, value])
    err = capsys.readouterr().err
    assert info.value.code == 2 and f"argument {option}: {message}" in err, err


@pytest.mark.parametrize("extra,message", [
    (["--motion", "--device", "cuda:7"], "--device cuda:7 is not used by --motion"),
    (["--pool-sizes", "--frames", "3"], "--frames 3 is not used by --pool-sizes"),
    (["--exposure-step", "--untrained"], "--untrained is not used by --exposure-step"),
    (["--motion", "--scene", "deadleaves"], "--scene deadleaves is not used by --motion"),
    (["--noise-samples", "3"], "--noise-samples 3 is not used by the default monitor benchmark"),
    (["--motion", "--pool-sizes"], "--motion and --pool-sizes are different benchmarks"),
    (["--frames", "2"], "--warmup 2 must be smaller than --frames 2"),
])
def test_monitor_refuses_options_its_mode_does_not_read(extra, message, no_run, capsys):
    assert run_cli(bench_cli.main, "python -m camhealth.bench", ["monitor", *extra]) == 2
    err = _err(capsys)
    assert len(err) == 1 and message in err[0], err
