"""``python -m camhealth.bench policy``: the exposure/gain policy's look-up table against the direct objective.

:class:`~camhealth.control.ExposurePolicy` decides from a precomputed table ``table[σ̂, MTF̂, ρ, α]`` of the weighted
AP (Eq. 4.7/4.8), interpolated trilinearly between its nodes. This benchmark draws ``--decisions`` random decisions
inside what the IOPC measured — σ̂ uniform in [0, the last σ bin's upper edge] DN, MTF̂ uniform between the end of the
MTF → motion-length relation and 1, ρ uniform in [0, 1], exposure log-uniform and gain uniform within the camera
limits — and scores each table resolution against the **direct objective** (:meth:`ExposurePolicy.objective`: the
same IOPC interpolation evaluated at the exact σ̂, MTF̂, ρ, maximised over the same α candidates — the grid α inside
the limits plus the α that put exposure or gain exactly on a limit):

* *loss* — direct AP at the direct objective's best α minus direct AP at the table's α [AP]: what the table's
  decision gives away (≥ 0 up to the log-α interpolation of a limit α; max, p99, mean);
* *other α* — share of decisions whose α differs from the direct objective's;
* *|expected − direct|* — the table's predicted AP at its α against the direct objective's there (max).

Rows: the default table, one at half and one at twice its resolution, and the direct objective itself (no table) as
the reference. ms/batch is the time of ``--decisions`` decisions, so it reads as µs per decision at the default 1000;
the table's build time and size are in the note. ``--batch``/``--size`` of the common options are not used;
``--repeats``/``--warmup`` time the decisions.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from camhealth.bench import BenchResult, Row

HELP = "exposure/gain policy: loss of the look-up table's decision against the direct objective, and µs per decision"

#: The common options this benchmark reads (the others are refused: camhealth.bench.check_options).
COMMON_READS = ('repeats', 'seed', 'warmup')

DEFAULT_IOPC = "runs/iopc_closed_loop/iopc.json"
#: Fewest ``--decisions`` (the loss statistics of each table, its p99 among them, are taken over them).
DECISIONS_MIN = 10
#: Most ``--decisions``: 100× the default 1000. A decision costs ≈ 3 ms of work at the default --repeats (the direct
#: objective once for the reference, 3 tables × 22 timed rounds of ≈ 30 µs, the direct row's 6 rounds of ≈ 0.15 ms), so
#: 100 000 take ≈ 5 min.
DECISIONS_MAX = 100_000


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--iopc", type=Path, default=Path(DEFAULT_IOPC),
                        help=f"IOPC file of a sweep (default {DEFAULT_IOPC}: "
                             "python -m camhealth.iopc --config configs/iopc.yaml --config configs/iopc_closed_loop.yaml)")
    parser.add_argument("--decisions", type=int, default=1000,
                        help=f"random decisions scored and timed, {DECISIONS_MIN}…{DECISIONS_MAX} (default 1000)")


def check_options(args: argparse.Namespace) -> None:
    """``ValueError`` naming ``--decisions`` and its value where it is no integer in [:data:`DECISIONS_MIN`,
    :data:`DECISIONS_MAX`]."""
    n = args.decisions
    if not (isinstance(n, int) and not isinstance(n, bool) and DECISIONS_MIN <= n <= DECISIONS_MAX):
        bound = f"<= {DECISIONS_MAX}" if isinstance(n, int) and n > DECISIONS_MAX else f">= {DECISIONS_MIN}"
        raise ValueError(f"--decisions = {n!r} must be an integer {bound} (allowed: {DECISIONS_MIN} … {DECISIONS_MAX})")


def _inputs(pol: Any, n: int, seed: int) -> list[tuple[float, float, float, float, float]]:
    """n random (σ̂ [DN], MTF̂, ρ, exposure [s], gain [dB]) inside the IOPCs and the camera limits."""
    rng = np.random.default_rng(seed)
    top = min(float(a.iopc.sigma_bins[-1] + 0.5 * np.diff(a.iopc.sigma_bins)[-1]) for a in pol.apps)
    least = max(float(a.iopc.blur_mtf[-1]) for a in pol.apps)
    (t0, t1), (g0, g1) = pol.limits.exposure_s, pol.limits.gain_db
    return [(float(rng.uniform(0.0, top)), float(rng.uniform(least, 1.0)), float(rng.uniform(0.0, 1.0)),
             float(math.exp(rng.uniform(math.log(t0), math.log(t1)))), float(rng.uniform(g0, g1)))
            for _ in range(n)]


def _direct(pol: Any, s: float, m: float, rho: float, t: float, g: float) -> tuple[float, float]:
    """(α, AP) maximising the direct objective over the decision's candidates (grid α inside the limits, and the α that
    put exposure or gain exactly on a limit); ties go to the α closest to 1, as in ``decide``."""
    lo, hi = pol._alpha_limits(t, g)
    ok = pol.feasible(t, g)
    cand = list(pol.alphas[ok]) + [min(max(lo, pol.alphas[0]), pol.alphas[-1]), max(min(hi, pol.alphas[-1]), pol.alphas[0])]
    cand = np.asarray(cand, dtype=np.float64)
    vals = pol.objective(s, m, cand, rho)
    best = float(vals.max())
    near = cand[vals >= best - 1e-6]
    return float(near[np.argmin(np.abs(np.log(near)))]), best


def run(args: argparse.Namespace) -> BenchResult:
    from camhealth.bench.corruption import _load, _time_round_robin, machine_description
    from camhealth.control import ExposurePolicy
    from camhealth.iopc import IOPC

    check_options(args)
    if not args.iopc.is_file():
        raise ValueError(f"--iopc {args.iopc}: no such file (make it with python -m camhealth.iopc --config configs/iopc.yaml "
                         "--config configs/iopc_closed_loop.yaml, or give the iopc.json of another sweep)")
    iopc = IOPC.load(args.iopc)
    load_before = _load()
    t_build = time.perf_counter()
    default = ExposurePolicy(iopc)
    build_s = {"default": time.perf_counter() - t_build}
    step = default.sigma_step
    variants = {"table, default resolution": (default, build_s["default"])}
    for name, kw in (("table, half the resolution", {"sigma_step_dn": 2 * step, "mtf_step": 0.02, "rho_levels": 3}),
                     ("table, twice the resolution", {"sigma_step_dn": step / 2, "mtf_step": 0.005, "rho_levels": 9})):
        t = time.perf_counter()
        pol = ExposurePolicy(iopc, **kw)
        variants[name] = (pol, time.perf_counter() - t)
    inputs = _inputs(default, args.decisions, args.seed)
    reference = [_direct(default, s, m, r, t, g) for s, m, r, t, g in inputs]
    rows: list[Row] = []
    summary: list[str] = []
    fns = {name: (lambda pol=pol: [pol.decide(s, m, t, g, rho=r) for s, m, r, t, g in inputs])
           for name, (pol, _) in variants.items()}
    times = _time_round_robin(fns, args.repeats, args.warmup)  # the table rows, round robin
    for name, (pol, built) in variants.items():
        decisions = [pol.decide(s, m, t, g, rho=r) for s, m, r, t, g in inputs]
        loss, other, err = [], 0, []
        for (s, m, r, t, g), d, (a_ref, best) in zip(inputs, decisions, reference):
            at = float(pol.objective(s, m, d.alpha, r))
            loss.append(best - at if math.isfinite(at) else math.inf)
            other += not math.isclose(d.alpha, a_ref, rel_tol=1e-9)
            if math.isfinite(at):
                err.append(abs(d.expected_ap - at))
        lv = np.asarray(loss)
        rows.append(Row(name, times[name], note=(
            f"σ̂ step {pol.sigma_step:.3g} DN, MTF̂ step {pol.mtf_step:.3g}, {pol.rho_grid.size} ρ levels: "
            f"{pol.table_bytes / 1e6:.1f} MB, built in {built:.2f} s · loss max {lv.max():.4f} / p99 {np.quantile(lv, 0.99):.4f} / "
            f"mean {lv.mean():.5f} AP · other α {100.0 * other / len(inputs):.1f} % · |expected − direct| max {max(err):.4f} AP")))
    direct = _time_round_robin({"direct": lambda: [_direct(default, s, m, r, t, g) for s, m, r, t, g in inputs]},
                               max(1, args.repeats // 4), min(args.warmup, 1))["direct"]
    rows.append(Row("direct objective (no table)", direct, note="the reference: loss 0 by definition"))
    result = BenchResult(
        title=f"Exposure/gain policy: look-up table against the direct objective, {args.decisions} random decisions, CPU",
        rows=rows, baseline=rows[0].name)
    result.header = [
        f"machine: {machine_description()}",
        f"command: `{getattr(args, 'command_line', 'python -m camhealth.bench policy')}`",
        f"date: {_dt.datetime.now().isoformat(timespec='seconds')}; load average before/after: {load_before} → {_load()}",
        f"IOPC: {args.iopc} ({iopc.name!r}: σ bins {', '.join(f'{v:g}' for v in iopc.sigma_bins)} DN; MTF → length relation "
        f"down to {float(iopc.blur_mtf[-1]):.3f} at {float(iopc.blur_length_px[-1]):g} px); camera limits "
        f"{default.limits.exposure_s} s, {default.limits.gain_db} dB",
        "ms/batch: all the decisions of a row (µs per decision at the default --decisions 1000); inputs uniform inside the "
        "IOPC (σ̂, MTF̂, ρ) and the limits (exposure log-uniform, gain uniform), seed --seed",
    ]
    per = rows[0].median_ms * 1e3 / args.decisions
    summary.append(f"default table: {per:.1f} µs per decision ({rows[-1].median_ms / rows[0].median_ms:.0f}× faster than "
                   "evaluating the objective directly)")
    result.summary = summary
    return result
