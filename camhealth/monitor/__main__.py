"""Command line: ``python -m camhealth.monitor SOURCE [--metadata FILE] [--sensor NAME] [--out DIR] …``.

Runs :class:`camhealth.monitor.Monitor` on every frame of SOURCE and writes one JSON line per frame
(stdout, or ``DIR/monitor.jsonl``), optional overlay PNGs, a progress bar (stderr) and a summary at the
end (``DIR/summary.json`` too). A robot recording (ROS 1 ``.bag``, ROS 2 ``.db3``/``.mcap``, rosbag2
folder) is read with the camera state of its topics, and ``--diagnostics-out`` writes one
``diagnostic_msgs/DiagnosticArray`` per frame (:mod:`camhealth.monitor.diagnostics`). Exit status: 0 on
success (unreadable frames in a folder or recording, partly decoded video frames, frames that do not fit
``--defect-map`` and recording frames whose time ``--diagnostics-out`` cannot hold are reported and skipped),
2 on an error (missing/unreadable source, undecodable video, ``--start`` past the end, damaged recording, unknown
topic, bad metadata, missing or refused model, no frame scored at all, a ``--defects-out`` that cannot be written —
after ``summary.json`` —, …), with a one-line message (``--debug``: the traceback).
Every option may also come from ``--config FILE`` (YAML/JSON, keys as ``--print_config`` writes them; ``--set``
entries as ``FIELD=VALUE`` strings).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Iterator, Sequence, TextIO

from camhealth._cli import BadValue, add_debug_flag, config_parser, run_cli
from camhealth.monitor.api import MAX_SAMPLES, MAX_WINDOW
from camhealth.monitor.tiling import MAX_AGE
from camhealth.physics.metadata import FULL_FIELDS, METADATA_RANGES, PRESETS, UNITS

__all__ = ["build_parser", "main"]

DESCRIPTION = """\
Monitor a camera's image quality frame by frame: patch-wise blur (MTF, horizontal and vertical, at the
normalised frequencies 0.05…0.6 of Nyquist) and noise (σ of photon shot, dark-current shot and readout
noise, the metadata residual ξ and the total, in DN of 255), aggregated over time by a temporal median
with its spread (thesis Eq. 5.4), an alarm when ξ says the image is noisier (or cleaner) than the camera
metadata allow, and, with --iopc, the exposure/gain advice of the IOPC policy (Eq. 4.5-4.8).

Only what the scene needs is estimated: black, saturated and (for blur) featureless and edge-free
(Gaussian-like texture, "no_edges") patches are skipped, static regions reuse their last estimate, and patches are estimated on a coarse lattice first and refined
only where the estimates or the patch content change. Every skip is counted in the JSON line.
"""

EPILOG = f"""\
SOURCE kinds: an image file (.png .jpg .tif .bmp …), a folder of frame images (natural file order), a
video file (.mp4 .avi .mkv …; OpenCV), a robot recording (ROS 1 .bag, ROS 2 .db3/.mcap file or rosbag2
folder; --topic names the camera) or the word 'street' (the 50-frame clip embedded in camhealth).

Recordings: sensor_msgs/Image (mono8, mono16, rgb8, bgr8, rgba8, bgra8, 16-bit colour, bayer_* 8/16 bit)
  and CompressedImage (JPEG/PNG) become gray (BT.601 luma; Bayer: --bayer). Camera state from topics
  (std_msgs numbers, sensor_msgs/Temperature, or TOPIC:FIELD.PATH): each frame takes the latest value at or
  before its stamp; fields without a topic come from --metadata/--sensor; a change restarts the aggregation.

Metadata file (--metadata), JSON or YAML, physical units (thesis Table 4.1):
    sensor: ICX285          # optional preset that fills fields not given ({', '.join(sorted(PRESETS))})
    gain_db: 12.0           # {METADATA_RANGES['gain_db'][0]:g} … {METADATA_RANGES['gain_db'][1]:g} dB
    exposure_s: 0.01        # {METADATA_RANGES['exposure_s'][0]:g} … {METADATA_RANGES['exposure_s'][1]:g} s
    temperature_c: 40       # {METADATA_RANGES['temperature_c'][0]:g} … {METADATA_RANGES['temperature_c'][1]:g} °C
  all fields: {', '.join(FULL_FIELDS)} (sensor_type: CCD|CMOS for is_cmos).
  A Full-Meta noise model needs all 11 (from the file or a preset); a missing or out-of-range field is an
  error that names the field and its range.

Output, one JSON object per frame (keys): frame, index, source_id, size, input_scaling, assessable, metadata,
  noise {{estimator, patch_px, grid, assessable, sigma_dn {{pn, dcsn, rn, xi, total: {{median, spread,
  temporal_spread, current}}}}, patches {{estimated, interpolated, reused, black, saturated, featureless,
  no_edges, not_assessable, total}}, refused {{reason: patches}}, banding {{row_dn, col_dn, patches}} (row and
  column noise, in total and xi; null without), defects {{hot, dark, checked, ppm, patches, recurring, known
  (with --defect-map)}} (defective pixels, not in total; null without), cause {{gain, dark_current, readout,
  patches}} (where the noise contradicts the metadata: what it most likely is; null without)}}, mtf {{…, h, v: {{median, …}} (8 values each), indicator}}, alarm {{state:
  ok|noisier|cleaner|not_assessable|unavailable, xi_dn, limit_dn, message}}, advice (with --iopc), timing_ms.
  Unreadable frames of a folder and partly decoded video frames give {{"frame_error": …}} lines, never scores.
  16-bit frames are scaled by their significant bits (--bit-depth; each line and the summary name the scaling
  used); a frame at another scale than the one before (auto: a depth guessed from each frame's largest value)
  restarts the aggregation with a warning — give the camera's bits with --bit-depth.
  A frame whose size is not the --defect-map's, or whose time stamp the --diagnostics-out file cannot hold,
  gets a {{"frame_error": …}} line too.
  See docs/monitor.md.

Examples:
  python -m camhealth.monitor street --sensor ICX285 --max-frames 10 --out runs/monitor
  python -m camhealth.monitor clip.mp4 --metadata meta.yaml --overlay --out runs/clip
  python -m camhealth.monitor frame.png --sensor EV76C661 --set gain_db=18 --iopc runs/iopc/iopc.json
      (the IOPC from python -m camhealth.iopc --config configs/iopc.yaml, run once)
  python -m camhealth.monitor run.mcap --topic /camera/image_raw --sensor ICX285 \
      --gain-topic /camera/gain_db --exposure-topic /camera/exposure_us --exposure-unit us \
      --diagnostics-out runs/run_diagnostics.mcap --out runs/run
"""


def _int_at_least(lo: int, hi: int | None = None):
    """Option type: an integer >= ``lo`` (and <= ``hi``), with a message naming the value and the bounds."""

    def parse(value: str | int) -> int:
        try:
            if isinstance(value, (bool, float)):  # (a config file's true or 2.5 is no count)
                raise ValueError
            n = int(value)
        except ValueError:
            raise BadValue(f"must be an integer, got {value!r}") from None
        if hi is not None and not lo <= n <= hi:
            raise BadValue(f"must be an integer {lo}…{hi}, got {n}")
        if n < lo:
            raise BadValue(f"must be >= {lo}, got {n}")
        return n

    return parse


_positive = _int_at_least(1)
_non_negative_int = _int_at_least(0)
#: Largest ``--threads``: more torch threads than this only oversubscribes the CPU (and from 2^31 torch refuses the count).
THREADS_MAX = 4 * (os.cpu_count() or 1)
_threads = _int_at_least(1, THREADS_MAX)
_max_age = _int_at_least(1, MAX_AGE)
_window = _int_at_least(1, MAX_WINDOW)
_samples = _int_at_least(1, MAX_SAMPLES)


def _number(value: str | float) -> float:
    """A number of an option (a config file's ``true`` is none: it would read as 1)."""
    try:
        if isinstance(value, bool):
            raise ValueError
        return float(value)
    except (TypeError, ValueError):
        raise BadValue(f"must be a number, got {value!r}") from None


def _non_negative(value: str | float) -> float:
    x = _number(value)
    if not x >= 0 or x == float("inf"):
        raise BadValue(f"must be a finite number >= 0, got {value}")
    return x


def _positive_number(value: str | float) -> float:
    x = _number(value)
    if not x > 0 or x == float("inf"):
        raise BadValue(f"must be a finite number > 0, got {value}")
    return x


def _bit_depth(value: str | int) -> int | str:
    if value == "auto":
        return value
    try:
        n = int(value)
    except ValueError:
        raise BadValue(f"must be 'auto' or an integer 8…16, got {value!r}") from None
    if not 8 <= n <= 16:
        raise BadValue(f"must be 'auto' or an integer 8…16, got {n}")
    return n


def _assignment(value: str) -> tuple[str, float]:
    """``FIELD=VALUE`` → (field, value) with ``field`` one of the metadata fields and ``value`` a number."""
    if not isinstance(value, str) or "=" not in value:
        raise BadValue(f"expected FIELD=VALUE, got {value!r}")
    key, _, raw = value.partition("=")
    key = key.strip()
    if key not in FULL_FIELDS:
        raise BadValue(f"unknown metadata field {key!r}; known: {', '.join(FULL_FIELDS)}")
    try:
        return key, float(raw)
    except ValueError:
        raise BadValue(f"{key} must be a number, got {raw!r}") from None


def _assignments(value: str | list[str]) -> str | list[str]:
    """Type of ``--set``: checks ``FIELD=VALUE`` strings and keeps them as written, so ``--print_config`` writes them
    as a list of strings that ``--config`` reads back. argparse calls it on each ``--set``; jsonargparse's check calls
    it again on the whole list (also the list of a config file). :func:`_overrides` makes the numbers."""
    for item in [value] if isinstance(value, str) else value:
        _assignment(item)
    return value


def _overrides(values: str | list[str]) -> dict[str, float]:
    """The metadata fields ``--set`` overrides (a config file may give one string instead of a list)."""
    return dict(_assignment(v) for v in ([values] if isinstance(values, str) else values))


def build_parser():
    """jsonargparse parser: every option may also come from ``--config FILE``; ``--print_config`` shows them."""
    p = config_parser(
        prog="python -m camhealth.monitor", description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("source", metavar="SOURCE",
                   help="image file, folder of frames, video file, recording (.bag .db3 .mcap, rosbag2 folder), or "
                        "'street' (embedded clip)")
    g = p.add_argument_group("camera metadata")
    g.add_argument("--metadata", metavar="FILE", help="JSON/YAML file of metadata fields in physical units (see below)")
    g.add_argument("--sensor", metavar="NAME", choices=sorted(PRESETS),
                   help=f"sensor preset ({', '.join(sorted(PRESETS))}) that fills fields the file does not give, "
                        "or is the metadata (at 0 dB, 10 ms, 25 °C) when there is no file")
    g.add_argument("--set", metavar="FIELD=VALUE", action="append", type=_assignments, default=[],
                   help="override one metadata field, e.g. --set gain_db=12 (repeatable)")
    g = p.add_argument_group("estimators")
    g.add_argument("--noise-model", metavar="NAME|FILE", default="noise_source_full",
                   help="noise estimator: shipped name (noise_source_full, noise_source_min, drne) or a "
                        ".pt/.ckpt/.pt2/.onnx file (default: noise_source_full)")
    g.add_argument("--mtf-model", metavar="NAME|FILE", default="mtf",
                   help="MTF estimator: shipped name 'mtf' or a file (default: mtf)")
    g.add_argument("--no-noise", action="store_true", help="do not estimate noise (no ξ alarm, no advice)")
    g.add_argument("--no-mtf", action="store_true", help="do not estimate blur (no advice)")
    g.add_argument("--precision", choices=("bf16", "fp32"), default="bf16",
                   help="network precision: bf16 (CPU autocast, default; ~2x faster) or fp32 (reference)")
    g.add_argument("--mtf-views", type=int, choices=(1, 2, 4), default=1,
                   help="MTF estimates of the patch and 1 or 3 flipped copies averaged (default 1; 2: ~5%% lower error, 2x MTF time)")
    g.add_argument("--per-patch-noise", action="store_true",
                   help="judge every noise patch on its own instead of adding up the evidence of a frame's patches "
                        "(physics-first noise_source_full; per-patch maps)")
    g.add_argument("--batch-size", type=_positive, default=128, metavar="N", help="patches per network call (default 128)")
    g.add_argument("--device", default="cpu", metavar="DEV",
                   help="where the networks (and noise_source_full's posterior) run: cpu (default), cuda or cuda:N; "
                        "frame statistics stay on the CPU")
    g.add_argument("--threads", type=_threads, default=None, metavar="N",
                   help="torch intra-op threads, 1…4 × the CPU count (default: 2, or 1 on a single-core machine — the 10 "
                        "frames/s of a 1280x1024 stream are measured with 2 threads on 2 cores; if other busy jobs share the cores, "
                        "set OMP_WAIT_POLICY=PASSIVE in the environment or use --threads 1: OpenMP threads that "
                        "spin-wait against other jobs can be 20x slower)")
    g = p.add_argument_group("scene-adaptive selection")
    g.add_argument("--mode", choices=("auto", "sampled", "map"), default="auto",
                   help="sampled: a frame-level answer from a few patches per frame (flat patches for noise, patches "
                        "with edges for blur, rotating over the frame; cost independent of camera motion); map: every "
                        "informative patch (per-patch maps, static reuse); auto (default): map with --per-patch or "
                        "--overlay, else sampled")
    g.add_argument("--noise-samples", type=_samples, default=8, metavar="N",
                   help=f"sampled mode: noise patches per frame, 1…{MAX_SAMPLES} (default 8)")
    g.add_argument("--mtf-samples", type=_samples, default=6, metavar="N",
                   help=f"sampled mode: MTF patches per frame, 1…{MAX_SAMPLES} (default 6)")
    g.add_argument("--no-adaptive", action="store_true",
                   help="estimate every informative patch of every frame (no static reuse, no coarse-to-fine)")
    g.add_argument("--no-reuse", action="store_true", help="do not reuse estimates of static regions across frames")
    g.add_argument("--static-pairs", action="store_true",
                   help="noise: also read each patch against the same patch of the previous frame where the scene "
                        "stood still (their difference holds the noise and none of the scene; patches that moved are "
                        "read alone). Lossless frames only: raw, PNG/TIFF, uncompressed video, ROS Image — not JPEG, "
                        "MJPEG or H.264, whose re-quantisation passes for noise on dense texture")
    g.add_argument("--no-exposure-evidence", action="store_true",
                   help="noise: do not add the camera's noise evidence at other exposure times (kept from earlier "
                        "frames whose metadata differ only in the exposure time; it splits an excess between dark "
                        "current, which grows with the exposure time, and readout noise)")
    g.add_argument("--no-refine", action="store_true",
                   help="estimate all changed patches at once, without the coarse lattice first")
    g.add_argument("--no-skip", action="store_true",
                   help="also estimate black, saturated, featureless and edge-free patches (not recommended)")
    g.add_argument("--max-age", type=_max_age, default=16, metavar="N",
                   help=f"re-estimate a static patch at least every N frames, 1…{MAX_AGE} (default 16; staggered over "
                        "the grid)")
    g.add_argument("--max-clipped", type=_non_negative, default=0.5, metavar="F",
                   help="skip a patch with more than this fraction of pixels at 0 or 255 DN (default 0.5)")
    g.add_argument("--min-structure-dn", type=_non_negative, default=2.0, metavar="DN",
                   help="blur: skip a patch whose noise-corrected structure contrast is below this (default 2 DN)")
    g = p.add_argument_group("aggregation and alarm")
    g.add_argument("--window", type=_window, default=5, metavar="N",
                   help=f"temporal median over the last N estimates of each patch, 1…{MAX_WINDOW} (default 5)")
    g.add_argument("--xi-threshold-dn", type=_non_negative, default=1.0, metavar="DN",
                   help="alarm when |ξ| exceeds this (and 3 standard errors of the median; default 1 DN)")
    g.add_argument("--xi-sigmas", type=_non_negative, default=3.0, metavar="K",
                   help="significance of the alarm in standard errors (default 3)")
    g.add_argument("--defect-map", type=Path, default=None, metavar="FILE",
                   help="the camera's known defective pixels, the frames' size: camera.maps.npz of python -m "
                        "camhealth.calibrate (hot_pixels), a .npy array or a mask image (non-zero = defective); the "
                        "defects on it count as known and the alarm names only the others")
    g.add_argument("--defects-out", type=Path, default=None, metavar="FILE",
                   help="write the run's defect map to FILE (.npz: defective_pixels, the pixels flagged in at least "
                        "--defects-min-frames frames, and flagged_frames), readable by --defect-map; .npz is appended "
                        "where missing, FILE's folder is created as --out's is, a folder as FILE is refused before the run")
    g.add_argument("--defects-min-frames", type=_positive, default=2, metavar="N",
                   help="--defects-out: frames a pixel must be flagged in (default 2: recurring; on a static camera "
                        "the scene's own points of light recur too)")
    g = p.add_argument_group("exposure/gain advice")
    g.add_argument("--iopc", metavar="FILE", action="append", default=[],
                   help="IOPC file (.json/.npz from python -m camhealth.iopc); repeat for several applications. "
                        "Enables the policy's advice (needs camhealth.control)")
    g.add_argument("--iopc-weights", type=_non_negative, nargs="+", metavar="W",
                   help="weights λ of the IOPCs (Eq. 4.8), one per --iopc")
    for name, key, what in (("exposure", "exposure_s", "exposure"), ("gain", "gain_db", "gain")):
        lo, hi = METADATA_RANGES[key]
        g.add_argument(f"--{name}-limits", type=_number, nargs=2, default=[lo, hi], metavar=("LO", "HI"),
                       help=f"camera {what} limits in {UNITS[key]}, LO <= HI within the metadata range {lo:g} … {hi:g} "
                            f"(default {lo:g} {hi:g})")
    g = p.add_argument_group("frames")
    g.add_argument("--start", type=_non_negative_int, default=0, metavar="N", help="first frame index (default 0)")
    g.add_argument("--stride", type=_positive, default=1, metavar="N", help="use every N-th frame (default 1)")
    g.add_argument("--max-frames", type=_positive, default=None, metavar="N", help="stop after N frames (default: all)")
    g.add_argument("--bit-depth", type=_bit_depth, default="auto", metavar="auto|N",
                   help="significant bits of 16-bit frames: N = 8…16 divides values by 2^N − 1 (12 for a 12-bit "
                        "camera); auto (default): a PNG's sBIT chunk, else guessed from the largest value; in a recording's "
                        "mono16/16-bit images auto means 16 — the summary names the scaling used")
    g = p.add_argument_group("output")
    g.add_argument("--out", type=Path, metavar="DIR",
                   help="write DIR/monitor.jsonl, DIR/summary.json and overlays there (default: JSON lines on stdout)")
    g.add_argument("--overlay", action="store_true",
                   help="write overlay PNGs (noise and blur heat maps) to DIR/overlays/ (needs --out)")
    g.add_argument("--overlay-every", type=_positive, default=1, metavar="N", help="overlay every N-th frame (default 1)")
    g.add_argument("--sigma-max-dn", type=_positive_number, default=20.0, metavar="DN",
                   help="top of the overlay's σ colour scale, > 0 (default 20 DN)")
    g.add_argument("--per-patch", action="store_true", help="include every patch's status and values in the JSON lines")
    g.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    _add_recording_arguments(p)
    add_debug_flag(p)
    return p


def _add_recording_arguments(p: argparse.ArgumentParser) -> None:
    from camhealth.monitor.recording import EXPOSURE_UNITS, GAIN_UNITS, TEMPERATURE_UNITS

    g = p.add_argument_group("robot recordings (ROS 1 .bag, ROS 2 .db3/.mcap, rosbag2 folder)")
    g.add_argument("--topic", metavar="TOPIC",
                   help="image topic to monitor (sensor_msgs/Image or CompressedImage); without it the image topics are listed")
    for name, what in (("exposure", "exposure time"), ("gain", "gain"), ("temperature", "sensor temperature")):
        g.add_argument(f"--{name}-topic", metavar="TOPIC[:FIELD]",
                       help=f"topic of the camera's {what} (std_msgs number, sensor_msgs/Temperature, or a field path "
                            "such as /camera/status:exposure.value); latest value at or before each frame")
    g.add_argument("--exposure-unit", choices=list(EXPOSURE_UNITS), default="s", help="unit of --exposure-topic (default s)")
    g.add_argument("--gain-unit", choices=list(GAIN_UNITS), default="db",
                   help="unit of --gain-topic: db or factor (linear amplitude gain; default db)")
    g.add_argument("--temperature-unit", choices=list(TEMPERATURE_UNITS), default="c",
                   help="unit of --temperature-topic: c (°C) or k (kelvin; default c)")
    g.add_argument("--bayer", choices=("green", "luma"), default="green",
                   help="bayer_* images: green = one green sample per 2x2 cell (half resolution, raw noise kept; default) "
                        "or luma = OpenCV demosaic + BT.601 luma (full resolution, noise smoothed)")
    g.add_argument("--diagnostics-out", type=Path, metavar="FILE",
                   help="write one diagnostic_msgs/DiagnosticArray per frame on /diagnostics to FILE (.mcap: ROS 2, "
                        ".bag: ROS 1), stamped with the image header time; level OK, WARN (uncertain) or ERROR (ξ alarm "
                        "or not assessable)")


def _recording_options(args: argparse.Namespace) -> Any:
    """RecordingOptions from the CLI, or ``None`` when no recording option was given (``--bit-depth`` applies to every
    source; :func:`~camhealth.monitor.sources.open_source` passes it on to a recording)."""
    from camhealth.monitor.recording import RecordingOptions

    opts = RecordingOptions(
        topic=args.topic, exposure_topic=args.exposure_topic, gain_topic=args.gain_topic,
        temperature_topic=args.temperature_topic, exposure_unit=args.exposure_unit, gain_unit=args.gain_unit,
        temperature_unit=args.temperature_unit, bayer=args.bayer,
    )
    return None if opts == RecordingOptions() else opts


class _Progress:
    def __init__(self, total: int | None, enabled: bool) -> None:
        self.bar = None
        if enabled:
            try:
                from tqdm import tqdm

                self.bar = tqdm(total=total, unit="frame", file=sys.stderr, dynamic_ncols=True)
            except ImportError:  # pragma: no cover - tqdm ships with lightning
                self.bar = None

    def update(self, text: str) -> None:
        if self.bar is not None:
            self.bar.set_postfix_str(text, refresh=False)
            self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()

    def write(self, text: str) -> None:
        """One line on stderr, above the bar."""
        if self.bar is not None:
            self.bar.write(text, file=sys.stderr)
        else:
            print(text, file=sys.stderr)


@contextlib.contextmanager
def _one_line_warnings(category: type[Warning], progress: _Progress) -> Iterator[None]:
    """Within it, every warning of ``category`` is one ``warning: …`` line on stderr, each time it is raised (other
    warnings are shown as before)."""
    with warnings.catch_warnings():
        warnings.simplefilter("always", category)
        shown = warnings.showwarning

        def show(message, cat, filename, lineno, file=None, line=None):  # noqa: ANN001 - warnings.showwarning's
            if issubclass(cat, category):
                progress.write(f"warning: {message}")
            else:
                shown(message, cat, filename, lineno, file, line)

        warnings.showwarning = show
        yield


def _fmt(x: Any, spec: str = ".2f") -> str:
    return "–" if x is None else format(x, spec)


def _human_summary(summary: dict, out: TextIO) -> None:
    ms = summary["ms_per_frame"]
    print(
        f"camhealth.monitor: {summary['frames']} frame(s) from {summary['source']} "
        f"({summary['unreadable_frames']} unreadable) in {summary['wall_s']:.1f} s; "
        f"median {_fmt(ms['median'], '.1f')} ms/frame (max {_fmt(ms['max'], '.1f')})",
        file=out,
    )
    for scaling, n in (summary.get("input_scaling") or {}).items():
        print(f"  input: {scaling} ({n} frame(s))", file=out)
    for task, counts in summary["patches"].items():
        parts = ", ".join(f"{v} {k}" for k, v in counts.items() if v)
        print(f"  {task} [{summary['estimators'][task]}]: {parts or 'no patches'}", file=out)
    last = summary.get("last") or {}
    noise, mtf = last.get("noise"), last.get("mtf")
    if noise and noise.get("sigma_dn"):
        s = noise["sigma_dn"]
        print(
            f"  last frame noise: total {_fmt(s['total']['median'])} ± {_fmt(s['total']['spread'])} DN; "
            f"PN {_fmt(s['pn']['median'])}, DCSN {_fmt(s['dcsn']['median'])}, RN {_fmt(s['rn']['median'])}, "
            f"ξ {_fmt(s['xi']['median'], '+.2f')} DN",
            file=out,
        )
    if mtf and mtf.get("indicator"):
        print(f"  last frame blur: MTF̃ (f_n = 0.1) {_fmt(mtf['indicator']['median'], '.3f')}", file=out)
    if summary["alarms"]:
        print("  ξ alarm states: " + ", ".join(f"{k} {v}" for k, v in summary["alarms"].items()), file=out)
    causes = summary.get("causes")
    if causes:
        named = ", ".join(f"{k} {v}" for k, v in causes.items() if k != "frames" and v)
        print(f"  noise departs from the metadata in {causes['frames']} frame(s); most probable cause: {named}", file=out)
    advice = last.get("advice")
    if advice and advice.get("available"):
        print(f"  advice: {advice['explanation']}", file=out)
    for key in ("jsonl", "overlays"):
        if summary.get(key):
            print(f"  {key}: {summary[key]}", file=out)
    d = summary.get("defects_out")
    if d and "error" not in d:
        print(f"  defect map: {d['path']} ({d['pixels']} pixels flagged in at least {d['min_frames']} frames)", file=out)


def _printable(text: str) -> str:
    """``text`` as it can be written as UTF-8: the bytes of a file name that are not UTF-8 (which Python holds as
    surrogates, ``os.fsdecode``) become ``\\xNN`` escapes; text that is valid UTF-8 is returned unchanged."""
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        try:
            return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
        except UnicodeEncodeError:  # a surrogate that is no escaped byte
            return text.encode("utf-8", "backslashreplace").decode("utf-8")


def _source_files(source: Any) -> list[Path]:
    """The files an opened SOURCE reads: an image, a video or a recording file itself, a folder's frame images, every
    file of a rosbag2 folder (its storage files and ``metadata.yaml``)."""
    path = Path(source.path)
    if source.kind == "folder":
        from camhealth.data.image_folder import list_images

        return list(list_images(path, recursive=False))
    if path.is_dir():
        return [p for p in path.rglob("*") if p.is_file()]
    return [path]


def _config_files(args: argparse.Namespace) -> list[str]:
    """The ``--config`` files the options were read from (not inline YAML), as the parser resolved them."""
    out = []
    for given in getattr(args, "config", None) or ():
        if given is not None:  # (None: inline YAML given to --config)
            out.append(str(getattr(given, "absolute", given)))  # jsonargparse's Path: resolved where it was parsed
    return out


def _input_files(args: argparse.Namespace, members: Sequence[Path] = ()) -> dict[Any, str]:
    """Every input of the run (``SOURCE`` and the files it reads, ``--defect-map``, ``--metadata``, ``--iopc``,
    ``--config``) by its resolved path and by its file identity (device, inode: a hard link or a link to it) →
    ``"OPTION PATH"``."""
    import os

    inputs = [("SOURCE", args.source), *(("SOURCE", m) for m in members), ("--defect-map", args.defect_map),
              ("--metadata", args.metadata), *(("--iopc", f) for f in args.iopc),
              *(("--config", f) for f in _config_files(args))]
    out: dict[Any, str] = {}
    for option, given in inputs:
        if given is None:
            continue
        path = Path(given)
        label = f"{option} {path}"
        try:
            out.setdefault(path.resolve(), label)
            if path.exists():
                st = os.stat(path)
                out.setdefault((st.st_dev, st.st_ino), label)
        except (OSError, RuntimeError):  # (RuntimeError: a symlink loop)
            continue
    return out


def _input_overwritten(args: argparse.Namespace, out: Path, inputs: dict[Any, str] | None = None) -> str | None:
    """The input file (``"OPTION PATH"``) that writing ``out`` would overwrite, or ``None``; ``inputs``:
    :func:`_input_files` (default: the inputs the options name, without the files of an opened SOURCE)."""
    import os

    inputs = _input_files(args) if inputs is None else inputs
    try:
        hit = inputs.get(out.resolve())
        if hit is None and out.exists():
            st = os.stat(out)
            hit = inputs.get((st.st_dev, st.st_ino))
    except (OSError, RuntimeError):
        return None
    return hit


#: The names of the overlay PNGs under ``DIR/overlays/`` (``frame_`` and the frame's index).
_OVERLAY_NAME = re.compile(r"frame_\d{6,}\.png")


def _check_outputs(args: argparse.Namespace, source: Any) -> None:
    """Refuses, before anything is written, an output that would overwrite an input (SOURCE, a file it reads, or
    another input file) and a ``--diagnostics-out`` that cannot be written (ValueError naming both)."""
    if args.diagnostics_out is not None and source.kind != "recording":
        raise ValueError(f"--diagnostics-out needs a ROS recording as SOURCE (.bag, .db3, .mcap or a rosbag2 folder), "
                         f"got {source.kind} {source.path}")
    outputs = [(option, path) for option, path in (("--defects-out", args.defects_out),
                                                   ("--diagnostics-out", args.diagnostics_out)) if path is not None]
    if args.out is not None:
        outputs += [("--out", args.out / "monitor.jsonl"), ("--out", args.out / "summary.json")]
    inputs = _input_files(args, _source_files(source)) if outputs else {}
    for option, path in outputs:
        overwritten = _input_overwritten(args, Path(path), inputs)
        if overwritten is not None:
            raise ValueError(f"{option} {args.out if option == '--out' else path} would overwrite the input {overwritten}"
                             + (f" (as {path})" if option == "--out" else "") + "; give another file or folder")
    if args.overlay:  # DIR/overlays/frame_NNNNNN.png: a frame of SOURCE there, or an overlay file that is an input
        folder = args.out / "overlays"
        try:
            where = folder.resolve()
            hit = next((label for key, label in inputs.items()
                        if isinstance(key, Path) and key.parent == where and _OVERLAY_NAME.fullmatch(key.name)), None)
            if hit is None and folder.is_dir():
                hit = next((found for p in folder.iterdir() if _OVERLAY_NAME.fullmatch(p.name)
                            for found in [_input_overwritten(args, p, inputs)] if found is not None), None)
        except (OSError, RuntimeError):
            hit = None
        if hit is not None:
            raise ValueError(f"--overlay would write its PNGs (frame_NNNNNN.png) to {folder} over the input {hit}; "
                             "give another --out DIR")
    if args.diagnostics_out is not None:
        from camhealth.monitor.diagnostics import check_diagnostics_path

        try:
            check_diagnostics_path(args.diagnostics_out)
        except (OSError, ValueError) as exc:
            raise ValueError(f"--diagnostics-out {args.diagnostics_out}: {exc}") from None


def run(args: argparse.Namespace) -> int:
    import torch

    from camhealth.monitor.sources import open_source

    torch.set_num_threads(args.threads if args.threads is not None else default_threads())
    from camhealth.runtime import keep_freed_memory

    keep_freed_memory()  # reuse freed activation memory across frames (see camhealth.runtime)
    if args.overlay and args.out is None:
        raise ValueError("--overlay needs --out DIR (the PNGs go to DIR/overlays/)")
    if args.no_noise and args.no_mtf:
        raise ValueError("--no-noise and --no-mtf together leave nothing to monitor")
    if args.max_clipped > 1:
        raise ValueError(f"--max-clipped = {args.max_clipped:g} must lie in [0, 1]")
    for name, key in (("exposure_limits", "exposure_s"), ("gain_limits", "gain_db")):
        flag, values = f"--{name.replace('_', '-')}", getattr(args, name)
        if len(values) != 2:  # (a --config file is not held to the flag's two values)
            raise ValueError(f"{flag} needs 2 values LO HI, got {values}")
        lo, hi = (float(v) for v in values)
        low, high = METADATA_RANGES[key]  # the advice's exposure and gain are metadata the monitor must accept
        if not low <= lo <= hi <= high:  # (NaN fails too)
            why = f"LO {lo:g} > HI {hi:g}" if lo > hi else "outside the range"
            raise ValueError(f"{flag} {lo:g} {hi:g}: {why}; need LO <= HI, both within the metadata range "
                             f"[{low:g}, {high:g}] {UNITS[key]}")
    if args.iopc_weights is not None and len(args.iopc_weights) != len(args.iopc):
        raise ValueError(f"--iopc-weights has {len(args.iopc_weights)} value(s) for {len(args.iopc)} --iopc file(s)")
    if args.defects_out is not None:  # checked before the run, whose end would otherwise find it unwritable
        from camhealth.monitor.defect_map import defect_map_path

        try:
            args.defects_out = defect_map_path(args.defects_out)
        except ValueError as exc:
            raise ValueError(f"--defects-out {args.defects_out}: {exc}") from None
        overwritten = _input_overwritten(args, args.defects_out)
        if overwritten is not None:
            raise ValueError(f"--defects-out {args.defects_out} would overwrite the input {overwritten}; give another "
                             "file for the run's defect map")
    source = open_source(args.source, args.start, args.stride, args.max_frames, bit_depth=args.bit_depth,
                         recording=_recording_options(args))
    try:
        _check_outputs(args, source)  # before anything is written
        if args.static_pairs:
            from camhealth.monitor.sources import lossy_source

            why = lossy_source(source)
            if why is not None:
                print(f"warning: --static-pairs reads pairs of lossless frames, and {why}: on dense texture a codec's "
                      "re-quantisation can pass for noise (docs/monitor.md, Static camera)", file=sys.stderr)
        return _run_source(args, source)
    finally:
        close = getattr(source, "close", None)
        if close is not None:
            close()


def _run_source(args: argparse.Namespace, source: Any) -> int:
    from camhealth.monitor.api import FrameSizeError, InputScalingChanged, Monitor, load_policy
    from camhealth.physics.metadata import read_metadata_mapping
    from camhealth.monitor.overlay import save_overlay
    from camhealth.monitor.tiling import SelectionConfig

    noise_model = None if args.no_noise else args.noise_model
    mtf_model = None if args.no_mtf else args.mtf_model
    metadata: Any = args.metadata
    if args.set:  # overrides go on top of the file's fields; the preset (if any) fills the rest
        metadata = {**(read_metadata_mapping(Path(args.metadata)) if args.metadata else {}), **_overrides(args.set)}
    policy = None
    if args.iopc:
        policy = load_policy(args.iopc, tuple(args.exposure_limits), tuple(args.gain_limits), args.iopc_weights)
    selection = SelectionConfig(max_clipped_fraction=args.max_clipped, min_structure_dn=args.min_structure_dn,
                                max_age=args.max_age)
    monitor = Monitor(
        noise_model=noise_model, mtf_model=mtf_model, metadata=metadata,
        sensor=args.sensor,
        window=args.window, mode=("map" if args.overlay or args.per_patch else "sampled") if args.mode == "auto" else args.mode,
        noise_samples=args.noise_samples, mtf_samples=args.mtf_samples, adaptive=not args.no_adaptive, reuse_static=not args.no_reuse, coarse_refine=not args.no_refine,
        skip_uninformative=not args.no_skip, selection=selection, precision=args.precision, mtf_views=args.mtf_views, pool_noise=not args.per_patch_noise, batch_size=args.batch_size, device=args.device,
        xi_threshold_dn=args.xi_threshold_dn, xi_sigmas=args.xi_sigmas, policy=policy, per_patch=args.per_patch,
        defect_map=args.defect_map, static_pairs=args.static_pairs, exposure_evidence=not args.no_exposure_evidence,
    )
    if args.defects_out is not None:  # (its folder is created, as --out's)
        args.defects_out.parent.mkdir(parents=True, exist_ok=True)
    diagnostics = None
    if args.diagnostics_out is not None:  # (before monitor.jsonl is opened: a writer that fails truncates nothing)
        from camhealth.monitor.diagnostics import DiagnosticsWriter

        diagnostics = DiagnosticsWriter(args.diagnostics_out, f"camhealth: {source.topic}",
                                        xi_threshold_dn=args.xi_threshold_dn, topic=source.topic)
    out_dir: Path | None = args.out
    if out_dir is not None:
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
            sink: TextIO = (out_dir / "monitor.jsonl").open("w", encoding="utf-8")
        except BaseException:
            if diagnostics is not None:
                diagnostics.abort()
            raise
        report_to: TextIO = sys.stdout
    else:
        sink, report_to = sys.stdout, sys.stderr
    progress = _Progress(source.length, not args.no_progress)
    unreadable: list[str] = []
    scalings: dict[str, int] = {}
    frames = 0
    overlays = 0
    t0 = time.perf_counter()

    def frame_error(item: Any, source_id: str, error: str, status: str) -> None:
        """A frame that is not scored: a ``frame_error`` line (and diagnostics message), counted as unreadable."""
        error = _printable(error)
        if diagnostics is not None:
            why = _diagnostics_error(diagnostics, item, source_id, error)
            if why is not None:  # (the reason once: a frame refused for its time names it already)
                error += "; no --diagnostics-out message for it" + ("" if why in error else f": {why}")
        unreadable.append(f"{source_id}: {error}")
        line = {"frame_error": error, "index": item.index, "source_id": source_id}
        sink.write(json.dumps(line, ensure_ascii=False) + "\n")
        progress.update(status)

    try:
        with _one_line_warnings(InputScalingChanged, progress):
            for item in source:
                source_id = _printable(item.source_id)  # (a file name need not be UTF-8; the outputs are)
                if item.error is not None:
                    frame_error(item, source_id, item.error, "unreadable frame")
                    continue
                if diagnostics is not None:  # a time the file cannot hold: that frame, not the run (before it is scored)
                    why = _diagnostics_time_error(diagnostics, item.stamp_ns, item.log_time_ns)
                    if why is not None:
                        frame_error(item, source_id, f"--diagnostics-out {args.diagnostics_out} cannot hold "
                                                     f"the time of this frame: {why}", "frame refused")
                        continue
                try:
                    report = monitor.process(item.frame, metadata=item.metadata, index=item.index, source_id=source_id,
                                             input_scaling=item.input_scaling())
                except FrameSizeError as exc:  # a frame the --defect-map does not fit: that frame, not the run
                    frame_error(item, source_id, str(exc), "frame refused")
                    continue
                frames += 1
                if item.scaling is not None:
                    scalings[item.scaling] = scalings.get(item.scaling, 0) + 1
                if diagnostics is not None:
                    diagnostics.write_report(report, item.stamp_ns, item.log_time_ns or 0, item.frame_id)
                sink.write(report.to_json() + "\n")
                sink.flush()
                if args.overlay and report.frame % args.overlay_every == 0:
                    png = out_dir / "overlays" / f"frame_{item.index:06d}.png"
                    save_overlay(png, item.frame, report, sigma_max_dn=args.sigma_max_dn)
                    overlays += 1
                progress.update(f"{report.timing_ms['total']:.0f} ms, ξ {report.alarm['state']}")
    finally:
        progress.close()
        if out_dir is not None:
            sink.close()
        if diagnostics is not None:
            diagnostics.close()
    if frames == 0 and not unreadable and args.start > 0:  # a video that does not report its frame count
        raise ValueError(f"--start {args.start} is past the end of {source.path}: no frame was read")
    summary = monitor.summary()
    summary.update(source=_printable(str(source.path)), kind=source.kind, unreadable_frames=len(unreadable), unreadable=unreadable[:20],
                   wall_s=time.perf_counter() - t0, input_scaling=scalings)
    if source.kind == "recording":
        summary["recording"] = source.summary()
    if diagnostics is not None:
        summary["diagnostics"] = diagnostics.summary()
    defects_error = None
    if args.defects_out is not None and monitor.frames:
        from camhealth._cli import debugging, one_line
        from camhealth.monitor.defect_map import save_defect_map

        found, counts = monitor.found_defects(args.defects_min_frames)
        try:
            written = save_defect_map(args.defects_out, found, counts)
            summary["defects_out"] = {"path": str(written), "pixels": int(found.sum()), "min_frames": args.defects_min_frames}
        except (OSError, ValueError) as exc:  # the run's other results are still written; the error comes after them
            if debugging():
                raise
            defects_error = f"--defects-out {args.defects_out}: the defect map could not be written: {one_line(exc)}"
            summary["defects_out"] = {"path": str(args.defects_out), "error": defects_error}
    if out_dir is not None:
        summary["jsonl"] = str(out_dir / "monitor.jsonl")
        if overlays:
            summary["overlays"] = f"{out_dir / 'overlays'} ({overlays} PNG)"
        (out_dir / "summary.json").write_text(json.dumps(summary, indent=1, ensure_ascii=False, allow_nan=False, default=str),
                                              encoding="utf-8")
    if frames == 0:  # every frame unreadable or refused: nothing was monitored, which is no success
        why = f"all {len(unreadable)} unreadable or refused (first: {unreadable[0]})" if unreadable else "none was read"
        raise ValueError(f"no frame of {source.path} could be scored: {why}"
                         + (f"; the frame errors are in {out_dir / 'monitor.jsonl'}" if out_dir is not None else ""))
    _human_summary(summary, report_to)
    if source.kind == "recording":
        for line in source.describe():
            print(line, file=report_to)
    if diagnostics is not None:
        d = summary["diagnostics"]
        print(f"  diagnostics: {d['path']} ({d['messages']} DiagnosticArray on {d['topic']}: "
              + ", ".join(f"{v} {k}" for k, v in d["levels"].items()) + ")", file=report_to)
    if defects_error is not None:
        raise OSError(defects_error + (f" (the run's results are in {out_dir})" if out_dir is not None else ""))
    return 0


def _diagnostics_time_error(diagnostics: Any, stamp_ns: int | None, log_time_ns: int | None) -> str | None:
    """Why ``diagnostics`` (a :class:`~camhealth.monitor.diagnostics.DiagnosticsWriter`) cannot write a message of
    this header stamp and log time (as its ``write_report`` would stamp it: the log time where the stamp is unknown),
    naming the value and the range, or ``None``."""
    log = log_time_ns or 0
    try:
        diagnostics.check_times(log if stamp_ns is None else stamp_ns, log)
    except ValueError as exc:
        return str(exc)
    return None


def _diagnostics_error(diagnostics: Any, item: Any, source_id: str, error: str) -> str | None:
    """The ERROR status of a frame that is not scored: stamped with its header stamp, or, where the file cannot hold
    that stamp, with its log time; ``None``, or why no message could be written (neither time fits the file: why its
    own time does not)."""
    log = item.log_time_ns or 0
    whys = []
    for stamp in dict.fromkeys((item.stamp_ns, None)):
        why = _diagnostics_time_error(diagnostics, stamp, log)
        if why is None:
            diagnostics.write_error(error, item.index, source_id, stamp, log, item.frame_id)
            return None
        whys.append(why)
    return whys[0]


def default_threads() -> int:
    """Intra-op threads of the CLI by default: 2, or 1 if this process may use only one core."""
    import os

    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    return max(1, min(2, cores))


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; an error is one line on stderr and exit status 2 (``--debug``: the traceback instead)."""
    return run_cli(lambda a: run(build_parser().parse_args(a)), "python -m camhealth.monitor", argv)


if __name__ == "__main__":
    raise SystemExit(main())
