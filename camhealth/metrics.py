"""Error metrics of the thesis: AMAE for MTF estimates (Eq. 5.1) and Bias/Std/RMS for noise levels (Eq. 6.2).

**AMAE** (Eq. 5.1). For an estimated and a ground-truth MTF sampled at the 8 normalised frequencies
f_i in the horizontal (H) and vertical (V) direction — camhealth's ``(…, 16)`` layout ``[H×8, V×8]``::

    MAE(w) = 1/8 · Σ_i |MTF_w^GT(f_i) − MTF^_w(f_i)|,   w ∈ {H, V}
    AMAE   = 1/2 · (MAE(H) + MAE(V))

reported in **%** (× 100; MTF values are dimensionless in [0, 1]). Frequencies whose estimate is NaN
(e.g. omitted by the preconditions of :mod:`camhealth.estimators.blur_under_noise`) are left out of the
mean of their direction; a direction without any valid frequency gives NaN.

**Bias / Std / RMS** (Eq. 6.2 as fixed in ``conventions.md``). For true levels σ and estimates σ̂ in DN::

    Bias = |E[σ − σ̂]|,   Std = std(σ̂ − σ),   RMS = √(Bias² + Std²)

with E the mean over the samples and std the population standard deviation (normalised by N, the
``E[(·)²]`` form of Eq. 6.2), so RMS equals the root-mean-square error √E[(σ̂ − σ)²].

All functions are batched, NaN-aware where documented, and reject bad input with a clear error.
"""

from __future__ import annotations

import torch

from camhealth._validation import check_float, check_tensor
from camhealth.physics.mtf import NORMALIZED_FREQUENCIES

__all__ = ["N_MTF", "mae_hv", "amae", "bias_std_rms", "noise_errors"]

#: Number of MTF values per direction (8) — a label vector holds ``2 * N_MTF`` = 16 values.
N_MTF: int = len(NORMALIZED_FREQUENCIES)


def _pair(pred: object, target: object, name_pred: str, name_target: str) -> tuple[torch.Tensor, torch.Tensor]:
    """``pred`` and ``target`` with ``target`` broadcast to ``pred``'s shape — one way only: a target that would
    enlarge ``pred`` (a (B,) estimate against a (B, 1) truth makes B × B pairs) is refused."""
    p = check_float(check_tensor(pred, name_pred), name_pred)
    t = check_float(check_tensor(target, name_target), name_target)
    try:
        shape = torch.broadcast_shapes(p.shape, t.shape)
    except RuntimeError as err:
        raise ValueError(
            f"{name_pred} {tuple(p.shape)} and {name_target} {tuple(t.shape)} cannot be broadcast together"
        ) from err
    if shape != p.shape:
        raise ValueError(
            f"{name_target} {tuple(t.shape)} must broadcast to {name_pred} {tuple(p.shape)} without enlarging it, but "
            f"together they broadcast to {tuple(shape)} (every {name_pred} paired with every {name_target}); give both "
            "the same shape, e.g. reshape one of them"
        )
    return p, t.expand_as(p)


def mae_hv(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """MAE of Eq. 5.1 per direction, in %: ``(…, 16)`` → ``(…, 2)`` = ``[MAE(H), MAE(V)]``.

    ``target`` (the ground truth) must be finite and of ``pred``'s shape or broadcastable to it without enlarging it
    (one (16,) truth for every row; a (B, 1, 16) target against (B, 16) estimates is refused); NaN entries of ``pred``
    are skipped (see module doc).
    """
    p, t = _pair(pred, target, "pred", "target")
    if p.ndim < 1 or p.shape[-1] != 2 * N_MTF:
        raise ValueError(f"MTF tensors must have shape (..., {2 * N_MTF}) ([H×{N_MTF}, V×{N_MTF}]), got {tuple(p.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise ValueError("target MTF must be finite (NaN/inf found in the ground truth)")
    if bool(torch.isinf(p).any()):
        raise ValueError("pred MTF must not hold ±inf (NaN marks an omitted frequency)")
    err = (p.double() - t.double()).abs().reshape(*p.shape[:-1], 2, N_MTF)
    return (100.0 * torch.nanmean(err, dim=-1)).to(p.dtype)


def amae(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """AMAE of Eq. 5.1 in %: ``(…, 16)`` → ``(…)``, the mean of MAE(H) and MAE(V)."""
    return mae_hv(pred, target).mean(dim=-1)


def bias_std_rms(estimate: torch.Tensor, truth: torch.Tensor, dim: int | tuple[int, ...] | None = None) -> dict[str, torch.Tensor]:
    """Bias, Std and RMS of Eq. 6.2 in the unit of the inputs (DN for noise levels).

    The one implementation in camhealth: :func:`lightning_modules.metrics.bias_std_rms` (the tuple form) calls it,
    and :class:`lightning_modules.metrics.NoiseErrorStats` (torchmetrics, for training) accumulates the same two
    sums, Σe and Σe², so that it syncs across processes. Std is the population std from those sums in float64,
    std² = mean(e²) − mean(e)² (clamped at 0): for errors in DN it loses nothing that matters (a relative error of
    ~1e-16·(bias/std)² in std²).

    Args:
        estimate: σ̂, any shape; truth: σ, of the same shape or broadcastable to it without enlarging it (a (B,)
            estimate against a (B, 1) truth is refused: it would pair every estimate with every truth). Both finite.
        dim: dimension(s) to reduce (the samples); ``None`` reduces everything.

    Returns:
        dict with ``bias`` = |mean(σ − σ̂)|, ``std`` = population std of (σ̂ − σ), ``rms`` = √(bias² + std²)
        and ``n`` (number of samples reduced), computed in float64 and returned in the promoted dtype of the two
        inputs (``torch.promote_types``: the same for either argument order; fp16 with fp64 gives fp64).

    Raises:
        ValueError: shapes as above, NaN/inf, an empty input, or a result that the output dtype cannot hold (|bias|
        or RMS above 65504 for float16 would be inf: pass float32 or float64 inputs).
    """
    e, t = _pair(estimate, truth, "estimate", "truth")
    if e.numel() == 0:
        raise ValueError("bias_std_rms needs at least one sample, got an empty tensor")
    err = e.double() - t.double()
    dims = tuple(range(err.ndim)) if dim is None else dim
    mean = err.mean(dim=dims)
    msq = err.square().mean(dim=dims)
    # a NaN/inf anywhere reaches these sums: checking them is ~20× cheaper than isfinite over every sample
    if not bool(torch.isfinite(msq).all()):
        for x, name in ((e, "estimate"), (t, "truth")):
            if not bool(torch.isfinite(x).all()):
                raise ValueError(f"{name} must be finite for Bias/Std/RMS (found NaN/inf); drop unassessable samples first")
        raise ValueError("the squared errors overflow float64 (|estimate − truth| above ~1e154)")
    std = (msq - mean.square()).clamp_min(0).sqrt()
    n = err.numel() // max(mean.numel(), 1)
    out_dtype = torch.promote_types(e.dtype, t.dtype)
    out = {"bias": mean.abs(), "std": std, "rms": msq.sqrt()}  # rms = √(bias² + std²)
    big = max(float(v.max()) for v in out.values()) if mean.numel() else 0.0
    if big > torch.finfo(out_dtype).max:
        raise ValueError(
            f"Bias/Std/RMS up to {big:.6g} do not fit the output dtype {out_dtype} (largest finite "
            f"{torch.finfo(out_dtype).max:g}); pass the estimates and truths as float32 or float64"
        )
    return {**{k: v.to(out_dtype) for k, v in out.items()}, "n": torch.tensor(n)}


def noise_errors(estimate: torch.Tensor, truth: torch.Tensor) -> dict[str, float]:
    """Bias/Std/RMS (DN) of a flat set of samples as plain floats (for tables and JSON)."""
    r = bias_std_rms(estimate.reshape(-1), truth.reshape(-1))
    return {"bias": float(r["bias"]), "std": float(r["std"]), "rms": float(r["rms"]), "n": int(r["n"])}
