"""The generated-block writer refuses a page whose markers are ambiguous before anything is written (naming the file,
the line and the marker), keeps a page's line endings, writes only into Markdown files, and refuses a command line
that would not parse back from its marker."""

from __future__ import annotations

import shlex

import pytest

from camhealth._cli import run_cli
from camhealth.bench import __main__ as bench_cli
from camhealth.docs import generated_blocks, replace_generated

TINY = ["data", "--batch", "2", "--repeats", "1", "--warmup", "0"]
A = "<!-- generated: python -m x --a 1 -->\n"
B = "<!-- generated: python -m y -->\n"
END = "<!-- end generated -->\n"

def _no_run(monkeypatch):
    """The benchmark's ``run`` fails the test: what is checked here is refused before it."""
    real = bench_cli.load

    class Module:
        def __init__(self, name):
            m = real(name)
            self.HELP, self.add_arguments = m.HELP, m.add_arguments

        def run(self, args):
            pytest.fail("the benchmark ran")

    monkeypatch.setattr(bench_cli, "load", Module)


PAGES = {
    # a block whose end marker was lost ran on to the next block's end: the prose and B's begin marker were deleted
    "unclosed before next": (A + "old A\n## Hand-written\nprose\n" + B + "old B\n" + END, "line 1", "python -m x --a 1"),
    "stray end": ("intro\n" + END + A + "old\n" + END, "line 2", "end marker"),
    "duplicate": (A + "one\n" + END + "<!-- generated: python -m x --a=1 --markdown -->\ntwo\n" + END, "line 4", "duplicate"),
    "malformed begin": ("<!-- generated: python -m x --a 1 --> trailing words\nold\n" + END, "line 1", "malformed"),
    "unparsable command": ("<!-- generated: python -m x --src it's.png -->\nold\n" + END, "line 1", "does not parse"),
}


@pytest.mark.parametrize("kind", sorted(PAGES))
def test_an_ambiguous_page_is_refused_naming_the_file_line_and_marker(kind, tmp_path):
    text, line, marker = PAGES[kind]
    page = tmp_path / "p.md"
    page.write_text(text, encoding="utf-8")
    with pytest.raises(ValueError) as info:
        replace_generated(page, "python -m x --a 1", "NEW")
    message = str(info.value)
    assert str(page) in message and line in message and marker in message, message
    assert page.read_text(encoding="utf-8") == text  # nothing written


@pytest.mark.parametrize("kind", sorted(PAGES))
def test_bench_docs_refuses_an_ambiguous_page_before_the_run(kind, tmp_path, monkeypatch, capsys):
    text, line, marker = PAGES[kind]
    page = tmp_path / "p.md"
    page.write_text(text, encoding="utf-8")
    _no_run(monkeypatch)
    assert run_cli(bench_cli.main, "python -m camhealth.bench", TINY + ["--docs", str(page)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--docs {page}" in err[0] and line in err[0] and marker in err[0], err


def test_a_begin_marker_with_trailing_blanks_is_its_block(tmp_path):
    """It did not match, so a second block was appended and the old table stayed."""
    page = tmp_path / "p.md"
    page.write_text("<!-- generated: python -m x --> \t\nold\n" + END, encoding="utf-8")
    assert replace_generated(page, "python -m x", "NEW") is True
    assert page.read_text(encoding="utf-8") == "<!-- generated: python -m x --> \t\nNEW\n" + END


def test_crlf_page_keeps_its_line_endings(tmp_path):
    page = tmp_path / "p.md"
    original = b"# T\r\n\r\nprose\r\n\r\n<!-- generated: python -m x -->\r\nold\r\n<!-- end generated -->\r\n\r\nafter\r\n"
    page.write_bytes(original)
    assert replace_generated(page, "python -m x", "| a |\n| b |\n") is True
    assert page.read_bytes() == original.replace(b"old\r\n", b"| a |\r\n| b |\r\n")
    assert replace_generated(page, "python -m y", "new") is False
    data = page.read_bytes()
    assert data.endswith(b"after\r\n\r\n<!-- generated: python -m y -->\r\nnew\r\n<!-- end generated -->\r\n")
    assert b"\n" not in data.replace(b"\r\n", b"")


@pytest.mark.parametrize("name", ["pyproject.toml", "notes.txt", "page"])
def test_only_markdown_files_are_written(name, tmp_path, monkeypatch, capsys):
    target = tmp_path / name
    target.write_text("[tool]\nx = 1\n", encoding="utf-8")
    with pytest.raises(ValueError, match="not a Markdown file"):
        replace_generated(target, "python -m x", "NEW")
    assert target.read_text(encoding="utf-8") == "[tool]\nx = 1\n"
    _no_run(monkeypatch)
    assert run_cli(bench_cli.main, "python -m camhealth.bench", TINY + ["--docs", str(target)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--docs {target}" in err[0] and "not a Markdown file" in err[0], err


def test_a_command_with_a_quote_or_blank_is_written_so_it_parses_back(tmp_path, monkeypatch):
    """The command line was joined unquoted: `it's.png` broke every later write to the page, `a b.json` became two words."""
    seen = {}

    class Stop(Exception):
        pass

    real = bench_cli.load

    class Module:
        def __init__(self, name):
            m = real(name)
            self.HELP, self.add_arguments = m.HELP, m.add_arguments

        def run(self, args):
            seen["command"] = args.command_line
            raise Stop

    monkeypatch.setattr(bench_cli, "load", Module)
    with pytest.raises(Stop):
        bench_cli.main(TINY + ["--out", str(tmp_path / "it's a.md"), "--docs", str(tmp_path / "p.md")])
    assert shlex.split(seen["command"])[-2:] == ["--out", str(tmp_path / "it's a.md")]
    page = tmp_path / "p.md"
    assert replace_generated(page, seen["command"], "t") is False
    assert replace_generated(page, seen["command"], "u") is True
    assert [c for c, _, _ in generated_blocks(page.read_text(encoding="utf-8"))] == [seen["command"]]


def test_an_unparsable_command_is_refused_before_writing(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("intro\n", encoding="utf-8")
    with pytest.raises(ValueError, match="does not parse back"):
        replace_generated(page, "python -m x --src it's.png", "NEW")
    assert page.read_text(encoding="utf-8") == "intro\n"


def test_the_cli_reference_lists_every_benchmark_demo_and_subcommand():
    """It left out demo closed-loop, bench coldstart/policy/siemens_star, bench.library_reuse and docs' subcommands."""
    from camhealth.bench import BENCHMARKS
    from camhealth.demo import DEMOS, build_parser
    from camhealth.docs import CLI_COMMANDS

    build_parser()
    listed = set(CLI_COMMANDS)
    assert {("camhealth.bench", (b,)) for b in BENCHMARKS} <= listed
    assert {("camhealth.demo", (d,)) for d in DEMOS} <= listed
    assert {("camhealth.docs", (w,)) for w in ("cli", "api", "tables")} <= listed
    assert ("camhealth.bench.library_reuse", ()) in listed
