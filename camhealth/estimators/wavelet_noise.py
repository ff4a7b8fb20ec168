"""Wavelet MAD noise estimator (Donoho & Johnstone 1994), as ``skimage.restoration.estimate_sigma`` computes it.

The robust median estimator of the noise standard deviation from the finest-scale diagonal wavelet
detail coefficients d (Daubechies-2 wavelet, one level, symmetric border extension)::

    σ̂ = median(|d|) / Φ⁻¹(0.75) = median(|d|) / 0.6745

The diagonal detail sub-band of a natural image holds little signal, and the median ignores the few large
coefficients of edges. **Left out of the median** are the coefficients that carry no noise:

- those with more than half of their 4×4-px support clipped (within ½ DN of 0 or 255: :data:`CLIP_MARGIN`; the
  rule of the B+F estimator's blocks): a saturated or black area holds no noise, and its coefficients would pull the
  median towards 0 (white noise of 20 DN with a quarter of the image at 255 DN read 12.7 DN, with half of it
  0.6 DN; with them left out 19.4 and 19.7 DN), and
- those of a noiseless flat or linear area (db2 has two vanishing moments), whose coefficients are float rounding
  (about 1e-17 for a flat area, 1e-7 for a float32 ramp; not exactly 0) and would pull the median down the same way
  (a flat 0.3 on the same half of the image: 0.6 DN, a float32 ramp there: 0.7 DN): coefficients with
  |d| ≤ :data:`FLAT_TOLERANCE` (1e-6 intensity units, ≈ 3·10⁻⁴ DN) that lie in a 3×3 block of such coefficients
  (an area of about 8×8 px or more), and
- those that are exactly 0, as scikit-image leaves them out.

An isolated tiny coefficient is kept: 8-bit noise of 0.3–5 DN makes some (0.01–1 % of them, where the values of
a support happen to cancel), and leaving them out would move σ̂ by up to 3 % (0.3 DN) against ``estimate_sigma``.

Where no coefficient is left (a constant image, or one that is clipped nearly everywhere) σ̂ is 0. On an image
without a clipped pixel and without a noiseless area nothing is left out, and σ̂ is exactly what
``estimate_sigma`` returns. Noise clipped at scattered pixels (strong noise near 0 or 255 DN) keeps nearly all its
coefficients: a support more than half clipped is rare there (3.5 % of the pixels clipped, 60 DN at mid-grey: none
left out). Leaving out every coefficient that touches a clipped pixel would select the places where the noise stayed
away from the bound and read it low (−7 % there). Such images read the noise that the clipping left (the std of the
clipped noise), below the noise before the clipping.

Two backends compute the same numbers: ``"skimage"`` transforms the batch with PyWavelets' ``dwtn`` (the one-level
``db2`` decomposition, 'symmetric' mode, its 'dd' sub-band: what ``estimate_sigma`` computes, and equal to it bit
for bit where nothing beyond the exact zeros is left out; tested) and takes the median with NumPy; where
PyWavelets is not installed (it is not a camhealth dependency) ``"torch"`` computes the same decomposition with
two strided 1-D convolutions, batched (equal to float precision, tested whenever PyWavelets is importable).

σ̂ is returned in **DN** (float).

Small images read low: the symmetric extension gives the border coefficients less noise, and they pull the
median down, the more the smaller and the odder the side (white noise at σ = 10 DN, 300 images per size: −9 % at
8 px, −28 % at 9, −7 % at 16, −18 % at 17, −3 % at 32, −11 % at 33, −0.9 % at 128, −3.0 % at 129). So an odd side is
cropped by one pixel before the transform (33 px then reads as 32: −3 %), and images under
:data:`MIN_SIZE` px are refused.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from camhealth._validation import check_choice
from camhealth.estimators._common import DN, check_patches

__all__ = ["DB2_DEC_HI", "MIN_SIZE", "CLIP_MARGIN", "FLAT_TOLERANCE", "wavelet_noise_sigma", "skimage_available",
           "diagonal_detail_db2", "clipped_support_db2", "flat_area_db2"]

#: Smallest image side [px] :func:`wavelet_noise_sigma` reads: from 16 px (even) σ̂ is within 7 % on white noise,
#: from 32 px within 3 % (smaller images read 9–34 % low, module docstring).
MIN_SIZE = 16
#: A pixel within this distance of 0 or 1 (½ DN of 8 bits) is clipped: the coefficients with more than half of their
#: support clipped are left out of the median (module docstring).
CLIP_MARGIN = 0.5 / 255.0
#: Coefficients with |d| at or below this (intensity units, images in [0, 1]) are float rounding (≈ 1e-17 to 1e-7);
#: in a 3×3 block of them they come from a noiseless flat or linear area and are left out of the median (module
#: docstring).
FLAT_TOLERANCE = 1e-6

#: Daubechies-2 decomposition high-pass filter (PyWavelets' ``Wavelet('db2').dec_hi``), from the db2 scaling
#: coefficients h = [(1+√3), (3+√3), (3−√3), (1−√3)] / (4√2) by the quadrature-mirror relation g_k = (−1)^k h_{3−k}.
_S3 = math.sqrt(3.0)
_H = [(1 + _S3) / (4 * math.sqrt(2.0)), (3 + _S3) / (4 * math.sqrt(2.0)), (3 - _S3) / (4 * math.sqrt(2.0)), (1 - _S3) / (4 * math.sqrt(2.0))]
DB2_DEC_HI: tuple[float, ...] = (-_H[0], _H[1], -_H[2], _H[3])
#: Φ⁻¹(0.75): the median of |N(0, 1)| (the value scikit-image's scipy.stats.norm.ppf(0.75) gives, to the last bit).
_MAD_TO_SIGMA = 0.6744897501960817


def skimage_available() -> bool:
    """True when the ``"skimage"`` backend can run (it needs PyWavelets, as ``estimate_sigma`` does)."""
    import importlib.util

    return importlib.util.find_spec("pywt") is not None


def _filter_along_last(x: torch.Tensor, taps: tuple[float, ...]) -> torch.Tensor:
    """One-level 4-tap filter + downsampling along the last dim ('symmetric' mode): length (N + 3) // 2."""
    lead, n = x.shape[:-1], x.shape[-1]
    ext = torch.cat([x[..., :3].flip(-1), x, x[..., -3:].flip(-1)], dim=-1)[..., 1:]  # symmetric by 3, drop one
    filt = torch.tensor(taps[::-1], dtype=x.dtype, device=x.device).view(1, 1, 4)
    out = torch.nn.functional.conv1d(ext.reshape(-1, 1, ext.shape[-1]), filt, stride=2)
    return out.reshape(*lead, out.shape[-1])[..., : (n + 3) // 2]


def _detail_along_last(x: torch.Tensor) -> torch.Tensor:
    """One-level db2 high-pass + downsampling along the last dim ('symmetric' mode): length (N + 3) // 2."""
    return _filter_along_last(x, DB2_DEC_HI)


def diagonal_detail_db2(images: torch.Tensor) -> torch.Tensor:
    """The 'dd' sub-band of a one-level 2-D db2 DWT of ``B×1×H×W`` images: (B, (H+3)//2, (W+3)//2), float64."""
    x = images[:, 0].double()
    d = _detail_along_last(x)  # along columns (x)
    return _detail_along_last(d.transpose(-1, -2)).transpose(-1, -2)  # then along rows (y)


def clipped_support_db2(images: torch.Tensor) -> torch.Tensor:
    """(B, (H+3)//2, (W+3)//2) bool: the coefficients of :func:`diagonal_detail_db2` with more than half of their
    4×4-px support (after the symmetric extension) within :data:`CLIP_MARGIN` of 0 or 1."""
    x = images[:, 0]
    c = ((x <= CLIP_MARGIN) | (x >= 1.0 - CLIP_MARGIN)).float()  # counts of 16: exact in float32
    ones = (1.0, 1.0, 1.0, 1.0)
    s = _filter_along_last(c, ones)
    return _filter_along_last(s.transpose(-1, -2), ones).transpose(-1, -2) > 8.0  # clipped pixels of 16


def flat_area_db2(d: torch.Tensor) -> torch.Tensor:
    """(B, h, w) bool: the coefficients of a 'dd' sub-band ``d`` (B, h, w) with |d| ≤ :data:`FLAT_TOLERANCE` that lie
    in a 3×3 block of such coefficients (a morphological opening): a noiseless flat or linear area of at least
    ≈ 8×8 px. An isolated tiny coefficient — noise that happens to cancel, 8-bit values that happen to agree — is kept."""
    tiny = d.abs() <= FLAT_TOLERANCE
    if not bool(tiny.any()):
        return tiny
    pool = torch.nn.functional.max_pool2d
    other = (~tiny).unsqueeze(1).float()
    core = pool(other, 3, stride=1, padding=1) == 0  # every coefficient of the 3×3 block tiny (the border: those inside)
    return (pool(core.float(), 3, stride=1, padding=1) > 0).squeeze(1) & tiny


def _torch_sigma(images: torch.Tensor, clipped: torch.Tensor | None) -> torch.Tensor:
    d = diagonal_detail_db2(images).abs()
    drop = flat_area_db2(d) | (d == 0)  # (exactly 0: left out as scikit-image does)
    if clipped is not None:
        drop = drop | clipped
    d = torch.where(drop, torch.full_like(d, float("nan")), d).flatten(1)
    med = torch.nanquantile(d, 0.5, dim=1)
    return torch.nan_to_num(med, nan=0.0) / _MAD_TO_SIGMA  # nothing left (a constant or clipped image): σ̂ = 0


def _pywt_sigma(images: torch.Tensor, clipped: torch.Tensor | None) -> torch.Tensor:
    """PyWavelets' one-level db2 'dd' sub-band of the whole batch in one ``dwtn`` call (what ``estimate_sigma``
    computes per image, bit for bit) and the median of the |d| kept, per image; float64 (B,)."""
    import pywt

    stack = np.ascontiguousarray(images[:, 0].detach().double().cpu().numpy().transpose(1, 2, 0))  # H×W×B
    dd = np.abs(pywt.dwtn(stack, "db2", mode="symmetric", axes=(0, 1))["dd"])  # h×w×B
    keep = (dd != 0) & ~flat_area_db2(torch.from_numpy(dd.transpose(2, 0, 1))).numpy().transpose(1, 2, 0)
    if clipped is not None:
        keep &= ~clipped.cpu().numpy().transpose(1, 2, 0)
    sig = np.zeros(dd.shape[-1], dtype=np.float64)
    for i in range(dd.shape[-1]):
        kept = dd[..., i][keep[..., i]]
        if kept.size:  # nothing left (a constant or clipped image): σ̂ = 0
            sig[i] = np.median(kept) / _MAD_TO_SIGMA
    return torch.from_numpy(sig)


def wavelet_noise_sigma(images: torch.Tensor, backend: str = "auto") -> torch.Tensor:
    """Noise level σ̂ [DN] of each image of a batch ``B×1×H×W`` in [0, 1] (wavelet MAD).

    The coefficients of clipped areas (more than half of the support within ½ DN of 0 or 255) and of noiseless flat
    areas are left out of the median (module docstring); an image with none left (constant, or clipped nearly
    everywhere) reads 0.

    Args:
        images: float batch in [0, 1] (DN/255), at least :data:`MIN_SIZE` px on each side (an odd side is cropped
            by one pixel).
        backend: ``"skimage"`` (PyWavelets' ``dwtn``, as ``skimage.restoration.estimate_sigma``; needs
            PyWavelets), ``"torch"`` (the same computation in torch) or ``"auto"`` (PyWavelets when available).

    Returns:
        (B,) σ̂ in DN (float32, float64 for float64 input).
    """
    check_choice(backend, "backend", ("auto", "skimage", "torch"))
    x = check_patches(images, "images", min_size=(MIN_SIZE, MIN_SIZE))
    h, w = x.shape[-2:]
    x = x[..., : h - h % 2, : w - w % 2]  # an odd side: its extension biases the median low (module docstring)
    out = torch.float64 if x.dtype == torch.float64 else torch.float32
    use_skimage = backend == "skimage" or (backend == "auto" and skimage_available())
    if use_skimage and not skimage_available():
        raise ImportError(
            "backend='skimage' needs PyWavelets (pip install PyWavelets) for skimage.restoration.estimate_sigma; "
            "use backend='torch' or 'auto'"
        )
    flat = x.detach().flatten(1)
    has = (flat.amin(1) <= CLIP_MARGIN) | (flat.amax(1) >= 1.0 - CLIP_MARGIN)  # images that reach a bound
    clipped = None  # nothing clipped (the common case): no mask
    if bool(has.any()):  # the mask of the images that reach a bound only
        sel = has.nonzero(as_tuple=True)[0]
        part = clipped_support_db2(x.detach()[sel])
        clipped = torch.zeros((x.shape[0], *part.shape[1:]), dtype=torch.bool, device=x.device)
        clipped[sel] = part
    if use_skimage:
        return (DN * _pywt_sigma(x, clipped)).to(device=x.device, dtype=out)
    return (DN * _torch_sigma(x, clipped)).to(out)
