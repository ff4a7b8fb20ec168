"""Camera shake as a random walk with inertia and impulsive jerks (after Boracchi & Foi 2012), rasterised exactly.

A second camera-shake model, of a different style from the smoothed heading walk of
:func:`camhealth.physics.nonlinear_motion_psf`: the camera position x_t (complex, px) moves with a velocity v_t of
constant speed whose change per step is

    ``Δv = a·(n_x + i·n_y) − c·x_t + J_t``,

with Gaussian "anxiety" noise n (weight a), a centripetal pull towards the start (weight c) that keeps the path
compact, and an impulsive jerk J_t = −2 v_t·e^{iπ(u − ½)} (a sharp turn of roughly 180° ± 90°, u uniform) drawn
with probability ``p_jerk`` per step. Every step is then rescaled to unit length, so the path is a polyline of
equal-duration, equal-length steps.

:func:`sample_random_walk` draws the trajectories (the only random function, seeded by a ``torch.Generator``);
:func:`trajectory_psf` is deterministic: it rescales any polyline to arc length L, centres its bounding box
on the kernel centre and rasterises it with the exact line/pixel-square coverage of
:mod:`camhealth.physics.motion_psf` (the same size policy: L ≤ k guarantees no mass is clipped). Kernels sum to 1.
"""

from __future__ import annotations

import math
import numbers

import torch

from camhealth._validation import check_finite, check_float, check_odd_kernel_size, check_tensor
from camhealth.physics._psf_common import batch_of, check_generator, positive_vector
from camhealth.physics.defocus_psf import _out_dtype, _work_dtype
from camhealth.physics.motion_psf import _check_length, _rasterise_polyline

__all__ = ["sample_random_walk", "trajectory_psf"]


def sample_random_walk(
    batch_size: int,
    n_steps: int = 64,
    anxiety: float = 0.3,
    centripetal: float = 0.005,
    p_jerk: float = 0.03,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
) -> torch.Tensor:
    """Draw B random-walk shake trajectories → (B, n_steps + 1, 2) vertices (x right, y down), unit step length.

    Args:
        batch_size: B ≥ 1. n_steps: steps N ≥ 2.
        anxiety: weight a of the Gaussian velocity noise, in [0, 2]. centripetal: weight c of the pull towards
            the start, in [0, 1]. p_jerk: probability of an impulsive jerk per step, in [0, 1].
        generator: ``torch.Generator`` (CPU) for reproducibility.
        dtype: floating dtype of the result.
    """
    for name, v, low in (("batch_size", batch_size, 1), ("n_steps", n_steps, 2)):
        if isinstance(v, bool) or not isinstance(v, numbers.Integral):  # (NumPy integers too, as kernel_size)
            raise TypeError(f"{name} must be an int, got {type(v).__name__}")
        if v < low:
            raise ValueError(f"{name} = {v} is out of the allowed range [{low}, inf)")
    batch_size, n_steps = int(batch_size), int(n_steps)
    check_generator(generator)
    for name, v, hi in (("anxiety", anxiety, 2.0), ("centripetal", centripetal, 1.0), ("p_jerk", p_jerk, 1.0)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not 0.0 <= v <= hi:
            raise ValueError(f"{name} = {v!r} is out of the allowed range [0, {hi}]")
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"dtype must be a floating torch.dtype, got {dtype}")
    b, n = batch_size, n_steps
    noise = torch.randn(b, n, 2, generator=generator, dtype=torch.float64)
    u = torch.rand(b, n, 2, generator=generator, dtype=torch.float64)
    phi0 = 2.0 * math.pi * torch.rand(b, generator=generator, dtype=torch.float64)
    v = torch.polar(torch.ones(b, dtype=torch.float64), phi0)
    x = torch.zeros(b, dtype=torch.complex128)
    path = [x]
    for t in range(n):
        jerk = torch.where(u[:, t, 0] < p_jerk, -2.0 * v * torch.polar(torch.ones(b, dtype=torch.float64), math.pi * (u[:, t, 1] - 0.5)),
                           torch.zeros_like(v))
        dv = anxiety * torch.complex(noise[:, t, 0], noise[:, t, 1]) - centripetal * x + jerk
        v = v + dv
        mag = v.abs()
        v = torch.where(mag > 1e-12, v / mag.clamp_min(1e-12), torch.polar(torch.ones(b, dtype=torch.float64), phi0))
        x = x + v
        path.append(x)
    p = torch.stack(path, dim=1)
    return torch.stack([p.real, p.imag], dim=-1).to(dtype)


def trajectory_psf(trajectory: torch.Tensor, length_px: torch.Tensor, kernel_size: int) -> torch.Tensor:
    """Kernels of polyline trajectories moved at uniform speed along their arc, scaled to arc length L.

    Args:
        trajectory: (B, M + 1, 2) vertices (x right, y down) in any unit, M ≥ 1 segments, a non-zero arc length
            (more than 1e-12 of the largest vertex coordinate: not vertices that differ by rounding alone).
        length_px: (B,) arc length L in px, in [0, kernel_size].
        kernel_size: odd kernel side k in px.

    Returns:
        (B, k, k) kernels summing to 1 (L = 0: the delta kernel), the path's bounding box on the kernel centre;
        float64 if an input is float64, else float32.
    """
    k = check_odd_kernel_size(kernel_size)
    tr = check_float(check_tensor(trajectory, "trajectory"), "trajectory")
    if tr.ndim != 3 or tr.shape[-1] != 2 or tr.shape[1] < 2 or tr.shape[0] < 1:
        raise ValueError(f"trajectory must have shape (B, M + 1 ≥ 2, 2), got {tuple(tr.shape)}")
    check_finite(tr, "trajectory")
    length = positive_vector(length_px, "length_px", 0.0, float("inf"), "px")
    _check_length(length, k)
    b = batch_of(length, tr)
    work = _work_dtype(tr.device)
    out_dtype = _out_dtype(length, tr)
    tr = tr.to(work).expand(b, *tr.shape[1:])
    seg = (tr[:, 1:] - tr[:, :-1]).norm(dim=-1)  # (B, M)
    arc = seg.sum(1)
    # relative to the coordinates' magnitude ("any unit": a path of 1e-20 m is a path), 0 where all vertices are 0
    if bool((arc <= 1e-12 * tr.abs().flatten(1).amax(1)).any()):
        raise ValueError("trajectory must have a non-zero arc length (all its vertices coincide, to within 1e-12 of "
                         "their coordinates)")
    scaled = tr * (length.to(work).expand(b) / arc)[:, None, None].to(tr.device)
    centre = 0.5 * (scaled.amax(dim=1, keepdim=True) + scaled.amin(dim=1, keepdim=True))
    weights = seg / arc[:, None]  # uniform speed along the arc: each segment's share of the exposure
    psf = _rasterise_polyline(scaled - centre, weights, k)
    total = psf.sum(dim=(-2, -1), keepdim=True)
    return (psf / total).to(out_dtype)
