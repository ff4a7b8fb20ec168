"""Photon transfer: the conversion gain K [DN/e⁻] from flat-field sets (EMVA 1288's photon-transfer method).

For a flat at mean level µ [DN] over the dark level µ_dark, photon shot noise (Poisson in the electrons,
thesis Sec. 3.2.2.1) adds K·(µ − µ_dark) to the dark variance (EMVA 1288 Release 4.0, Eq. 10–11):

    σ²_flat − σ²_dark = K · (µ − µ_dark)                                                          (1)

In camhealth's "digital gain" model (``conventions.md``) K = g·K0 with K0 = 255/FW: the full well maps to
255 DN at 0 dB. σ²_dark at each flat's exposure, temperature and gain comes from the dark fit
(:mod:`~camhealth.calibrate.dark_signal`), so the flats need no dark sets of their own. K0 is the weighted
least-squares slope of (1) through the origin over all flats, x = g·(µ − µ_dark), y = σ²_flat − σ²_dark;
the EMVA-style fit with a free intercept is kept as a check (its intercept should be ≈ 0).

Saturated flats (more than :data:`MAX_SATURATED_FRACTION` of the pixels at the highest code) are left out:
EMVA 1288 fits (1) below saturation only. The full well of camhealth's model is the charge at 255 DN:
FW = 255/K0 [e⁻] (EMVA's saturation capacity µ_e.sat at 0 dB).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

__all__ = ["MAX_SATURATED_FRACTION", "MIN_FLAT_LEVELS", "MIN_FLAT_SPAN", "FlatPoint", "PhotonTransferFit", "fit_photon_transfer"]

#: A flat with more than this fraction of its pixels at the highest code is saturated (left out of the fit).
MAX_SATURATED_FRACTION = 0.01
#: Unsaturated flat levels needed at least.
MIN_FLAT_LEVELS = 2
#: The brightest usable flat's signal must be at least this many times the darkest one's.
MIN_FLAT_SPAN = 2.0


@dataclass
class FlatPoint:
    """One flat set: mean [DN], temporal variance and 1σ uncertainties [DN²], dark level [DN], where it was
    taken (exposure [s], temperature [K], gain factor [–]) and the fraction of its pixels at the top code."""

    name: str
    exposure_s: float
    temperature_k: float
    gain_factor: float
    mean_dn: float
    mean_err_dn: float
    var_dn2: float
    var_err_dn2: float
    dark_mean_dn: float
    clipped_high: float
    gain_db: float = 0.0

    @property
    def saturated(self) -> bool:
        return self.clipped_high > MAX_SATURATED_FRACTION

    @property
    def signal_dn(self) -> float:
        """µ − µ_dark [DN]."""
        return self.mean_dn - self.dark_mean_dn


@dataclass
class PhotonTransferFit:
    """Result of :func:`fit_photon_transfer`.

    Attributes:
        k0, k0_err: conversion gain at 0 dB [DN/e⁻] and its 1σ uncertainty.
        chi2_dof: reduced χ² of the fit through the origin.
        free_slope, free_intercept: the EMVA-style fit y = K0·x + c (c ≈ 0 expected) [DN/e⁻, DN²].
        per_gain: gain [dB] → (K0 from that gain's flats alone, its 1σ) — a check of K ∝ g.
        used, excluded: flats fitted / left out, with the reason for each left out.
        x, y, y_err, residuals: the fitted points (x = g·(µ − µ_dark) [DN], y = σ²_flat − σ²_dark [DN²]) and the
            normalised residuals.
    """

    k0: float
    k0_err: float
    chi2_dof: float
    free_slope: float
    free_intercept: float
    per_gain: dict[float, tuple[float, float]]
    used: list[FlatPoint]
    excluded: list[tuple[FlatPoint, str]]
    x: np.ndarray = field(default_factory=lambda: np.zeros(0))
    y: np.ndarray = field(default_factory=lambda: np.zeros(0))
    y_err: np.ndarray = field(default_factory=lambda: np.zeros(0))
    residuals: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _slope_through_origin(x: np.ndarray, y: np.ndarray, e: np.ndarray) -> tuple[float, float, float]:
    w = 1.0 / e**2
    sxx = float((w * x * x).sum())
    k = float((w * x * y).sum()) / sxx
    err = math.sqrt(1.0 / sxx)
    dof = len(x) - 1
    chi2_dof = float((w * (y - k * x) ** 2).sum()) / dof if dof > 0 else float("nan")
    if dof > 0 and chi2_dof > 1.0:
        err *= math.sqrt(chi2_dof)
    return k, err, chi2_dof


def fit_photon_transfer(
    points: list[FlatPoint], dark_variance: Callable[[float, float, float], tuple[float, float]],
) -> PhotonTransferFit:
    """K0 from flats (module docstring). ``dark_variance(t [s], T [K], g [–]) -> (σ²_dark, 1σ) [DN²]``.

    Raises ``ValueError`` naming the flats when fewer than :data:`MIN_FLAT_LEVELS` unsaturated flats with a
    signal above the dark level remain, or their signals span less than :data:`MIN_FLAT_SPAN`×.
    """
    if not points:
        raise ValueError(
            f"no flat-field sets: at least {MIN_FLAT_LEVELS} are needed (uniform light at {MIN_FLAT_LEVELS}+ levels, "
            "e.g. 10 % … 70 % of saturation) to measure the conversion gain"
        )
    used, excluded = [], []
    for p in points:
        if p.saturated:
            excluded.append((p, f"saturated: {100 * p.clipped_high:.1f} % of pixels at the top code (limit {100 * MAX_SATURATED_FRACTION:g} %)"))
        elif not math.isfinite(p.var_dn2):
            excluded.append((p, f"clipped: {100 * p.clipped_high:.1f} % of pixels at the top code, nothing to fit"))
        elif not p.signal_dn > 0:
            excluded.append((p, f"no signal: mean {p.mean_dn:.3g} DN is not above the dark level {p.dark_mean_dn:.3g} DN"))
        else:
            used.append(p)
    if len(used) < MIN_FLAT_LEVELS:
        detail = "; ".join(f"{p.name}: {why}" for p, why in excluded) or "none left out"
        raise ValueError(
            f"{len(used)} usable flat set(s) of {len(points)}, at least {MIN_FLAT_LEVELS} are needed below saturation "
            f"(left out: {detail}); record flats at lower light or exposure so that < {100 * MAX_SATURATED_FRACTION:g} % "
            "of the pixels are at the top code"
        )
    signals = np.array([p.signal_dn for p in used])
    if signals.max() < MIN_FLAT_SPAN * signals.min():
        raise ValueError(
            f"the usable flats' signals span only {signals.max() / signals.min():.2f}× ({signals.min():.3g} … "
            f"{signals.max():.3g} DN over the dark level); they must span at least {MIN_FLAT_SPAN:g}× (e.g. flats "
            "from 10 % to 70 % of saturation)"
        )
    x, y, e = [], [], []
    for p in used:
        dv, dv_err = dark_variance(p.exposure_s, p.temperature_k, p.gain_factor)
        x.append(p.gain_factor * p.signal_dn)
        y.append(p.var_dn2 - dv)
        # the mean's uncertainty moves x: propagate it with the expected slope K = var/µ
        k_guess = (p.var_dn2 - dv) / max(p.signal_dn, 1e-12)
        e.append(math.sqrt(p.var_err_dn2**2 + dv_err**2 + (k_guess * p.mean_err_dn) ** 2) if math.isfinite(p.var_err_dn2) else abs(p.var_dn2) * 1e-2)
    xa, ya, ea = np.array(x), np.array(y), np.maximum(np.array(e), 1e-12)
    k0, k0_err, chi2_dof = _slope_through_origin(xa, ya, ea)
    if not k0 > 0:
        raise ValueError(
            f"the flats' variance does not rise with their level (slope {k0:.3g} DN/e⁻): are they really lit, and is the "
            "light constant during each set?"
        )
    if len(xa) >= 2:
        w = 1.0 / ea
        (slope, icpt), *_ = np.linalg.lstsq(np.stack([xa, np.ones_like(xa)], 1) * w[:, None], ya * w, rcond=None)
    else:
        slope, icpt = k0, 0.0
    per_gain: dict[float, tuple[float, float]] = {}
    for gdb in sorted({p.gain_db for p in used}):
        sel = np.array([p.gain_db == gdb for p in used])
        kg, kg_err, _ = _slope_through_origin(xa[sel], ya[sel], ea[sel])
        per_gain[float(gdb)] = (kg, kg_err)
    return PhotonTransferFit(
        k0=k0, k0_err=k0_err, chi2_dof=chi2_dof, free_slope=float(slope), free_intercept=float(icpt),
        per_gain=per_gain, used=used, excluded=excluded, x=xa, y=ya, y_err=ea, residuals=(ya - k0 * xa) / ea,
    )
