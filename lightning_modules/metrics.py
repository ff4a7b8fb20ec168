"""torchmetrics accumulators for the estimators' validation metrics.

- :class:`NoiseErrorStats` — Bias = |E[σ − σ̂]|, Std = std(σ̂ − σ), RMS = √(Bias² + Std²) in DN per output
  column (conventions.md, thesis Eq. 6.2), accumulated as running sums so it syncs across processes.
- :class:`AMAEPerFamily` — AMAE (Eq. 5.1): mean over H and V of the mean absolute MTF error over the 8
  frequencies, in %, averaged per blur family (defocus, linear motion, non-linear motion) and overall.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torchmetrics import Metric

__all__ = ["NoiseErrorStats", "AMAEPerFamily", "bias_std_rms", "amae_percent"]


def bias_std_rms(estimate: torch.Tensor, truth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(Bias, Std, RMS) of ``estimate − truth`` along dim 0 in float64 (Eq. 6.2; Std is the population std):
    :func:`camhealth.metrics.bias_std_rms` as a tuple."""
    from camhealth.metrics import bias_std_rms as _bias_std_rms

    r = _bias_std_rms(estimate.double(), truth.double(), dim=0)
    return r["bias"], r["std"], r["rms"]


def amae_percent(estimate: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Per-sample AMAE [%] of (B, 16) MTFs (H then V): mean of the H and V mean absolute errors × 100."""
    err = (estimate - truth).abs().view(-1, 2, 8).mean(2)
    return err.mean(1) * 100.0


class NoiseErrorStats(Metric):
    """Accumulates Bias/Std/RMS (DN) for ``names`` columns of (B, n) estimates against (B, n) truths."""

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
        e = (estimate.detach() - truth.detach()).double()
        self.sum_e += e.sum(0)
        self.sum_e2 += e.pow(2).sum(0)
        self.count += e.shape[0]

    def compute(self) -> dict[str, torch.Tensor]:  # type: ignore[override]
        n = self.count.clamp_min(1)
        mean = self.sum_e / n
        std = (self.sum_e2 / n - mean.pow(2)).clamp_min(0).sqrt()
        rms = (mean.pow(2) + std.pow(2)).sqrt()
        out: dict[str, torch.Tensor] = {}
        for i, name in enumerate(self.names):
            out[f"bias_{name}"] = mean[i].abs().float()
            out[f"std_{name}"] = std[i].float()
            out[f"rms_{name}"] = rms[i].float()
        return out


class AMAEPerFamily(Metric):
    """AMAE [%] per blur family and over all samples."""

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
        a = amae_percent(estimate.detach().double(), truth.detach().double())
        fam = family.long().clamp(0, len(self.families) - 1)
        self.sum_amae.index_add_(0, fam, a)
        self.count.index_add_(0, fam, torch.ones_like(a))

    def compute(self) -> dict[str, torch.Tensor]:  # type: ignore[override]
        out = {f"amae_{f}": (self.sum_amae[i] / self.count[i].clamp_min(1)).float() for i, f in enumerate(self.families)}
        out["amae"] = (self.sum_amae.sum() / self.count.sum().clamp_min(1)).float()
        return out
