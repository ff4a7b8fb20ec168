"""Calibrate an MTF estimator's uncertainty: ``python -m camhealth.bench mtf_error [--models FILE …] [--write]``.

Measures r(Ĥ), the RMS error of each MTF value against the estimate itself (:mod:`camhealth.estimators.mtf_error`),
on a calibration set with an exact truth: training's own PSF generators (disk, line, camera shake) on rendered
scenes (line art, gradient-filled shapes, 1/f texture with an exact pixel aperture; their own seed), every condition
of the robustness benchmark (clean, JPEG q 75–95, noise 1–10 DN, 5 DN), blur sizes ``--sizes``. Only the patches
the estimator calls assessable count. None of the robustness benchmark's held-out generators is used, so
``python -m camhealth.bench robustness --task mtf`` checks the table on PSFs it was not measured on.

The share of the error that the patches of one scene have in common (``shared``, ρ;
:func:`camhealth.estimators.mtf_error.shared_error_fraction`) is measured on frames: ``--frames`` per generator × size,
each a 3 × 3 grid of 192-px patches cut from one rendered calibration scene of 704 px
(:func:`camhealth.bench.robustness_mtf.calibration_frames`), clean.

Printed per model: the table (knot, RMS, values nearest the knot), the share of values with |Ĥ − H| ≤ u and ≤ 2u
on the calibration set itself, ρ and the share of the frames' medians within two of their standard error
(:func:`~camhealth.estimators.mtf_error.frame_uncertainty`) with it and without it (ρ = 0), and ms per patch. ``--write`` stores the table in the weights file
(description entry ``mtf_error``), where :meth:`camhealth.inference.Estimator.predict` reads it for ``mtf_std``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import torch

from camhealth.bench import BenchResult, IntRange, Row, shown

HELP = "calibrate the MTF estimator's per-value uncertainty (mtf_std) on training generators × rendered scenes"
SIZES = (2.0, 4.0, 7.0, 11.0, 16.0, 21.0, 25.0)

#: The common options this benchmark reads (the others are refused: camhealth.bench.check_options).
COMMON_READS = ('seed',)


#: Largest ``--per-cell``: the calibration set's own bound (:func:`camhealth.bench.robustness_mtf.calibration_cells`),
#: 16× the default 16. A unit of it is 12 patches of 192² float32 per size (3 generators × 4 conditions, ≈ 1.7 MiB):
#: 256 at the 7 default sizes keep ≈ 3 GiB of patches, made in ≈ 16 min (59 s at 16).
PER_CELL_MAX = 256
#: Largest ``--frames``: 16× the default 4. A unit of it is 3 frames of 576² float32 per size (≈ 3.8 MiB): 64 at the 7
#: default sizes keep ≈ 1.7 GiB of frames.
FRAMES_MAX = 64
#: Most ``--sizes``: twice the 7 default sizes (the patches and frames grow with the number of sizes).
SIZES_MAX = 14
#: The largest blur size of ``--sizes`` [px]: the kernels are 31 px (:data:`camhealth.bench.robustness_mtf.KERNEL`).
BLUR_SIZE_MAX = 29.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--models", nargs="*", default=None, help="MTF estimators (shipped names or .pt files; default 'mtf')")
    parser.add_argument("--per-cell", type=IntRange(1, PER_CELL_MAX), default=16,
                        help=f"patches per generator × size × condition, 1…{PER_CELL_MAX} (default 16)")
    parser.add_argument("--sizes", type=float, nargs="+", default=list(SIZES),
                        help=f"blur sizes in px, at most {SIZES_MAX} of them (default {' '.join(f'{s:g}' for s in SIZES)}; "
                             f"each at most {BLUR_SIZE_MAX:g})")
    parser.add_argument("--frames", type=IntRange(1, FRAMES_MAX), default=4,
                        help=f"frames per generator × size for the shared part of the error, 1…{FRAMES_MAX} (default 4)")
    parser.add_argument("--write", action="store_true",
                        help="store the table in each model's weights file (description entry 'mtf_error')")
    parser.add_argument("--json", type=Path, default=None, help="write every number to this JSON file")


def check_options(args: argparse.Namespace) -> None:
    """``ValueError`` naming ``--sizes`` and its values where more than :data:`SIZES_MAX` are given or one lies outside
    [0, :data:`BLUR_SIZE_MAX`] px (``--per-cell`` and ``--frames`` are checked when parsed)."""
    sizes = list(args.sizes)
    if len(sizes) > SIZES_MAX:
        raise ValueError(f"--sizes {shown(sizes)}: {len(sizes)} sizes, at most {SIZES_MAX} are allowed "
                         f"(each in [0, {BLUR_SIZE_MAX:g}] px)")
    if any(not 0.0 <= float(z) <= BLUR_SIZE_MAX for z in sizes):
        raise ValueError(f"--sizes {shown(sizes)} must lie in [0, {BLUR_SIZE_MAX:g}] px (the kernels are 31 px)")


def run(args: argparse.Namespace) -> BenchResult:
    import dataclasses

    from camhealth.bench.robustness_mtf import FRAME_GRID, PATCH, calibration_cells, calibration_frames
    from camhealth.estimators.mtf_error import fit_error_table, frame_uncertainty, mtf_uncertainty, shared_error_fraction
    from camhealth.export import set_description_entries
    from camhealth.inference import load_estimator

    check_options(args)
    t0 = time.perf_counter()
    cells = calibration_cells(args.per_cell, tuple(args.sizes), args.seed)
    frame_sets = calibration_frames(args.frames, tuple(args.sizes), args.seed)
    n = sum(c.image.shape[0] for c in cells)
    data = (f"training generators (disk, line, shake) × rendered scenes, sizes {' '.join(f'{s:g}' for s in args.sizes)} px, "
            f"clean / JPEG / noise 1–10 DN / 5 DN, {n} patches, seed {args.seed}, assessable patches only")
    header = [f"calibration set: {data}; made in {time.perf_counter() - t0:.0f} s", f"command: {args.command_line}"]
    rows, summary, results = [], [], {}
    for name in args.models or ["mtf"]:
        est = load_estimator(name)
        if est.kind != "mtf":
            raise ValueError(f"estimator {name!r} is {est.kind!r}; mtf_error calibrates MTF estimators")
        ests, truths, oks, times = [], [], [], []
        for c in cells:
            t = time.perf_counter()
            o = est.predict(c.image)
            times.append((time.perf_counter() - t) * 1e3 / c.image.shape[0])
            ests.append(o["mtf"]), truths.append(c.truth), oks.append(o["assessable"])
        e, tr, ok = torch.cat(ests), torch.cat(truths), torch.cat(oks)
        table = fit_error_table(e, tr, ok, data=data)
        u = mtf_uncertainty(e[ok], table)
        err = (e[ok] - tr[ok]).abs()
        c1, c2 = float((err <= u).float().mean()), float((err <= 2 * u).float().mean())
        # the frames: each one scene, one blur; the errors of its assessable patches against their common truth
        per_frame = []
        for frames, truth in frame_sets:
            patches = frames.unfold(-2, PATCH, PATCH).unfold(-2, PATCH, PATCH).reshape(-1, 1, PATCH, PATCH)
            o = est.predict(patches)
            m, a = o["mtf"].view(frames.shape[0], FRAME_GRID * FRAME_GRID, -1), o["assessable"].view(frames.shape[0], -1)
            per_frame += [(m[i][a[i]], truth[i].expand(int(a[i].sum()), -1)) for i in range(frames.shape[0])]
        rho = shared_error_fraction(per_frame, table)
        table = dataclasses.replace(table, shared=round(rho, 3))
        cover = {}
        for r_ in (0.0, table.shared):
            inside = [((f.median(0).values - t[0]).abs() <= 2 * frame_uncertainty(mtf_uncertainty(f, table).pow(2).mean(0).sqrt(),
                                                                                  f.shape[0], r_))
                      for f, t in per_frame if f.shape[0] > 0]
            cover[r_] = float(torch.cat(inside).float().mean()) if inside else float("nan")
        n_frames = sum(1 for f, _ in per_frame if f.shape[0] > 0)
        ms = float(torch.tensor(times).median())
        rows.append(Row(f"{est.name} (views 1)", [ms], note="ms per patch"))
        summary += ["", f"**{est.name}** — RMS |Ĥ − H| by the estimate Ĥ (nearest knot), {int(ok.sum())} of {n} patches assessable:", "",
                    "| Ĥ | " + " | ".join(f"{k:g}" for k in table.knots) + " |",
                    "|---|" + "---:|" * len(table.knots),
                    "| RMS | " + " | ".join(f"{r:.3f}" for r in table.rms) + " |",
                    "| values | " + " | ".join(str(int(v)) for v in _counts(e[ok], table.knots)) + " |", "",
                    f"On the calibration set itself: |Ĥ − H| ≤ u for {100 * c1:.0f} %, ≤ 2u for {100 * c2:.0f} % of the values; "
                    f"{ms:.1f} ms per patch.", "",
                    f"Shared by the patches of one scene (ρ, {n_frames} frames with an assessable patch of "
                    f"{len(per_frame)}): **{table.shared:.3f}**; the frames' medians within two standard errors of the "
                    f"median: {100 * cover[table.shared]:.0f} % with ρ, {100 * cover[0.0]:.0f} % with ρ = 0 (every patch's error "
                    "its own)."]
        results[est.name] = {"table": table.to_dict(), "within_1u": c1, "within_2u": c2, "ms": ms,
                             "frames_within_2se": cover[table.shared], "frames_within_2se_independent": cover[0.0]}
        if args.write:
            if est.backend != "torch" or Path(est.source).suffix.lower() != ".pt":
                raise ValueError(f"--write stores the table in a .pt weights file; {est.source} is not one")
            set_description_entries(est.source, {"mtf_error": table.to_dict()})
            summary.append(f"Written to {est.source} (description entry `mtf_error`).")
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=1))
    return BenchResult("MTF error table (mtf_std calibration)", rows, rows[0].name, header=header, summary=summary)


def _counts(est: torch.Tensor, knots: Any) -> torch.Tensor:
    kn = torch.tensor(list(knots), dtype=torch.float64)
    return torch.bincount((est.double().flatten()[:, None] - kn[None]).abs().argmin(1), minlength=kn.numel())
