"""Decision & control (thesis Sec. 4.4.2, 4.5.2, Ch. 7): choose exposure and gain for the detector.

- :mod:`~camhealth.control.policy` — :class:`ExposurePolicy`: α* = argmax AP(σ_new(α), MB_L(MTF̂)/α)
  (Eq. 4.5–4.8) from IOPCs, camera limits, DCSN ∝ t_exp, multi-application weights, a precomputed
  look-up table, and a :class:`Decision` that explains itself.
- :mod:`~camhealth.control.camera_sim` — :class:`SimulatedCamera`: clean frames rendered at any
  exposure/gain/scene motion/illumination through the physics core.
- :mod:`~camhealth.control.controllers` — fixed, intensity-tracking auto-exposure, IOPC policy.
- ``python -m camhealth.demo closed-loop`` — the three controllers on the street clip (:mod:`camhealth.demo`).
"""

from camhealth.control.camera_sim import Capture, SimulatedCamera, motion_kernel_for
from camhealth.control.controllers import (
    AutoExposureController,
    Controller,
    FixedController,
    IOPCController,
    Observation,
)
from camhealth.control.policy import Application, CameraLimits, Decision, ExposurePolicy, noise_scale

__all__ = [
    "ExposurePolicy", "CameraLimits", "Application", "Decision", "noise_scale",
    "SimulatedCamera", "Capture", "motion_kernel_for",
    "Controller", "Observation", "FixedController", "AutoExposureController", "IOPCController",
]
