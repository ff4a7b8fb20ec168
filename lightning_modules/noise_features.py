"""Physics the noise estimators compute in closed form instead of learning it.

- :func:`metadata_from_matrix` — (B, 11) raw metadata (``FULL_FIELDS`` order, physical units) →
  validated :class:`~camhealth.physics.CameraMetadata` (out-of-range values raise, naming field and range).
- :func:`physics_prior_dn` — the noise model's σ per source for the metadata the network is given
  (conventions.md): σ_PN = 255·√(g·Ī/FW) from the patch mean Ī of the (noisy) input, σ_DCSN = √(DC·t_exp)·g·255/FW
  (Eq. 3.14–3.15) and σ_RN (Eq. 3.16–3.19), all in DN, before clipping; plus their root-sum-square total.
  Dark-current and readout σ are exact functions of the metadata; σ_PN is exact up to the noise in Ī.
  The hybrid noise-source network learns only what these cannot give: clipping and saturation, scene
  content, and the metadata/image mismatch ξ.
- :func:`image_statistics` — cheap per-patch scalars: mean intensity, its square root (σ_PN ∝ √I), the
  fractions of clipped pixels at 0 and 255 DN, and Immerkær's (1996) fast noise estimate
  σ ≈ √(π/2) · Σ|I ∗ N| / (6 (W−2)(H−2)) with the Laplacian-difference mask
  N = [[1, −2, 1], [−2, 4, −2], [1, −2, 1]] (I in DN), which texture inflates and the network corrects;
  and Donoho's robust median-absolute-deviation estimate on the finest diagonal Haar detail,
  d = (I₀₀ − I₀₁ − I₁₀ + I₁₁)/2 over 2×2 blocks (var d = σ² for white noise), σ ≈ median|d| / 0.6745,
  which edges barely move.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from camhealth.physics.dark_current import dark_current_shot_sigma_e
from camhealth.physics.metadata import FULL_FIELDS, CameraMetadata
from camhealth.physics.readout_noise import readout_sigma_e

__all__ = ["metadata_from_matrix", "physics_prior_dn", "image_statistics", "IMAGE_STATISTICS", "CLIP_TOLERANCE"]

#: Names of the columns of :func:`image_statistics`.
IMAGE_STATISTICS: tuple[str, ...] = (
    "mean", "sqrt_mean", "clipped_low", "clipped_high", "immerkaer_sigma_dn", "haar_mad_sigma_dn",
)

#: A pixel counts as clipped within half a DN of 0 or 255.
CLIP_TOLERANCE = 0.5 / 255.0


def metadata_from_matrix(meta_raw: torch.Tensor) -> CameraMetadata:
    """(B, 11) raw metadata in ``FULL_FIELDS`` order → :class:`CameraMetadata` (validated)."""
    if not isinstance(meta_raw, torch.Tensor) or meta_raw.ndim != 2 or meta_raw.shape[1] != len(FULL_FIELDS):
        shape = tuple(meta_raw.shape) if isinstance(meta_raw, torch.Tensor) else type(meta_raw).__name__
        raise ValueError(f"raw metadata must be a (B, {len(FULL_FIELDS)}) tensor in FULL_FIELDS order, got {shape}")
    return CameraMetadata(**{n: meta_raw[:, i] for i, n in enumerate(FULL_FIELDS)})


def physics_prior_dn(image: torch.Tensor, meta: CameraMetadata) -> torch.Tensor:
    """Closed-form σ [DN] of (PN, DCSN, RN, total) for the metadata ``meta``, shape (B, 4), float32.

    Args:
        image: B×1×H×W noisy patches in [0, 1]; only their mean intensity is used (for σ_PN).
        meta: metadata of batch 1 or B, physical units.
    """
    b = image.shape[0]
    meta = meta.expand(b).to(device=image.device, dtype=torch.float64)
    mean_i = image.detach().float().clamp(0, 1).flatten(1).mean(1).double()
    dn = meta.dn_per_electron
    pn = 255.0 * (mean_i * meta.gain_factor / meta.full_well_e).sqrt()
    # Dark-current and readout σ depend on the metadata only: evaluate them once per distinct metadata row
    # (a monitored frame's patches share one camera state; the readout integral is the costly part).
    rows = torch.stack([getattr(meta, n) for n in FULL_FIELDS], dim=1)
    unique, inverse = torch.unique(rows, dim=0, return_inverse=True)
    if unique.shape[0] < b:
        first = torch.full((unique.shape[0],), b, dtype=torch.long, device=rows.device)
        first = first.scatter_reduce(0, inverse, torch.arange(b, device=rows.device), reduce="amin")
        distinct = meta[first]
        dc = (dark_current_shot_sigma_e(distinct) * distinct.dn_per_electron)[inverse]
        rn = (readout_sigma_e(distinct) * distinct.dn_per_electron)[inverse]
    else:
        dc = dark_current_shot_sigma_e(meta) * dn
        rn = readout_sigma_e(meta) * dn
    total = (pn.pow(2) + dc.pow(2) + rn.pow(2)).sqrt()
    return torch.stack([pn, dc, rn, total], dim=1).float()


_LAPLACE_DIFF = torch.tensor([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])


def image_statistics(image: torch.Tensor) -> torch.Tensor:
    """Per-patch scalars (B, 5) in the order of :data:`IMAGE_STATISTICS` (float32; see module docstring).

    Always computed in float32, also under bf16 autocast (bf16 cannot resolve 1 DN at 255 DN)."""
    if torch.is_autocast_enabled(image.device.type):
        with torch.autocast(device_type=image.device.type, enabled=False):
            return _image_statistics(image.float())
    return _image_statistics(image.float())


def _image_statistics(x: torch.Tensor) -> torch.Tensor:
    mean = x.flatten(1).mean(1)
    low = (x <= CLIP_TOLERANCE).float().flatten(1).mean(1)
    high = (x >= 1.0 - CLIP_TOLERANCE).float().flatten(1).mean(1)
    kernel = _LAPLACE_DIFF.to(device=x.device, dtype=x.dtype).view(1, 1, 3, 3)
    resp = F.conv2d(x * 255.0, kernel).abs().flatten(1).mean(1)
    immerkaer = math.sqrt(math.pi / 2.0) * resp / 6.0
    h, w = (x.shape[-2] // 2) * 2, (x.shape[-1] // 2) * 2
    q = x[..., :h, :w] * 255.0
    d = (q[..., 0::2, 0::2] - q[..., 0::2, 1::2] - q[..., 1::2, 0::2] + q[..., 1::2, 1::2]) / 2.0
    flat = d.abs().flatten(1)
    # lower median via top-k (= torch.median; exports to ONNX, which has no median operator)
    mad = flat.topk((flat.shape[1] - 1) // 2 + 1, dim=1, largest=False).values[:, -1] / 0.6745
    return torch.stack([mean, mean.clamp_min(0).sqrt(), low, high, immerkaer, mad], dim=1)
