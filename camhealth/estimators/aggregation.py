"""Temporal and spatial median aggregation of patch-wise estimates (thesis Sec. 5.6, Eq. 5.4–5.5).

When the corruption is stationary over a few frames (or over the image), the patch-wise estimates
σ̂^(k)(i, j) of consecutive frames k can be aggregated by their median (Eq. 5.4)::

    σ̃_n(i, j) = median(σ̂^(1)(i, j), …, σ̂^(n)(i, j))

over a window of n consecutive frames; the median ignores the outliers of single frames (over-exposed
or texture-rich content). :func:`temporal_median` computes it for every window position at once (a
strided view of the frame axis, no loop), together with the **spread** of the estimates inside each
window — ``1.4826 · median(|σ̂ − σ̃|)`` (the median absolute deviation, scaled to equal the standard
deviation for Gaussian scatter) — and the min/max of the window, as an uncertainty estimate that comes
with every aggregated value. :func:`spatial_median` does the same over the patches of one frame (or any
dimension), and both accept NaN for patches that could not be assessed. Float16/bfloat16 estimates are aggregated
in float32 and returned in their own dtype.

The thesis measures the benefit by the dispersion of the distribution P_σ̃n of all aggregated estimates:
its standard deviation σ_σ̃n, and the change ``Δ_{1→n} = σ_σ̃1 − σ_σ̃n`` (Eq. 5.5, Tab. 5.3).
:func:`uncertainty_by_window` returns both for a list of window sizes (default ``A_n`` = {1, 2, 4, 10,
20, 40, 100}, those that fit the sequence).

Units are those of the estimates (DN for noise levels, dimensionless for MTF values). All functions
are pure and batched.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Sequence

import torch

from camhealth._validation import FLOAT_DTYPES, check_choice, check_tensor

__all__ = ["WINDOW_SIZES", "MAD_TO_STD", "Aggregate", "temporal_median", "spatial_median", "uncertainty_by_window"]

#: Aggregation window sizes A_n of the thesis (frames).
WINDOW_SIZES: tuple[int, ...] = (1, 2, 4, 10, 20, 40, 100)
#: 1 / Φ⁻¹(0.75): scales a median absolute deviation to a standard deviation for Gaussian scatter.
MAD_TO_STD: float = 1.4826022185056018


@dataclass
class Aggregate:
    """Median-aggregated estimates with their uncertainty; all tensors have the same shape.

    Attributes:
        median: the aggregated estimate σ̃_n (Eq. 5.4), NaN where a window held no finite estimate.
        spread: 1.4826 · median absolute deviation inside the window (0 for a single estimate).
        low, high: smallest and largest finite estimate inside the window.
        count: number of finite estimates that went into each value.
    """

    median: torch.Tensor
    spread: torch.Tensor
    low: torch.Tensor
    high: torch.Tensor
    count: torch.Tensor


def _check_estimates(x: object, name: str) -> torch.Tensor:
    """A floating tensor of estimates in their own unit (DN, dimensionless MTF …); NaN allowed, ±inf not."""
    x = check_tensor(x, name)
    if x.dtype not in FLOAT_DTYPES:  # estimates are not images: no "/ 255" hint, their unit stays as it is
        raise TypeError(f"{name} must be a floating tensor (float16, bfloat16, float32 or float64), got dtype {x.dtype}; "
                        f"convert with {name}.float() (the values keep their unit)")
    if bool(torch.isinf(x).any()):
        raise ValueError(f"{name} must not hold ±inf (use NaN for patches that could not be assessed)")
    return x


def _check_dim(dim: object, ndim: int, name: str = "dim") -> int:
    """``dim`` as an axis index in [0, ndim): an int (NumPy integers too, not a bool) in [−ndim, ndim)."""
    if isinstance(dim, bool) or not isinstance(dim, numbers.Integral):
        raise TypeError(f"{name} must be an int (an axis), got {dim!r} ({type(dim).__name__})")
    d = int(dim)
    if not -ndim <= d < ndim:
        raise ValueError(f"{name} = {d} is out of range for a {ndim}-D tensor (allowed [{-ndim}, {ndim - 1}])")
    return d % ndim


def _check_count(v: object, name: str, low: int, high: int | None, what: str) -> int:
    """``v`` as an int (NumPy integers too, not a bool) in [low, high] (high None: no upper limit)."""
    if isinstance(v, bool) or not isinstance(v, numbers.Integral):
        raise TypeError(f"{name} must be an int, got {v!r} ({type(v).__name__})")
    v = int(v)
    if v < low or (high is not None and v > high):
        raise ValueError(f"{name} = {v} is out of the allowed range [{low}, {high if high is not None else 'inf'}] ({what})")
    return v


#: Longest row ``torch.nanquantile`` reduces (2²⁴ values; beyond it raises "input tensor is too large").
_QUANTILE_LIMIT = 2**24


def _nanmedian_last(w: torch.Tensor) -> torch.Tensor:
    """``torch.nanquantile(w, 0.5, dim=-1)`` (the mean of the two middle values of an even count, NaN where a row holds
    none), also for rows longer than :data:`_QUANTILE_LIMIT`, which torch refuses: those are sorted (NaN last) and
    the middle values read by index."""
    if w.shape[-1] <= _QUANTILE_LIMIT:
        return torch.nanquantile(w, 0.5, dim=-1)
    ordered = w.sort(dim=-1).values  # NaN sorts last
    n = (~torch.isnan(w)).sum(dim=-1, keepdim=True)
    lo, hi = ((n - 1) // 2).clamp_min(0), (n // 2).clamp_min(0)
    a, b = ordered.gather(-1, lo), ordered.gather(-1, hi)
    med = (a + 0.5 * (b - a)).squeeze(-1)
    return torch.where(n.squeeze(-1) > 0, med, torch.full_like(med, float("nan")))


def _reduce_last(w: torch.Tensor) -> Aggregate:
    """Median, spread, min, max and count over the last dim, ignoring NaN (NaN and count 0 where nothing is left,
    an empty last dim included). Half-precision estimates are reduced in float32 (torch.nanquantile needs it) and the
    results cast back to their dtype."""
    if w.dtype in (torch.float16, torch.bfloat16):
        agg = _reduce_last(w.float())
        return Aggregate(median=agg.median.to(w.dtype), spread=agg.spread.to(w.dtype), low=agg.low.to(w.dtype),
                         high=agg.high.to(w.dtype), count=agg.count)
    if w.shape[-1] == 0 or w.numel() == 0:  # nothing to reduce (no patches or frames): NaN, count 0
        nan = torch.full(w.shape[:-1], float("nan"), dtype=w.dtype, device=w.device)
        return Aggregate(median=nan, spread=nan.clone(), low=nan.clone(), high=nan.clone(),
                         count=torch.zeros(w.shape[:-1], dtype=torch.int64, device=w.device))
    med = _nanmedian_last(w)
    mad = _nanmedian_last((w - med[..., None]).abs())
    finite = torch.isfinite(w)
    low = torch.where(finite, w, torch.full_like(w, float("inf"))).amin(dim=-1)
    high = torch.where(finite, w, torch.full_like(w, float("-inf"))).amax(dim=-1)
    count = finite.sum(dim=-1)
    none = count == 0
    nan = torch.full_like(med, float("nan"))
    return Aggregate(
        median=med,
        spread=torch.where(none, nan, MAD_TO_STD * mad),
        low=torch.where(none, nan, low),
        high=torch.where(none, nan, high),
        count=count,
    )


def temporal_median(estimates: torch.Tensor, window: int, stride: int = 1, dim: int = 0) -> Aggregate:
    """Median over windows of ``window`` consecutive frames along ``dim`` (Eq. 5.4).

    Args:
        estimates: per-frame estimates, frames along ``dim`` (e.g. (T, P) patches per frame, or (T, P, 16)
            MTFs); NaN = not assessable.
        window: n >= 1 frames per window (at most the number of frames T).
        stride: step between window starts: 1 = a sliding (moving) median with one value per frame from
            frame n − 1 on, ``window`` = non-overlapping windows.
        dim: the frame axis, in [−ndim, ndim) (an int; out of range: ``ValueError``). An empty frame axis (no
            frames) raises ``ValueError``.

    Returns:
        :class:`Aggregate` whose frame axis has ``(T − n) // stride + 1`` entries (window k covers frames
        ``k·stride … k·stride + n − 1``); the other axes are unchanged.
    """
    x = _check_estimates(estimates, "estimates")
    if x.ndim == 0:
        raise ValueError("estimates must have a frame axis, got a scalar")
    dim = _check_dim(dim, x.ndim)
    t = x.shape[dim]
    if t == 0:
        if isinstance(window, bool) or not isinstance(window, numbers.Integral):
            raise TypeError(f"window must be an int, got {window!r} ({type(window).__name__})")
        raise ValueError(f"estimates have no frames along dim {dim} (shape {tuple(x.shape)}): nothing to aggregate")
    window = _check_count(window, "window", 1, t, f"frames: {t}")
    stride = _check_count(stride, "stride", 1, None, f"frames: {t}")
    windows = x.unfold(dim, window, stride)  # frame axis → number of windows, window contents last
    agg = _reduce_last(windows)
    return agg


def spatial_median(estimates: torch.Tensor, dim: int | Sequence[int] = -1) -> Aggregate:
    """Median over patches: reduce ``dim`` (one or several axes, e.g. the patch axis of (T, P)).

    The spatial counterpart of Eq. 5.4 (Sec. 5.7): for a corruption that is constant over the image,
    the median over the patches of one frame, with the same spread/min/max/count as :func:`temporal_median`.
    ``dim``: an int or a sequence of ints, each in [−ndim, ndim) (``TypeError`` for another type, ``ValueError`` out of
    range or for an axis named twice).
    """
    x = _check_estimates(estimates, "estimates")
    if x.ndim == 0:
        raise ValueError("estimates must have at least one axis to aggregate, got a scalar")
    if isinstance(dim, (str, bytes)) or not (isinstance(dim, numbers.Integral) or hasattr(dim, "__iter__")):
        raise TypeError(f"dim must be an int or a sequence of ints (axes), got {dim!r} ({type(dim).__name__})")
    dims = [_check_dim(d, x.ndim) for d in ([dim] if isinstance(dim, numbers.Integral) else list(dim))]
    if len(set(dims)) != len(dims):
        raise ValueError(f"dim = {dim} names an axis twice")
    keep = [d for d in range(x.ndim) if d not in dims]
    moved = x.permute(*keep, *dims).reshape(*[x.shape[d] for d in keep], math.prod(x.shape[d] for d in dims))
    return _reduce_last(moved)


def uncertainty_by_window(
    estimates: torch.Tensor,
    windows: Sequence[int] = WINDOW_SIZES,
    stride: str = "sliding",
    dim: int = 0,
) -> dict[int, dict[str, float]]:
    """Dispersion of the aggregated estimates versus the window size (Eq. 5.5, Tab. 5.3).

    For every n in ``windows`` (ints; sizes outside [1, T] are skipped) that fits the T frames: aggregate with :func:`temporal_median`
    (``stride="sliding"``: one window per frame position; ``"disjoint"``: non-overlapping windows) and
    pool all aggregated values (every window position and patch) into P_σ̃n. Returns, per n,
    ``{"std": σ_σ̃n, "median": median of P_σ̃n, "delta": Δ_{1→n} = σ_σ̃1 − σ_σ̃n, "mean_spread": mean
    in-window spread, "n_values": number of aggregated values}`` (std is the population standard deviation
    over the finite values).
    """
    check_choice(stride, "stride", ("sliding", "disjoint"))
    x = _check_estimates(estimates, "estimates")
    if x.ndim == 0:
        raise ValueError("estimates must have a frame axis, got a scalar")
    for n in windows:
        if isinstance(n, bool) or not isinstance(n, numbers.Integral):
            raise TypeError(f"every window must be an int (frames), got {n!r} ({type(n).__name__})")
    dim = _check_dim(dim, x.ndim)
    t = x.shape[dim]
    sizes = sorted({int(n) for n in windows if 1 <= n <= t} | {1})
    out: dict[int, dict[str, float]] = {}
    for n in sizes:  # a handful of window sizes, each one vectorised
        agg = temporal_median(x, n, stride=1 if stride == "sliding" else n, dim=dim)
        vals = agg.median[torch.isfinite(agg.median)].double()
        std = float(vals.std(unbiased=False)) if vals.numel() else float("nan")
        out[n] = {
            "std": std,
            "median": float(vals.median()) if vals.numel() else float("nan"),
            "mean_spread": float(torch.nanmean(agg.spread.double())) if agg.spread.numel() else float("nan"),
            "n_values": int(vals.numel()),
        }
    base = out[1]["std"]
    for n in out:
        out[n]["delta"] = base - out[n]["std"]
    return out
