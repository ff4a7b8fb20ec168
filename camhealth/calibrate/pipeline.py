"""``calibrate(...)``: frame sets → per-set statistics → dark fit → photon transfer → camera metadata.

Order of the analysis (each step's physics in its module):

1. every bias/dark set: master frame, hot pixels (:func:`~camhealth.calibrate.statistics.detect_hot_pixels`),
   temporal noise (temporal or censored estimator, :mod:`~camhealth.calibrate.statistics`);
2. every flat set: the same, hot pixels of the darks and its own pixels at 0 DN in every frame (dead:
   :func:`~camhealth.calibrate.statistics.stuck_at_zero`) excluded; 16-bit files (and in-memory frames on the 16-bit
   grid) that look like low-bit data without a declared bit depth are refused (:data:`LOW_BITS_CODES`);
3. dark fit in DN² at unit gain (:mod:`~camhealth.calibrate.dark_signal`): read noise per temperature and the
   dark current's Eq. 3.14 law (a χ²/dof above ``MAX_CHI2_DOF`` is warned about, naming the sets that deviate most);
4. photon transfer (:mod:`~camhealth.calibrate.photon_transfer`): K0 [DN/e⁻] → full well FW = 255/K0;
5. in electrons: σ_RN²(T) = intercept/K0² → the readout law (σ_SF, CMOS reset factor) → W by inverting Eq.
   3.17 (:mod:`~camhealth.calibrate.readout`); DC(T) = C/K0² → D_FM with the pixel pitch;
6. the metadata (validated against Table 4.1's ranges), EMVA 1288 figures and the maps.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import replace
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from camhealth.calibrate.dark_signal import (
    DarkPoint, arrhenius_factor, dfm_from_c, doubling_temperature, fit_dark, fit_read_noise_law, model_doubling_temperature,
)
from camhealth.calibrate.frames import (
    MIN_FRAMES, FrameSet, _brief, _short, check_bit_depth, check_max_frames, check_video_codec, load_frames_with_depth,
    sets_from_paths,
)
from camhealth.calibrate.manifest import CAMERA_FIELDS, OPERATING_POINT_FIELDS, read_manifest
from camhealth.calibrate.photon_transfer import MAX_CHI2_DOF, FlatPoint, fit_photon_transfer
from camhealth.calibrate.readout import white_noise_from_sigma
from camhealth.calibrate.result import CalibrationResult, FieldEstimate, SetRecord
from camhealth.calibrate.statistics import (
    QUANTISATION_LIMITED_BELOW, SetStatistics, detect_dead_pixels, detect_hot_pixels, quantisation_step, set_statistics,
    stuck_at_zero,
)
from camhealth.physics.metadata import FULL_FIELDS, METADATA_RANGES, UNITS, CameraMetadata

__all__ = ["ASSUMED", "LOW_BITS_CODES", "calibrate", "resolve_sets", "video_problems"]

#: 16-bit image files without an sBIT chunk or a ``bit_depth`` (and in-memory frames on the 16-bit grid, k/65535, with a
#: step of one code) whose values, over every set of a calibration, stay at or below this code (of 65535: 1/4 of full
#: scale) hold 14-bit (or 12/10/8-bit) data in their low bits, not 16-bit data: the calibration refuses them (read as
#: value/65535 their full well comes out 4× and more too large). A photon-transfer series reaches 10 … 70 % of full
#: scale, so 16-bit data do not stay this dark.
LOW_BITS_CODES = 16383

#: Values used for datasheet fields that are not given (each is marked "assumed" in the output). The noise
#: model's σ_RN and dark current are reproduced whatever these are: W absorbs the sense-node gain and pixel
#: clock, D_FM the pixel area. If W or D_FM would leave their range, the sense-node gain / pixel size are
#: moved within theirs.
ASSUMED: dict[str, float] = {
    "is_cmos": 1.0,
    "pixel_size_um": 5.0,
    "pixel_clock_hz": 50e6,
    "sense_node_gain_v_per_e": 5e-6,
    "reset_factor": 0.0,
}

#: What each operating-point field defaults to when the manifest does not give it.
DEFAULT_WHAT = {"gain_db": "lowest flat gain", "exposure_s": "median flat exposure",
                "temperature_c": "median dark-set temperature"}


def _in_range(value: Any, what: str, key: str) -> float:
    """``value`` of the metadata field ``key`` as a float within ``METADATA_RANGES[key]``: a real number (or a string
    that spells one, as a manifest may give it), not a bool; else ``ValueError`` naming ``what``, the value and the
    range."""
    lo, hi = METADATA_RANGES[key]
    unit = f" {UNITS[key]}" if UNITS.get(key) else ""
    need = f"must be a number in camhealth's range [{lo:g}, {hi:g}]{unit}"
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Real, str)):
        raise ValueError(f"{what} = {_brief(value)} {need}" + (", not a bool" if isinstance(value, (bool, np.bool_)) else ""))
    try:
        v = float(value)
    except (ValueError, OverflowError):
        raise ValueError(f"{what} = {_brief(value)} {need}") from None
    if not lo <= v <= hi:
        raise ValueError(f"{what} = {v:g}{unit} is outside camhealth's range [{lo:g}, {hi:g}]{unit}")
    return v


def _camera_values(camera: Mapping[str, Any]) -> dict[str, float]:
    """Datasheet fields as floats in their ``METADATA_RANGES``; ``sensor_type`` CCD|CMOS becomes ``is_cmos``, which
    is a bool or 0 (CCD) / 1 (CMOS); None is "not given". ``ValueError`` names the field, the value and the range."""
    cam = dict(camera)
    unknown = sorted(set(cam) - set(CAMERA_FIELDS))
    if unknown:
        raise ValueError(f"unknown camera field(s) {unknown}; known: {list(CAMERA_FIELDS)}")
    if "sensor_type" in cam:
        raw = cam.pop("sensor_type")
        st = raw.strip().upper() if isinstance(raw, str) else None
        if st not in ("CCD", "CMOS"):
            raise ValueError(f"camera field sensor_type = {_brief(raw)} must be CCD or CMOS")
        cam["is_cmos"] = 1.0 if st == "CMOS" else 0.0
    out = {}
    for k, v in cam.items():
        if v is None:
            continue
        if k == "is_cmos":  # a flag: a bool, or 0/1 (as camhealth's metadata stores it)
            v = float(v) if isinstance(v, (bool, np.bool_)) else _in_range(v, "camera field is_cmos", k)
            if v not in (0.0, 1.0):
                raise ValueError(f"camera field is_cmos = {v:g} must be 0 (CCD) or 1 (CMOS), or a bool (or give sensor_type: "
                                 "CCD|CMOS)")
        else:
            v = _in_range(v, f"camera field {k}", k)
        out[k] = v
    return out


def _operating_point_values(op: Mapping[str, Any]) -> dict[str, float]:
    """The operating point written to the metadata (``gain_db``, ``exposure_s``, ``temperature_c``), each a number in
    its ``METADATA_RANGES``, checked before any frame is read; ``ValueError`` names the field, the value and the range
    (an unknown field: the known ones)."""
    unknown = sorted(map(str, set(op) - set(OPERATING_POINT_FIELDS)))
    if unknown:
        raise ValueError(f"unknown operating-point field(s) {unknown}; known: {list(OPERATING_POINT_FIELDS)}")
    out = {}
    for k, v in op.items():
        if v is None:
            raise ValueError(f"operating point {k} = None must be a number in camhealth's range "
                             f"[{METADATA_RANGES[k][0]:g}, {METADATA_RANGES[k][1]:g}] {UNITS[k]}; leave it out for the default "
                             f"({DEFAULT_WHAT[k]})")
        out[k] = _in_range(v, f"operating point {k}", k)
    return out


def resolve_sets(
    frames: Sequence[FrameSet | str | Path] | str | Path, gain_db: float | None = None, temperature_c: float | None = None,
    bit_depth: int | None = None,
) -> tuple[list[FrameSet], dict[str, Any], dict[str, float]]:
    """Frame sets (with manifest camera fields and operating point) from FrameSets, manifests and paths; reads no
    frames.

    A ``.yaml``/``.yml``/``.csv`` path is read as a manifest; other paths are folders, videos or image files
    named by the convention of :mod:`camhealth.calibrate.frames`. ``bit_depth`` is the
    :attr:`~camhealth.calibrate.frames.FrameSet.bit_depth` of every set that does not give one. Sets that share a
    name are refused, naming it.
    """
    bit_depth = check_bit_depth(bit_depth)
    items = [frames] if isinstance(frames, (str, Path)) else list(frames)
    sets: list[FrameSet] = []
    camera: dict[str, Any] = {}
    op: dict[str, float] = {}
    loose: list[Path] = []
    for item in items:
        if isinstance(item, FrameSet):
            sets.append(item)
        elif Path(item).suffix.lower() in (".yaml", ".yml", ".csv"):
            m = read_manifest(item)
            sets.extend(m.sets)
            camera.update(m.camera)
            op.update(m.operating_point)
        else:
            loose.append(Path(item))
    if loose:
        sets.extend(sets_from_paths(loose, gain_db=gain_db, temperature_c=temperature_c))
    if bit_depth is not None:
        sets = [fs if fs.bit_depth is not None or fs.frames is not None else replace(fs, bit_depth=bit_depth) for fs in sets]
    if not sets:
        raise ValueError("no frame sets given: pass a manifest, or folders/videos/images of bias, dark and flat frames")
    _refuse_duplicate_names(sets)
    return sets, camera, op


def _refuse_duplicate_names(sets: Sequence[FrameSet]) -> None:
    """Raises ``ValueError`` naming the first name that several sets share, and those sets: the results, the warnings
    and the report tell the sets apart by their names."""
    where: dict[str, list[int]] = {}
    for i, fs in enumerate(sets):
        where.setdefault(fs.name, []).append(i)
    for name, idx in where.items():
        if len(idx) > 1:
            given = "; ".join(f"set {i + 1}: {sets[i].kind}, {sets[i].exposure_s:g} s, {sets[i].gain_db:g} dB, "
                              f"{sets[i].temperature_c:g} °C" + (f" ({sets[i].origin})" if sets[i].origin else "")
                              for i in idx[:4])
            raise ValueError(
                f"{len(idx)} sets are named {_brief(name, 120)} ({given}{'; …' if len(idx) > 4 else ''}); every set needs a "
                "name of its own, by which the results, the warnings and the report tell it apart: give each a name "
                "(FrameSet(name=...), or name in the manifest), or remove a set given twice (the same path twice)"
            )


def _clamp_near_range(name: str, value: float, err: float, warnings: list[str]) -> float:
    """A fitted value just outside its METADATA_RANGES interval (within 3σ or 3 % of the range end: a camera at the
    end of the range, measured with noise) is set to the range end with a warning; others are returned as they are."""
    lo, hi = METADATA_RANGES[name]
    for end, outside in ((hi, value > hi), (lo, value < lo)):
        if outside and abs(value - end) <= max(3 * err, 0.03 * abs(end)):
            warnings.append(f"{name} = {value:.5g} ± {err:.2g} is just outside camhealth's range [{lo:g}, {hi:g}]; set to {end:g}")
            return float(end)
    return value


def _record(fs: FrameSet, st: SetStatistics, used: bool = True, note: str = "") -> SetRecord:
    sig = st.sigma_dn
    return SetRecord(
        name=fs.name, kind=fs.kind, exposure_s=fs.exposure_s, gain_db=fs.gain_db, temperature_c=fs.temperature_c,
        n_frames=st.n_frames, height=st.height, width=st.width, mean_dn=st.mean_dn, sigma_dn=sig,
        sigma_err_dn=st.var_err_dn2 / (2 * sig) if sig > 0 else float("nan"), method=st.method,
        clipped_low=st.clipped_low, clipped_high=st.clipped_high, mirrored_sigma_dn=st.mirrored_sigma_dn,
        spatial_sigma_dn=math.sqrt(st.spatial_var_dn2), step_dn=st.step_dn, used=used, note=note,
    )


def video_problems(sets: Sequence[FrameSet]) -> None:
    """Raises ``ValueError`` for the first video of ``sets`` whose codec is not lossless
    (:func:`~camhealth.calibrate.frames.check_video_codec`) and the first image file given by name that is lossily
    compressed (JPEG: :func:`~camhealth.calibrate.frames.check_image_format`) — before any frame is read. (The
    image files in a set's folder are checked as they are read.)"""
    from camhealth.calibrate.frames import _is_video, check_image_format

    for fs in sets:
        for p in fs.paths:
            if p.is_dir():
                continue
            if _is_video(p):
                check_video_codec(p)
            else:
                check_image_format(p, fs.describe() + (f" ({fs.origin})" if fs.origin else ""))


def _load_checked(fs: FrameSet, max_frames: int | None, size: tuple[int, int] | None, size_from: str):
    """The set's frames (N×H×W in [0, 1]), their quantisation step [DN] and how they were scaled."""
    x, depth = load_frames_with_depth(fs, max_frames)
    if x.shape[0] < MIN_FRAMES:
        raise ValueError(f"{fs.describe()} has {x.shape[0]} frame(s); at least {MIN_FRAMES} are needed per set (20 recommended)")
    if size is not None and tuple(x.shape[1:]) != size:
        raise ValueError(
            f"{fs.describe()} has {x.shape[1]}×{x.shape[2]} px frames but {size_from} has {size[0]}×{size[1]} px; "
            "every set of a calibration must have one frame size"
        )
    # the step of the scale the files were read with (b-bit data as value/(2^b − 1)), else found from the values
    step = quantisation_step(x, depth.depth.bits if depth.depth is not None else None)
    if fs.frames is not None and fs.bit_depth != 16 and x.size:
        # in-memory frames: their largest value, and whether they lie on the 16-bit grid one code apart (16-bit data,
        # or low-bit codes divided by 65535: :func:`_refuse_low_bits`)
        depth.undeclared_max, depth.undeclared_file = float(np.rint(float(x.max()) * 65535.0)), ""
        depth.grid16 = depth.depth is None and math.isclose(step, 255.0 / 65535.0, rel_tol=1e-9)
    return x, step, depth


def _stats_with_hot(x: np.ndarray, known_hot: np.ndarray | None, name: str = "the set",
                    step_dn: float | None = None) -> tuple[SetStatistics, np.ndarray]:
    """Statistics of a dark set with its own hot pixels (and ``known_hot``) excluded; returns the hot mask."""
    st = set_statistics(x, known_hot, step_dn=step_dn, name=name)
    if st.method == "clipped":
        return st, known_hot if known_hot is not None else np.zeros(x.shape[1:], dtype=bool)
    hot = detect_hot_pixels(st.master_dn, st.sigma_dn, st.n_frames, st.step_dn)
    if known_hot is not None:
        hot = hot | known_hot
    if hot.any() and (known_hot is None or (hot & ~known_hot).any()):
        st = set_statistics(x, hot, step_dn=st.step_dn, name=name)
    return st, hot


def calibrate(
    frames: Sequence[FrameSet | str | Path] | str | Path,
    camera: Mapping[str, Any] | None = None,
    operating_point: Mapping[str, float] | None = None,
    max_frames: int | None = None,
    gain_db: float | None = 0.0,
    temperature_c: float | None = None,
    bit_depth: int | None = None,
) -> CalibrationResult:
    """A camera's metadata from bias, dark and flat frames (module docstring; ``docs/calibration.md``).

    Args:
        frames: :class:`~camhealth.calibrate.frames.FrameSet` objects (in-memory or on disk), manifest files
            (``.yaml``/``.yml``/``.csv``) and/or folders, videos and image files named by the convention.
        camera: datasheet values (``sensor_type``/``is_cmos``, ``pixel_size_um``, ``pixel_clock_hz``,
            ``sense_node_gain_v_per_e``, ``reset_factor``); they override a manifest's. Missing ones are
            assumed (:data:`ASSUMED`) and marked so.
        operating_point: ``gain_db``, ``exposure_s``, ``temperature_c`` written to the metadata (default: the
            lowest flat gain, the median flat exposure within 1 ms … 0.2 s, the median dark temperature).
        max_frames: read at most this many frames per set (None: all; else at least ``MIN_FRAMES``).
        gain_db, temperature_c: values for file names that do not give them.
        bit_depth: significant bits of 16-bit image files without an ``sBIT`` chunk, for sets that do not give their
            own (:attr:`~camhealth.calibrate.frames.FrameSet.bit_depth`; None: those files use the whole 16-bit
            range).

    Returns:
        :class:`~camhealth.calibrate.result.CalibrationResult`.

    Raises:
        FileNotFoundError: a manifest or a file it names is missing (all missing ones listed).
        ValueError: too few frames in a set (or a ``max_frames`` below ``MIN_FRAMES``), a set whose frames are all
            identical, a bias/dark set whose noise is below about half a code step (quantisation-limited), too few
            sets of a kind, exposures or flat levels that do not span a range, saturated flats, flats whose per-gain
            K0 contradict K = g·K0, mixed frame sizes, frames smaller than 5×5 px, a colour image file or video frame,
            mixed bit depths within a set, a video whose codec is not lossless, a camera field or operating point
            that is not a number in its range (checked before any frame is read), 16-bit files that look like 12-bit
            data in their low bits (:data:`LOW_BITS_CODES`), a result outside camhealth's parameter ranges — each
            message names the set or value and what is needed.
    """
    check_max_frames(max_frames)
    sets, cam_manifest, op_manifest = resolve_sets(frames, gain_db=gain_db, temperature_c=temperature_c, bit_depth=bit_depth)
    cam = _camera_values({**cam_manifest, **dict(camera or {})})
    op = _operating_point_values({**op_manifest, **dict(operating_point or {})})
    darks = [s for s in sets if s.kind in ("bias", "dark")]
    flats = [s for s in sets if s.kind == "flat"]
    counts = {k: sum(s.kind == k for s in sets) for k in ("bias", "dark", "flat")}
    if len(darks) < 2:
        raise ValueError(
            f"{len(darks)} bias/dark set(s) given ({counts['bias']} bias, {counts['dark']} dark); at least 2 are needed: "
            "a bias set at the shortest exposure and a dark set at a ≥ 4× longer one (more exposures and temperatures "
            "measure the dark current better)"
        )
    if len(flats) < 2:
        raise ValueError(
            f"{len(flats)} flat set(s) given; at least 2 are needed at different light levels or exposures below "
            "saturation (e.g. 10 % … 70 % of full scale) to measure the conversion gain"
        )
    video_problems(sets)
    warnings: list[str] = []
    records: list[SetRecord] = []
    # 16-bit files read at 16 bits and in-memory frames: (largest value, file or "", set, on the 16-bit grid)
    undeclared: list[tuple[float, str, FrameSet, bool]] = []
    size: tuple[int, int] | None = None
    size_from = ""
    hot: np.ndarray | None = None
    dark_stats: list[tuple[FrameSet, SetStatistics]] = []
    for fs in sorted(darks, key=lambda s: (s.temperature_c, s.gain_db, s.exposure_s)):
        x, step, depth = _load_checked(fs, max_frames, size, size_from)
        if depth.undeclared_max is not None:
            undeclared.append((depth.undeclared_max, depth.undeclared_file, fs, bool(depth.undeclared_file) or depth.grid16))
        if size is None:
            size, size_from = tuple(x.shape[1:]), fs.describe()
        st, hot = _stats_with_hot(x, hot, fs.describe(), step)
        if st.method == "clipped":
            advice = ("its noise is below one code at 0 DN: record it at a higher gain or bit depth, or with a camera offset "
                      "that lifts it off 0 DN" if st.clipped_low >= st.clipped_high else
                      "it sits at the top code: record it at a lower gain (a dark set this bright has light reaching the sensor, "
                      "or a far too high gain)")
            raise ValueError(
                f"{fs.describe()} is clipped: {100 * st.clipped_low:.1f} % of its values at 0 DN and {100 * st.clipped_high:.1f} % at "
                f"{st.upper_dn:.4g} DN leave nothing to fit; {advice}"
            )
        if st.quantisation_limited:
            raise ValueError(
                f"{fs.describe()} is quantisation-limited: its raw temporal variance {st.raw_var_dn2:.3g} DN² is below "
                f"{QUANTISATION_LIMITED_BELOW:g}·step² (step {st.step_dn:.4g} DN), i.e. its noise is below about half a code step, "
                "where the quantisation correction step²/12 does not hold and no read noise or dark current can be measured; "
                "record it at a higher gain or bit depth"
            )
        dark_stats.append((fs, st))
        del x
    pooled = sorted(((st.spatial_var_dn2 / st.var_dn2, fs) for fs, st in dark_stats if st.method == "censored" and st.var_dn2 > 0),
                    key=lambda r: -r[0])
    if pooled and pooled[0][0] > POOLED_PATTERN_WARN_FRACTION:
        many = sum(r > POOLED_PATTERN_WARN_FRACTION for r, _ in pooled)
        warnings.append(
            f"{many} clipped dark set(s) have a fixed pattern (DSNU) of more than {100 * POOLED_PATTERN_WARN_FRACTION:g} % of their "
            f"fitted variance (largest: {pooled[0][1].name!r}, {100 * pooled[0][0]:.0f} %); their censored fit pools the pixels, so the "
            "read noise and dark current include it — record the darks with a camera offset that keeps them off 0 DN (temporal estimator)"
        )
    flat_stats: list[tuple[FrameSet, SetStatistics]] = []
    stuck: dict[int, np.ndarray] = {}  # id(flat stats) → its pixels at 0 DN in every frame (dead), left out of it
    for fs in flats:
        x, step, depth = _load_checked(fs, max_frames, size, size_from)
        if depth.undeclared_max is not None:
            undeclared.append((depth.undeclared_max, depth.undeclared_file, fs, bool(depth.undeclared_file) or depth.grid16))
        dead0 = stuck_at_zero(x, hot)
        st = set_statistics(x, hot | dead0 if dead0.any() else hot, step_dn=step, name=fs.describe(), flat=True)
        if dead0.any():
            stuck[id(st)] = dead0
        flat_stats.append((fs, st))
        del x
    _refuse_low_bits(undeclared)
    if stuck:
        n_dead = int(np.logical_or.reduce(list(stuck.values())).sum())
        warnings.append(
            f"{n_dead} pixel(s) read 0 DN in every frame of {len(stuck)} flat set(s) (dead: no response): left out of those flats' "
            "statistics and flagged in dead_pixels"
        )
    # ---- dark fit (Gaussian statistics), photon transfer; then the clipped dark sets refitted with their
    # Poisson skew and the clipping model the frames show, and both fits repeated
    def dark_points(latent: dict) -> list[DarkPoint]:
        return [DarkPoint(fs.exposure_s, fs.temperature_k, fs.gain_factor, *latent.get(id(st), (st.var_dn2, st.var_err_dn2))[:2], fs.name)
                for fs, st in dark_stats]

    def dark_level(fs: FrameSet, latent: dict) -> float:
        """Mean dark level [DN] for a flat: the dark set closest in gain, then temperature, then exposure."""
        best = min(dark_stats, key=lambda d: (abs(d[0].gain_db - fs.gain_db), abs(d[0].temperature_c - fs.temperature_c),
                                              abs(math.log(d[0].exposure_s / fs.exposure_s))))
        return latent[id(best[1])][2] if id(best[1]) in latent else best[1].mean_dn

    def photon_transfer(dark_fit, latent: dict, law=None, k0: float = 0.0, k0_err: float = 0.0):
        """Flats' statistics and the photon-transfer fit; with the read-noise ``law`` (and the K0 it was made with)
        the dark variance at a flat temperature without dark sets follows the law instead of the nearest one."""
        fpoints = [
            FlatPoint(fs.name, fs.exposure_s, fs.temperature_k, fs.gain_factor, st.mean_dn, st.mean_err_dn, st.var_dn2,
                      st.var_err_dn2, dark_level(fs, latent), st.clipped_high, fs.gain_db, st.clipped_low, st.method,
                      st.quantisation_limited)
            for fs, st in flat_stats
        ]
        intercept_at = None
        if law is not None:
            def intercept_at(t_k: float) -> tuple[float, float]:
                v = law.var_e2(t_k) * k0**2
                return v, math.sqrt((law.sf_var_err_e2 * k0**2) ** 2 + (2 * v * k0_err / k0) ** 2)
        return fpoints, fit_photon_transfer(fpoints, lambda t, tk, g: dark_fit.predict_dn2(t, tk, g, intercept_at))

    dark = fit_dark(dark_points({}))
    fpoints, ptc = photon_transfer(dark, {})
    clipping = _refit_censored_darks(dark_stats, ptc.k0)
    warnings.extend(clipping["warnings"])
    if clipping["latent"]:
        dark = fit_dark(dark_points(clipping["latent"]))
        fpoints, ptc = photon_transfer(dark, clipping["latent"])
    is_cmos = bool(cam.get("is_cmos", ASSUMED["is_cmos"]))
    given_asn = cam.get("sense_node_gain_v_per_e")
    asn = given_asn if given_asn is not None else ASSUMED["sense_node_gain_v_per_e"]
    flat_temps = {round(p.temperature_k, 6) for p in fpoints}
    if any(dark.index_of(t) is None for t in flat_temps):  # flats at a temperature without darks: the read-noise law
        law = fit_read_noise_law(dark, ptc.k0, ptc.k0_err, is_cmos, asn, cam.get("reset_factor"))
        fpoints, ptc = photon_transfer(dark, clipping["latent"], law, ptc.k0, ptc.k0_err)
    if clipping["model"] == "well":
        warnings.append(
            "the dark frames look like charge clipped at 0 before the readout noise (sources clipped one after another; "
            f"log-likelihood {clipping['delta_nll']:.0f} better than clipping once at the end): their variance is fitted with that model"
        )
    for p, why in ptc.excluded:
        warnings.append(f"flat set {p.name!r} left out of the photon transfer: {why}")
    if ptc.chi2_dof > MAX_CHI2_DOF:
        worst = sorted(zip(np.abs(ptc.residuals), ptc.used), key=lambda r: -r[0])[:3]
        warnings.append(
            f"the photon transfer fits poorly: χ²/dof = {ptc.chi2_dof:.3g} (above {MAX_CHI2_DOF:g}; K0's uncertainty is inflated by "
            f"its square root); largest normalised residuals: {', '.join(f'{p.name} {r:.1f}' for r, p in worst)} — saturation or "
            "non-linearity near the top, light that changes during a set, or a wrong gain_db"
        )
    dark_fits_poorly = dark.chi2_dof > MAX_CHI2_DOF
    if dark_fits_poorly:
        warnings.append(_dark_fit_warning(dark, dark_stats))
    k0, k0_err = ptc.k0, ptc.k0_err
    full_well = 255.0 / k0
    full_well_err = full_well * k0_err / k0
    lo, hi = METADATA_RANGES["full_well_e"]
    full_well = _clamp_near_range("full_well_e", full_well, full_well_err, warnings)
    if not lo <= full_well <= hi:
        raise ValueError(
            f"the photon transfer gives a full well of {full_well:.4g} e⁻ (K0 = {k0:.4g} DN/e⁻ at 0 dB), outside camhealth's "
            f"range [{lo:g}, {hi:g}] e⁻; check the flats' gain_db (the full well is the charge at 255 DN at 0 dB)"
        )
    # ---- readout noise and W
    clock = cam.get("pixel_clock_hz", ASSUMED["pixel_clock_hz"])
    rn_law = fit_read_noise_law(dark, k0, k0_err, is_cmos, asn, cam.get("reset_factor"))
    sf = math.sqrt(max(rn_law.sf_var_e2, 0.0))
    sf_err = rn_law.sf_var_err_e2 / (2 * max(sf, 1e-12))
    inv = white_noise_from_sigma(sf, sf_err, clock, asn, is_cmos)
    w_lo, w_hi = METADATA_RANGES["white_noise_v_per_rthz"]
    if not w_lo <= inv.white_noise_v_per_rthz <= w_hi and given_asn is None:
        # σ_SF ∝ W/A_SN (the RTN part is negligible): move the assumed sense-node gain so that W lands mid-range
        target = 30e-9
        new_asn = float(np.clip(asn * target / max(inv.white_noise_v_per_rthz, 1e-15), *METADATA_RANGES["sense_node_gain_v_per_e"]))
        warnings.append(
            f"with the assumed sense-node gain {asn:g} V/e⁻ the read noise {sf:.3g} e⁻ needs W = {inv.white_noise_v_per_rthz:.3g} V/√Hz "
            f"(range {w_lo:g} … {w_hi:g}); sense_node_gain_v_per_e assumed {new_asn:.3g} V/e⁻ instead (give the datasheet value)"
        )
        asn = new_asn
        rn_law = fit_read_noise_law(dark, k0, k0_err, is_cmos, asn, cam.get("reset_factor"))
        sf = math.sqrt(max(rn_law.sf_var_e2, 0.0))
        sf_err = rn_law.sf_var_err_e2 / (2 * max(sf, 1e-12))
        inv = white_noise_from_sigma(sf, sf_err, clock, asn, is_cmos)
    w = inv.white_noise_v_per_rthz
    if not w_lo * (1 - 1e-6) <= w <= w_hi * (1 + 1e-6):
        margin = max(3 * inv.white_noise_err, 0.03 * w_hi)
        if w_hi < w <= w_hi + margin:  # a camera at the end of the range, measured a little beyond it
            warnings.append(f"W = {w:.4g} ± {inv.white_noise_err:.2g} V/√Hz is just above camhealth's maximum {w_hi:g}; set to {w_hi:g}")
            inv.white_noise_v_per_rthz = w_hi
        elif inv.white_noise_v_per_rthz < w_lo and sf <= inv.sigma_min_e * 1.05:
            warnings.append(
                f"the source-follower noise {sf:.3g} e⁻ is at or below the model's floor {inv.sigma_min_e:.3g} e⁻ for this pixel "
                f"clock and sense-node gain; W set to its minimum {w_lo:g} V/√Hz"
            )
            inv.white_noise_v_per_rthz = w_lo
        else:
            raise ValueError(
                f"the measured source-follower noise {sf:.4g} ± {sf_err:.2g} e⁻ needs W = {inv.white_noise_v_per_rthz:.4g} V/√Hz, outside "
                f"camhealth's range [{w_lo:g}, {w_hi:g}] V/√Hz at a pixel clock of {clock:g} Hz and sense-node gain {asn:g} V/e⁻ "
                f"(the model spans {inv.sigma_min_e:.3g} … {inv.sigma_max_e:.3g} e⁻ there); check the gain_db of the sets and the "
                "camera fields"
            )
    # ---- dark current → D_FM
    c_e = dark.c_dn2 / k0**2
    c_e_err = abs(c_e) * math.sqrt((dark.c_err_dn2 / max(abs(dark.c_dn2), 1e-300)) ** 2 + (2 * k0_err / k0) ** 2) if dark.c_dn2 != 0 else dark.c_err_dn2 / k0**2
    better = ("its uncertainty is inflated by the poor dark fit (above): correct the dark sets it names first" if dark_fits_poorly
              else None)
    if c_e <= 0:
        warnings.append(
            f"no dark current detected (fitted {c_e:.3g} ± {c_e_err:.2g} e⁻/s/K^1.5): D_FM = 0; "
            + (better or "longer or warmer dark frames would measure it")
        )
        c_e = 0.0
    elif c_e < 2 * c_e_err:
        warnings.append(f"the dark current is barely detected ({c_e:.3g} ± {c_e_err:.2g} e⁻/s/K^1.5, < 2σ): "
                        + (better or "longer or warmer darks measure it better"))
    pixel = cam.get("pixel_size_um")
    pixel_source = "given"
    if pixel is None:
        pixel, pixel_source = ASSUMED["pixel_size_um"], "assumed"
        dfm = dfm_from_c(c_e, pixel)
        if dfm > METADATA_RANGES["dark_fom_na_per_cm2"][1]:
            pixel = min(pixel * math.sqrt(dfm / 0.5), METADATA_RANGES["pixel_size_um"][1])
        warnings.append(
            f"pixel_size_um not given: assumed {pixel:.3g} µm (the dark frames measure pixel area × D_FM; give the datasheet pitch "
            "for a meaningful D_FM)"
        )
    dfm_err = dfm_from_c(c_e_err, pixel)
    dfm = _clamp_near_range("dark_fom_na_per_cm2", dfm_from_c(c_e, pixel), dfm_err, warnings)
    if dfm > METADATA_RANGES["dark_fom_na_per_cm2"][1]:
        raise ValueError(
            f"the dark current gives D_FM = {dfm:.4g} nA/cm² with a {pixel:g} µm pixel, above camhealth's range "
            f"[0, {METADATA_RANGES['dark_fom_na_per_cm2'][1]:g}] nA/cm²; check pixel_size_um and the dark sets' temperatures"
        )
    # ---- operating point
    flat_gains = sorted(p.gain_db for p in ptc.used)
    flat_exps = sorted(p.exposure_s for p in ptc.used)
    dark_temps = sorted(fs.temperature_c for fs, _ in dark_stats)
    defaults = {"gain_db": flat_gains[0], "exposure_s": flat_exps[len(flat_exps) // 2],
                "temperature_c": dark_temps[len(dark_temps) // 2]}
    op_values, clamped = {}, {}
    for k, v in defaults.items():
        lo, hi = METADATA_RANGES[k]
        op_values[k] = op[k] if k in op else float(np.clip(v, lo, hi))
        if k not in op and op_values[k] != v:  # the measured default lies outside the metadata's range: say so
            clamped[k] = f"clamped from {v:g} to the range [{lo:g}, {hi:g}] {UNITS[k]}"
            warnings.append(f"operating point {k}: the default ({DEFAULT_WHAT[k]}) is {v:g} {UNITS[k]}, outside camhealth's "
                            f"range [{lo:g}, {hi:g}]; {op_values[k]:g} {UNITS[k]} is written — give --operating-point "
                            f"{k}=VALUE within the range")
    fields: dict[str, FieldEstimate] = {}
    for k in OPERATING_POINT_FIELDS:
        fields[k] = FieldEstimate(float(op_values[k]), 0.0, UNITS[k], "operating point",
                                  "from the manifest" if k in op else "default: " + DEFAULT_WHAT[k]
                                  + (f", {clamped[k]}" if k in clamped else ""))
    fields["dark_fom_na_per_cm2"] = FieldEstimate(dfm, dfm_err, UNITS["dark_fom_na_per_cm2"], "fitted",
                                                  "Eq. 3.14 law through the dark sets' temporal variance")
    fields["full_well_e"] = FieldEstimate(full_well, full_well_err, UNITS["full_well_e"], "fitted", "photon transfer, 255 DN at 0 dB")
    fields["pixel_clock_hz"] = FieldEstimate(clock, 0.0, UNITS["pixel_clock_hz"], "given" if "pixel_clock_hz" in cam else "assumed",
                                             "" if "pixel_clock_hz" in cam else "not given; W absorbs it")
    fields["sense_node_gain_v_per_e"] = FieldEstimate(asn, 0.0, UNITS["sense_node_gain_v_per_e"], "given" if given_asn is not None else "assumed",
                                                      "" if given_asn is not None else "not given; W absorbs it")
    if rn_law.reset_fitted:
        fields["reset_factor"] = FieldEstimate(rn_law.reset_factor, rn_law.reset_factor_err, "", "fitted",
                                               "kTC residue from the read noise's rise with temperature (Eq. 3.16)")
    else:
        given_r = "reset_factor" in cam
        fields["reset_factor"] = FieldEstimate(rn_law.reset_factor, 0.0, "", "given" if given_r else "assumed",
                                               "" if given_r else ("CCD: CDS removes kTC" if not is_cmos else "one temperature: not separable from W"))
    fields["pixel_size_um"] = FieldEstimate(pixel, 0.0, UNITS["pixel_size_um"], pixel_source, "" if pixel_source == "given" else "D_FM absorbs it")
    fields["is_cmos"] = FieldEstimate(float(is_cmos), 0.0, "", "given" if "is_cmos" in cam else "assumed",
                                      "" if "is_cmos" in cam else "sensor type not given")
    fields["white_noise_v_per_rthz"] = FieldEstimate(inv.white_noise_v_per_rthz, inv.white_noise_err, UNITS["white_noise_v_per_rthz"], "fitted",
                                                     f"Eq. 3.17 inverted for σ_SF = {sf:.4g} e⁻")
    for k, v in (("is_cmos", ASSUMED["is_cmos"]), ("pixel_clock_hz", clock)):
        if k not in cam:
            warnings.append(f"{k} not given: assumed {v:g}")
    meta = CameraMetadata(**{k: fields[k].value for k in FULL_FIELDS})
    # ---- records, maps, EMVA figures
    for fs, st in dark_stats:
        records.append(_record(fs, st))
    used_names = {id(p) for p in ptc.used}
    for (fs, st), p in zip(flat_stats, fpoints):
        why = next((w for q, w in ptc.excluded if q is p), "")
        records.append(_record(fs, st, used=id(p) in used_names, note=why))
    maps, nonuni = _maps(dark_stats, flat_stats, fpoints, ptc, hot, stuck)
    t_ref = op_values["temperature_c"] + 273.15
    rn_ref = math.sqrt(max(rn_law.var_e2(t_ref), 0.0))
    emva = _emva(dark, ptc, rn_law, k0, k0_err, c_e, c_e_err, full_well, rn_ref, nonuni, hot, t_ref)
    emva["dead_pixels"] = int(maps["dead_pixels"].sum())
    fits = {
        "photon_transfer": {
            "k0_dn_per_e": k0, "k0_err": k0_err, "chi2_dof": ptc.chi2_dof,
            "free_fit": {"slope_dn_per_e": ptc.free_slope, "intercept_dn2": ptc.free_intercept},
            "per_gain_k0": {f"{g:g} dB": {"k0": v[0], "err": v[1]} for g, v in ptc.per_gain.items()},
            "normalised_residuals": ptc.residuals.tolist(),
        },
        "dark": {
            "temperatures_c": (dark.temperatures_k - 273.15).tolist(),
            "read_noise_e": np.sqrt(np.maximum(dark.intercept_dn2, 0) / k0**2).tolist(),
            "dark_current_e_per_s": (dark.free_slope_dn2_per_s / k0**2).tolist(),
            "law_c_e_per_s_per_k1_5": c_e, "law_c_err": c_e_err, "chi2_dof": dark.chi2_dof,
            "clipping_model": {"end": "clipped once at the end (camhealth's model)",
                               "well": "charge clipped at 0 before the readout, then again at the end"}[clipping["model"]],
            "clipping_delta_nll_for_well": clipping["delta_nll"],
            "normalised_residuals": dark.residuals.tolist(),
        },
        "read_noise_law": {"source_follower_e": sf, "source_follower_err_e": sf_err, "reset_factor": rn_law.reset_factor,
                           "reset_factor_fitted": rn_law.reset_fitted},
    }
    return CalibrationResult(meta, fields, emva, records, fits, maps, warnings, ptc, dark, rn_law)


#: A dark or bias set whose mean level lies more than this many of its group's shortest set's σ above that set's mean
#: (same temperature and gain) is named in the poor-dark-fit warning as possibly lit.
DARK_LEVEL_RISE_SIGMAS = 5.0


def _dark_fit_warning(dark, dark_stats: list[tuple[FrameSet, SetStatistics]]) -> str:
    """The warning for a dark fit whose χ²/dof exceeds :data:`MAX_CHI2_DOF`: the sets with the largest normalised
    residuals (in the fit's order: ``dark.points`` are ``dark_stats``'s), and the likely causes — a set whose
    exposure, gain or temperature is not the one given, light reaching a set given as bias/dark (its mean level far
    above the bias level of its temperature and gain: :data:`DARK_LEVEL_RISE_SIGMAS`), a dark level that changes."""
    resid = np.asarray(dark.residuals, dtype=np.float64)
    order = np.argsort(-np.abs(np.nan_to_num(resid)))[:3]
    worst = [(dark_stats[i][0], dark_stats[i][1], float(resid[i])) for i in order]
    groups: dict[tuple[float, float], tuple[FrameSet, SetStatistics]] = {}
    for fs, st in dark_stats:  # the shortest set of each temperature and gain: its level is the bias level
        key = (round(fs.temperature_c, 6), round(fs.gain_db, 6))
        if key not in groups or fs.exposure_s < groups[key][0].exposure_s:
            groups[key] = (fs, st)
    lit = []
    for fs, st, _ in worst:
        bfs, bst = groups[(round(fs.temperature_c, 6), round(fs.gain_db, 6))]
        rise = st.mean_dn - bst.mean_dn
        if bfs is not fs and math.isfinite(rise) and rise > DARK_LEVEL_RISE_SIGMAS * max(bst.sigma_dn, 1e-6):
            lit.append(f"{fs.name!r} sits {rise:.3g} DN above the level of {bfs.name!r} ({bst.mean_dn:.3g} DN, σ "
                       f"{bst.sigma_dn:.3g} DN) at its temperature and gain")
    return (
        f"the dark fit is poor: χ²/dof = {dark.chi2_dof:.3g} (above {MAX_CHI2_DOF:g}; the read noise's and dark current's "
        f"uncertainties are inflated by its square root); largest normalised residuals: "
        f"{', '.join(f'{fs.name!r} {r:+.1f}' for fs, _, r in worst)} — check these sets' exposure_s, gain_db and "
        "temperature_c (one that is not the set's own contradicts the others), whether light reached them (a lit set "
        "given as bias or dark, a light leak), and whether the dark level changed during a set"
        + (f"; {'; '.join(lit)}: light reaching the sensor, or a lit set given as dark" if lit else "")
    )


#: Log-likelihood advantage of "charge clipped in the well" needed before the dark sets are analysed with it.
WELL_CLIPPING_MIN_DELTA_NLL = 10.0
#: A clipped (censored) dark set whose fixed-pattern variance exceeds this fraction of its fitted variance is warned
#: about: the censored fit pools the pixels, so the DSNU enters its σ².
POOLED_PATTERN_WARN_FRACTION = 0.1


def _refuse_low_bits(undeclared: list[tuple[float, str, FrameSet, bool]]) -> None:
    """Raises ``ValueError`` when 16-bit image files read at 16 bits (no sBIT chunk, no ``bit_depth``) and in-memory
    frames (file ``""``; those with ``bit_depth`` 16 are not listed), at least one set of them on the 16-bit grid
    (k/65535, one code apart: the last element; always true for files), hold, over every such set, no value above
    :data:`LOW_BITS_CODES` (1/4 of full scale): 14-bit (or 12/10/8-bit) data stored in the low bits, which read as
    value/65535 would give a full well 4× (or more) too large. A photon-transfer series reaches 10 … 70 % of full
    scale, so 16-bit data of a calibration do not stay below 1/4 of it. The message names the largest value, where it
    is, the bit depth the values fit and how to declare it (``--bit-depth``, ``bit_depth``; for in-memory frames:
    divide the codes by 2^bits − 1, or ``bit_depth=16`` for 16-bit data)."""
    if not any(u[3] for u in undeclared):
        return
    top, file, fs, _ = max(undeclared, key=lambda u: u[0])
    if top > LOW_BITS_CODES:
        return
    bits = max(8, int(math.ceil(math.log2(top + 1)))) if top > 0 else 8
    bits = next(b for b in (8, 10, 12, 14) if bits <= b)
    factor = 2 ** (16 - bits)
    files = [u for u in undeclared if u[1]]
    memory = [u for u in undeclared if not u[1] and u[3]]
    what = " and ".join(
        part for part in (f"the 16-bit image files of {len(files)} set(s) (no sBIT chunk)" if files else "",
                          f"the in-memory frames of {len(memory)} set(s) on the 16-bit grid (k/65535)" if memory else "") if part)
    remedies = []
    if files:
        remedies.append(f"for files, give the camera's bit depth (--bit-depth {bits}, calibrate(bit_depth={bits}), or bit_depth in "
                        "the manifest), save them with an sBIT chunk, or give bit depth 16 if they really are 16-bit data")
    if memory:
        remedies.append(f"for in-memory frames, divide the camera's codes by 2^bits − 1 (x / {2**bits - 1} for {bits}-bit data), "
                        "not by 65535, or give their sets bit_depth=16 if they really are 16-bit data")
    shown = f"{_short(file)}, {fs.describe()}" if file else f"in-memory frames of {fs.describe()}"
    raise ValueError(
        f"{what} hold values up to {top:g} of 65535 only (largest: {shown}), at most {LOW_BITS_CODES} = 1/4 of full scale: "
        f"these look like {bits}-bit data stored in the low bits of 16-bit words (as OpenCV and many camera SDKs write them), "
        f"which read as 16-bit data would give a full well {factor}× too large (a photon-transfer series reaches 10 … 70 % of "
        f"full scale, so 16-bit data do not stay this dark); {'; '.join(remedies)}"
    )


#: A refitted dark group is not used when its log-likelihood is worse than that of a normal distribution fitted to
#: each of its sets by more than this many standard deviations of that difference (a fit that did not converge).
REFIT_WORSE_SIGMAS = 10.0
#: A refitted dark group is not used when its dark-signal variance at the longest exposure falls below this fraction
#: of the rise the sets' own (Gaussian) fits measure, while that rise is significant (a fit stuck at DC = 0).
REFIT_MIN_DARK_FRACTION = 0.05


def _refit_censored_darks(dark_stats: list[tuple[FrameSet, SetStatistics]], k0: float) -> dict[str, Any]:
    """Refit the clipped dark sets with the dark signal's Poisson skew, and pick the clipping model they show.

    A Gaussian fitted to the upper half of a clipped dark frame takes the Poisson skew of the dark-current shot
    noise for extra width (a few % of the dark variance). With K = g·K0 known, every (temperature, gain) group
    with ≥ 2 exposures and at least one clipped set is fitted jointly by
    :func:`~camhealth.calibrate.statistics.poisson_gaussian_group_fit` (offset o, readout σ_R, dark current DC)
    under two models: clipped once at the end (camhealth's, :func:`~camhealth.physics.form_image`), and charge
    clipped at 0 before the readout (a simulator or camera that clips after each source: the dark-current shot
    noise cannot make the well's charge negative). The second is used when its log-likelihood, summed over the
    groups, is better by more than :data:`WELL_CLIPPING_MIN_DELTA_NLL`.

    The fit starts at the group's shortest set's fitted mean (its latent mean for a clipped set: the offset o; 0, the
    offset-free model, when that mean lies within half its σ of 0), its σ and the dark current its sets' variances
    give. Its variance replaces only that of the group's clipped
    (``censored``) sets; sets measured by the temporal estimator keep theirs. A group fit is not used (its sets keep
    their Gaussian fits, with a warning) when its log-likelihood is worse than a normal distribution fitted to each
    set by more than :data:`REFIT_WORSE_SIGMAS` standard deviations, or when its dark signal at the longest exposure
    falls below :data:`REFIT_MIN_DARK_FRACTION` of the significant rise the sets' own fits measure.

    Returns ``model`` ("end" or "well"), ``delta_nll``, ``latent``: id(stats) → (σ_R² + K²·DC·t [DN²], 1σ, o [DN]),
    and ``warnings``.
    """
    from camhealth.calibrate.statistics import binned_normal_nll, poisson_gaussian_group_fit

    groups: dict[tuple[float, float], list[tuple[FrameSet, SetStatistics]]] = {}
    for fs, st in dark_stats:
        groups.setdefault((round(fs.temperature_c, 6), round(fs.gain_db, 6)), []).append((fs, st))
    fits: dict[str, list] = {"end": [], "well": []}
    delta = 0.0
    for members in groups.values():
        members = sorted(members, key=lambda d: d[0].exposure_s)
        if len({fs.exposure_s for fs, _ in members}) < 2 or not any(st.method == "censored" for _, st in members):
            continue
        k = members[0][0].gain_factor * k0
        (fb, sb), (fl, sl) = members[0], members[-1]
        rise = sl.var_dn2 - sb.var_dn2
        dc0 = max(rise / (k * k * max(fl.exposure_s - fb.exposure_s, 1e-12)), 1e-3)
        # the offset starts at the shortest set's fitted (latent) mean; within σ/2 of 0 at 0, camhealth's offset-free
        # model (a start several σ from the truth leaves the optimiser where every bin's likelihood is floored)
        o0 = sb.mean_dn if math.isfinite(sb.mean_dn) and abs(sb.mean_dn) > 0.5 * sb.sigma_dn else 0.0
        hists = [(st.hist_edges_dn, st.hist_counts) for _, st in members]
        ts = [fs.exposure_s for fs, _ in members]
        gauss = sum(binned_normal_nll(st.hist_edges_dn, st.hist_counts, (st.mean_dn, max(st.sigma_dn, 1e-6))) for _, st in members)
        nll = {}
        for model in ("end", "well"):
            p, cov, nll[model] = poisson_gaussian_group_fit(hists, ts, k, model == "well", (o0, max(sb.sigma_dn, 1e-6), dc0))
            fits[model].append((members, k, p, cov, nll[model], gauss, rise))
        delta += nll["end"] - nll["well"]
    model = "well" if delta > WELL_CLIPPING_MIN_DELTA_NLL else "end"
    latent: dict[int, tuple[float, float, float]] = {}
    warnings: list[str] = []
    for members, k, p, cov, nll, gauss, rise in fits[model]:
        o, sr, dc = p
        (fb, sb), (fl, sl) = members[0], members[-1]
        dof = sum(int((st.hist_counts > 0).sum()) for _, st in members)  # bins with counts: the scale of the NLL's spread
        worse = (nll - gauss) / math.sqrt(max(dof, 1))
        rise_err = math.hypot(sl.var_err_dn2, sb.var_err_dn2)
        dark_var = k * k * dc * fl.exposure_s
        where = f"{fb.temperature_c:g} °C, {fb.gain_db:g} dB"
        if worse > REFIT_WORSE_SIGMAS:
            why = (f"its log-likelihood is {nll - gauss:.4g} worse than a normal distribution fitted to each set "
                   f"({worse:.1f}σ; the fit did not converge, or the dark level changes with exposure)")
        elif rise > 5 * rise_err and dark_var < REFIT_MIN_DARK_FRACTION * rise:
            why = (f"it puts the dark signal at the longest exposure at {dark_var:.3g} DN², where the sets' own fits measure a "
                   f"rise of {rise:.3g} ± {rise_err:.2g} DN² (the fit stuck at no dark current)")
        else:
            why = ""
        if why:
            warnings.append(
                f"the Poisson refit of the clipped dark sets at {where} ({', '.join(repr(fs.name) for fs, _ in members)}) is not used: "
                f"{why}; their Gaussian (censored) fits are used instead, whose dark current can be a few % high"
            )
            continue
        for fs, st in members:
            if st.method != "censored":  # measured by the temporal estimator: kept
                continue
            var = sr**2 + k * k * dc * fs.exposure_s
            grad = np.array([0.0, 2 * sr, k * k * fs.exposure_s])
            err = float(np.sqrt(max(grad @ cov @ grad, 0.0))) if np.all(np.isfinite(cov)) else st.var_err_dn2
            latent[id(st)] = (var, err, o)
    return {"model": model, "delta_nll": delta, "latent": latent, "warnings": warnings}


def _maps(dark_stats, flat_stats, fpoints, ptc, hot, stuck=None) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Hot pixels, dead pixels (:func:`~camhealth.calibrate.statistics.detect_dead_pixels` on the signal of the brightest
    flat the photon transfer used — ``fpoints`` are the flats' points, in the order of ``flat_stats``, matched to
    ``ptc.used`` by identity, not by name — and the pixels at 0 DN in every frame of a flat: ``stuck``, id(flat stats)
    → mask), DSNU map [DN] (master bias minus its mean), PRNU map [–] (that flat's master over the dark level, relative
    to its mean), the masters, and the spatial non-uniformities."""
    stuck = stuck or {}
    bias_fs, bias_st = min(dark_stats, key=lambda d: (d[0].exposure_s, d[0].temperature_c, d[0].gain_db))
    long_fs, long_st = max(dark_stats, key=lambda d: (d[0].temperature_c, d[0].exposure_s, d[0].gain_db))
    keep = ~hot if hot is not None else np.ones_like(bias_st.master_dn, dtype=bool)
    dsnu = bias_st.master_dn - float(bias_st.master_dn[keep].mean())
    used = {id(p) for p in ptc.used}
    cands = [(fs, st, p) for (fs, st), p in zip(flat_stats, fpoints) if id(p) in used]
    flat_fs, flat_st, flat_point = max(cands, key=lambda d: d[1].mean_dn / d[0].gain_factor)
    signal = flat_st.master_dn - flat_point.dark_mean_dn
    dead0 = np.logical_or.reduce(list(stuck.values())) if stuck else np.zeros_like(keep)
    mean_signal = float(signal[keep & ~dead0].mean())
    prnu = signal / mean_signal - 1.0 if mean_signal > 0 else np.zeros_like(signal)
    dead = detect_dead_pixels(signal, flat_st.sigma_dn, flat_st.n_frames, flat_st.step_dn, hot) | (dead0 & keep)
    maps = {
        "hot_pixels": (hot if hot is not None else np.zeros_like(dsnu, dtype=bool)).astype(bool),
        "dead_pixels": dead.astype(bool),
        "dsnu_dn": dsnu.astype(np.float32),
        "prnu": prnu.astype(np.float32),
        "master_bias_dn": bias_st.master_dn,
        "master_dark_dn": long_st.master_dn,
        "master_flat_dn": flat_st.master_dn,
    }
    # EMVA 1288: DSNU = s_y.dark / K, PRNU = sqrt(s²_y.50 − s²_y.dark) / (µ_y.50 − µ_y.dark); temporal share removed
    nonuni = {
        "dsnu_dn": math.sqrt(bias_st.spatial_var_dn2),
        "dsnu_gain_db": bias_fs.gain_db,
        "prnu_fraction": math.sqrt(max(flat_st.spatial_var_dn2 - bias_st.spatial_var_dn2 * (flat_fs.gain_factor / bias_fs.gain_factor) ** 2, 0.0))
        / max(flat_point.signal_dn, 1e-12),
        "prnu_set": flat_fs.name,
    }
    return maps, nonuni


def _emva(dark, ptc, rn_law, k0, k0_err, c_e, c_e_err, full_well, rn_ref, nonuni, hot, t_ref) -> dict[str, Any]:
    td, td_err = doubling_temperature(dark)
    per_t = {}
    for j, t in enumerate(dark.temperatures_k):
        s = dark.free_slope_dn2_per_s[j]
        per_t[f"{t - 273.15:g} °C"] = {
            "dark_current_e_per_s": float(s / k0**2) if np.isfinite(s) else None,
            "dark_current_err": float(dark.free_slope_err[j] / k0**2) if np.isfinite(dark.free_slope_err[j]) else None,
            "law_e_per_s": float(c_e * arrhenius_factor(t)),
            "temporal_dark_noise_e": float(math.sqrt(max(dark.intercept_dn2[j], 0.0)) / k0),
        }
    return {
        "standard": "EMVA 1288 Release 4.0 definitions (linear camera model); computed by camhealth",
        "system_gain_k_dn_per_e_at_0db": k0,
        "system_gain_err": k0_err,
        "system_gain_k_per_gain": {f"{g:g} dB": {"k": v[0] * 10 ** (g / 20), "k0_from_these_flats": v[0], "err": v[1]} for g, v in ptc.per_gain.items()},
        "saturation_capacity_e_at_0db": full_well,
        "temporal_dark_noise_e": rn_ref,
        "temporal_dark_noise_at_c": t_ref - 273.15,
        "dynamic_range_db": 20 * math.log10(full_well / max(rn_ref, 1e-12)),
        "snr_max_db": 10 * math.log10(full_well),
        "dark_current": per_t,
        "dark_current_law_e_per_s_at_ref": c_e * float(arrhenius_factor(t_ref)),
        "doubling_temperature_k": td,
        "doubling_temperature_err": td_err,
        "doubling_temperature_of_eq_3_14_k": model_doubling_temperature(t_ref),
        "dsnu_e": nonuni["dsnu_dn"] / (k0 * 10 ** (nonuni["dsnu_gain_db"] / 20)),
        "prnu_percent": 100 * nonuni["prnu_fraction"],
        "hot_pixels": int(hot.sum()) if hot is not None else 0,
    }
