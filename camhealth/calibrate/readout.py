"""Source-follower noise σ_SF [e⁻] → thermal white noise W [V/√Hz]: the inversion of thesis Eq. 3.17–3.19.

Eq. 3.17 integrates S_SF(f)·H_CDS(f) up to the pixel clock; S_SF = W²·(1 + f_c/f) + [CMOS]·S_RTN(f) is
linear in W², so

    σ_SF² · D² = W² · I_w(f_clock) + [CMOS] · I_rtn(f_clock),   D = A_SN · A_SF · (1 − exp(−t_s/τ_D))

and W = √((σ_SF²·D² − [CMOS]·I_rtn) / I_w). The two integrals are read off
:func:`camhealth.physics.readout_noise.source_follower_sigma_e` at two values of W (exact: the model is
linear in W²), so the inversion uses the same integral as the forward model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from camhealth.physics.metadata import METADATA_RANGES, PRESETS, CameraMetadata
from camhealth.physics.readout_noise import source_follower_sigma_e

__all__ = ["WhiteNoiseInversion", "white_noise_from_sigma"]


@dataclass
class WhiteNoiseInversion:
    """W [V/√Hz] and its 1σ uncertainty for a σ_SF [e⁻]; ``sigma_min_e``/``sigma_max_e`` is the σ_SF that
    W's allowed range (1e-9 … 60e-9 V/√Hz) gives at this pixel clock, sense-node gain and sensor type."""

    white_noise_v_per_rthz: float
    white_noise_err: float
    sigma_min_e: float
    sigma_max_e: float


def _sf_variance_parts(pixel_clock_hz: float, sense_node_gain_v_per_e: float, is_cmos: bool) -> tuple[float, float]:
    """(A, B) with σ_SF² = W²·A + B [e⁻²]."""
    w1, w2 = 10e-9, 50e-9
    base = dict(PRESETS["ICX285"], pixel_clock_hz=pixel_clock_hz, sense_node_gain_v_per_e=sense_node_gain_v_per_e,
                is_cmos=float(is_cmos))
    meta = CameraMetadata(gain_db=0.0, exposure_s=0.01, temperature_c=25.0, **{**base, "white_noise_v_per_rthz": torch.tensor([w1, w2], dtype=torch.float64)})
    s = source_follower_sigma_e(meta).double()
    v1, v2 = float(s[0]) ** 2, float(s[1]) ** 2
    a = (v2 - v1) / (w2**2 - w1**2)
    return a, v1 - a * w1**2


def white_noise_from_sigma(
    sigma_sf_e: float, sigma_sf_err_e: float, pixel_clock_hz: float, sense_node_gain_v_per_e: float, is_cmos: bool,
) -> WhiteNoiseInversion:
    """W [V/√Hz] that gives the source-follower noise ``sigma_sf_e`` [e⁻] (module docstring), with its 1σ
    uncertainty from ``sigma_sf_err_e``. The result may lie outside W's allowed range; the caller decides."""
    a, b = _sf_variance_parts(pixel_clock_hz, sense_node_gain_v_per_e, is_cmos)
    lo, hi = METADATA_RANGES["white_noise_v_per_rthz"]
    smin, smax = math.sqrt(lo**2 * a + b), math.sqrt(hi**2 * a + b)
    w2 = (sigma_sf_e**2 - b) / a
    w = math.sqrt(max(w2, 0.0))
    err = sigma_sf_e * sigma_sf_err_e / (a * max(w, 1e-15))
    return WhiteNoiseInversion(w, err, smin, smax)
