"""Photon transfer: the conversion gain K [DN/e⁻] from flat-field sets (EMVA 1288's photon-transfer method).

For a flat at mean level µ [DN] over the dark level µ_dark, photon shot noise (Poisson in the electrons,
thesis Sec. 3.2.2.1) adds K·(µ − µ_dark) to the dark variance (EMVA 1288 Release 4.0, Eq. 10–11):

    σ²_flat − σ²_dark = K · (µ − µ_dark)                                                          (1)

In camhealth's "digital gain" model (``conventions.md``) K = g·K0 with K0 = 255/FW: the full well maps to
255 DN at 0 dB. σ²_dark at each flat's exposure, temperature and gain comes from the dark fit
(:mod:`~camhealth.calibrate.dark_signal`), so the flats need no dark sets of their own. K0 is the weighted
least-squares slope of (1) through the origin over all flats, x = g·(µ − µ_dark), y = σ²_flat − σ²_dark;
the EMVA-style fit with a free intercept is kept as a check (its intercept should be ≈ 0).

EMVA 1288 fits (1) below saturation only. Left out, each with its reason:

* saturated flats (more than :data:`MAX_SATURATED_FRACTION` of the values at the highest code — 255 DN or the
  level they pile up at, :func:`~camhealth.calibrate.statistics.top_clip_level`);
* partly clipped flats (method ``"censored"``: more than
  :data:`~camhealth.calibrate.statistics.CENSORED_ABOVE` of the values at the lowest or highest code): their
  censored fit pools the pixels, so the PRNU would enter their σ²;
* quantisation-limited flats (temporal noise below about half a code step);
* at each gain, the flats at and beyond the maximum of the variance when a brighter flat's variance lies
  significantly below it (EMVA 1288's saturation point: the variance falls as the pixels clip).

The per-gain K0 must agree (K = g·K0): gains whose K0 differ by more than :data:`MAX_GAIN_K0_SIGMAS` σ are refused
(a wrong gain_db). The full well of camhealth's model is the charge at 255 DN: FW = 255/K0 [e⁻] (EMVA's
saturation capacity µ_e.sat at 0 dB).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from camhealth.calibrate.statistics import CENSORED_ABOVE

__all__ = [
    "MAX_SATURATED_FRACTION", "MIN_FLAT_LEVELS", "MIN_FLAT_SPAN", "MAX_GAIN_K0_SIGMAS", "MAX_CHI2_DOF", "SATURATION_FALL_SIGMAS",
    "FlatPoint", "PhotonTransferFit", "fit_photon_transfer",
]

#: A flat with more than this fraction of its pixels at the highest code is saturated (left out of the fit).
MAX_SATURATED_FRACTION = 0.01
#: K0 of two gains further apart than this many σ contradict K = g·K0: refused.
MAX_GAIN_K0_SIGMAS = 5.0
#: A reduced χ² of the fit above this is reported as a poor fit (a warning of the pipeline).
MAX_CHI2_DOF = 5.0
#: A brighter flat's variance this many σ below the maximum marks the maximum as the saturation point.
SATURATION_FALL_SIGMAS = 3.0
#: Unsaturated flat levels needed at least.
MIN_FLAT_LEVELS = 2
#: The brightest usable flat's signal must be at least this many times the darkest one's.
MIN_FLAT_SPAN = 2.0


@dataclass
class FlatPoint:
    """One flat set: mean [DN], temporal variance and 1σ uncertainties [DN²], dark level [DN], where it was
    taken (exposure [s], temperature [K], gain factor [–]), the fraction of its values at the top code (and at
    0 DN), its noise estimator (:mod:`~camhealth.calibrate.statistics`) and whether it is quantisation-limited."""

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
    clipped_low: float = 0.0
    method: str = "temporal"
    quantisation_limited: bool = False

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
    signal above the dark level remain, or their signals span less than :data:`MIN_FLAT_SPAN`×; and naming the
    gains and their K0 when two gains' K0 differ by more than :data:`MAX_GAIN_K0_SIGMAS` σ.
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
        elif p.method == "censored":
            excluded.append((p, f"partly clipped: {100 * p.clipped_low:.2g} % of its values at 0 DN and {100 * p.clipped_high:.2g} % "
                                f"at the top code (more than {100 * CENSORED_ABOVE:g} %); the censored fit pools the pixels, so the "
                                "PRNU would enter its temporal variance"))
        elif p.quantisation_limited:
            excluded.append((p, "quantisation-limited: its temporal noise is below about half a code step, where the "
                                "quantisation correction does not hold; record it at a higher gain or bit depth"))
        elif not p.signal_dn > 0:
            excluded.append((p, f"no signal: mean {p.mean_dn:.3g} DN is not above the dark level {p.dark_mean_dn:.3g} DN"))
        else:
            used.append(p)
    for gdb in sorted({p.gain_db for p in used}):  # EMVA 1288: saturation at the variance's maximum
        same = sorted((p for p in used if p.gain_db == gdb), key=lambda p: p.signal_dn)
        i_max = max(range(len(same)), key=lambda i: same[i].var_dn2)
        top = same[i_max]
        fall = [q for q in same[i_max + 1:]
                if top.var_dn2 - q.var_dn2 > SATURATION_FALL_SIGMAS * math.hypot(top.var_err_dn2, q.var_err_dn2)]
        if fall:
            for p in same[i_max:]:
                used.remove(p)
                excluded.append((p, f"at or beyond the maximum of the variance at {gdb:g} dB ({top.var_dn2:.4g} DN² at "
                                    f"{top.mean_dn:.4g} DN; {fall[0].name} lies {top.var_dn2 - fall[0].var_dn2:.3g} DN² below it): "
                                    "saturation (EMVA 1288)"))
    if len(used) < MIN_FLAT_LEVELS:
        detail = "; ".join(f"{p.name}: {why}" for p, why in excluded) or "none left out"
        raise ValueError(
            f"{len(used)} usable flat set(s) of {len(points)}, at least {MIN_FLAT_LEVELS} are needed below saturation "
            f"(left out: {detail}); record flats at lower light or exposure so that at most {100 * CENSORED_ABOVE:g} % "
            "of their values are at the top code"
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
    pulls = [(abs(a[0] - b[0]) / math.hypot(a[1], b[1]), ga, gb) for ga, a in per_gain.items() for gb, b in per_gain.items()
             if ga < gb and math.hypot(a[1], b[1]) > 0]
    if pulls and max(pulls)[0] > MAX_GAIN_K0_SIGMAS:
        pull, ga, gb = max(pulls)
        values = ", ".join(f"{g:g} dB: {k:.4g} ± {e:.2g}" for g, (k, e) in per_gain.items())
        raise ValueError(
            f"the flats at {ga:g} dB and {gb:g} dB give K0 {per_gain[ga][0]:.4g} and {per_gain[gb][0]:.4g} DN/e⁻, {pull:.1f}σ apart "
            f"(at most {MAX_GAIN_K0_SIGMAS:g}σ; K0 per gain: {values}): they contradict K = g·K0; check the flats' gain_db"
        )
    return PhotonTransferFit(
        k0=k0, k0_err=k0_err, chi2_dof=chi2_dof, free_slope=float(slope), free_intercept=float(icpt),
        per_gain=per_gain, used=used, excluded=excluded, x=xa, y=ya, y_err=ea, residuals=(ya - k0 * xa) / ea,
    )
