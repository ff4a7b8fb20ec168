"""torchmetrics accumulators for the estimators' validation metrics.

- :class:`NoiseErrorStats` — Bias = |E[σ − σ̂]|, Std = std(σ̂ − σ), RMS = √(Bias² + Std²) in DN per output
  column (conventions.md, thesis Eq. 6.2), accumulated as running sums so it syncs across processes; NaN without
  samples (no data, not a perfect score).
- :class:`AMAEPerFamily` — AMAE (Eq. 5.1): mean over H and V of the mean absolute MTF error over the 8
  frequencies, in %, averaged per blur family (defocus, linear motion, non-linear motion) and overall; NaN for a
  family without samples (no data, not a perfect score).

The accumulators are float64 at every training precision: a cast of the module (Lightning's ``bf16-true`` and
``64-true``: ``module.to(dtype)``, ``.half()``, ``.double()``) moves them to the module's device and leaves their
dtype alone (:class:`Float64States`).
"""

from __future__ import annotations

from typing import Sequence

import torch
from torchmetrics import Metric

from camhealth import metrics as _metrics

__all__ = ["Float64States", "NoiseErrorStats", "AMAEPerFamily", "bias_std_rms", "amae_percent"]


def bias_std_rms(estimate: torch.Tensor, truth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(Bias, Std, RMS) of ``estimate − truth`` along dim 0 in float64 (Eq. 6.2; Std is the population std): the
    tuple form of :func:`camhealth.metrics.bias_std_rms` (finite inputs)."""
    r = _metrics.bias_std_rms(estimate.double(), truth.double(), dim=0)
    return r["bias"], r["std"], r["rms"]


def amae_percent(estimate: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Per-sample AMAE [%] of (B, 16) MTFs (H then V): mean of the H and V mean absolute errors × 100
    (:func:`camhealth.metrics.amae`)."""
    return _metrics.amae(estimate, truth)


class Float64States(Metric):
    """A torchmetrics ``Metric`` whose states keep their dtype (float64 sums and counts) when the module holding it
    is cast: torchmetrics guards its states against ``.half()`` / ``.float()`` / ``.double()`` only, not against
    ``module.to(torch.bfloat16)`` (what Lightning's ``bf16-true`` does), under which a count stops growing at 256
    and ``index_add_`` refuses float64 sources. A move to another device still moves them."""

    def _apply(self, fn, exclude_state=()):  # type: ignore[override]
        states = tuple(self._defaults)
        this = super()._apply(fn, exclude_state=(*exclude_state, *states))
        device = this.device  # (where torchmetrics moved its own bookkeeping)
        for key in states:
            default = this._defaults[key]
            if isinstance(default, torch.Tensor):
                this._defaults[key] = default.to(device)
                setattr(this, key, getattr(this, key).to(device))
        return this


class NoiseErrorStats(Float64States):
    """Accumulates Bias/Std/RMS (DN) for ``names`` columns of (B, n) estimates against (B, n) truths. A truth that is
    NaN/inf is a ``ValueError`` naming it (it would make every result NaN/inf); without samples every result is NaN
    (no data, not a perfect score), as :class:`AMAEPerFamily` gives it."""

    full_state_update = False

    def __init__(self, names: Sequence[str]) -> None:
        super().__init__()
        self.names = tuple(names)
        n = len(self.names)
        self.add_state("sum_e", default=torch.zeros(n, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("sum_e2", default=torch.zeros(n, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("count", default=torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, estimate: torch.Tensor, truth: torch.Tensor) -> None:  # type: ignore[override]
        if estimate.shape != truth.shape or estimate.ndim != 2 or estimate.shape[1] != len(self.names):
            raise ValueError(
                f"estimate {tuple(estimate.shape)} and truth {tuple(truth.shape)} must both be (B, {len(self.names)})"
            )
        if not bool(torch.isfinite(truth.detach()).all()):
            t = truth.detach()
            bad = ~torch.isfinite(t)
            column = self.names[int(bad.nonzero()[0, 1])]
            raise ValueError(f"truth must be finite for Bias/Std/RMS, but {int(bad.sum())} of {t.numel()} values are NaN/inf "
                             f"(first: {t[bad][0].item()}, column {column!r})")
        e = (estimate.detach() - truth.detach()).double()
        self.sum_e += e.sum(0)
        self.sum_e2 += e.pow(2).sum(0)
        self.count += e.shape[0]

    def compute(self) -> dict[str, torch.Tensor]:  # type: ignore[override]
        n = self.count.clamp_min(1)
        mean = self.sum_e / n
        std = (self.sum_e2 / n - mean.pow(2)).clamp_min(0).sqrt()
        rms = (mean.pow(2) + std.pow(2)).sqrt()
        if not bool(self.count > 0):  # no samples: no data, not a perfect 0
            mean, std, rms = (torch.full_like(v, float("nan")) for v in (mean, std, rms))
        out: dict[str, torch.Tensor] = {}
        for i, name in enumerate(self.names):
            out[f"bias_{name}"] = mean[i].abs().float()
            out[f"std_{name}"] = std[i].float()
            out[f"rms_{name}"] = rms[i].float()
        return out


class AMAEPerFamily(Float64States):
    """AMAE [%] per blur family and over all samples. ``family`` holds each sample's index into ``families``; an
    index outside them is a ``ValueError`` naming it. A family without samples (or no samples at all) gives NaN."""

    full_state_update = False

    def __init__(self, families: Sequence[str] = ("defocus", "linear", "nonlinear")) -> None:
        super().__init__()
        self.families = tuple(families)
        k = len(self.families)
        self.add_state("sum_amae", default=torch.zeros(k, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("count", default=torch.zeros(k, dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, estimate: torch.Tensor, truth: torch.Tensor, family: torch.Tensor) -> None:  # type: ignore[override]
        if estimate.shape != truth.shape or estimate.ndim != 2 or estimate.shape[1] != 16:
            raise ValueError(f"estimate {tuple(estimate.shape)} and truth {tuple(truth.shape)} must both be (B, 16)")
        k = len(self.families)
        if family.numel() != estimate.shape[0]:
            raise ValueError(f"family has {family.numel()} labels for {estimate.shape[0]} samples")
        labels = family.detach().reshape(-1)
        bad = (labels < 0) | (labels >= k)
        if labels.is_floating_point():
            bad |= labels != labels.floor()  # (NaN included)
        if bool(bad.any()):
            value = labels[bad][0].item()
            raise ValueError(f"family label {value!r} is not a family index 0..{k - 1} (families {list(self.families)})")
        fam = labels.long()
        a = amae_percent(estimate.detach().double(), truth.detach().double())
        self.sum_amae.index_add_(0, fam, a)
        self.count.index_add_(0, fam, torch.ones_like(a))

    def compute(self) -> dict[str, torch.Tensor]:  # type: ignore[override]
        nan = torch.full_like(self.sum_amae, float("nan"))
        per_family = torch.where(self.count > 0, self.sum_amae / self.count.clamp_min(1), nan)
        out = {f"amae_{f}": per_family[i].float() for i, f in enumerate(self.families)}
        total = self.count.sum()
        out["amae"] = (self.sum_amae.sum() / total if total > 0 else nan[0]).float()
        return out
