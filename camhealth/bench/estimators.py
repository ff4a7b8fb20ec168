"""``python -m camhealth.bench estimators``: held-out accuracy and ms/patch of the learned estimators, side by side,
against a thesis-size reference network on the same patches.

For every shipped model (``camhealth/weights/*.pt``; or ``--models``) and every ``--checkpoint``:

* **accuracy on held-out data** corrupted by the physics core — the *test* split (images never seen in
  training or validation) of the DataModule the shipped configs train on (``source: default`` + 60 dead-leaves
  images, ``seed: 0``), ``--per-image`` fixed crops per test image, corrupted with the DataModule's seeded test
  corruption: noise models — Bias/Std/RMS (Eq. 6.2, DN) of PN, DCSN, RN, total and ξ (total also on the
  samples whose metadata agree with the image, ``altered = False``); MTF models — AMAE (Eq. 5.1, %) per blur
  family over sizes ``--sizes`` (default 3–21 px);
* **speed**: ``Estimator.predict`` on a batch of ``--batch`` patches in fp32 and bf16 (closed-form physics prior
  and input checks included), median over ``--repeats``; params and FLOPs per patch;
* **reference**: the thesis-size noise network (16 full-resolution 64-channel layers, ≈ 17 GFLOP per 128-px patch,
  :class:`lightning_modules.ThesisNoiseNet`, untrained — timing only) on the same batch; the ratio column is
  relative to it.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import platform
import time

import torch

from camhealth.bench import BenchResult, Row

HELP = "held-out accuracy and ms/patch of the learned estimators vs a thesis-size reference network"
REFERENCE = "thesis-size noise net (16×64 full-res, fp32)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--models", nargs="*", default=None, help="shipped model names (default: all shipped)")
    parser.add_argument("--checkpoint", action="append", default=[], help="extra model file (.pt/.ckpt/.pt2/.onnx); repeatable")
    parser.add_argument("--per-image", type=int, default=16, help="held-out crops per test image (default 16)")
    parser.add_argument("--sizes", type=float, nargs=2, default=(3.0, 21.0), help="blur size range of the MTF test set, px")
    parser.add_argument("--deadleaves", type=int, default=60, help="dead-leaves images added to the default source (as in the configs)")
    parser.add_argument("--no-reference", action="store_true", help="skip the thesis-size reference network")


def _collect(dm, limit_batches: int | None = None) -> dict[str, torch.Tensor]:
    dm.setup("test")
    parts: dict[str, list[torch.Tensor]] = {}
    for i, batch in enumerate(dm.test_dataloader()):
        if limit_batches is not None and i >= limit_batches:
            break
        out = dm.on_after_batch_transfer(batch, 0)
        for k, v in out.items():
            if isinstance(v, torch.Tensor):
                parts.setdefault(k, []).append(v)
    return {k: torch.cat(v) for k, v in parts.items()}


def held_out_noise(args: argparse.Namespace) -> dict[str, torch.Tensor]:
    """Held-out noisy patches with labels (the shipped configs' data, test split)."""
    from datamodules import NoiseDataModule

    dm = NoiseDataModule(
        source="default", source_kwargs={"deadleaves": args.deadleaves}, patch_size=128, batch_size=64,
        val_patches_per_image=args.per_image, seed=0, metadata_set="full",
    )
    return _collect(dm)


def held_out_blur(args: argparse.Namespace) -> dict[str, torch.Tensor]:
    from datamodules import BlurDataModule

    dm = BlurDataModule(
        source="default", source_kwargs={"deadleaves": args.deadleaves}, patch_size=192, batch_size=32,
        val_patches_per_image=args.per_image, seed=0, size_range=tuple(args.sizes),
    )
    return _collect(dm)


def _meta(data: dict[str, torch.Tensor], sl: slice):
    from lightning_modules.noise_features import metadata_from_matrix

    return metadata_from_matrix(data["meta_raw"][sl])


def noise_accuracy(est, data: dict[str, torch.Tensor]) -> dict[str, float]:
    """Bias/Std/RMS [DN] of an estimator's outputs on held-out noise data."""
    from lightning_modules.metrics import bias_std_rms

    meta = _meta(data, slice(None)) if est.metadata_set != "none" else None
    out = est.predict(data["image"], meta, batch_size=64)
    res: dict[str, float] = {"n": float(data["image"].shape[0])}
    pairs = [("total", out["sigma_total"], data["sigma_total"])]
    if "sigma" in out:
        pairs += [(n, out["sigma"][:, i], data["sigma"][:, i]) for i, n in enumerate(("pn", "dcsn", "rn"))]
        pairs.append(("xi", out["xi"], data["xi"]))
    for name, e, t in pairs:
        b, s, r = bias_std_rms(e.double(), t.double())
        res.update({f"bias_{name}": b.item(), f"std_{name}": s.item(), f"rms_{name}": r.item()})
    keep = ~data["altered"]
    if bool(keep.any()):  # samples whose image was corrupted with the metadata the estimator is given (ξ = 0)
        for name, e, t in pairs:
            res[f"rms_{name}_consistent"] = bias_std_rms(e[keep].double(), t[keep].double())[2].item()
    return res


def mtf_accuracy(est, data: dict[str, torch.Tensor]) -> dict[str, float]:
    from lightning_modules.metrics import amae_percent

    out = est.predict(data["image"], batch_size=64)
    a = amae_percent(out["mtf"].double(), data["mtf"].double())
    res = {"n": float(a.numel()), "amae": a.mean().item()}
    for i, fam in enumerate(("defocus", "linear", "nonlinear")):
        sel = data["family"] == i
        if bool(sel.any()):
            res[f"amae_{fam}"] = a[sel].mean().item()
    return res


def _time(fn, repeats: int, warmup: int) -> list[float]:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return times


def run(args: argparse.Namespace) -> BenchResult:
    from camhealth.inference import load_estimator, shipped_models
    from lightning_modules import ThesisNoiseNet
    from lightning_modules.blocks import count_flops

    names = list(args.models) if args.models is not None else sorted(shipped_models())
    estimators = [load_estimator(n) for n in names] + [load_estimator(p) for p in args.checkpoint]
    if not estimators:
        raise SystemExit("no estimators: ship weights under camhealth/weights/ or pass --checkpoint")
    noise_data = held_out_noise(args) if any(e.kind != "mtf" for e in estimators) else None
    blur_data = held_out_blur(args) if any(e.kind == "mtf" for e in estimators) else None
    b = args.batch
    rows: list[Row] = []
    table = ["| model | kind | metadata | params | GFLOP/patch | ms/patch fp32 | ms/patch bf16 | accuracy (held-out) |", "|---|---|---|---:|---:|---:|---:|---|"]
    noise_table = [
        "| model | n | PN RMS | DCSN RMS | RN RMS | total Bias / Std / RMS | ξ RMS | M = M′ only: PN / DCSN / RN / total RMS |",
        "|---|---:|---:|---:|---:|---|---:|---|",
    ]
    for est in estimators:
        data = blur_data if est.kind == "mtf" else noise_data
        acc = mtf_accuracy(est, data) if est.kind == "mtf" else noise_accuracy(est, data)
        reps = max(1, b // data["image"].shape[0] + 1)
        x = data["image"].repeat(reps, 1, 1, 1)[:b]
        meta = None
        if est.metadata_set != "none":
            meta = _meta({"meta_raw": data["meta_raw"].repeat(reps, 1)[:b]}, slice(None))
        per = {}
        for prec in ("fp32", "bf16"):
            if prec == "bf16" and est.backend != "torch":
                continue
            times = _time(lambda: est.predict(x, meta, precision=prec, batch_size=b), args.repeats, args.warmup)
            if est.kind == "mtf":
                note = f"AMAE {acc['amae']:.2f} % (defocus {acc.get('amae_defocus', float('nan')):.2f}, linear {acc.get('amae_linear', float('nan')):.2f}, non-linear {acc.get('amae_nonlinear', float('nan')):.2f})"
            elif est.kind == "drne":
                note = f"total RMS {acc['rms_total']:.2f} DN"
            else:
                note = f"total RMS {acc['rms_total']:.2f} DN, PN {acc['rms_pn']:.2f}, DCSN {acc['rms_dcsn']:.2f}, RN {acc['rms_rn']:.2f}, ξ {acc['rms_xi']:.2f}"
            row = Row(f"{est.name} ({est.kind}, {prec})", times, note=f"{statistics_ms(times) / b:.2f} ms/patch; {note}")
            rows.append(row)
            per[prec] = statistics_ms(times) / b
        flops = est.description.get("flops_per_patch", float("nan"))
        acc_txt = rows[-1].note.split("; ", 1)[1]
        table.append(
            f"| {est.name} | {est.kind} | {est.metadata_set}{' + physics prior' if est.physics_prior else ''} | "
            f"{est.description.get('params', 0):,} | {flops / 1e9:.2f} | {per.get('fp32', float('nan')):.2f} | "
            f"{per.get('bf16', float('nan')):.2f} | {acc_txt} |"
        )
        if est.kind != "mtf":
            g = lambda k: acc.get(k, float("nan"))  # noqa: E731
            noise_table.append(
                f"| {est.name} | {int(acc['n'])} | {g('rms_pn'):.2f} | {g('rms_dcsn'):.2f} | {g('rms_rn'):.2f} | "
                f"{g('bias_total'):.2f} / {g('std_total'):.2f} / {g('rms_total'):.2f} | {g('rms_xi'):.2f} | "
                f"{g('rms_pn_consistent'):.2f} / {g('rms_dcsn_consistent'):.2f} / {g('rms_rn_consistent'):.2f} / "
                f"{g('rms_total_consistent'):.2f} |"
            )
    baseline = rows[0].name
    header = [
        f"{_dt.date.today().isoformat()}, {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads; batch {b}; `{getattr(args, 'command_line', 'python -m camhealth.bench estimators')}`",
    ]
    if not args.no_reference:
        ref = ThesisNoiseNet().eval()
        x = torch.rand(b, 1, 128, 128)
        with torch.inference_mode():
            times = _time(lambda: ref(x), max(2, args.repeats // 4), 1)
        flops = count_flops(ref, x[:1])
        rows.append(Row(REFERENCE, times, note=f"{statistics_ms(times) / b:.2f} ms/patch; {flops / 1e9:.1f} GFLOP/patch; untrained, timing only"))
        baseline = REFERENCE
    summary = ["Per-model summary (params, FLOPs, speed, held-out accuracy):", "", *table, "", "Noise metrics in DN (Eq. 6.2):", "", *noise_table]
    return BenchResult("Learned estimators: held-out accuracy and speed", rows, baseline, header, summary)


def statistics_ms(times: list[float]) -> float:
    from camhealth.bench import timing_stats

    return timing_stats(times)[0]
