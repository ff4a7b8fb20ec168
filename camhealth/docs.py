"""camhealth's documentation, generated so it cannot drift from the code.

``python -m camhealth.docs cli [--out docs/cli.md]``
    The command-line reference: the ``--help`` of every ``python -m camhealth.<tool>`` (and of each benchmark),
    as the parsers print it.
``python -m camhealth.docs api --out DIR [--strict]``
    The API reference as HTML with `pdoc <https://pdoc.dev>`_ (the ``docs`` extra: ``pip install -e ".[docs]"``):
    every public module of ``camhealth``, ``datamodules`` and ``lightning_modules``; ``--strict`` turns every
    warning pdoc or an import raises into an error.
``python -m camhealth.docs tables FILE.md``
    Lists the generated blocks of a Markdown file: ``<!-- generated: COMMAND -->`` … ``<!-- end generated -->``.

Generated blocks are written by the command they name (``python -m camhealth.bench robustness --docs
docs/benchmarks.md``): :func:`replace_generated` puts the new text between the block's markers and leaves the rest of
the file as it is. ``python -m camhealth.evaluate --docs FILE`` writes a whole page instead, the results page
(``docs/results.md``): FILE is (re)written whole when it does not exist or its first line is the page's title
(``# camhealth evaluation: …``); any other existing FILE is refused (exit status 2, naming it) before the evaluation runs.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import os
import pkgutil
import re
import shlex
import sys
import warnings
from pathlib import Path
from typing import Sequence

__all__ = [
    "CLI_COMMANDS",
    "api_modules",
    "build_api",
    "cli_help",
    "check_command",
    "cli_reference",
    "command_key",
    "generated_blocks",
    "help_options",
    "main",
    "replace_generated",
]

#: The benchmarks of ``python -m camhealth.bench`` (as :data:`camhealth.bench.BENCHMARKS` lists them; a test checks
#: that this is every one).
_BENCHMARKS = ("calibrate", "classical", "coldstart", "corruption", "data", "estimators", "monitor", "mtf_error",
               "policy", "robustness", "siemens_star")

#: ``(module, arguments before --help)`` of every command line, in the order of the reference: each tool, each of
#: its subcommands (demos, benchmarks, the docs' own), and the stand-alone benchmark modules.
CLI_COMMANDS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("camhealth.fit", ()),
    ("camhealth.export", ()),
    ("camhealth.model_card", ()),
    ("camhealth.monitor", ()),
    ("camhealth.calibrate", ()),
    ("camhealth.corrupt", ()),
    ("camhealth.evaluate", ()),
    ("camhealth.iopc", ()),
    ("camhealth.demo", ()),
    ("camhealth.demo", ("closed-loop",)),
    ("camhealth.data.native_mtf", ()),
    ("camhealth.bench", ()),
    *(("camhealth.bench", (b,)) for b in _BENCHMARKS),
    ("camhealth.bench.library_reuse", ()),
    ("camhealth.docs", ()),
    *(("camhealth.docs", (w,)) for w in ("cli", "api", "tables")),
)

_TOP_LEVEL = ("camhealth", "datamodules", "lightning_modules")
#: A begin marker: a whole line (trailing blanks allowed), ``<!-- generated: COMMAND -->``.
_BEGIN = re.compile(r"<!-- generated: (?P<command>[^>]*?) -->[ \t]*$")
_BEGIN_START = "<!-- generated:"
_END = "<!-- end generated -->"
#: Suffixes of the Markdown files a generated block may be written into.
MARKDOWN_SUFFIXES = (".md", ".markdown")
_HELP_WIDTH = "100"


def _entry(module: str):
    """The ``main(argv)`` of a command's module (``python -m pkg`` runs ``pkg.__main__``)."""
    try:
        mod = importlib.import_module(module + ".__main__")
    except ModuleNotFoundError as exc:
        if exc.name != module + ".__main__":
            raise
        mod = importlib.import_module(module)
    return mod.main


def cli_help(module: str, args: Sequence[str] = ()) -> str:
    """What ``python -m <module> <args> --help`` prints, run in this process (terminal width 100 columns)."""
    before = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = _HELP_WIDTH
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
            try:
                _entry(module)([*args, "--help"])
            except SystemExit as exc:
                if exc.code not in (0, None):
                    raise RuntimeError(f"`python -m {module} {' '.join(args)} --help` exited with {exc.code}") from None
    finally:
        if before is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = before
    text = out.getvalue().rstrip()
    if not text:
        raise RuntimeError(f"`python -m {module} {' '.join(args)} --help` printed nothing")
    return text


def help_options(text: str) -> set[str]:
    """The long option names (``--name``) a ``--help`` text lists."""
    return set(re.findall(r"(?<![\w-])--[A-Za-z][\w.-]*", text)) - {"--help"}


def cli_reference() -> str:
    """The Markdown command-line reference: one section per command with its ``--help``."""
    lines = [
        "# Command-line reference",
        "",
        "Generated by `python -m camhealth.docs cli --out docs/cli.md` from the parsers themselves (a test checks",
        "that every option listed here is the command's and every option of the command is listed). Every command",
        "reports an error as one line and exit status 2; `--debug` shows the traceback instead.",
        "",
    ]
    for module, args in CLI_COMMANDS:
        command = " ".join(["python -m", module, *args])
        lines += [f"## `{command}`", "", "```text", cli_help(module, args), "```", ""]
    return "\n".join(lines)


def api_modules() -> list[str]:
    """Every public module of the three top-level packages (no ``_private`` or ``__main__`` modules)."""
    names = []
    for top in _TOP_LEVEL:
        pkg = importlib.import_module(top)
        names.append(top)
        for info in pkgutil.walk_packages(pkg.__path__, top + "."):
            if not any(part.startswith("_") for part in info.name.split(".")[1:]):
                names.append(info.name)
    return names


def build_api(out: str | Path, strict: bool = False) -> Path:
    """Write the HTML API reference of :func:`api_modules` to ``out`` with pdoc (reStructuredText docstrings).
    ``strict``: a warning raised while importing or rendering is an error naming the warning."""
    try:
        import pdoc
        import pdoc.render
    except ImportError:
        raise ImportError("the API reference needs pdoc: pip install -e \".[docs]\"") from None
    out = Path(out)
    pdoc.render.configure(docformat="restructuredtext", show_source=False, search=True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pdoc.pdoc(*api_modules(), output_directory=out)
    ours = [w for w in caught if not _foreign(w)]
    if strict and ours:
        listed = "; ".join(f"{w.category.__name__}: {w.message}" for w in ours[:5])
        raise RuntimeError(f"{len(ours)} warning(s) while building the API reference: {listed}")
    for w in ours:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return out


def _foreign(w: warnings.WarningMessage) -> bool:
    """Warnings raised inside third-party packages on import (their own deprecations), not about camhealth."""
    path = str(w.filename)
    return "site-packages" in path and not any(f"{os.sep}{top}{os.sep}" in path for top in _TOP_LEVEL)


def generated_blocks(text: str, source: str | Path = "") -> list[tuple[str, int, int]]:
    """``(command, start, end)`` of every generated block of a Markdown text (character offsets of its content).

    Markers are whole lines (trailing blanks and ``\r\n`` allowed; a marker quoted inside a line of prose is text).
    Begin and end markers must alternate: a begin marker before the previous block's end, an end marker without a
    begin, a block without an end, a begin marker that is not ``<!-- generated: COMMAND -->``, a command that does
    not parse as a command line, or two blocks of the same command (:func:`command_key`) raise ``ValueError`` naming
    ``source`` (when given), the line and the marker, so nothing is written into a page whose blocks are ambiguous."""
    where = f"{source}: " if str(source) else ""
    blocks: list[tuple[str, int, int]] = []
    seen: dict[tuple, int] = {}
    open_block: tuple[str, int, int] | None = None  # (command, content start, line number)
    pos = 0
    for number, line in enumerate(text.splitlines(keepends=True), start=1):
        stripped = line.rstrip("\r\n").rstrip(" \t")
        if stripped.startswith(_BEGIN_START):
            m = _BEGIN.fullmatch(stripped)
            if m is None:
                raise ValueError(f"{where}line {number}: malformed begin marker {stripped!r} "
                                 f"(write it as '<!-- generated: COMMAND -->' on a line of its own)")
            if open_block is not None:
                raise ValueError(f"{where}line {open_block[2]}: generated block `{open_block[0]}` has no end marker "
                                 f"{_END!r} before the next begin marker (line {number})")
            command = m.group("command")
            try:
                key = command_key(command)
            except ValueError as exc:
                raise ValueError(f"{where}line {number}: the command of the begin marker `{command}` does not parse "
                                 f"({exc})") from None
            if key in seen:
                raise ValueError(f"{where}line {number}: generated block `{command}` is a duplicate of the block on "
                                 f"line {seen[key]} (same command); remove one of them")
            seen[key] = number
            open_block = (command, pos + len(line), number)
        elif stripped == _END:
            if open_block is None:
                raise ValueError(f"{where}line {number}: end marker {_END!r} without a begin marker before it")
            blocks.append((open_block[0], open_block[1], pos))
            open_block = None
        pos += len(line)
    if open_block is not None:
        raise ValueError(f"{where}line {open_block[2]}: generated block `{open_block[0]}` has no end marker {_END!r}")
    return blocks


def check_command(command: str) -> None:
    """``ValueError`` when ``command`` cannot name a generated block: it does not parse back as a command line (an
    unbalanced quote), or it holds ``-->`` or a line break (it would end its marker early)."""
    if "\n" in command or "\r" in command or ">" in command:
        raise ValueError(f"the command line `{command}` cannot be written into a begin marker (it holds '>' or a line break)")
    try:
        command_key(command)
    except ValueError as exc:
        raise ValueError(f"the command line `{command}` does not parse back ({exc})") from None


#: Options that do not change a generated table: the table is the same Markdown with or without them.
_PRESENTATION_ONLY = {"--markdown": 0, "--out": 1, "--docs": 1}


def command_key(command: str) -> tuple:
    """What a command line runs, for matching a generated block: ``--opt=value`` and ``--opt value`` are one option,
    options may come in any order, ``--markdown``, ``--out FILE`` and ``--docs FILE`` (which only say where and how
    the table is written) are left out. Words before the first option (program, subcommand) keep their order."""
    words = shlex.split(command)
    head: list[str] = []
    groups: list[tuple[str, ...]] = []
    for w in words:
        if w.startswith("--"):
            name, eq, value = w.partition("=")
            groups.append((name, value) if eq else (name,))
        elif groups:
            groups[-1] = (*groups[-1], w)
        else:
            head.append(w)
    kept = []
    for g in groups:
        n = _PRESENTATION_ONLY.get(g[0])
        if n is None:
            kept.append(g)
        elif len(g) > 1 + n:  # a presentation flag followed by positional words: keep those words
            kept.append(("", *g[1 + n:]))
    return tuple(head), tuple(sorted(kept))


def replace_generated(path: str | Path, command: str, content: str) -> bool:
    """Replace the content of the block of ``path`` whose begin marker names ``command`` by ``content`` and return
    True; without such a block append a new one at the end and return False. The rest of the file is kept, byte for
    byte: a file with ``\r\n`` line endings keeps them (the new content is written with them too).

    Commands are matched by :func:`command_key` (``--frames=16`` matches ``--frames 16``, option order and
    ``--markdown`` do not matter); a block found so keeps its marker as written. A page whose blocks do not parse
    (:func:`generated_blocks`), a file that is not Markdown (``.md``) or a ``command`` that cannot be read back
    (:func:`check_command`) raise ``ValueError`` before anything is written."""
    path = Path(path)
    if path.suffix.lower() not in MARKDOWN_SUFFIXES:
        raise ValueError(f"{path}: not a Markdown file (the suffix is not {' or '.join(MARKDOWN_SUFFIXES)})")
    check_command(command)
    if path.exists():
        with open(path, encoding="utf-8", newline="") as fh:
            text = fh.read()
    else:
        text = ""
    blocks = generated_blocks(text, path)
    eol = "\r\n" if "\r\n" in text else "\n"
    body = content.replace("\r\n", "\n").rstrip("\n") + "\n"
    if eol != "\n":
        body = body.replace("\n", eol)
    key = command_key(command)
    found = [(start, end) for cmd, start, end in blocks if command_key(cmd) == key]  # (at most one: no duplicates)
    if found:
        start, end = found[0]
        new = text[:start] + body + text[end:]
    else:
        sep = "" if not text or text.endswith(eol + eol) else (eol if text.endswith("\n") else eol + eol)
        new = f"{text}{sep}<!-- generated: {command} -->{eol}{body}{_END}{eol}"
    with open(path, "w", encoding="utf-8", newline="") as fh:
        fh.write(new)
    return bool(found)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m camhealth.docs", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="what", required=True, metavar="{cli,api,tables}")
    c = sub.add_parser("cli", help="the command-line reference (Markdown)")
    c.add_argument("--out", type=Path, default=None, help="write it to this file (default: print it)")
    a = sub.add_parser("api", help="the API reference (HTML, pdoc)")
    a.add_argument("--out", type=Path, required=True, help="output folder")
    a.add_argument("--strict", action="store_true", help="any warning is an error")
    t = sub.add_parser("tables", help="list the generated blocks of a Markdown file and their commands")
    t.add_argument("file", type=Path)
    args = p.parse_args(argv)
    if args.what == "cli":
        text = cli_reference()
        if args.out is None:
            print(text)
        else:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(text, encoding="utf-8")
            print(args.out)
    elif args.what == "api":
        print(build_api(args.out, strict=args.strict))
    else:
        if args.file.is_dir():
            raise ValueError(f"{args.file}: is a folder; give a Markdown file")
        for command, start, end in generated_blocks(args.file.read_text(encoding="utf-8"), args.file):
            print(command)
    return 0


if __name__ == "__main__":  # pragma: no cover
    from camhealth._cli import run_cli

    sys.exit(run_cli(main, "python -m camhealth.docs"))
