"""``python -m camhealth.bench monitor``: ms per 1280×1024 8-bit frame of the real-time monitor, the saving
of scene-adaptive patch selection, its accuracy, and the thesis-size noise network on the same patches.

Frames: the embedded street clip (``--scene street``; 768×576, people walking past a static background)
upscaled bilinearly to ``--width``×``--height`` (default 1280×1024), or a static dead-leaves scene
(``--scene deadleaves``), optionally over-exposed (``--brightness`` > 1 scales the scene and clips it, so
that saturated patches appear and the saving of skipping them shows), blurred by a defocus disk of
``--defocus-px`` px and corrupted with the full sensor-noise chain of :func:`camhealth.physics.form_image`
(``--sensor`` at ``--gain-db``, ``--exposure-s``, ``--temperature-c``; a fresh noise realisation per
frame), quantised to 8 bits (uint8 DN, what a camera delivers). The monitor gets the matching metadata.

Rows (round-robin per frame, so every row sees the same frames under the same machine load; each time is
``Monitor.process`` of one uint8 frame plus its JSON line, i.e. conversion, tiling, patch statistics,
selection, batched inference, aggregation and report):

* ``every patch`` — all 128-px and 192-px patches estimated, no skipping (``skip_uninformative=False``);
* ``informative patches`` — every informative patch of every frame ("fully monitored": noise sources on
  every informative 128-px patch, MTF on every informative 192-px patch) — the baseline of the ratio column;
* ``adaptive`` — the monitor's default: skip + static-region reuse + coarse lattice → refine; the first
  timed frame is cold (state reset), the rest are a stream;
* ``adaptive, monitor alone in its process`` — the adaptive monitor run by itself in a fresh interpreter on the
  same frames (as ``python -m camhealth.monitor`` runs; interleaving three monitors in one process costs each
  of them cache and allocator traffic that a deployed monitor does not see), first ``--warmup`` frames not
  counted; this is the row the ≤ 100 ms target is judged on (skipped with ``--no-memory-probe``);
* ``informative patches + static pairs`` (with ``--static-pairs``) — as ``informative patches``, with
  ``static_pairs=True``: each noise patch is also read against the same patch of the previous frame where the
  scene stood still (:mod:`camhealth.estimators.static_pair`); a summary line gives the patches per frame read from
  a pair and the answers against the realised σ and against those of ``informative patches``. (The adaptive
  monitor reuses a still patch's estimate until it is due again, so there pairs are read at that rate);
* ``informative, fp32`` — as ``informative`` with fp32 networks (first ``--slow-frames`` frames);
* the note of the monitor rows gives the median **CPU time** per frame (``time.process_time``, all threads):
  on a machine shared with other jobs it is what the frame costs independent of the load (with one thread it
  is the wall time on an idle core);
* ``thesis-size noise net`` — :class:`camhealth.nets.drne.ThesisNoiseNet` (16 full-resolution
  64-channel layers, fp32) on ``--thesis-patches`` of the same informative noise patches, scaled to all
  of them (first ``--slow-frames`` frames); the note gives the speed ratio to the camhealth noise
  estimator on the same patches.

* ``reading the recording (.mcap / .db3 / .bag)`` — the same uint8 frames written as ``sensor_msgs/Image`` (mono8)
  with a gain topic (``std_msgs/Float64``, one value per frame) into an MCAP file, a ROS 2 SQLite3 file and a
  ROS 1 bag (``camhealth.data.rosbag.RecordingWriter``), then read as ``python -m camhealth.monitor REC --topic
  … --gain-topic …`` reads them (``camhealth.monitor.sources.open_source``): per frame the time to get the next
  item — read, deserialise, convert to a gray tensor, match the gain — plus building that frame's metadata from
  the recorded gain (``CameraMetadata.replace``, what ``Monitor.process`` does with it), timed in the same
  round-robin rounds as the monitor rows (same machine load). The note gives it as a percentage of the
  adaptive monitor's per-frame time in those rounds: the overhead reading a recording adds (target ≤ 10 %).
  The files are freshly written, so they are read from the page cache (a recording on a slow disk adds its
  read time).

Summary lines: patches estimated per frame (saving of skipping and of the adaptive scheme, skip reasons);
accuracy on the informative patches of ``adaptive`` vs ``informative`` against the truth — σ_total
Bias/Std/RMS (Eq. 6.2, DN; truth: the realised σ of the noise in each patch, ``image − noise-free``,
including quantisation) and MTF AMAE (Eq. 5.1, %; truth: the MTF of the applied defocus disk; the street
frames carry their own camera and upscaling blur on top, so AMAE is a consistency measure there) and the
RMS difference between the two; bf16 vs fp32 differences; peak resident memory (``VmHWM``) of one adaptive
monitor alone in a fresh interpreter (the frames, models, Python and torch included), and of this process
after the three monitor rows and after the slow rows; the machine and its load average before and after.
``--true-gain-db``: the frames come from a sensor at that gain while the monitors are told ``--gain-db`` (a metadata
mismatch); the ξ line then gives the ξ of a right answer — the metadata's closed form after clipping
(:func:`~camhealth.estimators.noise_features.physics_prior_dn`) less the realised σ, median over the informative
patches — beside the median ξ of the informative and adaptive monitors (and the pairs' line, theirs).
``--batch``/``--size``/``--repeats`` of the common options are not used (set, they are refused; the frame count is
``--frames``).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import resource
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from camhealth.bench import BenchResult, Row

HELP = ("ms per 1280×1024 frame of the monitor (every / informative / adaptive patches), accuracy, thesis-size net, "
        "reading a recording")

#: The common options this benchmark reads (the others are refused: camhealth.bench.check_options).
COMMON_READS = ('seed', 'warmup')

ALL = "every patch (no skipping)"
INFORMATIVE = "informative patches (fully monitored)"
ADAPTIVE = "adaptive (skip + reuse static + coarse→refine)"
PAIRS = "informative patches + static pairs"
ALONE = "adaptive, monitor alone in its process"
FP32 = "informative patches, fp32"
THESIS = "thesis-size noise net, same noise patches"
RECORDING = "reading the recording ({})"
RECORDING_FORMATS = (".mcap", ".db3", ".bag")
TARGET_MS = 100.0
TARGET_RECORDING_PCT = 10.0
TARGET_RSS_MB = 1024.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frames", type=int, default=16, help="frames in the timed stream (default 16)")
    parser.add_argument("--width", type=int, default=1280, help="frame width in px (default 1280)")
    parser.add_argument("--height", type=int, default=1024, help="frame height in px (default 1024)")
    parser.add_argument("--scene", choices=("street", "deadleaves"), default="street", help="frame content (default street)")
    parser.add_argument("--noise-model", default="noise_source_full",
                        help="noise estimator name or file (default noise_source_full)")
    parser.add_argument("--mtf-model", default="mtf", help="MTF estimator name or file (default mtf)")
    parser.add_argument("--untrained", action="store_true",
                        help="use freshly initialised networks of the shipped architectures (timing only; accuracy meaningless)")
    parser.add_argument("--sensor", default="ICX285", help="sensor preset of the noise and the metadata (default ICX285)")
    parser.add_argument("--gain-db", type=float, default=12.0, help="gain in dB (default 12)")
    parser.add_argument("--exposure-s", type=float, default=0.01, help="exposure in s (default 0.01)")
    parser.add_argument("--temperature-c", type=float, default=40.0, help="sensor temperature in °C (default 40)")
    parser.add_argument("--brightness", type=float, default=1.0,
                        help="scale the clean scene's intensity (>1 over-exposes: saturated patches to skip; default 1)")
    parser.add_argument("--defocus-px", type=float, default=3.0,
                        help="defocus disk diameter in px applied to every frame (default 3)")
    parser.add_argument("--precision", choices=("bf16", "fp32"), default="bf16",
                        help="precision of the monitor rows (default bf16)")
    parser.add_argument("--device", default="cpu",
                        help="where the monitors' networks (and noise_source_full's posterior) run: cpu (default), cuda "
                             "or cuda:N; frame statistics stay on the CPU")
    parser.add_argument("--no-memory-probe", dest="memory_probe", action="store_false",
                        help="skip the peak-memory run of one monitor in a fresh interpreter")
    parser.add_argument("--slow-frames", type=int, default=2,
                        help="frames timed for the fp32 and thesis-size rows (default 2; 0: no such rows)")
    parser.add_argument("--thesis-patches", type=int, default=4,
                        help="patches the thesis-size net is timed on (default 4; 0: no thesis row)")
    parser.add_argument("--static-pairs", action="store_true",
                        help="add the row 'informative patches + static pairs' (every informative patch every frame, each noise "
                             "patch also read against the previous frame where the scene stood still: "
                             "Monitor(static_pairs=True, adaptive=False)); the street clip is a still camera with people walking "
                             "past, --scene deadleaves a scene where nothing moves")
    parser.add_argument("--motion", action="store_true",
                        help="moving-camera benchmark: sampled mode vs every informative patch on the static street clip, "
                             "the clip with simulated ego-motion and unrelated photographs (see camhealth.bench.monitor_motion)")
    parser.add_argument("--noise-samples", type=int, default=8, help="--motion: noise patches per frame in sampled mode (default 8)")
    parser.add_argument("--mtf-samples", type=int, default=6, help="--motion: MTF patches per frame in sampled mode (default 6)")
    parser.add_argument("--window", type=int, default=5, help="--motion: frames of the temporal aggregation (default 5)")
    parser.add_argument("--backends", action="store_true",
                        help="--motion: also time the sampled monitor with the MTF network exported to .pt2 and ONNX")
    parser.add_argument("--exposure-step", action="store_true",
                        help="the monitor on an exposure time alternating --exposure-ratio × --exposure-s / --exposure-s, "
                             "with and without the other exposure time's evidence, on three cameras (see "
                             "camhealth.bench.monitor_exposure)")
    parser.add_argument("--exposure-ratio", type=float, default=8.0,
                        help="--exposure-step: long / short exposure time (default 8)")
    parser.add_argument("--pool-sizes", action="store_true",
                        help="the pooled noise estimator reading a frame's patches in groups of 1…12 and whole, on "
                             "photographs of the independent sensor model, as told and --pool-step-db louder (see "
                             "camhealth.bench.monitor_pool: the measurement behind NOISE_MIN_POOL)")
    parser.add_argument("--pool-step-db", type=float, default=12.0,
                        help="--pool-sizes: how much louder than told the second camera's gain is, dB (default 12)")
    parser.add_argument("--pool-draws", type=int, default=4,
                        help="--pool-sizes: noise realisations per photograph and camera (default 4)")
    parser.add_argument("--true-gain-db", type=float, default=None,
                        help="the sensor's real gain in dB when it differs from the metadata's --gain-db (a metadata "
                             "mismatch: ξ ≠ 0; the summary compares each monitor's ξ with the closed form of the metadata "
                             "less the realised σ; default: the same)")


def _frames(args: argparse.Namespace, meta) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(uint8 frames T×H×W, noise-free blurred frames T×H×W in [0, 1], true MTF (16,))."""
    import kornia

    from camhealth.physics import defocus_psf, form_image, mtf_hv

    t, h, w = args.frames, args.height, args.width
    if args.scene == "street":
        from camhealth.data import street_sequence

        clean = torch.stack([f for f, _ in street_sequence(max_frames=t)])
        if clean.shape[0] < t:
            raise ValueError(f"--frames {t} exceeds the {clean.shape[0]} frames of the street clip")
        clean = kornia.geometry.resize(clean, (h, w), interpolation="bilinear", antialias=False).clamp(0, 1)
    else:
        from camhealth.data import dead_leaves

        clean = dead_leaves((h, w), r_min=3.0, seed=args.seed)[None].expand(t, -1, -1, -1).contiguous()
    if args.brightness != 1.0:
        clean = (clean * args.brightness).clamp(0, 1)
    k = max(3, int(2 * (args.defocus_px // 2) + 3))
    psf = defocus_psf(torch.tensor([float(args.defocus_px)]), k)
    gen = torch.Generator().manual_seed(args.seed)
    noisy, blurred = [], []
    for i in range(t):  # one frame at a time keeps the peak memory of the set-up low
        out = form_image(clean[i : i + 1], meta, defocus_psf=psf, generator=gen)
        noisy.append((out.image[0, 0] * 255.0).round().clamp(0, 255).to(torch.uint8))
        blurred.append(out.blurred[0, 0].float())
    return torch.stack(noisy), torch.stack(blurred), mtf_hv(psf)[0].float()


def _models(args: argparse.Namespace, tmp: Path) -> tuple[Any, Any]:
    if not args.untrained:
        return args.noise_model, args.mtf_model
    from camhealth.export import export_weights
    from lightning_modules import MTFEstimator, NoiseSourceEstimator

    torch.manual_seed(args.seed)
    return (export_weights(NoiseSourceEstimator(), tmp / "noise_source_untrained.pt"),
            export_weights(MTFEstimator(), tmp / "mtf_untrained.pt"))


def _truth_sigma(noisy: torch.Tensor, blurred: torch.Tensor, grid) -> torch.Tensor:
    """Realised σ_total [DN] of every noise patch: std of (8-bit image − noise-free image)."""
    diff = noisy.float() - blurred * 255.0
    return grid.extract(diff).flatten(1).std(1, unbiased=False)


def _has_value(report) -> torch.Tensor:
    from camhealth.monitor.tiling import ESTIMATED, INTERPOLATED, REUSED

    code = report.code
    return ((code == ESTIMATED) | (code == INTERPOLATED) | (code == REUSED)) & torch.isfinite(report.values[:, -1])


#: The mode flags of ``monitor`` (each a different benchmark) and the options each mode reads (``None``: the default
#: mode). An option a mode does not read is refused when given (the table's command line would claim it).
_MODE_FLAGS = {"motion": "--motion", "pool_sizes": "--pool-sizes", "exposure_step": "--exposure-step"}
_MODE_ONLY = {"noise_samples", "mtf_samples", "window", "backends", "exposure_ratio", "pool_step_db", "pool_draws"}
_COMMON_MONITOR = {"sensor", "gain_db", "exposure_s", "temperature_c", "noise_model"}
_READS = {
    "motion": _COMMON_MONITOR | {"frames", "width", "height", "defocus_px", "precision", "mtf_model", "untrained",
                                 "memory_probe", "slow_frames", "thesis_patches", "true_gain_db", "warmup",
                                 "noise_samples", "mtf_samples", "window", "backends"},
    "pool_sizes": _COMMON_MONITOR | {"pool_step_db", "pool_draws"},
    "exposure_step": _COMMON_MONITOR | {"frames", "width", "height", "precision", "exposure_ratio"},
}


#: Largest ``--width`` and ``--height`` [px]: 8192 (an 8K sensor's 7680 fits), 6.4× the default 1280 × 1024 on a
#: side. The frames are made before any row runs and kept: a pixel holds ≈ 9 bytes (the uint8 frame, the float32 clean
#: scene and noise-free frame; --motion ≈ 15, three streams), 600 MB a frame at 8192 × 8192.
FRAME_SIDE_MAX = 8192
#: Most ``--frames``: 1000 (the street clip has 50; ``--scene deadleaves`` repeats one scene), ≈ 60× the docs' 16.
FRAMES_MAX = 1000
#: Most pixels of all the frames, ``--frames`` × ``--width`` × ``--height``: 2**28 (16 frames of 4096 × 4096, or 204 of
#: the default 1280 × 1024; 12.8× the docs' 16 default frames): ≈ 2.4 GB of frames (≈ 4 GB with --motion).
FRAME_PIXELS_MAX = 2**28
#: Most ``--pool-draws``: 16× the default 4 (every photograph is read 2 × draws times, each in groups of 1…12 patches).
POOL_DRAWS_MAX = 64


def check_sizes(args: argparse.Namespace) -> None:
    """``ValueError`` naming the option and its value where a size or count of the chosen mode is out of its range:
    ``--width``/``--height`` (1…:data:`FRAME_SIDE_MAX`), ``--frames`` (…:data:`FRAMES_MAX`; the lower bound is the
    mode's own check) and all the frames' pixels (:data:`FRAME_PIXELS_MAX`), ``--device`` a device of this machine,
    ``--noise-samples``/``--mtf-samples`` and ``--window`` the monitor's ranges (``MAX_SAMPLES``, ``MAX_WINDOW`` of
    :mod:`camhealth.monitor.api`), ``--pool-draws`` (1…:data:`POOL_DRAWS_MAX`)."""
    from camhealth.bench import check_count, check_device_option

    mode = next((dest for dest in _MODE_FLAGS if getattr(args, dest, False)), None)
    if mode == "pool_sizes":  # (too few draws, a draw that is no integer: the mode's own check)
        draws = args.pool_draws
        if isinstance(draws, int) and draws > POOL_DRAWS_MAX:
            raise ValueError(f"--pool-draws must be an integer <= {POOL_DRAWS_MAX}, got {draws} "
                             f"(allowed: 1 … {POOL_DRAWS_MAX})")
        return
    check_count("--width", args.width, 1, FRAME_SIDE_MAX)
    check_count("--height", args.height, 1, FRAME_SIDE_MAX)
    if args.frames > FRAMES_MAX:  # (the fewest frames are the mode's own check)
        fewest = {None: 1, "motion": 2, "exposure_step": 3}[mode]
        raise ValueError(f"--frames must be <= {FRAMES_MAX}, got {args.frames} (allowed: {fewest} … {FRAMES_MAX})")
    pixels = args.frames * args.width * args.height
    if pixels > FRAME_PIXELS_MAX:
        raise ValueError(f"--frames {args.frames} × --width {args.width} × --height {args.height} = {pixels} px of frames "
                         f"must be <= {FRAME_PIXELS_MAX} (= 2**28; the frames are all kept in memory): use fewer or "
                         "smaller frames")
    if mode is None:
        check_device_option(args.device)
    if mode == "motion":
        from camhealth.monitor.api import MAX_SAMPLES, MAX_WINDOW

        check_count("--noise-samples", args.noise_samples, 1, MAX_SAMPLES)
        check_count("--mtf-samples", args.mtf_samples, 1, MAX_SAMPLES)
        check_count("--window", args.window, 1, MAX_WINDOW)


def check_options(args: argparse.Namespace) -> None:
    """The options of ``args`` for its mode (:func:`check_mode_options`), then their sizes (:func:`check_sizes`)."""
    check_mode_options(args)
    check_sizes(args)


def check_mode_options(args: argparse.Namespace) -> None:
    """``ValueError`` naming the options when two mode flags are given (``--motion``, ``--pool-sizes``,
    ``--exposure-step`` are different benchmarks), when an option is given that the chosen mode does not read
    (``--device`` with ``--motion``, ``--noise-samples`` without it, …: the table's header would record it), and, in
    the default mode with the memory probe, when ``--warmup`` ≥ ``--frames`` (the headline row would have no frame)."""
    modes = [flag for dest, flag in _MODE_FLAGS.items() if getattr(args, dest, False)]
    if len(modes) > 1:
        raise ValueError(f"{modes[0]} and {modes[1]} are different benchmarks: give one of them per run")
    mode = next((dest for dest in _MODE_FLAGS if getattr(args, dest, False)), None)
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--warmup", type=int, default=2)
    add_arguments(parser)
    names = {a.dest: a.option_strings[0] for a in parser._actions if a.option_strings}
    defaults = vars(parser.parse_args([]))
    for dest, default in defaults.items():
        if dest in _MODE_FLAGS or not hasattr(args, dest):
            continue
        reads = dest not in _MODE_ONLY if mode is None else dest in _READS[mode]
        value = getattr(args, dest)
        if not reads and value != default:
            shown = names[dest] if isinstance(default, bool) else f"{names[dest]} {value}"
            where = modes[0] if modes else "the default monitor benchmark (without --motion, --pool-sizes or --exposure-step)"
            raise ValueError(f"{shown} is not used by {where}; leave it out")
    if mode is None and getattr(args, "memory_probe", True) and 1 <= args.frames <= args.warmup:  # (--frames 0: its own check)
        raise ValueError(f"--warmup {args.warmup} must be smaller than --frames {args.frames} (the row of the monitor alone "
                         "in its process leaves out the warm-up frames), or pass --no-memory-probe")


def run(args: argparse.Namespace) -> BenchResult:
    from camhealth.bench.corruption import _load
    from camhealth.physics import CameraMetadata

    check_options(args)
    if getattr(args, "motion", False):
        from camhealth.bench.monitor_motion import run_motion

        return run_motion(args)
    if getattr(args, "pool_sizes", False):
        from camhealth.bench.monitor_pool import run_pool_sizes

        return run_pool_sizes(args)
    if getattr(args, "exposure_step", False):
        from camhealth.bench.monitor_exposure import run_exposure_step

        return run_exposure_step(args)
    checks = ((args.frames, "--frames", 1), (args.slow_frames, "--slow-frames", 0), (args.thesis_patches, "--thesis-patches", 0),
              (args.width, "--width", 1), (args.height, "--height", 1))
    for v, name, lo in checks:
        if v < lo:
            raise ValueError(f"{name} must be >= {lo}, got {v}")
    if not args.brightness > 0:
        raise ValueError(f"--brightness must be > 0, got {args.brightness}")
    from camhealth.runtime import keep_freed_memory

    keep_freed_memory()  # as python -m camhealth.monitor does
    load_before = _load()
    rss_start = peak_rss_mb()
    meta = CameraMetadata.preset(args.sensor, gain_db=args.gain_db, exposure_s=args.exposure_s, temperature_c=args.temperature_c)
    true_gain = getattr(args, "true_gain_db", None)
    frames, blurred, mtf_true = _frames(args, meta if true_gain is None else meta.replace(gain_db=true_gain))
    tmpdir = Path(tempfile.mkdtemp(prefix="camhealth_bench_monitor_"))
    try:
        return _run(args, meta, frames, blurred, mtf_true, tmpdir, load_before, rss_start)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)


def peak_rss_mb() -> float:
    """Peak resident memory of this process [MB]: ``VmHWM`` of ``/proc/self/status`` (the high-water mark of
    this address space, reset by ``exec``), else ``ru_maxrss`` (which a child inherits from its parent)."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def rss_probe(config_path: str) -> dict[str, float]:
    """Peak resident memory of one adaptive :class:`Monitor` alone: run in a fresh interpreter by the
    benchmark (``config_path``: JSON with the frames file, models, metadata, precision, threads)."""
    import json

    from camhealth.monitor import Monitor
    from camhealth.physics import CameraMetadata

    from camhealth.runtime import keep_freed_memory

    cfg = json.loads(Path(config_path).read_text())
    torch.set_num_threads(int(cfg["threads"]))
    keep_freed_memory()
    frames = torch.load(cfg["frames"], weights_only=True)
    start = peak_rss_mb()
    mon = Monitor(cfg["noise_model"], cfg["mtf_model"], metadata=CameraMetadata(**cfg["metadata"]), precision=cfg["precision"],
                  mode=cfg.get("mode", "map"), **cfg.get("kwargs", {}))
    ms, cpu = [], []
    with torch.inference_mode():
        for f in frames:
            c0, t0 = time.process_time(), time.perf_counter()
            mon.process(f).to_json()
            ms.append((time.perf_counter() - t0) * 1e3)
            cpu.append((time.process_time() - c0) * 1e3)
    return {"start_mb": start, "peak_mb": peak_rss_mb(), "ms": ms, "cpu_ms": cpu}


def _probe_memory(
    args: argparse.Namespace, frames: torch.Tensor, meta, noise_model: Any, mtf_model: Any, tmpdir: Path, mode: str = "map",
    kwargs: dict | None = None,
) -> dict[str, float] | None:
    import json
    import os
    import subprocess
    import sys

    torch.save(frames, tmpdir / "frames.pt")
    cfg = {"frames": str(tmpdir / "frames.pt"), "noise_model": str(noise_model), "mtf_model": str(mtf_model),
           "metadata": {k: v[0] for k, v in meta.to_dict().items()}, "precision": args.precision,
           "threads": torch.get_num_threads(), "mode": mode, "kwargs": kwargs or {}}
    (tmpdir / "probe.json").write_text(json.dumps(cfg))
    code = "import json, sys; from camhealth.bench.monitor import rss_probe; print(json.dumps(rss_probe(sys.argv[1])))"
    try:
        r = subprocess.run([sys.executable, "-c", code, str(tmpdir / "probe.json")], capture_output=True, text=True,
                           timeout=900, env={**os.environ, "OMP_NUM_THREADS": str(torch.get_num_threads())})
        return json.loads(r.stdout.strip().splitlines()[-1]) if r.returncode == 0 else None
    except (OSError, subprocess.SubprocessError, ValueError, IndexError):
        return None


class RecordingReader:
    """The benchmark frames (T×H×W uint8) written as a recording of kind ``suffix`` (mono8 on
    ``/camera/image_raw``, the gain on ``/camera/gain_db`` before every frame) and read back as the monitor CLI
    reads them; :meth:`step` times one frame: the next item of the source (read, deserialise, gray tensor,
    gain matched) plus the frame's metadata built from the recorded gain."""

    def __init__(self, frames: torch.Tensor, meta, tmpdir: Path, suffix: str) -> None:
        import numpy as np

        from camhealth.data.rosbag import RecordingWriter
        from camhealth.monitor.recording import RecordingOptions
        from camhealth.monitor.sources import open_source

        self.path, self.meta = tmpdir / f"bench_recording{suffix}", meta
        t0_ns, period = 1_700_000_000 * 10**9, 100 * 10**6
        gain = float(meta.gain_db[0])
        with RecordingWriter(self.path) as w:
            for i in range(frames.shape[0]):
                w.add_number("/camera/gain_db", gain, t0_ns + i * period - 1)
                w.add_image("/camera/image_raw", np.ascontiguousarray(frames[i].numpy()), t0_ns + i * period)
        self.source = open_source(self.path, recording=RecordingOptions(topic="/camera/image_raw", gain_topic="/camera/gain_db"))
        self._it = iter(self.source)

    def step(self) -> float | None:
        """ms for the next frame, or ``None`` at the end of the recording."""
        t0 = time.perf_counter()
        item = next(self._it, None)
        if item is None:
            return None
        if item.error is not None:
            raise ValueError(f"benchmark recording {self.path}: {item.error}")
        self.meta.replace(**item.metadata)
        return (time.perf_counter() - t0) * 1e3

    def close(self) -> None:
        self.source.close()


def recording_times(frames: torch.Tensor, meta, tmpdir: Path, suffix: str) -> list[float]:
    """ms per frame to read all ``frames`` back from a recording of kind ``suffix`` (:class:`RecordingReader`)."""
    reader = RecordingReader(frames, meta, tmpdir, suffix)
    times: list[float] = []
    try:
        while (t := reader.step()) is not None:
            times.append(t)
    finally:
        reader.close()
    return times


def _run(args: argparse.Namespace, meta, frames: torch.Tensor, blurred: torch.Tensor, mtf_true: torch.Tensor, tmpdir: Path,
         load_before: str, rss_start: float) -> BenchResult:
    from camhealth.bench.corruption import _load, machine_description
    from camhealth.estimators.noise_features import physics_prior_dn
    from camhealth.metrics import amae, noise_errors
    from camhealth.monitor import Monitor
    from camhealth.monitor.api import NOISE_FIELDS
    from camhealth.nets.drne import ThesisNoiseNet

    noise_model, mtf_model = _models(args, tmpdir)
    common = dict(noise_model=noise_model, mtf_model=mtf_model, metadata=meta, precision=args.precision,
                  device=args.device)
    monitors = {
        ALL: Monitor(**common, mode="map", adaptive=False, skip_uninformative=False),
        INFORMATIVE: Monitor(**common, mode="map", adaptive=False),
        ADAPTIVE: Monitor(**common, mode="map"),
    }
    if getattr(args, "static_pairs", False):
        monitors[PAIRS] = Monitor(**common, mode="map", adaptive=False, static_pairs=True)
    fp32 = Monitor(**{**common, "precision": "fp32"}, mode="map", adaptive=False)
    thesis = ThesisNoiseNet().eval()
    noise_est = monitors[INFORMATIVE].estimators["noise"].est
    for m in (*monitors.values(), fp32):  # warm-up (oneDNN kernels), then forget the state
        for _ in range(args.warmup):
            m.process(frames[0])
        m.reset()
    times: dict[str, list[float]] = {name: [] for name in (*monitors, FP32, THESIS)}
    cpu: dict[str, list[float]] = {name: [] for name in monitors}
    reports: dict[str, list[Any]] = {name: [] for name in monitors}
    thesis_ratio: list[float] = []
    bf16_vs_fp32: dict[str, float] = {}
    readers = {suffix: RecordingReader(frames, meta, tmpdir, suffix) for suffix in RECORDING_FORMATS}
    reading: dict[str, list[float]] = {suffix: [] for suffix in RECORDING_FORMATS}
    with torch.inference_mode():
        for i in range(args.frames):
            for name, m in monitors.items():
                c0, t0 = time.process_time(), time.perf_counter()
                r = m.process(frames[i], index=i)
                r.to_json()
                times[name].append((time.perf_counter() - t0) * 1e3)
                cpu[name].append((time.process_time() - c0) * 1e3)
                reports[name].append(r)
            for suffix, reader in readers.items():  # in the same round, under the same machine load
                reading[suffix].append(reader.step())
        rss_peak = peak_rss_mb()  # before the slow rows
        for i in range(min(args.slow_frames, args.frames)):
            t0 = time.perf_counter()
            rf = fp32.process(frames[i], index=i)
            rf.to_json()
            times[FP32].append((time.perf_counter() - t0) * 1e3)
            rb = reports[INFORMATIVE][i]
            both = _has_value(rb.noise) & _has_value(rf.noise)
            d_sigma = (rb.noise.values[both, -1] - rf.noise.values[both, -1]).abs()
            bothm = _has_value(rb.mtf) & _has_value(rf.mtf)
            d_mtf = (rb.mtf.values[bothm] - rf.mtf.values[bothm]).abs()
            bf16_vs_fp32["sigma_max"] = max(bf16_vs_fp32.get("sigma_max", 0.0), float(d_sigma.max()) if d_sigma.numel() else 0.0)
            bf16_vs_fp32["mtf_max"] = max(bf16_vs_fp32.get("mtf_max", 0.0), float(d_mtf.max()) if d_mtf.numel() else 0.0)
            # thesis-size net on the same informative noise patches (a subset, scaled)
            grid = rb.noise.grid_obj
            inf_idx = _has_value(rb.noise).nonzero()[:, 0]
            n_inf = int(inf_idx.numel())
            if n_inf and args.thesis_patches:
                sub = inf_idx[: args.thesis_patches]
                patches = grid.extract(frames[i].float() / 255.0)[sub].contiguous()
                t0 = time.perf_counter()
                thesis(patches)
                t_thesis = (time.perf_counter() - t0) * 1e3
                t0 = time.perf_counter()
                noise_est.predict(patches, metadata=meta, precision=args.precision)
                t_ours = (time.perf_counter() - t0) * 1e3
                times[THESIS].append(t_thesis * n_inf / sub.numel())
                thesis_ratio.append(t_thesis / max(t_ours, 1e-6))
    for reader in readers.values():
        reader.close()
    rss_all = peak_rss_mb()
    probe = _probe_memory(args, frames, meta, noise_model, mtf_model, tmpdir,
                          kwargs={"device": args.device} if args.device != "cpu" else None) if args.memory_probe else None

    # ---- patches estimated per frame, accuracy
    def per_frame(name: str, task: str, key: str) -> float:
        return sum(getattr(r, task).counts.get(key, 0) for r in reports[name]) / len(reports[name])

    def fresh(name: str, task: str) -> float:  # patches sent to the network
        return per_frame(name, task, "estimated") + per_frame(name, task, "not_assessable")

    grid_n = reports[ALL][0].noise.grid_obj
    err_full, err_adapt, diff, mtf_full, mtf_adapt = [], [], [], [], []
    truth_sig, xi_adapt, xi_full, xi_right = [], [], [], []
    mismatch = getattr(args, "true_gain_db", None) is not None
    for i in range(args.frames):
        rf, ra = reports[INFORMATIVE][i], reports[ADAPTIVE][i]
        both = _has_value(rf.noise) & _has_value(ra.noise)
        truth = _truth_sigma(frames[i], blurred[i], grid_n)[both]
        if mismatch:  # the ξ a right answer gives: the metadata's closed form (after clipping) less the realised σ
            patches = grid_n.extract(frames[i].float() / 255.0)[both]
            xi_right.append(physics_prior_dn(patches, meta, clipping=True)[:, 7] - truth)
            xi_full.append(rf.noise.values[both, NOISE_FIELDS.index("xi")])
        err_full.append(rf.noise.values[both, -1])
        err_adapt.append(ra.noise.values[both, -1])
        truth_sig.append(truth)
        diff.append(ra.noise.values[both, -1] - rf.noise.values[both, -1])
        xi_adapt.append(ra.noise.values[both, NOISE_FIELDS.index("xi")])
        bm = _has_value(rf.mtf) & _has_value(ra.mtf)
        mtf_full.append(rf.mtf.values[bm])
        mtf_adapt.append(ra.mtf.values[bm])
    truth_all = torch.cat(truth_sig)
    full_e = noise_errors(torch.cat(err_full), truth_all) if truth_all.numel() else None
    adapt_e = noise_errors(torch.cat(err_adapt), truth_all) if truth_all.numel() else None
    d_all = torch.cat(diff)
    mf, ma = torch.cat(mtf_full), torch.cat(mtf_adapt)
    amae_full = float(amae(mf, mtf_true.expand_as(mf)).mean()) if mf.numel() else float("nan")
    amae_adapt = float(amae(ma, mtf_true.expand_as(ma)).mean()) if ma.numel() else float("nan")
    amae_diff = float(amae(ma, mf).mean()) if ma.numel() else float("nan")
    xi_all = torch.cat(xi_adapt)

    def med(parts: list[torch.Tensor]) -> float:
        t = torch.cat(parts) if parts else torch.zeros(0)
        return float(t.median()) if t.numel() else float("nan")

    def fmt(e: dict | None) -> str:
        return "–" if e is None else f"Bias {e['bias']:.3f} / Std {e['std']:.3f} / RMS {e['rms']:.3f} DN (n = {e['n']})"

    pair_lines = []
    if PAIRS in reports:  # the pairs' answers against the fully monitored ones on the same patches
        pe, pd, pxi = [], [], []
        for i in range(args.frames):
            ra, rp = reports[INFORMATIVE][i], reports[PAIRS][i]
            both = _has_value(ra.noise) & _has_value(rp.noise)
            pe.append(rp.noise.values[both, -1])
            pd.append(rp.noise.values[both, -1] - ra.noise.values[both, -1])
            pxi.append(rp.noise.values[both, NOISE_FIELDS.index("xi")])
        truth_p = torch.cat([_truth_sigma(frames[i], blurred[i], grid_n)[_has_value(reports[INFORMATIVE][i].noise)
                                                                        & _has_value(reports[PAIRS][i].noise)]
                             for i in range(args.frames)])
        pair_e = noise_errors(torch.cat(pe), truth_p) if truth_p.numel() else None
        dp, xp = torch.cat(pd), torch.cat(pxi)
        read = [r.noise.coverage.get("static_pairs", 0) for r in reports[PAIRS]]
        pair_lines.append(
            f"static pairs: {sum(read) / len(read):.1f} noise patches per frame read from a pair (frames 2…{args.frames}: "
            f"{sum(read[1:]) / max(len(read) - 1, 1):.1f}); σ_total vs realised σ {fmt(pair_e)}; against the informative "
            f"patches' RMS {float(dp.pow(2).mean().sqrt()) if dp.numel() else float('nan'):.3f} DN; ξ median "
            f"{float(xp.median()) if xp.numel() else float('nan'):+.3f} DN")

    # ---- rows
    n_noise, n_mtf = reports[ALL][0].noise.counts["total"], reports[ALL][0].mtf.counts["total"]
    rows = []
    for name in monitors:
        rn, rm = fresh(name, "noise"), fresh(name, "mtf")
        note = (f"CPU {Row(name, cpu[name]).median_ms:.0f} ms/frame; {rn:.1f}/{n_noise} noise + {rm:.1f}/{n_mtf} MTF patches "
                f"through the networks per frame")
        if name == ADAPTIVE:
            note += (f" (+{per_frame(name, 'noise', 'reused'):.1f}+{per_frame(name, 'mtf', 'reused'):.1f} reused, "
                     f"{per_frame(name, 'noise', 'interpolated'):.1f}+{per_frame(name, 'mtf', 'interpolated'):.1f} interpolated; "
                     f"cold first frame {times[name][0]:.0f} ms)")
        rows.append(Row(name, times[name], note=note))
    if times[FP32]:
        d_s, d_m = bf16_vs_fp32.get("sigma_max", float("nan")), bf16_vs_fp32.get("mtf_max", float("nan"))
        rows.append(Row(FP32, times[FP32], note=f"{len(times[FP32])} frame(s); bf16 − fp32: max |Δσ_total| "
                        f"{d_s:.3f} DN, max |ΔMTF| {d_m:.4f}"))
    if times[THESIS]:
        ratio = sorted(thesis_ratio)[len(thesis_ratio) // 2]
        rows.append(Row(THESIS, times[THESIS], note=f"fp32, timed on {args.thesis_patches} patch(es) and scaled to the "
                        f"{fresh(INFORMATIVE, 'noise'):.1f} informative ones; {ratio:.0f}× the camhealth noise estimator's time "
                        f"on the same patches ({args.precision})", speedup=ratio, speedup_of="thesis net / camhealth noise"))
    alone_ms = None
    if probe and probe.get("ms") and len(probe["ms"]) > args.warmup:
        alone = Row(ALONE, probe["ms"][args.warmup :], note=(
            f"the adaptive monitor alone in a fresh interpreter (as `python -m camhealth.monitor` runs), same frames; "
            f"CPU {Row(ALONE, probe['cpu_ms'][args.warmup:]).median_ms:.0f} ms/frame; first {args.warmup} frame(s) "
            f"(cold: {probe['ms'][0]:.0f} ms incl. the kernel warm-up) not counted"))
        rows.insert(3, alone)
        alone_ms = alone.median_ms
    adaptive_ms = Row(ADAPTIVE, times[ADAPTIVE]).median_ms
    reading_pct = {}
    for suffix, t in reading.items():
        r = Row(RECORDING.format(suffix), t)
        reading_pct[suffix] = 100.0 * r.median_ms / adaptive_ms
        r.note = (f"read + deserialise + gray tensor + gain matched + frame metadata, mono8, timed in the same rounds as "
                  f"the monitors; {reading_pct[suffix]:.1f} % of the adaptive monitor's {adaptive_ms:.1f} ms/frame "
                  f"(target ≤ {TARGET_RECORDING_PCT:.0f} %: {'met' if reading_pct[suffix] <= TARGET_RECORDING_PCT else 'NOT met'})")
        rows.append(r)
    informative_ms = Row(INFORMATIVE, times[INFORMATIVE]).median_ms
    skip_noise = {k: per_frame(INFORMATIVE, "noise", k) for k in ("black", "saturated")}
    skip_mtf = {k: per_frame(INFORMATIVE, "mtf", k) for k in ("black", "saturated", "featureless", "no_edges")}
    model_note = f"{noise_model}, {mtf_model}"
    if args.untrained:
        model_note = "UNTRAINED networks (timing only; accuracy numbers are not meaningful)"
    header = [
        f"machine: {machine_description()}",
        f"load average before: {load_before} (1/5/15 min); date {_dt.date.today().isoformat()}",
        f"frames: {args.frames} × {args.width}×{args.height} uint8, scene {args.scene} (brightness ×{args.brightness:g}), "
        f"defocus {args.defocus_px:g} px, "
        f"{args.sensor} at {args.gain_db:g} dB / {args.exposure_s * 1e3:g} ms / {args.temperature_c:g} °C (metadata given"
        f"{'' if getattr(args, 'true_gain_db', None) is None else f'; the sensor at {args.true_gain_db:g} dB'}); "
        f"models: {model_note}; precision {args.precision}; device {args.device}; warm-up {args.warmup} frame(s)",
        f"command: {getattr(args, 'command_line', 'python -m camhealth.bench monitor')}",
    ]
    verdict = (lambda ms: ("met" if ms <= TARGET_MS else "NOT met")) if (args.width, args.height) == (1280, 1024) else \
        (lambda ms: "defined for 1280×1024 only")
    summary = [
        (f"adaptive monitor alone in its process: median {alone_ms:.1f} ms/frame (target ≤ {TARGET_MS:.0f} ms: "
         f"{verdict(alone_ms)}); " if alone_ms is not None else "")
        + f"adaptive interleaved with the two other monitors: median {adaptive_ms:.1f} ms/frame, CPU "
        f"{Row(ADAPTIVE, cpu[ADAPTIVE]).median_ms:.1f} ms/frame (target ≤ {TARGET_MS:.0f} ms: {verdict(adaptive_ms)}); "
        f"every informative patch every "
        f"frame: {informative_ms:.1f} ms, CPU {Row(INFORMATIVE, cpu[INFORMATIVE]).median_ms:.1f} ms ({verdict(informative_ms)})",
        (f"peak resident memory of one adaptive monitor alone (fresh interpreter, VmHWM): {probe['peak_mb']:.0f} MB "
         f"(Python + torch + camhealth before the monitor: {probe['start_mb']:.0f} MB; target ≤ {TARGET_RSS_MB:.0f} MB: "
         f"{'met' if probe['peak_mb'] <= TARGET_RSS_MB else 'NOT met'}); " if probe else "")
        + f"this benchmark process: {rss_peak:.0f} MB after the three monitor rows (all three monitors, their models, all "
        f"frames; {rss_start:.0f} MB at start), {rss_all:.0f} MB after the fp32 and thesis-size rows"
        + ("" if alone_ms is not None or not args.memory_probe else
           "; the run of the monitor alone in a fresh interpreter failed: no row and no verdict for it"),
        f"skipped as uninformative per frame: noise {skip_noise}, MTF {skip_mtf}; network patches per frame "
        f"{fresh(ALL, 'noise') + fresh(ALL, 'mtf'):.1f} (every) → "
        f"{fresh(INFORMATIVE, 'noise') + fresh(INFORMATIVE, 'mtf'):.1f} "
        f"(informative) → {fresh(ADAPTIVE, 'noise') + fresh(ADAPTIVE, 'mtf'):.1f} (adaptive)",
        f"σ_total on informative patches vs realised σ — informative: {fmt(full_e)}; adaptive: {fmt(adapt_e)}; "
        f"adaptive − informative RMS {float(d_all.pow(2).mean().sqrt()) if d_all.numel() else float('nan'):.3f} DN",
        f"MTF AMAE vs the applied defocus — informative {amae_full:.2f} %, adaptive {amae_adapt:.2f} %; "
        f"adaptive vs informative {amae_diff:.2f} %",
        "reading a recording adds " + ", ".join(f"{p:.1f} % ({k})" for k, p in reading_pct.items())
        + f" to the adaptive monitor's per-frame time (target ≤ {TARGET_RECORDING_PCT:.0f} %: "
        f"{'met' if max(reading_pct.values()) <= TARGET_RECORDING_PCT else 'NOT met'})",
        (f"ξ on informative patches (metadata correct, truth 0): median "
         f"{float(xi_all.median()) if xi_all.numel() else float('nan'):+.3f} DN" if not mismatch else
         f"metadata mismatch: the sensor's gain {args.true_gain_db:g} dB, the metadata's {args.gain_db:g} dB; on the informative "
         f"patches the metadata's closed form less the realised σ (the ξ of a right answer) has median {med(xi_right):+.3f} DN, "
         f"ξ median: informative {med(xi_full):+.3f} DN, adaptive {float(xi_all.median()) if xi_all.numel() else float('nan'):+.3f} DN"),
        *pair_lines,
        f"load average after: {_load()}",
    ]
    title = f"Monitor, {args.width}×{args.height} frames (ms per frame)"
    return BenchResult(title, rows, INFORMATIVE, header=header, summary=summary)
