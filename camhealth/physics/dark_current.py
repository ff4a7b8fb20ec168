"""Dark current and dark-current shot noise (thesis Eq. 3.14–3.15, Konnik & Welsh 2014).

Mean dark current per pixel (Janesick's empirical law with Varshni's silicon band gap):

    DC(T) = 2.55e15 · d_p²[cm²] · D_FM[nA/cm²] · T^1.5 · exp(−E_g(T) / (2kT))     [e⁻/s/px]
    E_g(T) = 1.1557 − 7.021e-4 · T² / (T + 1108)                                   [eV]

with T in kelvin and k = 8.617343e-5 eV/K. The dark signal is S = DC · t_exp [e⁻]; dark-current shot
noise (DCSN) is Poisson(S) − S (signal independent, γ = 0) with σ_DCSN = √S [e⁻], converted to DN by the
gain: σ[DN] = σ[e⁻] · g · 255 / FW. The mean dark signal itself is taken as removed by dark-frame
calibration (offset 0 DN), so DCSN is zero-mean.
"""

from __future__ import annotations

import torch

from camhealth.physics.metadata import BOLTZMANN_EV_PER_K, CameraMetadata

__all__ = [
    "band_gap_ev",
    "dark_current_e_per_s",
    "dark_signal_e",
    "dark_current_shot_sigma_e",
    "dark_current_shot_sigma_dn",
]

#: Prefactor of the dark-current law [e⁻/s/cm²/(nA/cm²)/K^1.5] (conventions.md).
DARK_CURRENT_PREFACTOR = 2.55e15
#: Varshni parameters of silicon: E_g0 [eV], α [eV/K], β [K].
SILICON_EG0_EV, SILICON_ALPHA_EV_PER_K, SILICON_BETA_K = 1.1557, 7.021e-4, 1108.0


def band_gap_ev(temperature_k: torch.Tensor) -> torch.Tensor:
    """Silicon band gap E_g(T) [eV] at temperature T [K] (Varshni)."""
    t = torch.as_tensor(temperature_k)
    return SILICON_EG0_EV - SILICON_ALPHA_EV_PER_K * t * t / (t + SILICON_BETA_K)


def dark_current_e_per_s(meta: CameraMetadata) -> torch.Tensor:
    """Mean dark current DC [e⁻/s/px] of every sample, shape (B,). Computed in float64."""
    t = meta.temperature_k.double()
    pixel_area_cm2 = (meta.pixel_size_um.double() * 1e-4) ** 2
    return (
        DARK_CURRENT_PREFACTOR
        * pixel_area_cm2
        * meta.dark_fom_na_per_cm2.double()
        * t.pow(1.5)
        * torch.exp(-band_gap_ev(t) / (2.0 * BOLTZMANN_EV_PER_K * t))
    ).to(meta.dtype)


def dark_signal_e(meta: CameraMetadata) -> torch.Tensor:
    """Mean dark signal S = DC · t_exp [e⁻/px], shape (B,)."""
    return dark_current_e_per_s(meta) * meta.exposure_s


def dark_current_shot_sigma_e(meta: CameraMetadata) -> torch.Tensor:
    """σ_DCSN = √S [rms e⁻], shape (B,) (Eq. 3.15)."""
    return dark_signal_e(meta).sqrt()


def dark_current_shot_sigma_dn(meta: CameraMetadata) -> torch.Tensor:
    """σ_DCSN in DN after gain (before clipping), shape (B,)."""
    return dark_current_shot_sigma_e(meta) * meta.dn_per_electron
