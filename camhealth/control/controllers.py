"""Exposure/gain controllers for the closed loop: fixed, intensity-tracking auto-exposure, IOPC policy.

Every controller sees, after each frame, an :class:`Observation` (the rendered frame, its metadata and
the detector's output) and returns the (exposure [s], gain [dB]) for the next frame.

* :class:`FixedController` — constant parameters (the thesis's "fixed" configuration).
* :class:`AutoExposureController` — a built-in-camera style controller (thesis Sec. 7.3: it "tracks a
  mean image intensity level of 50 % and prioritizes changing t_exp over ISO gain"). In the log domain
  it moves the total exposure E = t·g towards the target, E ← E·(target/mean)^k with damping k and a
  dead band, and allocates E to the exposure time first (up to the longest exposure) and to the gain
  only beyond it (and takes gain back first when the image is too bright).
* :class:`IOPCController` — the framework: estimates σ̂ and MTF̂ on the tiles overlapping the current
  detections (Eq. 4.4 medians; all tiles when nothing is detected), asks the
  :class:`~camhealth.control.policy.ExposurePolicy` for α* and applies it (exposure ÷ α, gain × α, so
  the intensity stays). It decides after the first frame on which σ̂ and MTF̂ can be estimated (as in the
  thesis's Parking Lot run, where that is the first frame) and, with ``decide_every = n``, on frames 0, n,
  2n, … (the policy's ``min_gain`` is the hysteresis).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from camhealth.control.camera_sim import Capture
from camhealth.control.policy import CameraLimits, Decision, ExposurePolicy
from camhealth.detection.protocol import Detection
from camhealth.iopc.estimation import PHYSICS, estimate_regions, median_estimates, resolve_estimator

__all__ = ["Observation", "Controller", "FixedController", "AutoExposureController", "IOPCController", "MAX_CLIPPED_FRACTION"]

#: The share of a frame's pixels at 0 or 255 DN above which :class:`IOPCController` keeps the parameters: more than
#: half clipped, as the estimators call a patch black or saturated (its noise and blur clipped away). With the
#: simulator's labels σ̂ and MTF̂ would still come back, read off a frame that shows neither.
MAX_CLIPPED_FRACTION = 0.5


@dataclass
class Observation:
    """What a controller sees after frame ``frame``: the capture (batch of one), the detector's output
    on it, and the parameters it was taken with."""

    frame: int
    capture: Capture
    detections: Detection
    exposure_s: float
    gain_db: float


class Controller(Protocol):
    """``reset(exposure_s, gain_db)`` then ``update(observation) -> (exposure_s, gain_db)`` per frame."""

    name: str

    def reset(self, exposure_s: float, gain_db: float) -> tuple[float, float]: ...

    def update(self, obs: Observation) -> tuple[float, float]: ...


def _is_real(v: Any) -> bool:
    """A real number (Python or NumPy), not a bool and not text."""
    return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_))


def _check_capture_matches(obs: Observation, who: str) -> None:
    """Refuse an observation whose capture is not a batch of one, or whose ``exposure_s``/``gain_db`` contradict the
    parameters the capture was taken with (``ValueError`` naming both)."""
    cap = obs.capture
    n = int(cap.image.shape[0])
    if n != 1:
        raise ValueError(f"{who}: an observation's capture must be a batch of one (index it, capture[i]); got a batch "
                         f"of {n}")
    t_cap, g_cap = float(cap.exposure_s[0]), float(cap.gain_db[0])
    for nm, v, unit in (("exposure_s", obs.exposure_s, "s"), ("gain_db", obs.gain_db, "dB")):
        if not (_is_real(v) and math.isfinite(v)):
            raise ValueError(f"{who}: observation {nm} = {v!r} {unit} must be a finite number")
    # the capture stores its parameters as float32: equal within its rounding
    if not math.isclose(obs.exposure_s, t_cap, rel_tol=1e-6):
        raise ValueError(f"{who}: observation exposure_s = {obs.exposure_s!r} s contradicts the capture's exposure "
                         f"{t_cap:.9g} s; they must be equal (relative tolerance 1e-6)")
    if not math.isclose(obs.gain_db, g_cap, rel_tol=1e-6, abs_tol=1e-6):
        raise ValueError(f"{who}: observation gain_db = {obs.gain_db!r} dB contradicts the capture's gain {g_cap:.9g} dB; "
                         "they must be equal (within 1e-6)")


class FixedController:
    """Constant exposure [s] and gain [dB], inside the camera's limits.

    Args:
        exposure_s: exposure time [s], a number within ``limits.exposure_s``.
        gain_db: gain [dB], a number within ``limits.gain_db``.
        name: the controller's name.
        limits: :class:`~camhealth.control.policy.CameraLimits` (default: 0.001–0.2 s, 0–24 dB, Table 4.1).
    """

    def __init__(self, exposure_s: float, gain_db: float = 0.0, name: str = "fixed",
                 limits: CameraLimits | None = None) -> None:
        if limits is not None and not isinstance(limits, CameraLimits):
            raise TypeError(f"FixedController: limits must be a CameraLimits, got {type(limits).__name__} {limits!r:.60}")
        self.limits = limits or CameraLimits()
        for nm, v, unit in (("exposure_s", exposure_s, "s"), ("gain_db", gain_db, "dB")):
            if not _is_real(v):
                raise ValueError(f"FixedController: {nm} = {v!r:.60} is not allowed: a number [{unit}], got "
                                 f"{type(v).__name__}")
        self.exposure_s, self.gain_db, self.name = float(exposure_s), float(gain_db), name
        if not (math.isfinite(self.exposure_s) and self.exposure_s > 0 and math.isfinite(self.gain_db)):
            raise ValueError(f"FixedController: exposure_s = {exposure_s!r} s must be a finite number > 0 and gain_db = "
                             f"{gain_db!r} dB finite")
        (t0, t1), (g0, g1) = self.limits.exposure_s, self.limits.gain_db
        if not t0 <= self.exposure_s <= t1:
            raise ValueError(f"FixedController: exposure_s = {exposure_s!r} s is out of the allowed range [{t0:g}, {t1:g}] s "
                             "(the camera limits)")
        if not g0 <= self.gain_db <= g1:
            raise ValueError(f"FixedController: gain_db = {gain_db!r} dB is out of the allowed range [{g0:g}, {g1:g}] dB "
                             "(the camera limits)")

    def reset(self, exposure_s: float | None = None, gain_db: float | None = None) -> tuple[float, float]:
        return self.exposure_s, self.gain_db

    def update(self, obs: Observation) -> tuple[float, float]:
        return self.exposure_s, self.gain_db


class AutoExposureController:
    """Intensity-tracking auto-exposure that prefers exposure over gain.

    Args:
        target_mean: target mean intensity in (0, 1) (0.5 = 50 %, as the thesis's camera).
        limits: camera limits; exposure is used up to ``limits.exposure_s[1]`` before any gain.
        damping: exponent k of the log-domain step (1 = jump to the target in one frame).
        deadband: no change while |mean/target − 1| < deadband.
        max_step: largest factor of E per frame.
    """

    def __init__(self, target_mean: float = 0.5, limits: CameraLimits | None = None, damping: float = 0.7,
                 deadband: float = 0.05, max_step: float = 4.0, name: str = "auto-exposure") -> None:
        for nm, v in (("target_mean", target_mean), ("damping", damping), ("deadband", deadband), ("max_step", max_step)):
            if not _is_real(v):
                raise ValueError(f"{nm} = {v!r:.60} is not allowed: a number, got {type(v).__name__}")
        if limits is not None and not isinstance(limits, CameraLimits):
            raise TypeError(f"limits must be a CameraLimits, got {type(limits).__name__} {limits!r:.60}")
        if not 0 < target_mean < 1:
            raise ValueError(f"target_mean = {target_mean!r} must lie in (0, 1)")
        if not 0 < damping <= 1:
            raise ValueError(f"damping = {damping!r} must lie in (0, 1]")
        if not deadband >= 0:
            raise ValueError(f"deadband = {deadband!r} is out of the allowed range: a number >= 0")
        if not max_step > 1:
            raise ValueError(f"max_step = {max_step!r} is out of the allowed range: a number > 1")
        self.target, self.limits, self.damping = float(target_mean), limits or CameraLimits(), float(damping)
        self.deadband, self.max_step, self.name = float(deadband), float(max_step), name

    def reset(self, exposure_s: float, gain_db: float) -> tuple[float, float]:
        return self.limits.clamp(exposure_s, gain_db)

    def allocate(self, total: float) -> tuple[float, float]:
        """Split a total exposure E = t·g [s] (a finite number > 0) into (t [s], gain [dB]), exposure first, within the
        limits."""
        if not (_is_real(total) and math.isfinite(total) and total > 0):
            raise ValueError(f"{self.name}: total exposure = {total!r} s is out of the allowed range: a finite number > 0 "
                             "(exposure × gain factor)")
        (t0, t1), (g0, g1) = self.limits.exposure_s, self.limits.gain_db
        gmin = 10 ** (g0 / 20)
        t = min(max(total / gmin, t0), t1)
        g = min(max(total / t, gmin), 10 ** (g1 / 20))
        return t, 20 * math.log10(g)

    def update(self, obs: Observation) -> tuple[float, float]:
        mean = float(obs.capture.mean_intensity[0])
        if not (math.isfinite(mean) and math.isfinite(obs.exposure_s) and math.isfinite(obs.gain_db)):
            raise ValueError(f"{self.name}: mean intensity {mean!r}, exposure {obs.exposure_s!r} s and gain {obs.gain_db!r} dB "
                             "must be finite")
        ratio = self.target / max(mean, 1e-4)
        if abs(mean / self.target - 1) < self.deadband:
            return obs.exposure_s, obs.gain_db
        step = min(max(ratio**self.damping, 1 / self.max_step), self.max_step)
        total = obs.exposure_s * 10 ** (obs.gain_db / 20) * step
        return self.allocate(total)


class IOPCController:
    """The IOPC policy in the loop.

    Args:
        policy: :class:`~camhealth.control.policy.ExposurePolicy`.
        noise_estimator, mtf_estimator: estimators or specs as :func:`camhealth.iopc.resolve_estimator` takes them
            (``"physics"``: the simulator's labels, ``"immerkaer"``, a name or path for ``load_estimator``, an object
            with the predict contract); resolved, and refused if they do not fit their role, when the controller is
            built.
        decide_every: ``None``: decide once, after the first frame on which something can be assessed (a frame
            where σ̂ or MTF̂ is not available, e.g. a black frame, keeps the parameters and the next frame is tried).
            ``n``: decide on the frames 0, n, 2n, … counted from :meth:`reset`; a due frame with nothing
            assessable keeps the parameters, and the next attempt is the next due frame (no retry in between).
        score_threshold: detections that define the regions to estimate on.
        use_sources: pass the per-source σ̂ (noise-source estimators, physics labels) to the policy.
        reference_intensity: optional mean intensity in (0, 1] of the frames the IOPC was measured on, as the
            detector saw them (the sweep's provenance ``frames.mean_intensity``: after ``SweepConfig.intensity``).
            When given, σ̂ is rescaled to that brightness, σ_eff = σ̂ · reference / mean, before the IOPC is
            consulted: for a contrast-invariant detector
            (HOG's block normalisation, CNNs with normalisation) a darker image with the same σ̂ is as
            hard as a brighter one with proportionally more noise. This is an extension of the thesis,
            whose IOPCs and policy ignore the image intensity (Sec. 7.2: "we did not investigate the
            influence of image intensity"); default ``None`` = the thesis's policy.
    """

    def __init__(self, policy: ExposurePolicy, noise_estimator: Any = PHYSICS, mtf_estimator: Any = PHYSICS,
                 decide_every: int | None = None, score_threshold: float = 0.5, use_sources: bool = True,
                 reference_intensity: float | None = None, name: str = "IOPC policy") -> None:
        if decide_every is not None and (isinstance(decide_every, bool) or not isinstance(decide_every, numbers.Integral)
                                         or decide_every < 1):
            raise ValueError(f"decide_every = {decide_every!r} must be a positive integer or None")
        if not isinstance(policy, ExposurePolicy):
            raise TypeError(f"policy must be an ExposurePolicy, got {type(policy).__name__}")
        # a threshold outside [0, 1] (or NaN) keeps no detection, and the estimates silently fall back to the whole frame
        if isinstance(score_threshold, bool) or not isinstance(score_threshold, numbers.Real) or not 0 <= score_threshold <= 1:
            raise ValueError(f"score_threshold = {score_threshold!r} is out of the allowed range: a number in [0, 1] "
                             "(detector score)")
        if not isinstance(use_sources, bool):
            raise ValueError(f"use_sources = {use_sources!r} must be True or False")
        if reference_intensity is not None and (isinstance(reference_intensity, bool)
                                                or not isinstance(reference_intensity, numbers.Real)):
            raise ValueError(f"reference_intensity = {reference_intensity!r} must be a number in (0, 1] or None")
        self.policy = policy
        self.noise, self.mtf = resolve_estimator(noise_estimator, "noise"), resolve_estimator(mtf_estimator, "mtf")
        self.decide_every, self.score_threshold, self.use_sources, self.name = decide_every, score_threshold, use_sources, name
        if reference_intensity is not None and not 0 < reference_intensity <= 1:
            raise ValueError(f"reference_intensity = {reference_intensity!r} must lie in (0, 1]")
        self.reference_intensity = reference_intensity
        self.decisions: list[tuple[int, Decision, dict[str, Any]]] = []
        # frames on which nothing was decided, and why (the frame is clipped, or the policy cannot tell)
        self.refusals: list[tuple[int, str]] = []
        self._n_updates = 0

    def reset(self, exposure_s: float, gain_db: float) -> tuple[float, float]:
        self.decisions = []
        self.refusals = []
        self._n_updates = 0
        return self.policy.limits.clamp(exposure_s, gain_db)

    def _due(self) -> bool:
        """Whether this frame is one to decide on (counts the frame). ``decide_every=None``: every frame until the
        first decision has been made; ``n``: frames 0, n, 2n, …"""
        n = self._n_updates
        self._n_updates += 1
        return not self.decisions if self.decide_every is None else n % self.decide_every == 0

    def estimate(self, obs: Observation) -> dict[str, Any]:
        """Eq. 4.4 medians of σ̂ and MTF̂ over the tiles overlapping the current detections (a capture of one frame)."""
        cap = obs.capture
        if int(cap.image.shape[0]) != 1:
            raise ValueError(f"{self.name}: an observation's capture must be a batch of one (index it, capture[i]); got a "
                             f"batch of {int(cap.image.shape[0])}")
        keep = obs.detections["scores"] >= self.score_threshold
        regions = [obs.detections["boxes"][keep]]
        physics = {"blurred": cap.blurred, "mtf": cap.mtf, "sigma_dn": cap.sigma_dn}
        est = estimate_regions(cap.image, regions, self.noise, self.mtf, metadata=cap.meta, physics=physics,
                               fallback_all=True)
        med = median_estimates(est)
        med["n_regions"] = int(keep.sum())
        return med

    def update(self, obs: Observation) -> tuple[float, float]:
        """The parameters for the next frame. ``obs.capture`` must be a batch of one whose exposure and gain are
        ``obs.exposure_s`` and ``obs.gain_db`` (``ValueError`` naming both otherwise)."""
        _check_capture_matches(obs, self.name)
        if not self._due():
            return obs.exposure_s, obs.gain_db
        clipped = float(obs.capture.clipped_fraction[0])
        if clipped > MAX_CLIPPED_FRACTION:  # a black or saturated frame: its noise and blur are clipped away
            self.refusals.append((obs.frame, f"{clipped:.0%} of the frame's pixels are clipped (more than "
                                             f"{MAX_CLIPPED_FRACTION:.0%}): parameters kept"))
            return obs.exposure_s, obs.gain_db
        med = self.estimate(obs)
        if not (math.isfinite(med["sigma_tilde"]) and math.isfinite(med["mtf_tilde"])):
            return obs.exposure_s, obs.gain_db  # nothing assessable: keep
        sources = med["sigma_sources_tilde"] if self.use_sources else None
        sigma = med["sigma_tilde"]
        if self.reference_intensity is not None:
            scale = self.reference_intensity / max(float(obs.capture.mean_intensity[0]), 1e-3)
            med["intensity_scale"] = scale
            sigma = sigma * scale
            sources = [v * scale for v in sources] if sources is not None else None
        mtf = min(max(med["mtf_tilde"], 0.0), 1.0)  # an MTF lies in [0, 1]; an estimator may overshoot either side
        try:
            d = self.policy.decide(sigma, mtf, obs.exposure_s, obs.gain_db, sigma_sources=sources)
        except ValueError as exc:  # e.g. more blur than the IOPC's MTF → length relation measured: it cannot tell
            self.refusals.append((obs.frame, f"{exc}: parameters kept"))
            return obs.exposure_s, obs.gain_db
        self.decisions.append((obs.frame, d, med))
        return d.exposure_s, d.gain_db
