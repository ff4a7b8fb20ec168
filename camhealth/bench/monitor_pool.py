"""``python -m camhealth.bench monitor --pool-sizes``: what a pooled noise reading of a few patches can still tell —
the measurement behind :data:`camhealth.monitor.api.NOISE_MIN_POOL`.

The physics-first noise estimator pooled (``predict(..., pool=True)``) adds up the evidence of the patches it reads
together, which show one camera state. A monitor re-estimates only some patches of a frame (a still patch's periodic
refresh, a patch that changed, a new sample), and read alone those have only their own flat details. This scenario
reads the same patches in groups of 1, 2, 4, 6, 8 and 12 and as the whole frame.

Frames: scikit-image's photographs (:func:`camhealth.data.build_source`, ``"skimage"``; those of at least 256 px),
cut into 128-px patches, corrupted by the independent implementation of the sensor model
(:func:`camhealth.bench.sensor_variants.simulate_variant`) at ``--sensor`` (exposure ``--exposure-s``, ``--temperature-c``),
rounded to 8 bits, twice: the camera as told (``--gain-db``) and ``--pool-step-db`` louder than told (the estimator
is told ``--gain-db`` both times), ``--pool-draws`` noise realisations each. Per frame the patches that are assessable
read with their whole frame are drawn in a random order and read in consecutive groups of each size.

Reported per group size, over the patches assessable with their whole frame: the share still assessable; on the
louder camera, the share of the assessable ones that follow the image (ξ < 0, the mismatch seen) and their median
ξ [DN] beside the whole frame's; and ms per patch of the reading (the timing rows, ms per patch).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import math
import time

import torch

from camhealth.bench import BenchResult, Row

#: The group sizes read; the whole frame is read as well.
GROUPS = (1, 2, 4, 6, 8, 12)


def run_pool_sizes(args: argparse.Namespace) -> BenchResult:
    import inspect

    from camhealth.bench.corruption import _load, machine_description
    from camhealth.bench.sensor_variants import simulate_variant
    from camhealth.data import build_source
    from camhealth.inference import load_estimator
    from camhealth.physics import CameraMetadata

    if isinstance(args.pool_draws, bool) or not isinstance(args.pool_draws, int) or args.pool_draws < 1:
        raise ValueError(f"--pool-draws must be an integer >= 1, got {args.pool_draws!r}")
    if not math.isfinite(args.pool_step_db) or args.pool_step_db < 0:
        raise ValueError(f"--pool-step-db must be a finite gain step >= 0 dB, got {args.pool_step_db!r}")
    draws = args.pool_draws
    load_before = _load()
    est = load_estimator(args.noise_model)
    if "pool" not in inspect.signature(est.predict).parameters:
        raise ValueError(f"--pool-sizes reads a pooled noise estimator (predict(..., pool=True)); {args.noise_model!r} has none")
    told = CameraMetadata.preset(args.sensor, gain_db=args.gain_db, exposure_s=args.exposure_s,
                                 temperature_c=args.temperature_c)
    louder = told.replace(gain_db=args.gain_db + args.pool_step_db)
    g = torch.Generator().manual_seed(args.seed)
    source = build_source("skimage")
    sizes = (*GROUPS, "frame")
    # per camera and size: patches read, assessable, following the image, their ξ; per size: the time per patch
    tally = {(cam, k): [0, 0, 0, []] for cam in ("told", "louder") for k in sizes}
    times: dict[object, list[float]] = {k: [] for k in sizes}
    frames = 0
    for i in range(len(source)):
        img, _ = source[i]
        h, w = (int(s) // 128 * 128 for s in img.shape[-2:])
        if h < 256 or w < 256:
            continue
        clean = img[:1, :h, :w].unfold(1, 128, 128).unfold(2, 128, 128).reshape(-1, 1, 128, 128).clamp(0, 1)
        frames += 1
        for cam, meta in [(c, m) for c, m in (("told", told), ("louder", louder)) for _ in range(draws)]:
            noisy, _ = simulate_variant(clean, meta, (), g)
            shot = (noisy * 255).round().to(torch.uint8)
            t = time.perf_counter()
            whole = est.predict(shot, told, pool=True)
            times["frame"].append((time.perf_counter() - t) * 1e3 / shot.shape[0])
            ok = torch.as_tensor(whole["assessable"])
            idx = ok.nonzero()[:, 0]
            _count(tally[(cam, "frame")], whole, torch.ones_like(ok))
            for k in GROUPS:
                order = idx[torch.randperm(idx.numel(), generator=g)]
                for s in range(0, order.numel() - k + 1, k):
                    sel = order[s : s + k]
                    t = time.perf_counter()
                    out = est.predict(shot[sel], told, pool=True)
                    times[k].append((time.perf_counter() - t) * 1e3 / k)
                    _count(tally[(cam, k)], out, torch.ones(k, dtype=torch.bool))
    rows = [Row(f"pooled reading of {k} patch{'es' if k != 1 else ''}" if k != "frame" else "pooled reading of the whole frame",
                times[k], note="ms per patch") for k in sizes]
    table = ["| patches read together | assessable, told camera | assessable, louder camera | louder: ξ < 0 (mismatch seen) | louder: median ξ [DN] |",
             "|---:|---:|---:|---:|---:|"]
    for k in sizes:
        a, b = tally[("told", k)], tally[("louder", k)]
        xi = torch.tensor(b[3]).median().item() if b[3] else float("nan")
        table.append(f"| {k if k != 'frame' else 'whole frame'} | {_share(a[1], a[0])} ({a[0]}) | {_share(b[1], b[0])} ({b[0]}) | "
                     f"{_share(b[2], b[1])} | {xi:+.2f} |")
    header = [
        f"machine: {machine_description()}",
        f"load average before: {load_before} (1/5/15 min); date {_dt.date.today().isoformat()}",
        f"{frames} scikit-image photographs ({draws} noise draws each) cut into 128-px patches, the independent sensor model "
        f"(camhealth.bench.sensor_variants), 8-bit; {args.sensor} at {args.gain_db:g} dB told, {args.exposure_s * 1e3:g} ms, "
        f"{args.temperature_c:g} °C; the louder camera at {args.gain_db + args.pool_step_db:g} dB; estimator {args.noise_model}; "
        f"over the patches assessable read with their whole frame (its own row: all patches); seed {args.seed}",
        f"command: {getattr(args, 'command_line', 'python -m camhealth.bench monitor --pool-sizes')}",
    ]
    summary = table + ["", f"load average after: {_load()}"]
    return BenchResult("Pooled noise readings of a few patches (ms per patch)", rows, rows[-1].name, header=header,
                       summary=summary)


def _count(cell: list, out: dict, among: torch.Tensor) -> None:
    """Add a reading's patches ``among`` to ``cell``: [read, assessable, following the image (ξ < 0), ξ of those]."""
    ok = torch.as_tensor(out["assessable"]).bool()[among]
    xi = torch.as_tensor(out["xi"]).float()[among]
    cell[0] += int(among.sum())
    cell[1] += int(ok.sum())
    seen = ok & (xi < 0)
    cell[2] += int(seen.sum())
    cell[3].extend(xi[seen].tolist())


def _share(a: int, b: int) -> str:
    return f"{100.0 * a / b:.0f} %" if b else "–"
