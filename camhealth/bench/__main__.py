"""Command line: ``python -m camhealth.bench <benchmark> [--batch B --size S --repeats N --warmup N
--threads T --markdown --out FILE --docs FILE]``. Benchmarks are listed in :data:`camhealth.bench.BENCHMARKS`.

Each benchmark is a subcommand with ``--config FILE`` and ``--print_config`` after its name (before it, they cover
the whole command: the benchmark's options nested under its name, as LightningCLI's subcommands).

``--docs FILE`` writes the markdown table into FILE between the markers ``<!-- generated: COMMAND -->`` and
``<!-- end generated -->`` of the block whose command is this one (without ``--docs``; ``--opt=value`` and
``--opt value``, the options' order and ``--markdown`` do not matter), so a page's tables are regenerated in place
by the commands they name (:mod:`camhealth.docs`). Options are written in full (``--doc`` for ``--docs`` is an
error), and a ``--docs`` file that cannot be written (a folder, a missing folder, a page whose generated blocks do not
parse) is refused before the benchmark runs. So is a value out of its option's range and an option the chosen
benchmark, task or mode does not read (the table's header would record it as used): one line naming the option, the
value and what is allowed (the benchmark's ``check_options``, :func:`camhealth.bench.check_options`)."""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path
from typing import Sequence

from camhealth._cli import BadValue, add_debug_flag, config_parser, run_cli
from camhealth.bench import (  # noqa: F401 - (the bounds of the common options, defined with the benchmarks' own)
    BATCH_MAX, BENCHMARKS, REPEATS_MAX, SEED_MAX, SIZE_MAX, THREADS_MAX, WARMUP_MAX, check_options, format_table, load,
)


def _integer(value: str | int) -> int:
    if isinstance(value, (bool, float)):  # (a config file's true or 2.5 is no count)
        raise BadValue(f"must be an integer, got {value!r}")
    return int(value)


def _bounded(lo: int, hi: int):
    """Option type: an integer in [lo, hi], else :class:`BadValue` naming the value and the range."""

    def parse(value: str | int) -> int:
        try:
            n = _integer(value)
        except BadValue:
            raise BadValue(f"must be an integer, got {value!r} (allowed: {lo} … {hi})") from None
        except (TypeError, ValueError):
            raise BadValue(f"must be an integer, got {value!r} (allowed: {lo} … {hi})") from None
        if n < lo:
            raise BadValue(f"must be ≥ {lo}, got {n} (allowed: {lo} … {hi})")
        if n > hi:
            raise BadValue(f"must be ≤ {hi}, got {n} (allowed: {lo} … {hi})")
        return n

    parse.__name__ = f"int in [{lo}, {hi}]"
    return parse


def check_output_file(path: Path, option: str) -> None:
    """Refuse an output file (``--out``, ``--json``) before the benchmark runs: a folder, a path under a file, a
    folder that cannot be written (``BadValue`` naming the option and the path). A missing parent folder is made now."""
    if path.is_dir():
        raise BadValue(f"{option} {path}: is a folder; give a file name")
    if path.exists() and not path.is_file():
        raise BadValue(f"{option} {path}: not a regular file")
    parent = path.parent
    existing = parent
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise BadValue(f"{option} {path}: {existing} is a file, where a folder was expected")
    if path.exists():
        if not os.access(path, os.W_OK):
            raise BadValue(f"{option} {path}: the file cannot be written (permissions)")
    elif not os.access(existing, os.W_OK | os.X_OK):
        raise BadValue(f"{option} {path}: the file cannot be created in {existing} (permissions)")
    parent.mkdir(parents=True, exist_ok=True)


def check_docs_file(path: Path, command: str | None = None) -> None:
    """Refuse a ``--docs`` target the table could not be written to, before the benchmark runs: a folder, a file in
    a folder that does not exist, a file that is not Markdown (``.md``), cannot be written or whose generated blocks
    do not parse (a block without its end marker, an end marker without a block, two blocks of one command: the line
    and the marker are named), and a ``command`` that could not be read back from a marker (``BadValue`` naming the
    path; exit status 2)."""
    from camhealth.docs import MARKDOWN_SUFFIXES, check_command, generated_blocks

    if path.is_dir():
        raise BadValue(f"--docs {path}: is a folder; give a Markdown file (its generated block is written there)")
    parent = path.parent
    if not parent.is_dir():
        raise BadValue(f"--docs {path}: the folder {parent} does not exist (create it, or give another file)")
    if path.suffix.lower() not in MARKDOWN_SUFFIXES:
        raise BadValue(f"--docs {path}: not a Markdown file (the suffix is not {' or '.join(MARKDOWN_SUFFIXES)}); "
                       "give a Markdown file")
    if command is not None:
        try:
            check_command(command)
        except ValueError as exc:
            raise BadValue(f"--docs {path}: {exc}") from None
    if path.exists():
        if not path.is_file():
            raise BadValue(f"--docs {path}: not a regular file; give a Markdown file")
        if not os.access(path, os.R_OK | os.W_OK):
            raise BadValue(f"--docs {path}: the file cannot be read and written (permissions)")
        try:
            with open(path, encoding="utf-8", newline="") as fh:
                generated_blocks(fh.read())
        except UnicodeDecodeError as exc:
            raise BadValue(f"--docs {path}: not a UTF-8 text file ({exc.reason} at byte {exc.start})") from None
        except ValueError as exc:
            raise BadValue(f"--docs {path}: {exc}") from None
    elif not os.access(parent, os.W_OK | os.X_OK):
        raise BadValue(f"--docs {path}: the file cannot be created in {parent} (permissions)")


def _without_docs(argv: Sequence[str]) -> list[str]:
    """The command line less ``--docs FILE`` (the block's name is the command that makes it)."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == "--docs":
            skip = True
        elif not a.startswith("--docs="):
            out.append(a)
    return out


def build_parser():
    """jsonargparse parser with one subcommand per benchmark (each with the common options and its module's own)."""
    # allow_abbrev=False: an option is its whole name (``--doc`` is no ``--docs``), so the command line a --docs block is
    # named by is the command as every other spelling of it writes it
    parser = config_parser(prog="python -m camhealth.bench", description=__doc__, formatter_class=argparse.HelpFormatter,
                           allow_abbrev=False)
    sub = parser.add_subcommands(dest="benchmark", required=True, metavar="BENCHMARK")
    for name in BENCHMARKS:
        module = load(name)
        p = config_parser(prog=f"python -m camhealth.bench {name}", description=module.HELP,
                          formatter_class=argparse.HelpFormatter,  # (argparse's help, as the benchmarks' own texts expect)
                          allow_abbrev=False)
        p.add_argument("--batch", type=_bounded(1, BATCH_MAX), default=32, help=f"batch size B, 1…{BATCH_MAX} (default 32)")
        p.add_argument("--size", type=_bounded(1, SIZE_MAX), default=192,
                       help=f"image side H = W in px, 1…{SIZE_MAX} (default 192)")
        p.add_argument("--repeats", type=_bounded(1, REPEATS_MAX), default=20,
                       help=f"timed repeats per row, 1…{REPEATS_MAX} (default 20)")
        p.add_argument("--warmup", type=_bounded(0, WARMUP_MAX), default=2,
                       help=f"untimed warm-up calls per row, 0…{WARMUP_MAX} (default 2)")
        p.add_argument("--threads", type=_bounded(1, THREADS_MAX), default=None,
                       help="torch intra-op threads, 1…4 × the CPU count (default: torch's)")
        p.add_argument("--seed", type=_bounded(0, SEED_MAX), default=0,
                       help="seed of the batch and of the parameters, 0…2**32 − 1 (default 0)")
        p.add_argument("--markdown", action="store_true", help="print a markdown table")
        p.add_argument("--out", type=Path, default=None, help="append the markdown table to FILE (created if missing)")
        p.add_argument("--docs", type=Path, default=None,
                       help="write the markdown table into FILE's generated block of this command (appended if none)")
        module.add_arguments(p)
        sub.add_subcommand(name, p, help=module.HELP)
    add_debug_flag(parser)
    return parser


def parse(argv: Sequence[str] | None = None):
    """The chosen benchmark's options (a namespace with ``benchmark``, its name, added) from ``argv``."""
    args = build_parser().parse_args(argv)
    options = args[args.benchmark]
    options.benchmark = args.benchmark
    return options


def main(argv: Sequence[str] | None = None) -> int:
    args = parse(argv)
    # the benchmark's checks of its options against each other (an option its task does not read, …), before anything
    check_options(args)
    # shlex.join: an argument with a blank or a quote is written so the command parses back as the same words
    args.command_line = "python -m camhealth.bench " + shlex.join(_without_docs(sys.argv[1:] if argv is None else argv))
    # every output is checked now, not after a benchmark of minutes
    if args.docs is not None:
        check_docs_file(args.docs, args.command_line)
    if args.out is not None:
        check_output_file(args.out, "--out")
    if getattr(args, "json", None) is not None:
        check_output_file(args.json, "--json")
    import torch

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    result = load(args.benchmark).run(args)
    print(format_table(result, markdown=args.markdown), flush=True)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with args.out.open("a", encoding="utf-8") as fh:
            fh.write(format_table(result, markdown=True) + "\n\n")
        print(f"\nappended the markdown table to {args.out}")
    if args.docs is not None:
        from camhealth.docs import replace_generated

        replaced = replace_generated(args.docs, args.command_line, format_table(result, markdown=True))
        print(f"\n{'replaced' if replaced else 'added'} the generated block `{args.command_line}` in {args.docs}")
    return 0


if __name__ == "__main__":  # a bad value is one line and exit status 2 (--debug: the traceback)
    raise SystemExit(run_cli(main, "python -m camhealth.bench"))
