"""Block-based noise estimation with adaptive Gaussian filtering ("B+F"; Shin, Park, Yang & Jung 2005).

The thesis's "B+F" baseline (Sec. 4.3.2, [Shi+05]), with the 8×16 px blocks the thesis used (instead of
the paper's 3×16). For an image y = x + n with white noise n of standard deviation σ:

1. **Blocks.** Split the image into non-overlapping blocks of ``block = (8, 16)`` px (rows × columns;
   a remainder at the right/bottom border is ignored) and compute each block's intensity standard
   deviation s_k. Blocks that are mostly saturated (more than half of their pixels at 0 or 255 DN) carry no
   measurable noise and are left out (if every block is saturated, all are used).
2. **Homogeneous blocks.** The ``fraction`` (default 10 %, at least one) of the remaining blocks with the
   smallest s_k are the smoothest ones; their mean s_k is the initial estimate σ₀. Because the smallest
   of many noisy standard deviations are biased low (≈ −11 % for 10 % of 128-px blocks of pure noise),
   the homogeneous class is then widened to every usable block with ``s_k ≤ κ·σ₀`` (κ = 1.5): on a flat
   image that is every block, on a textured one the blocks whose texture adds at most ≈ 1.2 σ² to the
   noise variance.
3. **Adaptive Gaussian filter.** A Gaussian low-pass g whose width grows with the initial estimate,
   ``σ_g = clip(0.5 px + σ₀ / (10 DN) px, 0.5 px, 3 px)`` (weak noise: narrow filter, so little texture
   leaks into the residual; strong noise: wider filter, so more of the noise is captured), is applied to
   the image (reflect padding).
4. **Residual.** On the homogeneous blocks the residual r = y − g ⊛ y is (nearly) pure noise, with variance
   σ²·‖δ − g‖² for white noise (δ the unit impulse). The estimate is the pooled standard deviation of r
   over the selected blocks divided by ‖δ − g‖₂, so a flat noisy block returns σ itself.

σ̂ is returned in **DN** (float). Typical behaviour, also reported in the thesis: texture that survives in
the "smoothest" blocks inflates low noise levels, and picking the blocks with the smallest standard
deviation biases high noise levels low (by a few % for 128-px patches). Everything is batched: per-image
filters are applied in one grouped convolution.

**Small blocks read low.** The standard deviation of a few pixels scatters widely, so the smoothest blocks of
step 2 are those whose noise happened to be small, and the smaller the block the lower σ₀, the narrower the filter
and the fewer the blocks that κ·σ₀ admits. Measured on white noise (64 images of 128 px, σ = 2, 10, 30, 60 DN; the
range over σ): 2×2 px −53…−61 %, 2×4 −28…−32 %, 3×3 −24…−28 %, 4×4 −10…−12 %, 4×5 and 2×10 −5…−8 %, 24-px blocks
(2×12, 3×8, 4×6) −2.6…−5.1 %, 5×5 −2…−4 %, 32-px blocks (2×16, 4×8) −0.4…−2.1 %, 6×6 and larger within ±1 %
(the default 8×16: +0.1…+0.4 %). So blocks must hold at least :data:`MIN_BLOCK_AREA` px (32: within ≈ 2 %).
"""

from __future__ import annotations

import math
import numbers

import torch

from camhealth._validation import check_range
from camhealth.estimators._common import DN, check_patches, work_dtype

__all__ = ["BLOCK_SIZE", "MIN_BLOCK_AREA", "block_filter_noise_sigma", "adaptive_gaussian_width"]

#: Block size (rows, columns) in px used by the thesis.
BLOCK_SIZE: tuple[int, int] = (8, 16)
#: Fewest pixels a block may hold (rows × columns): smaller blocks read the noise low, by more than 2 % (24 px: up to
#: −5 %, 16 px: −12 %, 4 px: −61 %; module docstring).
MIN_BLOCK_AREA = 32
_SATURATED = 0.5  # a block with more than this fraction of clipped pixels is left out
_MAX_WIDTH_PX = 3.0
_KAPPA = 1.5  # homogeneous: block std <= κ · σ₀


def adaptive_gaussian_width(sigma0_dn: torch.Tensor) -> torch.Tensor:
    """Gaussian filter standard deviation σ_g [px] from the initial noise estimate σ₀ [DN] (step 3).

    ``sigma0_dn``: a tensor of real numbers (any shape), each finite and ≥ 0 [DN]; anything else (a list, a bool or
    complex tensor) raises a ``TypeError``, NaN, ±inf or a negative σ₀ a ``ValueError``, naming it."""
    if not isinstance(sigma0_dn, torch.Tensor):
        raise TypeError(f"sigma0_dn must be a torch.Tensor of noise levels σ₀ [DN] (finite, ≥ 0), got "
                        f"{type(sigma0_dn).__name__} {sigma0_dn!r:.60}")
    if sigma0_dn.dtype == torch.bool or sigma0_dn.is_complex():
        raise TypeError(f"sigma0_dn must hold real noise levels σ₀ [DN] (finite, ≥ 0), got dtype {sigma0_dn.dtype}")
    check_range(sigma0_dn.detach(), "sigma0_dn", 0.0, math.inf, "DN")
    return (0.5 + sigma0_dn / 10.0).clamp(0.5, _MAX_WIDTH_PX)


def _gaussian_kernels(width_px: torch.Tensor, size: int) -> torch.Tensor:
    """(B, size, size) normalised isotropic Gaussians of standard deviation ``width_px`` (B,)."""
    r = torch.arange(size, device=width_px.device, dtype=width_px.dtype) - size // 2
    g1 = torch.exp(-0.5 * (r[None, :] / width_px[:, None]) ** 2)
    g1 = g1 / g1.sum(dim=1, keepdim=True)
    return g1[:, :, None] * g1[:, None, :]


def block_filter_noise_sigma(
    images: torch.Tensor, block: tuple[int, int] = BLOCK_SIZE, fraction: float = 0.1
) -> torch.Tensor:
    """Noise level σ̂ [DN] of each image of a batch ``B×1×H×W`` in [0, 1] (B+F, Shin et al. 2005).

    Args:
        images: float batch in [0, 1] (DN/255), at least one block large.
        block: block size (rows, columns) in px, ints (NumPy integers too), each >= 2 and together at least
            :data:`MIN_BLOCK_AREA` px (smaller blocks read the noise low; module docstring).
        fraction: share of the (unsaturated) blocks taken as homogeneous, a real number in (0, 1].

    Returns:
        (B,) σ̂ in DN (float32, float64 for float64 input).
    """
    if not (isinstance(block, (tuple, list)) and len(block) == 2
            and all(isinstance(v, numbers.Integral) and not isinstance(v, bool) for v in block)):
        raise TypeError(f"block must be a pair of ints (rows, columns), got {block!r}")
    bh, bw = int(block[0]), int(block[1])
    if bh < 2 or bw < 2:
        raise ValueError(f"block = {(bh, bw)} px: both sides must be >= 2")
    if bh * bw < MIN_BLOCK_AREA:
        raise ValueError(f"block = {(bh, bw)} px holds {bh * bw} px, fewer than the {MIN_BLOCK_AREA} px that keep σ̂ within "
                         f"≈ 2 % (smaller blocks read the noise low: 16 px −12 %, 4 px −61 %); use e.g. (4, 8) or the "
                         f"default {BLOCK_SIZE}")
    if isinstance(fraction, bool) or not isinstance(fraction, numbers.Real):
        raise TypeError(f"fraction must be a real number in (0, 1], got {fraction!r} ({type(fraction).__name__})")
    if not (0.0 < float(fraction) <= 1.0):
        raise ValueError(f"fraction = {float(fraction):g} is out of the allowed range (0, 1]")
    x = check_patches(images, "images", min_size=(bh, bw))
    work = work_dtype(x)
    y = x.to(work)
    b, _, h, w = y.shape
    nh, nw = h // bh, w // bw
    crop = y[:, :, : nh * bh, : nw * bw]

    def blocks(t: torch.Tensor) -> torch.Tensor:  # (B, 1, nh·bh, nw·bw) → (B, nh·nw, bh·bw)
        return t.reshape(b, nh, bh, nw, bw).permute(0, 1, 3, 2, 4).reshape(b, nh * nw, bh * bw)

    blk = blocks(crop)
    s_k = blk.std(dim=-1, unbiased=True) * DN  # (B, K) DN
    clipped = ((blk <= 0.0) | (blk >= 1.0)).to(work).mean(dim=-1)
    usable = clipped <= _SATURATED
    usable = torch.where(usable.any(dim=1, keepdim=True), usable, torch.ones_like(usable))
    n_use = usable.sum(dim=1)  # (B,)
    k_sel = (n_use.to(work) * float(fraction)).ceil().clamp_min(1).long()  # (B,)
    ranked = torch.where(usable, s_k, torch.full_like(s_k, math.inf)).argsort(dim=1)
    rank = torch.empty_like(ranked)
    rank.scatter_(1, ranked, torch.arange(s_k.shape[1], device=y.device).expand_as(ranked))
    smoothest = (rank < k_sel[:, None]).to(work)  # (B, K)
    sigma0 = (s_k * smoothest).sum(dim=1) / smoothest.sum(dim=1)
    homogeneous = (usable & (s_k <= _KAPPA * sigma0[:, None])) | (smoothest > 0)
    sel_f = homogeneous.to(work)

    width = adaptive_gaussian_width(sigma0)
    size = 2 * math.ceil(3.0 * _MAX_WIDTH_PX) + 1
    kernels = _gaussian_kernels(width, size)  # (B, k, k)
    pad = size // 2
    mode = "reflect" if pad < min(h, w) else "replicate"
    padded = torch.nn.functional.pad(y, (pad, pad, pad, pad), mode=mode)
    smooth = torch.nn.functional.conv2d(padded.reshape(1, b, h + 2 * pad, w + 2 * pad), kernels[:, None], groups=b)
    resid = blocks((y - smooth.reshape(b, 1, h, w))[:, :, : nh * bh, : nw * bw])  # (B, K, n)
    n_px = bh * bw
    r_mean = resid.mean(dim=-1, keepdim=True)
    ss = (resid - r_mean).square().sum(dim=-1)  # per-block sum of squares about the block mean
    pooled = (ss * sel_f).sum(dim=1) / (sel_f.sum(dim=1) * (n_px - 1))
    delta = torch.zeros_like(kernels)
    delta[:, pad, pad] = 1.0
    gain = (delta - kernels).square().sum(dim=(1, 2)).sqrt()  # ‖δ − g‖₂
    out = torch.float64 if x.dtype == torch.float64 else torch.float32
    return (DN * pooled.sqrt() / gain).to(out)
