"""Real-time camera monitor (issue 7): ``python -m camhealth.monitor SOURCE`` and :class:`Monitor`.

- :mod:`~camhealth.monitor.api` — :class:`Monitor` (``process(frame) -> FrameReport``, one JSON line per
  frame): patch-wise MTF (H/V) and noise sources (PN, DCSN, RN, ξ, total) with the temporal median
  aggregation of thesis Eq. 5.4, the ξ alarm (Eq. 4.3) and the IOPC policy's exposure/gain advice
  (Eq. 4.5–4.8); :func:`load_metadata`, :func:`load_policy`.
- :mod:`~camhealth.monitor.tiling` — patch grids, cheap patch statistics, informative-patch selection with
  reasons, static-region reuse by frame differencing, coarse-lattice-then-refine.
- :mod:`~camhealth.monitor.overlay` — heat maps and overlay PNGs.
- :mod:`~camhealth.monitor.sources` — images, folders of frames, videos, the embedded street clip.
- :mod:`~camhealth.monitor.recording` — ROS 1/ROS 2/MCAP recordings with the camera state of their topics.
- :mod:`~camhealth.monitor.defect_map` — a camera's known defective pixels (calibration's hot-pixel map).
- :mod:`~camhealth.monitor.diagnostics` — one ``diagnostic_msgs/DiagnosticArray`` per frame (``.mcap``/``.bag``).

See ``docs/monitor.md``; the benchmark is ``python -m camhealth.bench monitor``.
"""

from camhealth.monitor.api import (
    NOISE_FIELDS,
    FrameReport,
    Monitor,
    TaskReport,
    as_frame,
    load_metadata,
    load_policy,
    xi_alarm,
    beyond_range_alarm,
    banding_text,
    defects_text,
    new_defect_ppm,
    DEFECT_ALARM_PPM,
    mtf_under_banding,
    MTF_BANDING_LIMIT_DN,
)
from camhealth.monitor.tiling import STATUS_NAMES, PatchGrid, SelectionConfig

__all__ = [
    "Monitor",
    "FrameReport",
    "TaskReport",
    "NOISE_FIELDS",
    "STATUS_NAMES",
    "PatchGrid",
    "SelectionConfig",
    "as_frame",
    "load_metadata",
    "load_policy",
    "xi_alarm",
    "beyond_range_alarm",
    "banding_text",
    "defects_text",
    "new_defect_ppm",
    "DEFECT_ALARM_PPM",
    "mtf_under_banding",
    "MTF_BANDING_LIMIT_DN",
]
