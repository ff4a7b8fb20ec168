"""Model cards for shipped weights: ``python -m camhealth.model_card WEIGHTS --command "..." [--notes "..."]``.

A card is a Markdown file next to the weights (``camhealth/weights/<name>.md``) in one template, the sections of
Hugging Face's model cards: model details, intended use, training data, evaluation, speed, limitations, how to
reproduce, training procedure. It is written from what the weights file itself records (kind, architecture
arguments, params, FLOPs, held-out test metrics of the fit), the command that reproduces it, and a fresh timing of
``Estimator.predict`` on this machine (fp32 and bf16). ``--refresh`` rewrites a card in place, keeping its command
and training procedure.

``python -m camhealth.model_card WEIGHTS --verify`` measures the stored metrics again: it runs the test of the fit
(:meth:`lightning.Trainer.test`, CPU) on the test split the file records (description ``evaluation``: the datamodule,
its arguments, the precision and any ``limit_test_batches``; ``--data-config CONFIG`` for a file that records none — the ``data:`` and
``trainer: precision`` of a fit config) and prints each metric stored and measured. It exits with 1 when one differs by
more than ``--atol + --rtol·|stored|``: a card whose numbers no longer describe its weights (:func:`verify_metrics`).
"""

from __future__ import annotations

import datetime as _dt
import json
import platform
import re
import sys
from pathlib import Path
from typing import Sequence

import torch

from camhealth._cli import add_debug_flag, config_parser, run_cli

__all__ = ["SECTIONS", "card_text", "main", "read_card", "verify_metrics", "write_card"]

_DATA = {
    "noise_source": "`datamodules.NoiseDataModule` — embedded scikit-image photos + 50 street frames + procedural "
    "dead-leaves images (`source: default`; 60 of them with `configs/noise_source.yaml`, "
    "`source_kwargs: {deadleaves: N}`), 128-px patches, split by image/clip with seed 0 "
    "(70/15/15), sensor noise of the physics core (photon, dark current, readout; gain, clipping) with metadata "
    "sampled uniformly over thesis Table 4.1, half of the samples with altered metadata M′ (ξ ≠ 0).",
    "drne": "`datamodules.NoiseDataModule` as for the noise-source models (no metadata given to the network).",
    "mtf": "`datamodules.BlurDataModule` — procedural dead-leaves scenes rendered with the exact pixel aperture "
    "(`supersample: 4`, native MTF 1.009 at f_n = 0.6; each image its own edge density, contrast, shading and share of thin "
    "leaves 0.5–4 px wide), 192-px patches, "
    "defocus / linear / non-linear motion blur of 1–25 px (one family per sample, defocus twice as often as each "
    "motion family), sensor noise on half of the samples (in the Fig. 3.7 order: photon noise before the motion "
    "blur); labels = exact MTF of the applied PSF, which is the "
    "patch's whole MTF because the scenes have none of their own. No photographs or street frames (their own blur "
    "is unknown or large: `docs/data.md`).",
}


def _time_predict(est, batch: int = 32, min_run_time_s: float = 1.0) -> dict[str, float]:
    """ms per patch of ``predict`` in fp32 and bf16 on a batch of ``batch``: the median over blocks of calls
    (:meth:`torch.utils.benchmark.Timer.blocked_autorange`, warm-up included, at least ``min_run_time_s`` s)."""
    from torch.utils.benchmark import Timer

    from camhealth.physics.metadata import CameraMetadata

    x = torch.rand(batch, 1, est.patch_size, est.patch_size) * 0.6 + 0.2
    meta = CameraMetadata.preset("ICX285", batch_size=batch) if est.metadata_set != "none" else None
    out = {}
    for prec in ("fp32", "bf16"):
        timer = Timer("est.predict(x, meta, precision=prec)", globals={"est": est, "x": x, "meta": meta, "prec": prec},
                      num_threads=torch.get_num_threads())  # all threads, as predict runs (Timer's default is 1)
        out[prec] = timer.blocked_autorange(min_run_time=min_run_time_s).median / batch * 1e3
    return out


_INTENDED = {
    ("noise_source", "minimal"): "σ of photon shot, dark-current shot and readout noise (DN) and the residual ξ of one "
    "gray 128-px patch, given gain, exposure and temperature only (Min-Meta, thesis Ch. 6). For cameras whose "
    "full metadata are known use `noise_source_full` (the closed form, physics first) instead.",
    ("noise_source", "none"): "σ of photon shot, dark-current shot and readout noise (DN) of one gray 128-px patch "
    "with no metadata at all (w/o-Meta, thesis Ch. 6): the thesis's comparison network.",
    ("drne", "none"): "The total noise level σ (DN) of a gray patch and a per-pixel σ map, no metadata (a DRNE-style "
    "network, thesis Ch. 5); the learned counterpart of the classical noise-level baselines.",
    ("mtf", "none"): "The MTF of a gray 192-px patch, horizontal and vertical at f_n = 0.05 … 0.6 of Nyquist "
    "(thesis Ch. 5): blur from defocus and motion, per patch, for the monitor.",
}

_LIMITATIONS = {
    "noise_source": "Trained and tested on camhealth's own simulator only. On data it did not make "
    "(`python -m camhealth.bench robustness --frames 16 --threads 2`: an independent implementation of the sensor "
    "model, downsampled real photographs and street frames, JPEG) its per-source error is far above the metadata's "
    "closed form where the metadata are right (Min-Meta PN / DCSN / RN RMS 0.75 / 0.70 / 2.05 DN against 0.01 / "
    "0.00 / 0.02, both scales pooled), and under strong noise (10–60 DN before clipping) it splits the total (within 1.2 DN) "
    "wrongly among the sources (PN / "
    "DCSN RMS 5.8 / 6.8 DN). It never says `assessable=False` for textured patches. Use it only where the metadata it "
    "needs are unknown or untrusted.",
    "drne": "Trained and tested on camhealth's own simulator only; on the robustness benchmark "
    "(`python -m camhealth.bench robustness --frames 16 --threads 2`) its total-σ RMS is 1.44 DN on matched data "
    "(the metadata's closed form: 0.02 DN; both scales pooled) and under strong noise (10–60 DN before clipping) σ is "
    "within 6.0 % (p90). Gray patches only; no noise "
    "sources, no ξ.",
    "mtf": "Trained on dead-leaves scenes only, with the three PSF families above. On PSFs and scenes it was not "
    "trained on — rendered line art, shapes filled with gradients and 1/f textures with an exact pixel aperture, so the "
    "truth is exact (`python -m camhealth.bench robustness --task mtf --per-cell 8 --threads 2`) — its AMAE is 7.6 / "
    "8.7 / 11.9 % (defocus / linear / non-linear), 3.0–4.8× its value on held-out dead leaves, 4.9 / 5.7 / 5.4 % on the "
    "patches it calls assessable, and 13.0 % on 3-px kernels (4.1 % on the assessable ones): it judges sharpness partly "
    "from the scene's own fine content, so it reads line art too sharp (up to +9 points at 21-px kernels) and edge-free "
    "textures far too blurred (−11 to −30). A slanted edge on a chart is more accurate where one is available. `mtf_std` is a 1-σ error "
    "bar per value from the file's error table (RMS error at each estimate, measured on training's generators × "
    "rendered scenes: `python -m camhealth.bench mtf_error`) and the spread over `views`: 97 % of the values on "
    "assessable patches of held-out generators lie within 2·`mtf_std`. The patches of one scene share most of their "
    "error (ρ = 0.68 of its variance, the table's `shared`): a frame's median over n patches is only √(ρ + (π/2)(1 − ρ)/n) "
    "times as uncertain as one patch, which is what the monitor states (91–97 % of the frame answers within two of it on frames of held-out PSFs). "
    "Gray patches only; featureless (after the noise is removed), "
    "edge-free (Gaussian-like texture or a single grating, whose contrast and blur one patch cannot tell apart: the "
    "noise-corrected gradient kurtosis), black or saturated patches are `assessable=False`.",
}

_INDEPENDENT = {
    "noise_source": "On data camhealth's simulator did not make (an independent sensor simulator, JPEG, mismatched "
    "metadata): `python -m camhealth.bench robustness` (*Robustness* in `docs/benchmarks.md`); its photographs and "
    "street frames are not held-out scenes for this network — 8 of the 10 photographs and the whole street clip are "
    "in its training split.",
    "drne": "On data camhealth's simulator did not make: `python -m camhealth.bench robustness` (*Robustness* in "
    "`docs/benchmarks.md`); its photographs and street frames are not held-out scenes for this network — 8 of the 10 "
    "photographs and the whole street clip are in its training split.",
    "mtf": "On PSFs and scenes it was not trained on: `python -m camhealth.bench robustness --task mtf` "
    "(*Robustness of the MTF estimator* in `docs/benchmarks.md`).",
}


SECTIONS = ("Model details", "Intended use", "Training data", "Evaluation", "Speed", "Limitations",
            "How to reproduce", "Training procedure")


def card_text(weights: Path, command: str, notes: str = "", timing: dict[str, float] | None = None) -> str:
    """The Markdown model card of a weights file, in the sections of :data:`SECTIONS` (Hugging Face's model-card
    headings): details and size from the file's own description, intended use and limitations per kind, the data
    it was trained on, the held-out metrics stored in the file, a fresh timing of ``predict`` (or ``timing``:
    ms/patch for ``"fp32"`` and ``"bf16"``), the command that reproduces it and ``notes`` (its training procedure).
    """
    from camhealth.inference import load_estimator

    est = load_estimator(weights)
    d = est.description
    timing = timing if timing is not None else _time_predict(est)
    metrics = d.get("metrics", {})
    intended = _INTENDED.get((est.kind, est.metadata_set), _INTENDED.get((est.kind, "none"), ""))
    lines = [
        f"# Model card: `{est.name}`",
        "",
        "## Model details",
        "",
        f"- **Kind**: {est.kind} ({d['class_path']}); patch {est.patch_size} px; metadata: {est.metadata_set}",
        f"- **Architecture arguments**: `{json.dumps(d.get('init_args', {}))}`",
        f"- **Size**: {d.get('params', 0):,} parameters, {d.get('flops_per_patch', 0) / 1e9:.2f} GFLOP per patch.",
        *_trunk_line(est),
        _format_line(est),
        _load_line(est),
        "",
        "## Intended use",
        "",
        intended,
        "",
        "## Training data",
        "",
        _DATA[est.kind],
        "",
        "## Evaluation",
        "",
        "Held-out test split of the training generator, measured after fit and stored in the file with the split "
        f"it was measured on (`python -m camhealth.model_card {est.name} --verify` runs that test again and compares); "
        "the same simulator made it, so it is not independent evidence (on the benchmark's own patches: "
        f"`python -m camhealth.bench estimators --models {est.name}`). " + _INDEPENDENT[est.kind],
        "",
        "| metric | value |",
        "|---|---:|",
        *[f"| {k} | {_metric_cell(v)} |" for k, v in sorted(metrics.items())],
        "",
        "Units: σ metrics (bias/std/rms) in DN of 255 (Eq. 6.2); AMAE in % (Eq. 5.1).",
        "",
        "## Speed",
        "",
        f"`Estimator.predict`, batch 32, {platform.processor() or platform.machine()}, {torch.get_num_threads()} "
        f"threads, {_dt.date.today().isoformat()}: {timing['fp32']:.2f} ms/patch fp32, {timing['bf16']:.2f} ms/patch "
        "bf16 (`python -m camhealth.model_card WEIGHTS --refresh` measures it again).",
        "",
        "## Limitations",
        "",
        _LIMITATIONS[est.kind],
        "",
        "## How to reproduce",
        "",
        f"`{command}`",
    ]
    if notes:
        lines += ["", "## Training procedure", "", notes]
    return "\n".join(lines) + "\n"


#: The card's "Format" line per backend of :class:`camhealth.inference.Estimator`.
_FORMATS = {
    "torch": "camhealth weights (`torch.load(weights_only=True)`: tensors and a JSON description, no code).",
    "pt2": "exported program (`torch.export`, `.pt2`: the bare network's graph, checked before it is loaded, and a "
           "JSON description; runs on the CPU).",
    "onnx": "ONNX (ONNX Runtime alone runs it; the JSON description in the model's metadata; runs on the CPU).",
}


def _format_line(est) -> str:
    source = str(est.source)
    text = _FORMATS.get(est.backend, _FORMATS["torch"])
    if est.backend == "torch" and source.lower().endswith(".ckpt"):
        text = ("Lightning checkpoint (`torch.load(weights_only=True)`: tensors and a JSON description, no code; "
                "`python -m camhealth.export --format weights` makes the weights file).")
    return f"- **Format**: {text}"


def _load_line(est) -> str:
    """The card's "Load" line: the shipped name where the estimator was loaded from a shipped file, else its path."""
    from camhealth.inference import shipped_models

    shipped = shipped_models().get(est.name)
    try:
        is_shipped = shipped is not None and Path(est.source).resolve() == shipped.resolve()
    except OSError:
        is_shipped = False
    if is_shipped:
        return f"- **Load**: `camhealth.load_estimator({est.name!r})` (no network access)."
    return f"- **Load**: `camhealth.load_estimator({str(est.source)!r})`."


def _metric_cell(value) -> str:
    """A metric of the file in the card's table: three decimals, or "no samples" for one without data (null or NaN:
    e.g. a blur family the test split had no patch of)."""
    if value is None or (isinstance(value, float) and value != value):
        return "no samples"
    return f"{value:.3f}"


def read_card(path: str | Path) -> tuple[str, str]:
    """The reproduce command and the training-procedure notes of an existing card (``(command, notes)``); a
    ``ValueError`` names the file when it has no command."""
    text = Path(path).read_text(encoding="utf-8")
    m = re.search(r"## How to reproduce\s*\n\s*`([^`]+)`", text) or re.search(r"\*\*Reproduce\*\*: `([^`]+)`", text)
    if m is None:
        raise ValueError(f"model card {str(path)!r} has no reproduce command ('## How to reproduce' section)")
    n = re.search(r"## (?:Training procedure|Notes)\s*\n\n(.*)\Z", text, flags=re.S)
    return m.group(1), (n.group(1).strip() if n else "")


def _trunk_line(est) -> list[str]:
    net = getattr(est, "_net", None)
    if net is None or not hasattr(net, "trunk_activity"):
        return []
    act = net.trunk_activity()
    dead = " — dead: the branches see the image only through the scalar statistics" if act == 0 else ""
    return [f"- **Trunk activity**: {act:.0%} of the pooled trunk features vary over a probe batch{dead}."]


def write_card(weights: str | Path, command: str, notes: str = "") -> Path:
    """Write the card of ``weights`` (a file, or a shipped model's name: :func:`weights_path`) next to the file."""
    weights = weights_path(weights)
    out = weights.with_suffix(".md")
    out.write_text(card_text(weights, command, notes), encoding="utf-8")
    return out


def weights_path(weights: str | Path) -> Path:
    """The weights file a card is for: an existing path as given, else a shipped model's name resolved to its file in
    ``camhealth/weights`` (``"drne"`` → ``camhealth/weights/drne.pt``). ``noise_source_full`` (the closed-form noise
    model, no weights) and retired names are refused naming them; anything else is left to the loader's error."""
    from camhealth.inference import PHYSICS_NOISE_MODEL, RETIRED, shipped_models

    path = Path(weights)
    if path.exists() or not isinstance(weights, str):
        return path
    if weights == PHYSICS_NOISE_MODEL:
        raise ValueError(f"{weights!r} is the closed-form noise model: it has no weights file and no model card; "
                         f"give a weights file (.pt) or one of the shipped names {sorted(shipped_models())}")
    if weights in RETIRED:
        raise ValueError(f"the shipped model {weights!r} is retired: {RETIRED[weights]}")
    return shipped_models().get(weights, path)


def _evaluation_from_config(config: str | Path) -> dict:
    """The ``evaluation`` entry of a fit config (YAML: its ``data:`` section and ``trainer: precision``)."""
    import yaml

    from camhealth.export import check_evaluation

    path = Path(config)
    if not path.is_file():
        raise FileNotFoundError(f"--data-config {str(path)!r}: no such file (a fit config, e.g. configs/drne.yaml)")
    cfg = yaml.safe_load(path.read_text(encoding="utf-8"))
    if not isinstance(cfg, dict) or not isinstance(cfg.get("data"), dict):
        raise ValueError(f"--data-config {str(path)!r} has no 'data:' section with class_path and init_args")
    data = {"class_path": cfg["data"].get("class_path"), "init_args": cfg["data"].get("init_args") or {}}
    trainer = cfg.get("trainer") if isinstance(cfg.get("trainer"), dict) else {}
    precision = str(trainer.get("precision", "32-true"))
    return check_evaluation({"data": data, "precision": precision}, f"--data-config {str(path)!r}")


def verify_metrics(weights: str | Path, data_config: str | Path | None = None, rtol: float = 0.02,
                   atol: float = 0.01) -> list[dict]:
    """Measure a weights file's stored test metrics again and compare.

    The test split is the one the file records (description ``evaluation``) or, for a file without a record, the one
    of ``data_config`` (a fit config). The run is :meth:`lightning.Trainer.test` of the file's LightningModule on
    CPU in the recorded precision, the datamodule with ``num_workers = 0`` (the split and its corruption do not
    depend on the workers). Returns one row per stored metric: ``metric``, ``stored``, ``measured`` (None where
    the run logs none), ``ok`` (both null — a metric without data —, or ``|measured − stored| ≤ atol + rtol·|stored|``;
    σ metrics in DN, AMAE in %)."""
    import math

    import datamodules
    import lightning as L

    from camhealth.export import check_evaluation, load_module

    for name, value in (("rtol", rtol), ("atol", atol)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{name} = {value!r} must be a finite number ≥ 0")
    path = weights_path(weights)
    module, desc = load_module(path)
    stored = desc.get("metrics")
    if not stored:
        raise ValueError(f"{path} records no metrics to verify (a file exported without --test_after_fit)")
    if data_config is not None:
        evaluation = _evaluation_from_config(data_config)
    elif desc.get("evaluation") is not None:
        evaluation = check_evaluation(desc["evaluation"], f"{path}: description evaluation")
    else:
        raise ValueError(f"{path} records no evaluation (the test data of its metrics); give --data-config CONFIG, "
                         f"the fit config that trained it (e.g. configs/drne.yaml)")
    cls = getattr(datamodules, evaluation["data"]["class_path"].split(".", 1)[1])
    init_args = {**evaluation["data"]["init_args"], "num_workers": 0}
    datamodule = cls(**init_args)
    if hasattr(module, "log_figures"):
        module.log_figures = False
    trainer = L.Trainer(accelerator="cpu", devices=1, precision=evaluation["precision"], logger=False,
                        limit_test_batches=evaluation.get("limit_test_batches", 1.0),
                        enable_progress_bar=False, enable_model_summary=False, enable_checkpointing=False)
    measured = trainer.test(module, datamodule=datamodule, verbose=False)[0]
    rows = []
    for key, value in stored.items():
        got = measured.get(key)
        got = None if got is None or float(got) != float(got) else float(got)
        if value is None or got is None:
            ok = value is None and got is None
        else:
            ok = abs(got - value) <= atol + rtol * abs(value)
        rows.append({"metric": key, "stored": value, "measured": got, "ok": ok})
    return rows


def _verify_table(rows: list[dict]) -> str:
    def cell(v):
        return "null" if v is None else f"{v:.4g}"

    lines = ["| metric | stored | measured | difference | ok |", "|---|---:|---:|---:|---|"]
    for r in rows:
        diff = "" if r["stored"] is None or r["measured"] is None else f"{r['measured'] - r['stored']:+.3g}"
        lines.append(f"| {r['metric']} | {cell(r['stored'])} | {cell(r['measured'])} | {diff} | "
                     f"{'yes' if r['ok'] else '**NO**'} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> Path:
    p = config_parser(prog="python -m camhealth.model_card", description=__doc__)
    p.add_argument("weights", help="camhealth weights file (.pt), or a shipped model's name (e.g. drne: "
                                   "camhealth/weights/drne.pt); the card is written next to the file (.md)")
    p.add_argument("--command", default=None, help="the command that trained it (or --refresh)")
    p.add_argument("--refresh", action="store_true",
                   help="keep the existing card's command and training procedure, measure and write the rest again")
    p.add_argument("--notes", default=None, help="the training procedure (free text); with --refresh: the card's")
    p.add_argument("--verify", action="store_true",
                   help="measure the stored test metrics again on the recorded test split and compare (exit 1 when "
                        "one differs); writes nothing")
    p.add_argument("--data-config", default=None,
                   help="with --verify: the fit config whose data and precision to test on, for a file that records none")
    p.add_argument("--rtol", type=float, default=0.02, help="with --verify: relative tolerance")
    p.add_argument("--atol", type=float, default=0.01, help="with --verify: absolute tolerance (DN or %%)")
    add_debug_flag(p)
    args = p.parse_args(argv)
    if args.verify:
        if args.command is not None or args.refresh or args.notes is not None:
            raise ValueError("--verify writes no card: give it without --command, --refresh and --notes")
        weights = weights_path(args.weights)
        rows = verify_metrics(weights, args.data_config, rtol=args.rtol, atol=args.atol)
        print(_verify_table(rows))
        bad = [r["metric"] for r in rows if not r["ok"]]
        if bad:
            print(f"{weights}: {len(bad)} of {len(rows)} stored metrics differ from a fresh test: {', '.join(bad)}")
            raise SystemExit(1)
        print(f"{weights}: all {len(rows)} stored metrics reproduced (atol {args.atol}, rtol {args.rtol})")
        return weights
    if args.data_config is not None:
        raise ValueError("--data-config is an option of --verify")
    if (args.command is None) == (not args.refresh):
        raise ValueError("give either --command (the command that trained the weights) or --refresh (keep the card's)")
    weights = weights_path(args.weights)
    command, notes = args.command, args.notes
    if args.refresh:
        command, old_notes = read_card(weights.with_suffix(".md"))
        notes = old_notes if notes is None else notes
    out = write_card(weights, command, notes or "")
    print(out)
    return out


if __name__ == "__main__":  # pragma: no cover
    sys.exit(run_cli(main, "python -m camhealth.model_card"))
