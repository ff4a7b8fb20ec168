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

__all__ = ["MAX_CLIPPED_FRACTION", "MIN_CONTRAST_DN", "assess_patches"]

#: Fraction of clipped pixels above which a patch is "black"/"saturated" (not assessable).
MAX_CLIPPED_FRACTION = 0.5
#: Contrast (std, DN) below which a patch carries no blur information ("featureless"; MTF only).
MIN_CONTRAST_DN = 2.0


def assess_patches(patches: torch.Tensor, kind: str) -> tuple[torch.Tensor, list[str]]:
    """Which B×1×P×P patches (in [0, 1]) an estimator of ``kind`` can assess, and why not.

    black / saturated: more than half of the pixels within 0.5 DN of 0 / 255 (noise is clipped away,
    blur invisible); featureless (MTF only): contrast below 2 DN (no edges to measure blur on)."""
    x = patches.flatten(1)
    x = x if x.dtype in (torch.float32, torch.float64) else x.float()
    tol = 0.5 / 255.0
    n = x.shape[1]
    # clipped counts only where a patch reaches 0/255; variance from two sums (Welford's var_mean is ~30×
    # slower here; values lie in [0, 1], so E[x²] − E[x]² in float64 cannot cancel below 1e-9)
    low = (x <= tol).sum(1, dtype=torch.int32) / n if bool((x.amin(1) <= tol).any()) else torch.zeros(x.shape[0])
    high = (x >= 1 - tol).sum(1, dtype=torch.int32) / n if bool((x.amax(1) >= 1 - tol).any()) else torch.zeros(x.shape[0])
    mean = x.sum(1).double() / n
    var = torch.linalg.vector_norm(x, dim=1).double().square() / n - mean.square()
    std_dn = var.clamp_min(0).sqrt() * 255.0
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
