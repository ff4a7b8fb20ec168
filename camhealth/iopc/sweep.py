"""The IOPC sweep (thesis Sec. 4.4.1, Fig. 4.6): corrupt, estimate, detect, score, bin.

Grid: linear-motion lengths L [px] × 4 directions Φ ∈ {0, 45, 90, 135}° × sensor-noise levels σ [DN]
(thesis Sec. 5.1.1 / 7.1; L = 0 is one cell per noise level, its direction is irrelevant). Each cell is
independent:

1. corrupt all N_I clean frames (optionally dimmed to the camera's exposure level, ``intensity``) with
   the physics core (:func:`camhealth.physics.form_image`): the sub-pixel linear-motion PSF of length L
   at Φ, then sensor noise of the configured sensor (optionally quantised to 8 bit). Following
   thesis Sec. 7.1 the default noise is *sensor noise only* (dark-current shot noise + readout noise,
   no photon noise); the level σ is reached by the camera gain, the physical way to "amplify the raw
   noise" (both sources scale with the gain g, so g = σ / σ(0 dB); with photon noise, whose σ grows as
   √g, the quadratic σ² = a·g + b·g² is solved, where the photon term a is multiplied by the PSF energy
   Σpsf², because photon shot noise arises before the motion blur and the blur averages it). A level that
   needs a gain outside 0–24 dB (Table 4.1) cannot be produced by that sensor: the cell is **marked** and
   skipped, never approximated;
2. estimate σ̂ and MTF̂ only on the tiles overlapping ground-truth boxes and take the Eq. 4.4 medians
   (:mod:`camhealth.iopc.estimation`);
3. run the frozen detector on the corrupted frames and compute COCO AP at IoU 0.5 over detections with
   score >= 0.5 (:mod:`camhealth.detection.average_precision`), jointly over the N_I frames;
4. record the tuple (σ̃, MTF̃, AP) with the cell's ground truth (true σ, PSF MTF), counts and time.

Cells whose nominal corruption lies outside the estimators' valid range (``valid_sigma_dn``,
``valid_length_px``) are computed but **marked**, as are cells without an assessable object tile;
:class:`~camhealth.iopc.curves.IOPC` keeps them in ``records`` but out of the curves.

Execution. The cells form a map-style ``Dataset`` and :class:`IOPCSweepModule`'s ``predict_step``
processes one cell, so ``Trainer.predict`` runs the grid with whatever strategy the user already uses
(a DDP user gets the cells spread over the ranks by Lightning's distributed sampler) and shows its
progress bar. Every finished cell is written to ``cache_dir/<fingerprint>/cell_*.json`` (atomic rename)
and cached cells are skipped: an interrupted sweep resumes where it stopped, and after a distributed run
the cache is where the ranks' results meet. The fingerprint hashes everything that determines a cell's
result (config, frames, ground truth, detector and estimator descriptions), so a changed setting never
reuses stale cells. Randomness: cell ``k`` draws its noise from a generator seeded with
``hash(seed, cell key)``, so results do not depend on the order or the rank that runs the cells.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import lightning as L
import numpy as np
import torch

from camhealth._validation import check_image
from camhealth.detection.average_precision import GroundTruth, evaluate_detections, validate_ground_truth
from camhealth.detection.protocol import Detector, validate_detections
from camhealth.detection.torch_adapter import TorchDetector
from camhealth.iopc.curves import IOPC, MTF_BINS, SIGMA_BINS_DN, _bin_centres
from camhealth.iopc.estimation import estimate_regions, estimator_fingerprint, estimator_name, median_estimates
from camhealth.physics.dark_current import dark_current_shot_sigma_dn
from camhealth.physics.image_formation import NOISE_SOURCES, form_image
from camhealth.physics.metadata import METADATA_RANGES, CameraMetadata, factor_to_db
from camhealth.physics.motion_psf import linear_motion_psf
from camhealth.physics.mtf import mtf_hv, mtf_indicator
from camhealth.physics.readout_noise import readout_sigma_dn

__all__ = [
    "SweepGrid",
    "SensorSetting",
    "SweepConfig",
    "make_cells",
    "noise_gain_db",
    "IOPCSweep",
    "IOPCSweepModule",
    "CellDataset",
    "log_iopc",
]


@dataclass
class SweepGrid:
    """The corruption grid.

    Attributes:
        lengths_px: linear-motion lengths L [px] (0 = no blur); thesis d ∈ {3, 7, 11, 15, 21}.
        angles_deg: motion directions Φ [deg] (0 horizontal, 90 vertical).
        noise_levels_dn: target sensor-noise σ [DN] (0 = no noise); thesis {5, …, 25}, bins up to 30.
    """

    lengths_px: list[float] = field(default_factory=lambda: [0.0, 3.0, 7.0, 11.0, 15.0, 21.0])
    angles_deg: list[float] = field(default_factory=lambda: [0.0, 45.0, 90.0, 135.0])
    noise_levels_dn: list[float] = field(default_factory=lambda: [0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0])


@dataclass
class SensorSetting:
    """Sensor and operating point of the sweep's noise (gain is set per cell).

    Attributes:
        preset: ``"ICX285"`` or ``"EV76C661"``.
        temperature_c: sensor temperature [°C]. Default 70 °C: the EV76C661's sensor noise is then 1.99
            DN at 0 dB, so 30 DN needs 23.6 dB, inside Table 4.1's 0–24 dB (thesis 5.1.1 used 330 K and
            amplified the raw noise without a gain limit).
        exposure_s: exposure time [s] (thesis 5.1.1: 0.1 s).
        sources: noise sources, subset of photon/dark/readout (thesis 7.1: dark + readout).
    """

    preset: str = "EV76C661"
    temperature_c: float = 70.0
    exposure_s: float = 0.1
    sources: list[str] = field(default_factory=lambda: ["dark", "readout"])


@dataclass
class SweepConfig:
    """Everything that determines the sweep's result besides frames, ground truth and models.

    Attributes:
        grid: :class:`SweepGrid`.
        sensor: :class:`SensorSetting`.
        valid_sigma_dn: [low, high] σ [DN] the noise estimator was trained for (cells outside: marked).
        valid_length_px: [low, high] blur length [px] the MTF estimator was trained for.
        sigma_bins_dn, mtf_bins: IOPC bin centres (thesis defaults): at least 2 each, finite and strictly
            increasing; σ̃ bins >= 0 DN, MTF̃ bins in [0, 1].
        score_threshold, iou_threshold: AP settings (App. A.1).
        intensity: scene brightness of the sweep: the clean frames are multiplied by this (and clipped at
            1, saturation) before the corruption — 1 = the frames as they are (the thesis's IOPCs). Set it
            to the operating point's exposure level so that photon noise and 8-bit quantisation match the
            camera the curves are used for (e.g. the closed-loop demo's camera renders the clip at 0.5).
        quantize: round the corrupted frames to whole DN (an 8-bit camera), as the simulated camera does.
        seed: noise seed (an integer).
        detector_batch_size: frames per detector call (an integer >= 1).
        estimator_batch_size: tiles per estimator call (an integer >= 1).

    :meth:`validate` checks every field before any cell is computed; each error names the key, the value and the
    allowed range.
    """

    grid: SweepGrid = field(default_factory=SweepGrid)
    sensor: SensorSetting = field(default_factory=SensorSetting)
    valid_sigma_dn: list[float] = field(default_factory=lambda: [0.0, 30.0])
    valid_length_px: list[float] = field(default_factory=lambda: [0.0, 31.0])
    sigma_bins_dn: list[float] = field(default_factory=lambda: list(SIGMA_BINS_DN))
    mtf_bins: list[float] = field(default_factory=lambda: list(MTF_BINS))
    score_threshold: float = 0.5
    iou_threshold: float = 0.5
    intensity: float = 1.0
    quantize: bool = False
    seed: int = 0
    detector_batch_size: int = 4
    estimator_batch_size: int = 64

    def validate(self) -> "SweepConfig":
        g = self.grid
        if not isinstance(g, SweepGrid):
            raise ValueError(f"grid = {g!r} is not allowed: a grid with lengths_px, angles_deg and noise_levels_dn")
        if not isinstance(self.sensor, SensorSetting):
            raise ValueError(f"sensor = {self.sensor!r} is not allowed: a sensor setting (preset, temperature_c, exposure_s, "
                             "sources)")
        for name, vals, lo, hi in (
            ("grid.lengths_px", g.lengths_px, 0.0, 63.0),
            ("grid.angles_deg", g.angles_deg, -360.0, 360.0),
            ("grid.noise_levels_dn", g.noise_levels_dn, 0.0, 255.0),
        ):
            if not isinstance(vals, (list, tuple)) or not vals:
                raise ValueError(f"{name} = {vals!r} is not allowed: a non-empty list of numbers in [{lo:g}, {hi:g}]")
            for v in vals:
                if not (_is_real(v) and math.isfinite(v) and lo <= v <= hi):  # a bool is no length/angle/level
                    raise ValueError(f"{name} value {v!r} is out of the allowed range [{lo:g}, {hi:g}]")
            # a repeated value makes cells with the same key and seed: computed twice and counted twice in the bins
            dup = sorted({float(v) for v in vals if sum(float(u) == float(v) for u in vals) > 1})
            if dup:
                raise ValueError(f"{name} = {list(vals)!r} repeats {dup}: each value must appear once")
        bad = [s for s in self.sensor.sources if s not in NOISE_SOURCES]
        if bad:
            raise ValueError(f"sensor.sources {bad} are not noise sources; choose from {list(NOISE_SOURCES)}")
        if any(v > 0 for v in g.noise_levels_dn) and not self.sensor.sources:
            raise ValueError("grid.noise_levels_dn has levels > 0 but sensor.sources is empty")
        CameraMetadata.preset(self.sensor.preset, temperature_c=self.sensor.temperature_c,
                              exposure_s=self.sensor.exposure_s)  # validates the operating point
        for name, rng in (("valid_sigma_dn", self.valid_sigma_dn), ("valid_length_px", self.valid_length_px)):
            # the cells outside are marked only after every cell is computed: a range that no value can reach is refused now
            if not (isinstance(rng, (list, tuple)) and len(rng) == 2 and all(_is_real(v) and not math.isnan(v) for v in rng)
                    and 0 <= rng[0] <= rng[1] and math.isfinite(rng[0])):
                raise ValueError(f"{name} = {rng!r} is out of the allowed range: [low, high], two numbers with "
                                 "0 <= low <= high, low finite")
        if not (_is_real(self.intensity) and math.isfinite(self.intensity) and 0 < self.intensity <= 4):
            raise ValueError(f"intensity = {self.intensity!r} is out of the allowed range (0, 4]")
        if not isinstance(self.quantize, (bool, np.bool_)):
            raise ValueError(f"quantize = {self.quantize!r} is not allowed: true or false")
        if not (_is_real(self.score_threshold) and 0.0 <= self.score_threshold <= 1.0):
            raise ValueError(f"score_threshold = {self.score_threshold!r} is out of the allowed range [0, 1]")
        if not (_is_real(self.iou_threshold) and 0.0 < self.iou_threshold < 1.0):
            raise ValueError(f"iou_threshold = {self.iou_threshold!r} is out of the allowed range (0, 1)")
        # the bins are only used after every cell is computed (IOPC.from_records): refuse bad ones before that
        _bin_centres(self.sigma_bins_dn, "sigma_bins_dn", "sigma")
        _bin_centres(self.mtf_bins, "mtf_bins", "mtf")
        for name in ("detector_batch_size", "estimator_batch_size"):
            v = getattr(self, name)
            if not (_is_int(v) and v >= 1):
                raise ValueError(f"{name} = {v!r} is out of the allowed range: an integer >= 1")
        if not _is_int(self.seed):
            raise ValueError(f"seed = {self.seed!r} is not allowed: the noise seed must be an integer")
        return self


def _is_real(v: Any) -> bool:
    """A real number (Python or numpy), not a bool and not text."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _is_int(v: Any) -> bool:
    """An integer (Python or numpy), not a bool."""
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


def _check_patches_fit(size_hw: tuple[int, int], noise_estimator: Any, mtf_estimator: Any) -> None:
    """Refuse frames that cannot hold one estimator tile (128 px noise / 192 px MTF for ``"physics"``, else the
    estimator's ``patch_size``) before any cell is computed; ``None`` (no estimate) needs none."""
    h, w = size_hw
    for role, est, physics_patch in (("noise", noise_estimator, 128), ("MTF", mtf_estimator, 192)):
        if est is None:
            continue
        p = physics_patch if isinstance(est, str) and est == "physics" else getattr(est, "patch_size", None)
        if p is not None and int(p) > min(h, w):
            raise ValueError(f"frames of {w}×{h} px cannot hold one {int(p)}-px {role} estimator patch; the frames' "
                             f"height and width must be >= {int(p)} px")


def make_cells(grid: SweepGrid) -> list[dict[str, Any]]:
    """The grid's cells in a fixed order (noise level outer, then length, then direction)."""
    cells = []
    for s in grid.noise_levels_dn:
        for length in grid.lengths_px:
            for a in ([0.0] if float(length) == 0.0 else grid.angles_deg):
                key = f"L{float(length):g}_a{float(a):g}_s{float(s):g}"
                cells.append({"index": len(cells), "key": key, "length_px": float(length), "angle_deg": float(a),
                              "noise_level_dn": float(s)})
    return cells


def noise_gain_db(level_dn: float, meta: CameraMetadata, sources: Sequence[str], mean_intensity: float,
                  psf_energy: float = 1.0) -> float:
    """Gain [dB] at which ``sources`` reach a total σ of ``level_dn`` [DN] for ``meta`` (at its other
    settings) and a mean output intensity ``mean_intensity`` in [0, 1] (photon noise only).

    σ²(g) = a·g + b·g² with a = 255²·I·E/FW (photon, "digital gain" model) and b = σ_DCSN² + σ_RN² at
    0 dB (both scale with g). E = ``psf_energy`` = Σpsf² of the motion PSF (1 without blur): photon shot
    noise arises before the motion blur (physics chain: photon noise → blur → DCSN → readout), and blurring
    independent per-pixel noise with the PSF multiplies its variance by Σpsf² (0.14 at L = 7 px). Returns
    ``nan`` if no positive gain reaches the level (e.g. a level of 0 DN).

    Inputs are checked first (``ValueError``/``TypeError`` naming the value and the allowed range): ``level_dn`` a
    finite number >= 0 DN, ``meta`` a :class:`~camhealth.physics.CameraMetadata` of batch 1, ``sources`` a list or
    tuple of names from ('photon', 'dark', 'readout'), ``mean_intensity`` a number in [0, 1] and ``psf_energy`` in
    (0, 1].
    """
    if not (_is_real(level_dn) and math.isfinite(level_dn) and level_dn >= 0):
        raise ValueError(f"level_dn = {level_dn!r} is out of the allowed range: a finite number >= 0 DN (a noise σ)")
    if not isinstance(meta, CameraMetadata):
        raise TypeError(f"meta must be a CameraMetadata, got {type(meta).__name__}")
    if meta.batch_size != 1:
        raise ValueError(f"meta has batch {meta.batch_size}; allowed: 1 (one operating point; index the sample, meta[i])")
    if not isinstance(sources, (list, tuple)) or not all(isinstance(x, str) for x in sources):
        raise ValueError(f"sources = {sources!r:.80} is not allowed: a list of names from {list(NOISE_SOURCES)}")
    bad = [x for x in sources if x not in NOISE_SOURCES]
    if bad:
        raise ValueError(f"sources {bad} are not noise sources; allowed: a subset of {list(NOISE_SOURCES)}")
    if not (_is_real(mean_intensity) and 0.0 <= mean_intensity <= 1.0):
        raise ValueError(f"mean_intensity = {mean_intensity!r} is out of the allowed range [0, 1] (intensity, DN/255)")
    if not (_is_real(psf_energy) and 0.0 < psf_energy <= 1.0):
        raise ValueError(f"psf_energy = {psf_energy!r} is out of the allowed range (0, 1] (Σpsf² of a normalised PSF)")
    m0 = meta.replace(gain_db=0.0)
    a = 255.0**2 * mean_intensity * float(psf_energy) / float(m0.full_well_e[0]) if "photon" in sources else 0.0
    b = 0.0
    if "dark" in sources:
        b += float(dark_current_shot_sigma_dn(m0)[0]) ** 2
    if "readout" in sources:
        b += float(readout_sigma_dn(m0)[0]) ** 2
    s2 = float(level_dn) ** 2
    if b > 0:
        g = (-a + math.sqrt(a * a + 4.0 * b * s2)) / (2.0 * b)
    elif a > 0:
        g = s2 / a
    else:
        return float("nan")
    return float(factor_to_db(torch.tensor(g, dtype=torch.float64))) if g > 0 else float("nan")


def _cell_seed(seed: int, key: str) -> int:
    return int.from_bytes(hashlib.blake2b(f"{seed}\x1f{key}".encode(), digest_size=8).digest(), "big") >> 2


class IOPCSweep:
    """A sweep over one set of frames: holds frames, ground truth, the frozen detector and estimators.

    Args:
        frames: clean frames N×1×H×W in [0, 1] (same size), kept on the CPU.
        ground_truth: one {boxes, labels} per frame (COCO annotations or pseudo ground truth).
        detector: frozen detector (protocol); a detector with ``.to(device)`` follows the sweep device.
        noise_estimator, mtf_estimator: resolved estimators or ``"physics"`` (see estimation module).
        config: :class:`SweepConfig`.
        cache_dir: folder for per-cell results (resume, multi-process); ``None`` for no cache.
        frame_ids: ids of the frames (provenance and fingerprint).
        provenance: extra provenance entries (e.g. the ground-truth source).
    """

    def __init__(
        self,
        frames: torch.Tensor,
        ground_truth: Sequence[GroundTruth],
        detector: Detector,
        noise_estimator: Any,
        mtf_estimator: Any,
        config: SweepConfig | None = None,
        cache_dir: str | Path | None = None,
        frame_ids: Sequence[str] | None = None,
        provenance: dict[str, Any] | None = None,
    ) -> None:
        check_image(frames, "frames")
        lo, hi = torch.aminmax(frames)
        if lo < 0 or hi > 1:
            raise ValueError(f"frames must lie in [0, 1] (DN/255), got values in [{lo.item():g}, {hi.item():g}]")
        self.frames = frames.detach().cpu()
        self.ground_truth = validate_ground_truth(list(ground_truth))
        if len(self.ground_truth) != frames.shape[0]:
            raise ValueError(f"{len(self.ground_truth)} ground-truth entries for {frames.shape[0]} frames")
        if isinstance(detector, torch.nn.Module):
            detector = TorchDetector(detector)  # a bare module: freeze it behind the protocol
        if not callable(detector):
            raise TypeError(f"detector must be callable, got {type(detector).__name__}")
        self.detector = detector
        self.noise_estimator = noise_estimator
        self.mtf_estimator = mtf_estimator
        self.config = (config or SweepConfig()).validate()
        _check_patches_fit(tuple(frames.shape[-2:]), noise_estimator, mtf_estimator)
        self.cells = make_cells(self.config.grid)
        self.frame_ids = list(frame_ids) if frame_ids is not None else [f"frame{i}" for i in range(frames.shape[0])]
        self.extra_provenance = dict(provenance or {})
        self.cache_dir = Path(cache_dir) / self.fingerprint() if cache_dir is not None else None
        s = self.config.sensor
        self.meta0 = CameraMetadata.preset(s.preset, temperature_c=s.temperature_c, exposure_s=s.exposure_s)

    # ------------------------------------------------------------------ identity
    def _detector_config(self) -> Any:
        cfg = getattr(self.detector, "config", None)
        return cfg() if callable(cfg) else {"name": getattr(self.detector, "name", type(self.detector).__name__)}

    def fingerprint(self) -> str:
        """Hash of everything that determines a cell's result (16 hex digits)."""
        h = hashlib.blake2b(digest_size=8)
        h.update(json.dumps(asdict(self.config), sort_keys=True).encode())
        if "photon" in self.config.sensor.sources:
            # the gain of a blurred cell with photon noise accounts for the PSF energy (Σpsf²); cells cached by a
            # camhealth that solved it for unblurred photon noise have other noise levels and are not reused
            h.update(b"photon gain: psf energy")
        h.update(json.dumps(self._detector_config(), sort_keys=True, default=str).encode())
        h.update(estimator_fingerprint(self.noise_estimator).encode() + b"|" + estimator_fingerprint(self.mtf_estimator).encode())
        h.update("\x1f".join(self.frame_ids).encode())
        # the frames' bytes as stored (numpy has no bfloat16: viewed as bytes, the same bytes for every dtype)
        h.update(hashlib.blake2b(self.frames.contiguous().view(torch.uint8).numpy().tobytes(), digest_size=8).digest())
        for g in self.ground_truth:  # every field of it (boxes, labels, iscrowd, …): each can change the AP
            for key in sorted(g):
                v = g[key]
                h.update(key.encode() + (v.detach().cpu().numpy().tobytes() if isinstance(v, torch.Tensor) else repr(v).encode()))
        return h.hexdigest()

    def provenance(self) -> dict[str, Any]:
        """How the curves are made (stored in the IOPC file).

        ``frames.mean_intensity`` is the mean of the frames as swept, in [0, 1]: the clean frames multiplied by
        ``config.intensity`` and clipped at 1 (what :class:`~camhealth.control.IOPCController`'s
        ``reference_intensity`` needs); ``frames.source_mean_intensity`` is the mean of the clean frames as given.
        """
        import datetime as _dt
        import platform
        import subprocess

        def version(pkg: str) -> str:
            try:
                from importlib.metadata import version as v

                return v(pkg)
            except Exception:  # noqa: BLE001 - provenance is best effort
                return "?"

        try:
            commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                                    cwd=Path(__file__).resolve().parent).stdout.strip() or "?"
        except (OSError, subprocess.SubprocessError):
            commit = "?"
        return {
            "method": "thesis Sec. 4.4.1 / Eq. 4.4: corrupt (physics core) → patch-wise estimates on tiles "
                      "overlapping ground truth → median → detector AP@0.5 (COCOeval, score ≥ 0.5) → bins",
            "config": asdict(self.config),
            "detector": self._detector_config(),
            "noise_estimator": estimator_name(self.noise_estimator),
            "mtf_estimator": estimator_name(self.mtf_estimator),
            # mean_intensity: the frames as swept (after the config's intensity and its clipping at 1), i.e. the
            # brightness the detector saw; source_mean_intensity: the clean frames as given
            "frames": {"n": len(self.frame_ids), "ids": self.frame_ids, "size_hw": list(self.frames.shape[-2:]),
                       "mean_intensity": float(self._scaled(self.frames).mean()),
                       "source_mean_intensity": float(self.frames.mean())},
            "ground_truth_boxes": int(sum(g["boxes"].shape[0] for g in self.ground_truth)),
            "fingerprint": self.fingerprint(),
            "versions": {p: version(p) for p in ("camhealth", "torch", "kornia", "lightning", "pycocotools",
                                                  "opencv-python-headless", "numpy")},
            "git_commit": commit,
            "python": platform.python_version(),
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            **self.extra_provenance,
        }

    # ------------------------------------------------------------------ cache
    def _cache_path(self, cell: dict[str, Any]) -> Path | None:
        if self.cache_dir is None:
            return None
        return self.cache_dir / f"cell_{cell['index']:05d}_{cell['key']}.json"

    def cached(self, cell: dict[str, Any]) -> dict[str, Any] | None:
        """The cached record of ``cell``, or ``None`` when there is none to use.

        A cache file that is not this cell's record counts as not cached, and the cell is computed again (and its
        file rewritten): a file that cannot be read, is not UTF-8 text or not JSON (torn or corrupt), holds no JSON
        object, or holds the record of another cell (its ``index`` or ``key`` differ from ``cell``'s, e.g. a file
        copied or renamed by hand), or lacks a field every record has (``sigma_tilde``, ``mtf_tilde``, ``ap``, …)."""
        p = self._cache_path(cell)
        if p is None or not p.is_file():
            return None
        try:
            rec = json.loads(p.read_text(encoding="utf-8"))
        except (ValueError, OSError, RecursionError):  # JSONDecodeError and UnicodeDecodeError are ValueErrors
            return None  # a torn or corrupt file (a crash while writing before the rename cannot happen; be safe anyway)
        if not isinstance(rec, dict) or rec.get("key") != cell["key"] or not _is_int(rec.get("index")) \
                or rec["index"] != cell["index"] or not all(k in rec for k in _RECORD_KEYS):
            return None  # not this cell's (complete) record
        return {k: (float("nan") if v is None and k in _FLOAT_KEYS else v) for k, v in rec.items()}

    def _store(self, cell: dict[str, Any], record: dict[str, Any]) -> None:
        p = self._cache_path(cell)
        if p is None:
            return
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_suffix(f".tmp{os.getpid()}")
        tmp.write_text(json.dumps(_json_record(record)))
        os.replace(tmp, p)

    def remaining_cells(self) -> list[dict[str, Any]]:
        """Cells without a cached record."""
        return [c for c in self.cells if self.cached(c) is None]

    # ------------------------------------------------------------------ one cell
    def _scaled(self, frames: torch.Tensor) -> torch.Tensor:
        k = self.config.intensity
        return frames if k == 1.0 else (frames * k).clamp_(0.0, 1.0)

    def run_cell(self, cell: dict[str, Any], device: torch.device | str = "cpu") -> dict[str, Any]:
        """Process one grid cell (or return its cached record). Pure given the cell and the sweep."""
        hit = self.cached(cell)
        if hit is not None:
            return hit
        t0 = time.perf_counter()
        cfg = self.config
        dev = torch.device(device)
        rec: dict[str, Any] = {
            **{k: cell[k] for k in ("index", "key", "length_px", "angle_deg", "noise_level_dn")},
            "gain_db": float("nan"), "ap": float("nan"), "n_gt": 0, "n_detections": 0,
            "sigma_tilde": float("nan"), "mtf_tilde": float("nan"), "sigma_sources_tilde": None,
            "sigma_true_dn": float("nan"), "mtf_true": float("nan"),
            "n_noise_tiles": 0, "n_mtf_tiles": 0, "n_noise_assessed": 0, "n_mtf_assessed": 0,
            "marked": False, "reason": "",
        }
        length, angle, level = cell["length_px"], cell["angle_deg"], cell["noise_level_dn"]
        n = self.frames.shape[0]
        meta = None
        sources: tuple[str, ...] = ()
        psf = None
        if length > 0:  # the PSF does not depend on the gain; its energy sets the blurred photon noise
            k = int(math.ceil(length)) + 2
            k += 1 - k % 2
            psf = linear_motion_psf(torch.tensor([length]), torch.tensor([angle]), k)
        if level > 0:
            sources = tuple(cfg.sensor.sources)
            energy = float(psf.double().pow(2).sum()) if psf is not None else 1.0
            gain = noise_gain_db(level, self.meta0, sources, float(self._scaled(self.frames).mean()), energy)
            lo, hi = METADATA_RANGES["gain_db"]
            if not (math.isfinite(gain) and lo - 1e-6 <= gain <= hi + 1e-6):
                blur = (f" (the {length:g}-px motion blur averages the photon noise: Σpsf² = {energy:.3f})"
                        if psf is not None and "photon" in sources else "")
                rec.update(gain_db=gain, marked=True, reason=(
                    f"noise level {level:g} DN needs gain {gain:.1f} dB with {cfg.sensor.preset} at "
                    f"{cfg.sensor.temperature_c:g} °C, {cfg.sensor.exposure_s:g} s{blur}; outside [{lo:g}, {hi:g}] dB"))
                rec["seconds"] = time.perf_counter() - t0
                self._store(cell, rec)
                return rec
            gain = min(max(gain, lo), hi)
            rec["gain_db"] = gain
            meta = self.meta0.replace(gain_db=gain).expand(n).to(device=dev)
        if psf is not None:
            psf = psf.to(dev)
            mtf_true = mtf_hv(psf.double()).float()
            psf = psf.expand(n, *psf.shape[-2:])
        else:
            mtf_true = torch.ones(1, 16)
        rec["mtf_true"] = float(mtf_indicator(mtf_true)[0])
        gen = torch.Generator(device=dev).manual_seed(_cell_seed(cfg.seed, cell["key"]))
        clean = self._scaled(self.frames.to(dev))
        with torch.no_grad():
            f = form_image(clean, meta, motion_psf=psf, sources=sources, generator=gen, quantize=cfg.quantize)
        image = f.image
        rec["sigma_true_dn"] = float(f.sigma_total_dn.mean())
        # --- detector on the corrupted frames → AP
        to = getattr(self.detector, "to", None)
        if callable(to):
            to(dev)
        dets = []
        for s in range(0, n, cfg.detector_batch_size):
            chunk = image[s : s + cfg.detector_batch_size]
            dets += validate_detections(self.detector(chunk), chunk.shape[0], tuple(chunk.shape[-2:]), name="detector output")
        res = evaluate_detections(dets, self.ground_truth, tuple(image.shape[-2:]), cfg.iou_threshold, cfg.score_threshold)
        rec.update(ap=res.ap, n_gt=res.n_gt, n_detections=res.n_detections)
        # --- estimates on the tiles overlapping ground truth → Eq. 4.4 medians
        physics = {"blurred": f.blurred, "mtf": mtf_true.expand(n, 16), "sigma_dn": f.sigma_dn}
        est = estimate_regions(
            image, [g["boxes"] for g in self.ground_truth], self.noise_estimator, self.mtf_estimator,
            metadata=meta if meta is not None else self.meta0.replace(gain_db=0.0).expand(n),
            physics=physics, fallback_all=False, batch_size=cfg.estimator_batch_size,
        )
        med = median_estimates(est)
        rec.update(
            sigma_tilde=med["sigma_tilde"], mtf_tilde=med["mtf_tilde"], sigma_sources_tilde=med["sigma_sources_tilde"],
            n_noise_tiles=est.n_noise_tiles, n_mtf_tiles=est.n_mtf_tiles,
            n_noise_assessed=int(est.sigma.numel()), n_mtf_assessed=int(est.mtf.numel()),
        )
        reasons = []
        vs, vl = cfg.valid_sigma_dn, cfg.valid_length_px
        if not vs[0] <= level <= vs[1]:
            reasons.append(f"noise level {level:g} DN outside the noise estimator's valid range [{vs[0]:g}, {vs[1]:g}] DN")
        if not vl[0] <= length <= vl[1]:
            reasons.append(f"blur length {length:g} px outside the MTF estimator's valid range [{vl[0]:g}, {vl[1]:g}] px")
        if not math.isfinite(rec["sigma_tilde"]) or not math.isfinite(rec["mtf_tilde"]):
            reasons.append("no assessable tile overlapping a ground-truth box")
        if reasons:
            rec.update(marked=True, reason="; ".join(reasons))
        rec["seconds"] = time.perf_counter() - t0
        self._store(cell, rec)
        return rec

    # ------------------------------------------------------------------ whole grid
    def collect(self, records: Sequence[dict[str, Any]] = ()) -> list[dict[str, Any]]:
        """All cells' records: from ``records`` (by index), else from the cache; raises if any is missing."""
        by_index = {int(r["index"]): r for r in records}
        out, missing = [], []
        for c in self.cells:
            r = by_index.get(c["index"]) or self.cached(c)
            if r is None:
                missing.append(c["key"])
            else:
                out.append(r)
        if missing:
            raise RuntimeError(f"{len(missing)} cell(s) have no result, e.g. {missing[:3]}")
        return out

    def to_iopc(self, records: Sequence[dict[str, Any]]) -> IOPC:
        """Bin records into an :class:`~camhealth.iopc.curves.IOPC` with this sweep's provenance."""
        name = f"AP@{self.config.iou_threshold:g} {self._detector_config().get('name', 'detector')}"
        return IOPC.from_records(records, self.config.sigma_bins_dn, self.config.mtf_bins, self.provenance(), name)

    def run(self, trainer: L.Trainer | None = None, **trainer_kwargs: Any) -> IOPC:
        """Run all cells through ``trainer.predict`` (a new CPU/auto Trainer if none) and bin them.

        With several processes (DDP) every rank runs its share of the cells; the ranks' records meet in
        the cache, which must then be set (``cache_dir``) on a file system all ranks see. The loader then
        holds the whole grid on every rank, so that the distributed sampler's split depends only on the grid
        (never on which cells a rank found cached at its own moment); cached cells are read, not recomputed,
        and every rank reaches the barrier.
        """
        if trainer is None:
            kw = {"accelerator": "auto", "devices": 1, "logger": False, "enable_checkpointing": False,
                  "enable_model_summary": False}
            kw.update(trainer_kwargs)
            trainer = L.Trainer(**kw)
        if trainer.world_size > 1 and self.cache_dir is None:
            raise ValueError("a distributed sweep needs cache_dir (on a file system all ranks share)")
        distributed = trainer.world_size > 1
        # one process: only the uncached cells; several: the whole grid on every rank (see above)
        todo = list(self.cells) if distributed else self.remaining_cells()
        records: list[dict[str, Any]] = []
        if todo:
            loader = torch.utils.data.DataLoader(CellDataset(todo), batch_size=1, shuffle=False, collate_fn=_single)
            out = trainer.predict(IOPCSweepModule(self), dataloaders=loader, return_predictions=True)
            records = list(out or [])
        trainer.strategy.barrier()
        return self.to_iopc(self.collect(records))

    def run_local(self, device: torch.device | str = "cpu", rank: int = 0, world_size: int = 1,
                  progress: bool = True) -> list[dict[str, Any]]:
        """Run this rank's share of the grid in-process (no Trainer; used by the callback inside a running fit):
        cells ``rank``, ``rank + world_size``, … of :attr:`cells`, skipping those already cached. The share
        depends only on the grid, so the ranks cover it disjointly whenever each of them gets here. Returns the
        records this rank computed."""
        if not (_is_int(world_size) and world_size >= 1):
            raise ValueError(f"world_size = {world_size!r} is out of the allowed range: an integer >= 1")
        if not (_is_int(rank) and 0 <= rank < world_size):
            raise ValueError(f"rank = {rank!r} is out of the allowed range: an integer in [0, {world_size - 1}]")
        todo = [c for c in self.cells[rank::world_size] if self.cached(c) is None]
        it: Any = todo
        if progress and todo:
            from tqdm.auto import tqdm

            it = tqdm(todo, desc=f"IOPC sweep (rank {rank})", leave=False)
        return [self.run_cell(c, device) for c in it]


_FLOAT_KEYS = ("gain_db", "ap", "sigma_tilde", "mtf_tilde", "sigma_true_dn", "mtf_true", "seconds")
#: Fields every cell record holds (what :meth:`IOPC.from_records` reads): a cached file without one is not a record.
_RECORD_KEYS = ("index", "key", "length_px", "angle_deg", "noise_level_dn", "sigma_tilde", "mtf_tilde", "ap", "marked")


def _json_record(rec: dict[str, Any]) -> dict[str, Any]:
    out = {}
    for k, v in rec.items():
        if isinstance(v, float) and not math.isfinite(v):
            v = None
        out[k] = v
    return out


def _single(items: list[dict[str, Any]]) -> dict[str, Any]:
    return items[0]


class CellDataset(torch.utils.data.Dataset):
    """Map-style dataset of grid cells (dicts), one cell per item."""

    def __init__(self, cells: Sequence[dict[str, Any]]) -> None:
        self.cells = list(cells)

    def __len__(self) -> int:
        return len(self.cells)

    def __getitem__(self, index: int) -> dict[str, Any]:
        return self.cells[index]


class IOPCSweepModule(L.LightningModule):
    """LightningModule whose ``predict_step`` processes one grid cell of an :class:`IOPCSweep`.

    It has no parameters: the detector and estimators are frozen and held by the sweep (not registered
    as sub-modules, so they are never trained, wrapped or checkpointed).
    """

    def __init__(self, sweep: IOPCSweep) -> None:
        super().__init__()
        self._sweep = [sweep]  # a list: keeps nn.Module estimators out of the module tree

    @property
    def sweep(self) -> IOPCSweep:
        return self._sweep[0]

    def forward(self, cell: dict[str, Any]) -> dict[str, Any]:
        return self.sweep.run_cell(cell, self.device)

    def predict_step(self, batch: dict[str, Any], batch_idx: int, dataloader_idx: int = 0) -> dict[str, Any]:
        # Lightning's SIGTERM handler only notes the signal (its fit loop stops on it, its predict loop does not): stop
        # before the next cell, exit status 143 (128 + SIGTERM); cells already done stay in the sweep's cache_dir
        connector = getattr(self._trainer, "_signal_connector", None) if self._trainer is not None else None
        if getattr(connector, "received_sigterm", False):
            print(f"camhealth.iopc: terminated (SIGTERM) before cell {batch_idx}", file=sys.stderr)
            raise SystemExit(143)
        return self.sweep.run_cell(batch, self.device)


def log_iopc(experiment: Any, iopc: IOPC, step: int = 0, tag: str = "iopc") -> bool:
    """Log the IOPC heat map and curves to a TensorBoard ``SummaryWriter`` (or a TensorBoardLogger's
    ``experiment``): a figure, the 2-D AP surface as an image, and scalars per measured bin.
    Returns False if ``experiment`` cannot log figures."""
    if not hasattr(experiment, "add_figure"):
        return False
    import matplotlib.pyplot as plt

    fig = iopc.figure()
    experiment.add_figure(f"{tag}/curves", fig, global_step=step)
    plt.close(fig)
    surf = np.nan_to_num(iopc.ap_2d, nan=0.0)[::-1].copy()  # σ up
    experiment.add_image(f"{tag}/ap_2d", torch.as_tensor(surf, dtype=torch.float32)[None], global_step=step)
    experiment.add_scalar(f"{tag}/ap_clean", float(iopc.ap_2d[0, -1]) if iopc.count_2d[0, -1] else float("nan"), step)
    experiment.add_scalar(f"{tag}/marked_cells", float(len(iopc.marked_records)), step)
    return True
