"""Input–output performance curves (IOPCs): how a frozen detector's AP depends on blur and noise.

Thesis Sec. 4.4.1 and Ch. 7.1.

- :mod:`~camhealth.iopc.curves` — :class:`IOPC`: σ̃/MTF̃ bins, 1-D and 2-D curves, counts, marked
  cells, the MTF → motion-length relation, provenance; JSON/NPZ round trip; heat-map figure.
- :mod:`~camhealth.iopc.estimation` — tiles overlapping objects, patch-wise σ̂/MTF̂ with injected
  estimators (inference contract), the Eq. 4.4 median; ``"physics"`` labels and Immerkær's classical
  noise estimator as documented stand-ins.
- :mod:`~camhealth.iopc.sweep` — the grid (motion length × direction × sensor noise), one cell per
  ``predict_step`` of :class:`IOPCSweepModule` (Lightning predict loop), cached and resumable.
- ``python -m camhealth.iopc --config configs/iopc.yaml`` — the standalone sweep (:mod:`camhealth.iopc.cli`).
"""

from camhealth.iopc.curves import (
    FORMAT_VERSION,
    IOPC,
    MTF_BINS,
    SIGMA_BINS_DN,
    bin_index,
    blur_relation,
    blur_relation_noise_level,
)
from camhealth.iopc.estimation import (
    PHYSICS,
    ImmerkaerNoiseEstimator,
    RegionEstimates,
    estimate_regions,
    estimator_name,
    extract_tiles,
    median_estimates,
    overlap_mask,
    resolve_estimator,
    tile_grid,
)
#: Names of :mod:`camhealth.iopc.sweep`, imported on first use: the sweep runs in Lightning's predict loop, and the
#: curves and the estimation are also read where Lightning is not wanted (the monitor's exposure/gain advice).
_SWEEP_NAMES = ("CellDataset", "IOPCSweep", "IOPCSweepModule", "SensorSetting", "SweepConfig", "SweepGrid", "log_iopc",
                "make_cells", "noise_gain_db")


def __getattr__(name: str):
    if name in _SWEEP_NAMES:
        from camhealth.iopc import sweep

        return getattr(sweep, name)
    raise AttributeError(f"module 'camhealth.iopc' has no attribute {name!r}")


__all__ = [
    "IOPC", "SIGMA_BINS_DN", "MTF_BINS", "FORMAT_VERSION", "bin_index", "blur_relation", "blur_relation_noise_level",
    "PHYSICS", "ImmerkaerNoiseEstimator", "RegionEstimates", "estimate_regions", "estimator_name", "extract_tiles",
    "median_estimates", "overlap_mask", "resolve_estimator", "tile_grid",
    "IOPCSweep", "IOPCSweepModule", "CellDataset", "SweepConfig", "SweepGrid", "SensorSetting", "log_iopc",
    "make_cells", "noise_gain_db",
]
