"""Input conventions shared by every estimator's ``predict``: patches (tensor or array, DN or [0, 1], gray layouts),
metadata (``CameraMetadata``, a dict of fields, a preset name or a metadata file) and the assessability flags of
patches that are black, saturated or featureless. A lower layer than :mod:`camhealth.inference` and
:mod:`camhealth.estimators`, which both use it."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch

from camhealth.physics.metadata import CameraMetadata

__all__ = ["MAX_CLIPPED_FRACTION", "MIN_CONTRAST_DN", "STRUCTURE_BLOCK", "assess_patches", "structure_contrast_dn"]

#: Fraction of clipped pixels above which a patch is "black"/"saturated" (not assessable).
MAX_CLIPPED_FRACTION = 0.5
#: Noise-corrected structure contrast (DN, :func:`structure_contrast_dn`) below which a patch carries no blur
#: information ("featureless"; MTF only).
MIN_CONTRAST_DN = 2.0
#: Block side [px] of the block means whose spread is the structure contrast.
STRUCTURE_BLOCK = 8
#: 1 / Φ⁻¹(0.75): median absolute value of a standard normal → σ.
_MAD_NORMAL = 0.6744897501960817


def structure_contrast_dn(patches: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Noise-corrected structure contrast and robust noise level of B×1×P×P patches in [0, 1] → ((B,), (B,)) DN.

    - noise σ̂ = median|d| / 0.6745 of the finest diagonal Haar detail d = (I₀₀ − I₀₁ − I₁₀ + I₁₁)/2 over the
      2×2 blocks of every other block row (Donoho's MAD estimate: var d = σ² for white noise; edges and texture
      touch few d, so the median ignores them);
    - structure s = √max(0, var(B₈) − σ̂²/64) of the 8×8 block means B₈ (P ≥ 16; the patch cropped to a
      multiple of 8): scene content at ≥ 16-px periods, from which the noise (variance σ²/64 in a block mean)
      is removed. On a flat patch with white noise s is ~0 whatever σ (the spread of var(B₈) over its P²/64
      blocks is σ²/64·√(128/P²), e.g. 0.37 DN² at σ = 20 DN and P = 192, against (2 DN)² = 4 DN²).
      Patches under 16 px use the pixels themselves: s = √max(0, var − σ̂²).

    The monitor's tiling computes the same two statistics frame-wide (:mod:`camhealth.monitor.tiling`)."""
    x = patches[:, 0].float() * 255.0
    b, h, w = x.shape
    h2, w2 = h - h % 2, w - w % 2
    if h2 < 2 or w2 < 2:
        return x.double().flatten(1).std(1, unbiased=False).float(), torch.zeros(b)
    # d of every other row of 2×2 blocks (P²/8 samples: ~2 % standard error of σ̂, half the selection work)
    q = x[:, :h2, :w2]
    step = 4 if h2 >= 8 else 2
    d = 0.5 * (q[:, 0::step, 0::2] - q[:, 0::step, 1::2] - q[:, 1::step, 0::2] + q[:, 1::step, 1::2])
    flat = d.abs().flatten(1)
    noise = flat.kthvalue((flat.shape[1] + 1) // 2, dim=1).values.double() / _MAD_NORMAL
    blk = STRUCTURE_BLOCK
    if min(h, w) >= 2 * blk:
        hb, wb = h - h % blk, w - w % blk
        means = x[:, :hb, :wb].reshape(b, hb // blk, blk, wb // blk, blk).mean((2, 4)).flatten(1).double()
        var = means.var(1, unbiased=False) - noise.square() / (blk * blk)
    else:
        var = x.double().flatten(1).var(1, unbiased=False) - noise.square()
    return var.clamp_min(0).sqrt().float(), noise.float()


def assess_patches(patches: torch.Tensor, kind: str) -> tuple[torch.Tensor, list[str]]:
    """Which B×1×P×P patches (in [0, 1]) an estimator of ``kind`` can assess, and why not.

    black / saturated: more than half of the pixels within 0.5 DN of 0 / 255 (noise is clipped away,
    blur invisible); featureless (MTF only): noise-corrected structure contrast (:func:`structure_contrast_dn`)
    below :data:`MIN_CONTRAST_DN` = 2 DN — no edges to measure blur on, however strong the noise (a flat patch with
    20 DN of noise has the contrast of its noise, not of a scene)."""
    x = patches.flatten(1)
    x = x if x.dtype in (torch.float32, torch.float64) else x.float()
    tol = 0.5 / 255.0
    n = x.shape[1]
    # clipped counts only where a patch reaches 0/255
    low = (x <= tol).sum(1, dtype=torch.int32) / n if bool((x.amin(1) <= tol).any()) else torch.zeros(x.shape[0])
    high = (x >= 1 - tol).sum(1, dtype=torch.int32) / n if bool((x.amax(1) >= 1 - tol).any()) else torch.zeros(x.shape[0])
    if kind == "mtf":
        std_dn = structure_contrast_dn(patches.float() if patches.dtype not in (torch.float32, torch.float64) else patches)[0]
    else:
        std_dn = torch.full((x.shape[0],), float("inf"))
    reason = []
    for lo, hi, s in zip(low.tolist(), high.tolist(), std_dn.tolist()):
        if lo > MAX_CLIPPED_FRACTION:
            reason.append("black")
        elif hi > MAX_CLIPPED_FRACTION:
            reason.append("saturated")
        elif kind == "mtf" and s < MIN_CONTRAST_DN:
            reason.append("featureless")
        else:
            reason.append("")
    return torch.tensor([r == "" for r in reason], dtype=torch.bool), reason


def _to_patches(images: Any, patch_size: int, input_range: str) -> torch.Tensor:
    if input_range not in ("auto", "unit", "dn"):
        raise ValueError(f"input_range = {input_range!r} must be 'auto', 'unit' or 'dn'")
    if isinstance(images, np.ndarray):
        if images.dtype == object or images.dtype.kind not in "uif":
            raise TypeError(f"images must be a numeric array, got dtype {images.dtype}")
        is_int = images.dtype.kind in "ui"
        t = torch.from_numpy(np.ascontiguousarray(images))
    elif isinstance(images, torch.Tensor):
        if images.dtype == torch.bool or images.is_complex():
            raise TypeError(f"images must be a real numeric tensor, got dtype {images.dtype}")
        is_int = not images.is_floating_point()
        t = images.detach().cpu()
    else:
        raise TypeError(f"images must be a torch.Tensor or numpy.ndarray, got {type(images).__name__}")
    t = _gray_patch_layout(t, patch_size)
    if tuple(t.shape[-2:]) != (patch_size, patch_size):
        raise ValueError(
            f"patches must be {patch_size}×{patch_size} px for this estimator, got {t.shape[-2]}×{t.shape[-1]}; "
            f"tile larger images (camhealth.monitor does)"
        )
    t = t.to(torch.float64 if t.dtype == torch.float64 else torch.float32)
    if t.shape[0] == 0:  # an empty batch: empty outputs
        return t.float()
    lo_t, hi_t = torch.aminmax(t)  # one pass; NaN propagates into both, ±inf shows as an extreme
    lo, hi = float(lo_t), float(hi_t)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        bad = int((~torch.isfinite(t)).sum())
        raise ValueError(f"images contain {bad} non-finite value(s) (NaN/Inf); allowed: finite DN 0…255 or [0, 1]")
    if is_int or input_range == "dn":
        if lo < 0 or hi > 255:
            raise ValueError(f"images in DN must lie in [0, 255], got min {lo:g}, max {hi:g} (8-bit DN only)")
        t = t / 255.0
    else:
        if lo < -1e-6 or hi > 1 + 1e-6:
            hint = " (looks like DN: pass input_range='dn')" if hi <= 255 and lo >= 0 else ""
            raise ValueError(f"float images must lie in [0, 1], got min {lo:g}, max {hi:g}{hint}")
    return t.clamp(0, 1).float()


_LAYOUTS = "B×1×H×W, B×H×W or H×W gray patches"


def _gray_patch_layout(t: torch.Tensor, patch_size: int) -> torch.Tensor:
    """``t`` as B×1×H×W, or a ``ValueError`` that names the layout it looks like: colour with channels last
    (H×W×C, B×H×W×C) or first (B×C×H×W), or C×H×W colour that could as well be a few gray patches."""
    shape = "×".join(map(str, t.shape))
    colour = "convert colour to gray first (camhealth.data.to_gray, BT.601 luma)"
    if t.ndim in (3, 4) and t.shape[-1] in (3, 4) and min(t.shape[-3:-1]) > 4:
        layout = "an H×W×C" if t.ndim == 3 else "a B×H×W×C"
        raise ValueError(f"images of shape {shape} look like {layout} colour image (channels last); the estimators take "
                         f"{_LAYOUTS}: {colour}")
    if t.ndim == 2:
        return t[None, None]
    if t.ndim == 3:
        if t.shape[0] in (3, 4) and tuple(t.shape[1:]) == (patch_size, patch_size):
            raise ValueError(
                f"images of shape {shape} are ambiguous: {t.shape[0]} gray patches (B×H×W) or one colour image "
                f"(C×H×W, channels first); pass gray patches as B×1×H×W (x[:, None]), or {colour}"
            )
        return t[:, None]
    if t.ndim == 4 and t.shape[1] in (3, 4):
        raise ValueError(f"images of shape {shape} look like a B×C×H×W colour batch (channels first); the estimators take "
                         f"{_LAYOUTS}: {colour}")
    if t.ndim != 4 or t.shape[1] != 1:
        raise ValueError(f"images must be {_LAYOUTS}, got shape {shape}")
    return t


def _to_metadata(metadata: Any, batch: int, base_preset: str | None) -> CameraMetadata:
    if isinstance(metadata, (str, Path)):  # a preset name or a metadata file (camera.yaml of camhealth.calibrate)
        meta = CameraMetadata.lookup(metadata)
    elif isinstance(metadata, CameraMetadata):
        meta = metadata
    elif isinstance(metadata, Mapping):
        meta = CameraMetadata.from_dict(dict(metadata), base=base_preset)
    else:
        raise TypeError(
            f"metadata must be CameraMetadata, a dict of fields, a preset name or a .yaml/.json file, got {type(metadata).__name__}"
        )
    if meta.batch_size not in (1, batch):
        raise ValueError(f"metadata has batch size {meta.batch_size}; it must be 1 or the number of patches {batch}")
    return meta  # batch 1 stays batch 1 (broadcast over the patches)
