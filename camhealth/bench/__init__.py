"""Benchmarks: ``python -m camhealth.bench <name> [options]``.

Each benchmark is a module registered in :data:`BENCHMARKS` (name → module path) that provides

* ``HELP`` — one line for ``--help``;
* ``add_arguments(parser)`` — its own options (the common ones are added by the CLI);
* ``run(args) -> BenchResult`` — the measurement.

and optionally

* ``check_options(args)`` — its checks of the options against each other (an option the chosen task or mode does not
  read, a count too large for the other options), a ``ValueError`` naming the option, the value and what is allowed;
  the CLI calls it before any output file is checked or the benchmark starts (:func:`check_options`).

Add a benchmark (e.g. ``estimators``, ``data``) by writing such a module and adding one line here. The
table formatting (plain text and markdown) is shared, and so are the option types with a range (:class:`IntRange`,
:class:`FloatRange`) and the refusal of options a task ignores (:func:`refuse_unread`).
"""

from __future__ import annotations

import argparse
import importlib
import math
import os
import statistics
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any, Callable, Iterable, Sequence

from camhealth._cli import BadValue, FloatRange, IntRange

__all__ = ["BENCHMARKS", "Row", "BenchResult", "load", "timing_stats", "format_table", "add_allocator_argument", "apply_allocator",
           "IntRange", "FloatRange", "check_count", "check_options", "refuse_unread", "shown", "option_defaults",
           "option_message", "check_device_option", "COMMON_DEFAULTS", "SEED_MAX", "THREADS_MAX", "BATCH_MAX", "SIZE_MAX", "REPEATS_MAX",
           "WARMUP_MAX"]

#: Largest ``--seed``: the benchmarks' generators take seeds (and seeds derived from them) below 2**32.
SEED_MAX = 2**32 - 1
#: Largest ``--threads``: more torch threads than this only oversubscribes the CPU (and a huge count crashed torch).
THREADS_MAX = 4 * (os.cpu_count() or 1)
#: Largest ``--batch``, ``--size``, ``--repeats`` and ``--warmup``: generous, far beyond any table of the docs, short
#: of runs that would take days or all the memory. ``SIZE_MAX`` also bounds the benchmarks' own patch sizes.
BATCH_MAX, SIZE_MAX, REPEATS_MAX, WARMUP_MAX = 4096, 4096, 100_000, 10_000

#: Registered benchmarks: CLI name → module implementing ``HELP``, ``add_arguments`` and ``run``.
BENCHMARKS: dict[str, str] = {
    "calibrate": "camhealth.bench.calibrate",
    "corruption": "camhealth.bench.corruption",
    "data": "camhealth.bench.data",
    "classical": "camhealth.bench.classical",
    "coldstart": "camhealth.bench.coldstart",
    "estimators": "camhealth.bench.estimators",
    "monitor": "camhealth.bench.monitor",
    "mtf_error": "camhealth.bench.mtf_error",
    "policy": "camhealth.bench.policy",
    "robustness": "camhealth.bench.robustness",
    "siemens_star": "camhealth.bench.siemens_star",
}


def load(name: str) -> ModuleType:
    """Import the module of benchmark ``name`` (``ValueError`` listing the known ones otherwise)."""
    if name not in BENCHMARKS:
        raise ValueError(f"unknown benchmark {name!r}; known: {sorted(BENCHMARKS)}")
    return importlib.import_module(BENCHMARKS[name])


def check_count(option: str, value: Any, lo: int, hi: int, why_lo: str = "") -> None:
    """``ValueError`` naming ``option`` and ``value`` where it is no integer in [lo, hi] (``why_lo``: the reason for
    ``lo``, written after it): ``--frames must be >= 1, got 0 (allowed: 1 … 1000)``."""
    allowed = f"(allowed: {lo} … {hi})"
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{option} must be an integer, got {value!r} {allowed}")
    if value < lo:
        raise ValueError(f"{option} must be >= {lo}{why_lo}, got {value} {allowed}")
    if value > hi:
        raise ValueError(f"{option} must be <= {hi}, got {value} {allowed}")


#: The common options every benchmark's parser has that a benchmark may not read, and their defaults: a module lists
#: those it reads in ``COMMON_READS`` (all of them where it has none); one set away from its default that the
#: benchmark does not read is refused (:func:`check_options`), since the table's header would record it as used.
COMMON_DEFAULTS: dict[str, Any] = {"batch": 32, "size": 192, "repeats": 20, "warmup": 2, "seed": 0}


def check_options(args) -> None:
    """Refuse a common option (:data:`COMMON_DEFAULTS`) set away from its default that the module of benchmark
    ``args.benchmark`` does not read (its ``COMMON_READS``), naming it; then run the module's own
    ``check_options(args)``, where it has one (module docstring)."""
    module = load(args.benchmark)
    reads = getattr(module, "COMMON_READS", tuple(COMMON_DEFAULTS))
    for dest, default in COMMON_DEFAULTS.items():
        if dest not in reads and getattr(args, dest, default) != default:
            read = ", ".join("--" + r for r in reads) or "none"
            raise ValueError(f"--{dest} {shown(getattr(args, dest))} is not used by `python -m camhealth.bench "
                             f"{args.benchmark}` (of the common options it reads {read}); leave it out")
    check = getattr(module, "check_options", None)
    if check is not None:
        check(args)


def shown(value: Any) -> str:
    """An option's value as it is typed: list items separated by blanks, numbers without a trailing ``.0``."""
    if isinstance(value, (list, tuple)):
        return " ".join(shown(v) for v in value)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def option_defaults(add_arguments: Callable[[argparse.ArgumentParser], None]) -> dict[str, tuple[str, Any]]:
    """``dest → (option, default)`` of every option that ``add_arguments`` adds (the defaults its parser gives)."""
    parser = argparse.ArgumentParser(add_help=False)
    add_arguments(parser)
    defaults = vars(parser.parse_args([]))
    return {a.dest: (a.option_strings[0], defaults[a.dest]) for a in parser._actions if a.option_strings}


def refuse_unread(args, add_arguments: Callable[[argparse.ArgumentParser], None], reads: Iterable[str],
                  where: str) -> None:
    """``ValueError`` naming the first option of ``add_arguments`` that is set away from its default in ``args`` while
    ``where`` (``--task jpeg``, …) does not read it (``reads``: the destinations it reads): the table's header would
    record the option as if it had been used. An attribute ``args`` lacks counts as the default (``run`` called
    directly with a namespace of the options it reads)."""
    reads = set(reads)
    for dest, (option, default) in option_defaults(add_arguments).items():
        if dest in reads or not hasattr(args, dest):
            continue
        value = getattr(args, dest)
        if value != default:
            what = option if isinstance(default, bool) else f"{option} {shown(value)}".rstrip()
            raise ValueError(f"{what} is not used by {where}; leave it out")


def option_message(exc: BaseException, name: str, option: str, value: Any) -> str:
    """``exc``'s message with the parameter ``name`` (``name = 'x'``, ``name='x'``, ``name='cpu'``) written as the
    option is typed (``option x``): what a library function says about an argument, said of the command line's option."""
    text = str(exc)
    for v in dict.fromkeys((value, "cpu")):
        text = text.replace(f"{name} = {v!r}", f"{option} {v}").replace(f"{name}={v!r}", f"{option} {v}")
    return text


def check_device_option(device: Any, option: str = "--device") -> None:
    """``ValueError`` naming ``option`` and its value where ``device`` is no device of this machine
    (:func:`camhealth.inference.check_device`), before any work."""
    from camhealth.inference import check_device

    try:
        check_device(device)
    except (TypeError, ValueError) as exc:
        raise ValueError(option_message(exc, "device", option, device)) from None


def add_allocator_argument(parser) -> None:
    """``--default-malloc`` of the benchmarks that time the training data path (as ``camhealth.fit`` runs it)."""
    parser.add_argument(
        "--default-malloc",
        action="store_true",
        help="leave glibc's allocator settings alone (default: keep freed memory for reuse, as camhealth.fit does)",
    )


def apply_allocator(args) -> str:
    """Keep freed memory for reuse unless ``--default-malloc`` (``camhealth.runtime``); returns the header line
    with the process's actual setting (it cannot be undone once applied, e.g. by an earlier run in-process)."""
    from camhealth.runtime import freed_memory_kept, keep_freed_memory

    if not getattr(args, "default_malloc", False):
        keep_freed_memory()
    if freed_memory_kept():
        how = "" if not getattr(args, "default_malloc", False) else " (set earlier in this process; --default-malloc cannot undo it)"
        return f"allocator: freed memory kept for reuse (camhealth.runtime.keep_freed_memory, as in camhealth.fit){how}"
    return "allocator: glibc defaults"


def timing_stats(times_ms: Sequence[float]) -> tuple[float, float, float]:
    """(median, first quartile, third quartile) of a list of timings [ms]."""
    xs = sorted(times_ms)
    if not xs:
        return float("nan"), float("nan"), float("nan")
    if len(xs) == 1:
        return xs[0], xs[0], xs[0]
    q1, _, q3 = statistics.quantiles(xs, n=4, method="inclusive")
    return statistics.median(xs), q1, q3


@dataclass
class Row:
    """One timed item: ``times_ms`` per repeat (already scaled to the full batch), a ``ratio`` to the
    baseline row (filled by :class:`BenchResult`), an optional ``speedup`` (loop time / vectorised time)
    with what it compares in ``speedup_of``, and a free-text ``note``."""

    name: str
    times_ms: list[float]
    note: str = ""
    speedup: float | None = None
    speedup_of: str = ""
    ratio: float | None = None

    @property
    def median_ms(self) -> float:
        return timing_stats(self.times_ms)[0]

    @property
    def iqr_ms(self) -> tuple[float, float]:
        _, q1, q3 = timing_stats(self.times_ms)
        return q1, q3


@dataclass
class BenchResult:
    """Rows plus the name of the baseline row for the ratio column, header lines and summary lines."""

    title: str
    rows: list[Row]
    baseline: str
    header: list[str] = field(default_factory=list)
    summary: list[str] = field(default_factory=list)

    def row(self, name: str) -> Row:
        for r in self.rows:
            if r.name == name:
                return r
        raise KeyError(name)

    def fill_ratios(self) -> None:
        base = self.row(self.baseline).median_ms
        for r in self.rows:
            r.ratio = r.median_ms / base if base > 0 else float("nan")


def _fmt(x: float | None, spec: str) -> str:
    return "–" if x is None or x != x else format(x, spec)


def format_table(result: BenchResult, markdown: bool = False) -> str:
    """The result as a plain-text or markdown table, with header and summary lines."""
    result.fill_ratios()
    cols = ["row", "ms/batch (median)", "IQR [ms]", f"× {result.baseline}", "speed-up", "note"]
    body = []
    for r in result.rows:
        q1, q3 = r.iqr_ms
        speed = "" if r.speedup is None else f"{r.speedup:.0f}× ({r.speedup_of})" if r.speedup >= 10 else f"{r.speedup:.1f}× ({r.speedup_of})"
        body.append([r.name, _fmt(r.median_ms, ".1f"), f"{_fmt(q1, '.1f')}–{_fmt(q3, '.1f')}", _fmt(r.ratio, ".2f"), speed, r.note])
    lines: list[str] = []
    if markdown:
        lines += [f"### {result.title}", ""] + [f"{h}  " for h in result.header] + [""]
        lines.append("| " + " | ".join(cols) + " |")
        lines.append("|" + "|".join(["---", "---:", "---:", "---:", "---:", "---"]) + "|")
        lines += ["| " + " | ".join(c.replace("|", "\\|") for c in row) + " |" for row in body]
        tables = any(s.lstrip().startswith("|") for s in result.summary)  # summaries with their own tables print as they are
        lines += [""] + (list(result.summary) if tables else [f"- {s}" for s in result.summary])
    else:
        widths = [max(len(cols[i]), *(len(row[i]) for row in body)) for i in range(len(cols))]
        align = ["<", ">", ">", ">", "<", "<"]
        fmt_row = lambda row: "  ".join(f"{c:{a}{w}}" for c, a, w in zip(row, align, widths)).rstrip()  # noqa: E731
        lines += [result.title, "=" * len(result.title)] + result.header + [""]
        lines += [fmt_row(cols), fmt_row(["-" * w for w in widths])] + [fmt_row(row) for row in body]
        lines += [""] + result.summary
    return "\n".join(lines)
