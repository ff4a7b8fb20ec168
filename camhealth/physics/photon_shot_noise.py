"""Photon shot noise (thesis Sec. 3.2.2.1, γ = 1) under the "digital gain" model of conventions.md.

At gain factor g the scene delivers N = I · FW / g photo-electrons for an output intensity I ∈ [0, 1]
(full well FW [e⁻] maps to 255 DN after gain). N is Poisson distributed; the gain amplifies signal and
noise back to I, so

    σ_PN(I) = 255 · √(g · I / FW)   [DN]

per pixel. Doubling the gain (to compensate half the light) raises σ_PN by √2.

Precision: the arithmetic runs in float32 for float16/bfloat16 intensities (FW/g reaches 10⁵ e⁻, beyond
float16's largest number, and g/FW down to 10⁻⁵ is subnormal there), in the input's dtype otherwise. The σ
functions return the input's dtype; :func:`photo_electrons` returns float32 for half-precision input (electron
counts up to 10⁵ do not fit float16).
"""

from __future__ import annotations

import torch

from camhealth._validation import check_finite
from camhealth.physics._format import check_range, show_outside
from camhealth.physics.metadata import CameraMetadata

__all__ = ["photo_electrons", "photon_shot_sigma_dn", "photon_shot_sigma_patch_dn"]


def _work(t: torch.Tensor) -> torch.Tensor:
    """``t`` in its compute dtype: float32 for float16/bfloat16 tensors, other dtypes unchanged."""
    return t.to(torch.float32) if t.dtype in (torch.float16, torch.bfloat16) else t


def _per_sample(v: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Per-sample values (B,) of the metadata shaped to broadcast over ``ref`` (B×…), or ``ValueError`` naming both
    batch sizes unless the metadata has 1 or B samples."""
    b = ref.shape[0] if ref.ndim else 1
    if v.shape[0] not in (1, b):
        raise ValueError(f"metadata batch {v.shape[0]} does not match the intensity batch {b} (shape {tuple(ref.shape)}): "
                         "give metadata of batch 1 or one per sample")
    return v.to(device=ref.device, dtype=ref.dtype).view(-1, *([1] * (ref.ndim - 1)))


def photo_electrons(intensity: torch.Tensor, meta: CameraMetadata) -> torch.Tensor:
    """Expected photo-electrons per pixel, N = I · FW / g [e⁻]; ``intensity`` is B×… in [0, 1] (else ``ValueError``).
    Returned in the intensity's dtype, or float32 for float16/bfloat16 intensities."""
    check_range(intensity, "intensity", 0.0, 1.0, "(DN/255)")
    x = _work(intensity)
    return x.clamp_min(0) * _per_sample(meta.full_well_e / meta.gain_factor, x)


def photon_shot_sigma_dn(intensity: torch.Tensor, meta: CameraMetadata) -> torch.Tensor:
    """Per-pixel σ_PN [DN] = 255·√(g·I/FW) for intensities I ∈ [0, 1] of shape B×… (NaN or a value outside [0, 1]:
    ``ValueError`` naming it), in the intensity's dtype."""
    check_range(intensity, "intensity", 0.0, 1.0, "(DN/255)")
    x = _work(intensity)
    return (255.0 * (x.clamp_min(0) * _per_sample(meta.gain_factor / meta.full_well_e, x)).sqrt()).to(intensity.dtype)


def photon_shot_sigma_patch_dn(intensity: torch.Tensor, meta: CameraMetadata) -> torch.Tensor:
    """Patch-level σ_PN [DN], shape (B,): the root-mean-square of the per-pixel σ over each sample,
    i.e. √(mean σ²) = 255·√(g·mean(I)/FW) (clipping ignored). Each sample's mean intensity must lie in [0, 1]
    (DN/255; a DN image, 0…255, is refused with ``ValueError``); single pixels may ring slightly below 0 after a
    blur and count as 0. Returned in the intensity's dtype."""
    out_dtype = intensity.dtype
    intensity = _work(intensity)
    if intensity.ndim < 1 or meta.batch_size not in (1, intensity.shape[0]):
        raise ValueError(f"metadata batch {meta.batch_size} does not match the intensity batch (shape "
                         f"{tuple(intensity.shape)}): give metadata of batch 1 or one per sample")
    raw = intensity.detach().flatten(1).mean(1)
    check_finite(raw, "mean intensity")  # (B,): a NaN anywhere in a sample shows here
    bad = (raw < -1e-6) | (raw > 1.0 + 1e-6)
    if bool(bad.any()):
        i = int(bad.nonzero()[0, 0])
        raise ValueError(f"mean intensity[{i}] = {show_outside(float(raw[i]), -1e-6, 1.0 + 1e-6, raw.dtype)} is out of the "
                         "allowed range [0, 1] (DN/255)")
    mean_i = intensity.clamp_min(0).flatten(1).mean(1)
    return (255.0 * (mean_i * (meta.gain_factor / meta.full_well_e).to(mean_i)).sqrt()).to(out_dtype)
