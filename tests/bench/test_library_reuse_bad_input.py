"""``python -m camhealth.bench.library_reuse``: ``--min-run-time`` and ``--threads`` are bounded when parsed, one line
naming the option, its value and its range. Nothing is timed here."""

from __future__ import annotations

import pytest

from camhealth.bench import library_reuse
from camhealth.bench.__main__ import THREADS_MAX


@pytest.mark.parametrize("argv,message", [
    (["--min-run-time", "1000000"], "argument --min-run-time: must be <= 30, got 1000000 (allowed: > 0 … 30 s)"),
    (["--min-run-time", "31"], "argument --min-run-time: must be <= 30, got 31"),
    (["--min-run-time", "0"], "argument --min-run-time: must be > 0, got 0 (allowed: > 0 … 30 s)"),
    (["--threads", "100000"], f"argument --threads: must be <= {THREADS_MAX}, got 100000 (allowed: 1 … {THREADS_MAX})"),
])
def test_min_run_time_and_threads_are_bounded(argv, message, monkeypatch, capsys):
    """``--min-run-time 1000000`` timed each of 15 cases' two calls for 11 days each; ``--min-run-time 0`` was refused
    as "--threads = 1 must be ≥ 1 and --min-run-time = 0.0 > 0", naming a --threads that was right."""
    monkeypatch.setattr(library_reuse, "compare", lambda *a, **k: pytest.fail("the comparison ran"))
    with pytest.raises(SystemExit) as info:
        library_reuse.main(argv)
    err = capsys.readouterr().err
    assert info.value.code == 2 and message in err and "--threads = 1" not in err, err
