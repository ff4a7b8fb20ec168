"""Camera calibration: a real camera's metadata from bias, dark and flat frames.

``python -m camhealth.calibrate FRAMES... --out camera.yaml [--report DIR]`` or
:func:`calibrate` — see ``docs/calibration.md``. One module per model:

- :mod:`~camhealth.calibrate.frames` — frame sets, reading them, the file-name convention;
- :mod:`~camhealth.calibrate.manifest` — YAML/CSV manifests;
- :mod:`~camhealth.calibrate.statistics` — per-set mean, temporal noise (temporal or censored estimator,
  thesis Alg. 1's histogram rectification), master frames, hot pixels;
- :mod:`~camhealth.calibrate.dark_signal` — read noise per temperature, dark current and its Eq. 3.14 law;
- :mod:`~camhealth.calibrate.photon_transfer` — conversion gain from flats (EMVA 1288) → full well;
- :mod:`~camhealth.calibrate.readout` — read noise → thermal white noise W (Eq. 3.17 inverted);
- :mod:`~camhealth.calibrate.result` — the result, ``camera.yaml``, details and maps;
- :mod:`~camhealth.calibrate.report` — photon-transfer curve, dark signal, residuals (PNG + Markdown);
- :mod:`~camhealth.calibrate.synthetic` — stacks of a known camera from the physics core.
"""

from camhealth.calibrate.frames import KINDS, MIN_FRAMES, FrameSet, parse_set_name, sets_from_paths
from camhealth.calibrate.manifest import Manifest, read_manifest
from camhealth.calibrate.pipeline import ASSUMED, calibrate, resolve_sets
from camhealth.calibrate.result import CalibrationResult, FieldEstimate
from camhealth.calibrate.synthetic import Protocol, synthetic_sets

__all__ = [
    "ASSUMED", "KINDS", "MIN_FRAMES", "CalibrationResult", "FieldEstimate", "FrameSet", "Manifest", "Protocol",
    "calibrate", "parse_set_name", "read_manifest", "resolve_sets", "sets_from_paths", "synthetic_sets",
]
