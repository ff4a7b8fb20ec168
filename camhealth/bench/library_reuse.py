"""``python -m camhealth.bench.library_reuse``: camhealth's own code beside the library call that could replace it.

Each row times both with :class:`torch.utils.benchmark.Timer` (median over blocks, ``--threads`` threads) on the
same input after checking that they agree, so a replacement is made only where the library is not slower:

- ``fft``: :func:`camhealth.physics.image_formation._fft_convolve` vs :func:`kornia.filters.fft_conv`
  (``behaviour="conv"``), per-sample kernels of 25–63 px on 16–64 patches of 128–512 px;
- ``filter2d``: Kornia's ``filter2d`` with the kernel flipped by hand vs ``behaviour="conv"``;
- ``gray``: :func:`camhealth.data.to_gray`'s NumPy weighting vs :func:`kornia.color.rgb_to_grayscale` on
  the same array (through a float64 tensor), and on tensors (the BT.601 weighted sum vs Kornia);
- ``bias_std_rms``: the tuple form's former body (float64 sums, no checks) vs :func:`camhealth.metrics.bias_std_rms`.
"""

from __future__ import annotations

import sys
from typing import Callable, Sequence

import numpy as np
import torch

from camhealth._cli import add_debug_flag, config_parser, run_cli

__all__ = ["ROWS", "compare", "main"]


def _median_ms(fn: Callable[[], object], threads: int, min_run_time: float) -> float:
    from torch.utils.benchmark import Timer

    return Timer("fn()", globals={"fn": fn}, num_threads=threads).blocked_autorange(min_run_time=min_run_time).median * 1e3


def _fft_cases():
    import kornia

    from camhealth.physics.image_formation import _fft_convolve

    for b, s, k in [(16, 128, 25), (16, 192, 41), (64, 128, 63), (4, 512, 41)]:
        g = torch.Generator().manual_seed(0)
        x = torch.rand(b, 1, s, s, generator=g)
        psf = torch.rand(b, k, k, generator=g)
        psf = psf / psf.sum((-1, -2), keepdim=True)
        yield (f"fft: {b}×{s}² px, kernel {k}", lambda x=x, p=psf: _fft_convolve(x, p, "reflect"),
               lambda x=x, p=psf: kornia.filters.fft_conv(x, p, "reflect", behaviour="conv"), 1e-5)


def _filter2d_cases():
    import kornia

    for b, s, k in [(16, 128, 7), (16, 192, 15), (64, 128, 31)]:
        g = torch.Generator().manual_seed(0)
        x = torch.rand(b, 1, s, s, generator=g)
        psf = torch.rand(b, k, k, generator=g)
        yield (f"filter2d: {b}×{s}² px, kernel {k}",
               lambda x=x, p=psf: kornia.filters.filter2d(x, p.flip(-1, -2), border_type="reflect"),
               lambda x=x, p=psf: kornia.filters.filter2d(x, p, border_type="reflect", behaviour="conv"), 1e-6)


def _gray_cases():
    from kornia.color import rgb_to_grayscale

    from camhealth.data.io import BT601_WEIGHTS, to_gray

    def kornia_array(arr: np.ndarray) -> np.ndarray:
        out = np.float64 if arr.dtype == np.float64 else np.float32
        t = torch.from_numpy(np.ascontiguousarray(arr[..., :3])).to(torch.float64).permute(2, 0, 1)
        return rgb_to_grayscale(t)[0].numpy().astype(out)

    def weighted_sum(x: torch.Tensor) -> torch.Tensor:  # the BT.601 sum written out
        w = torch.tensor(BT601_WEIGHTS, dtype=x.dtype).view(3, 1, 1)
        return (x[..., :3, :, :] * w).sum(dim=-3, keepdim=True)

    rng = np.random.default_rng(0)
    for shape, dt in [((1024, 1280, 3), np.uint8), ((1024, 1280, 3), np.float64), ((480, 640, 4), np.uint8)]:
        a = rng.integers(0, 255, shape).astype(dt)
        yield (f"gray: array {'×'.join(map(str, shape))} {np.dtype(dt).name}", lambda a=a: to_gray(a),
               lambda a=a: kornia_array(a), 1e-3)
    for shape in [(8, 3, 256, 256), (1, 3, 1024, 1280)]:
        x = torch.rand(shape, generator=torch.Generator().manual_seed(0))
        yield (f"gray: tensor {'×'.join(map(str, shape))}", lambda x=x: weighted_sum(x), lambda x=x: rgb_to_grayscale(x), 1e-6)


def _bias_cases():
    from camhealth.metrics import bias_std_rms

    def sums(estimate: torch.Tensor, truth: torch.Tensor):
        e = (estimate - truth).double()
        bias = e.mean(0)
        std = (e.pow(2).mean(0) - bias.pow(2)).clamp_min(0).sqrt()
        return bias.abs(), std, (bias.pow(2) + std.pow(2)).sqrt()

    def shared(estimate: torch.Tensor, truth: torch.Tensor):
        r = bias_std_rms(estimate, truth, dim=0)
        return r["bias"], r["std"], r["rms"]

    for shape in [(2000,), (2000, 4), (200000,)]:
        g = torch.Generator().manual_seed(0)
        e = torch.rand(shape, generator=g, dtype=torch.float64)
        t = torch.rand(shape, generator=g, dtype=torch.float64)
        yield (f"bias_std_rms: {'×'.join(map(str, shape))} (library = camhealth.metrics)", lambda e=e, t=t: sums(e, t), lambda e=e, t=t: shared(e, t), 1e-9)


ROWS: dict[str, Callable] = {"fft": _fft_cases, "filter2d": _filter2d_cases, "gray": _gray_cases, "bias_std_rms": _bias_cases}


def _max_diff(a, b) -> float:
    a = a if isinstance(a, tuple) else (a,)
    b = b if isinstance(b, tuple) else (b,)
    return max(float(np.max(np.abs(np.asarray(x, dtype=np.float64) - np.asarray(y, dtype=np.float64)))) for x, y in zip(a, b))


def compare(rows: Sequence[str], threads: int = 1, min_run_time: float = 1.0) -> list[dict]:
    """One dict per case: ``name``, ``own_ms``, ``library_ms``, ``max_diff`` (after checking it is within the case's
    tolerance; a disagreement raises ``AssertionError``)."""
    unknown = sorted(set(rows) - set(ROWS))
    if unknown:
        raise ValueError(f"unknown rows {unknown}; allowed {sorted(ROWS)}")
    out = []
    for row in rows:
        for name, own, lib, tol in ROWS[row]():
            diff = _max_diff(own(), lib())
            if not diff <= tol:
                raise AssertionError(f"{name}: camhealth and the library differ by {diff:.3g} > {tol:g}")
            out.append({"name": name, "own_ms": _median_ms(own, threads, min_run_time),
                        "library_ms": _median_ms(lib, threads, min_run_time), "max_diff": diff})
    return out


#: Largest ``--min-run-time`` [s]: 30× the default 1 s. Every case times two calls for at least this long (15 cases
#: with every row), so 30 s is ≈ 15 min of timing.
MIN_RUN_TIME_MAX = 30.0


def main(argv: Sequence[str] | None = None) -> list[dict]:
    from camhealth.bench import THREADS_MAX, FloatRange, IntRange

    p = config_parser(prog="python -m camhealth.bench.library_reuse", description=__doc__.split("\n\n")[0])
    p.add_argument("--rows", nargs="+", choices=sorted(ROWS), default=sorted(ROWS), help="which comparisons (default all)")
    p.add_argument("--threads", type=IntRange(1, THREADS_MAX, "4 × the CPU count"), default=1,
                   help="torch threads of the timed calls, 1…4 × the CPU count (default 1)")
    p.add_argument("--min-run-time", type=FloatRange(0.0, MIN_RUN_TIME_MAX, unit=" s"), default=1.0,
                   help=f"seconds per Timer.blocked_autorange, > 0 … {MIN_RUN_TIME_MAX:g} (default 1)")
    add_debug_flag(p)
    args = p.parse_args(argv)
    results = compare(args.rows, args.threads, args.min_run_time)
    print(f"| case | camhealth [ms] | library [ms] | library / camhealth | max diff |\n|---|---|---|---|---|")
    for r in results:
        print(f"| {r['name']} | {r['own_ms']:.3f} | {r['library_ms']:.3f} | {r['library_ms'] / r['own_ms']:.2f} | {r['max_diff']:.1e} |")
    return results


if __name__ == "__main__":  # pragma: no cover
    sys.exit(run_cli(main, "python -m camhealth.bench.library_reuse"))
