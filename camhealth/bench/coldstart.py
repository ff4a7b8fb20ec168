"""``python -m camhealth.bench coldstart``: how long a fresh process takes to its first monitor report.

Every repeat starts new interpreters (nothing is cached in-process; the OS file cache is warm after the first):

* ``python -c pass`` — the interpreter alone (the floor of every row);
* ``import camhealth.monitor`` — the interpreter plus the monitor's imports (torch and camhealth; neither Lightning
  nor Kornia is imported);
* ``CLI → first report`` — ``python -m camhealth.monitor SOURCE --max-frames 1 --sensor ICX285 --threads T
  --noise-model N`` until its first JSON line is on stdout (what a robot's launch waits for);
* the phases of the same work through the API in one process (``camhealth.monitor.Monitor``; default models):
  ``import``, ``load estimators`` (the constructor), ``first frame`` (``process`` of the first frame: on the first
  frame of a size the monitor runs each network once per padded batch size so that oneDNN builds its kernels then,
  :class:`Monitor` ``warmup``) and ``frame, kernels built`` (a second monitor with ``warmup=False`` on the same
  frame in the same process, where oneDNN's kernels exist). ``kernel warm-up`` is the difference of the two.

The summary gives ``CLI → first report`` minus the median warm-up: the cold start excluding the warm-up of the
kernels, with the warm-up reported beside it. Whether ``lightning`` was imported is checked in the API process.
``--batch``/``--size``/``--warmup``/``--seed`` of the common options are not used (set, they are refused);
``--repeats`` is the number of fresh processes per row (default 5 here; any value given, 20 included, is used). ``--source FILE`` is a path relative to
the folder the command runs in (the child processes run in the repository root, so it is made absolute first) and
must be an existing image file.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from camhealth.bench import BenchResult, Row, check_count, timing_stats

HELP = "cold start of the monitor: a fresh process to its first report (imports, model loading, kernel warm-up)"

#: The common options this benchmark reads (the others are refused: camhealth.bench.check_options).
COMMON_READS = ('repeats',)

ROOT = Path(__file__).resolve().parents[2]

PHASES_SCRIPT = r"""
import json, sys, time
t0 = time.perf_counter()
import torch
from camhealth.monitor import Monitor
t1 = time.perf_counter()
torch.set_num_threads({threads})
frame = {frame}
t2 = time.perf_counter()
cold = Monitor(noise_model={noise!r}, sensor="ICX285")
t3 = time.perf_counter()
cold.process(frame)
t4 = time.perf_counter()
warm = Monitor(noise_model={noise!r}, sensor="ICX285", warmup=False)  # oneDNN's kernels are built now
t5 = time.perf_counter()
warm.process(frame)
t6 = time.perf_counter()
leaked = sorted({{n.split(".")[0] for n in sys.modules}} & {{"lightning", "lightning_modules", "datamodules"}})
print(json.dumps({{"import": t1 - t0, "load": t3 - t2, "first": t4 - t3, "frame": t6 - t5, "leaked": leaked}}))
"""


#: Fresh processes per row unless --repeats says otherwise (the common default, 20, is for in-process timings).
DEFAULT_REPEATS = 5


def resolve_source(value: str) -> str:
    """``--source``: ``"street"`` as it is, else the image file as an absolute path (a relative one is relative to the
    folder the command runs in, not to the repository root the child processes run in); ``BadValue`` naming the
    value when there is no such file."""
    from camhealth._cli import BadValue

    if value == "street":
        return value
    path = Path(value).expanduser()
    if not path.is_file():
        raise BadValue(f"no such image file: {value} ({'a folder' if path.is_dir() else 'not found'}, relative to "
                       f"{Path.cwd()}); give an image file or 'street'")
    return str(path.resolve())


#: Most ``--repeats`` here (the common bound is for calls of milliseconds): 40× the docs' 5. A repeat starts four fresh
#: interpreters, ≈ 4 s on the docs' machine, so 200 take ≈ 13 min.
REPEATS_MAX = 200


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--source", type=resolve_source, default="street",
                        help="an image file (relative to the current folder), or 'street' (default: the embedded "
                             "clip's first frame, 768×576)")
    parser.add_argument("--noise-model", default="noise_source_full",
                        help="noise estimator of the monitor (default noise_source_full, the monitor's default)")
    # its own default: the common --repeats default (20) cannot be told from an explicit --repeats 20
    parser.set_defaults(repeats=DEFAULT_REPEATS)
    for action in parser._actions:
        if action.dest == "repeats":
            action.help = f"fresh processes per row, 1…{REPEATS_MAX} (default {DEFAULT_REPEATS})"


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def _wall(cmd: list[str]) -> float:
    """Seconds from starting ``cmd`` to its exit (``RuntimeError`` with its stderr if it fails)."""
    t = time.perf_counter()
    run = subprocess.run(cmd, cwd=ROOT, env=_env(), capture_output=True, text=True)
    if run.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {run.stderr.strip()[-500:]}")
    return time.perf_counter() - t


def _first_report(cmd: list[str]) -> float:
    """Seconds from starting ``cmd`` to the first line on its stdout; the process is then let finish."""
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    dt = time.perf_counter() - t
    _, err = proc.communicate()
    if proc.returncode != 0 or not line.startswith("{"):
        raise RuntimeError(f"{' '.join(cmd)} gave no report (exit {proc.returncode}): {err.strip()[-500:]}")
    return dt


def _frame_expr(source: str) -> str:
    if source == "street":
        return "next(iter(__import__('camhealth.data', fromlist=['street_sequence']).street_sequence(max_frames=1)))[0]"
    return f"__import__('camhealth.data.io', fromlist=['read_image']).read_image({source!r})"


def check_options(args: argparse.Namespace) -> None:
    """``ValueError`` naming ``--repeats`` and its value where it is more than :data:`REPEATS_MAX` fresh processes."""
    check_count("--repeats", args.repeats, 1, REPEATS_MAX)


def run(args: argparse.Namespace) -> BenchResult:
    check_options(args)
    repeats = args.repeats
    try:
        source = resolve_source(args.source)  # (the parser did this already; run() may be called with a namespace)
    except ValueError as exc:
        raise ValueError(f"--source: {exc}") from None
    threads = args.threads or 2
    py = sys.executable
    cli = [py, "-m", "camhealth.monitor", source, "--max-frames", "1", "--sensor", "ICX285", "--threads",
           str(threads), "--no-progress", "--noise-model", args.noise_model]
    phases_script = PHASES_SCRIPT.format(threads=threads, noise=args.noise_model, frame=_frame_expr(source))
    cols: dict[str, list[float]] = {k: [] for k in ("pass", "import", "cli", "p_import", "p_load", "p_first", "p_frame",
                                                    "p_warmup")}
    leaked: set[str] = set()
    for _ in range(repeats):  # round robin: a drift of the machine's load hits every row alike
        cols["pass"].append(_wall([py, "-c", "pass"]))
        cols["import"].append(_wall([py, "-c", "import camhealth.monitor"]))
        cols["cli"].append(_first_report(cli))
        run_ = subprocess.run([py, "-c", phases_script], cwd=ROOT, env=_env(), capture_output=True, text=True)
        if run_.returncode != 0:
            raise RuntimeError(f"the API phases script failed: {run_.stderr.strip()[-500:]}")
        ph = json.loads(run_.stdout.strip().splitlines()[-1])
        for k in ("import", "load", "first", "frame"):
            cols[f"p_{k}"].append(ph[k])
        cols["p_warmup"].append(ph["first"] - ph["frame"])
        leaked |= set(ph["leaked"])
    ms = {k: [1e3 * x for x in v] for k, v in cols.items()}
    rows = [
        Row("python -c pass", ms["pass"], "interpreter start"),
        Row("import camhealth.monitor", ms["import"], "fresh process, exits after the imports"),
        Row("CLI → first report", ms["cli"], f"{' '.join(cli[1:])}"),
        Row("API: import", ms["p_import"], "torch + camhealth.monitor, in the API process"),
        Row("API: load estimators", ms["p_load"], f"Monitor(noise_model={args.noise_model!r}, mtf_model='mtf')"),
        Row("API: first frame", ms["p_first"], "process() of the first frame, kernel warm-up included"),
        Row("API: frame, kernels built", ms["p_frame"], "the same frame, a second Monitor(warmup=False)"),
        Row("API: kernel warm-up", ms["p_warmup"], "first frame − frame with the kernels built"),
    ]
    cli_med = timing_stats(ms["cli"])[0]
    warm_med = timing_stats(ms["p_warmup"])[0]
    return BenchResult(
        title="Monitor cold start (fresh processes)",
        rows=rows,
        baseline="python -c pass",
        header=[
            f"repeats: {repeats} fresh processes per row; torch threads {threads}; source {source!r}; "
            f"noise model {args.noise_model!r}",
            f"lightning / lightning_modules / datamodules imported by the API process: {sorted(leaked) or 'none'}",
        ],
        summary=[
            f"CLI → first report {cli_med:.0f} ms (median), of which kernel warm-up ≈ {warm_med:.0f} ms: "
            f"{cli_med - warm_med:.0f} ms to the first report excluding the warm-up",
            f"fastest CLI run {min(ms['cli']):.0f} ms",
        ],
    )
