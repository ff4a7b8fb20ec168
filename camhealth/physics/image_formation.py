"""The image-formation chain of thesis Fig. 3.7 / Sec. 5.4 as one batched, pure function.

    clean scene → defocus blur → photon shot noise → motion blur → dark-current shot noise
    → readout noise → gain → clipping to [0, 255] DN (saturation) → quantisation (optional)

Everything is computed per sample for a batch ``B×1×H×W`` in [0, 1] (= DN/255) with per-sample PSFs and
per-sample :class:`~camhealth.physics.metadata.CameraMetadata`. Noise is generated in electrons and
scaled to the output by the gain, g·255/FW DN per electron, so the clean signal maps back onto itself.

Labels. For every sample the result carries, per source (PN, DCSN, RN):

* ``sigma_dn`` — the realised standard deviation of that source's noise in the patch after gain and
  clipping [DN]. Clipping is attributed to the sources in proportion to their realised noise at each
  clipped pixel (at unclipped pixels each source keeps its own noise exactly).
* ``sigma_expected_dn`` — the analytic expectation before clipping [DN]: PN from the mean clean
  intensity (times √Σh² of the motion PSF, which averages PN), DCSN = √(DC·t_exp), RN from Eq. 3.17.

Gradients. The output is differentiable w.r.t. the clean image through the blurs (and the identity of
the additive noise); noise draws are treated as constants (Gaussian parts are reparameterised,
x + σ·ε; for the Poisson parts the gradient is the straight-through identity of their mean). Clipping
has zero gradient at clipped pixels; quantisation uses the straight-through estimator.

Precision. Physics runs in float32 (float64 for float64 input); float16/bfloat16 inputs are upcast and
the result cast back, so half-precision batches never see overflowing electron counts.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Sequence

import kornia
import torch

from camhealth._validation import check_image, check_tensor
from camhealth.physics.dark_current import dark_current_shot_sigma_e, dark_signal_e
from camhealth.physics.metadata import CameraMetadata
from camhealth.physics.photon_shot_noise import photon_shot_sigma_patch_dn
from camhealth.physics.readout_noise import readout_sigma_e

__all__ = ["NOISE_SOURCES", "ImageFormation", "apply_psf", "form_image", "sample_poisson"]

#: Noise sources in label order: photon shot noise, dark-current shot noise, readout noise.
NOISE_SOURCES: tuple[str, ...] = ("photon", "dark", "readout")


@dataclass
class ImageFormation:
    """Result of :func:`form_image`; all σ in DN (of 255), shapes (B, 3) per source or (B,).

    Attributes:
        image: corrupted images B×1×H×W in [0, 1], dtype of the input.
        sigma_dn: realised σ of (PN, DCSN, RN) after gain and clipping, (B, 3).
        sigma_total_dn: realised σ of all noise together after clipping, (B,).
        sigma_expected_dn: analytic σ of (PN, DCSN, RN) before clipping, (B, 3).
        sigma_total_expected_dn: √(Σ expected²), (B,).
        clipped_fraction: fraction of pixels clipped at 0 or 255 DN, (B,).
        blurred: noise-free blurred image (defocus then motion) B×1×H×W, float32/64.
    """

    image: torch.Tensor
    sigma_dn: torch.Tensor
    sigma_total_dn: torch.Tensor
    sigma_expected_dn: torch.Tensor
    sigma_total_expected_dn: torch.Tensor
    clipped_fraction: torch.Tensor
    blurred: torch.Tensor


def _work_dtype(dtype: torch.dtype) -> torch.dtype:
    return torch.float64 if dtype == torch.float64 else torch.float32


#: Kernels at least this large are applied by FFT (reflect-padded, so the result equals the direct
#: convolution up to float rounding); smaller ones by Kornia's grouped ``filter2d``.
FFT_MIN_KERNEL = 11


def _fft_size(n: int) -> int:
    """Smallest integer >= n whose only prime factors are 2, 3 and 5 (fast FFT lengths)."""
    m = n
    while True:
        r = m
        for f in (2, 3, 5):
            while r % f == 0:
                r //= f
        if r == 1:
            return m
        m += 1


@functools.lru_cache(maxsize=32)
def _dft_factors(n: int, k: int, half: bool, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """DFT matrix exp(−2πi·u·(j − k//2)/n) of a centred length-k kernel: (n, k), or (k, n//2 + 1) if half."""
    real = torch.float64
    u = torch.arange(n // 2 + 1 if half else n, dtype=real)
    j = torch.arange(k, dtype=real) - k // 2
    phase = -2.0 * math.pi * torch.remainder(u[:, None] * j[None, :], n) / n
    mat = torch.polar(torch.ones_like(phase), phase).to(device=device, dtype=dtype)
    return mat.transpose(0, 1).contiguous() if half else mat


def _psf_spectrum(psf: torch.Tensor, nh: int, nw: int) -> torch.Tensor:
    """rfft2 of the centred kernels zero-padded to nh×nw, by two small DFT matmuls: (B, nh, nw//2 + 1)."""
    k = psf.shape[-1]
    cdtype = torch.complex128 if psf.dtype == torch.float64 else torch.complex64
    ey = _dft_factors(nh, k, False, cdtype, psf.device)  # (nh, k)
    ex = _dft_factors(nw, k, True, cdtype, psf.device)  # (k, nw//2+1)
    return torch.matmul(ey, torch.matmul(psf.to(cdtype), ex))


def _fft_convolve(image: torch.Tensor, psf: torch.Tensor, border: str) -> torch.Tensor:
    """True convolution with per-sample odd kernels via reflect/replicate padding and a zero-padded rfft2.

    With p = k//2 border pixels on each side the circular convolution never wraps into the output window,
    so the result equals the padded direct convolution (``filter2d``) up to float rounding.
    """
    h, w = image.shape[-2:]
    k = psf.shape[-1]
    p = k // 2
    padded = torch.nn.functional.pad(image, (p, p, p, p), mode=border)
    nh, nw = _fft_size(h + 2 * p), _fft_size(w + 2 * p)
    spec = torch.fft.rfft2(padded, s=(nh, nw))
    spec = spec * _psf_spectrum(psf, nh, nw).unsqueeze(1)
    out = torch.fft.irfft2(spec, s=(nh, nw))
    return out[..., p : p + h, p : p + w]


def apply_psf(image: torch.Tensor, psf: torch.Tensor) -> torch.Tensor:
    """Convolve every sample with its own PSF in one grouped call (Kornia ``filter2d``).

    Args:
        image: B×C×H×W.
        psf: (B, k, k) or (1, k, k) kernels (true convolution: the kernel is flipped for the
            correlation ``filter2d`` computes). Reflect padding keeps the mean; when the kernel is larger
            than the image, replicate padding is used instead.

    Odd kernels of size >= ``FFT_MIN_KERNEL`` are applied in the Fourier domain (same padding, same
    result up to float rounding, several times faster for the 21–45 px kernels of the corruptions).
    """
    check_tensor(psf, "psf")
    if psf.ndim != 3 or psf.shape[-1] != psf.shape[-2]:
        raise ValueError(f"psf must have shape (B, k, k), got {tuple(psf.shape)}")
    if psf.shape[0] not in (1, image.shape[0]):
        raise ValueError(f"psf batch {psf.shape[0]} does not match image batch {image.shape[0]}")
    k = psf.shape[-1]
    if k == 1:
        return image * psf.to(image.dtype).view(-1, 1, 1, 1)
    border = "reflect" if k // 2 < min(image.shape[-2:]) else "replicate"
    if k >= FFT_MIN_KERNEL and k % 2 == 1 and image.dtype in (torch.float32, torch.float64):
        return _fft_convolve(image, psf.to(device=image.device, dtype=image.dtype), border)
    return kornia.filters.filter2d(image, psf.flip(-1, -2).to(image.dtype), border_type=border)


def _per_sample(v: torch.Tensor, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    return v.to(device=device, dtype=dtype).view(-1, 1, 1, 1)


def form_image(
    clean: torch.Tensor,
    meta: CameraMetadata | None = None,
    defocus_psf: torch.Tensor | None = None,
    motion_psf: torch.Tensor | None = None,
    sources: Sequence[str] = NOISE_SOURCES,
    generator: torch.Generator | None = None,
    quantize: bool = False,
    source_follower_e: torch.Tensor | None = None,
    poisson_exact_below: float = 1e3,
) -> ImageFormation:
    """Corrupt a batch of clean images with the Fig. 3.7 chain.

    Args:
        clean: B×C×H×W in [0, 1] (float16/bfloat16/float32/float64); camhealth images are monochrome
            (C = 1), other C are corrupted channel by channel with independent noise.
        meta: per-sample camera metadata (batch 1 or B); required when ``sources`` is not empty.
        defocus_psf: (B, k, k) defocus kernels, or ``None`` for none.
        motion_psf: (B, k, k) motion kernels, or ``None``.
        sources: which noise sources to realise, a subset of ``("photon", "dark", "readout")``.
        generator: torch generator on the image's device for reproducible noise.
        quantize: round the output to whole DN (straight-through gradient).
        source_follower_e: optional cached :func:`~camhealth.physics.readout_noise.source_follower_sigma_e`.
        poisson_exact_below: electron counts below this are Poisson-sampled exactly, above it with the
            normal approximation.

    Returns:
        :class:`ImageFormation` with the image and the labels.
    """
    check_image(clean, "clean", channels=None)
    if clean.min() < 0 or clean.max() > 1:
        raise ValueError(
            f"clean images must lie in [0, 1] (DN/255), got values in [{clean.min().item():g}, {clean.max().item():g}]"
        )
    sources = tuple(sources)
    unknown = [s for s in sources if s not in NOISE_SOURCES]
    if unknown:
        raise ValueError(f"unknown noise source(s) {unknown}; choose from {list(NOISE_SOURCES)}")
    b = clean.shape[0]
    out_dtype = clean.dtype
    wd = _work_dtype(out_dtype)
    dev = clean.device
    x = clean.to(wd)
    if defocus_psf is not None:
        x = apply_psf(x, defocus_psf)

    zeros = torch.zeros(b, device=dev, dtype=wd)
    if sources:
        if meta is None:
            raise ValueError("form_image needs camera metadata (meta) to realise noise sources")
        if meta.batch_size not in (1, b):
            raise ValueError(f"metadata batch {meta.batch_size} does not match image batch {b}")
        meta = meta.expand(b).to(device=dev)
        to_int = _per_sample(meta.gain_factor / meta.full_well_e, wd, dev)  # intensity per electron
    noise = []  # per-source realised noise in intensity units (before clipping)
    expected = []
    # --- photon shot noise (before motion blur)
    if "photon" in sources:
        electrons = x.clamp_min(0) / to_int
        with torch.no_grad():
            n_pn = (sample_poisson(electrons, generator, poisson_exact_below) - electrons) * to_int
        exp_pn = photon_shot_sigma_patch_dn(x, meta).to(wd)
    else:
        n_pn, exp_pn = None, zeros
    # --- motion blur of signal (and of the photon noise it carries)
    if motion_psf is not None:
        if n_pn is not None:
            both = apply_psf(torch.cat([x, n_pn], dim=1), motion_psf)
            c = x.shape[1]
            x, n_pn = both[:, :c], both[:, c:]
            exp_pn = exp_pn * motion_psf.to(device=dev, dtype=wd).pow(2).flatten(1).sum(1).sqrt().expand(b)
        else:
            x = apply_psf(x, motion_psf)
    signal = x
    if n_pn is not None:
        noise.append(n_pn)
    expected.append(exp_pn)
    # --- dark-current shot noise (signal independent, Poisson in the dark electrons)
    if "dark" in sources:
        dark = _per_sample(dark_signal_e(meta), wd, dev).expand_as(signal).contiguous()
        with torch.no_grad():
            noise.append((sample_poisson(dark, generator, poisson_exact_below) - dark) * to_int)
        expected.append(dark_current_shot_sigma_e(meta).to(wd) * meta.dn_per_electron.to(wd))
    else:
        expected.append(zeros)
    # --- readout noise (Gaussian)
    if "readout" in sources:
        rn_e = readout_sigma_e(meta, source_follower_e).to(wd)
        with torch.no_grad():
            eps = torch.randn(signal.shape, generator=generator, device=dev, dtype=wd)
            noise.append(eps * _per_sample(rn_e, wd, dev) * to_int)
        expected.append(rn_e * meta.dn_per_electron.to(wd))
    else:
        expected.append(zeros)

    # --- gain is folded into to_int; clipping (saturation) and attribution of the clipped noise
    present = [s for s in NOISE_SOURCES if s in sources]
    if noise:
        total_noise = torch.stack(noise).sum(0)
        unclipped = signal + total_noise
        y = unclipped.clamp(0.0, 1.0)
        realised = y.detach() - signal.detach()
        clipped = (unclipped < 0) | (unclipped > 1)
        ratio = torch.where(clipped & (total_noise != 0), realised / torch.where(total_noise == 0, 1.0, total_noise), 1.0)
        sig = []
        it = iter(noise)
        for s in NOISE_SOURCES:
            sig.append((next(it) * ratio).flatten(1).std(1) * 255.0 if s in present else zeros)
        sigma = torch.stack(sig, 1)
        sigma_total = realised.flatten(1).std(1) * 255.0
        clipped_fraction = clipped.flatten(1).to(wd).mean(1)
    else:
        y = signal.clamp(0.0, 1.0)
        sigma = torch.zeros(b, 3, device=dev, dtype=wd)
        sigma_total = zeros
        clipped_fraction = ((signal <= 0) | (signal >= 1)).flatten(1).to(wd).mean(1)
    if quantize:
        y = y + ((y * 255.0).round() / 255.0 - y).detach()
    exp = torch.stack(expected, 1)
    return ImageFormation(
        image=y.to(out_dtype),
        sigma_dn=sigma,
        sigma_total_dn=sigma_total,
        sigma_expected_dn=exp,
        sigma_total_expected_dn=exp.pow(2).sum(1).sqrt(),
        clipped_fraction=clipped_fraction,
        blurred=signal.detach(),
    )
