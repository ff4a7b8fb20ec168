"""Two exposures of a static scene: their difference carries the noise and nothing of the scene.

Model (conventions.md): a pixel of frame t reads I_t = S + n_t [DN], the scene S the same in both frames of a
static camera, the noise n_t independent from frame to frame with variance v(S) = a·S + σ_DCSN² + σ_RN² (+ 1/12 DN²
of 8-bit rounding). Then

    (I₁ − I₂)/√2 = (n₁ − n₂)/√2   has variance v(S) at every pixel, and no scene content at all,

while (I₁ + I₂)/2 = S + (n₁ + n₂)/2 is the scene with half the noise variance. One image cannot tell fine scene
content from noise (the *scene floor* of ``python -m camhealth.bench robustness``: 0.8 DN at the median as recorded,
2 DN on busy scenes, as much as a visible mismatch adds); a static pair can.

:func:`static_pair_image` folds the pair into one image the single-image noise statistics read unchanged: the 2×2
block means of the average plus the scaled difference,

    J = B₂[(I₁ + I₂)/2] + (I₁ − I₂)/√2.

B₂ is constant on each 2×2 block, so J's Haar details (diagonal, horizontal, vertical) are exactly those of
(n₁ − n₂)/√2 — white noise of variance v(m), m the block's mean intensity, whatever the scene — and J's block means
are the scene's block means plus the difference's (noise variance v/8 + v/4). A pixel clipped at 0 or 255 DN in
either frame is clipped in J (its difference no longer carries the noise). So a noise estimate of J is a noise
estimate of the camera free of the scene, and where the scene moved or the light changed between the frames, J's details carry
the change — structure that the texture and neighbour checks of
:func:`camhealth.estimators.physics_noise.physics_noise_posterior` refuse.

**Was the scene still?** Noise does not know the scene: a detail's variance depends on the block's intensity alone.
Where the camera or an object moved, the focus changed, or a lossy codec re-quantised the two exposures differently,
the difference carries the scene's change, and two tests look for it:

- :func:`pair_shift` — a shift δ of the scene (camera shake, vibration) makes the difference follow the scene's
  gradient, I₁ − I₂ ≈ δ·∂S/∂x, while for a still pair it is uncorrelated with the average's gradient (n₁ − n₂ and
  n₁ + n₂ are uncorrelated for equal variances). A patch whose correlation along x or y exceeds
  max(:data:`PAIR_SHIFT_LIMIT`, 4/√n) has moved. This sees a tenth of a pixel on a textured patch.
- :func:`scene_leak` — a change that follows no gradient (a focus change, a codec's re-quantisation, a non-rigid
  change) sits where the scene has edges and fine detail. On the pair's diagonal details it compares the mean of
  d²/v̂(m) over the blocks with the steepest scene (the upper quarter of the average's block-mean gradient) with the
  blocks with the flattest (the lower half), v̂(m) = â + b̂·m the pair's own linear NLF. For a still pair the ratio is
  1 within its sampling error; off 1 by more than max(:data:`SCENE_LEAK_LIMIT`, 4 standard errors), either way, the
  pair is not read (below 1: the change sits in fine texture whose block means are flat, and the NLF fit took up
  part of it). It cannot see a change on a texture that is everywhere alike (no flat blocks to compare with).

A third test asks whether the two frames carry the same noise (:func:`pair_noise_balance`): a gain or a readout
that changed between the exposures leaves the scene still but makes the difference read the mean of two noise
levels (a 20 DN reference beside a 5 DN image read 14.6 DN); a patch whose variances differ by more than
:data:`PAIR_NOISE_LIMIT` (relative) beyond 4 standard errors is not read as a pair.

A change of the light between the exposures (I₂ = α·I₁ + β) moves the block means, not the details, and passes
the first two (the third while the shot noise's variance moves by less than the limit). Structure that only the horizontal and vertical details carry (a row-wise change) does not enter the evidence
(the diagonal detail) and is left to the texture check.

**Clipping.** The average A = (I₁ + I₂)/2 and the scaled difference D = (I₁ − I₂)/√2 of equal-variance Gaussian
noise are independent, and neither frame clips exactly where |D| < √2·min(A − ½, 254.5 − A)
(:func:`difference_limits_dn`): given the observed average, a used pixel's difference is a symmetric truncated normal
with a known limit, whatever the scene and however strong the noise. Selecting and binning blocks by A keeps that
model exact, so the noise estimate reads its details at the average's block mean (its flatness test and 3-σ cut,
which read D, move the kept variance by under 1 % at 60 DN).

Fixed-pattern offsets the two frames share (hot pixels, column fixed-pattern noise) cancel in the difference, as the
scene does: the pair measures the temporal noise, which is what the sensor model's sources are.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
import torch

from camhealth._order import sorted_values
from camhealth._validation import check_finite

__all__ = ["static_pair_image", "static_pair_blocks", "difference_limits_dn", "pair_fold", "PairFold", "scene_leak", "SCENE_LEAK_LIMIT", "pair_shift", "PAIR_SHIFT_LIMIT",
           "pair_noise_balance", "PAIR_NOISE_LIMIT", "pair_stillness"]


def _check_pair(image: Any, reference: Any, min_side: int = 3) -> None:
    """Two floating-point B×1×H×W tensors of one shape (H, W ≥ ``min_side``; B = 0 allowed), finite and in [0, 1]
    (DN/255): ``TypeError``/``ValueError`` naming what was given otherwise."""
    if not isinstance(image, torch.Tensor) or not isinstance(reference, torch.Tensor):
        raise TypeError(f"image and reference must be tensors, got {type(image).__name__} and {type(reference).__name__}")
    if image.shape != reference.shape:
        raise ValueError(f"reference must have the image's shape {tuple(image.shape)} (the same patches of another "
                         f"exposure), got {tuple(reference.shape)}")
    if image.ndim != 4 or image.shape[1] != 1 or min(image.shape[-2:]) < min_side:
        raise ValueError(f"image must be a B×1×H×W tensor with H, W ≥ {min_side}, got {tuple(image.shape)}")
    if not image.is_floating_point() or not reference.is_floating_point():
        raise TypeError(f"image and reference must be floating point in [0, 1], got {image.dtype} and {reference.dtype}")
    if image.numel() == 0:
        return
    for x, name in ((image, "image"), (reference, "reference")):
        lo, hi = torch.aminmax(x.detach())  # one reduction: NaN propagates into both, ±inf lands in one
        if not bool(torch.isfinite(lo) & torch.isfinite(hi)):
            check_finite(x, name)  # names how many values are NaN/inf and the first
        if lo < 0 or hi > 1:
            raise ValueError(f"{name} must lie in [0, 1] (DN/255), got values in [{lo.item():g}, {hi.item():g}]")


def static_pair_image(image: torch.Tensor, reference: torch.Tensor, clamp: bool = True) -> torch.Tensor:
    """J = B₂[(I₁ + I₂)/2] + (I₁ − I₂)/√2 of two B×1×H×W exposures of a static scene in [0, 1] (module docstring).

    Args:
        image: B×1×H×W floating-point frame I₁ in [0, 1].
        reference: I₂, the same scene and camera state from another exposure, same shape.
        clamp: J clamped to [0, 1] (an image like any other). The scaled difference swings √2 times as far as either
            frame's noise, so under strong noise J leaves [0, 1] where neither frame clips (σ = 60 DN at mid-grey: 5 %
            of the pixels); a clamp there cuts the difference's tails, and a noise estimate read from the clamped J reads
            low (−8 % at 60 DN). ``False`` keeps those values, as
            :func:`~camhealth.estimators.physics_noise.physics_noise_posterior` reads J (its usable pixels are those of
            :func:`difference_limits_dn`).

    Returns:
        B×1×H×W float32 (in [0, 1] with ``clamp``): its Haar details are the pair's noise alone (variance v(m)
        [DN²/255²]), its 2×2 block means the scene's; 0 or 1 wherever either frame is clipped. An odd last row or
        column keeps the average there (it forms no 2×2 block).
    """
    _check_pair(image, reference, min_side=1)
    x1, x2 = image.detach().float(), reference.detach().float()
    avg = (x1 + x2) * 0.5
    b, c, h, w = avg.shape
    h2, w2 = h // 2 * 2, w // 2 * 2
    out = (x1 - x2) * (1.0 / math.sqrt(2.0))
    if h2 and w2:  # the block means, each spread over its 2×2 block (a view, not a copy)
        blocks = _block_mean(avg[..., :h2, :w2])
        out[..., :h2, :w2] += blocks.view(b, c, h2 // 2, 1, w2 // 2, 1).expand(b, c, h2 // 2, 2, w2 // 2, 2).reshape(b, c, h2, w2)
    if h2 < h:
        out[..., h2:, :] += avg[..., h2:, :]
    if w2 < w:
        out[..., :h2, w2:] += avg[..., :h2, w2:]
    if clamp:
        out.clamp_(0.0, 1.0)
    out.masked_fill_(torch.minimum(x1, x2) <= 0.0, 0.0)
    return out.masked_fill_(torch.maximum(x1, x2) >= 1.0, 1.0)


def _block_max(x: torch.Tensor) -> torch.Tensor:
    """The largest of each 2×2 block of B×C×H×W (H, W even), as ``max_pool2d(x, 2)`` (the same values; 8× faster on
    a 2-core CPU: 0.06 against 0.50 ms for 16 patches of 128 px)."""
    return torch.maximum(torch.maximum(x[..., 0::2, 0::2], x[..., 0::2, 1::2]), torch.maximum(x[..., 1::2, 0::2], x[..., 1::2, 1::2]))


def _block_min(x: torch.Tensor) -> torch.Tensor:
    """The smallest of each 2×2 block of B×C×H×W (H, W even), as ``-max_pool2d(-x, 2)``."""
    return torch.minimum(torch.minimum(x[..., 0::2, 0::2], x[..., 0::2, 1::2]), torch.minimum(x[..., 1::2, 0::2], x[..., 1::2, 1::2]))


def _block_mean(x: torch.Tensor) -> torch.Tensor:
    """The mean of each 2×2 block of B×C×H×W (H, W even), as ``avg_pool2d(x, 2)`` to the last bit or two (a sum of
    four strided views: 0.06 against 0.18 ms for 16 patches of 128 px on a 2-core CPU)."""
    return (x[..., 0::2, 0::2] + x[..., 0::2, 1::2] + x[..., 1::2, 0::2] + x[..., 1::2, 1::2]) * 0.25


def _block_grad2(m: torch.Tensor) -> torch.Tensor:
    """Squared central differences of block means, vertical plus horizontal (0 where a neighbour is missing)."""
    g = torch.zeros_like(m)
    g[..., 1:-1, :] += (m[..., 2:, :] - m[..., :-2, :]).square()
    g[..., :, 1:-1] += (m[..., :, 2:] - m[..., :, :-2]).square()
    return g


def _pair_dn(image: torch.Tensor, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The pair in DN (float32): the scaled difference (I₁ − I₂)/√2, the average (I₁ + I₂)/2 and the pixels within
    ½ DN of 0 or 255 DN in either frame (bool), all B×1×H×W. Two floating-point B×1×H×W tensors of one shape, H and
    W ≥ 3; else ``TypeError``/``ValueError`` naming what was given."""
    _check_pair(image, reference)
    x1, x2 = image.detach().float() * 255.0, reference.detach().float() * 255.0
    diff = (x1 - x2) * (1.0 / math.sqrt(2.0))
    avg = (x1 + x2) * 0.5
    clip = (torch.minimum(x1, x2) <= 0.5) | (torch.maximum(x1, x2) >= 254.5)
    return diff, avg, clip


def static_pair_blocks(image: torch.Tensor, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The 2×2-block quantities of a static pair that its flatness and clipping tests read, float32 (B×1×H×W in
    [0, 1], H, W ≥ 8; module docstring).

    Returns:
        m_d: block means of the scaled difference (I₁ − I₂)/√2 [DN], (B, 1, h, w): noise of variance v/4.
        g2: their squared central differences, vertical plus horizontal [DN²] (noise variance v/2 each, as the
            block-mean gradients of one frame on a flat scene).
        lo, hi: the smallest and largest pixel of each block of the average (I₁ + I₂)/2 [DN].
    """
    f = pair_fold(image, reference)
    return f.m_d, f.g2, f.lo, f.hi


def difference_limits_dn(image: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """How far the scaled difference of a static pair may swing before either frame clips, given the pair's average:
    (B, 1, h, w, 4) float32 [DN], the four pixels of each 2×2 block (I₀₀, I₀₁, I₁₀, I₁₁; an odd last row or column is
    dropped, as by the block statistics), B×1×H×W frames in [0, 1] (H, W ≥ 8).

    A pixel of frame t reads I_t = S + n_t with n₁, n₂ independent N(0, v). The average A = (I₁ + I₂)/2 and the
    scaled difference D = (I₁ − I₂)/√2 are then independent (uncorrelated Gaussians), and I₁ = A + D/√2,
    I₂ = A − D/√2: neither frame clips (both within ½ DN of the bounds' inside) exactly where

        |D| < c = √2·min(A − ½, 254.5 − A)   [DN].

    So a pixel used only where neither frame clips carries D conditioned on |D| < c — a symmetric truncated normal
    whose variance is v·h(c/√v), h(u) = E[z² | |z| < u] (:func:`camhealth.estimators.noise_features.truncated_second_moment`)
    — and since A is observed, c is known pixel by pixel whatever the scene. That is the pair's whole clipping model;
    one frame has to infer it from block means instead (:func:`camhealth.estimators.physics_noise._kept_variance_factor`).
    0 where either frame clips (within ½ DN of 0 or 255 DN: |D| ≥ c there), so a block is usable exactly where its
    four limits are positive."""
    return pair_fold(image, reference).limits


class PairFold(NamedTuple):
    """What :func:`~camhealth.estimators.physics_noise.physics_noise_posterior` reads of a static pair, from one pass
    (:func:`pair_fold`): the unclamped fold (:func:`static_pair_image` with ``clamp=False``), the blocks of
    :func:`static_pair_blocks` (m_d, g2, lo, hi), the limits of :func:`difference_limits_dn`, and the average's block
    means m_avg [DN] (B, 1, h, w)."""

    fold: torch.Tensor
    m_d: torch.Tensor
    g2: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    limits: torch.Tensor
    m_avg: torch.Tensor


def pair_fold(image: torch.Tensor, reference: torch.Tensor) -> PairFold:
    """The fold (as :func:`static_pair_image` with ``clamp=False``), the blocks of :func:`static_pair_blocks`, the limits of
    :func:`difference_limits_dn` (both read from here) and the average's block means of B×1×H×W frames in [0, 1]
    (H, W ≥ 8), the sum and difference of the frames formed once. The limits: c = √2·(127 − |A − 127.5|) with
    A = 127.5·(x₁ + x₂) [DN]; the frames read A ± d with d = (I₁ − I₂)/2, so one of them is within ½ DN of a bound
    exactly where |d| ≥ c/√2, i.e. |D| = 255·|x₁ − x₂|/√2 ≥ c, and c is set to 0 there."""
    _check_pair(image, reference, min_side=8)
    x1, x2 = image.detach().float(), reference.detach().float()
    b, ch, h, w = x1.shape
    h2, w2 = h // 2 * 2, w // 2 * 2
    total, diff = x1 + x2, x1 - x2  # [0, 2] and [−1, 1]
    t2, d2 = total[..., :h2, :w2], diff[..., :h2, :w2]
    avg_blocks = _block_mean(t2).mul_(0.5)  # the average's block means in [0, 1]
    fold = diff * (1.0 / math.sqrt(2.0))
    fold[..., :h2, :w2] += avg_blocks.view(b, ch, h2 // 2, 1, w2 // 2, 1).expand(b, ch, h2 // 2, 2, w2 // 2, 2).reshape(b, ch, h2, w2)
    if h2 < h:
        fold[..., h2:, :] += total[..., h2:, :] * 0.5
    if w2 < w:
        fold[..., :h2, w2:] += total[..., :h2, w2:] * 0.5
    fold.masked_fill_(torch.minimum(x1, x2) <= 0.0, 0.0).masked_fill_(torch.maximum(x1, x2) >= 1.0, 1.0)
    # the limits as in difference_limits_dn: c = √2·(127 − |A − 127.5|), 0 where |D| ≥ c
    c = (t2 - 1.0).abs_().mul_(-127.5 * math.sqrt(2.0)).add_(127.0 * math.sqrt(2.0))
    c.masked_fill_(d2.abs().mul_(255.0 / math.sqrt(2.0)) >= c, 0.0).clamp_min_(0.0)
    limits = torch.stack([c[..., 0::2, 0::2], c[..., 0::2, 1::2], c[..., 1::2, 0::2], c[..., 1::2, 1::2]], dim=-1)
    m_d = _block_mean(d2).mul_(255.0 / math.sqrt(2.0))
    return PairFold(fold, m_d, _block_grad2(m_d), _block_min(t2).mul_(127.5), _block_max(t2).mul_(127.5), limits,
                    avg_blocks.mul(255.0))


#: Largest deviation of :func:`scene_leak` (the steep blocks' normalised detail energy over the flat ones') from 1 of a
#: still pair, beside 4 of its standard errors: 0.1 lets through a change that adds ≈ 10 % to the noise variance of
#: the steepest quarter of the blocks, ≈ 2.5 % on the patch (1 % of σ).
SCENE_LEAK_LIMIT = 0.1


def scene_leak(image: torch.Tensor, reference: torch.Tensor, pool: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """How much of the scene a pair's difference carries (module docstring), (B,) float64 each: the ratio of the mean
    normalised diagonal detail energy d²/v̂(m) of the steep blocks (upper quarter of the average's block-mean gradient)
    to that of the flat blocks (lower half), and its standard error √(2/n_steep + 2/n_flat). Blocks with a pixel within
    ½ DN of 0 or 255 DN in either frame are left out; a patch with fewer than 64 usable blocks gets ratio 1 and an
    infinite error. ``pool``: one camera state — the NLF v̂ is fitted over all patches, the ratio stays per patch.

    Args:
        image, reference: B×1×H×W exposures in [0, 1] (H, W ≥ 8); B = 0 gives empty results.
        pool: True or False (a string such as ``"yes"`` raises a ``TypeError``).
    """
    _check_pool(pool)
    diff, avg, clip = _pair_dn(image, reference)
    return _scene_leak(diff, avg, clip, pool)


def _check_pool(pool: Any) -> None:
    """Refuse a ``pool`` flag that is not a bool (``"no"`` would read as True and pool)."""
    if not isinstance(pool, (bool, np.bool_)):
        raise TypeError(f"pool = {pool!r:.40} must be True or False, got {type(pool).__name__}")


def _scene_leak(diff: torch.Tensor, avg: torch.Tensor, clip: torch.Tensor, pool: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`scene_leak` of the pair's arrays in DN (:func:`_pair_dn`)."""
    h2, w2 = diff.shape[-2] // 2 * 2, diff.shape[-1] // 2 * 2
    diff, avg, clip = diff[..., :h2, :w2], avg[..., :h2, :w2], clip[..., :h2, :w2]
    d = (diff[..., 0::2, 0::2] - diff[..., 0::2, 1::2] - diff[..., 1::2, 0::2] + diff[..., 1::2, 1::2]) * 0.5
    m = _block_mean(avg)
    g = _block_grad2(m)
    ok = ~((clip[..., 0::2, 0::2] | clip[..., 0::2, 1::2]) | (clip[..., 1::2, 0::2] | clip[..., 1::2, 1::2]))
    ok[..., 0, :] = False
    ok[..., -1, :] = False
    ok[..., :, 0] = False
    ok[..., :, -1] = False
    b = diff.shape[0]
    f64 = torch.float64
    d2, mm, okf = d.square().flatten(1).to(f64), m.flatten(1).to(f64), ok.flatten(1).to(f64)
    # the pair's own NLF, d² ≈ a + c·m by least squares over the usable blocks (pooled: over the frame)
    n = okf.sum(1)
    s_m, s_mm, s_d, s_md = (okf * mm).sum(1), (okf * mm * mm).sum(1), (okf * d2).sum(1), (okf * mm * d2).sum(1)
    if pool:
        n, s_m, s_mm, s_d, s_md = (t.sum().expand(b) for t in (n, s_m, s_mm, s_d, s_md))
    det = n * s_mm - s_m * s_m
    slope = torch.where(det > 1e-9 * n.clamp_min(1) ** 2, (n * s_md - s_m * s_d) / det.clamp_min(1e-30), torch.zeros_like(det))
    slope = slope.clamp_min(0.0)
    icpt = (s_d - slope * s_m) / n.clamp_min(1.0)
    v = (icpt.unsqueeze(1) + slope.unsqueeze(1) * mm).clamp_min(1e-3)
    z = d2 / v
    # the usable blocks of each patch split at the median and the upper quartile of the scene's gradient
    okf_b = ok.flatten(1)
    gk = torch.where(okf_b, g.flatten(1), torch.full_like(g.flatten(1), math.inf))
    sorted_g = sorted_values(gk)
    n_use = okf_b.sum(1, keepdim=True)
    t_flat = sorted_g.gather(1, (n_use // 2 - 1).clamp_min(0))
    t_steep = sorted_g.gather(1, (n_use - n_use // 4).clamp(0, gk.shape[1] - 1))
    flat = (okf_b & (gk <= t_flat)).to(f64)
    steep = (okf_b & (gk >= t_steep)).to(f64)
    nf, ns = flat.sum(1), steep.sum(1)
    enough = n_use.squeeze(1) >= 64
    ratio = torch.where(enough, ((z * steep).sum(1) / ns.clamp_min(1.0)) / ((z * flat).sum(1) / nf.clamp_min(1.0)).clamp_min(1e-12),
                        torch.ones_like(nf))
    se = torch.where(enough, (2.0 / ns.clamp_min(1.0) + 2.0 / nf.clamp_min(1.0)).sqrt(), torch.full_like(nf, math.inf))
    return ratio, se


#: Largest |correlation| of a still pair's difference with the average's gradient (:func:`pair_shift`), beside 4/√n.
PAIR_SHIFT_LIMIT = 0.05


def pair_shift(image: torch.Tensor, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Correlation of a pair's difference I₁ − I₂ with the horizontal and vertical central differences of its average
    (module docstring), (B, 2) float64, and the number n of pixels it was read on, (B,): the pixels of the interior
    with no pixel of the 3×3 neighbourhood within ½ DN of 0 or 255 DN in either frame. A still pair reads 0 within
    1/√n; a patch shifted by δ px reads the share of its difference that δ·∇S explains. Fewer than 64 pixels: 0.

    Args:
        image, reference: B×1×H×W exposures in [0, 1] (H, W ≥ 3); B = 0 gives empty results.
    """
    diff, avg, clip = _pair_dn(image, reference)
    return _pair_shift(diff, avg, clip)


def _pair_shift(diff: torch.Tensor, avg: torch.Tensor, clip: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`pair_shift` of the pair's arrays in DN (:func:`_pair_dn`; the correlation does not depend on the
    difference's scale)."""
    d = diff[..., 1:-1, 1:-1]
    gx = (avg[..., 1:-1, 2:] - avg[..., 1:-1, :-2]) * 0.5
    gy = (avg[..., 2:, 1:-1] - avg[..., :-2, 1:-1]) * 0.5
    rows = clip[..., :, :-2] | clip[..., :, 1:-1] | clip[..., :, 2:]  # the 3×3 neighbourhood, one axis at a time
    ok = (~(rows[..., :-2, :] | rows[..., 1:-1, :] | rows[..., 2:, :])).flatten(1).float()
    d, gx, gy = d.flatten(1), gx.flatten(1), gy.flatten(1)
    n = ok.sum(1)
    scale = 1.0 / n.clamp_min(1.0)

    def centred(v: torch.Tensor) -> torch.Tensor:  # about its mean over the pixels read, 0 elsewhere
        return (v - (v * ok).sum(1, keepdim=True) * scale.unsqueeze(1)) * ok

    dc = centred(d)
    s_dd = torch.linalg.vecdot(dc, dc)

    def corr(gr: torch.Tensor) -> torch.Tensor:
        gc = centred(gr)
        den = (s_dd * torch.linalg.vecdot(gc, gc)).double().sqrt()
        num = torch.linalg.vecdot(dc, gc).double()
        return torch.where((n >= 64) & (den > 0), num / den.clamp_min(1e-300), torch.zeros_like(num))

    n = n.double()
    return torch.stack([corr(gx), corr(gy)], 1), n


#: Largest relative difference (v₁ − v₂)/(v₁ + v₂) of a pair's two noise variances (:func:`pair_noise_balance`) that
#: passes where it is significant (|z| > 4): a variance ratio of 1.5 (σ 1.22×). A light change of 10 % between the
#: exposures moves the shot noise's variance by 10 % (0.05); a gain change of 2 dB already by 0.23 of the total's.
PAIR_NOISE_LIMIT = 0.2


def pair_noise_balance(image: torch.Tensor, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Whether the two frames of a pair carry the same noise: the relative difference ρ = (v₁ − v₂)/(v₁ + v₂) of their
    noise variances and its z score, (B,) float64 each (0 and 0 with fewer than 64 blocks).

    The pair's fold assumes one noise variance v in both frames (module docstring); a gain or a readout that changed
    between the exposures breaks it, and the difference then reads the mean of the two. On the diagonal Haar details of
    the 2×2 blocks without a clipped pixel (within ½ DN of 0 or 255 DN in either frame), the average's d_A = s +
    (d₁ + d₂)/2 and the scaled difference's d_D = (d₁ − d₂)/√2 (s the scene's, d_t frame t's noise of variance v_t)
    have E[d_A·d_D] = (v₁ − v₂)/(2√2) and E[d_D²] = (v₁ + v₂)/2, whatever the scene: ρ̂ = √2·Σd_A·d_D / Σd_D², and
    z = Σd_A·d_D / √Σ(d_A·d_D)² (mean 0 and variance 1 for equal noise; the scene widens both sums alike).

    Args:
        image, reference: B×1×H×W exposures in [0, 1] (H, W ≥ 3); B = 0 gives empty results.
    """
    diff, avg, clip = _pair_dn(image, reference)
    return _pair_noise_balance(diff, avg, clip)


def _pair_noise_balance(diff: torch.Tensor, avg: torch.Tensor, clip: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    h, w = diff.shape[-2] // 2 * 2, diff.shape[-1] // 2 * 2

    def detail(t: torch.Tensor) -> torch.Tensor:
        t = t[..., :h, :w].double()
        return (t[..., 0::2, 0::2] - t[..., 0::2, 1::2] - t[..., 1::2, 0::2] + t[..., 1::2, 1::2]).flatten(1) * 0.5

    c = clip[..., :h, :w]
    ok = ~(c[..., 0::2, 0::2] | c[..., 0::2, 1::2] | c[..., 1::2, 0::2] | c[..., 1::2, 1::2]).flatten(1)
    d_a, d_d = detail(avg), detail(diff)
    prod = d_a * d_d * ok
    n = ok.sum(1)
    s_dd = (d_d.square() * ok).sum(1)
    s_p, s_pp = prod.sum(1), prod.square().sum(1)
    enough = (n >= 64) & (s_dd > 0) & (s_pp > 0)
    rho = torch.where(enough, math.sqrt(2.0) * s_p / s_dd.clamp_min(1e-300), torch.zeros_like(s_p))
    z = torch.where(enough, s_p / s_pp.clamp_min(1e-300).sqrt(), torch.zeros_like(s_p))
    return rho, z


def pair_stillness(image: torch.Tensor, reference: torch.Tensor, pool: bool = False) -> torch.Tensor:
    """Whether each patch of a pair is shown to hold a still scene of one noise level, (B,) bool: :func:`scene_leak`
    within max(:data:`SCENE_LEAK_LIMIT`, 4 standard errors) of 1, both :func:`pair_shift` correlations within
    max(:data:`PAIR_SHIFT_LIMIT`, 4/√n) of 0, and the frames' noise variances alike (:func:`pair_noise_balance`:
    |ρ| ≤ :data:`PAIR_NOISE_LIMIT` or |z| ≤ 4; a reference at another gain is not this camera state) — the tests on
    one pass over the pair. ``pool``: one camera state (the scene-leak NLF over all patches; the tests stay per patch).

    A patch without the evidence for both tests — fewer than 64 usable blocks for :func:`scene_leak` (its error is
    infinite) or fewer than 64 pixels for :func:`pair_shift`, e.g. a patch clipped (within ½ DN of 0 or 255 DN) in
    either frame almost everywhere — is not shown still: False ("cannot tell" is not "still").

    Args:
        image, reference: B×1×H×W exposures in [0, 1] (H, W ≥ 8); B = 0 gives an empty result.
        pool: True or False (a string such as ``"yes"`` raises a ``TypeError``).
    """
    _check_pool(pool)
    diff, avg, clip = _pair_dn(image, reference)
    leak, leak_se = _scene_leak(diff, avg, clip, pool)
    shift, n = _pair_shift(diff, avg, clip)
    rho, z = _pair_noise_balance(diff, avg, clip)
    evidence = torch.isfinite(leak_se) & (n >= 64)
    return (evidence & ((leak - 1.0).abs() <= torch.clamp_min(4.0 * leak_se, SCENE_LEAK_LIMIT))
            & (shift.abs().amax(1) <= torch.clamp_min(4.0 / n.clamp_min(1.0).sqrt(), PAIR_SHIFT_LIMIT))
            & ((rho.abs() <= PAIR_NOISE_LIMIT) | (z.abs() <= 4.0)))
