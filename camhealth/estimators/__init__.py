"""Classical (non-learned) estimators: noise levels, standard MTF measurements and aggregation.

They are the baselines the thesis compares its learned estimators with (chapters 5 and 6), batched and
vectorised, returning the same quantities as the labels of the data pipeline: σ in DN (float) for
noise, and MTF at the 8 normalised frequencies H/V as (B, 16) for blur.

- :mod:`~camhealth.estimators.pca_noise` — PCA of the patch covariance (Chen, Zhu & Heng 2015).
- :mod:`~camhealth.estimators.block_filter_noise` — "B+F": homogeneous 8×16 blocks and adaptive Gaussian
  filtering (Shin et al. 2005).
- :mod:`~camhealth.estimators.wavelet_noise` — wavelet MAD (Donoho & Johnstone), scikit-image's
  ``estimate_sigma``.
- :mod:`~camhealth.estimators.aggregation` — temporal/spatial median aggregation with spread (Eq. 5.4–5.5).
- :mod:`~camhealth.estimators.blur_under_noise` — defocus pre-filter b₂ and division by MTF(b₂) (Sec. 5.5).
- :mod:`~camhealth.estimators.slanted_edge` — ISO 12233 slanted-edge MTF.
- :mod:`~camhealth.estimators.siemens_star` — ISO 15775 Siemens-star MTF (CTF, Gaussian fit, Eq. 3.25).
- :mod:`~camhealth.estimators.charts` — the synthetic slanted-edge and Siemens-star charts.

See ``docs/estimators_classical.md`` for accuracy and speed.
"""

from camhealth.estimators.aggregation import WINDOW_SIZES, Aggregate, spatial_median, temporal_median, uncertainty_by_window
from camhealth.estimators.block_filter_noise import block_filter_noise_sigma
from camhealth.estimators.blur_under_noise import (
    EPSILON,
    PREFILTER_DIAMETER_PX,
    BlurUnderNoiseResult,
    divide_out_prefilter,
    estimate_blur_under_noise,
    prefilter,
    prefilter_mtf,
)
from camhealth.estimators.charts import siemens_star_chart, siemens_star_geometry, slanted_edge_chart, slanted_edge_rois
from camhealth.estimators.pca_noise import pca_noise_sigma
from camhealth.estimators.siemens_star import SiemensStarResult, mtf_from_ctf, siemens_star_ctf, siemens_star_mtf
from camhealth.estimators.slanted_edge import SlantedEdgeResult, slanted_edge_mtf, slanted_edge_mtf_hv
from camhealth.estimators.wavelet_noise import wavelet_noise_sigma

#: The classical noise-level estimators by name: images B×1×H×W in [0, 1] → σ̂ (B,) in DN.
NOISE_ESTIMATORS = {
    "pca": pca_noise_sigma,
    "bf": block_filter_noise_sigma,
    "wavelet": wavelet_noise_sigma,
}

__all__ = [
    "NOISE_ESTIMATORS",
    "pca_noise_sigma",
    "block_filter_noise_sigma",
    "wavelet_noise_sigma",
    "WINDOW_SIZES",
    "Aggregate",
    "temporal_median",
    "spatial_median",
    "uncertainty_by_window",
    "PREFILTER_DIAMETER_PX",
    "EPSILON",
    "BlurUnderNoiseResult",
    "prefilter",
    "prefilter_mtf",
    "divide_out_prefilter",
    "estimate_blur_under_noise",
    "SlantedEdgeResult",
    "slanted_edge_mtf",
    "slanted_edge_mtf_hv",
    "SiemensStarResult",
    "siemens_star_ctf",
    "siemens_star_mtf",
    "mtf_from_ctf",
    "slanted_edge_chart",
    "slanted_edge_rois",
    "siemens_star_chart",
    "siemens_star_geometry",
]
