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
- :func:`nlf_statistics` — a coarse noise-level function of the patch: the 2×2 blocks sorted by their mean
  and cut into three equal-count intensity terciles, the Haar-MAD σ and the mean intensity of each. Photon
  noise grows with intensity (σ_PN² ∝ I), dark-current and readout noise do not, so the three points tell the
  signal-dependent from the signal-independent part of the noise where the patch spans a range of intensities.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from camhealth.physics.dark_current import dark_current_shot_sigma_e
from camhealth.physics.metadata import FULL_FIELDS, CameraMetadata
from camhealth.physics.readout_noise import readout_sigma_e

__all__ = [
    "metadata_from_matrix", "physics_prior_dn", "image_statistics", "laplace_difference", "box_mean3", "IMAGE_STATISTICS",
    "CLIP_TOLERANCE", "nlf_statistics", "NLF_STATISTICS",
]

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


def physics_prior_dn(image: torch.Tensor, meta: CameraMetadata, cache: dict | None = None) -> torch.Tensor:
    """Closed-form σ [DN] of (PN, DCSN, RN, total) for the metadata ``meta``, shape (B, 4), float32.

    Args:
        image: B×1×H×W noisy patches in [0, 1]; only their mean intensity is used (for σ_PN).
        meta: metadata of batch 1 or B, physical units.
        cache: optional dict that keeps (σ_DCSN, σ_RN) [DN] per distinct metadata row between calls (an
            inference loop that sees the same camera state on every frame integrates the readout noise
            once); at most 64 rows are kept.
    """
    b = image.shape[0]
    if meta.batch_size not in (1, b):
        raise ValueError(f"metadata batch {meta.batch_size} does not match the {b} patches")
    mean_i = image.detach().float().clamp(0, 1).flatten(1).mean(1).double()
    # Dark-current and readout σ depend on the metadata only: evaluate them once per distinct metadata row
    # (a monitored frame's patches share one camera state; the readout integral is the costly part).
    rows = torch.stack([getattr(meta, n).to(device=image.device, dtype=torch.float64) for n in FULL_FIELDS], dim=1)
    if rows.shape[0] == 1:
        unique, inverse = rows, torch.zeros(1, dtype=torch.long, device=rows.device)
    else:
        unique, inverse = torch.unique(rows, dim=0, return_inverse=True)
    keys = [(tuple(r), meta.constants) for r in unique.tolist()]  # the fixed sensor constants are part of the key
    found = [cache.get(k) if cache is not None else None for k in keys]
    todo = [i for i, f in enumerate(found) if f is None]
    if todo:
        meta64 = meta.to(device=image.device, dtype=torch.float64)
        first = torch.full((unique.shape[0],), rows.shape[0], dtype=torch.long, device=rows.device)
        first = first.scatter_reduce(0, inverse, torch.arange(rows.shape[0], device=rows.device), reduce="amin")
        distinct = meta64[first[torch.tensor(todo, dtype=torch.long, device=rows.device)]]
        dn = distinct.dn_per_electron
        values = torch.stack([dark_current_shot_sigma_e(distinct) * dn, readout_sigma_e(distinct) * dn,
                              distinct.gain_factor / distinct.full_well_e], dim=1).tolist()
        for i, v in zip(todo, values):
            found[i] = tuple(v)
            if cache is not None:
                if len(cache) >= 64:
                    cache.pop(next(iter(cache)))
                cache[keys[i]] = found[i]
    dc_u, rn_u, g_fw_u = torch.tensor(found, dtype=torch.float64, device=rows.device).unbind(1)
    dc, rn, g_fw = dc_u[inverse], rn_u[inverse], g_fw_u[inverse]
    if meta.batch_size == 1:
        dc, rn, g_fw = dc.expand(b), rn.expand(b), g_fw.expand(b)
    pn = 255.0 * (mean_i * g_fw).sqrt()
    total = (pn.pow(2) + dc.pow(2) + rn.pow(2)).sqrt()
    return torch.stack([pn, dc, rn, total], dim=1).float()


_LAPLACE_DIFF = torch.tensor([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])


def laplace_difference(x: torch.Tensor) -> torch.Tensor:
    """Immerkær's mask N = [[1, −2, 1], [−2, 4, −2], [1, −2, 1]] over B×C×H×W without padding → (H−2)×(W−2).

    N is the outer product of [1, −2, 1] with itself, so it is applied as two second differences of shifted
    slices (exactly the 3×3 correlation, ~5× faster on CPU than a one-channel ``conv2d``)."""
    r = x[..., :, :-2] - 2.0 * x[..., :, 1:-1] + x[..., :, 2:]
    return r[..., :-2, :] - 2.0 * r[..., 1:-1, :] + r[..., 2:, :]


def box_mean3(x: torch.Tensor) -> torch.Tensor:
    """3×3 mean of B×C×H×W with replicate borders (= ``avg_pool2d(pad(x, 1, "replicate"), 3, stride=1)``),
    separably from shifted slices (~5× faster on CPU than ``avg_pool2d``)."""
    p = F.pad(x, (1, 1, 1, 1), mode="replicate")
    r = p[..., :, :-2] + p[..., :, 1:-1] + p[..., :, 2:]
    return (r[..., :-2, :] + r[..., 1:-1, :] + r[..., 2:, :]) / 9.0


def image_statistics(image: torch.Tensor) -> torch.Tensor:
    """Per-patch scalars (B, 5) in the order of :data:`IMAGE_STATISTICS` (float32; see module docstring).

    Always computed in float32, also under bf16 autocast (bf16 cannot resolve 1 DN at 255 DN)."""
    if torch.is_autocast_enabled(image.device.type):
        with torch.autocast(device_type=image.device.type, enabled=False):
            return _image_statistics(image.float())
    return _image_statistics(image.float())


def _haar_blocks(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """|d| and the mean [DN] of every 2×2 block of B×1×H×W patches in [0, 1], each (B, ⌊H/2⌋·⌊W/2⌋), with
    d = (I₀₀ − I₀₁ − I₁₀ + I₁₁)/2 the finest diagonal Haar detail (var d = σ² for white noise)."""
    h, w = (x.shape[-2] // 2) * 2, (x.shape[-1] // 2) * 2
    q = x[..., :h, :w] * 255.0
    a, b, c, e = q[..., 0::2, 0::2], q[..., 0::2, 1::2], q[..., 1::2, 0::2], q[..., 1::2, 1::2]
    return ((a - b - c + e) / 2.0).abs().flatten(1), ((a + b + c + e) / 4.0).flatten(1)


def _lower_median(x: torch.Tensor) -> torch.Tensor:
    """Lower median along the last dimension. ONNX has no median operator: there it is the top-k form (3–4×
    slower); torch.median returns the lower median for an even count, the same value."""
    if torch.onnx.is_in_onnx_export():
        return x.topk((x.shape[-1] - 1) // 2 + 1, dim=-1, largest=False).values[..., -1]
    return x.median(dim=-1).values


def _image_statistics(x: torch.Tensor) -> torch.Tensor:
    mean = x.flatten(1).mean(1)
    low = (x <= CLIP_TOLERANCE).float().flatten(1).mean(1)
    high = (x >= 1.0 - CLIP_TOLERANCE).float().flatten(1).mean(1)
    resp = laplace_difference(x * 255.0).abs().flatten(1).mean(1)
    immerkaer = math.sqrt(math.pi / 2.0) * resp / 6.0
    mad = _lower_median(_haar_blocks(x)[0]) / 0.6745
    return torch.stack([mean, mean.clamp_min(0).sqrt(), low, high, immerkaer, mad], dim=1)


#: Names of the columns of :func:`nlf_statistics`.
NLF_STATISTICS: tuple[str, ...] = (
    "nlf_log_mad_dark", "nlf_log_mad_mid", "nlf_log_mad_bright", "nlf_mean_dark", "nlf_mean_mid", "nlf_mean_bright",
)


def nlf_statistics(image: torch.Tensor) -> torch.Tensor:
    """A three-point noise-level function of each patch, (B, 6) float32 in the order of :data:`NLF_STATISTICS`.

    The finest diagonal Haar details d = (I₀₀ − I₀₁ − I₁₀ + I₁₁)/2 of the 2×2 blocks (I in DN; var d = σ² for
    white noise) are ordered by their block's mean intensity and cut into three equal-count terciles (dark, mid,
    bright; a remainder of one or two blocks is dropped). Per tercile: log(σ̂ + 0.1) with σ̂ = median|d| / 0.6745
    [DN], and the mean intensity of its blocks in [0, 1]. Clipped blocks are kept (their σ̂ drops toward 0,
    which the network reads together with the clipped fractions). Needs at least 3 blocks (H, W ≥ 2 px and
    H·W ≥ 12 px). Always float32, also under bf16 autocast."""
    if torch.is_autocast_enabled(image.device.type):
        with torch.autocast(device_type=image.device.type, enabled=False):
            return _nlf_statistics(image.float())
    return _nlf_statistics(image.float())


def _nlf_statistics(x: torch.Tensor) -> torch.Tensor:
    d, m = _haar_blocks(x)
    b, n3 = d.shape[0], d.shape[1] // 3
    if n3 < 1:
        raise ValueError(f"nlf_statistics needs at least 3 blocks of 2×2 px, got a {tuple(x.shape[-2:])} patch")
    order = m.argsort(dim=1)[:, : 3 * n3]
    d = d.gather(1, order).view(b, 3, n3)
    m = m.gather(1, order).view(b, 3, n3)
    sigma = _lower_median(d) / 0.6745
    return torch.cat([torch.log(sigma + 0.1), m.mean(2) / 255.0], dim=1)
