"""Model cards for shipped weights: ``python -m camhealth.model_card WEIGHTS --command "..." [--notes "..."]``.

A card is a Markdown file next to the weights (``camhealth/weights/<name>.md``) written from what the weights
file itself records (kind, architecture arguments, params, FLOPs, held-out test metrics of the fit) plus the
command that reproduced it, and a fresh timing of ``Estimator.predict`` on this machine (fp32 and bf16).
"""

from __future__ import annotations

import datetime as _dt
import json
import platform
from pathlib import Path
from typing import Sequence

import torch

from camhealth._cli import config_parser

__all__ = ["card_text", "write_card", "main"]

_DATA = {
    "noise_source": "`datamodules.NoiseDataModule` — embedded scikit-image photos + 50 street frames + procedural "
    "dead-leaves images (`source: default`; 60 of them with `configs/noise_source.yaml`, "
    "`source_kwargs: {deadleaves: N}`), 128-px patches, split by image/clip with seed 0 "
    "(70/15/15), sensor noise of the physics core (photon, dark current, readout; gain, clipping) with metadata "
    "sampled uniformly over thesis Table 4.1, half of the samples with altered metadata M′ (ξ ≠ 0).",
    "drne": "`datamodules.NoiseDataModule` as for the noise-source models (no metadata given to the network).",
    "mtf": "`datamodules.BlurDataModule` — the same images (dead leaves as in the config used), 192-px patches, "
    "defocus / linear / non-linear motion "
    "blur of 1–25 px (one family per sample, equal weights), labels = exact MTF of the applied PSF.",
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


def card_text(weights: Path, command: str, notes: str = "", timing: dict[str, float] | None = None) -> str:
    from camhealth.inference import load_estimator

    est = load_estimator(weights)
    d = est.description
    timing = timing if timing is not None else _time_predict(est)
    metrics = d.get("metrics", {})
    lines = [
        f"# Model card: `{est.name}`",
        "",
        f"- **Kind**: {est.kind} ({d['class_path']}); patch {est.patch_size} px; metadata: {est.metadata_set}",
        f"- **Load**: `camhealth.load_estimator({est.name!r})` (no network access; tensors only).",
        f"- **Architecture arguments**: `{json.dumps(d.get('init_args', {}))}`",
        f"- **Size**: {d.get('params', 0):,} parameters, {d.get('flops_per_patch', 0) / 1e9:.2f} GFLOP per patch.",
        f"- **Speed** (`Estimator.predict`, batch 32, {platform.processor() or platform.machine()}, "
        f"{torch.get_num_threads()} threads, {_dt.date.today().isoformat()}): {timing['fp32']:.2f} ms/patch fp32, "
        f"{timing['bf16']:.2f} ms/patch bf16.",
        *_trunk_line(est),
        f"- **Data**: {_DATA[est.kind]}",
        f"- **Reproduce**: `{command}`",
        "",
        "## Held-out test metrics (test split, after fit)",
        "",
        "| metric | value |",
        "|---|---:|",
        *[f"| {k} | {v:.3f} |" for k, v in sorted(metrics.items())],
        "",
        "Units: σ metrics (bias/std/rms) in DN of 255 (Eq. 6.2); AMAE in % (Eq. 5.1).",
    ]
    if notes:
        lines += ["", "## Notes", "", notes]
    return "\n".join(lines) + "\n"


def _trunk_line(est) -> list[str]:
    net = getattr(getattr(est, "_module", None), "net", None)
    if net is None or not hasattr(net, "trunk_activity"):
        return []
    act = net.trunk_activity()
    dead = " — dead: the branches see the image only through the scalar statistics" if act == 0 else ""
    return [f"- **Trunk activity**: {act:.0%} of the pooled trunk features vary over a probe batch{dead}."]


def write_card(weights: str | Path, command: str, notes: str = "") -> Path:
    weights = Path(weights)
    out = weights.with_suffix(".md")
    out.write_text(card_text(weights, command, notes), encoding="utf-8")
    return out


def main(argv: Sequence[str] | None = None) -> Path:
    p = config_parser(prog="python -m camhealth.model_card", description=__doc__)
    p.add_argument("weights", help="camhealth weights file (.pt)")
    p.add_argument("--command", required=True, help="the command that trained it")
    p.add_argument("--notes", default="", help="free text appended to the card")
    args = p.parse_args(argv)
    out = write_card(args.weights, args.command, args.notes)
    print(out)
    return out


if __name__ == "__main__":  # pragma: no cover
    main()
