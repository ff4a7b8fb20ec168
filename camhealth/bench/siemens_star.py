"""``python -m camhealth.bench siemens_star``: the Siemens star (ISO 15775) under white noise, with its noise correction
and without it, error and ms per chart side by side.

:func:`~camhealth.estimators.siemens_star_mtf` takes the noise's extremes out of every ring's I_max − I_min (noise σ and
correlation from the star's uniform corners; ``docs/estimators_classical.md``, *Noise*) and calls a star whose noise
exceeds :data:`~camhealth.estimators.siemens_star.MAX_NOISE_CONTRAST` of its contrast not assessable. Passing
``levels=`` reads no corner and fits the raw CTF: the uncorrected method, the reference here.

Kernels, on a 512-px star: a Gaussian blur of σ = 2 px (the correction's two shares were chosen on it), then kernels it
was not chosen on — a hexagonal aperture and camera shake of 3–15 px. White noise of 0–25 DN is added after the blur,
``--images`` draws per cell, and every estimate is scored by AMAE (Eq. 5.1, %) against the kernel's H/V labels. Rows
time both on the 25 charts of the 10-DN column (ms per batch; per chart in the note). ``--batch``/``--size`` of the
common options are not used.
"""

from __future__ import annotations

import argparse
import datetime as _dt

import torch

from camhealth.bench import BenchResult, IntRange, Row

HELP = "Siemens star under white noise: AMAE and ms/chart with its noise correction and of the raw CTF"

#: The common options this benchmark reads (the others are refused: camhealth.bench.check_options).
COMMON_READS = ('repeats', 'seed', 'warmup')

NOISE_DN = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0)


#: Largest ``--images``: 16× the default 4. Each draw is a 512² float32 chart per kernel and level (9 × 6), and the 9 × 64
#: charts at 10 DN are kept for the timed rows (≈ 0.6 GiB).
IMAGES_MAX = 64


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--images", type=IntRange(1, IMAGES_MAX), default=4,
                        help=f"noise draws per kernel and level, 1…{IMAGES_MAX} (default 4)")


def _kernels(gen: torch.Generator) -> dict[str, torch.Tensor]:
    from camhealth.physics import gaussian_psf
    from camhealth.physics.motion_psf import nonlinear_motion_psf, sample_shake_noise
    from camhealth.physics.polygon_psf import polygon_psf

    out = {"Gaussian σ 2 px": gaussian_psf(torch.tensor([2.0]), 25).float()}
    for d in (3.0, 7.0, 11.0, 15.0):
        out[f"hexagon {d:g} px"] = polygon_psf(torch.tensor([d]), 6, 31, rotation_deg=15.0).float()
        out[f"shake {d:g} px"] = nonlinear_motion_psf(torch.tensor([d]), torch.tensor([30.0]), torch.tensor([0.7]),
                                                     sample_shake_noise(1, 64, generator=gen), 31).float()
    return out


def run(args: argparse.Namespace) -> BenchResult:
    from camhealth.bench.corruption import _load, _time_round_robin, machine_description
    from camhealth.estimators import siemens_star_mtf
    from camhealth.estimators.charts import siemens_star_chart
    from camhealth.metrics import amae
    from camhealth.physics import apply_psf, mtf_hv

    load_before = _load()
    gen = torch.Generator().manual_seed(args.seed)
    star = siemens_star_chart(512)
    n = args.images

    def cell(errors: list[float]) -> str:
        if not errors:
            return "–"
        return f"{sum(errors) / len(errors):.1f}" + ("" if len(errors) == n else f" ({len(errors)}/{n})")

    lines = [f"AMAE [%] with the noise correction / of the raw CTF (`levels=` given), mean over {n} noise draws; – not "
             "assessable in any draw, (k/n) assessable in k of n", "",
             "| kernel | " + " | ".join(f"{dn:g} DN" for dn in NOISE_DN) + " |", "|---|" + "---:|" * len(NOISE_DN)]
    timed = []
    worst = {"corrected": 0.0, "raw": 0.0}
    for name, psf in _kernels(gen).items():
        label = mtf_hv(psf).double()[0]
        blurred = apply_psf(star, psf)
        cells = []
        for dn in NOISE_DN:
            x = (blurred.expand(n, -1, -1, -1) + dn / 255.0 * torch.randn(n, 1, 512, 512, generator=gen)).clamp(0, 1)
            if dn == 10.0:
                timed.append(x)
            res, raw = siemens_star_mtf(x), siemens_star_mtf(x, levels=(0.2, 0.8)).mtf.double()
            corrected = [float(amae(res.mtf[i].double(), label)) for i in range(n) if bool(res.assessable[i])]
            uncorrected = [float(amae(raw[i], label)) for i in range(n)]
            if dn <= 15.0:
                worst["corrected"] = max([worst["corrected"], *corrected])
                worst["raw"] = max([worst["raw"], *uncorrected])
            cells.append(f"{cell(corrected)} / {cell(uncorrected)}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    batch = torch.cat(timed)
    fns = {"Siemens star, noise corrected (default)": lambda: siemens_star_mtf(batch).mtf,
           "Siemens star, raw CTF (levels= given)": lambda: siemens_star_mtf(batch, levels=(0.2, 0.8)).mtf}
    with torch.inference_mode():
        times = _time_round_robin(fns, args.repeats, args.warmup)
    rows = [Row(k, times[k]) for k in fns]
    for r in rows:
        r.note = f"{r.median_ms / len(batch):.1f} ms/chart ({len(batch)} charts at 10 DN)"
    result = BenchResult(title=f"Siemens star under white noise: {len(_kernels(torch.Generator()))} kernels × "
                               f"{len(NOISE_DN)} levels × {n} draws, 512-px charts, CPU", rows=rows, baseline=rows[1].name)
    result.header = [
        f"machine: {machine_description()}",
        f"command: `{getattr(args, 'command_line', 'python -m camhealth.bench siemens_star')}`",
        f"date: {_dt.datetime.now().isoformat(timespec='seconds')}; load average before/after: {load_before} → {_load()}",
        f"median over {args.repeats} round-robin repeats after {args.warmup} warm-up calls",
    ]
    result.summary = [f"worst single-chart AMAE at 0–15 DN: {worst['corrected']:.1f} % corrected, {worst['raw']:.1f} % raw",
                      ""] + lines
    return result
