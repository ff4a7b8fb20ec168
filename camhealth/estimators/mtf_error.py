"""A calibrated uncertainty for MTF estimates: the RMS error of an estimator as a function of its own answer.

An MTF estimator that reads a scene unlike its training is wrong mostly where the answer leaves room to be wrong:
an estimate Ĥ near 1 (little blur at that frequency) or near 0 (no contrast left) can be off by little, one in
between by much more. The shipped ``mtf`` table (``python -m camhealth.bench mtf_error``, assessable patches) has
RMS 0.02 at Ĥ = 0 and 1, 0.04–0.06 at Ĥ = 0.05 and 0.95 and 0.18 at Ĥ = 0.5–0.6; on the robustness benchmark the
error against Ĥ looks alike for every PSF family, blur size and condition, and for PSF generators the table was and
was not measured on (``python -m camhealth.bench robustness --task mtf``). The spread of the estimates of flipped views of
a patch sees only the part of the error the views do not share; a scene's own content (line art read too sharp,
smooth textures too blurred) moves all views alike.

An :class:`MTFErrorTable` holds r(Ĥ), the RMS error (MTF units, 0–1) at knots of Ĥ, measured on a calibration
set with an exact truth (``python -m camhealth.bench mtf_error``). The uncertainty of each value is

    u = √(r(Ĥ)² + s²),

r interpolated linearly between the knots, s the spread of the views (0 for one view). It is a 1-σ error bar of
one patch's value: where the errors are those of the calibration set, |Ĥ − H| ≤ 2u for about 95 % of the values.
It is not a bound: a source unlike every calibration scene (one with a strong blur of its own) can be wrong by
more.

**What the patches of one scene share.** The error is mostly the scene's: patches of one frame of line art are all
read too sharp, so the median over a frame's patches is not √n times more accurate than one patch. ``shared`` is the
share ρ of a value's error variance that the patches of one scene have in common — the mean product of the
standardised errors z = (Ĥ − H)/r(Ĥ) of two patches of one frame over the mean z² (:func:`shared_error_fraction`),
measured on frames of the calibration scenes (``python -m camhealth.bench mtf_error``). A median of n patches of one
scene then has the standard error r·√(ρ + (π/2)(1 − ρ)/n) (:func:`frame_uncertainty`, the large-n form of a
median's variance, which overstates it for few patches), which is what the monitor states for a frame.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import torch

__all__ = ["DEFAULT_KNOTS", "MTFErrorTable", "fit_error_table", "frame_uncertainty", "mtf_uncertainty",
           "shared_error_fraction"]

#: Knots of Ĥ for :func:`fit_error_table`: finer near 0 and 1, where the error changes fastest.
DEFAULT_KNOTS = (0.0, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 1.0)


def _interp(x: torch.Tensor, xp: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """Piecewise-linear interpolation of (xp, fp) at x, constant beyond the ends; xp strictly increasing, on x's
    device."""
    x = torch.minimum(torch.maximum(x, xp[0]), xp[-1])  # tensor bounds: no copy to the host
    i = torch.bucketize(x, xp, right=True).clamp(1, xp.numel() - 1)
    x0, x1, f0, f1 = xp[i - 1], xp[i], fp[i - 1], fp[i]
    return f0 + (f1 - f0) * (x - x0) / (x1 - x0)


@dataclass(frozen=True)
class MTFErrorTable:
    """RMS error of an MTF estimator against its own estimate (module docstring).

    Attributes:
        knots: estimates Ĥ at which ``rms`` is given, strictly increasing, the first 0 and the last 1.
        rms: RMS of Ĥ − H at each knot [MTF units, 0–1], each in [0, 1].
        values: number of MTF values behind the fit (≥ 1).
        data: what the calibration set was (free text, for the model card).
        shared: the share ρ ∈ [0, 1] of the error variance that the patches of one scene have in common (module
            docstring); 0 where it was not measured (each patch's error its own).
    """

    knots: tuple[float, ...]
    rms: tuple[float, ...]
    values: int
    data: str = ""
    shared: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "knots", tuple(float(k) for k in self.knots))
        object.__setattr__(self, "rms", tuple(float(r) for r in self.rms))
        k, r = self.knots, self.rms
        if len(k) < 2 or len(k) != len(r):
            raise ValueError(f"mtf_error: knots ({len(k)}) and rms ({len(r)}) must have the same length ≥ 2")
        if not all(math.isfinite(v) for v in k + r):
            raise ValueError(f"mtf_error: knots {list(k)} and rms {list(r)} must be finite")
        if k[0] != 0.0 or k[-1] != 1.0 or any(b <= a for a, b in zip(k, k[1:])):
            raise ValueError(f"mtf_error: knots {list(k)} must increase strictly from 0 to 1")
        if any(not 0.0 <= v <= 1.0 for v in r):
            raise ValueError(f"mtf_error: rms {list(r)} must lie in the allowed range [0, 1]")
        if isinstance(self.values, bool) or not isinstance(self.values, numbers.Integral) or self.values < 1:
            raise ValueError(f"mtf_error: values = {self.values!r} must be a positive integer")
        if isinstance(self.shared, bool) or not isinstance(self.shared, numbers.Real) or not 0.0 <= self.shared <= 1.0:
            raise ValueError(f"mtf_error: shared = {self.shared!r} must be a number in the allowed range [0, 1]")
        object.__setattr__(self, "values", int(self.values))
        object.__setattr__(self, "shared", float(self.shared))

    def __call__(self, mtf: torch.Tensor) -> torch.Tensor:
        """r(Ĥ) at each value of ``mtf`` (any shape, MTF units) → the same shape, float32, on ``mtf``'s device."""
        m = torch.as_tensor(mtf).float()
        return _interp(m, torch.tensor(self.knots, device=m.device), torch.tensor(self.rms, device=m.device))

    def to_dict(self) -> dict[str, Any]:
        return {"knots": list(self.knots), "rms": list(self.rms), "values": self.values, "data": self.data,
                "shared": self.shared}

    @classmethod
    def from_dict(cls, d: Any, where: str = "mtf_error") -> "MTFErrorTable":
        """Rebuild from :meth:`to_dict` (a file's description); a malformed entry is one ``ValueError`` naming
        ``where`` and the field."""
        if not isinstance(d, Mapping):
            raise ValueError(f"{where}: mtf_error must be a JSON object, got {type(d).__name__}")
        unknown = sorted(set(map(str, d)) - {"knots", "rms", "values", "data", "shared"})
        if unknown:
            raise ValueError(f"{where}: mtf_error has unknown fields {unknown}; allowed: data, knots, rms, shared, values")
        for name in ("knots", "rms"):
            v = d.get(name)
            if not isinstance(v, (list, tuple)) or not all(isinstance(x, numbers.Real) and not isinstance(x, bool) for x in v):
                raise ValueError(f"{where}: mtf_error {name} = {v!r} must be a list of numbers")
        if not isinstance(d.get("data", ""), str):
            raise ValueError(f"{where}: mtf_error data must be a string")
        try:
            return cls(tuple(d["knots"]), tuple(d["rms"]), d.get("values", 0), d.get("data", ""), d.get("shared", 0.0))
        except ValueError as exc:  # its message starts "mtf_error: …": prefixed by ``where`` unless that says the same
            raise ValueError(str(exc) if where == "mtf_error" else f"{where}: {exc}") from None


def mtf_uncertainty(mtf: torch.Tensor, table: MTFErrorTable | None, spread: torch.Tensor | None = None) -> torch.Tensor:
    """Per-value uncertainty u = √(r(Ĥ)² + s²) of MTF estimates (module docstring).

    Args:
        mtf: (…) estimates Ĥ [0–1] (NaN: an omitted value, whose u is NaN).
        table: the estimator's :class:`MTFErrorTable`; None: no calibration — u is the spread alone (NaN without one).
        spread: (…) standard deviation of the flipped views' estimates, ≥ 0 or NaN (not known), of ``mtf``'s shape or
            broadcastable to it; or None (one view: s = 0).

    Returns:
        (…) float32 uncertainty [MTF units], on ``mtf``'s device.

    Raises:
        TypeError: ``table`` is neither an :class:`MTFErrorTable` nor None.
        ValueError: ``spread`` of another shape, negative or infinite.
    """
    if table is not None and not isinstance(table, MTFErrorTable):
        raise TypeError(f"table must be an MTFErrorTable or None, got {type(table).__name__}")
    m = torch.as_tensor(mtf).float()
    s = None if spread is None else torch.as_tensor(spread).float()
    if s is not None:
        try:
            fits = torch.broadcast_shapes(m.shape, s.shape) == m.shape
        except RuntimeError:
            fits = False
        if not fits:
            raise ValueError(f"spread {tuple(s.shape)} must have the shape of mtf {tuple(m.shape)} (or broadcast to it)")
        if s.device.type != "meta" and bool((s < 0).any() | torch.isinf(s).any()):
            bad = s[(s < 0) | torch.isinf(s)].flatten()[0].item()
            raise ValueError(f"spread must be a standard deviation (≥ 0, or NaN where not known), got {bad:g}")
    if table is None:
        return s.clone() if s is not None else torch.full_like(m, float("nan"))
    r = table(m)
    return r if s is None else torch.sqrt(r * r + s * s)


def fit_error_table(estimate: torch.Tensor, truth: torch.Tensor, valid: torch.Tensor | None = None,
                    knots: Sequence[float] = DEFAULT_KNOTS, min_values: int = 32, data: str = "") -> MTFErrorTable:
    """Measure r(Ĥ): the RMS of ``estimate − truth`` over the values nearest each knot of Ĥ.

    A knot with fewer than ``min_values`` values takes the linear interpolation of its neighbours' RMS (the end
    knots the nearest measured one).

    Args:
        estimate, truth: (B, 16) MTF values [0–1] (any matching shape).
        valid: (B,) bool, the patches to use (e.g. the assessable ones); None: all. Another dtype: ``TypeError``.
        knots: strictly increasing from 0 to 1.
        min_values: values a knot needs for its own RMS, an int ≥ 1 (another type: ``TypeError``).
        data: description of the calibration set.
    """
    est, tru = torch.as_tensor(estimate).double(), torch.as_tensor(truth).double()
    if est.shape != tru.shape or est.numel() == 0:
        raise ValueError(f"estimate {tuple(est.shape)} and truth {tuple(tru.shape)} must have the same non-empty shape")
    if not (torch.isfinite(est).all() and torch.isfinite(tru).all()):
        raise ValueError("estimate and truth must be finite")
    if isinstance(min_values, bool) or not isinstance(min_values, numbers.Integral):
        raise TypeError(f"min_values must be an int (values per knot), got {min_values!r} ({type(min_values).__name__})")
    if min_values < 1:
        raise ValueError(f"min_values = {min_values} must be ≥ 1")
    min_values = int(min_values)
    if valid is not None:
        valid = torch.as_tensor(valid)
        if valid.dtype != torch.bool:
            raise TypeError(f"valid must be a bool tensor (one flag per patch), got dtype {valid.dtype}; a float or "
                            f"integer mask is not cast (use mask > 0 if that is what is meant)")
        if valid.shape != est.shape[:1]:
            raise ValueError(f"valid {tuple(valid.shape)} must be ({est.shape[0]},), one flag per patch")
        est, tru = est[valid], tru[valid]
    kn = torch.tensor([float(k) for k in knots], dtype=torch.float64)
    MTFErrorTable(tuple(kn.tolist()), (0.0,) * kn.numel(), 1)  # validates the knots
    e, t = est.flatten(), tru.flatten()
    nearest = (e[:, None] - kn[None]).abs().argmin(1)
    counts = torch.bincount(nearest, minlength=kn.numel())
    sq = torch.zeros(kn.numel(), dtype=torch.float64).index_add_(0, nearest, (e - t) ** 2)
    ok = counts >= min_values
    if not bool(ok.any()):
        raise ValueError(f"no knot has min_values = {min_values} values ({int(e.numel())} values in all)")
    rms = (sq[ok] / counts[ok]).sqrt()
    full = _interp(kn, kn[ok], rms) if int(ok.sum()) > 1 else rms.expand(kn.numel())
    return MTFErrorTable(tuple(kn.tolist()), tuple(full.clamp(0, 1).tolist()), int(e.numel()), data)


def shared_error_fraction(frames: Sequence[tuple[torch.Tensor, torch.Tensor]], table: MTFErrorTable) -> float:
    """ρ: the share of the error variance that the patches of one frame have in common (module docstring).

    Args:
        frames: per frame ``(estimate, truth)`` of its assessable patches, (n, 16) each (the same truth on every row:
            one blur per frame); frames with fewer than two patches add nothing.
        table: the error table that standardises each value's error by r(Ĥ).

    Returns:
        Σ over frames of Σ_{i≠j} z_i·z_j over Σ over the same frames of (n − 1)·Σ_i z_i² (per value, pooled over the
        16), clamped to [0, 1]; z = (Ĥ − H)/r(Ĥ). 0 without a frame of two patches.

    Raises:
        TypeError: ``table`` is not an :class:`MTFErrorTable`.
        ValueError: a frame whose estimate and truth differ in shape or hold NaN/inf (naming the frame).
    """
    if not isinstance(table, MTFErrorTable):
        raise TypeError(f"table must be an MTFErrorTable, got {type(table).__name__}")
    cross = norm = 0.0
    for k, (est, tru) in enumerate(frames):
        est, tru = torch.as_tensor(est).double(), torch.as_tensor(tru).double()
        if est.shape != tru.shape or est.ndim != 2:
            raise ValueError(f"estimate {tuple(est.shape)} and truth {tuple(tru.shape)} must be the same (n, K) shape")
        if not (bool(torch.isfinite(est).all()) and bool(torch.isfinite(tru).all())):
            raise ValueError(f"frames[{k}]: estimate and truth must be finite, got NaN/inf")
        n = est.shape[0]
        if n < 2:
            continue
        z = (est - tru) / table(est).double().clamp_min(1e-3)
        total = z.sum(0)
        cross += float((total.square() - z.square().sum(0)).sum())
        norm += float((n - 1) * z.square().sum())
    return min(max(cross / norm, 0.0), 1.0) if norm > 0 else 0.0


def _count(n: object) -> int:
    """``n`` as an int ≥ 1 (an integer-valued float or numpy integer is accepted); else ``ValueError`` naming it."""
    ok = not isinstance(n, bool) and isinstance(n, (numbers.Integral, float)) and math.isfinite(n) and n == int(n) and n >= 1
    if not ok:
        raise ValueError(f"n = {n!r} must be an integer ≥ 1 (a count of values)")
    return int(n)


def frame_uncertainty(estimator_std: torch.Tensor, n: int, shared: float) -> torch.Tensor:
    """Standard error of the median of ``n`` patches of one scene whose values each have the uncertainty
    ``estimator_std`` (u) and share the part ``shared`` (ρ) of its variance: u·√(ρ + (π/2)(1 − ρ)/n).

    With each value's error √ρ·u·z₀ + √(1 − ρ)·u·z_i (z standard normal, z₀ common to the scene) the median is
    √ρ·u·z₀ + √(1 − ρ)·u·median(z_i); (π/2)/n is the large-n variance of the median of n standard normals, the same
    form the monitor's other standard errors of a median use. It overstates the exact variance for few values (by
    25 % in the standard error at n = 1 and 2, about 10 % at n = 6), so the stated uncertainty errs on the safe side.

    ``estimator_std`` must be ≥ 0 (NaN: not known, and the result NaN there); ``shared`` a number (not a bool) in [0, 1].
    """
    n = _count(n)
    if isinstance(shared, bool) or not isinstance(shared, numbers.Real):
        raise TypeError(f"shared must be a number in [0, 1], got {shared!r} ({type(shared).__name__})")
    if not 0.0 <= shared <= 1.0:
        raise ValueError(f"shared = {shared} must lie in the allowed range [0, 1]")
    u = torch.as_tensor(estimator_std).float()
    if u.device.type != "meta" and bool(((u < 0) | torch.isinf(u)).any()):
        bad = u[(u < 0) | torch.isinf(u)].flatten()[0].item()
        raise ValueError(f"estimator_std must be an uncertainty (≥ 0, or NaN where not known), got {bad:g}")
    return u * math.sqrt(float(shared) + (math.pi / 2.0) * (1.0 - float(shared)) / n)
