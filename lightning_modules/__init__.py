"""LightningModules of camhealth's learned estimators (thesis Sec. 4.3).

- :class:`NoiseSourceEstimator` — σ of photon shot, dark-current shot and readout noise plus the residual ξ
  from a patch and camera metadata (w/o-, Min-, Full-Meta; hybrid with the closed-form noise model).
- :class:`NoiseLevelEstimator` — DRNE-style pixel-wise total-noise σ map and its patch statistics.
- :class:`MTFEstimator` — MTF at 8 frequencies, horizontal and vertical, from a 192-px patch.
- :class:`IOPCCallback` — input-output performance curves of a frozen detector at the end of ``fit``.
"""

from lightning_modules.base import EstimatorModule
from lightning_modules.drne import NoiseLevelEstimator, NoiseLevelNet, ThesisNoiseNet
from lightning_modules.iopc_callback import IOPCCallback
from lightning_modules.mtf import MTFEstimator, MTFNet, MTFPreprocess
from lightning_modules.noise_source import NoiseSourceEstimator, NoiseSourceNet, NoiseTrunk

__all__ = [
    "EstimatorModule", "NoiseSourceEstimator", "NoiseSourceNet", "NoiseTrunk", "NoiseLevelEstimator",
    "NoiseLevelNet", "ThesisNoiseNet", "MTFEstimator", "MTFNet", "MTFPreprocess", "IOPCCallback",
]
