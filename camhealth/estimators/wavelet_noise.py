"""Wavelet MAD noise estimator (Donoho & Johnstone 1994), through ``skimage.restoration.estimate_sigma``.

The robust median estimator of the noise standard deviation from the finest-scale diagonal wavelet
detail coefficients d (Daubechies-2 wavelet, one level, symmetric border extension)::

    σ̂ = median(|d|) / Φ⁻¹(0.75) = median(|d|) / 0.6745

(coefficients that are exactly 0 are left out, as scikit-image does: they come from clipped or flat
areas). The diagonal detail sub-band of a natural image holds little signal, and the median ignores the
few large coefficients of edges.

scikit-image provides this estimator and :func:`wavelet_noise_sigma` calls it — the whole batch in one
call, with the images stacked along a channel axis. scikit-image needs the optional PyWavelets package
for it; where PyWavelets is not installed (it is not a camhealth dependency), the same one-level
``db2`` decomposition ('symmetric' mode: half-sample symmetric extension, the ``dwtn`` 'dd' sub-band) is
computed here with two strided 1-D convolutions and the same median rule, batched in torch. The two
paths agree to float precision (tested whenever PyWavelets is importable); ``backend`` picks one.

σ̂ is returned in **DN** (float).

Small images read low: the symmetric extension gives the border coefficients less noise, and they pull the
median down, the more the smaller and the odder the side (white noise at σ = 10 DN, 300 images per size: −9 % at
8 px, −28 % at 9, −7 % at 16, −18 % at 17, −3 % at 32, −11 % at 33, −0.9 % at 128, −3.0 % at 129). So an odd side is
cropped by one pixel before the transform (33 px then reads as 32: −3 %), and images under
:data:`MIN_SIZE` px are refused.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import torch

from camhealth._validation import check_choice
from camhealth.estimators._common import DN, check_patches

__all__ = ["DB2_DEC_HI", "MIN_SIZE", "wavelet_noise_sigma", "skimage_available", "diagonal_detail_db2"]

#: Smallest image side [px] :func:`wavelet_noise_sigma` reads: from 16 px (even) σ̂ is within 7 % on white noise,
#: from 32 px within 3 % (smaller images read 9–34 % low, module docstring).
MIN_SIZE = 16

#: Daubechies-2 decomposition high-pass filter (PyWavelets' ``Wavelet('db2').dec_hi``), from the db2 scaling
#: coefficients h = [(1+√3), (3+√3), (3−√3), (1−√3)] / (4√2) by the quadrature-mirror relation g_k = (−1)^k h_{3−k}.
_S3 = math.sqrt(3.0)
_H = [(1 + _S3) / (4 * math.sqrt(2.0)), (3 + _S3) / (4 * math.sqrt(2.0)), (3 - _S3) / (4 * math.sqrt(2.0)), (1 - _S3) / (4 * math.sqrt(2.0))]
DB2_DEC_HI: tuple[float, ...] = (-_H[0], _H[1], -_H[2], _H[3])
#: Φ⁻¹(0.75): the median of |N(0, 1)|.
_MAD_TO_SIGMA = 0.6744897501960817


def skimage_available() -> bool:
    """True when scikit-image's ``estimate_sigma`` can run (it needs PyWavelets)."""
    import importlib.util

    return importlib.util.find_spec("pywt") is not None


def _detail_along_last(x: torch.Tensor) -> torch.Tensor:
    """One-level db2 high-pass + downsampling along the last dim ('symmetric' mode): length (N + 3) // 2."""
    lead, n = x.shape[:-1], x.shape[-1]
    ext = torch.cat([x[..., :3].flip(-1), x, x[..., -3:].flip(-1)], dim=-1)[..., 1:]  # symmetric by 3, drop one
    filt = torch.tensor(DB2_DEC_HI[::-1], dtype=x.dtype, device=x.device).view(1, 1, 4)
    out = torch.nn.functional.conv1d(ext.reshape(-1, 1, ext.shape[-1]), filt, stride=2)
    return out.reshape(*lead, out.shape[-1])[..., : (n + 3) // 2]


def diagonal_detail_db2(images: torch.Tensor) -> torch.Tensor:
    """The 'dd' sub-band of a one-level 2-D db2 DWT of ``B×1×H×W`` images: (B, (H+3)//2, (W+3)//2), float64."""
    x = images[:, 0].double()
    d = _detail_along_last(x)  # along columns (x)
    return _detail_along_last(d.transpose(-1, -2)).transpose(-1, -2)  # then along rows (y)


def _torch_sigma(images: torch.Tensor) -> torch.Tensor:
    d = diagonal_detail_db2(images).flatten(1).abs()
    d = torch.where(d == 0, torch.full_like(d, float("nan")), d)
    med = torch.nanquantile(d, 0.5, dim=1)
    return torch.nan_to_num(med, nan=0.0) / _MAD_TO_SIGMA  # every coefficient 0: a constant image, σ̂ = 0


def wavelet_noise_sigma(images: torch.Tensor, backend: str = "auto") -> torch.Tensor:
    """Noise level σ̂ [DN] of each image of a batch ``B×1×H×W`` in [0, 1] (wavelet MAD).

    Args:
        images: float batch in [0, 1] (DN/255), at least :data:`MIN_SIZE` px on each side (an odd side is cropped
            by one pixel).
        backend: ``"skimage"`` (call ``skimage.restoration.estimate_sigma``; needs PyWavelets),
            ``"torch"`` (the same computation in torch) or ``"auto"`` (scikit-image when available).

    Returns:
        (B,) σ̂ in DN (float32, float64 for float64 input).
    """
    check_choice(backend, "backend", ("auto", "skimage", "torch"))
    x = check_patches(images, "images", min_size=(MIN_SIZE, MIN_SIZE))
    h, w = x.shape[-2:]
    x = x[..., : h - h % 2, : w - w % 2]  # an odd side: its extension biases the median low (module docstring)
    out = torch.float64 if x.dtype == torch.float64 else torch.float32
    use_skimage = backend == "skimage" or (backend == "auto" and skimage_available())
    if use_skimage:
        if not skimage_available():
            raise ImportError(
                "backend='skimage' needs PyWavelets (pip install PyWavelets) for skimage.restoration.estimate_sigma; "
                "use backend='torch' or 'auto'"
            )
        from skimage.restoration import estimate_sigma

        stack = np.ascontiguousarray(x[:, 0].detach().double().cpu().numpy().transpose(1, 2, 0))  # H×W×B
        with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # an image whose every coefficient is 0: median of nothing
            sig = np.asarray(estimate_sigma(stack, average_sigmas=False, channel_axis=-1), dtype=np.float64)
        # scikit-image leaves the zero coefficients out; where none is left (a constant image) σ̂ is 0, as on the torch path
        return (DN * torch.as_tensor(np.nan_to_num(sig, nan=0.0))).to(device=x.device, dtype=out)
    return (DN * _torch_sigma(x)).to(out)
