"""``python -m camhealth.bench data``: patches per second delivered by the training DataModules.

Rows (embedded default images unless ``--source``; ``--batch`` patches per batch):

* :class:`~datamodules.NoiseDataModule` training batches (128 px, all noise sources, ξ probability 0.5) and
  validation batches (fixed, seeded corruption);
* :class:`~datamodules.BlurDataModule` training batches (192 px, defocus / linear / non-linear motion, sizes
  up to 31 px), without and with noise after the blur (Fig. 3.7 order).

One timed call = fetch the next clean batch from the DataLoader (patch extraction, augmentation, collation)
+ ``on_after_batch_transfer`` (the corruption and labels) on the CPU, i.e. what a training loop waits for.
Rows are timed round-robin so that load from other processes hits all rows alike. ``--size`` is not used
(the patch sizes are ``--noise-patch`` and ``--blur-patch``).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import time

import torch

from camhealth.bench import SIZE_MAX, THREADS_MAX, BenchResult, IntRange, Row, add_allocator_argument, apply_allocator

HELP = "patches/s delivered by NoiseDataModule and BlurDataModule (loading + on-the-fly corruption)"

#: The common options this benchmark reads (the others are refused: camhealth.bench.check_options).
COMMON_READS = ('batch', 'repeats', 'seed', 'warmup')

NOISE_TRAIN = "NoiseDataModule train"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--source", default="default", help="image source spec (default: the embedded images)")
    # --workers: at most 4 × the CPU count, as --threads (each worker is a process with its own copy of the sources;
    # more only oversubscribes the CPU); the patch sizes: at most the common --size's bound
    parser.add_argument("--workers", type=IntRange(0, THREADS_MAX), default=0,
                        help="DataLoader workers, 0…4 × the CPU count (default 0)")
    parser.add_argument("--noise-patch", type=IntRange(1, SIZE_MAX), default=128,
                        help=f"noise patch size in px, 1…{SIZE_MAX} (default 128)")
    parser.add_argument("--blur-patch", type=IntRange(69, SIZE_MAX), default=192,
                        help=f"blur patch size in px, 69…{SIZE_MAX} (69: 2 × the 35-px kernel − 1; default 192)")
    add_allocator_argument(parser)


def run(args: argparse.Namespace) -> BenchResult:
    from camhealth.bench.corruption import _load, machine_description
    from datamodules import BlurDataModule, NoiseDataModule
    from datamodules.patches import cycle_batches

    b = args.batch
    allocator = apply_allocator(args)  # as python -m camhealth.fit runs the corruption (camhealth.runtime)
    load_before = _load()
    torch.manual_seed(args.seed)
    common = dict(source=args.source, batch_size=b, num_workers=args.workers, seed=args.seed, val_patches_per_image=b)
    specs = {
        NOISE_TRAIN: (NoiseDataModule(patch_size=args.noise_patch, **common), "train", f"{args.noise_patch} px, PN+DCSN+RN, ξ p = 0.5"),
        "NoiseDataModule val": (NoiseDataModule(patch_size=args.noise_patch, **common), "val", "fixed seeded crops + corruption"),
        "BlurDataModule train": (BlurDataModule(patch_size=args.blur_patch, **common), "train", f"{args.blur_patch} px, 3 families, size ≤ 31 px"),
        "BlurDataModule train + noise": (
            BlurDataModule(patch_size=args.blur_patch, noise=True, **common), "train", "blur, then noise in Fig. 3.7 order",
        ),
        "NoiseDataModule train, train_rng=counter": (
            NoiseDataModule(patch_size=args.noise_patch, train_rng="counter", **common), "train",
            "as NoiseDataModule train, counter-based random fields",
        ),
        "BlurDataModule train + noise, train_rng=counter": (
            BlurDataModule(patch_size=args.blur_patch, noise=True, train_rng="counter", **common), "train",
            "as BlurDataModule train + noise, counter-based random fields",
        ),
    }
    nexts, corr = {}, {}
    for name, (dm, stage, _) in specs.items():
        dm.setup("fit" if stage == "train" else "validate")
        nexts[name] = cycle_batches(dm.train_dataloader() if stage == "train" else dm.val_dataloader())
        corr[name] = []
    for name, (dm, stage, _) in specs.items():  # compile the counter-based kernels before any timing
        if dm.train_rng != "torch":
            dm.on_after_batch_transfer(nexts[name](), 0)
    times: dict[str, list[float]] = {name: [] for name in specs}
    sizes: dict[str, int] = {}
    for rep in range(args.warmup + args.repeats):
        for name, (dm, _, _) in specs.items():
            t0 = time.perf_counter()
            batch = nexts[name]()
            t1 = time.perf_counter()
            out = dm.on_after_batch_transfer(batch, 0)
            t2 = time.perf_counter()
            sizes[name] = int(out["image"].shape[0])
            if rep >= args.warmup:
                times[name].append((t2 - t0) * 1e3)
                corr[name].append((t2 - t1) * 1e3)
    rows = []
    summary = []
    for name, (_, _, what) in specs.items():
        row = Row(name, times[name])
        n = sizes[name]
        pps = n * 1e3 / row.median_ms
        cps = n * 1e3 / sorted(corr[name])[len(corr[name]) // 2]
        row.note = f"{pps:.0f} patches/s ({what}; corruption alone {cps:.0f}/s; {n} per batch)"
        rows.append(row)
        summary.append(f"{name}: {pps:.0f} patches/s delivered incl. corruption")
    result = BenchResult(title=f"Data benchmark: batches of {b} patches, CPU, {args.workers} workers", rows=rows, baseline=NOISE_TRAIN)
    result.header = [
        f"machine: {machine_description()}",
        f"command: `{getattr(args, 'command_line', 'python -m camhealth.bench data')}`",
        f"date: {_dt.datetime.now().isoformat(timespec='seconds')}; load average before/after: {load_before} → {_load()}",
        f"median over {args.repeats} round-robin repeats after {args.warmup} warm-up batches; one call = next clean batch "
        "from the DataLoader + on_after_batch_transfer (corruption + labels)",
        allocator,
    ]
    result.summary = summary
    return result
