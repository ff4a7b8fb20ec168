"""JPEG's quantised 8×8 block transform, seen in a decoded 8-bit patch: whether a lossy codec has coded the noise.

Model (ITU-T T.81): the encoder cuts the image into 8×8 blocks on a grid anchored at the frame's corner, takes each
block's orthonormal 2-D DCT-II, C_uv = ¼·c_u·c_v·Σ_yx I(y, x)·cos((2y + 1)uπ/16)·cos((2x + 1)vπ/16) (c₀ = 1/√2, else 1),
and keeps round(C_uv/Q_uv), Q_uv the quality's quantisation step (a table scaled by the quality: at quality 95 the
steps of the frequencies u, v ≥ 4 are 2–12 DN, at 75 12–50 DN, at 50 24–121 DN). The decoder inverts the DCT and
rounds to whole DN, so a decoded block's coefficients on the codec's grid are

    C_uv = Q_uv·k + e,   e ≈ N(0, 1/12 DN²)

(the orthonormal DCT of the 64 pixels' rounding errors, each uniform on ±½ DN): a comb of teeth 1/√12 = 0.29 DN wide.
Every coefficient the codec set to zero — most of the high-frequency ones wherever the noise σ is below Q/2, which is
how the codec removes noise — lies within ±0.5 DN of 0 with probability erf(√6/2) = 0.92 and within 0.5–1 DN with
0.08: a *jitter ratio* of 11 between the two windows.

A patch whose noise was added after the codec (or never coded) has no such comb: a coefficient is the scene's value
s plus noise of σ_t² = σ² + 1/12 DN² (its own 8-bit rounding included), whose share within ±0.5 DN is at most
erf(a) and whose share within 0.5–1 DN is erf(2a) − erf(a) at s = 0, a = 0.5/(σ_t·√2) (:func:`noise_jitter_ratio`:
2.0 at σ = 0.5 DN, 1.3 at 1 DN, 3.6 at 0.3 DN); any other s and any mixture of them gives less.

**Test.** The patch is cut into 16×16-px tiles, each of which holds one whole 8×8 block starting at every grid
offset (dy, dx) ∈ 0…7² (64 per offset on a 128-px patch). At each offset its blocks — those without a pixel within
½ DN of 0 or 255, where the clipping bends the comb — give the share z of their 16 highest-frequency coefficients
(u, v ∈ 4…7: the codec's largest steps, a scene's least content) within ±0.5 DN. A codec's grid holds far more of them
than the other offsets, whose blocks straddle two coded blocks; noise added afterwards makes every offset alike. The
patch is **coded** where, at the offset with the most,

- z exceeds the median offset's by :data:`ZERO_EXCESS_LIMIT` (0.1; without a codec sampling keeps it near 0.02, but
  a scene that was itself a JPEG and got a quiet camera's noise afterwards keeps its grid's zeros: up to 0.25 on the
  robustness benchmark's frames at 0.8 DN), and
- those coefficients' jitter ratio exceeds :data:`JITTER_RATIO_LIMIT` (3: noise of σ above 0.35 DN stays below it
  whatever the scene, a codec's rounding reads 11 at the median) by three standard errors of the counts
  (near − 3·ring > 3·√(near + 9·ring)), so a comb of the codec's width, not of noise, is what sits at zero — which
  tells a coded patch from a JPEG scene that was exposed to noise afterwards (1.3 there), and
- at least :data:`MIN_COEFFICIENTS` coefficients (32 unclipped blocks) were counted there.

What it finds on the robustness benchmark's frames, coded again at other qualities, crop offsets and in colour:
``python -m camhealth.bench robustness --task jpeg`` (docs/benchmarks.md). Strong noise coded at quality ≥ 95, whose
steps are below the noise and whose codec removed little of it, is often not coded by the test — nor is quality 100
(steps of 1 DN, nothing removed).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from camhealth._validation import check_float, check_range

__all__ = ["BLOCK", "FREQUENCIES", "ZERO_EXCESS_LIMIT", "JITTER_RATIO_LIMIT", "MIN_COEFFICIENTS", "FRAME_SAMPLE", "JpegGrid",
           "jpeg_grid", "coded_frame", "noise_jitter_ratio", "codec_jitter_ratio"]

#: JPEG's block size [px].
BLOCK = 8
#: The DCT frequencies u, v (of 0…7) whose coefficients the test reads: the codec's largest quantisation steps.
FREQUENCIES: tuple[int, ...] = (4, 5, 6, 7)
#: Least excess of the share of coefficients within ±0.5 DN at the best grid offset over the median offset's.
ZERO_EXCESS_LIMIT = 0.1
#: Least jitter ratio (share within ±0.5 DN over share within 0.5–1 DN) of the coefficients at the best offset.
JITTER_RATIO_LIMIT = 3.0
#: Fewest coefficients counted at the best offset (32 blocks: half of a 128-px patch's tiles unclipped).
MIN_COEFFICIENTS = 512
#: Patches of a frame :func:`coded_frame` reads: one codec codes the whole frame, so a few patches tell.
FRAME_SAMPLE = 4
# patches per batched call (16 frequencies × 64 offsets per 16-px tile, float32: 0.26 MB per 128-px patch)
_CHUNK = 64


@dataclass(frozen=True)
class JpegGrid:
    """What :func:`jpeg_grid` reads, per patch (B,).

    Attributes:
        coded: the codec's quantised block grid is there (module docstring).
        zero_excess: share of the coefficients within ±0.5 DN at the best grid offset minus the median offset's.
        jitter_ratio: at the best offset, the coefficients within ±0.5 DN over those within 0.5–1 DN (NaN: none).
        offset: (B, 2) int64, the best offset (dy, dx) [px] of the grid's corner in the patch, 0…7.
        coefficients: (B,) int64, the coefficients counted at the best offset.
    """

    coded: torch.Tensor
    zero_excess: torch.Tensor
    jitter_ratio: torch.Tensor
    offset: torch.Tensor
    coefficients: torch.Tensor


def noise_jitter_ratio(sigma_dn: float | torch.Tensor) -> torch.Tensor:
    """The largest jitter ratio that coefficients of noise σ [DN] (8-bit rounding included: σ_t² = σ² + 1/12) reach:
    erf(a)/(erf(2a) − erf(a)), a = 0.5/(σ_t·√2), the share within ±0.5 DN over that within 0.5–1 DN of N(0, σ_t²).

    ``sigma_dn``: a real number, or a real tensor or sequence of them (``TypeError`` for a string, a bool or another
    type), finite and ≥ 0."""
    if isinstance(sigma_dn, (bool, str, bytes)) or (isinstance(sigma_dn, torch.Tensor)
                                                    and (sigma_dn.dtype == torch.bool or sigma_dn.is_complex())):
        raise TypeError(f"sigma_dn must be a real number or a real tensor [DN], got {sigma_dn!r} ({type(sigma_dn).__name__})")
    try:
        s = torch.as_tensor(sigma_dn, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"sigma_dn must be a real number or a real tensor [DN], got {type(sigma_dn).__name__}") from None
    if bool((s < 0).any()) or not bool(torch.isfinite(s).all()):
        raise ValueError(f"sigma_dn must be finite and ≥ 0, got {sigma_dn!r}")
    a = 0.5 / ((s.square() + 1.0 / 12.0).sqrt() * math.sqrt(2.0))
    return torch.erf(a) / (torch.erf(2.0 * a) - torch.erf(a))


def codec_jitter_ratio() -> float:
    """The jitter ratio of coefficients a codec set to zero and the decoder rounded: e ~ N(0, 1/12 DN²), erf(√6/2) over
    erf(√6) − erf(√6/2) = 11.0."""
    return float(noise_jitter_ratio(0.0))


def _dct_weights() -> torch.Tensor:
    """(|FREQUENCIES|², 1, 8, 8) orthonormal 2-D DCT-II basis of the frequencies read (JPEG's FDCT)."""
    k = torch.arange(BLOCK, dtype=torch.float64)
    basis = torch.cos(math.pi * (2.0 * k.view(1, -1) + 1.0) * k.view(-1, 1) / (2.0 * BLOCK)) * math.sqrt(2.0 / BLOCK)
    basis[0] /= math.sqrt(2.0)
    f = basis[list(FREQUENCIES)]
    n = len(FREQUENCIES)
    return (f.view(n, 1, BLOCK, 1) * f.view(1, n, 1, BLOCK)).reshape(n * n, 1, BLOCK, BLOCK).float()


_WEIGHTS = _dct_weights()


def _read(x: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Per patch of B×1×H×W whole DN (H, W ≥ 16): the zero excess, and at the best offset the coefficients within
    ±0.5 DN and within 0.5–1 DN, the offset and the coefficients counted.

    The patch is cut into 16×16-px tiles; each tile holds, for every grid offset (dy, dx) ∈ 0…7², one whole block
    starting there, so one batched DCT over the tiles' 8×8 block positions gives every offset its blocks (one per
    tile: 64 on a 128-px patch) at a third of the work of every block position."""
    b, _, h, w = x.shape
    th, tw = h // (2 * BLOCK), w // (2 * BLOCK)
    tiles = (x[..., :th * 2 * BLOCK, :tw * 2 * BLOCK].reshape(b, th, 2 * BLOCK, tw, 2 * BLOCK)
             .permute(0, 1, 3, 2, 4).reshape(b * th * tw, 1, 2 * BLOCK, 2 * BLOCK))
    c = F.conv2d(tiles, _WEIGHTS.to(x.device))[..., :BLOCK, :BLOCK].abs_()  # (tiles, 16 frequencies, dy, dx)
    near = (c < 0.5).sum(1, dtype=torch.float32)
    ring = (c < 1.0).sum(1, dtype=torch.float32) - near
    clip = ((tiles < 0.5) | (tiles > 254.5)).float()
    clipped = F.max_pool2d(F.max_pool2d(clip, (BLOCK, 1), stride=1), (1, BLOCK), stride=1)[:, 0, :BLOCK, :BLOCK]
    used = 1.0 - clipped  # a block with a pixel within ½ DN of a bound is not read

    def per_offset(t: torch.Tensor) -> torch.Tensor:  # sum over the tiles → (B, 64), offset dy·8 + dx
        return (t * used).view(b, th * tw, BLOCK * BLOCK).sum(1).double()

    n_near, n_ring = per_offset(near), per_offset(ring)
    counted = per_offset(torch.ones_like(near)) * (len(FREQUENCIES) ** 2)
    share = n_near / counted.clamp_min(1.0)
    best = share.argmax(1, keepdim=True)
    excess = share.gather(1, best)[:, 0] - share.median(1).values
    near_b, ring_b = n_near.gather(1, best)[:, 0], n_ring.gather(1, best)[:, 0]
    offset = torch.stack([best[:, 0] // BLOCK, best[:, 0] % BLOCK], 1)
    return excess, near_b, ring_b, offset, counted.gather(1, best)[:, 0].long()


def jpeg_grid(patches: torch.Tensor) -> JpegGrid:
    """Whether B×1×H×W 8-bit patches in [0, 1] (values k/255) show JPEG's quantised 8×8 block grid (module docstring).

    Patches under 16 px in either side hold no 16-px tile and are not coded (their counts 0).

    Raises:
        ValueError: not a B×1×H×W tensor, values outside [0, 1] or not finite (naming the first).
        TypeError: not a floating-point tensor.
    """
    if not isinstance(patches, torch.Tensor) or patches.ndim != 4 or patches.shape[1] != 1:
        raise ValueError(f"patches must be a B×1×H×W tensor, got "
                         f"{tuple(patches.shape) if isinstance(patches, torch.Tensor) else type(patches).__name__}")
    check_range(check_float(patches, "patches"), "patches", 0.0, 1.0, "(DN/255)")
    b, _, h, w = patches.shape
    excess, near, ring = (torch.zeros(b, dtype=torch.float64) for _ in range(3))
    offset = torch.zeros(b, 2, dtype=torch.int64)
    count = torch.zeros(b, dtype=torch.int64)
    if b > 0 and h >= 2 * BLOCK and w >= 2 * BLOCK:
        with torch.autocast(device_type=patches.device.type, enabled=False):
            x = (patches.detach().double() * 255.0).round().float()
            for i in range(0, b, _CHUNK):
                e, n_near, n_ring, o, n = _read(x[i:i + _CHUNK])
                excess[i:i + _CHUNK], near[i:i + _CHUNK], ring[i:i + _CHUNK] = e.cpu(), n_near.cpu(), n_ring.cpu()
                offset[i:i + _CHUNK], count[i:i + _CHUNK] = o.cpu(), n.cpu()
    ratio = torch.where(ring > 0, near / ring.clamp_min(1.0), torch.where(near > 0, torch.inf, torch.nan))
    # the jitter ratio above its limit beyond the counts' sampling (Poisson): near − r·ring > 3·√(near + r²·ring)
    r = JITTER_RATIO_LIMIT
    beyond = near - r * ring > 3.0 * (near + r * r * ring).sqrt()
    coded = (excess > ZERO_EXCESS_LIMIT) & beyond & (count >= MIN_COEFFICIENTS)
    return JpegGrid(coded, excess, ratio, offset, count)


def coded_frame(patches: torch.Tensor, sample: int = FRAME_SAMPLE) -> bool:
    """Whether the B×1×H×W patches of one frame (8-bit, in [0, 1]) show JPEG's block grid: :func:`jpeg_grid` on
    ``sample`` of them evenly spaced (all, if fewer), coded where at least half of those that hold
    :data:`MIN_COEFFICIENTS` coefficients are (a frame whose sampled patches hold none — clipped nearly everywhere, or
    under 96 px — is not). One codec codes a whole frame, so a few patches tell at a fraction of the cost (0.4 ms per
    128-px patch). ``sample``: an int ≥ 1 (``TypeError`` for another type, a bool included)."""
    if isinstance(sample, bool) or not isinstance(sample, numbers.Integral):
        raise TypeError(f"sample must be an int (patches to read), got {sample!r} ({type(sample).__name__})")
    sample = int(sample)
    if sample < 1:
        raise ValueError(f"sample = {sample} is out of the allowed range [1, inf) (patches to read)")
    b = patches.shape[0] if isinstance(patches, torch.Tensor) and patches.ndim == 4 else None
    if b is None:
        jpeg_grid(patches)  # raises, naming what was given
    if b == 0:
        return False
    idx = torch.linspace(0, b - 1, min(b, sample)).round().long().unique()
    read = jpeg_grid(patches[idx.to(patches.device)])
    held = read.coefficients >= MIN_COEFFICIENTS
    return bool(held.any()) and 2 * int(read.coded.sum()) >= int(held.sum())
