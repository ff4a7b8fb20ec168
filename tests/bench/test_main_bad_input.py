"""``python -m camhealth.bench``: output files, the seed, the thread count and monitor's mode options are refused
before the benchmark runs, with one line naming the option, its value and its range. Nothing is benchmarked here."""

from __future__ import annotations

import pytest

from camhealth._cli import run_cli
from camhealth.bench import __main__ as bench_cli

TINY = ["data", "--batch", "2", "--repeats", "1", "--warmup", "0"]


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


@pytest.mark.parametrize("argv,message", [
    (["policy", "--decisions", "100001"], "--decisions = 100001 must be an integer <= 100000 (allowed: 10 … 100000)"),
    (["policy", "--decisions", "3"], "--decisions = 3 must be an integer >= 10 (allowed: 10 … 100000)"),
    (["monitor", "--width", "100000"], "--width must be <= 8192, got 100000 (allowed: 1 … 8192)"),
    (["monitor", "--motion", "--height", "8193"], "--height must be <= 8192, got 8193 (allowed: 1 … 8192)"),
    (["monitor", "--exposure-step", "--width", "0"], "--width must be >= 1, got 0 (allowed: 1 … 8192)"),
    (["monitor", "--scene", "deadleaves", "--frames", "1001"], "--frames must be <= 1000, got 1001 (allowed: 1 … 1000)"),
    (["monitor", "--scene", "deadleaves", "--frames", "300"],
     "--frames 300 × --width 1280 × --height 1024 = 393216000 px of frames must be <= 268435456"),
    (["monitor", "--device", "nosuch"], "--device nosuch is not a device name"),
    (["monitor", "--motion", "--window", "1001"], "--window must be <= 1000, got 1001 (allowed: 1 … 1000)"),
    (["monitor", "--motion", "--noise-samples", "257"], "--noise-samples must be <= 256, got 257 (allowed: 1 … 256)"),
    (["monitor", "--motion", "--mtf-samples", "0"], "--mtf-samples must be >= 1, got 0 (allowed: 1 … 256)"),
    (["monitor", "--pool-sizes", "--pool-draws", "65"], "--pool-draws must be an integer <= 64, got 65 (allowed: 1 … 64)"),
    (["calibrate", "--frame-size", "1025"], "--frame-size must be <= 1024, got 1025 (allowed: 16 … 1024)"),
    (["calibrate", "--frame-size", "8"], "--frame-size must be >= 16, got 8 (allowed: 16 … 1024)"),
    (["calibrate", "--sensors", "101"], "--sensors must be <= 100, got 101 (allowed: 0 … 100)"),
    (["calibrate", "--sensors", "-1"], "--sensors must be >= 0, got -1 (allowed: 0 … 100)"),
    (["calibrate", "--frames", "101"], "--frames must be <= 100, got 101 (allowed: 4 … 100)"),
    (["calibrate", "--patches", "1025"], "--patches must be <= 1024, got 1025 (allowed: 2 … 1024)"),
    (["calibrate", "--variants", "nope"], "--variants nope: unknown variant(s) ['nope']"),
    (["coldstart", "--repeats", "201"], "--repeats must be <= 200, got 201 (allowed: 1 … 200)"),
])
def test_counts_and_sizes_are_bounded_before_the_run(argv, message, no_run, capsys):
    """``policy --decisions 10**11``, ``monitor --width 100000 --height 100000`` (10**10 px a frame) and
    ``calibrate --sensors 100000`` started; now one line naming the option, its value and its range."""
    assert run_cli(bench_cli.main, "python -m camhealth.bench", argv) == 2
    err = _err(capsys)
    assert len(err) == 1 and message in err[0], err


@pytest.mark.parametrize("argv,message", [
    (["classical", "--charts", "257"], "argument --charts: must be <= 256, got 257 (allowed: 1 … 256)"),
    (["classical", "--noise-size", "4097"], "argument --noise-size: must be <= 4096, got 4097 (allowed: 32 … 4096)"),
    (["data", "--noise-patch", "4097"], "argument --noise-patch: must be <= 4096, got 4097 (allowed: 1 … 4096)"),
    (["data", "--blur-patch", "100000"], "argument --blur-patch: must be <= 4096, got 100000 (allowed: 69 … 4096)"),
    (["data", "--workers", "100000"], "argument --workers: must be <= "),
    (["siemens_star", "--images", "65"], "argument --images: must be <= 64, got 65 (allowed: 1 … 64)"),
    (["corruption", "--loop-repeats", "101"], "argument --loop-repeats: must be <= 100, got 101 (allowed: 1 … 100)"),
    (["corruption", "--loop-images", "4097"], "argument --loop-images: must be <= 4096, got 4097"),
    (["corruption", "--sf-frequencies", "1000001"], "argument --sf-frequencies: must be <= 1000000, got 1000001"),
])
def test_counts_and_sizes_are_bounded_when_parsed(argv, message, no_run, capsys):
    with pytest.raises(SystemExit) as info:
        bench_cli.main(argv)
    err = capsys.readouterr().err
    assert info.value.code == 2 and message in err, err


@pytest.mark.parametrize("argv, option", [
    (["data", "--size", "32"], "--size 32"),
    (["calibrate", "--batch", "4"], "--batch 4"),
    (["calibrate", "--repeats", "3"], "--repeats 3"),
    (["estimators", "--seed", "3"], "--seed 3"),
    (["coldstart", "--warmup", "1"], "--warmup 1"),
    (["robustness", "--size", "64"], "--size 64"),
    (["monitor", "--batch", "8"], "--batch 8"),
    (["mtf_error", "--warmup", "5"], "--warmup 5"),
])
def test_a_common_option_the_benchmark_does_not_read_is_refused(argv, option, no_run):
    """Set, the option was ignored, and the table's header recorded it as if it had been used."""
    name = argv[0]
    with pytest.raises(ValueError, match=rf"^{option} is not used by `python -m camhealth.bench {name}` "
                                         r"\(of the common options it reads .*\); leave it out$"):
        bench_cli.main(argv)


@pytest.mark.parametrize("argv", [
    ["data", "--batch", "2", "--repeats", "1", "--warmup", "0", "--seed", "1"],
    ["calibrate", "--seed", "3"],
    ["coldstart", "--repeats", "3"],
    ["monitor", "--warmup", "1", "--seed", "2"],
    ["robustness", "--seed", "7", "--batch", "32"],  # a common option at its default is no choice: accepted
])
def test_the_common_options_a_benchmark_reads_are_accepted(argv, monkeypatch):
    class Started(Exception):
        pass

    real = bench_cli.load

    class Module:  # the checks pass and the benchmark would start
        def __init__(self, name):
            self.HELP, self.add_arguments = real(name).HELP, real(name).add_arguments

        def run(self, args):
            raise Started

    monkeypatch.setattr(bench_cli, "load", Module)
    with pytest.raises(Started):
        bench_cli.main(argv)
