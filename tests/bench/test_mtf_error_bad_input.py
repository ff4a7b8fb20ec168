"""``python -m camhealth.bench mtf_error``: bad counts and sizes are refused before the calibration set is made, naming
the option the user typed (not the calibration functions' ``per_cell`` and ``sizes``). Nothing is benchmarked here."""

from __future__ import annotations

import pytest

from camhealth._cli import run_cli
from camhealth.bench import __main__ as bench_cli


@pytest.mark.parametrize("argv,message", [
    (["--frames", "0"], "argument --frames: must be >= 1, got 0 (allowed: 1 … 64)"),
    (["--frames", "65"], "argument --frames: must be <= 64, got 65 (allowed: 1 … 64)"),
    (["--per-cell", "0"], "argument --per-cell: must be >= 1, got 0 (allowed: 1 … 256)"),
    (["--per-cell", "257"], "argument --per-cell: must be <= 256, got 257 (allowed: 1 … 256)"),
])
def test_counts_name_the_option(argv, message, no_run, capsys):
    """``--frames 0`` made the whole calibration set (a minute) and then failed naming ``per_cell``."""
    with pytest.raises(SystemExit) as info:
        bench_cli.main(["mtf_error", *argv])
    err = capsys.readouterr().err
    assert info.value.code == 2 and message in err and "per_cell" not in err, err


@pytest.mark.parametrize("sizes,message", [
    (["40"], "--sizes 40 must lie in [0, 29] px"),
    (["3", "-1"], "--sizes 3 -1 must lie in [0, 29] px"),
    ([str(s) for s in range(1, 16)], "--sizes 1 2 3 4 5 6 7 8 9 10 11 12 13 14 15: 15 sizes, at most 14 are allowed"),
])
def test_sizes_name_the_option(sizes, message, no_run, capsys):
    assert run_cli(bench_cli.main, "python -m camhealth.bench", ["mtf_error", "--sizes", *sizes]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0] and "sizes =" not in err[0], err
