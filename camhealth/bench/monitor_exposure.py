"""``python -m camhealth.bench monitor --exposure-step``: the monitor on a camera whose exposure time steps between
two values (an auto-exposure), with and without the evidence it keeps from the other exposure time.

One camera state cannot split a signal-independent excess between dark-current shot noise and readout noise: both
add a constant to the noise-level function. Their dependence on the exposure time differs (σ_DCSN² ∝ t_exp,
conventions Eq. 3.15; σ_RN does not depend on it), so frames of the same camera at two exposure times split them.
The monitor keeps each state's latest noise evidence and adds it to frames whose metadata differ only in the
exposure time (``Monitor(exposure_evidence=True)``, the default; :mod:`camhealth.monitor.api`). This scenario
measures what that does on frames camhealth's simulator did not make.

Frames: the embedded street clip (768×576, people walking past a static background) resized bilinearly to
``--width``×``--height``, corrupted by the independent implementation of the sensor model
(:func:`camhealth.bench.sensor_variants.simulate_variant`, NumPy, written from the equations; a fresh noise
realisation per frame) and rounded to 8 bits. The exposure time alternates between ``--exposure-ratio`` ×
``--exposure-s`` (even frames) and ``--exposure-s`` (odd frames); the image brightness stays the same (the model's
input is the output intensity, as an auto-exposure that trades gain elsewhere keeps it). Every frame comes with
its metadata (``--sensor`` at ``--gain-db`` and ``--temperature-c``, the frame's exposure time). Three cameras:

* ``matched`` — the camera is what its metadata say;
* ``hotter sensor`` — the sensor is :data:`HOTTER_K` K warmer than its metadata say (dark current up);
* ``white noise ×3`` — the read-out chain's white noise is :data:`WHITE_NOISE_FACTOR` × the metadata's (readout
  noise up).

Each camera's frames go through four monitors — sampled mode (the default) and map mode, each with
``exposure_evidence`` on (the default) and off — one frame to each in turn, so all see the same machine load.

Truth: each frame's realised dark-current and readout noise [DN] over the whole frame (the simulator's labels).
Both are signal-independent, so every patch shares them (clipped pixels aside). The photon shot noise depends on
each patch's signal, and a frame's median over patches is not a whole-frame value; it is left out of the error.
Reported per camera and monitor, over the frames from the second on (the first has no other exposure time to
draw on), separately for the long and the short exposure: the RMS and the mean of the error of the frame's σ_DCSN
and σ_RN (the frame report's ``median``) against the truth, the frames whose alarm says ``noisier`` (the visible excesses)
or ``ok``, and of the frames with a ``cause`` (their patches follow the image) those whose most probable cause is
the camera's (dark current, readout noise). ms/frame of each monitor in the timing rows (``Monitor.process`` plus the JSON line).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import math
import time
from typing import Any

import torch

from camhealth.bench import BenchResult, Row

#: The hotter camera's sensor is this much warmer than its metadata say [K].
HOTTER_K = 25.0
#: The white-noise camera's read-out white noise is this multiple of the metadata's.
WHITE_NOISE_FACTOR = 3.0
CAMERAS = ("matched", "hotter sensor", "white noise ×3")
#: The cause (:data:`camhealth.monitor.api.CAUSE_GROUPS`) each camera's mismatch is (None: none).
CAUSE_OF = {"matched": None, "hotter sensor": "dark_current", "white noise ×3": "readout"}
MODES = ("sampled", "map")


def _clean_frames(frames: int, size: tuple[int, int]) -> torch.Tensor:
    """T×1×H×W street frames in [0, 1], resized bilinearly."""
    import kornia

    from camhealth.data import street_sequence

    clip = torch.stack([f for f, _ in street_sequence(max_frames=frames)])
    if clip.shape[0] < frames:
        raise ValueError(f"--frames {frames} exceeds the {clip.shape[0]} frames of the street clip")
    return kornia.geometry.resize(clip, size, interpolation="bilinear", antialias=False).clamp(0, 1)


def _overrides(camera: str, meta) -> dict[str, float] | None:
    if camera == "hotter sensor":
        return {"temperature_c": float(meta.temperature_c) + HOTTER_K}
    if camera == "white noise ×3":
        return {"white_noise_v_per_rthz": float(meta.white_noise_v_per_rthz) * WHITE_NOISE_FACTOR}
    return None


def exposure_stream(clean: torch.Tensor, meta, exposures: list[float], camera: str, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 T×H×W frames of ``camera`` (one of :data:`CAMERAS`) at the given exposure times, and the realised
    σ (T, 3) of photon, dark-current and readout noise [DN] of each frame (the independent simulator's labels)."""
    from camhealth.bench.sensor_variants import simulate_variant

    if camera not in CAMERAS:
        raise ValueError(f"camera = {camera!r} must be one of {list(CAMERAS)}")
    gen = torch.Generator().manual_seed(seed)
    frames, truth = [], []
    for i, t in enumerate(exposures):
        m = meta.replace(exposure_s=torch.tensor([t], dtype=torch.float64))
        x, s = simulate_variant(clean[i : i + 1], m, (), gen, _overrides(camera, m))
        frames.append((x[0, 0] * 255.0).round().clamp(0, 255).to(torch.uint8))
        truth.append(s[0])
    return torch.stack(frames), torch.stack(truth)


def _rms(errors: list[float]) -> float:
    return math.sqrt(sum(e * e for e in errors) / len(errors)) if errors else float("nan")


def _mean(errors: list[float]) -> float:
    return sum(errors) / len(errors) if errors else float("nan")


def run_exposure_step(args: argparse.Namespace) -> BenchResult:
    from camhealth.bench.corruption import _load, machine_description
    from camhealth.monitor import Monitor
    from camhealth.monitor.api import top_cause
    from camhealth.physics import CameraMetadata

    ratio = float(args.exposure_ratio)
    if not (math.isfinite(ratio) and ratio > 1.0):
        raise ValueError(f"--exposure-ratio = {args.exposure_ratio} must be a number > 1 (long / short exposure time)")
    if args.frames < 3:
        raise ValueError(f"--frames must be >= 3 with --exposure-step (two exposure times, then the error), got {args.frames}")
    t_short = float(args.exposure_s)
    t_long = t_short * ratio
    told = {"gain_db": float(args.gain_db), "exposure_s": t_long, "temperature_c": float(args.temperature_c)}
    meta = CameraMetadata.preset(args.sensor, **told)  # checks every field's range, the long exposure time included
    CameraMetadata.preset(args.sensor, **{**told, "exposure_s": t_short})
    exposures = [t_long if i % 2 == 0 else t_short for i in range(args.frames)]
    load_before = _load()
    clean = _clean_frames(args.frames, (args.height, args.width))
    w0 = 1  # the first frame has no other exposure time to draw on
    rows: list[Row] = []
    table = [
        "| camera | monitor | exposure evidence | σ_DCSN error, long / short: RMS (mean) [DN] | σ_RN error, long / short: "
        "RMS (mean) [DN] | true σ_DCSN / σ_RN, long [DN] | alarm noisier / ok | cause named: right / frames with one | "
        "other exposure times used |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for camera in CAMERAS:
        frames, truth = exposure_stream(clean, meta, exposures, camera, args.seed)
        mons = {(mode, kept): Monitor(args.noise_model, None, sensor=args.sensor, metadata=told, mode=mode,
                                      exposure_evidence=kept, precision=args.precision)
                for mode in MODES for kept in (True, False)}
        got: dict[Any, list] = {k: [] for k in mons}
        times: dict[Any, list[float]] = {k: [] for k in mons}
        for i in range(frames.shape[0]):
            for k, mon in mons.items():
                t0 = time.perf_counter()
                rep = mon.process(frames[i], {"exposure_s": exposures[i]})
                rep.to_json()
                times[k].append((time.perf_counter() - t0) * 1e3)
                got[k].append(rep)
        for (mode, kept), reps in got.items():
            err = {(q, long): [] for q in (1, 2) for long in (True, False)}
            states, other, causes = [], [], []
            for i in range(w0, len(reps)):
                r = reps[i]
                states.append(r.alarm.get("state"))
                if r.noise is not None and r.noise.cause:  # the most probable cause of the frame's followed patches
                    causes.append(top_cause(r.noise.cause))
                other.append(int(r.noise.coverage.get("other_exposures", 0)) if r.noise is not None else 0)
                if r.noise is None or not r.noise.assessable:
                    continue
                for q in (1, 2):
                    err[(q, i % 2 == 0)].append(float(r.noise.median[q]) - float(truth[i, q]))

            def cell(q: int) -> str:
                return " / ".join(f"{_rms(e):.2f} ({_mean(e):+.2f})" for e in (err[(q, True)], err[(q, False)]))

            long_truth = truth[0::2]
            n = len(states)
            table.append(
                f"| {camera} | {mode} | {'on' if kept else 'off'} | {cell(1)} | {cell(2)} | "
                f"{float(long_truth[:, 1].mean()):.2f} / {float(long_truth[:, 2].mean()):.2f} | "
                f"{states.count('noisier')}/{n} / {states.count('ok')}/{n} | "
                f"{'–' if CAUSE_OF[camera] is None else causes.count(CAUSE_OF[camera])} / {len(causes)} | "
                f"{sum(1 for o in other if o > 0)}/{n} |")
            rows.append(Row(f"{camera}: {mode}, exposure evidence {'on' if kept else 'off'}", times[(mode, kept)][w0:],
                            note="ms per frame"))
    header = [
        f"machine: {machine_description()}",
        f"load average before: {load_before} (1/5/15 min); date {_dt.date.today().isoformat()}",
        f"{args.frames} street frames of {args.width}×{args.height} uint8, the independent sensor model "
        f"(camhealth.bench.sensor_variants); {args.sensor} at {args.gain_db:g} dB, {args.temperature_c:g} °C told, the "
        f"exposure alternating {t_long * 1e3:g} / {t_short * 1e3:g} ms (×{ratio:g}); cameras: matched, sensor "
        f"{HOTTER_K:g} K hotter, white noise ×{WHITE_NOISE_FACTOR:g}; precision {args.precision}; errors over frames "
        f"{w0 + 1}…{args.frames} (long: the odd-numbered frames from the third on, short: the even-numbered ones)",
        f"command: {getattr(args, 'command_line', 'python -m camhealth.bench monitor --exposure-step')}",
    ]
    summary = table + ["", f"load average after: {_load()}"]
    title = f"Monitor on an exposure time stepping ×{ratio:g}, {args.width}×{args.height} frames (ms per frame)"
    return BenchResult(title, rows, rows[0].name, header=header, summary=summary)
