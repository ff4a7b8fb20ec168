"""``python -m camhealth.demo closed-loop``: three exposure/gain controllers on the same simulated camera.

The closed loop of thesis Sec. 7.3 (Parking Lot, Fig. 7.6), on camhealth's own data: a
:class:`~camhealth.control.SimulatedCamera` renders frames of the embedded street clip (768×576 px) at
each controller's exposure and gain with scene motion, low illumination and the noise of a real sensor
preset (physics core, Fig. 3.7 chain, 8-bit output). For every frame the three controllers are rendered
as one batch, the frozen detector (OpenCV HOG people detector by default) runs on each, and each
controller picks the parameters of its next frame:

* **fixed** — constant (exposure, gain);
* **auto-exposure** — tracks 50 % mean intensity, exposure before gain (a built-in camera controller);
* **IOPC policy** — estimates σ̂/MTF̂ on the tiles around its detections and applies α* of the
  :class:`~camhealth.control.ExposurePolicy` built from an IOPC file (``python -m camhealth.iopc``).

Ground truth is pseudo ground truth from the detector on the pristine clean frames (score >= 0.6), and
the AP is COCO AP@0.5 over the controller's detections with score >= 0.5 on all frames. Outputs in
``--out``: ``closed_loop.png`` (parameter trajectories, AP bars, example frames with boxes, the IOPC
heat map with each controller's operating points), ``closed_loop.md`` (the table) and
``closed_loop.json`` (everything per frame, the policy's explanations, the configuration).

The default IOPC is the one ``configs/iopc.yaml`` + ``configs/iopc_closed_loop.yaml`` produce: measured
on frames 0–24 of the clip (the demo runs on frames 25–49, so the policy is never evaluated on frames its
curves were measured on) at this camera's operating point (ICX285, all noise sources, intensity 0.5, 8
bit). ``--repeats n`` reruns the loop with n camera noise seeds and reports AP mean ± std.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from camhealth._cli import BadValue, IntAtLeast, IntRange, add_debug_flag, config_parser, run_cli

__all__ = ["main", "run_closed_loop", "parse_slice"]

THESIS_AP = {"built-in auto-exposure": 0.2608, "fixed": 0.4754, "framework (IOPC policy)": 0.6056}


def parse_slice(text: str) -> slice:
    """``"25:50"`` / ``"::2"`` / ``"10"`` → slice; anything else (``"abc"``, ``"1:2:3:4"``, a step of 0) is a
    :class:`~camhealth._cli.BadValue` (an ``argparse.ArgumentTypeError`` and ``ValueError``) naming the text."""
    parts = str(text).split(":")
    try:
        if len(parts) > 3:
            raise ValueError
        if len(parts) == 1:
            n = int(parts[0])
            return slice(n, n + 1) if n != -1 else slice(n, None)
        vals = [int(p) if p.strip() else None for p in parts] + [None] * (3 - len(parts))
    except ValueError:
        raise BadValue(f"must be a frame index or a slice start:stop[:step] of integers (e.g. 25:50), got {text!r}") from None
    if vals[2] == 0:
        raise BadValue(f"the step of a slice start:stop:step must not be 0, got {text!r}")
    return slice(*vals)


class SliceOption:
    """Option type of ``--frames``: a text :func:`parse_slice` accepts (kept as text, as the results record it), else
    :class:`~camhealth._cli.BadValue` naming it, at parse time. Its ``repr`` is what ``--help`` shows."""

    def __call__(self, value: Any) -> str:
        parse_slice(value)
        return str(value)

    def __repr__(self) -> str:
        return "start:stop[:step]"


def _frames(spec: str, sl: slice) -> tuple[torch.Tensor, list[str]]:
    from camhealth.data import build_source

    src = build_source(spec)
    idx = list(range(len(src)))[sl]
    if not idx:
        raise ValueError(f"frames {sl} select no image of {spec!r} ({len(src)} images)")
    items = [src[i] for i in idx]
    return torch.stack([im for im, _ in items]), [i for _, i in items]


def run_closed_loop(args: argparse.Namespace) -> dict[str, Any]:
    """Run the three controllers; returns the result dict (also written to ``args.out``)."""
    from camhealth.control import (
        AutoExposureController,
        CameraLimits,
        ExposurePolicy,
        FixedController,
        IOPCController,
        SimulatedCamera,
    )
    from camhealth.detection import HOGPeopleDetector, pseudo_ground_truth
    from camhealth.iopc import IOPC, resolve_estimator

    t_start = time.perf_counter()
    iopc_path = Path(args.iopc)
    if not iopc_path.is_file():
        raise SystemExit(
            f"IOPC file {iopc_path} not found: run `python -m camhealth.iopc --config configs/iopc.yaml "
            "--config configs/iopc_closed_loop.yaml` first (or pass --iopc PATH)"
        )
    iopc = IOPC.load(iopc_path)
    specs = iopc.provenance.get("estimator_specs", {})
    noise_spec = args.noise_estimator or specs.get("noise", "physics")
    mtf_spec = args.mtf_estimator or specs.get("mtf", "physics")
    noise_est, mtf_est = resolve_estimator(noise_spec, "noise"), resolve_estimator(mtf_spec, "mtf")
    frames, ids = _frames(args.source, parse_slice(args.frames))
    detector = HOGPeopleDetector()
    gt = pseudo_ground_truth(detector, frames, args.pseudo_score)
    limits = CameraLimits(_exposure_limits(args), tuple(args.limits_gain))
    policy = ExposurePolicy(iopc, limits, min_gain=args.min_gain)
    reference = _reference_intensity(iopc) if args.normalize_intensity else None
    size = tuple(frames.shape[-2:])
    example_frame = len(frames) // 2
    runs = []
    for rep in range(args.repeats):  # repeats differ only in the noise seed of the camera
        camera = SimulatedCamera(frames, args.sensor, args.illumination, args.motion, args.angle, args.temperature,
                                 seed=args.seed + rep)
        controllers = [
            FixedController(args.exposure, args.gain, name="fixed"),
            AutoExposureController(0.5, limits, name="auto-exposure"),
            IOPCController(policy, noise_est, mtf_est, decide_every=args.decide_every, name="IOPC policy",
                           reference_intensity=reference),
        ]
        runs.append(_run_once(camera, controllers, detector, gt, size, example_frame, args))
    first = runs[0]
    results = first["results"]
    for i, r in enumerate(results):
        aps = [run["results"][i]["ap"] for run in runs]
        r["ap_runs"] = aps
        r["ap_mean"] = float(np.mean(aps))
        r["ap_std"] = float(np.std(aps, ddof=1)) if len(aps) > 1 else 0.0
    decisions = first["decisions"]
    examples = first["examples"]
    res = {
        "config": {k: (v if not isinstance(v, Path) else str(v)) for k, v in vars(args).items() if k != "func"},
        "exposure_limits_s": list(limits.exposure_s),
        "frames": ids, "n_gt": results[0]["n_gt"], "iopc": str(iopc_path), "iopc_name": iopc.name,
        "estimators": {"noise": noise_spec, "mtf": mtf_spec},
        "results": results, "decisions": decisions, "repeats": args.repeats,
        "decisions_per_repeat": [len(run["decisions"]) for run in runs],
        "alpha_per_repeat": [[d["alpha"] for d in run["decisions"]] for run in runs],
        "seconds": time.perf_counter() - t_start,
    }
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "closed_loop.json").write_text(json.dumps(_finite(res), indent=1, ensure_ascii=False))
    table = format_table(res)
    (out_dir / "closed_loop.md").write_text(table + "\n")
    _plot(out_dir / "closed_loop.png", res, examples, gt[example_frame], iopc, example_frame)
    print(table)
    print(f"\nwritten: {out_dir}/closed_loop.png, closed_loop.md, closed_loop.json ({res['seconds']:.0f} s)")
    return res


def _run_once(camera: Any, controllers: list[Any], detector: Any, gt: list[Any], size: tuple[int, int],
              example_frame: int, args: argparse.Namespace) -> dict[str, Any]:
    """One pass of the three controllers over the frames (the frame's three captures as one request)."""
    from camhealth.control import Observation
    from camhealth.detection import evaluate_detections

    params = [c.reset(args.exposure, args.gain) for c in controllers]
    traj: list[list[dict[str, Any]]] = [[] for _ in controllers]
    dets: list[list[Any]] = [[] for _ in controllers]
    examples: dict[str, Any] = {}
    for k in range(len(camera)):
        cap = camera.capture([k] * len(controllers), [p[0] for p in params], [p[1] for p in params])
        out = detector(cap.image)
        if k == example_frame:
            examples = {"image": cap.image.cpu(), "detections": out}
        for i, c in enumerate(controllers):
            obs = Observation(k, cap[i], out[i], params[i][0], params[i][1])
            traj[i].append({
                "frame": k, "exposure_ms": params[i][0] * 1e3, "gain_db": params[i][1],
                "blur_px": float(cap.blur_length_px[i]), "sigma_dn": float(cap.sigma_total_dn[i]),
                "mtf_true": float(0.5 * (cap.mtf[i, 1] + cap.mtf[i, 9])), "mean": float(cap.mean_intensity[i]),
                "n_det": int((out[i]["scores"] >= 0.5).sum()),
            })
            dets[i].append(out[i])
            params[i] = c.update(obs)
    results = []
    for i, c in enumerate(controllers):
        ap = evaluate_detections(dets[i], gt, size)
        tr = traj[i]
        results.append({
            "controller": c.name, "ap": ap.ap, "n_gt": ap.n_gt, "n_detections": ap.n_detections,
            "exposure_ms_median": float(np.median([r["exposure_ms"] for r in tr])),
            "gain_db_median": float(np.median([r["gain_db"] for r in tr])),
            "blur_px_median": float(np.median([r["blur_px"] for r in tr])),
            "sigma_dn_median": float(np.median([r["sigma_dn"] for r in tr])),
            "mean_intensity_median": float(np.median([r["mean"] for r in tr])),
            "trajectory": tr,
        })
    decisions = [
        {"frame": f, "alpha": d.alpha, "exposure_ms": d.exposure_s * 1e3, "gain_db": d.gain_db,
         "expected_ap": d.expected_ap, "current_ap": d.current_ap, "sigma_tilde": med["sigma_tilde"],
         "mtf_tilde": med["mtf_tilde"], "sigma_sources_tilde": med["sigma_sources_tilde"],
         "n_regions": med["n_regions"], "explanation": d.explanation}
        for f, d, med in controllers[2].decisions
    ]
    return {"results": results, "decisions": decisions, "examples": examples}


def _exposure_limits(args: argparse.Namespace) -> tuple[float, float]:
    """The controllers' exposure limits [s]: ``--limits-exposure``, with the longest exposure capped at what the
    simulated camera renders for the scene motion, MAX_MOTION_PX / motion (253 px of blur: 168.7 ms at 1500 px/s),
    so that no controller asks for an exposure the camera refuses."""
    from camhealth.control.camera_sim import MAX_MOTION_PX

    t_min, t_max = (float(v) for v in args.limits_exposure)
    _check_limits("--limits-exposure", t_min, t_max, "s")
    if args.motion > 0:
        cap = MAX_MOTION_PX / float(args.motion)
        while float(args.motion) * cap > MAX_MOTION_PX:  # the camera computes v·t: stay within it after rounding
            cap = math.nextafter(cap, 0.0)
        if cap < t_min:
            raise SystemExit(f"--motion {args.motion:g} px/s: the simulated camera renders at most {MAX_MOTION_PX:g} px of "
                             f"motion blur, i.e. exposures up to {cap * 1e3:.4g} ms, below the shortest exposure "
                             f"--limits-exposure {t_min * 1e3:g} ms; lower the motion or the exposure limit")
        t_max = min(t_max, cap)
    return t_min, t_max


def _check_limits(option: str, low: float, high: float, unit: str) -> None:
    """A ``MIN MAX`` pair of finite numbers with MIN <= MAX inside the simulated camera's range of the field
    (``METADATA_RANGES``: exposure 1–200 ms, gain 0–24 dB), else ``SystemExit`` naming the option and both values."""
    from camhealth.physics.metadata import METADATA_RANGES

    if not (math.isfinite(low) and math.isfinite(high)) or low > high:
        raise SystemExit(f"{option} {low:g} {high:g}: MIN must be <= MAX (both finite, in {unit})")
    lo, hi = METADATA_RANGES["exposure_s" if unit == "s" else "gain_db"]
    if low < lo or high > hi:
        raise SystemExit(f"{option} {low:g} {high:g}: must lie within the camera's range [{lo:g}, {hi:g}] {unit}")


def _reference_intensity(iopc: Any) -> float:
    """The mean intensity in (0, 1] of the IOPC's frames as its sweep's detector saw them (``--normalize-intensity``).

    The provenance's ``frames.mean_intensity`` is that mean, after ``SweepConfig.intensity`` scaled (and clipped)
    the frames, when the file also records ``frames.source_mean_intensity`` (the clean frames' mean). A file without
    ``source_mean_intensity`` records the clean frames' mean as ``mean_intensity``; its swept mean is estimated below.
    """
    frames = iopc.provenance.get("frames", {})
    ref = frames.get("mean_intensity")
    if ref is None:
        raise SystemExit("--normalize-intensity needs an IOPC whose provenance has frames.mean_intensity "
                         "(made by this version of python -m camhealth.iopc)")
    ref = float(ref)
    if "source_mean_intensity" not in frames:
        # mean_intensity is the unscaled mean m of the clean frames f; the sweep showed the detector min(k·f, 1) with
        # k = config.intensity. The mean of min(k·f, 1) cannot be recovered from m alone; k·m clipped to 1 is exact
        # when no pixel saturates (k <= 1 always) and an upper bound otherwise (min(·, 1) is concave).
        k = iopc.provenance.get("config", {}).get("intensity", 1.0)
        if not (isinstance(k, (int, float)) and not isinstance(k, bool) and math.isfinite(k) and k > 0):
            raise SystemExit(f"--normalize-intensity: the IOPC's provenance config.intensity = {k!r} is not a number > 0")
        ref = min(ref * float(k), 1.0)
    if not (math.isfinite(ref) and 0 < ref <= 1):
        raise SystemExit(f"--normalize-intensity: the IOPC frames' mean intensity {ref!r} is out of the allowed range "
                         "(0, 1]")
    return ref


def _finite(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def format_table(res: dict[str, Any]) -> str:
    """Markdown table of the closed-loop result, with the thesis's numbers for orientation."""
    c = res["config"]
    lim = res.get("exposure_limits_s", c["limits_exposure"])
    capped = " (longest exposure capped by the camera's motion-blur limit)" if lim[1] < c["limits_exposure"][1] else ""
    lines = [
        f"Closed loop on {len(res['frames'])} street frames ({c['frames']}), {res['n_gt']} pseudo-GT people; "
        f"{c['sensor']} at {c['temperature']:g} °C, illumination {c['illumination']:g}/s, motion "
        f"{c['motion']:g} px/s at {c['angle']:g}°; start {c['exposure'] * 1e3:g} ms / {c['gain']:g} dB; limits "
        f"{lim[0] * 1e3:g}–{lim[1] * 1e3:g} ms{capped}, {c['limits_gain'][0]:g}–"
        f"{c['limits_gain'][1]:g} dB; estimators noise={res['estimators']['noise']}, mtf={res['estimators']['mtf']}.",
        "",
        f"| controller | AP@0.5 (seed {c['seed']}) | AP@0.5 mean ± std over repeats | detections | exposure [ms] | gain [dB] "
        "| motion blur [px] | σ [DN] | mean intensity |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in res["results"]:
        lines.append(
            f"| {r['controller']} | {100 * r['ap']:.1f} % | {100 * r['ap_mean']:.1f} ± {100 * r['ap_std']:.1f} % "
            f"(n = {len(r['ap_runs'])}) | {r['n_detections']} | {r['exposure_ms_median']:.2f} | "
            f"{r['gain_db_median']:.1f} | {r['blur_px_median']:.1f} | {r['sigma_dn_median']:.2f} | "
            f"{r['mean_intensity_median']:.2f} |"
        )
    lines += ["", "Parameters, blur, σ (realised, before 8-bit rounding) and intensity: medians over the frames of "
              "the first repeat; repeats differ in the camera's noise seed. Thesis (real robot, YOLOv4 cars, Sec. 7.3): built-in auto-exposure "
              "26.1 %, fixed 47.5 %, framework 60.6 %."]
    for d in res["decisions"][:3]:
        lines += ["", f"Policy decision after frame {d['frame']}: {d['explanation']}"]
    if len(res["decisions"]) > 3:
        lines += ["", f"(+ {len(res['decisions']) - 3} later decisions in closed_loop.json)"]
    return "\n".join(lines)


def _plot(path: Path, res: dict[str, Any], examples: dict[str, Any], gt: Any, iopc: Any, frame: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    colors = ["tab:gray", "tab:red", "tab:blue"]
    fig = plt.figure(figsize=(17, 8.5))
    gs = fig.add_gridspec(2, 4, height_ratios=[1, 1.15])
    keys = [("exposure_ms", "exposure [ms]"), ("gain_db", "gain [dB]"), ("blur_px", "motion blur L [px] / σ [DN] (dashed)")]
    for j, (key, label) in enumerate(keys):
        ax = fig.add_subplot(gs[0, j])
        for r, col in zip(res["results"], colors):
            x = [t["frame"] for t in r["trajectory"]]
            ax.plot(x, [t[key] for t in r["trajectory"]], color=col, label=r["controller"], lw=1.8)
            if key == "blur_px":
                ax.plot(x, [t["sigma_dn"] for t in r["trajectory"]], color=col, ls="--", lw=1.2)
        ax.set_xlabel("frame"), ax.set_ylabel(label), ax.grid(alpha=0.3)
        if j == 0:
            ax.legend(fontsize=8)
    ax = fig.add_subplot(gs[0, 3])
    names = [r["controller"] for r in res["results"]]
    means = [100 * r["ap_mean"] for r in res["results"]]
    stds = [100 * r["ap_std"] for r in res["results"]]
    ax.bar(names, means, yerr=stds if res["repeats"] > 1 else None, color=colors, capsize=4)
    for i, (v, e) in enumerate(zip(means, stds)):
        ax.text(i, v + e + 1.5, f"{v:.1f} %" + (f" ± {e:.1f}" if res["repeats"] > 1 else ""), ha="center", fontsize=8)
    ax.set_ylim(0, 105), ax.set_ylabel(f"AP@0.5 [%] (mean of {res['repeats']} noise seed(s))"), ax.set_title("camhealth (thesis robot: 26.1 / 47.5 / 60.6 %)", fontsize=9)
    ax.tick_params(axis="x", labelsize=8)
    img = examples["image"]
    for i, (r, col) in enumerate(zip(res["results"], colors)):
        ax = fig.add_subplot(gs[1, i])
        ax.imshow(img[i, 0].numpy(), cmap="gray", vmin=0, vmax=1)
        for b in gt["boxes"].tolist():
            ax.add_patch(Rectangle((b[0], b[1]), b[2] - b[0], b[3] - b[1], fill=False, ec="deepskyblue", lw=1.5))
        d = examples["detections"][i]
        for b, s in zip(d["boxes"].tolist(), d["scores"].tolist()):
            if s >= 0.5:
                ax.add_patch(Rectangle((b[0], b[1]), b[2] - b[0], b[3] - b[1], fill=False, ec="orange", lw=1.5))
        t = r["trajectory"][frame]
        ax.set_title(f"{r['controller']}: {t['exposure_ms']:.1f} ms, {t['gain_db']:.1f} dB, L = {t['blur_px']:.1f} px, "
                     f"σ = {t['sigma_dn']:.1f} DN", fontsize=8)
        ax.axis("off")
    ax = fig.add_subplot(gs[1, 3])
    surf = np.ma.masked_invalid(iopc.ap_2d)
    mesh = ax.pcolormesh(_edges(iopc.mtf_bins), _edges(iopc.sigma_bins), surf, cmap="viridis", vmin=0, vmax=1)
    fig.colorbar(mesh, ax=ax, label="AP (IOPC)")
    ax.set_facecolor("#dddddd")
    for r, col in zip(res["results"], colors):
        ax.plot([t["mtf_true"] for t in r["trajectory"]], [t["sigma_dn"] for t in r["trajectory"]], "o", ms=6,
                color=col, mec="white", mew=0.8, label=r["controller"])
    ax.set_xlabel("MTF̃"), ax.set_ylabel("σ [DN]"), ax.set_title("IOPC (AP) and the controllers' operating points", fontsize=9)
    fig.suptitle("Closed loop: blue = pseudo ground truth, orange = detections (score ≥ 0.5), frame "
                 f"{frame} of the run", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _edges(centres: np.ndarray) -> np.ndarray:
    """Bin edges (midpoints, half a spacing beyond the ends) of possibly non-uniform bin centres."""
    c = np.asarray(centres, dtype=np.float64)
    mids = 0.5 * (c[1:] + c[:-1])
    return np.concatenate([[c[0] - (mids[0] - c[0])], mids, [c[-1] + (c[-1] - mids[-1])]])


#: Largest ``--seed`` (torch and numpy seeds are below 2**32), ``--repeats`` and ``--threads`` of the demos.
SEED_MAX = 2**32 - 1
REPEATS_MAX = 1000
THREADS_MAX = 4 * (os.cpu_count() or 1)


#: The demos: subcommand → the function that runs it on its options.
DEMOS: dict[str, Any] = {}


def build_parser():
    """jsonargparse parser with one subcommand per demo; ``--config FILE`` / ``--print_config`` before the
    subcommand cover all of it, after it the demo's own options (as LightningCLI's subcommands)."""
    p = config_parser(prog="python -m camhealth.demo", description=__doc__.split("\n\n")[0])
    sub = p.add_subcommands(dest="demo", required=True)
    c = config_parser(prog="python -m camhealth.demo closed-loop")
    c.add_argument("--iopc", default="runs/iopc_closed_loop/iopc.json",
                   help="IOPC file (default: the one configs/iopc_closed_loop.yaml writes, matched to this camera)")
    c.add_argument("--source", default="street", help="clean frames (camhealth.data.build_source spec)")
    c.add_argument("--frames", type=SliceOption(), default="25:50",
                   help="slice start:stop[:step] (or one index) of the source's frames (default 25:50)")
    c.add_argument("--sensor", default="ICX285", choices=["ICX285", "EV76C661"])
    c.add_argument("--temperature", type=float, default=25.0, help="sensor temperature [°C]")
    c.add_argument("--illumination", type=float, default=60.0,
                   help="scene illumination E [1/s]: a radiance of 1 fills the well in 1/E s at 0 dB (default 60)")
    c.add_argument("--motion", type=float, default=1500.0, help="scene motion [px/s] (default 1500)")
    c.add_argument("--angle", type=float, default=0.0, help="motion direction [deg] (default 0 = horizontal)")
    c.add_argument("--exposure", type=float, default=0.008, help="start (and fixed) exposure [s] (default 0.008)")
    c.add_argument("--gain", type=float, default=0.0, help="start (and fixed) gain [dB] (default 0)")
    c.add_argument("--limits-exposure", type=float, nargs=2, default=[0.001, 0.2], metavar=("MIN", "MAX"))
    c.add_argument("--limits-gain", type=float, nargs=2, default=[0.0, 24.0], metavar=("MIN", "MAX"))
    c.add_argument("--noise-estimator", default=None,
                   help="noise estimator spec (default: the one the IOPC was made with, from its provenance)")
    c.add_argument("--mtf-estimator", default=None, help="MTF estimator spec (default: as the IOPC's)")
    c.add_argument("--decide-every", type=IntAtLeast(1), default=None,
                   help="IOPC policy re-decides every n ≥ 1 frames (default: once, after the first frame)")
    c.add_argument("--normalize-intensity", action="store_true",
                   help="rescale σ̂ to the IOPC frames' brightness before the look-up (extension, see IOPCController)")
    c.add_argument("--min-gain", type=float, default=0.01, help="smallest expected AP gain for a change")
    c.add_argument("--pseudo-score", type=float, default=0.6, help="pseudo ground-truth score threshold")
    c.add_argument("--seed", type=IntRange(0, SEED_MAX), default=0, help="noise seed of the first repeat, 0…2**32 − 1")
    c.add_argument("--repeats", type=IntRange(1, REPEATS_MAX), default=1,
                   help=f"runs with noise seeds seed, seed+1, … (AP mean ± std), 1…{REPEATS_MAX}")
    c.add_argument("--threads", type=IntRange(1, THREADS_MAX, "4 × the CPU count"), default=None,
                   help="torch threads, 1…4 × the CPU count (default: torch's)")
    c.add_argument("--out", default="runs/demo", help="output folder (default runs/demo)")
    sub.add_subcommand("closed-loop", c, help="fixed vs auto-exposure vs IOPC policy on a simulated camera")
    DEMOS["closed-loop"] = run_closed_loop
    add_debug_flag(p)
    return p


def _check_options(options) -> None:
    """``ValueError`` naming the option, its value and its range, before any work (the IOPC, frames and detector
    load slowly): ``--pseudo-score`` outside [0, 1], ``--seed`` + ``--repeats`` past 2**32 − 1, an ``--out`` that is a
    file or lies under one, an ``--iopc`` that is a folder."""
    import math

    score = getattr(options, "pseudo_score", None)
    if score is not None and not (math.isfinite(score) and 0.0 <= score <= 1.0):
        raise ValueError(f"--pseudo-score must be in [0, 1], got {score}")
    seed, repeats = getattr(options, "seed", None), getattr(options, "repeats", None)
    if seed is not None and repeats is not None and seed + repeats - 1 > SEED_MAX:
        raise ValueError(f"--seed {seed} + --repeats {repeats} − 1 must be ≤ {SEED_MAX} (the seeds of the repeats)")
    out = getattr(options, "out", None)
    if out is not None:
        path = Path(out)
        node = path
        while not node.exists() and node != node.parent:
            node = node.parent
        if node.exists() and not node.is_dir():
            raise ValueError(f"--out {out}: {node} is a file, where the output folder was to be made or written into")
    iopc = getattr(options, "iopc", None)
    if iopc is not None and Path(str(iopc)).is_dir():
        raise ValueError(f"--iopc {iopc}: is a folder; give the IOPC file (.json)")


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    options = args[args.demo]
    for option in ("limits_exposure", "limits_gain"):  # before any work (the IOPC, frames and detector load slowly)
        if getattr(options, option, None) is not None:
            low, high = (float(v) for v in getattr(options, option))
            _check_limits("--" + option.replace("_", "-"), low, high, "s" if option == "limits_exposure" else "dB")
    _check_options(options)
    if getattr(options, "threads", None) is not None:
        torch.set_num_threads(options.threads)
    DEMOS[args.demo](options)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main, "python -m camhealth.demo"))
