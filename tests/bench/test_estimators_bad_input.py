"""``python -m camhealth.bench estimators``: errors name the command line's options (``--per-image``, ``--sizes``,
``--device``, ``--models``), not the parameters of the DataModules and loaders behind them, and an option of the noise
set without a noise estimator (or of the MTF set without an MTF one) is refused. Nothing is benchmarked here."""

from __future__ import annotations

import pytest

from camhealth._cli import run_cli
from camhealth.bench import __main__ as bench_cli

PROG = "python -m camhealth.bench"


def _line(argv, capsys) -> str:
    assert run_cli(bench_cli.main, PROG, argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    return err[-1]


@pytest.mark.parametrize("argv,message,internal", [
    (["--per-image", "0"], "argument --per-image: must be >= 1, got 0 (allowed: 1 … 256)", "val_patches_per_image"),
    (["--per-image", "100000"], "argument --per-image: must be <= 256, got 100000", "val_patches_per_image"),
    (["--deadleaves", "-1"], "argument --deadleaves: must be >= 0, got -1 (allowed: 0 … 1000)", "deadleaves ="),
    (["--deadleaves", "100000"], "argument --deadleaves: must be <= 1000, got 100000", "deadleaves ="),
    (["--sizes", "21", "3"], "--sizes 21 3 must satisfy 0 ≤ LOW ≤ HIGH ≤ 63 px", "size_range"),
    (["--sizes", "-1", "5"], "--sizes -1 5 must satisfy 0 ≤ LOW ≤ HIGH ≤ 63 px", "size_range"),
    (["--sizes", "3", "70"], "--sizes 3 70 must satisfy 0 ≤ LOW ≤ HIGH ≤ 63 px", "size_range"),
    (["--device", "nosuch"], "--device nosuch is not a device name; allowed: 'cpu', 'cuda' or 'cuda:N'", "device ="),
])
def test_errors_name_the_option_before_the_run(argv, message, internal, no_run, capsys):
    line = _line(["estimators", *argv], capsys)
    assert message in line and internal not in line, line


@pytest.fixture
def no_data(monkeypatch):
    """The held-out sets fail the test: what is checked must be refused once the estimators are loaded, before them."""
    from camhealth.bench import estimators

    for name in ("held_out_noise", "held_out_blur"):
        monkeypatch.setattr(estimators, name, lambda args, name=name: pytest.fail(f"{name} was made"))


@pytest.mark.parametrize("argv,message", [
    (["--models", "mtf", "--deadleaves", "10"],
     "--deadleaves 10 is not used by --models mtf (no noise estimator among them)"),
    (["--models", "mtf", "--xi-fields", "gain_db"], "--xi-fields gain_db is not used by --models mtf"),
    (["--models", "mtf", "--split-floor"], "--split-floor is not used by --models mtf"),
    (["--models", "drne", "--mtf-views", "1", "2"],
     "--mtf-views 1 2 is not used by --models drne (no MTF estimator among them)"),
    (["--models", "drne", "--sizes", "3", "9"], "--sizes 3 9 is not used by --models drne"),
    (["--models", "nosuch"], "--models nosuch: no estimator named or at 'nosuch'"),
    (["--models", "--checkpoint", "missing.pt"], "--checkpoint missing.pt: no estimator named or at 'missing.pt'"),
])
def test_the_estimators_read_the_options_given(argv, message, no_data, capsys):
    """``--models mtf --deadleaves 10`` measured the MTF model as without it (the docstring said it does not apply)."""
    line = _line(["estimators", "--no-reference", *argv], capsys)
    assert message in line, line


@pytest.mark.parametrize("models,reads,unread,made,message", [
    (["mtf"], ["--mtf-views", "1", "2", "4", "--sizes", "3", "9"], ["--deadleaves", "10"], "held_out_blur",
     "--deadleaves 10 is not used by --models mtf"),
    (["drne"], ["--deadleaves", "10", "--xi-fields", "gain_db", "--split-floor"], ["--sizes", "3", "9"], "held_out_noise",
     "--sizes 3 9 is not used by --models drne"),
])
def test_a_run_reads_the_options_of_its_estimators_only(models, reads, unread, made, message, no_data, capsys):
    """The options of the estimators' own set are accepted (the set is made); the other set's are refused."""
    with pytest.raises(pytest.fail.Exception, match=f"{made} was made"):
        bench_cli.main(["estimators", "--no-reference", "--models", *models, *reads])
    assert message in _line(["estimators", "--no-reference", "--models", *models, *reads, *unread], capsys)
