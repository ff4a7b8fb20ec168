"""``python -m camhealth.bench estimators``: held-out accuracy and ms/patch of the learned estimators, side by side,
against a thesis-size reference network on the same patches.

For every shipped model (``camhealth/weights/*.pt`` and ``noise_source_full``, the physics-first noise estimator; or
``--models``) and every ``--checkpoint``:

* **accuracy on held-out data** corrupted by the physics core — the *test* split (images never seen in
  training or validation) of the DataModule the shipped configs train on (``source: default`` + 60 dead-leaves
  images, ``seed: 0``), ``--per-image`` fixed crops per test image, corrupted with the DataModule's seeded test
  corruption: noise models — Bias/Std/RMS (Eq. 6.2, DN) of PN, DCSN, RN, total and ξ (total also on the
  samples whose metadata agree with the image, ``altered = False``); MTF models — on the test split of the MTF
  training source (``configs/mtf_full.yaml``'s ``source_kwargs``; ``--deadleaves`` does not apply) — AMAE
  (Eq. 5.1, %) per blur family over sizes ``--sizes`` (default 3–21 px), with ``--mtf-views 1 2 4`` also for the averaged estimates of
  flipped copies (``Estimator.predict(views=...)``), timed alike;
* **speed**: ``Estimator.predict`` on a batch of ``--batch`` patches in fp32 and bf16 (closed-form physics prior
  and input checks included), median over ``--repeats``; params and FLOPs per patch;
* **reference**: the thesis-size noise network (16 full-resolution 64-channel layers, ≈ 17 GFLOP per 128-px patch,
  :class:`camhealth.nets.drne.ThesisNoiseNet`, untrained — timing only) on the same batch; the ratio column is
  relative to it.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import math
import platform
import time
from typing import Any

import torch

from camhealth.bench import BenchResult, IntRange, Row, check_device_option, option_defaults, option_message, refuse_unread

HELP = "held-out accuracy and ms/patch of the learned estimators vs a thesis-size reference network"
REFERENCE = "thesis-size noise net (16×64 full-res, fp32)"

#: The common options this benchmark reads (the others are refused: camhealth.bench.check_options).
COMMON_READS = ('batch', 'repeats', 'warmup')


#: Largest ``--per-image``: 16× the default 16. The noise set's test split holds 11 images at the default --deadleaves
#: (176 crops at 16): 256 crops each are ≈ 2800 patches of 128² float32 (≈ 0.2 GiB; the MTF set's are 192²), and
#: every estimator reads all of them.
PER_IMAGE_MAX = 256
#: Largest ``--deadleaves``: ≈ 17× the configs' 60. Each is a 256² image rendered when the noise set is made, and ≈ 15 %
#: of them are test images (``--per-image`` crops each: ≈ 150 × 256 crops ≈ 2.4 GiB at both bounds).
DEADLEAVES_MAX = 1000
#: The largest blur size of ``--sizes`` [px]: the largest of the MTF test set's DataModule (``BlurDataModule``).
BLUR_SIZE_MAX = 63.0
#: Options read only with a noise estimator (the noise set) and only with an MTF estimator (the MTF set).
NOISE_ONLY = ("deadleaves", "xi_fields", "split_floor")
MTF_ONLY = ("sizes", "mtf_views")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--models", nargs="*", default=None, help="shipped model names (default: all shipped)")
    parser.add_argument("--checkpoint", action="append", default=[], help="extra model file (.pt/.ckpt/.pt2/.onnx); repeatable")
    parser.add_argument("--per-image", type=IntRange(1, PER_IMAGE_MAX), default=16,
                        help=f"held-out crops per test image, 1…{PER_IMAGE_MAX} (default 16)")
    parser.add_argument(
        "--mtf-views", type=int, nargs="+", default=[1], choices=(1, 2, 4),
        help="for MTF models, also rows with the estimates of 2 or 4 flipped copies averaged (Estimator.predict views=); default 1",
    )
    parser.add_argument("--sizes", type=float, nargs=2, default=[3.0, 21.0], metavar=("LOW", "HIGH"),
                        help=f"blur size range of the MTF test set, px, 0 ≤ LOW ≤ HIGH ≤ {BLUR_SIZE_MAX:g} (default 3 21)")
    parser.add_argument("--deadleaves", type=IntRange(0, DEADLEAVES_MAX), default=60,
                        help=f"dead-leaves images added to the default source of the noise set (as in the noise configs), "
                             f"0…{DEADLEAVES_MAX} (default 60)")
    from camhealth.physics.metadata import FULL_FIELDS

    parser.add_argument(
        "--xi-fields", nargs="+", default=None, metavar="FIELD", choices=FULL_FIELDS,
        help="metadata fields altered for the ξ samples of the noise set (default: the configs' gain_db temperature_c "
        "white_noise_v_per_rthz; the thesis's protocol alters the gain only: --xi-fields gain_db)",
    )
    parser.add_argument(
        "--split-floor", action="store_true",
        help="also print the Bayes-optimal DCSN/RN split's RMS on the noise set for a noise level known to 0/1/2/5 %%",
    )
    parser.add_argument("--no-reference", action="store_true", help="skip the thesis-size reference network")
    parser.add_argument("--device", default="cpu",
                        help="where the estimators' networks (and noise_source_full's posterior) run: cpu (default), cuda "
                             "or cuda:N (load_estimator(device=)); input checks and patch statistics stay on the CPU")


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
    """Held-out noisy patches with labels (the shipped configs' data, test split; ξ samples alter
    ``args.xi_fields``, by default the configs' fields)."""
    from datamodules import NoiseDataModule
    from datamodules.noise import XI_FIELDS

    xi_fields = getattr(args, "xi_fields", None) or XI_FIELDS
    dm = NoiseDataModule(
        source="default", source_kwargs={"deadleaves": args.deadleaves}, patch_size=128, batch_size=64,
        val_patches_per_image=args.per_image, seed=0, metadata_set="full", xi_fields=tuple(xi_fields),
    )
    return _collect(dm)


def mtf_training_source() -> tuple[str, dict[str, Any]]:
    """``(source, source_kwargs)`` of the shipped MTF schedule (``configs/mtf_full.yaml``): its test split is the MTF
    held-out set, so held-out scenes are rendered exactly as the training scenes are (same native MTF)."""
    from pathlib import Path

    import yaml

    cfg = yaml.safe_load((Path(__file__).resolve().parents[1] / "configs" / "mtf_full.yaml").read_text())
    data = cfg["data"]["init_args"]
    return str(data.get("source", "default")), dict(data.get("source_kwargs") or {})


def held_out_blur(args: argparse.Namespace) -> dict[str, torch.Tensor]:
    from datamodules import BlurDataModule

    source, source_kwargs = mtf_training_source()
    dm = BlurDataModule(
        source=source, source_kwargs=source_kwargs, patch_size=192, batch_size=32,
        val_patches_per_image=args.per_image, seed=0, size_range=tuple(args.sizes),
    )
    return _collect(dm)


def split_floor(
    data: dict[str, torch.Tensor], xi_fields: tuple[str, ...], xi_probability: float = 0.5,
    rel_errors: tuple[float, ...] = (0.0, 0.01, 0.02, 0.05), grid: int = 161, seed: int = 0,
) -> list[dict[str, float]]:
    """RMS [DN] of the Bayes-optimal DCSN/RN split of held-out noise data, given the signal-independent noise.

    An oracle that knows the *analytic* σ_DCSN² + σ_RN² of every patch (under the image metadata M′) up to a
    relative error of its σ (``rel_errors``: log-normal, seeded), the metadata M it is told, and the prior the
    data were drawn with (M′ = M with probability 1 − ``xi_probability``, else one of ``xi_fields`` redrawn
    uniformly from its range, gain uniformly in the linear factor), and which sees a gain change exactly (the
    photon noise shows it, and a gain change keeps the DCSN : RN ratio of M). Its posterior-mean split is
    compared with the analytic σ of M′. What remains is the ambiguity between alterations that change only
    signal-independent noise (temperature → DCSN, white noise → RN): a floor for any estimator of the split
    trained on these data, before clipping, texture and the estimate of the noise level itself.
    """
    from camhealth.physics.metadata import FULL_FIELDS, METADATA_RANGES
    from datamodules.noise import expected_sigma_dn
    from camhealth.estimators.noise_features import metadata_from_matrix

    meta_m, meta_i = data["meta_raw"].double(), data["meta_image_raw"].double()
    truth = data["sigma_expected"].double()
    n = meta_m.shape[0]
    clean = torch.full((n, 1, 2, 2), 0.5, dtype=torch.float64)  # PN does not enter the DCSN/RN split

    def analytic(rows: torch.Tensor) -> torch.Tensor:
        return expected_sigma_dn(clean[:1].expand(rows.shape[0], -1, -1, -1), metadata_from_matrix(rows))

    base = analytic(meta_m)
    gain_col = FULL_FIELDS.index("gain_db")
    gain_altered = meta_m[:, gain_col] != meta_i[:, gain_col]
    hyps = []  # (log prior, (n, G) DCSN, (n, G) RN) of the signal-independent alterations
    others = [f for f in xi_fields if f != "gain_db"]
    for f in others:
        lo, hi = METADATA_RANGES[f]
        values = torch.linspace(lo, hi, grid, dtype=torch.float64)
        rows = meta_m.repeat_interleave(grid, 0)
        rows[:, FULL_FIELDS.index(f)] = values.repeat(n)
        s = analytic(rows).view(n, grid, 3)
        hyps.append((math.log(xi_probability / len(xi_fields)), s[..., 1], s[..., 2]))
    v_true = truth[:, 1] ** 2 + truth[:, 2] ** 2
    v0 = base[:, 1] ** 2 + base[:, 2] ** 2  # what M predicts
    gen = torch.Generator().manual_seed(seed)
    eps = torch.randn(n, generator=gen, dtype=torch.float64)
    results = []
    for rel in rel_errors:
        v_obs = v_true * torch.exp(2.0 * rel * eps)
        width = max(2.0 * rel, 0.005)  # std of log V, at least 0.5 % (keeps the consistent hypothesis finite)
        lv = torch.log(v_obs + 1e-9)
        comps = [(math.log(1.0 - xi_probability) - 0.5 * ((lv - torch.log(v0 + 1e-9)) / width) ** 2, base[:, 1], base[:, 2])]
        for log_prior, d, r in hyps:
            ll = -0.5 * ((lv[:, None] - torch.log(d**2 + r**2 + 1e-9)) / width) ** 2
            w = torch.softmax(ll, 1)
            comps.append((log_prior + torch.logsumexp(ll, 1) - math.log(grid), (w * d).sum(1), (w * r).sum(1)))
        post = torch.softmax(torch.stack([c[0] for c in comps], 1), 1)
        est_d = torch.zeros(n, dtype=torch.float64)
        est_r = torch.zeros_like(est_d)
        for k, (_, d, r) in enumerate(comps):
            scale = (v_obs / (d**2 + r**2).clamp_min(1e-12)).sqrt()
            est_d += post[:, k] * d * scale
            est_r += post[:, k] * r * scale
        # gain changes are seen in the photon noise: the split keeps M's ratio
        scale0 = (v_obs / v0.clamp_min(1e-12)).sqrt()
        est_d = torch.where(gain_altered, base[:, 1] * scale0, est_d)
        est_r = torch.where(gain_altered, base[:, 2] * scale0, est_r)
        err_d, err_r = est_d - truth[:, 1], est_r - truth[:, 2]
        results.append({"rel_error": rel, "rms_dcsn": err_d.pow(2).mean().sqrt().item(), "rms_rn": err_r.pow(2).mean().sqrt().item()})
    return results


def _meta(data: dict[str, torch.Tensor], sl: slice):
    from camhealth.estimators.noise_features import metadata_from_matrix

    return metadata_from_matrix(data["meta_raw"][sl])


def noise_accuracy(est, data: dict[str, torch.Tensor]) -> dict[str, float]:
    """Bias/Std/RMS [DN] of an estimator's outputs on held-out noise data."""
    from camhealth.metrics import bias_std_rms

    meta = _meta(data, slice(None)) if est.metadata_set != "none" else None
    out = est.predict(data["image"], meta, batch_size=64)
    res: dict[str, float] = {"n": float(data["image"].shape[0])}
    pairs = [("total", out["sigma_total"], data["sigma_total"])]
    if "sigma" in out:
        pairs += [(n, out["sigma"][:, i], data["sigma"][:, i]) for i, n in enumerate(("pn", "dcsn", "rn"))]
        pairs.append(("xi", out["xi"], data["xi"]))
    for name, e, t in pairs:
        r = bias_std_rms(e.double(), t.double(), dim=0)
        res.update({f"{k}_{name}": r[k].item() for k in ("bias", "std", "rms")})
    keep = ~data["altered"]
    if bool(keep.any()):  # samples whose image was corrupted with the metadata the estimator is given (ξ = 0)
        for name, e, t in pairs:
            res[f"rms_{name}_consistent"] = bias_std_rms(e[keep].double(), t[keep].double(), dim=0)["rms"].item()
    return res


def mtf_accuracy(est, data: dict[str, torch.Tensor], views: int = 1) -> dict[str, float]:
    from camhealth.metrics import amae

    out = est.predict(data["image"], batch_size=64, views=views)
    a = amae(out["mtf"].double(), data["mtf"].double())
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


def _time_round_robin(fns, repeats: int, warmup: int) -> list[list[float]]:
    """Times [ms] of each call in ``fns``, ``repeats`` rounds that call every one once (after ``warmup`` rounds), so
    that a drift of the machine's speed hits all of them alike."""
    for _ in range(warmup):
        for fn in fns:
            fn()
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(repeats):
        for i, fn in enumerate(fns):
            t = time.perf_counter()
            fn()
            times[i].append((time.perf_counter() - t) * 1e3)
    return times


def check_options(args: argparse.Namespace) -> None:
    """``ValueError`` naming the option and its value: ``--sizes LOW HIGH`` outside 0 ≤ LOW ≤ HIGH ≤
    :data:`BLUR_SIZE_MAX` px, and a ``--device`` that is no device of this machine (the DataModule and the loader
    would name their own parameters, ``size_range`` and ``device``)."""
    low, high = (float(v) for v in args.sizes)
    if not 0.0 <= low <= high <= BLUR_SIZE_MAX:
        raise ValueError(f"--sizes {low:g} {high:g} must satisfy 0 ≤ LOW ≤ HIGH ≤ {BLUR_SIZE_MAX:g} px (the blur size range "
                         "of the MTF test set)")
    check_device_option(getattr(args, "device", "cpu"))


def _load_estimators(args: argparse.Namespace) -> list:
    """The estimators of ``--models`` (default: every shipped one) and ``--checkpoint``; a name or file that cannot be
    loaded is a ``ValueError`` naming the option."""
    from camhealth.inference import PHYSICS_NOISE_MODEL, load_estimator, shipped_models

    models = list(args.models) if args.models is not None else sorted([*shipped_models(), PHYSICS_NOISE_MODEL])
    names = [("--models", n) for n in models]
    out = []
    for option, name in names + [("--checkpoint", p) for p in args.checkpoint]:
        try:
            out.append(load_estimator(name, device=args.device))
        except (OSError, ValueError) as exc:
            raise ValueError(f"{option} {name}: {option_message(exc, 'device', '--device', args.device)}") from None
    return out


def run(args: argparse.Namespace) -> BenchResult:
    from camhealth.nets import ThesisNoiseNet, count_flops

    check_options(args)
    estimators = _load_estimators(args)
    if not estimators:
        raise SystemExit("no estimators: ship weights under camhealth/weights/ or pass --checkpoint")
    # an option of the noise set without a noise estimator, or of the MTF set without an MTF one, is read by nothing
    kinds = {"mtf" if e.kind == "mtf" else "noise" for e in estimators}
    for kind, only in (("noise", NOISE_ONLY), ("MTF", MTF_ONLY)):
        if kind.lower() not in kinds:
            given = ([" ".join(["--models", *args.models])] if args.models is not None else []) + \
                    [f"--checkpoint {p}" for p in args.checkpoint]
            refuse_unread(args, add_arguments, set(option_defaults(add_arguments)) - set(only),
                          f"{' '.join(given) or 'the shipped estimators'} (no {kind} estimator among them)")
    noise_data = held_out_noise(args) if any(e.kind != "mtf" for e in estimators) else None
    blur_data = held_out_blur(args) if any(e.kind == "mtf" for e in estimators) else None
    b = args.batch
    rows: list[Row] = []
    table = ["| model | kind | metadata | params | GFLOP/patch | ms/patch fp32 | ms/patch bf16 | accuracy (held-out) |", "|---|---|---|---:|---:|---:|---:|---|"]
    noise_table = [
        "| model | n | PN RMS | DCSN RMS | RN RMS | total Bias / Std / RMS | ξ RMS | M = M′ only: PN / DCSN / RN / total RMS |",
        "|---|---:|---:|---:|---:|---|---:|---|",
    ]
    # (estimator, views, predict kwargs of the noise row)
    jobs: list[tuple[Any, int, dict[str, Any]]] = [
        (est, v, {}) for est in estimators for v in (sorted(set(args.mtf_views)) if est.kind == "mtf" else [1])
    ]
    # accuracy first, then every (model, views, precision) timed round-robin: the VM's speed drifts within minutes,
    # and rows timed one after the other could differ by 1.6× for two models of the same architecture
    accs, calls = [], []
    for est, views, nkw in jobs:
        data = blur_data if est.kind == "mtf" else noise_data
        accs.append(mtf_accuracy(est, data, views) if est.kind == "mtf" else noise_accuracy(est, data))
        reps = max(1, b // data["image"].shape[0] + 1)
        x = data["image"].repeat(reps, 1, 1, 1)[:b]
        meta = None
        if est.metadata_set != "none":
            meta = _meta({"meta_raw": data["meta_raw"].repeat(reps, 1)[:b]}, slice(None))
        kw = {"views": views} if est.kind == "mtf" else nkw
        for prec in ("fp32", "bf16"):
            if prec == "bf16" and est.backend != "torch":
                continue
            calls.append((len(accs) - 1, prec, lambda est=est, x=x, meta=meta, prec=prec, kw=kw: est.predict(x, meta, precision=prec, batch_size=b, **kw)))
    timed = _time_round_robin([fn for _, _, fn in calls], args.repeats, args.warmup)
    for j, ((est, views, nkw), acc) in enumerate(zip(jobs, accs)):
        label = est.name if views == 1 else f"{est.name} ×{views} views"
        if est.kind == "mtf":
            note = f"AMAE {acc['amae']:.2f} % (defocus {acc.get('amae_defocus', float('nan')):.2f}, linear {acc.get('amae_linear', float('nan')):.2f}, non-linear {acc.get('amae_nonlinear', float('nan')):.2f})"
        elif est.kind == "drne":
            note = f"total RMS {acc['rms_total']:.2f} DN"
        else:
            note = f"total RMS {acc['rms_total']:.2f} DN, PN {acc['rms_pn']:.2f}, DCSN {acc['rms_dcsn']:.2f}, RN {acc['rms_rn']:.2f}, ξ {acc['rms_xi']:.2f}"
        per = {}
        for (k, prec, _), times in zip(calls, timed):
            if k != j:
                continue
            rows.append(Row(f"{label} ({est.kind}, {prec})", times, note=f"{statistics_ms(times) / b:.2f} ms/patch; {note}"))
            per[prec] = statistics_ms(times) / b
        flops = est.description.get("flops_per_patch", float("nan"))
        table.append(
            f"| {label} | {est.kind} | {est.metadata_set}{' (closed form first, no network)' if est.description.get('params') == 0 else ''} | "
            f"{est.description.get('params', 0):,} | {flops * views / 1e9:.2f} | {per.get('fp32', float('nan')):.2f} | "
            f"{per.get('bf16', float('nan')):.2f} | {note} |"
        )
        if est.kind != "mtf":
            g = lambda k: acc.get(k, float("nan"))  # noqa: E731
            noise_table.append(
                f"| {label} | {int(acc['n'])} | {g('rms_pn'):.2f} | {g('rms_dcsn'):.2f} | {g('rms_rn'):.2f} | "
                f"{g('bias_total'):.2f} / {g('std_total'):.2f} / {g('rms_total'):.2f} | {g('rms_xi'):.2f} | "
                f"{g('rms_pn_consistent'):.2f} / {g('rms_dcsn_consistent'):.2f} / {g('rms_rn_consistent'):.2f} / "
                f"{g('rms_total_consistent'):.2f} |"
            )
    baseline = rows[0].name
    header = [
        f"{_dt.date.today().isoformat()}, {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads; batch {b}; device {args.device}; "
        f"`{getattr(args, 'command_line', 'python -m camhealth.bench estimators')}`",
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
    if getattr(args, "split_floor", False) and noise_data is not None:
        from datamodules.noise import XI_FIELDS

        floor = split_floor(noise_data, tuple(getattr(args, "xi_fields", None) or XI_FIELDS))
        summary += [
            "", "Bayes-optimal DCSN/RN split on the same noise patches (`split_floor`: knows the signal-independent σ up "
            "to the stated relative error, the metadata M and the alteration prior; analytic σ, no clipping):", "",
            "| σ of DCSN²+RN² known to | DCSN RMS | RN RMS |", "|---:|---:|---:|",
            *[f"| {100 * f['rel_error']:.0f} % | {f['rms_dcsn']:.2f} | {f['rms_rn']:.2f} |" for f in floor],
        ]
    return BenchResult("Learned estimators: held-out accuracy and speed", rows, baseline, header, summary)


def statistics_ms(times: list[float]) -> float:
    from camhealth.bench import timing_stats

    return timing_stats(times)[0]
