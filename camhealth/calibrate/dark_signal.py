"""Dark signal: read noise per temperature and the dark current's Arrhenius law from bias and dark sets.

In camhealth's sensor model (thesis Sec. 3.2.2, ``conventions.md``) a dark frame at exposure t, temperature
T and gain factor g carries zero-mean readout noise and dark-current shot noise; its temporal variance in
DN² is

    σ²_dark(t, T, g) = g² · K0² · (σ_RN²(T) + DC(T) · t)                                           (1)

with K0 = 255/FW [DN/e⁻] the conversion gain at 0 dB, σ_RN [e⁻] the readout noise (Eq. 3.16–3.19) and
DC(T) [e⁻/s] the dark current of Eq. 3.14,

    DC(T) = 2.55e15 · d_p² · D_FM · T^1.5 · exp(−E_g(T) / (2kT)) = C · f(T).                        (2)

This is EMVA 1288's "dark current from the variance of the dark signal" (Release 4.0, Eq. 21 with the
dark-current compensation that camhealth's model has: the mean dark signal is removed, its shot noise
stays). Divided by g², (1) is linear in the unknowns once K0 is known; K0 comes from the flats
(:mod:`~camhealth.calibrate.photon_transfer`), so the dark fit is done in DN² at unit gain:

* **free fit** (per temperature T_j: an intercept a_j = K0²·σ_RN²(T_j) and a slope s_j = K0²·DC(T_j)) —
  the thesis's "read noise and dark current per temperature" (Eq. 3.27–3.28: σ_DCSN² = σ_Dark² − σ_RN²),
  and EMVA 1288's dark current per temperature with its doubling temperature T_d (DC ∝ 2^(T/T_d));
* **law fit** (the intercepts a_j as before, one C for every temperature through (2)) — the dark-current
  figure of merit D_FM written to the metadata.

Readout noise vs temperature (CMOS kTC residue, Eq. 3.16): σ_RN²(T) = σ_SF² + r²·kT/(q·A_SN), linear in T;
with ≥ 2 temperatures of a CMOS sensor and no reset factor given, (σ_SF², r²) are fitted to the intercepts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from camhealth.physics.dark_current import DARK_CURRENT_PREFACTOR, band_gap_ev
from camhealth.physics.metadata import BOLTZMANN_EV_PER_K, BOLTZMANN_J_PER_K, ELEMENTARY_CHARGE_C

__all__ = [
    "MIN_EXPOSURE_SPAN", "DarkPoint", "DarkFit", "ReadNoiseLaw", "arrhenius_factor", "fit_dark", "fit_read_noise_law",
    "doubling_temperature", "model_doubling_temperature", "dfm_from_c",
]

#: The longest dark exposure must be at least this many times the shortest.
MIN_EXPOSURE_SPAN = 4.0


def arrhenius_factor(temperature_k: np.ndarray | float) -> np.ndarray:
    """f(T) = T^1.5 · exp(−E_g(T)/(2kT)) [K^1.5] of Eq. 3.14, so that DC = 2.55e15·d_p²·D_FM·f(T)."""
    t = np.asarray(temperature_k, dtype=np.float64)
    eg = band_gap_ev(torch.as_tensor(t, dtype=torch.float64)).numpy()
    return t**1.5 * np.exp(-eg / (2.0 * BOLTZMANN_EV_PER_K * t))


@dataclass
class DarkPoint:
    """One dark (or bias) set's measurement: exposure [s], temperature [K], gain factor [–], variance and its
    1σ uncertainty [DN²], name."""

    exposure_s: float
    temperature_k: float
    gain_factor: float
    var_dn2: float
    var_err_dn2: float
    name: str = ""

    @property
    def y(self) -> float:
        """Variance at unit gain [DN²]."""
        return self.var_dn2 / self.gain_factor**2

    @property
    def y_err(self) -> float:
        return self.var_err_dn2 / self.gain_factor**2


@dataclass
class DarkFit:
    """Result of :func:`fit_dark` (all in DN² at unit gain unless said otherwise).

    Attributes:
        temperatures_k: the distinct temperatures T_j [K].
        intercept_dn2, intercept_err_dn2: a_j = K0²·σ_RN²(T_j) of the law fit and its 1σ uncertainty.
        c_dn2, c_err_dn2: C' = K0²·C with DC(T) = C·f(T) [DN²/s/K^1.5].
        free_slope_dn2_per_s, free_slope_err: s_j = K0²·DC(T_j) of the free fit (NaN with < 2 exposures at T_j).
        free_intercept_dn2: a_j of the free fit.
        chi2_dof: reduced χ² of the law fit (1 when the uncertainties are right).
        residuals: (point, normalised residual of the law fit) for the report.
        points: the measurements.
    """

    temperatures_k: np.ndarray
    intercept_dn2: np.ndarray
    intercept_err_dn2: np.ndarray
    c_dn2: float
    c_err_dn2: float
    free_slope_dn2_per_s: np.ndarray
    free_slope_err: np.ndarray
    free_intercept_dn2: np.ndarray
    chi2_dof: float
    points: list[DarkPoint] = field(default_factory=list)
    residuals: np.ndarray = field(default_factory=lambda: np.zeros(0))
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    def index_of(self, temperature_k: float) -> int | None:
        hits = np.nonzero(np.isclose(self.temperatures_k, temperature_k, atol=1e-6))[0]
        return int(hits[0]) if hits.size else None

    def predict_dn2(self, exposure_s: float, temperature_k: float, gain_factor: float,
                    intercept_at: "callable | None" = None) -> tuple[float, float]:
        """Predicted dark variance [DN²] and its 1σ uncertainty at (t, T, g) from the law fit. At a temperature
        without dark sets the intercept comes from ``intercept_at(T) -> (a, err)`` (the read-noise law) or the
        nearest measured temperature."""
        j = self.index_of(temperature_k)
        if j is not None:
            a, a_err = float(self.intercept_dn2[j]), float(self.intercept_err_dn2[j])
        elif intercept_at is not None:
            a, a_err = intercept_at(temperature_k)
        else:
            j = int(np.argmin(np.abs(self.temperatures_k - temperature_k)))
            a, a_err = float(self.intercept_dn2[j]), float(self.intercept_err_dn2[j])
        f = float(arrhenius_factor(temperature_k)) * exposure_s
        v = a + self.c_dn2 * f
        err = math.hypot(a_err, self.c_err_dn2 * f)  # (no overflow of the squares at a huge exposure)
        return gain_factor**2 * v, gain_factor**2 * err


def _wls(design: np.ndarray, y: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Weighted least squares: parameters, covariance (scaled by χ²/dof when that exceeds 1), χ²/dof."""
    w = 1.0 / np.maximum(sigma, 1e-300)
    a = design * w[:, None]
    b = y * w
    params, *_ = np.linalg.lstsq(a, b, rcond=None)
    cov = np.linalg.pinv(a.T @ a)
    dof = max(len(y) - design.shape[1], 0)
    chi2 = float(((a @ params - b) ** 2).sum())
    chi2_dof = chi2 / dof if dof > 0 else float("nan")
    if dof > 0 and chi2_dof > 1.0:
        cov = cov * chi2_dof
    return params, cov, chi2_dof


def fit_dark(points: list[DarkPoint]) -> DarkFit:
    """Fit the dark model (module docstring) to bias and dark sets.

    Raises ``ValueError`` when the sets cannot separate read noise from dark current: fewer than 2 distinct
    exposure times at any one temperature, or exposures spanning less than :data:`MIN_EXPOSURE_SPAN`×.
    """
    if not points:
        raise ValueError("no bias or dark sets: at least 2 are needed (a bias set and a dark set at a longer exposure)")
    temps = np.array(sorted({round(p.temperature_k, 6) for p in points}))
    exposures = sorted({p.exposure_s for p in points})
    per_t = {t: sorted({p.exposure_s for p in points if abs(p.temperature_k - t) < 1e-6}) for t in temps}
    best = max(per_t.values(), key=len)
    if len(best) < 2:
        raise ValueError(
            f"the bias/dark sets have {len(exposures)} distinct exposure time(s) "
            f"({', '.join(f'{e:g} s' for e in exposures)}) but none of their {len(temps)} temperature(s) has 2: "
            "at least 2 exposures at one temperature are needed (a bias set at the shortest exposure and dark sets "
            "at longer ones)"
        )
    span = max(v[-1] / v[0] for v in per_t.values() if len(v) >= 2)
    if span < MIN_EXPOSURE_SPAN:
        raise ValueError(
            f"the dark exposures span only {span:.2f}× (longest/shortest at one temperature); they must span at "
            f"least {MIN_EXPOSURE_SPAN:g}× to separate read noise from dark current (e.g. 1 ms bias and ≥ 4 ms darks; "
            "longer darks measure the dark current better)"
        )
    y = np.array([p.y for p in points])
    ey = np.array([p.y_err for p in points])
    if not np.all(np.isfinite(ey)) or np.any(ey <= 0):
        ey = np.where(np.isfinite(ey) & (ey > 0), ey, np.nanmax(np.abs(y)) * 1e-2 + 1e-12)
    t_idx = np.array([int(np.argmin(np.abs(temps - p.temperature_k))) for p in points])
    nt = len(temps)
    fx = np.array([float(arrhenius_factor(p.temperature_k)) * p.exposure_s for p in points])

    # law fit: one intercept per temperature, one C for all
    design = np.zeros((len(points), nt + 1))
    design[np.arange(len(points)), t_idx] = 1.0
    design[:, nt] = fx
    params, cov, chi2_dof = _wls(design, y, ey)
    resid = (y - design @ params) / ey

    # free fit: intercept and slope per temperature (where it has ≥ 2 exposures)
    free_a = np.full(nt, np.nan)
    free_s = np.full(nt, np.nan)
    free_se = np.full(nt, np.nan)
    for j, t in enumerate(temps):
        sel = t_idx == j
        ts = np.array([p.exposure_s for p, s in zip(points, sel) if s])
        if len(set(ts.tolist())) >= 2:
            d = np.stack([np.ones(sel.sum()), ts], 1)
            pj, cj, _ = _wls(d, y[sel], ey[sel])
            free_a[j], free_s[j], free_se[j] = pj[0], pj[1], math.sqrt(max(cj[1, 1], 0.0))
        else:
            free_a[j] = float(np.average(y[sel], weights=1 / ey[sel] ** 2))
    return DarkFit(
        temperatures_k=temps,
        intercept_dn2=params[:nt],
        intercept_err_dn2=np.sqrt(np.maximum(np.diag(cov)[:nt], 0.0)),
        c_dn2=float(params[nt]),
        c_err_dn2=float(math.sqrt(max(cov[nt, nt], 0.0))),
        free_slope_dn2_per_s=free_s,
        free_slope_err=free_se,
        free_intercept_dn2=free_a,
        chi2_dof=chi2_dof,
        points=list(points),
        residuals=resid,
        covariance=cov,
    )


@dataclass
class ReadNoiseLaw:
    """σ_RN²(T) = σ_SF² + r²·kT/(q·A_SN) [e⁻²] fitted to (or assumed for) the per-temperature intercepts."""

    sf_var_e2: float
    sf_var_err_e2: float
    reset_factor: float
    reset_factor_err: float
    reset_fitted: bool
    sense_node_gain_v_per_e: float
    is_cmos: bool

    def ktc_var_e2(self, temperature_k: float) -> float:
        """(r·σ_SN)² [e⁻²] at T (0 for a CCD)."""
        if not self.is_cmos:
            return 0.0
        return self.reset_factor**2 * BOLTZMANN_J_PER_K * temperature_k / (ELEMENTARY_CHARGE_C * self.sense_node_gain_v_per_e)

    def var_e2(self, temperature_k: float) -> float:
        return self.sf_var_e2 + self.ktc_var_e2(temperature_k)


def fit_read_noise_law(
    fit: DarkFit, k0: float, k0_err: float, is_cmos: bool, sense_node_gain_v_per_e: float,
    reset_factor: float | None,
) -> ReadNoiseLaw:
    """σ_SF² and (CMOS, ≥ 2 temperatures, no ``reset_factor`` given) the reset factor r from the intercepts
    a_j = K0²·σ_RN²(T_j) [DN²] (module docstring). A fitted r² < 0 (no rise with temperature) gives r = 0."""
    t = fit.temperatures_k
    var_e = fit.intercept_dn2 / k0**2
    # relative uncertainty of K0² enters every intercept alike
    err_e = np.sqrt((fit.intercept_err_dn2 / k0**2) ** 2 + (var_e * 2 * k0_err / k0) ** 2)
    ktc_per_k = BOLTZMANN_J_PER_K / (ELEMENTARY_CHARGE_C * sense_node_gain_v_per_e)  # e⁻²/K at r = 1
    if is_cmos and reset_factor is None and len(t) >= 2:
        d = np.stack([np.ones_like(t), t * ktc_per_k], 1)
        p, c, _ = _wls(d, var_e, fit.intercept_err_dn2 / k0**2)
        if p[1] > 0:
            r = math.sqrt(min(p[1], 1.0))
            r_err = math.sqrt(max(c[1, 1], 0.0)) / (2 * max(r, 1e-9))
            sf = float(p[0])
            sf_err = math.sqrt(max(c[0, 0], 0.0) + (sf * 2 * k0_err / k0) ** 2)
            if p[1] > 1.0:  # r capped at 1: refit σ_SF² with r = 1
                sf = float(np.average(var_e - t * ktc_per_k, weights=1 / err_e**2))
            return ReadNoiseLaw(sf, sf_err, r, min(r_err, 1.0), True, sense_node_gain_v_per_e, is_cmos)
        reset_factor = 0.0
        fitted = True
    else:
        fitted = False
        reset_factor = 0.0 if reset_factor is None else float(reset_factor)
    ktc = (t * ktc_per_k * reset_factor**2) if is_cmos else np.zeros_like(t)
    w = 1 / err_e**2
    sf = float(np.average(var_e - ktc, weights=w))
    # spread between temperatures counts too when it exceeds the measurement error
    sf_err = math.sqrt(1 / w.sum())
    if len(t) > 1:
        scatter = math.sqrt(float(np.average((var_e - ktc - sf) ** 2, weights=w)) / (len(t) - 1))
        sf_err = max(sf_err, scatter)
    return ReadNoiseLaw(sf, sf_err, reset_factor, 0.0, fitted, sense_node_gain_v_per_e, is_cmos)


def doubling_temperature(fit: DarkFit) -> tuple[float, float]:
    """EMVA 1288's doubling temperature T_d [K] of the dark current (DC ∝ 2^(T/T_d)) from the free fit's
    per-temperature dark currents (weighted regression of log2 DC on T), and its 1σ uncertainty; NaN with
    fewer than 2 temperatures that have a positive dark current."""
    ok = np.isfinite(fit.free_slope_dn2_per_s) & (fit.free_slope_dn2_per_s > 0) & np.isfinite(fit.free_slope_err)
    if ok.sum() < 2:
        return float("nan"), float("nan")
    t = fit.temperatures_k[ok]
    s = fit.free_slope_dn2_per_s[ok]
    e = np.maximum(fit.free_slope_err[ok] / s / math.log(2.0), 1e-6)  # σ of log2 s
    p, c, _ = _wls(np.stack([np.ones_like(t), t], 1), np.log2(s), e)
    if p[1] <= 0:
        return float("nan"), float("nan")
    return float(1.0 / p[1]), float(math.sqrt(max(c[1, 1], 0.0)) / p[1] ** 2)


def model_doubling_temperature(temperature_k: float) -> float:
    """T_d [K] of the Eq. 3.14 law at T: 1 / (d log2 DC / dT), by a central difference."""
    h = 0.01
    d = (math.log2(float(arrhenius_factor(temperature_k + h))) - math.log2(float(arrhenius_factor(temperature_k - h)))) / (2 * h)
    return 1.0 / d


def dfm_from_c(c_e: float, pixel_size_um: float) -> float:
    """D_FM [nA/cm²] from C = DC/f(T) [e⁻/s/K^1.5] and the pixel pitch [µm] (Eq. 3.14)."""
    return c_e / (DARK_CURRENT_PREFACTOR * (pixel_size_um * 1e-4) ** 2)
