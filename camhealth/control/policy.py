"""Exposure/gain policy from IOPCs: trade motion blur against noise to maximise detector AP.

Thesis Sec. 4.4.2 (Eq. 4.5–4.7) and Sec. 4.5.2 (Eq. 4.8). Changing the exposure time by

    α = t_exp^old / t_exp^new                                                        (4.6)

scales the collected light and the motion-blur length by 1/α (sensor linearity, constant relative
speed); the gain is multiplied by α to restore the image intensity ("digital gain", the thesis's worst
case). Per noise source this gives, in DN after the gain,

    σ_RN → α·σ_RN,   σ_PN → √α·σ_PN,   σ_DCSN → √α·σ_DCSN   (σ²_DCSN ∝ t_exp, Sec. 3.2.2.2)

so σ_new = σ̂·√(ρ·α² + (1 − ρ)·α) with ρ = σ_RN²/σ² the share of gain-linear noise. With only a total
σ̂ the policy uses ρ = 1, i.e. σ_new = α·σ̂ exactly as in Eq. 4.7; a noise-source estimate (σ̂_PN,
σ̂_DCSN, σ̂_RN) gives ρ. The blur side goes through the MTF → motion-length relation MB_L learned by the
sweep (:meth:`~camhealth.iopc.IOPC.length_from_mtf`; the relation MB ~ MTF⁻¹ is non-linear, thesis
note to Eq. 4.7): L̂ = MB_L(MTF̂), L_new = L̂/α, MTF_new = MB_L⁻¹(L_new). Then

    α* = argmax_α Σ_i λ_i · AP_i(σ_new(α), MTF_new,i(α))                         (4.7, 4.8)

over the α that keep t_exp/α and gain·α inside the camera's limits, with AP_i the 2-D IOPC of
application i (bilinear between bin centres; empty bins take the nearest measured bin and the
explanation says so). Ties go to the α closest to 1, and a change is only made if the expected gain is
at least ``min_gain`` (hysteresis).

Look-up table. All of this is precomputed on a grid of σ̂ (0.5 DN steps, finer for finer σ bins), MTF̂ (0.01 steps,
from 0 to exactly 1), ρ (5 levels) and α (65 log-spaced values in [1/16, 16], step 2^(1/8) ≈ 9 %): ``table[s, m, r, a]``
is the weighted AP. A decision interpolates the table trilinearly between the eight nodes around (σ̂, MTF̂, ρ) —
the objective is continuous in all three, and rounding to the nearest node moved σ̂ by up to a quarter of a σ bin and
ρ by up to 0.125 — then takes a feasibility mask over the 65 α and an argmax: tens of microseconds
(``docs/control.md``). :meth:`ExposurePolicy.objective` evaluates the same function
directly (no table) for checks; a σ̂ beyond the table's last node (``sigma_max_dn``) is decided with it, exactly.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from camhealth.iopc.curves import IOPC, bin_index

__all__ = ["CameraLimits", "Application", "Decision", "ExposurePolicy", "noise_scale", "MAX_TABLE_ENTRIES"]

#: Largest look-up table a policy builds, in entries: 200 MB as float32, a few GB of float64 while it is built. The
#: default tables hold 0.8 million (closed-loop IOPC) and 2.3 million (thesis grid).
MAX_TABLE_ENTRIES = 50_000_000


@dataclass(frozen=True)
class CameraLimits:
    """The camera's exposure [s] and gain [dB] ranges (inclusive)."""

    exposure_s: tuple[float, float] = (0.001, 0.2)
    gain_db: tuple[float, float] = (0.0, 24.0)

    def __post_init__(self) -> None:
        for nm, pair, unit in (("exposure", self.exposure_s, "s"), ("gain", self.gain_db, "dB")):
            if not (isinstance(pair, (tuple, list)) and len(pair) == 2 and all(_is_real(v) for v in pair)):
                raise ValueError(f"{nm} limits {pair!r} must be a pair of numbers (low, high) [{unit}]")
        t0, t1 = (float(v) for v in self.exposure_s)
        g0, g1 = (float(v) for v in self.gain_db)
        if not (math.isfinite(t0) and math.isfinite(t1) and 0 < t0 <= t1):
            raise ValueError(f"exposure limits {self.exposure_s!r} must satisfy 0 < low <= high (seconds)")
        if not (math.isfinite(g0) and math.isfinite(g1) and g0 <= g1):
            raise ValueError(f"gain limits {self.gain_db!r} must be finite with low <= high (dB)")
        object.__setattr__(self, "exposure_s", (t0, t1))
        object.__setattr__(self, "gain_db", (g0, g1))

    def clamp(self, exposure_s: float, gain_db: float) -> tuple[float, float]:
        """(exposure, gain) clipped into the limits; NaN or infinite values are refused (``ValueError``)."""
        if not (math.isfinite(exposure_s) and math.isfinite(gain_db)):
            raise ValueError(f"exposure_s = {exposure_s!r} s and gain_db = {gain_db!r} dB must be finite numbers to clamp "
                             f"into {self.exposure_s} s, {self.gain_db} dB")
        return (min(max(exposure_s, self.exposure_s[0]), self.exposure_s[1]),
                min(max(gain_db, self.gain_db[0]), self.gain_db[1]))


@dataclass
class Application:
    """One target application: its IOPC and weight λ (Eq. 4.8)."""

    iopc: IOPC
    weight: float = 1.0
    name: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.iopc, IOPC):
            raise TypeError(f"Application.iopc must be an IOPC, got {type(self.iopc).__name__}")
        if not (_is_real(self.weight) and math.isfinite(self.weight) and self.weight >= 0):
            raise ValueError(f"application weight λ = {self.weight!r} must be a finite number >= 0")
        self.weight = float(self.weight)
        self.name = self.name or self.iopc.name
        if self.iopc.blur_length_px.size < 2:
            raise ValueError(f"IOPC {self.name!r} has no MTF → motion-length relation (sweep needs ≥ 2 lengths)")


class Decision:
    """A policy decision. The numbers are computed by the table look-up; ``explanation`` and ``details``
    (and the predicted σ/MTF/lengths, which need the IOPCs) are computed on first access, so that the
    decision itself stays in the microseconds.

    Attributes:
        alpha: α* = t_old / t_new.
        exposure_s, gain_db: the new camera parameters [s], [dB].
        expected_ap: weighted AP predicted at the new parameters (Σ λ_i AP_i; the AP for one application).
        current_ap: the same at the current parameters (α = 1); NaN if those are outside the limits.
        expected_gain: expected_ap − current_ap.
        changed: whether the parameters change.
        explanation: one paragraph — which bins, which curve, which limit (lazy).
        details: the same as data (lazy): σ_new, MTF_new, motion lengths, bins per application, limits.
        sigma_new_dn, mtf_new, length_px, length_new_px: shortcuts into ``details`` (first application).
    """

    __slots__ = ("alpha", "exposure_s", "gain_db", "expected_ap", "current_ap", "expected_gain", "changed",
                 "_explain", "_cache")

    def __init__(self, alpha: float, exposure_s: float, gain_db: float, expected_ap: float, current_ap: float,
                 changed: bool, explain: Any) -> None:
        self.alpha, self.exposure_s, self.gain_db = alpha, exposure_s, gain_db
        self.expected_ap, self.current_ap = expected_ap, current_ap
        self.expected_gain = expected_ap - current_ap
        self.changed = changed
        self._explain = explain
        self._cache: tuple[str, dict[str, Any]] | None = None

    def _resolve(self) -> tuple[str, dict[str, Any]]:
        if self._cache is None:
            self._cache = self._explain()
        return self._cache

    @property
    def explanation(self) -> str:
        return self._resolve()[0]

    @property
    def details(self) -> dict[str, Any]:
        return self._resolve()[1]

    @property
    def sigma_new_dn(self) -> float:
        return float(self.details["sigma_new_dn"])

    @property
    def mtf_new(self) -> list[float]:
        return [a["mtf_new"] for a in self.details["applications"]]

    @property
    def length_px(self) -> float:
        return float(self.details["applications"][0]["length_px"])

    @property
    def length_new_px(self) -> float:
        return float(self.details["applications"][0]["length_new_px"])

    def __repr__(self) -> str:
        return (f"Decision(alpha={self.alpha:.4g}, exposure_s={self.exposure_s:.4g}, gain_db={self.gain_db:.3g}, "
                f"expected_ap={self.expected_ap:.3f}, expected_gain={self.expected_gain:+.3f}, changed={self.changed})")


def noise_scale(alpha: np.ndarray | float, rho: np.ndarray | float) -> np.ndarray:
    """σ_new / σ̂ = √(ρ·α² + (1 − ρ)·α): gain-linear share ρ scales with α, the rest with √α."""
    a = np.asarray(alpha, dtype=np.float64)
    r = np.asarray(rho, dtype=np.float64)
    return np.sqrt(r * a * a + (1.0 - r) * a)


class ExposurePolicy:
    """α* = argmax AP(σ_new, MTF_new) from one or more IOPCs, with camera limits, as a look-up table.

    Args:
        applications: an :class:`~camhealth.iopc.IOPC`, an ``(IOPC, λ)`` pair, an :class:`Application`, or a
            list or tuple of IOPCs / ``(IOPC, λ)`` pairs / Applications (Eq. 4.8 weights λ). A pair's λ is a real
            number, so a tuple of two IOPCs is two applications.
        limits: :class:`CameraLimits`.
        alpha_range: (min, max) α considered.
        n_alpha: number of log-spaced α (odd, so that α = 1 is on the grid).
        sigma_max_dn: largest σ̂ in the table [DN] (default: last σ bin + one bin spacing); for a larger σ̂
            :meth:`decide` evaluates the objective directly (as :meth:`objective`, no table; noted in the
            explanation), so its α and expected AP are exact there too.
        sigma_step_dn, mtf_step: table resolution (σ [DN], default: half the finest σ-bin spacing, <= 0.5 DN;
            MTF̂, dimensionless, in (0, 0.5]). The MTF̂ axis runs from 0 to exactly 1 in ceil(1/mtf_step) equal
            intervals, so the step used (``self.mtf_step``) is 1/ceil(1/mtf_step): ``mtf_step`` itself where it
            divides 1, else slightly smaller (0.03 → 1/34 ≈ 0.0294).
        rho_levels: number of ρ levels in [0, 1] (an integer >= 2).
        min_gain: smallest expected AP gain that justifies a change.

    Decisions never leave the limits: a decision "on a limit" is exactly on it (exposure t_min or t_max [s], gain
    g_min or g_max [dB]), and the result is clamped into :class:`CameraLimits` against float rounding.
    """

    def __init__(
        self,
        applications: IOPC | Sequence[IOPC | tuple[IOPC, float] | Application],
        limits: CameraLimits | None = None,
        alpha_range: tuple[float, float] = (1.0 / 16.0, 16.0),
        n_alpha: int = 65,
        sigma_max_dn: float | None = None,
        sigma_step_dn: float | None = None,
        mtf_step: float = 0.01,
        rho_levels: int = 5,
        min_gain: float = 0.0,
    ) -> None:
        self.apps = _as_applications(applications)
        for app in self.apps:
            m = np.asarray(app.iopc.blur_mtf, dtype=np.float64)
            if m.size < 2 or not m[-1] < m[0]:
                raise ValueError(f"IOPC {app.name!r}: its MTF → motion-length relation {m.tolist()} does not fall with the "
                                 "motion length, so it cannot tell one blur from another (sweep lengths that blur the frames)")
        if limits is not None and not isinstance(limits, CameraLimits):
            raise TypeError(f"limits must be a CameraLimits, got {type(limits).__name__}")
        self.limits = limits or CameraLimits()
        if not (isinstance(alpha_range, (tuple, list)) and len(alpha_range) == 2 and all(_is_real(v) for v in alpha_range)):
            raise ValueError(f"alpha_range {alpha_range!r} must be a pair of numbers (low, high)")
        a0, a1 = (float(v) for v in alpha_range)
        if not (0 < a0 < 1 < a1 and math.isfinite(a1)):
            raise ValueError(f"alpha_range {alpha_range!r} must satisfy 0 < low < 1 < high")
        if not _is_real(n_alpha) or int(n_alpha) != n_alpha or n_alpha < 3 or n_alpha % 2 == 0:
            raise ValueError(f"n_alpha = {n_alpha!r} must be an odd integer >= 3 (α = 1 on the grid)")
        if sigma_step_dn is None:  # half the finest σ-bin spacing, at most 0.5 DN
            sigma_step_dn = min(0.5, min(float(np.diff(a.iopc.sigma_bins).min()) for a in self.apps) / 2)
        if not (_is_real(sigma_step_dn) and math.isfinite(sigma_step_dn) and sigma_step_dn > 0):
            raise ValueError(f"sigma_step_dn = {sigma_step_dn!r} DN is out of the allowed range: a finite number > 0")
        if not (_is_real(mtf_step) and 0 < mtf_step <= 0.5):
            raise ValueError(f"mtf_step = {mtf_step!r} is out of the allowed range (0, 0.5]")
        if not (_is_real(rho_levels) and int(rho_levels) == rho_levels and rho_levels >= 2):
            raise ValueError(f"rho_levels = {rho_levels!r} is out of the allowed range: an integer >= 2")
        if not (_is_real(min_gain) and math.isfinite(min_gain) and min_gain >= 0):
            raise ValueError(f"min_gain = {min_gain!r} is out of the allowed range: a finite number >= 0 (AP)")
        self.min_gain = float(min_gain)
        # symmetric in log α around 1 where possible
        la = np.linspace(math.log(a0), math.log(a1), int(n_alpha))
        la[int(np.argmin(np.abs(la)))] = 0.0
        self.alphas = np.exp(la)
        self.i_one = int(np.argmin(np.abs(la)))
        last_bin = max(float(a.iopc.sigma_bins[-1]) for a in self.apps)
        if sigma_max_dn is None:
            smax = max(float(a.iopc.sigma_bins[-1] + np.diff(a.iopc.sigma_bins)[-1]) for a in self.apps)
        else:
            # the table covers at least the σ the IOPCs measured (σ̂ beyond its end takes the direct, slower path)
            if not (_is_real(sigma_max_dn) and math.isfinite(sigma_max_dn) and sigma_max_dn >= last_bin):
                raise ValueError(f"sigma_max_dn = {sigma_max_dn!r} DN is out of the allowed range: a finite number >= the "
                                 f"IOPCs' last σ bin, {last_bin:g} DN")
            smax = float(sigma_max_dn)
        self.sigma_step = float(sigma_step_dn)
        n_table = (math.floor(max(smax, self.sigma_step) / self.sigma_step) + 2) * (math.ceil(1.0 / float(mtf_step) - 1e-9) + 1) \
            * int(rho_levels) * int(n_alpha)
        if n_table > MAX_TABLE_ENTRIES:
            raise ValueError(f"the table would hold {n_table:.3g} entries (σ̂ up to {smax:g} DN in {self.sigma_step:g}-DN steps, MTF̂ "
                             f"in {float(mtf_step):g} steps, {rho_levels} ρ levels, {n_alpha} α): more than the allowed "
                             f"{MAX_TABLE_ENTRIES:.3g} ({MAX_TABLE_ENTRIES * 4 / 1e9:g} GB as float32); coarsen sigma_step_dn or mtf_step")
        # at least two nodes (0 and one step), so there is always a cell to interpolate in
        self.sigma_grid = np.arange(0.0, max(smax, self.sigma_step) + 0.5 * self.sigma_step, self.sigma_step)
        # 0 … 1 exactly, in n equal intervals (the step used is 1/n <= mtf_step): an arange with a step that does not
        # divide 1 (0.03, 0.3) would end short of 1 and look a sharp frame (MTF̂ = 1) up as a blurred one
        n_mtf = max(1, math.ceil(1.0 / float(mtf_step) - 1e-9))
        self.mtf_step = 1.0 / n_mtf
        self.mtf_grid = np.linspace(0.0, 1.0, n_mtf + 1)
        self.rho_grid = np.linspace(0.0, 1.0, int(rho_levels))
        self.table = self._build_table()
        self._sigma_top = min(_sigma_top(a.iopc) for a in self.apps)
        # plain-Python copies for the per-decision fast path
        self._alpha_list = self.alphas.tolist()
        self._n_sigma, self._n_mtf, self._n_rho_1 = self.sigma_grid.size, self.mtf_grid.size, self.rho_grid.size - 1
        self._log_a0, self._dlog_a = float(la[0]), float(la[1] - la[0])
        self._sigma_grid_end = float(self.sigma_grid[-1])

    # ------------------------------------------------------------------ the objective
    def _app_terms(self, app: Application, sigma: np.ndarray, mtf: np.ndarray, alpha: np.ndarray, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """AP, σ_new and MTF_new of one application; arrays broadcast together."""
        length = app.iopc.length_from_mtf(mtf)
        mtf_new = app.iopc.mtf_from_length(length / alpha)
        sigma_new = sigma * noise_scale(alpha, rho)
        return app.iopc.interpolate(sigma_new, mtf_new), sigma_new, mtf_new

    def objective(self, sigma: float, mtf: float, alpha: np.ndarray | float, rho: float = 1.0) -> np.ndarray:
        """Σ_i λ_i AP_i(σ_new(α), MTF_new,i(α)) evaluated directly (no table); vectorised over α. −∞ where α ≠ 1 raises
        σ_new beyond what an IOPC measured (as in :meth:`decide`: no candidate)."""
        a = np.asarray(alpha, dtype=np.float64)
        total = np.float64(0.0)
        for app in self.apps:
            ap, _, _ = self._app_terms(app, np.float64(sigma), np.float64(mtf), a, np.float64(rho))
            total = total + app.weight * ap
        return np.where(self._beyond(float(sigma), a, float(rho)), -np.inf, total)

    def _build_table(self) -> np.ndarray:
        s = self.sigma_grid[:, None, None, None]
        m = self.mtf_grid[None, :, None, None]
        r = self.rho_grid[None, None, :, None]
        a = self.alphas[None, None, None, :]
        total = np.zeros((s.shape[0], m.shape[1], r.shape[2], a.shape[3]), dtype=np.float64)
        for app in self.apps:
            length = app.iopc.length_from_mtf(m)
            mtf_new = app.iopc.mtf_from_length(length / a)  # (1, M, 1, A)
            sigma_new = s * noise_scale(a, r)  # (S, 1, R, A)
            total += app.weight * app.iopc.interpolate(sigma_new, mtf_new)
        # finite everywhere: which α predict a σ beyond what the sweep measured is decided per decision, exactly
        # (:meth:`_beyond`), so a node beyond does not spill into its neighbours' interpolation
        return total.astype(np.float32)

    @property
    def table_bytes(self) -> int:
        return int(self.table.nbytes)

    # ------------------------------------------------------------------ decisions
    def feasible(self, exposure_s: float, gain_db: float) -> np.ndarray:
        """(A,) bool: α whose t/α and gain·α lie within the limits."""
        lo, hi = self._alpha_interval(exposure_s, gain_db)
        return (self.alphas >= lo) & (self.alphas <= hi)

    def _alpha_limits(self, exposure_s: float, gain_db: float) -> tuple[float, float]:
        """Exact [α_lo, α_hi] with t/α ∈ exposure limits and gain·α ∈ gain limits: the α that put exposure or gain
        on a limit."""
        (t0, t1), (g0, g1) = self.limits.exposure_s, self.limits.gain_db
        lo = max(exposure_s / t1, 10.0 ** ((g0 - gain_db) / 20.0))
        hi = min(exposure_s / t0, 10.0 ** ((g1 - gain_db) / 20.0))
        return lo, hi

    def _alpha_interval(self, exposure_s: float, gain_db: float) -> tuple[float, float]:
        """:meth:`_alpha_limits` widened by a relative tolerance of 1e-9, for the feasibility test only (a grid α
        within float rounding of a limit counts as feasible; its result is clamped into the limits)."""
        lo, hi = self._alpha_limits(exposure_s, gain_db)
        return lo * (1 - 1e-9), hi * (1 + 1e-9)

    def _row_at(self, row: np.ndarray, alpha: float) -> float:
        """Table row at a non-grid α: linear in log α between the neighbouring grid points."""
        p = (math.log(alpha) - self._log_a0) / self._dlog_a
        i = min(max(int(p), 0), self.alphas.size - 2)
        f = p - i
        lo, hi = float(row[i]), float(row[i + 1])
        if f <= 0.0 or f >= 1.0:
            return lo if f <= 0.0 else hi
        return lo * (1.0 - f) + hi * f

    def _row(self, sigma: float, mtf: float, rho: float) -> np.ndarray:
        """(A,) weighted AP over the α grid at (σ̂ [DN], MTF̂, ρ): trilinear between the table's eight neighbouring
        nodes. Only for σ̂ within the table: :meth:`decide` evaluates σ̂ beyond it with :meth:`objective`."""
        idx, frac = [], []
        for p, n in ((sigma / self.sigma_step, self._n_sigma), (mtf / self.mtf_step, self._n_mtf),
                     (rho * self._n_rho_1, self._n_rho_1 + 1)):
            p = min(max(p, 0.0), n - 1.0)
            i = min(int(p), n - 2)
            idx.append(i)
            frac.append(p - i)
        (i, j, k), (fs, fm, fr) = idx, frac
        gs, gm, gr = 1.0 - fs, 1.0 - fm, 1.0 - fr
        w = np.array([gs * gm * gr, gs * gm * fr, gs * fm * gr, gs * fm * fr,
                      fs * gm * gr, fs * gm * fr, fs * fm * gr, fs * fm * fr])
        return w @ self.table[i:i + 2, j:j + 2, k:k + 2].reshape(8, -1).astype(np.float64)

    def _beyond(self, sigma: float, alpha: np.ndarray | float, rho: float) -> np.ndarray:
        """α ≠ 1 whose predicted σ [DN] rises beyond what an IOPC measured (its last σ bin's centre plus half the
        spacing): the AP there would be read as flat, so such an α is no candidate (the current parameters, α = 1,
        always are)."""
        a = np.asarray(alpha, dtype=np.float64)
        sigma_new = sigma * noise_scale(a, rho)
        return (sigma_new > self._sigma_top) & (sigma_new > sigma) & (a != 1.0)

    def decide(
        self,
        sigma_hat: float,
        mtf_hat: float,
        exposure_s: float,
        gain_db: float,
        sigma_sources: Sequence[float] | None = None,
        rho: float | None = None,
    ) -> Decision:
        """New (exposure, gain) for an image with estimated σ̂ [DN] and MTF̂ taken at (exposure [s],
        gain [dB]).

        Candidates are the table's α inside the camera limits plus the two α that put exposure or gain
        exactly on a limit (their AP interpolated in log α), so a policy that wants "as much as the camera
        allows" gets exactly the limit; the new (exposure, gain) are clamped into the limits, so float
        rounding never puts them outside.

        Args:
            sigma_hat: total noise estimate σ̂ [DN] (Eq. 4.4 median), >= 0. Beyond the table's last node
                (``sigma_grid[-1]``) the objective is evaluated directly (:meth:`objective`) instead of the table.
            mtf_hat: blur indicator MTF̂ in [0, 1].
            exposure_s, gain_db: the parameters the image was taken with.
            sigma_sources: optional (σ_PN, σ_DCSN, σ_RN) [DN] → ρ = σ_RN²/Σσ².
            rho: explicit gain-linear noise share in [0, 1] (default 1: σ ∝ α, Eq. 4.7).
        """
        for name, value in (("sigma_hat", sigma_hat), ("mtf_hat", mtf_hat), ("exposure_s", exposure_s), ("gain_db", gain_db)):
            if not _is_real(value):
                raise ValueError(f"{name} = {value!r} must be a number, got {type(value).__name__}")
        if not (math.isfinite(sigma_hat) and sigma_hat >= 0):
            raise ValueError(f"sigma_hat = {sigma_hat!r} DN must be a finite number >= 0")
        if not (math.isfinite(mtf_hat) and 0.0 <= mtf_hat <= 1.0 + 1e-6):
            raise ValueError(f"mtf_hat = {mtf_hat!r} must lie in [0, 1]")
        for app in self.apps:  # more blur than the sweep measured: no length, so no prediction of a shorter exposure
            least = float(app.iopc.blur_mtf[-1])
            if mtf_hat < least - 0.5 * self.mtf_step:
                raise ValueError(
                    f"mtf_hat = {mtf_hat:.3f} is blurrier than the MTF → motion-length relation of IOPC {app.name!r} "
                    f"reaches (MTF̃ {least:.3f} at {float(app.iopc.blur_length_px[-1]):g} px): how a shorter exposure "
                    "would change it cannot be told from this IOPC (sweep longer motion blurs)")
        if not (math.isfinite(exposure_s) and exposure_s > 0):
            raise ValueError(f"exposure_s = {exposure_s!r} s must be a finite number > 0")
        if not (math.isfinite(gain_db) and abs(gain_db) <= 200.0):  # (10^(gain/20) overflows a float near 6000 dB)
            raise ValueError(f"gain_db = {gain_db!r} dB is out of the allowed range: a finite gain in [-200, 200] dB")
        rho_v = self._rho(sigma_sources, rho)
        lo_x, hi_x = self._alpha_limits(exposure_s, gain_db)
        lo, hi = lo_x * (1 - 1e-9), hi_x * (1 + 1e-9)  # = _alpha_interval: feasibility with a float tolerance
        lo_c, hi_c = max(lo, self._alpha_list[0]), min(hi, self._alpha_list[-1])
        if lo_c > hi_c:
            raise ValueError(
                f"no α in [{self.alphas[0]:.3g}, {self.alphas[-1]:.3g}] keeps exposure {exposure_s:g} s / α within "
                f"{self.limits.exposure_s} s and gain {gain_db:g} dB + 20·log10 α within {self.limits.gain_db} dB"
            )
        # σ̂ beyond the table's last node: the table cannot tell it from that node, so the objective is evaluated
        # directly (exact, −∞ where α predicts σ beyond what the IOPCs measured) for the grid α and the limit α
        exact = sigma_hat > self._sigma_grid_end
        row = self.objective(sigma_hat, mtf_hat, self.alphas, rho_v) if exact else self._row(sigma_hat, mtf_hat, rho_v)
        a0, a1 = bisect.bisect_left(self._alpha_list, lo_c), bisect.bisect_right(self._alpha_list, hi_c)
        cand_a: list[float] = self._alpha_list[a0:a1]
        cand_v: list[float] = row[a0:a1].tolist()
        # σ_new grows with α, so only the largest candidate can tell whether any predicts σ beyond the IOPCs
        if sigma_hat * math.sqrt(rho_v * hi_c * hi_c + (1.0 - rho_v) * hi_c) > self._sigma_top:
            cand_v = np.where(self._beyond(sigma_hat, self.alphas[a0:a1], rho_v), -np.inf, row[a0:a1]).tolist()
        # the limits themselves (exact, not widened), if they fall between grid points
        for e in (min(max(lo_x, self._alpha_list[0]), hi_c), max(min(hi_x, self._alpha_list[-1]), lo_c)):
            if not cand_a or (e < cand_a[0] * (1 - 1e-12) or e > cand_a[-1] * (1 + 1e-12)):
                cand_a.append(e)
                if exact:
                    cand_v.append(float(self.objective(sigma_hat, mtf_hat, e, rho_v)))
                else:
                    cand_v.append(-math.inf if self._beyond(sigma_hat, e, rho_v) else self._row_at(row, e))
        best = max(cand_v)
        if not math.isfinite(best):
            raise ValueError(f"every α the limits allow predicts σ beyond what the IOPC measured (σ̂ = {sigma_hat:g} DN): "
                             "the effect of a change cannot be told")
        alpha = min((a for a, v in zip(cand_a, cand_v) if v >= best - 1e-6), key=lambda a: abs(math.log(a)))
        cur_ok = lo <= 1.0 <= hi
        current = float(row[self.i_one]) if cur_ok else float("nan")
        held = None
        if cur_ok and alpha != 1.0 and best - current < self.min_gain:
            held, alpha = best - current, 1.0
        expected = current if alpha == 1.0 and cur_ok else best
        # t/α and gain + 20·log10 α can miss a limit by float rounding (or by the feasibility tolerance): clamp
        t_new, g_new = self.limits.clamp(exposure_s / alpha, gain_db + 20.0 * math.log10(alpha))
        args = (alpha, float(sigma_hat), float(mtf_hat), float(exposure_s), float(gain_db), rho_v, current, expected,
                cur_ok, held, (lo, hi), (t_new, g_new))
        return Decision(alpha, t_new, g_new, expected, current, alpha != 1.0, lambda: self._explain(*args))

    def _rho(self, sigma_sources: Sequence[float] | None, rho: float | None) -> float:
        if rho is not None and sigma_sources is not None:
            raise ValueError("give either sigma_sources or rho, not both")
        if sigma_sources is not None:  # plain floats: this is on the per-decision path
            if isinstance(sigma_sources, (str, bytes)) or not all(_is_real(v) for v in sigma_sources):
                raise ValueError(f"sigma_sources = {sigma_sources!r} must be three numbers σ >= 0 [DN] (PN, DCSN, RN)")
            src = [float(v) for v in sigma_sources]
            if len(src) != 3 or not all(math.isfinite(v) and v >= 0 for v in src):
                raise ValueError(f"sigma_sources must be three σ >= 0 [DN] (PN, DCSN, RN), got {src}")
            tot = src[0] * src[0] + src[1] * src[1] + src[2] * src[2]
            return src[2] * src[2] / tot if tot > 0 else 1.0
        if rho is None:
            return 1.0
        if not (_is_real(rho) and math.isfinite(rho) and 0 <= rho <= 1):
            raise ValueError(f"rho = {rho!r} must lie in [0, 1]")
        return float(rho)

    def _explain(self, alpha: float, sigma_hat: float, mtf_hat: float, t: float, g: float, rho: float,
                 current: float, expected: float, cur_ok: bool, held: float | None,
                 interval: tuple[float, float], new: tuple[float, float]) -> tuple[str, dict[str, Any]]:
        t_new, g_new = new
        per_app = []
        sigma_new = float(sigma_hat * noise_scale(alpha, rho))
        for app in self.apps:
            ap_new, _, mtf_new = self._app_terms(app, np.float64(sigma_hat), np.float64(mtf_hat), np.float64(alpha), np.float64(rho))
            ap_now = float(app.iopc.interpolate(sigma_hat, mtf_hat))
            length = float(app.iopc.length_from_mtf(mtf_hat))
            per_app.append({
                "name": app.name, "weight": app.weight, "ap_now": ap_now, "ap_new": float(ap_new),
                "length_px": length, "length_new_px": length / alpha, "mtf_new": float(mtf_new),
                "bin_now": self._bin(app.iopc, sigma_hat, mtf_hat), "bin_new": self._bin(app.iopc, sigma_new, float(mtf_new)),
            })
        t0, t1 = self.limits.exposure_s
        at_limit = []
        lo, hi = interval
        if alpha >= hi * (1 - 1e-6):  # cannot shorten further
            at_limit.append("shortest exposure" if t_new <= t0 * (1 + 1e-6) else "highest gain")
        if alpha <= lo * (1 + 1e-6):  # cannot lengthen further
            at_limit.append("longest exposure" if t_new >= t1 * (1 - 1e-6) else "lowest gain")
        details = {
            "alpha": alpha, "rho": rho, "sigma_hat_dn": sigma_hat, "mtf_hat": mtf_hat,
            "sigma_new_dn": sigma_new, "applications": per_app, "limits_reached": at_limit,
            "alpha_interval": [lo, hi], "current_feasible": cur_ok, "expected_ap": expected, "current_ap": current,
            "sigma_beyond_table": sigma_hat > self._sigma_grid_end,
            "held_by_min_gain": held,
        }
        gain = expected - current if cur_ok else float("nan")
        a0 = per_app[0]
        verb = "keep" if alpha == 1.0 else ("shorten" if alpha > 1 else "lengthen")
        lines = [
            f"σ̂ = {sigma_hat:.2f} DN, MTF̂ = {mtf_hat:.3f} (≈ {a0['length_px']:.1f} px motion by the MTF→length "
            f"relation of {a0['name']!r}) at t = {t * 1e3:.2f} ms, gain = {g:.1f} dB.",
            f"Decision: {verb} the exposure, α* = {alpha:.3g} → t = {t_new * 1e3:.2f} ms, gain = {g_new:.1f} dB "
            f"(predicted σ = {sigma_new:.2f} DN with gain-linear share ρ = {rho:.2f}, motion ≈ {a0['length_new_px']:.1f} px).",
        ]
        for a in per_app:
            bn, bw = a["bin_now"], a["bin_new"]
            lines.append(
                f"IOPC {a['name']!r} (λ = {a['weight']:g}): now bin (σ̃ {bn['sigma_bin']:g} DN, MTF̃ {bn['mtf_bin']:.1f}) "
                f"[{bn['status']}] AP {a['ap_now']:.3f} → bin (σ̃ {bw['sigma_bin']:g} DN, MTF̃ {bw['mtf_bin']:.1f}) "
                f"[{bw['status']}] AP {a['ap_new']:.3f}."
            )
        lines.append(
            f"Expected AP {current:.3f} → {expected:.3f} ({gain:+.3f})." if cur_ok else
            f"Current parameters are outside the limits; expected AP at the new ones {expected:.3f}."
        )
        if held is not None:
            lines.append(f"(The best feasible change would gain {held:+.3f} < min_gain = {self.min_gain:g}: kept.)")
        if at_limit:
            lines.append("At the camera limit: " + ", ".join(at_limit) + " (α cannot go further that way).")
        if details["sigma_beyond_table"]:
            lines.append(f"σ̂ is beyond the look-up table (which ends at {self._sigma_grid_end:g} DN): the objective was "
                         "evaluated directly, without the table.")
        return " ".join(lines), details

    @staticmethod
    def _bin(iopc: IOPC, sigma: float, mtf: float) -> dict[str, Any]:
        (i,), (ins_s,) = bin_index([sigma], iopc.sigma_bins)
        (j,), (ins_m,) = bin_index([mtf], iopc.mtf_bins)
        measured = bool(iopc.count_2d[i, j] > 0)
        status = ("measured" if measured else "empty, filled from the nearest measured bin") + (
            "" if ins_s and ins_m else ", beyond the curve (clamped)")
        return {"sigma_bin": float(iopc.sigma_bins[i]), "mtf_bin": float(iopc.mtf_bins[j]), "measured": measured,
                "status": status, "count": int(iopc.count_2d[i, j])}


def _sigma_top(iopc: IOPC) -> float:
    """The largest σ [DN] an IOPC measured: its last σ bin's centre plus half the spacing to the one before."""
    bins = np.asarray(iopc.sigma_bins, dtype=np.float64)
    return float(bins[-1] + 0.5 * (bins[-1] - bins[-2])) if bins.size > 1 else float(bins[-1])


def _is_real(v: Any) -> bool:
    """A real number (Python or numpy), not a bool."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _is_pair(a: Any) -> bool:
    """An ``(IOPC, λ)`` pair: two items, an IOPC and a real number."""
    return isinstance(a, (tuple, list)) and len(a) == 2 and isinstance(a[0], IOPC) and _is_real(a[1])


def _as_applications(applications: Any) -> list[Application]:
    forms = "an IOPC, an Application, or a list/tuple of IOPCs, (IOPC, weight λ) pairs and Applications"
    if isinstance(applications, (IOPC, Application)):
        applications = [applications]
    # a bare (IOPC, λ) pair is one application; a tuple of two IOPCs is two
    if _is_pair(applications):
        applications = [applications]
    if not isinstance(applications, (list, tuple)):
        raise TypeError(f"applications must be {forms}; got {type(applications).__name__}")
    out = []
    for a in applications:
        if isinstance(a, Application):
            out.append(a)
        elif isinstance(a, IOPC):
            out.append(Application(a))
        elif _is_pair(a):
            out.append(Application(a[0], float(a[1])))
        elif isinstance(a, (tuple, list)) and len(a) == 2 and isinstance(a[0], IOPC):
            raise TypeError(f"application weight λ = {a[1]!r} is not allowed: a real number >= 0 (pair (IOPC, λ))")
        else:
            raise TypeError(f"applications must be {forms}; got an item of type {type(a).__name__}")
    if not out:
        raise ValueError("the policy needs at least one application (IOPC)")
    if sum(a.weight for a in out) <= 0:
        raise ValueError("at least one application weight λ must be > 0")
    return out
