"""``python -m camhealth.bench classical``: error and ms per patch of the classical estimators, side by side.

Rows (fixed seed; every row sees the same inputs in every repeat):

* noise — :func:`~camhealth.estimators.pca_noise_sigma` (PCA, Chen et al. 2015),
  :func:`~camhealth.estimators.block_filter_noise_sigma` (B+F, Shin et al. 2005, 8×16 blocks) and
  :func:`~camhealth.estimators.wavelet_noise_sigma` (wavelet MAD; scikit-image when PyWavelets is installed,
  else the equivalent torch path — both rows when both exist), on a batch of ``--batch`` noise patches of
  ``--noise-size`` px: half natural crops of the embedded images, half dead leaves (texture-rich), with
  white Gaussian noise of σ ∈ {5, 10, 15, 20, 25} DN (cycled over the batch) and clipping. Error: Bias / Std /
  RMS of σ̂ against the realised σ (Eq. 6.2), in DN.
* blur — :func:`~camhealth.estimators.slanted_edge_mtf_hv` (ISO 12233) and
  :func:`~camhealth.estimators.siemens_star_mtf` (ISO 15775) on ``--charts`` synthetic charts blurred by
  defocus and linear motion kernels of 3–21 px. Error: mean AMAE (Eq. 5.1, %) against the MTF labels
  (slanted edge also against the exact MTF in the direction it measures, 5°/95°).

Timing as in the other benchmarks: rows round-robin, median and IQR over the repeats (ms per batch); the
note gives ms per patch (or chart) and the error. The ratio column is relative to PCA.
"""

from __future__ import annotations

import argparse
import datetime as _dt
from typing import Callable

import torch

from camhealth.bench import SIZE_MAX, BenchResult, IntRange, Row

HELP = "error and ms/patch of the classical estimators (PCA, B+F, wavelet; slanted edge, Siemens star)"

#: The common options this benchmark reads (the others are refused: camhealth.bench.check_options).
COMMON_READS = ('batch', 'repeats', 'seed', 'warmup')

PCA = "PCA noise (Chen et al. 2015)"
SIGMAS_DN = (5.0, 10.0, 15.0, 20.0, 25.0)


#: Largest ``--charts`` (per chart row): 64× the default 4. A chart is a 256² slanted edge and a 512² Siemens star
#: (≈ 1.3 MiB float32, blurred copies beside), timed 22 rounds at ≈ 10 ms a chart: 256 take ≈ 1 min.
CHARTS_MAX = 256


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # --noise-size: at most the common --size's bound (a batch of 32 such patches is 2 GiB of float32)
    parser.add_argument("--noise-size", type=IntRange(32, SIZE_MAX), default=128,
                        help=f"noise patch size in px, 32…{SIZE_MAX} (PCA needs 64 sub-patches of 8×8; default 128)")
    parser.add_argument("--charts", type=IntRange(1, CHARTS_MAX), default=4,
                        help=f"blurred charts per chart row, 1…{CHARTS_MAX} (default 4)")
    parser.add_argument("--source", default="default", help="image source of the natural crops (default: embedded)")


def _noise_batch(args: argparse.Namespace) -> tuple[torch.Tensor, torch.Tensor]:
    from camhealth.data import build_source, dead_leaves
    from camhealth.evaluate import _ImageCache, _sample_patches

    b, s = args.batch, args.noise_size
    gen = torch.Generator().manual_seed(args.seed)
    n_nat = b // 2
    nat = _sample_patches(_ImageCache(build_source(args.source)), n_nat, s, gen) if n_nat else torch.zeros(0, 1, s, s)
    dl = torch.stack([dead_leaves(s, r_min=2.0, supersample=2, seed=args.seed + i) for i in range(b - n_nat)])
    clean = torch.cat([nat, dl])
    sig = torch.tensor([SIGMAS_DN[i % len(SIGMAS_DN)] for i in range(b)])
    noisy = (clean + torch.randn(clean.shape, generator=gen) * sig.view(-1, 1, 1, 1) / 255.0).clamp(0, 1)
    truth = (noisy - clean).flatten(1).std(dim=1) * 255.0
    return noisy, truth


def _charts(n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    from camhealth.estimators.charts import siemens_star_chart, slanted_edge_chart
    from camhealth.physics import apply_psf, defocus_psf, linear_motion_psf, mtf_from_psf, mtf_hv

    d = torch.linspace(3.0, 21.0, n)
    fam = torch.arange(n) % 2
    psf = torch.where(fam.view(-1, 1, 1) == 0, defocus_psf(d, 23), linear_motion_psf(d, 30.0 * torch.arange(n).float(), 23))
    sle = apply_psf(slanted_edge_chart(256).expand(n, -1, -1, -1).contiguous(), psf).clamp(0, 1)
    star = apply_psf(siemens_star_chart(512).expand(n, -1, -1, -1).contiguous(), psf).clamp(0, 1)
    return sle, star, mtf_hv(psf), mtf_from_psf(psf, (5.0, 95.0)).reshape(n, -1)


def run(args: argparse.Namespace) -> BenchResult:
    from camhealth.bench.corruption import _load, _time_round_robin, machine_description
    from camhealth.estimators import block_filter_noise_sigma, pca_noise_sigma, siemens_star_mtf, slanted_edge_mtf_hv
    from camhealth.estimators.wavelet_noise import skimage_available, wavelet_noise_sigma
    from camhealth.metrics import amae, noise_errors

    if args.batch < 2:
        raise ValueError(f"--batch must be >= 2 (half natural, half dead leaves), got {args.batch}")
    if args.charts < 1:
        raise ValueError(f"--charts must be >= 1, got {args.charts}")
    load_before = _load()
    torch.manual_seed(args.seed)
    noisy, truth = _noise_batch(args)
    sle, star, labels, exact = _charts(args.charts)

    noise_fns: dict[str, Callable[[], torch.Tensor]] = {
        PCA: lambda: pca_noise_sigma(noisy),
        "B+F noise (Shin et al. 2005)": lambda: block_filter_noise_sigma(noisy),
        "wavelet MAD noise (torch path)": lambda: wavelet_noise_sigma(noisy, backend="torch"),
    }
    if skimage_available():
        noise_fns["wavelet MAD noise (scikit-image)"] = lambda: wavelet_noise_sigma(noisy, backend="skimage")
    chart_fns: dict[str, Callable[[], torch.Tensor]] = {
        "slanted edge (ISO 12233)": lambda: slanted_edge_mtf_hv(sle),
        "Siemens star (ISO 15775)": lambda: siemens_star_mtf(star).mtf,
    }
    with torch.inference_mode():
        times = _time_round_robin({**noise_fns, **chart_fns}, args.repeats, args.warmup)
        outs = {name: fn() for name, fn in {**noise_fns, **chart_fns}.items()}

    rows, summary = [], []
    b = len(noisy)
    for name in noise_fns:
        row = Row(name, times[name])
        e = noise_errors(outs[name], truth)
        row.note = f"{row.median_ms / b:.2f} ms/patch · Bias {e['bias']:.2f} / Std {e['std']:.2f} / RMS {e['rms']:.2f} DN"
        rows.append(row)
        summary.append(f"{name}: RMS {e['rms']:.2f} DN at {row.median_ms / b:.2f} ms per {args.noise_size}-px patch")
    for name in chart_fns:
        row = Row(name, times[name])
        err = float(amae(outs[name], labels).mean())
        extra = f", {float(amae(outs[name], exact).mean()):.2f} % vs the exact MTF at 5°/95°" if "slanted" in name else ""
        row.note = f"{row.median_ms / args.charts:.1f} ms/chart · AMAE {err:.2f} % vs labels{extra}"
        rows.append(row)
        summary.append(f"{name}: AMAE {err:.2f} % vs labels at {row.median_ms / args.charts:.1f} ms per chart")
    result = BenchResult(
        title=f"Classical estimators: {b} noise patches of {args.noise_size} px, {args.charts} charts per chart row, CPU",
        rows=rows,
        baseline=PCA,
    )
    result.header = [
        f"machine: {machine_description()}",
        f"command: `{getattr(args, 'command_line', 'python -m camhealth.bench classical')}`",
        f"date: {_dt.datetime.now().isoformat(timespec='seconds')}; load average before/after: {load_before} → {_load()}",
        f"median over {args.repeats} round-robin repeats after {args.warmup} warm-up calls; ms per batch in the table, "
        "ms per patch/chart and the error in the note",
        "noise: half natural crops, half dead leaves, white Gaussian σ ∈ {5, …, 25} DN; charts: defocus and linear "
        "motion of 3–21 px (slanted edge 256 px, Siemens star 512 px)",
    ]
    result.summary = summary
    return result
