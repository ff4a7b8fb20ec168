"""``python -m camhealth.bench`` itself: options are written in full (an abbreviation is refused, so a ``--docs`` block
is named by one spelling of its command), and a ``--docs`` file that cannot be written is refused before the
benchmark runs. Nothing is benchmarked here."""

from __future__ import annotations

import pytest

from camhealth._cli import run_cli
from camhealth.bench import __main__ as bench_cli

TINY = ["data", "--batch", "2", "--repeats", "1", "--warmup", "0"]


@pytest.mark.parametrize("abbreviated", [["--doc", "page.md"], ["--mark"], ["--rep", "3"], ["--doc=page.md"]])
def test_abbreviated_options_are_refused(abbreviated, no_run, capsys):
    """argparse took unambiguous prefixes: ``--doc FILE`` wrote a block named "… --doc FILE" and ``--mark`` one named
    "… --mark", beside the block of the same command, so a page grew a duplicate block per spelling."""
    with pytest.raises(SystemExit) as info:
        bench_cli.main(TINY + abbreviated)
    assert info.value.code == 2 and "unrecognized arguments" in capsys.readouterr().err


def test_full_option_names_still_parse():
    args = bench_cli.parse(TINY + ["--markdown", "--docs", "page.md"])
    assert args.markdown is True and str(args.docs) == "page.md"


def _bad_docs(tmp_path, kind):
    if kind == "folder":
        (tmp_path / "a_dir.md").mkdir()
        return tmp_path / "a_dir.md", "is a folder"
    if kind == "missing folder":
        return tmp_path / "no_such_dir" / "benchmarks.md", "does not exist"
    if kind == "broken block":
        page = tmp_path / "page.md"
        page.write_text("<!-- generated: python -m camhealth.bench data -->\n| table |\n", encoding="utf-8")
        return page, "has no end marker"
    page = tmp_path / "latin1.md"
    page.write_bytes("caf\xe9".encode("latin-1"))
    return page, "not a UTF-8 text file"


@pytest.mark.parametrize("kind", ["folder", "missing folder", "broken block", "not utf-8"])
def test_a_docs_file_that_cannot_be_written_is_refused_before_the_run(kind, tmp_path, no_run, capsys):
    """Exit status 2 and one line naming the file, before the benchmark (it failed after the whole run, the table lost)."""
    path, why = _bad_docs(tmp_path, kind)
    assert run_cli(bench_cli.main, "python -m camhealth.bench", TINY + ["--docs", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--docs {path}" in err[0] and why in err[0], err


def test_a_new_docs_file_in_an_existing_folder_is_accepted(tmp_path, monkeypatch):
    seen = {}
    real = bench_cli.load

    class Stop(Exception):
        pass

    class Module:
        def __init__(self, name):
            m = real(name)
            self.HELP, self.add_arguments = m.HELP, m.add_arguments

        def run(self, args):
            seen["docs"] = args.docs
            raise Stop

    monkeypatch.setattr(bench_cli, "load", Module)
    with pytest.raises(Stop):
        bench_cli.main(TINY + ["--docs", str(tmp_path / "new.md")])
    assert seen["docs"] == tmp_path / "new.md" and not (tmp_path / "new.md").exists()


@pytest.mark.parametrize("bench,option,value,bound", [("classical", "--noise-size", "16", 32), ("classical", "--charts", "0", 1),
                                                      ("data", "--workers", "-1", 0), ("data", "--noise-patch", "0", 1),
                                                      ("data", "--blur-patch", "68", 69)])
def test_sizes_and_counts_are_checked_when_parsed(bench, option, value, bound, no_run, capsys):
    """Exit status 2 naming the option and its bound before the benchmark runs (they were refused only by the
    estimator or the DataModule, after the batches were built)."""
    with pytest.raises(SystemExit) as info:
        bench_cli.main([bench, option, value])
    assert info.value.code == 2 and f"argument {option}: must be >= {bound}, got {value}" in capsys.readouterr().err

