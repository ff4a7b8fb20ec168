"""Command line: ``python -m camhealth.calibrate FRAMES... --out camera.yaml [--report DIR]``.

FRAMES are manifests (``.yaml``/``.yml``/``.csv``) and/or folders, videos and image files of bias, dark and
flat frames named by the convention ``<kind>_<exposure>_<gain>_<temperature>`` (e.g. ``dark_200ms_12dB_60C/``).
Writes the metadata YAML (accepted as-is by ``predict``, the monitor and ``fit``), ``<out>.calibration.yaml``
(uncertainties, EMVA 1288 figures, sets, fits) and ``<out>.maps.npz`` (hot pixels, DSNU, PRNU, masters); with
``--report DIR`` also ``DIR/report.md`` with ``calibration.png`` and ``maps.png``. Exit status 0 on success,
2 on an input error (one line naming what is missing and how many are needed), before anything is written: no
output may overwrite an input (the command line's FRAMES and every file a manifest names), be written into a
frame folder, or put the report into a frame folder or a folder of input files. See docs/calibration.md.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path
from typing import Sequence

from camhealth._cli import BadValue, add_debug_flag, config_parser, debugging, run_cli
from camhealth.physics.metadata import METADATA_RANGES

__all__ = ["build_parser", "main"]

EPILOG = """\
Recording (docs/calibration.md): ≥ 4 frames per set (20 recommended); a bias set (cap on, shortest exposure),
dark sets at ≥ 4× longer exposures (several temperatures measure the dark current's law), and ≥ 2 flat sets
(uniform light, 10 % … 70 % of full scale; a second gain checks K ∝ gain).

Examples:
  python -m camhealth.calibrate manifest.yaml --out camera.yaml --report calib_report
  python -m camhealth.calibrate bias_1ms_12dB_25C/ dark_200ms_12dB_25C/ flat_10ms_0dB_25C_L1.mkv \\
      flat_10ms_0dB_25C_L2.mkv --sensor-type CMOS --pixel-size-um 5.3 --out camera.yaml
  python -m camhealth.monitor clip.mp4 --metadata camera.yaml --set gain_db=12

Videos must be lossless (FFV1, HuffYUV, PNG, uncompressed …); lossy codecs (MJPEG, H.264 …) are refused,
and so are JPEG image files. 16-bit files without an sBIT chunk whose values never exceed 16383 (1/4 of full
scale) are refused as low-bit data unless --bit-depth gives their significant bits.
"""


def _assignment(text: str) -> tuple[str, float]:
    if "=" not in text:
        raise BadValue(f"expected FIELD=VALUE, got {text!r}")
    k, v = text.split("=", 1)
    try:
        return k.strip(), float(v)
    except ValueError:
        raise BadValue(f"{k.strip()} = {v!r} must be a number") from None


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise BadValue(f"must be an integer, got {text!r}") from None
    if n < 1:
        raise BadValue(f"must be >= 1, got {n}")
    return n


def _number_in(text: str | float, lo: float, hi: float, unit: str, what: str) -> float:
    """``text`` as a number of ``unit`` in [lo, hi], else :class:`BadValue` naming the value and the range."""
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise BadValue(f"must be a number of {unit}, got {text!r}") from None
    if not lo <= v <= hi:
        raise BadValue(f"must lie in {what} {lo:g} … {hi:g} {unit}, got {text}")
    return v


def _gain_db(text: str | float) -> float:
    """Option type: a gain in dB inside camhealth's metadata range (``METADATA_RANGES['gain_db']``)."""
    return _number_in(text, *METADATA_RANGES["gain_db"], "dB", "camhealth's gain range")


def _temperature_c(text: str | float) -> float:
    """Option type: a sensor temperature in °C inside :data:`~camhealth.calibrate.frames.TEMPERATURE_RANGE_C`."""
    from camhealth.calibrate.frames import TEMPERATURE_RANGE_C

    return _number_in(text, *TEMPERATURE_RANGE_C, "°C", "the sensor temperature range")


def _bit_depth(text: str | int) -> int:
    """Option type: significant bits of 16-bit files without sBIT, in :data:`~camhealth.calibrate.frames.BIT_DEPTH_RANGE`."""
    from camhealth.calibrate.frames import BIT_DEPTH_RANGE

    lo, hi = BIT_DEPTH_RANGE
    try:
        b = int(str(text).strip())
    except ValueError:
        raise BadValue(f"must be a whole number of bits, got {text!r}") from None
    if not lo <= b <= hi:
        raise BadValue(f"must lie in [{lo}, {hi}] bits, got {text}")
    return b


def _same_file(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` name the same file (the same resolved path, or hard links to one file)."""
    try:
        return a.resolve() == b.resolve() or (a.exists() and b.exists() and os.path.samefile(a, b))
    except (OSError, RuntimeError):  # (RuntimeError: a symlink loop)
        return False


def _outputs(args: argparse.Namespace) -> tuple[tuple[str, Path], ...]:
    """(option, path) of every file the calibration writes (the details file is written beside --out)."""
    out = args.out
    maps = args.maps if args.maps is not None else out.with_name(out.stem + ".maps.npz")
    details = out.with_name(out.stem + ".calibration.yaml")
    return (("--out", out), ("--maps", maps), ("--out", details))


def _resolved(path: Path) -> Path:
    try:
        return path.resolve()
    except (OSError, RuntimeError):
        return path.absolute()


def _input_problem(args: argparse.Namespace, sets) -> str | None:
    """Why an output cannot be written given the frame sets (read from FRAMES and manifests, no frame read), or
    ``None``: an output file that is a frame of a set (a file a manifest names, or an image in a set's folder), an
    output file inside a set's folder, or a report folder that is a set's folder, lies inside one, or holds a set's
    files (the report's PNGs would join the frames)."""
    folders: dict[Path, Path] = {}  # resolved → as given: set folders
    parents: dict[Path, Path] = {}  # resolved → a file in it: folders of loose input files and videos
    files: list[Path] = []
    for fs in sets:
        for p in fs.paths:
            if p.is_dir():
                folders.setdefault(_resolved(p), p)
                try:
                    files.extend(q for q in p.iterdir() if q.is_file())
                except OSError:
                    pass
            else:
                files.append(p)
                parents.setdefault(_resolved(p.parent), p)
    for option, path in _outputs(args):
        for f in files:
            if _same_file(path, f):
                return f"argument {option}: writing {path} would overwrite the input {f}; give another path"
        parent = _resolved(path.parent)
        if parent in folders:
            return f"argument {option}: {path} lies in the frame folder {folders[parent]} (an input); write it elsewhere"
    if args.report is not None:
        report = _resolved(args.report)
        for r, given in folders.items():
            if report == r or r in report.parents:
                return (f"argument --report: {args.report} is {'the' if report == r else 'inside the'} frame folder {given} (an "
                        "input); its calibration.png and maps.png would join the frames; give another folder")
        if report in parents:
            return (f"argument --report: {args.report} holds the input {parents[report]}; its calibration.png and maps.png "
                    "would join the frames; give another folder")
    return None


def _output_problem(args: argparse.Namespace) -> str | None:
    """Why an output path cannot be written (checked before the frames are read), or ``None``: a folder, a path under
    a file, or a file that is one of the inputs (FRAMES) or another output."""
    out = args.out
    outputs = _outputs(args)
    maps, details = outputs[1][1], outputs[2][1]
    for option, path in outputs:
        if path.is_dir():
            return f"argument {option}: {path} is a folder; give the name of the file to write"
        blocking = [d for d in path.parents if d.exists() and not d.is_dir()]
        if blocking:
            return f"argument {option}: cannot write {path}: {blocking[0]} is a file, not a folder"
        for frames in map(Path, args.frames):
            if _same_file(path, frames):
                return f"argument {option}: writing {path} would overwrite the input {frames}; give another path"
    if _same_file(maps, out) or _same_file(maps, details):
        return f"argument --maps: {maps} is also a file --out writes ({out}, {details}); give another path"
    if args.report is not None and args.report.exists() and not args.report.is_dir():
        return f"argument --report: {args.report} is a file; give a folder for report.md, calibration.png and maps.png"
    return None


def build_parser():
    """jsonargparse parser: every option may also come from ``--config FILE``; ``--print_config`` shows them."""
    p = config_parser(
        prog="python -m camhealth.calibrate", description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("frames", nargs="+", metavar="FRAMES", help="manifest(s) and/or folders, videos, image files of bias/dark/flat sets")
    p.add_argument("--out", type=Path, required=True, metavar="FILE", help="metadata YAML to write (e.g. camera.yaml)")
    p.add_argument("--report", type=Path, default=None, metavar="DIR", help="write report.md, calibration.png and maps.png here")
    p.add_argument("--maps", type=Path, default=None, metavar="FILE", help="maps NPZ (default <out stem>.maps.npz)")
    p.add_argument("--max-frames", type=_positive_int, default=None, metavar="N", help="read at most N frames per set")
    g = p.add_argument_group("file names without a gain or temperature token")
    g.add_argument("--gain-db", type=_gain_db, default=0.0, metavar="DB",
                   help="gain of sets whose names give none, {:g} … {:g} dB (default 0)".format(*METADATA_RANGES["gain_db"]))
    g.add_argument("--temperature-c", type=_temperature_c, default=None, metavar="C",
                   help="temperature of sets whose names give none, -60 … 150 °C (default: an error)")
    p.add_argument("--bit-depth", type=_bit_depth, default=None, metavar="BITS",
                   help="significant bits of 16-bit image files without an sBIT chunk (e.g. 12 for 12-bit data in the low bits; "
                        "8 … 16; default: the whole 16-bit range); a manifest's bit_depth takes precedence")
    g = p.add_argument_group("datasheet values (override the manifest's camera section; missing ones are assumed and marked so)")
    g.add_argument("--sensor-type", choices=("CCD", "CMOS"), default=None)
    g.add_argument("--pixel-size-um", type=float, default=None, metavar="UM")
    g.add_argument("--pixel-clock-hz", type=float, default=None, metavar="HZ")
    g.add_argument("--sense-node-gain-v-per-e", type=float, default=None, metavar="V")
    g.add_argument("--reset-factor", type=float, default=None, metavar="R", help="CMOS kTC residue 0…1 (default: fitted from ≥ 2 temperatures, else 0)")
    p.add_argument("--operating-point", action="append", default=[], metavar="FIELD=VALUE",  # → _assignment in main
                   help="gain_db, exposure_s or temperature_c written to the metadata (repeatable)")
    add_debug_flag(p)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:  # FIELD=VALUE strings (from the command line or a --config list) → (field, value)
        operating_point = dict(_assignment(a) for a in args.operating_point)
    except argparse.ArgumentTypeError as exc:
        parser.error(f"argument --operating-point: {exc}")
    problem = _output_problem(args)  # before the (long) reading of the frames
    if problem:
        parser.error(problem)
    from camhealth.calibrate import calibrate
    from camhealth.calibrate.pipeline import resolve_sets, video_problems
    from camhealth.calibrate.report import write_report

    try:  # the sets (manifests read, names parsed, videos' codecs checked; no frame read) for the outputs' check
        sets, _, _ = resolve_sets(args.frames, gain_db=args.gain_db, temperature_c=args.temperature_c, bit_depth=args.bit_depth)
        video_problems(sets)
    except (FileNotFoundError, ValueError) as exc:
        if debugging():
            raise
        print(f"error: {exc}", file=sys.stderr)
        return 2
    problem = _input_problem(args, sets)
    if problem:
        parser.error(problem)

    camera = {k: v for k, v in {
        "sensor_type": args.sensor_type, "pixel_size_um": args.pixel_size_um, "pixel_clock_hz": args.pixel_clock_hz,
        "sense_node_gain_v_per_e": args.sense_node_gain_v_per_e, "reset_factor": args.reset_factor,
    }.items() if v is not None}
    command = "python -m camhealth.calibrate " + " ".join(shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
    try:
        result = calibrate(args.frames, camera=camera, operating_point=operating_point, max_frames=args.max_frames,
                           gain_db=args.gain_db, temperature_c=args.temperature_c, bit_depth=args.bit_depth)
    except (FileNotFoundError, ValueError) as exc:
        if debugging():
            raise
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        written = result.save(args.out, maps=args.maps, header=f"command: {command}")
    except OSError as exc:  # (the paths were checked; a permission or a disk can still refuse)
        if debugging():
            raise
        print(f"error: cannot write the calibration: {exc}", file=sys.stderr)
        return 2
    for n, fe in result.fields.items():
        unc = f" ± {fe.uncertainty:.3g}" if fe.uncertainty else ""
        print(f"{n:<26} {fe.value:<12.6g}{unc:<12} {fe.unit:<7} {fe.source}")
    for w in result.warnings:
        print(f"warning: {w}")
    for kind, path in written.items():
        print(f"wrote {kind}: {path}")
    if args.report is not None:
        try:
            print(f"wrote report: {write_report(result, args.report, command)}")
        except OSError as exc:
            if debugging():
                raise
            print(f"error: cannot write the report to {args.report}: {exc}", file=sys.stderr)
            return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main, "python -m camhealth.calibrate"))
