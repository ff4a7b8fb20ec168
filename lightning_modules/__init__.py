"""LightningModules that train camhealth's learned estimators (thesis Sec. 4.3): loss, metrics, logging, figures.

The networks themselves are plain ``torch.nn.Module``s in :mod:`camhealth.nets` (inference needs no Lightning);
their names stay importable from here.

- :class:`NoiseSourceEstimator` — trains :class:`~camhealth.nets.noise_source.NoiseSourceNet`: σ of photon shot,
  dark-current shot and readout noise plus the residual ξ from a patch and camera metadata (w/o- and Min-Meta).
- :class:`NoiseLevelEstimator` — trains :class:`~camhealth.nets.drne.NoiseLevelNet`: DRNE-style pixel-wise
  total-noise σ map and its patch statistics.
- :class:`MTFEstimator` — trains :class:`~camhealth.nets.mtf.MTFNet`: MTF at 8 frequencies, horizontal and
  vertical, from a 192-px patch.
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
