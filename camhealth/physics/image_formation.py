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
  intensity (times √Σh² of the motion PSF, which averages PN — with the taps that the border padding folds onto
  one pixel counted together, :func:`psf_noise_gain_sq`: a 41-px blur of a 32-px patch reads its photon noise
  several times near the borders, 1.28× √Σh²), DCSN = √(DC·t_exp), RN from Eq. 3.17.

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
import numbers
from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np
import torch

from camhealth._validation import check_finite, check_float, check_image, check_tensor
from camhealth.physics._format import show_outside
from camhealth.physics._psf_common import check_generator
from camhealth.physics.counter_rng import (
    LazyCompiled, check_counter_size, counter_keys, counter_normal, counter_normal_at, counter_normal_expr,
)
from camhealth.physics.dark_current import dark_current_shot_sigma_e, dark_signal_e
from camhealth.physics.metadata import CameraMetadata
from camhealth.physics.photon_shot_noise import photon_shot_sigma_patch_dn
from camhealth.physics.readout_noise import readout_sigma_e

__all__ = [
    "NOISE_SOURCES", "RNG_KINDS", "ImageFormation", "check_rng", "apply_psf", "form_image", "kernel_support_radii", "plan_support_groups",
    "poisson_z_table", "sample_poisson", "sample_poisson_per_sample",
]

#: Noise sources in label order: photon shot noise, dark-current shot noise, readout noise.
NOISE_SOURCES: tuple[str, ...] = ("photon", "dark", "readout")

#: Random-number sources of the noise fields (``rng`` argument): torch's generators, or counter-based draws.
RNG_KINDS: tuple[str, ...] = ("torch", "counter")


def check_rng(rng: str) -> str:
    """``rng`` if it names a random-number source, else a ValueError naming the allowed ones."""
    if rng not in RNG_KINDS:
        raise ValueError(f"rng must be one of {list(RNG_KINDS)}, got {rng!r}")
    return rng


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
        blurred: noise-free blurred image (defocus then motion) B×1×H×W, float32/64, before clipping; it carries
            the blur's gradient where the input requires one (detach it before keeping it beyond the step).
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
FFT_MIN_KERNEL = 39


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

    It also equals :func:`kornia.filters.fft_conv` with ``behaviour="conv"`` (to roundoff; tested), which is
    1.1–1.9× slower on these batches (16–64 patches of 128–512 px, kernels 25–63 px, 1 thread:
    ``python -m camhealth.bench.library_reuse --rows fft``): Kornia transforms the kernel with a full-size ``rfftn`` per call and the padded image at
    its own length, where this takes the kernel's spectrum from two small DFT matmuls (:func:`_psf_spectrum`) and
    pads to a 2·3·5-smooth FFT length (:func:`_fft_size`).
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


#: Cost model of one grouped convolution on the CPU (oneDNN), in multiply-adds per image pixel: a kernel
#: of area a costs about a + ``_PIXEL_OVERHEAD_MACS`` (padding, gather, scatter), and every extra call a
#: fixed ``_CALL_OVERHEAD_MACS`` (Python, dispatch). oneDNN's depthwise convolution vectorises over
#: channels: below 16 channels per call its cost per image rises 5–20× (measured on the 2-core EPYC of
#: docs/benchmarks.md), so groups hold at least ``_MIN_GROUP_CHANNELS`` channels.
_PIXEL_OVERHEAD_MACS = 40.0
_CALL_OVERHEAD_MACS = 3e6
_MIN_GROUP_CHANNELS = 16


def kernel_support_radii(psf: torch.Tensor) -> torch.Tensor:
    """Half-extents (r_y, r_x) [px] of each kernel's non-zero support about its centre: (B, 2) int64.

    A (B, k, k) kernel centred at (k//2, k//2) equals its crop to (2·r_y + 1)×(2·r_x + 1).
    """
    k = psf.shape[-1]
    nz = psf != 0
    dist = (torch.arange(k, device=psf.device) - k // 2).abs()
    ry = torch.where(nz.any(2), dist, torch.zeros_like(dist)).amax(1)
    rx = torch.where(nz.any(1), dist, torch.zeros_like(dist)).amax(1)
    return torch.stack([ry, rx], 1)


def plan_support_groups(radii: torch.Tensor, channels: int = 1, pixels: int = 1) -> list[tuple[torch.Tensor, int, int]]:
    """Split a batch into groups that each convolve with one kernel crop, minimising the estimated cost.

    Samples are ordered by orientation (wide, square, tall support) and size, cut into blocks of at least
    ``_MIN_GROUP_CHANNELS`` channels, and consecutive blocks are joined into groups by dynamic
    programming under the cost model above (a group convolves all its samples with the largest crop of
    its members in each axis).

    Args:
        radii: (B, 2) support half-extents from :func:`kernel_support_radii`.
        channels: image channels C (a group's channel count is C × its samples).
        pixels: H·W per channel.

    Returns:
        ``[(indices, r_y, r_x), …]``: sample indices (int64, on the radii's device) and the crop radii.
    """
    if radii.ndim != 2 or radii.shape[1] != 2 or radii.shape[0] == 0:
        raise ValueError(f"radii must have shape (B, 2) with B >= 1, got {tuple(radii.shape)}")
    if int(channels) < 1 or int(pixels) < 1:
        raise ValueError(f"channels = {channels} and pixels = {pixels} must be >= 1")
    r = radii.detach().to("cpu", torch.int64)
    b = r.shape[0]
    ry, rx = r[:, 0], r[:, 1]
    # orientation class first (−1 wide, 0 near-square, +1 tall), then the larger radius
    orient = torch.sign(ry - rx) * ((ry - rx).abs() * 2 > torch.maximum(ry, rx)).long()
    order = torch.argsort(orient * 4096 + torch.maximum(ry, rx) * 64 + torch.minimum(ry, rx), stable=True)
    block = max(1, -(-_MIN_GROUP_CHANNELS // max(int(channels), 1)))
    starts = list(range(0, b, block))
    if len(starts) > 1 and b - starts[-1] < block:  # a short last block joins its neighbour
        starts.pop()
    bounds = starts + [b]
    ry_o, rx_o = ry[order].tolist(), rx[order].tolist()
    nb = len(starts)
    # best[j]: least cost of the first j blocks; prefix maxima per candidate group computed on the fly
    best = [0.0] + [float("inf")] * nb
    cut = [0] * (nb + 1)
    for j in range(1, nb + 1):
        my = mx = 0
        for i in range(j - 1, -1, -1):  # group = blocks i..j-1
            lo, hi = bounds[i], bounds[i + 1]
            my, mx = max(my, max(ry_o[lo:hi])), max(mx, max(rx_o[lo:hi]))
            n = bounds[j] - bounds[i]
            c = best[i] + n * channels * pixels * ((2 * my + 1) * (2 * mx + 1) + _PIXEL_OVERHEAD_MACS) + _CALL_OVERHEAD_MACS
            if c < best[j]:
                best[j], cut[j] = c, i
    groups = []
    j = nb
    while j > 0:
        i = cut[j]
        idx = order[bounds[i] : bounds[j]]
        groups.append((idx.to(radii.device), int(ry[idx].max()), int(rx[idx].max())))
        j = i
    return groups[::-1]


def _convolve_same(image: torch.Tensor, psf: torch.Tensor, border: str) -> torch.Tensor:
    """True convolution of every sample with its own (B, kh, kw) odd kernel, output of the input's size."""
    kh, kw = psf.shape[-2:]
    if kh == kw and kh >= FFT_MIN_KERNEL and kh % 2 == 1 and image.dtype in (torch.float32, torch.float64):
        return _fft_convolve(image, psf.to(device=image.device, dtype=image.dtype), border)
    import kornia  # here, not at the top: inference never blurs, and importing Kornia lengthens its cold start

    return kornia.filters.filter2d(image, psf.to(image.dtype), border_type=border, behaviour="conv")


def apply_psf(image: torch.Tensor, psf: torch.Tensor, group_by_support: bool = True) -> torch.Tensor:
    """Convolve every sample with its own PSF in a few grouped calls (Kornia ``filter2d``, the batch folded
    into channels; never a loop over samples).

    Args:
        image: B×C×H×W.
        psf: (B, k, k) or (1, k, k) kernels (true convolution: the kernel is flipped for the
            correlation ``filter2d`` computes). Reflect padding keeps the mean; when the kernel is larger
            than the image, replicate padding is used instead.
        group_by_support: crop each kernel to its non-zero support and convolve the batch in a few
            groups of equal crop size (:func:`plan_support_groups`), instead of every sample with the full
            k×k kernel. A 5 px disk or a horizontal motion line then costs a fraction of the 23×23 kernel
            the batch's largest blur needs. Same result up to float summation order (the dropped taps
            are exact zeros; the padding is chosen from the full kernel size either way).

    The image must be a floating B×C×H×W tensor (else ``TypeError``/``ValueError``: an integer image would be
    convolved with the kernel cast to its dtype, i.e. truncated to 0). The kernels must be finite and of odd size k
    (a centre pixel: an even kernel would shift the image by half a pixel), else ``ValueError``; they are applied as
    given (any sum, any sign): the checks that a blur kernel is non-negative and sums to 1 are :func:`form_image`'s.

    Odd kernels of size >= ``FFT_MIN_KERNEL`` are applied in the Fourier domain (same padding, same
    result up to float rounding; faster than the direct convolution for the 45 px kernels of non-linear
    motion, while oneDNN's direct convolution wins up to ~31 px on CPU).
    """
    check_float(image, "image")
    if image.ndim != 4:
        raise ValueError(f"image must have shape B×C×H×W (4 dims), got {tuple(image.shape)}")
    check_tensor(psf, "psf")
    if psf.ndim != 3 or psf.shape[-1] != psf.shape[-2]:
        raise ValueError(f"psf must have shape (B, k, k), got {tuple(psf.shape)}")
    _check_odd_psf(psf, "psf")
    if psf.shape[0] not in (1, image.shape[0]):
        raise ValueError(f"psf batch {psf.shape[0]} does not match image batch {image.shape[0]}")
    check_finite(psf, "psf")  # a NaN tap would turn every image it touches into NaN
    k = psf.shape[-1]
    if k == 1:
        return image * psf.to(image.dtype).view(-1, 1, 1, 1)
    border = "reflect" if k // 2 < min(image.shape[-2:]) else "replicate"
    if not group_by_support or psf.shape[0] == 1 or (k >= FFT_MIN_KERNEL and k % 2 == 1):
        return _convolve_same(image, psf, border)
    groups = plan_support_groups(kernel_support_radii(psf), image.shape[1], image.shape[-2] * image.shape[-1])
    c = k // 2
    if len(groups) == 1:
        _, ry, rx = groups[0]
        return _convolve_same(image, psf[:, c - ry : c + ry + 1, c - rx : c + rx + 1], border)
    out = None
    for idx, ry, rx in groups:
        kern = psf.index_select(0, idx)[:, c - ry : c + ry + 1, c - rx : c + rx + 1]
        idx = idx.to(image.device)  # the kernels may live on another device than the images (filter2d moves them)
        part = _take_samples(image, idx)
        res = part * kern.to(part.dtype).view(-1, 1, 1, 1) if ry == rx == 0 else _convolve_same(part, kern, border)
        if out is None:
            out = res.new_empty(image.shape)
        out = out.index_copy(0, idx, res) if res.requires_grad else out.index_copy_(0, idx, res)
    return out


@functools.lru_cache(maxsize=64)
def _fold_overlap(n: int, k: int, border: str) -> torch.Tensor:
    """(k, k) float64: for the taps a, b of a k-wide kernel run over an n-px axis with ``border`` padding (as
    :func:`apply_psf` pads), the share of the n output positions at which both taps read the same input pixel —
    1 on the diagonal, and off it where the padding folds two taps onto one pixel near a border."""
    front = (k - 1) // 2
    idx = torch.arange(n, dtype=torch.float64).view(1, 1, n)
    padded = torch.nn.functional.pad(idx, (front, k - 1 - front), mode=border)[0, 0]
    win = padded.unfold(0, k, 1)  # (n, k): the input pixel each tap reads, per output position
    return (win[:, :, None] == win[:, None, :]).double().mean(0)


def psf_noise_gain_sq(psf: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(B,) the factor by which :func:`apply_psf` scales the variance of white noise on a ``height``×``width`` image,
    averaged over its pixels: Σ_a Σ_b h_a h_b · P(taps a and b read the same pixel) with the border padding that
    :func:`apply_psf` uses. Away from the borders it is Σ h²; near them the padding lets several taps read one noise
    sample, which raises it (by up to 2× per axis with reflect padding, more with replicate padding of a kernel
    larger than the image)."""
    psf = psf.double()
    k = psf.shape[-1]
    if k == 1:
        return psf.flatten(1).square().sum(1)
    border = "reflect" if k // 2 < min(height, width) else "replicate"
    kern = psf.flip(-1, -2).to("cpu")  # the correlation kernel filter2d runs
    my, mx = _fold_overlap(int(height), k, border), _fold_overlap(int(width), k, border)
    return (kern * (my @ kern @ mx.T)).sum((-1, -2)).to(psf.device)


def _take_samples(t: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``t.index_select(0, idx)`` for a B×… tensor, as an index_select of whole rows of a (1, B, N) view: on CPU
    the dim-0 form gathers element by element (≈ 1 ms for 16 of 32 192² images on one thread; ≈ 130 ms with two
    threads while another process keeps both cores busy), the row form copies contiguous rows (≈ 0.06 ms).
    Same values, differentiable."""
    n = idx.numel()
    return t.reshape(1, t.shape[0], -1).index_select(1, idx).view(n, *t.shape[1:])


#: Poisson rates below this are drawn with ``torch.poisson``; from it up to ``exact_below`` by exact
#: inversion started from an asymptotic expansion of the quantile (:func:`_poisson_quantile_expansion`).
_EXPANSION_MIN_RATE = 10.0
#: Beyond this |z| the expansion is not trusted at all; those (rare) draws are settled with the exact CDF.
_EXPANSION_MAX_Z = 5.0


def _poisson_quantile_expansion(rate: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Asymptotic (large-λ) expansion of the Poisson quantile at u = Φ(z), and its error margin.

    The exact quantile min{k : F(k) ≥ u} is floor(y) with y = 1 + x(u) and x the root of
    Q(x + 1, λ) = u (Q the regularised upper incomplete gamma, F(k) = Q(k + 1, λ)). Its expansion in
    powers of λ^-1/2 (the normal-asymptotic inversion of the incomplete gamma function, cf. Temme 1992;
    Giles 2016) is

        y = λ + √λ·z + (z² + 2)/6 − (z/36 + z³/72)/√λ + (−8/405 + 7z²/810 + z⁴/270)/λ + O(λ^-3/2).

    The returned ``margin`` is 1/2 − δ with the error envelope δ = (0.04 + 0.01·z⁶)/λ^1.5 plus a bound
    on the float rounding of y: floor(y) is the exact quantile wherever |frac(y) − 1/2| < margin. The envelope
    exceeds the true error of y by a factor ≥ 2.5 for every λ ≥ 10, |z| ≤ 5 and quantile boundary with
    1e-10 < F(k) < 1 − 1e-10 (checked against SciPy on a dense grid in tests/bench). Computed in place
    to keep large temporaries few.
    """
    eps = torch.finfo(rate.dtype).eps
    z2 = z * z
    inv_s = rate.clamp_min(1.0).rsqrt_()
    # (−8/405 + z²·(7/810 + z²/270))/λ
    y = torch.mul(z2, 1.0 / 270.0).add_(7.0 / 810.0).mul_(z2).sub_(8.0 / 405.0).mul_(inv_s).mul_(inv_s)
    # − z·(1/36 + z²/72)/√λ
    t = torch.mul(z2, 1.0 / 72.0).add_(1.0 / 36.0).mul_(z).mul_(inv_s)
    y.sub_(t).add_(z2, alpha=1.0 / 6.0).add_(rate).add_(1.0 / 3.0)
    y.addcmul_(torch.mul(rate, inv_s, out=t), z)  # + √λ·z
    # margin = 1/2 − (0.04 + 0.01·z⁶)/λ^1.5 − 12·eps·(λ + z² + 2)   (12·eps·(…) bounds the rounding of y)
    far = z2 > _EXPANSION_MAX_Z**2
    margin = torch.mul(z2, z2, out=t).mul_(z2).mul_(0.01).add_(0.04).mul_(inv_s).mul_(inv_s).mul_(inv_s)
    margin.add_(z2.add_(rate).add_(2.0).mul_(12.0 * eps)).neg_().add_(0.5)
    margin.masked_fill_(far, -1.0)
    return y, margin


def _poisson_fixup(rate: torch.Tensor, z: torch.Tensor, k: torch.Tensor, frac: torch.Tensor, margin: torch.Tensor) -> torch.Tensor:
    """Exact inversion min{k : F(k) ≥ Φ(z)} for entries whose expansion y = k + frac is too close to a
    quantile boundary, with the exact CDF F(k) = Q(k + 1, λ) (regularised upper incomplete gamma)."""
    lam = rate.double()
    u = torch.special.ndtr(z.double())
    k = k.double()
    out = torch.empty_like(lam)
    near = margin > 0  # error envelope < 1/2: the true boundary is the nearest integer to y
    if bool(near.any()):
        i = near.nonzero().squeeze(1)
        kb = k[i] - (frac[i] < 0.5).double()  # the answer is kb or kb + 1
        cdf = torch.special.gammaincc(kb.clamp_min(0.0) + 1.0, lam[i])
        out[i] = torch.where(kb < 0, torch.zeros_like(kb), kb + (u[i] > cdf).double())
    if not bool(near.all()):  # far tails: walk from floor(y) to the exact quantile
        i = (~near).nonzero().squeeze(1)
        kk, li, ui = k[i].clamp_min(0.0), lam[i], u[i]
        for _ in range(100_000):
            up = ui > torch.special.gammaincc(kk + 1.0, li)
            down = ~up & (kk > 0) & (ui <= torch.special.gammaincc(kk.clamp_min(1.0), li))
            if not bool((up | down).any()):
                break
            kk = kk + up.double() - down.double()
        out[i] = kk
    return out.to(rate.dtype)


def _raise_bad_rate(rate: torch.Tensor, flat: torch.Tensor) -> None:
    """ValueError naming the first rate of ``rate`` (flattened: ``flat``) that is NaN, infinite or negative."""
    bad = ~torch.isfinite(flat) | (flat < 0)
    i = int(bad.nonzero()[0, 0])
    where = ", ".join(str(int(j)) for j in torch.unravel_index(torch.tensor(i), tuple(rate.shape))) if rate.ndim else ""
    raise ValueError(
        f"Poisson rate[{where}] = {float(flat[i]):g} is out of the allowed range [0, inf) (expected counts must be "
        f"finite and non-negative; {int(bad.sum())} of {flat.numel()} rates are not)"
    )


def sample_poisson(
    rate: torch.Tensor, generator: torch.Generator | None = None, exact_below: float = 1e3, rng: str = "torch"
) -> torch.Tensor:
    """Poisson samples of ``rate`` (finite, ≥ 0; a NaN, infinite or negative rate raises ``ValueError`` naming it).
    Rates ≥ ``exact_below`` use the normal approximation N(λ, λ) (skewness 1/√λ ≤ 0.03 there); smaller rates are
    drawn exactly.

    ``rng`` picks the source of the standard normals z: ``"torch"`` (``torch.randn`` from ``generator``) or
    ``"counter"`` (:mod:`~camhealth.physics.counter_rng`, keys drawn from ``generator``). With ``"counter"``
    one compiled pass computes z, the normal approximation and the quantile expansion for every entry and
    marks the entries that need more (λ < 10, or an expansion within its error bound of a boundary); only
    those are then settled, with z recomputed at their indices. The algorithm, hence the distribution, is
    the same.

    Exact draws for 10 ≤ λ < ``exact_below`` invert the Poisson CDF at u = Φ(z) for one standard normal
    z per entry: an asymptotic expansion gives the quantile directly, and the few entries (≤ 1 %) whose
    expansion lands within its error bound of a quantile boundary are settled with the exact CDF. This is
    equal in distribution to ``torch.poisson`` and costs little more than one ``randn`` (``torch.poisson``
    runs a scalar sampler per element on CPU, ~2–3× slower here). Rates below 10 use ``torch.poisson``
    (a vectorised sequential inversion was tried and is slower on CPU).
    """
    exact_below = _check_exact_below(exact_below, "exact_below")
    check_generator(generator)
    if rate.numel() == 0:
        return rate.clone()
    work = (rate if rate.dtype in (torch.float32, torch.float64) else rate.float()).reshape(-1)
    lo, hi = (float(t) for t in torch.aminmax(work))
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo < 0:  # NaN propagates into lo/hi
        _raise_bad_rate(rate, work)
    small_below = min(_EXPANSION_MIN_RATE, exact_below)
    if hi < small_below:  # all small: exact scalar sampler
        return torch.poisson(work, generator=generator).to(rate.dtype).view_as(rate)
    if check_rng(rng) == "counter":
        one = torch.ones(1, 1, dtype=work.dtype, device=work.device)
        out = _sample_poisson_counter(work.view(1, -1), one, work.numel(), generator, exact_below, small_below)
        return out.to(rate.dtype).view_as(rate)
    # N(λ, λ) everywhere first (the answer for λ ≥ exact_below); the exact regimes overwrite their entries
    z = torch.randn(work.shape, generator=generator, device=work.device, dtype=work.dtype)
    out = work.sqrt().mul_(z).add_(work)
    if lo < exact_below:
        # the exact regimes run only on their own entries, found by one nonzero (a gather costs less than
        # the expansion's ~25 full-size passes); then split into expansion (λ ≥ 10) and scalar (λ < 10) draws
        i = (work < exact_below).nonzero().squeeze(1)
        lam = work[i]
        small = lam < small_below
        mid = (~small).nonzero().squeeze(1)
        if mid.numel():
            lam_m, zi = lam[mid], z[i[mid]]
            y, margin = _poisson_quantile_expansion(lam_m, zi)
            k = torch.floor(y)
            frac = y.sub_(k)
            check = (torch.sub(frac, 0.5).abs_() > margin).nonzero().squeeze(1)  # within the error envelope
            if check.numel():
                k.index_copy_(0, check, _poisson_fixup(lam_m[check], zi[check], k[check], frac[check], margin[check]))
            out.index_copy_(0, i[mid], k)
        if lo < small_below:
            j = small.nonzero().squeeze(1)
            out.index_copy_(0, i[j], torch.poisson(lam[j], generator=generator))
    return out.to(rate.dtype).view_as(rate)


def _k_poisson_counter(
    signal: torch.Tensor, unit: torch.Tensor, keys: torch.Tensor, n: int, exact_below: float, small_below: float,
    centred: bool, small_value: float, with_signal: bool,
) -> torch.Tensor:
    """One pass of :func:`sample_poisson` with counter normals for (R, n) draws of the rates
    λ = max(signal, 0)/unit (signal (R, n) or (R, 1), unit broadcastable): N(λ, λ) for λ ≥ ``exact_below``, the
    quantile expansion's floor where it is reliable, NaN where the entry needs the exact CDF, and
    ``small_value`` for λ < ``small_below`` (NaN: settle them with ``torch.poisson``; a number: the caller
    draws them otherwise). ``centred``: return the noise (draw − λ)·unit instead of the draw.
    ``with_signal``: return ``cat([signal, result], 1)`` (R, 2n), the input of the two-channel motion blur."""
    r = signal.shape[0]
    rate = signal.clamp_min(0) / unit
    z = counter_normal_expr(torch.arange(r * n, dtype=torch.int32, device=keys.device).view(r, n), keys, rate.dtype)
    approx = rate + rate.sqrt() * z
    y, margin = _poisson_quantile_expansion(rate.expand(r, n), z)
    k = torch.floor(y)
    exact = torch.where(((y - k) - 0.5).abs() < margin, k, torch.nan)
    draw = torch.where(rate >= exact_below, approx, exact)
    out = (draw - rate) * unit if centred else draw
    out = torch.where(rate < small_below, small_value, out)
    return torch.cat([signal.expand(r, n), out], 1) if with_signal else out


_poisson_counter = LazyCompiled(_k_poisson_counter)


def _sample_poisson_counter(
    signal: torch.Tensor, unit: torch.Tensor, n: int, generator: torch.Generator | None, exact_below: float,
    small_below: float, centred: bool = False, small_value: float = math.nan, with_signal: bool = False,
) -> torch.Tensor:
    """(R, n) Poisson draws of the float32/64 rates λ = max(signal, 0)/unit (signal (R, n) or (R, 1), unit (R, 1)
    or (1, 1)) with counter-based normals (see :func:`sample_poisson` and :func:`_k_poisson_counter`)."""
    r = signal.shape[0]
    check_counter_size(r * n)
    keys = counter_keys(generator, signal.device)
    out = _poisson_counter(
        signal, unit, keys, n, float(exact_below), float(small_below), bool(centred), float(small_value), bool(with_signal)
    )
    res = out[:, n:] if with_signal else out
    rows, cols = torch.isnan(res).nonzero(as_tuple=True)
    if rows.numel():
        unit_j = unit.expand(r, n)[rows, cols]
        lam = signal.expand(r, n)[rows, cols].clamp_min(0) / unit_j  # the kernel's λ, element by element
        draw = torch.empty_like(lam)
        small = lam < small_below
        mid = (~small).nonzero().squeeze(1)
        if mid.numel():  # the expansion is within its error bound of a boundary (or |z| > 5): exact CDF
            flat = rows[mid].to(torch.int32) * n + cols[mid].to(torch.int32)
            lam_m, zi = lam[mid], counter_normal_at(flat, keys, lam.dtype)
            y, margin = _poisson_quantile_expansion(lam_m, zi)
            k = torch.floor(y)
            draw[mid] = _poisson_fixup(lam_m, zi, k, y.sub_(k), margin)
        if bool(small.any()):
            draw[small] = torch.poisson(lam[small], generator=generator)
        res[rows, cols] = (draw - lam) * unit_j if centred else draw
    return out


def _photon_noise_counter(
    x: torch.Tensor, to_int: torch.Tensor, generator: torch.Generator | None, exact_below: float,
    with_signal: bool = False,
) -> torch.Tensor:
    """Photon shot noise in intensity units of B×C×H×W intensities ``x`` with ``to_int`` (B, 1, 1, 1) intensity
    per electron: (Poisson(x/to_int) − x/to_int)·to_int in one compiled pass (plus the few exact settlements);
    ``with_signal``: ``cat([x, noise], 1)``, B×2C×H×W, written by the same pass."""
    b, c = x.shape[:2]
    n = x[0].numel()
    small_below = min(_EXPANSION_MIN_RATE, exact_below)
    out = _sample_poisson_counter(
        x.reshape(b, n), to_int.reshape(b, 1), n, generator, exact_below, small_below, True, with_signal=with_signal
    )
    return out.view(b, 2 * c, *x.shape[2:]) if with_signal else out.view_as(x)


def _dark_noise_counter(
    dark_e: torch.Tensor, to_int: torch.Tensor, shape: Sequence[int], generator: torch.Generator | None,
    exact_below: float, dtype: torch.dtype,
) -> torch.Tensor:
    """Dark-current shot noise in intensity units, (Poisson(λ_b) − λ_b)·to_int_b for every pixel of sample b,
    ``dark_e`` (B,) float64 dark electrons, ``to_int`` (B, 1, 1, 1): the counter path of
    :func:`sample_poisson_per_sample` (one per-sample z-space table, one compiled pass), centred and scaled in
    the same pass."""
    b = int(shape[0])
    n = 1
    for d in shape[1:]:
        n *= int(d)
    unit = to_int.reshape(b, 1).to(dtype)
    return _poisson_per_sample_counter(dark_e, b, n, generator, exact_below, dtype, unit).view(*shape)


#: Half-width of the z range of the per-sample inversion tables: counter normals have |z| ≤ 5.9.
_Z_TABLE_HALF_RANGE = 6.0
#: Fewest cells of a per-sample inversion table (doubled until no cell holds two quantile boundaries).
_Z_TABLE_MIN_CELLS = 1024
#: Most cells (2 MB per sample): enough for boundaries 1/√λ apart up to λ ≈ 4.8e8.
_Z_TABLE_MAX_CELLS = 2**18


def poisson_z_table(rate: torch.Tensor, exact_below: float = 1e3, cells: int = _Z_TABLE_MIN_CELLS) -> torch.Tensor:
    """Per-sample inversion tables of the Poisson quantile in the normal deviate z: (B, cells') float64.

    For a rate λ the draw of the inverse-CDF method at u = Φ(z) is k(z) = min{k : F(k) ≥ Φ(z)} = #{j : t_j < z}
    with the boundaries t_j = Φ⁻¹(F(j)), F(j) = Q(j + 1, λ) (computed as Φ⁻¹(F) below the median and
    −Φ⁻¹(1 − F) above it, so that neither tail loses precision). The range |z| ≤ 6 is cut into ``cells'`` equal
    cells (``cells`` doubled until no cell holds two boundaries; the boundaries are ≈ 1/√λ apart near the mode,
    so 1 024 cells suffice up to λ ≈ 7 000). Cell c stores ``base + s/2``: ``base`` = #{j : t_j < z_c} at its
    left edge z_c, and s ∈ [0, 1) the position (t − z_c)/w of the one boundary t inside the cell (s = 1.5 if
    none). A draw is then ``base + (frac > s)`` with frac = (z − z_c)/w — one table lookup, exact (up to the
    float64 rounding of t) for every z of the range. Rows with λ ≥ ``exact_below`` (the normal
    approximation) get an unused table of λ = 0.
    """
    exact_below = _check_exact_below(exact_below, "exact_below")
    lam = torch.as_tensor(rate).detach().to(torch.float64)
    if lam.ndim != 1:
        raise ValueError(f"rate must have shape (B,), got {tuple(lam.shape)}")
    if bool((lam < 0).any()) or not bool(torch.isfinite(lam).all()):
        raise ValueError(f"Poisson rates must be finite and >= 0, got {lam.tolist()}")
    small = lam < exact_below
    lam_t = torch.where(small, lam, torch.zeros_like(lam))
    top = float(lam_t.max()) if lam_t.numel() else 0.0
    # per row the counts k_lo … k_lo + K − 1 with F(k_lo − 1) < 1e-10 < Φ(−6) (lower tail ≤ exp(−49/2)) and
    # 1 − F beyond the last < 1e-15: their boundaries are the only ones within |z| ≤ 6 (the rest fold into
    # base = k_lo below and the last count above)
    k_lo = (lam_t - 7.0 * lam_t.sqrt()).floor().clamp_min(0.0)
    k_len = int(math.ceil(15.0 * math.sqrt(top) + 30.0))
    ks = k_lo[:, None] + torch.arange(k_len, dtype=torch.float64, device=lam.device)[None, :]
    # F and 1 − F from the probabilities of the window (one gammaincc per row for the mass below it;
    # cumulative sums instead of an incomplete-gamma evaluation per count: ~20× faster, same values to ~1e-13)
    pmf = torch.exp(torch.xlogy(ks, lam_t[:, None]) - lam_t[:, None] - torch.lgamma(ks + 1.0))
    below_window = torch.where(k_lo > 0, torch.special.gammaincc(k_lo.clamp_min(1.0), lam_t), torch.zeros_like(lam_t))
    lower = torch.cumsum(pmf, 1).add_(below_window[:, None])  # F(j) = P(X ≤ j)
    upper = torch.cumsum(pmf.flip(1), 1).flip(1) - pmf  # 1 − F(j) = P(X > j) within the window (+ < 1e-15)
    t = torch.special.ndtri(torch.minimum(lower, upper))
    t = torch.where(lower < 0.5, t, -t)
    t[:, -1] = math.inf  # the tail beyond (< 1e-15) is folded into the last count
    t = torch.cummax(t, 1).values.contiguous()  # guard the order against rounding between the two branches
    cells = int(cells)
    while True:
        w = 2.0 * _Z_TABLE_HALF_RANGE / cells
        edges = torch.arange(cells + 1, dtype=torch.float64, device=lam.device) * w - _Z_TABLE_HALF_RANGE
        below = torch.searchsorted(t, edges.expand(t.shape[0], -1).contiguous())  # #{t_j < edge}
        count = below[:, 1:] - below[:, :-1]
        crowded = int(count.max()) > 1
        if not crowded or cells >= _Z_TABLE_MAX_CELLS:
            break
        cells *= 2
    if crowded:
        raise ValueError(
            f"Poisson rate {top:g} e⁻ is too large for exact per-sample draws (at most ≈ {(_Z_TABLE_MAX_CELLS / 12) ** 2:.2g} "
            f"e⁻ with {_Z_TABLE_MAX_CELLS} table cells); lower exact_below ({exact_below:g}) so that such rates use "
            "the normal approximation"
        )
    base = below[:, :-1]
    inner = torch.gather(t, 1, base.clamp(max=k_len - 1))
    s = torch.where(count == 1, (inner - edges[:-1]) / w, torch.full_like(inner, 1.5)).clamp(0.0, 1.5)
    return base.to(torch.float64) + k_lo[:, None] + 0.5 * s


def _poisson_z_expr(
    table: torch.Tensor, rate: torch.Tensor, keys: torch.Tensor, index: torch.Tensor, exact_below: float
) -> torch.Tensor:
    """Draws at the counter normals z of the elements ``index`` (int32, (R, n)) for the per-row rates ``rate``
    (R, 1): the z-table lookup of :func:`poisson_z_table` where λ < ``exact_below``, λ + √λ·z above; an
    element-wise expression for use inside compiled kernels."""
    cells = table.shape[1]
    z = counter_normal_expr(index, keys, rate.dtype)
    pos = (z.to(torch.float64) + _Z_TABLE_HALF_RANGE) * (cells / (2.0 * _Z_TABLE_HALF_RANGE))
    cell = pos.floor().clamp(0, cells - 1)
    v = torch.gather(table, 1, cell.to(torch.int64))
    base = v.floor()
    draw = (base + ((pos - cell) > (v - base) * 2.0).to(torch.float64)).to(rate.dtype)
    return torch.where(rate >= exact_below, rate + rate.sqrt() * z, draw)


def _k_poisson_z_table(
    table: torch.Tensor, rate: torch.Tensor, scale: torch.Tensor, keys: torch.Tensor, n: int, exact_below: float,
    centred: bool,
) -> torch.Tensor:
    """(R, n) draws of the per-row rates ``rate`` (R, 1) (:func:`_poisson_z_expr`) times ``scale`` (R, 1) and, if
    ``centred``, minus λ first."""
    r = table.shape[0]
    draw = _poisson_z_expr(table, rate, keys, torch.arange(r * n, dtype=torch.int32, device=keys.device).view(r, n), exact_below)
    return (draw - rate) * scale if centred else draw * scale


_poisson_z_draws = LazyCompiled(_k_poisson_z_table)


def _poisson_per_sample_spec(
    lam: torch.Tensor, b: int, n: int, generator: torch.Generator | None, exact_below: float, wd: torch.dtype,
    unit: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(z-table, λ (B, 1), unit (B, 1), keys) of B×n counter draws of the per-sample rates ``lam`` (B,) float64 in
    the work dtype ``wd``: what the compiled passes (:func:`_k_poisson_z_table`, :func:`_k_noise_clip_and_label`)
    evaluate. Draws the field's keys from ``generator``."""
    check_counter_size(b * n)
    keys = counter_keys(generator, lam.device)
    rate = lam.to(wd)[:, None]
    scale = torch.ones_like(rate) if unit is None else unit.reshape(b, 1).to(wd)
    return poisson_z_table(lam, exact_below), rate, scale, keys


def _poisson_per_sample_counter(
    lam: torch.Tensor, b: int, n: int, generator: torch.Generator | None, exact_below: float, dtype: torch.dtype,
    unit: torch.Tensor | None = None,
) -> torch.Tensor:
    """(B, n) Poisson draws of the per-sample rates ``lam`` (B,) float64 with counter normals (one compiled pass);
    ``unit`` (B, 1): return (draw − λ)·unit instead."""
    wd = dtype if dtype in (torch.float32, torch.float64) else torch.float32
    table, rate, scale, keys = _poisson_per_sample_spec(lam, b, n, generator, exact_below, wd, unit)
    return _poisson_z_draws(table, rate, scale, keys, n, float(exact_below), unit is not None).to(dtype)


def sample_poisson_per_sample(
    rate: torch.Tensor, shape: Sequence[int], generator: torch.Generator | None = None, exact_below: float = 1e3,
    dtype: torch.dtype = torch.float32, rng: str = "torch",
) -> torch.Tensor:
    """Poisson samples of shape ``shape`` = (B, …) whose rate is constant within each sample: ``rate`` (B,) ≥ 0
    (e.g. the dark electrons of a frame, the same at every pixel).

    Rates ≥ ``exact_below`` use the normal approximation N(λ, λ), as :func:`sample_poisson`. Smaller rates are
    drawn by inverting each sample's tabulated CDF F(k) = Q(k + 1, λ) (float64, k up to λ + 12√λ + 24, beyond
    which the tail mass is < 1e-15) at a uniform u: a guide table of 4·K cells gives the smallest candidate k
    for u's cell in one table lookup, and the few draws whose u lies above F(k) are advanced to the exact quantile.
    u is a float32 uniform (multiples of 2⁻²⁴), so the draw is the exact inverse-CDF draw on that grid. Costs
    about one ``rand`` plus three gathers per element, ~10× less than ``torch.poisson`` (a scalar sampler per
    element) at λ ≈ 5.

    ``dtype`` is float32 or float64 (else ``TypeError``): half-precision formats cannot hold the counts.

    ``rng``: ``"torch"`` draws u and z with ``torch.rand``/``torch.randn`` from ``generator``. ``"counter"``
    inverts at the counter normal z of each element (:mod:`~camhealth.physics.counter_rng`, keys from
    ``generator``) with a per-sample z-space table (:func:`poisson_z_table`): the draw is min{k : F(k) ≥ Φ(z)}
    for λ < ``exact_below`` and λ + √λ·z above, in one compiled pass with a single table lookup per element.
    """
    check_rng(rng)
    exact_below = _check_exact_below(exact_below, "exact_below")
    check_generator(generator)
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(
            f"dtype must be torch.float32 or torch.float64 for Poisson counts (float16 overflows above 65 504 e⁻ and "
            f"bfloat16 rounds counts above 256), got {dtype}"
        )
    rate = torch.as_tensor(rate)
    b = int(shape[0])
    if rate.ndim != 1 or rate.shape[0] != b:
        raise ValueError(f"rate must have shape ({b},) for samples of shape {tuple(shape)}, got {tuple(rate.shape)}")
    n = 1
    for d in shape[1:]:
        n *= int(d)
    lam = rate.detach().to(dtype=torch.float64)
    if bool((lam < 0).any()) or not bool(torch.isfinite(lam).all()):
        raise ValueError(f"Poisson rates must be finite and >= 0, got {lam.tolist()}")
    if rng == "counter":  # one per-sample z-space table and one compiled pass (poisson_z_table)
        return _poisson_per_sample_counter(lam, b, n, generator, exact_below, dtype).view(*shape)
    out = torch.empty(b, n, dtype=dtype, device=rate.device)
    large = lam >= exact_below
    if bool(large.any()):
        i = large.nonzero().squeeze(1)
        z = torch.randn(int(i.numel()), n, generator=generator, dtype=dtype, device=rate.device)
        out[i] = z.mul_(lam[i].sqrt().to(dtype)[:, None]).add_(lam[i].to(dtype)[:, None])
    if not bool(large.all()):
        i = (~large).nonzero().squeeze(1)
        lam_s = lam[i]
        top = float(lam_s.max())
        k_len = int(math.ceil(top + 12.0 * math.sqrt(top) + 24.0))
        ks = torch.arange(k_len, dtype=torch.float64, device=rate.device)
        cdf = torch.special.gammaincc(ks[None, :] + 1.0, lam_s[:, None])  # F(k) = P(X ≤ k), (b', K)
        cdf[:, -1] = 1.0  # the tail beyond K (< 1e-15) is folded into the last entry
        # F rounded *down* to float32: for every float32 u, u > F ⟺ u > F32 (no float32 lies in (F32, F])
        cdf32 = cdf.float()
        cdf32 = torch.where(cdf32.double() > cdf, torch.nextafter(cdf32, torch.zeros_like(cdf32)), cdf32)
        cells = 4 * k_len
        edges = torch.arange(cells, dtype=torch.float64, device=rate.device) / cells
        guide = torch.searchsorted(cdf, edges.expand(lam_s.shape[0], -1).contiguous())  # smallest k: F(k) ≥ j/cells
        # one table of (k, F32(k)) pairs per cell, packed as int64 so that a single lookup fetches both
        pairs = torch.stack([guide.float(), torch.gather(cdf32, 1, guide)], dim=2).view(torch.int64).squeeze(2)
        bs = int(i.numel())
        u = torch.rand(bs, n, generator=generator, dtype=torch.float32, device=rate.device)
        # flat cell index into the (bs, cells) table: index_select is ~5× faster than a 2-D gather here
        itype = torch.int32 if bs * cells < 2**31 else torch.int64
        cell = u.mul(cells).to(itype).clamp_(max=cells - 1)
        cell += torch.arange(0, bs * cells, cells, dtype=itype, device=rate.device)[:, None]
        got = pairs.view(-1).index_select(0, cell.view(-1)).view(torch.float32).view(bs, n, 2)
        del cell
        k = got[..., 0]  # a strided view: the few corrections below write into ``got``
        rows, cols = (u > got[..., 1]).nonzero(as_tuple=True)  # u beyond F(k): the quantile is larger
        for _ in range(2):  # usually one step; a cell can hold several boundaries only in the far tail
            if not rows.numel():
                break
            kk = k[rows, cols] + 1.0
            k[rows, cols] = kk
            still = u[rows, cols] > cdf32[rows, kk.long()]
            rows, cols = rows[still], cols[still]
        if rows.numel():  # the rest (tail cells): binary search of each draw's own CDF row
            uu = u[rows, cols]
            k[rows, cols] = torch.searchsorted(cdf32[rows], uu[:, None]).squeeze(1).float()
        out[i] = k.to(dtype)
    return out.view(*shape)


def _k_noise_clip_and_label(
    signal: torch.Tensor, fields: tuple[torch.Tensor, ...], dark: tuple[torch.Tensor, ...] | None,
    readout: tuple[torch.Tensor, torch.Tensor] | None, exact_below: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Clipping and attribution of :func:`form_image` for (B, N) rows: the clipped image and, per row, the sum
    and sum of squares of each source's attributed noise, of the realised total noise, and the clipped count
    (B, 2·S + 3). The noise is ``fields`` (realised (B, N) fields) followed by the dark-current and readout
    noise drawn in the same pass from their specifications, so that neither is written out: ``dark`` =
    (z-table, λ (B, 1), intensity per electron (B, 1), keys) as in :func:`_dark_noise_counter`, ``readout`` =
    (σ in intensity (B, 1), keys) as in :func:`~camhealth.physics.counter_rng.counter_normal` — the same numbers
    as the separate passes with the same keys."""
    noise = list(fields)
    if dark is not None or readout is not None:
        r, n = signal.shape
        index = torch.arange(r * n, dtype=torch.int32, device=signal.device).view(r, n)
        if dark is not None:
            table, rate, unit, keys = dark
            noise.append((_poisson_z_expr(table, rate, keys, index, exact_below) - rate) * unit)
        if readout is not None:
            scale, keys = readout
            noise.append(counter_normal_expr(index, keys, signal.dtype) * scale)
    total = noise[0]
    for n in noise[1:]:
        total = total + n
    unclipped = signal + total
    y = unclipped.clamp(0.0, 1.0)
    clipped = (unclipped < 0) | (unclipped > 1)
    realised = torch.where(clipped, y - signal, total)
    ratio = torch.where(clipped & (total != 0), realised / total, 1.0)
    stats = []
    for n in noise:
        a = n * ratio
        stats += [a.sum(1), (a * a).sum(1)]
    stats += [realised.sum(1), (realised * realised).sum(1), clipped.to(signal.dtype).sum(1)]
    return y, torch.stack(stats, 1)


_noise_clip_and_label = LazyCompiled(_k_noise_clip_and_label)


def _sample_std(t: torch.Tensor) -> torch.Tensor:
    """Per-sample standard deviation (unbiased) over all but the first dim, (B,), from one pass of sums.
    The noise fields it is used on are (near) zero-mean, so the sum-of-squares form does not cancel."""
    dims = tuple(range(1, t.ndim))
    n = t[0].numel()
    s1 = t.sum(dims).double()
    s2 = torch.linalg.vector_norm(t, dim=dims).double().square()
    return ((s2 - s1 * s1 / n) / max(n - 1, 1)).clamp_min(0).sqrt().to(t.dtype)


def _per_sample(v: torch.Tensor, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    return v.to(device=device, dtype=dtype).view(-1, 1, 1, 1)


#: Largest |sum − 1| of a blur kernel that :func:`form_image` accepts (or the dtype's machine epsilon, if larger:
#: a bfloat16 kernel's sum is only known to ~4e-3).
_PSF_SUM_TOLERANCE = 1e-3


def _check_odd_psf(psf: torch.Tensor, name: str) -> None:
    """``ValueError`` naming ``name`` unless the (B, k, k) kernels have an odd size k."""
    k = psf.shape[-1]
    if k % 2 == 0:
        raise ValueError(f"{name} must have an odd size k (shape (B, k, k)), got k = {k}: a kernel needs a centre pixel "
                         "to keep the image in place, an even one shifts it by half a pixel; sample the PSF on an odd grid")


def _check_exact_below(value: object, name: str = "poisson_exact_below") -> float:
    """``value`` as a float if it is a number in [10, inf] (electrons), else ``TypeError``/``ValueError`` naming it:
    below 10 e⁻ the normal approximation N(λ, λ) it switches to is skewed and reaches below 0 (inf: every count exact)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a number of electrons, got {type(value).__name__} {value!r:.40}")
    v = float(value)
    if not v >= _EXPANSION_MIN_RATE:  # (NaN fails it)
        raise ValueError(
            f"{name} = {show_outside(v, _EXPANSION_MIN_RATE, math.inf)} e⁻ is out of the allowed range "
            f"[{_EXPANSION_MIN_RATE:g}, inf] e⁻ (counts below it are drawn exactly, above it from the normal approximation "
            "N(λ, λ), which is skewed and reaches below 0 for λ < 10; inf draws every count exactly)"
        )
    return v


def _check_blur_psf(psf: object, name: str = "psf") -> torch.Tensor:
    """``psf`` if it is a (B, k, k) floating tensor (k ≥ 1) of finite, non-negative kernels that each sum to 1
    (within ``_PSF_SUM_TOLERANCE``; values down to −10⁻⁶ of a kernel's largest magnitude count as rounding of 0),
    else ``TypeError``/``ValueError`` naming ``name``, the kernel and what is wrong (conventions.md: a PSF
    spreads the light of a pixel, it neither adds nor removes any)."""
    check_tensor(psf, name)
    if psf.dtype not in (torch.float16, torch.bfloat16, torch.float32, torch.float64):
        raise TypeError(f"{name} must be a floating tensor (float16, bfloat16, float32 or float64), got dtype {psf.dtype}")
    if psf.ndim != 3 or psf.shape[-1] != psf.shape[-2] or psf.shape[-1] < 1:
        raise ValueError(f"{name} must have shape (B, k, k) with k >= 1, got {tuple(psf.shape)}")
    _check_odd_psf(psf, name)
    if psf.shape[0] == 0:
        return psf
    check_finite(psf, name)
    flat = psf.detach().reshape(psf.shape[0], -1)
    flat = flat if flat.dtype in (torch.float32, torch.float64) else flat.float()
    low, at = flat.min(dim=1)
    bad = low < -1e-6 * flat.abs().amax(dim=1)
    if bool(bad.any()):
        i = int(torch.nonzero(bad)[0, 0])
        r, c = divmod(int(at[i]), psf.shape[2])
        raise ValueError(f"{name} must be non-negative (a blur kernel spreads light); kernel {i} has {float(low[i]):g} "
                         f"at row {r}, column {c}")
    total = flat.double().sum(dim=1)
    tol = max(_PSF_SUM_TOLERANCE, torch.finfo(psf.dtype).eps)
    bad = (total - 1.0).abs() > tol
    if bool(bad.any()):
        i = int(torch.nonzero(bad)[0, 0])
        raise ValueError(f"{name} kernel {i} sums to {float(total[i]):g}; a blur kernel must sum to 1 (±{tol:g}) so that it "
                         "keeps the image's mean (normalise it: psf / psf.sum((-2, -1), keepdim=True))")
    return psf


def _check_source_follower(sf: object, b: int) -> None:
    """``TypeError``/``ValueError`` naming ``source_follower_e`` unless it is a floating tensor of 1 or ``b`` finite values
    ≥ 0 (σ_SF in e⁻: a NaN would turn every image into NaN, a wrong length fail deep inside)."""
    check_float(check_tensor(sf, "source_follower_e"), "source_follower_e")
    if sf.ndim > 1 or sf.numel() not in (1, b):
        raise ValueError(f"source_follower_e must have shape (1,) or (B,) = ({b},) (σ_SF [e⁻] of every sample), got shape "
                         f"{tuple(sf.shape)}")
    check_finite(sf, "source_follower_e")
    if sf.numel() and bool((sf < 0).any()):
        raise ValueError(f"source_follower_e = {float(sf.min()):g} e⁻ is out of the allowed range [0, inf) e⁻ "
                         "(a standard deviation)")


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
    rng: str = "torch",
) -> ImageFormation:
    """Corrupt a batch of clean images with the Fig. 3.7 chain.

    Args:
        clean: B×C×H×W in [0, 1] (float16/bfloat16/float32/float64); camhealth images are monochrome
            (C = 1), other C are corrupted channel by channel with independent noise.
        meta: per-sample camera metadata (batch 1 or B); required when ``sources`` is not empty.
        defocus_psf: (B, k, k) defocus kernels, or ``None`` for none.
        motion_psf: (B, k, k) motion kernels, or ``None``. Both must be floating, finite, non-negative and
            sum to 1 per kernel (:func:`_check_blur_psf`; else ``TypeError``/``ValueError`` naming the argument).
        sources: which noise sources to realise, a subset of ``("photon", "dark", "readout")`` (a single name such
            as ``"photon"`` stands for that one source).
        generator: torch generator on the image's device for reproducible noise (a ``torch.Generator`` or ``None``).
        quantize: round the output to whole DN (straight-through gradient); a bool.
        source_follower_e: optional cached :func:`~camhealth.physics.readout_noise.source_follower_sigma_e` [e⁻]:
            finite, ≥ 0, of shape (1,) or (B,).
        poisson_exact_below: electron counts below this are Poisson-sampled exactly, above it with the
            normal approximation; in [10, inf] e⁻ (inf: every count exact).
        rng: random numbers of the noise fields: ``"torch"`` (default; torch's generator streams) or
            ``"counter"`` (:mod:`~camhealth.physics.counter_rng`: compiled counter-based draws keyed from
            ``generator``, one compiled pass per source: same distributions, about half the time of the
            noise stage on CPU, but other draws than ``"torch"`` for the same generator state).

    Returns:
        :class:`ImageFormation` with the image and the labels.
    """
    check_image(clean, "clean", channels=None)
    lo, hi = torch.aminmax(clean)
    if lo < 0 or hi > 1:
        raise ValueError(f"clean images must lie in [0, 1] (DN/255), got values in [{lo.item():g}, {hi.item():g}]")
    check_rng(rng)
    if not isinstance(quantize, (bool, np.bool_)):  # ("no" would read as True)
        raise TypeError(f"quantize = {quantize!r:.40} must be True or False (a bool), got {type(quantize).__name__}")
    quantize = bool(quantize)
    poisson_exact_below = _check_exact_below(poisson_exact_below)
    check_generator(generator)
    if sources is None or not isinstance(sources, Iterable):
        raise TypeError(f"sources must be a noise source name or a sequence of them (from {list(NOISE_SOURCES)}), got "
                        f"{type(sources).__name__} {sources!r:.40}")
    sources = (sources,) if isinstance(sources, str) else tuple(sources)
    unknown = [s for s in sources if s not in NOISE_SOURCES]
    if unknown:
        raise ValueError(f"unknown noise source(s) {unknown}; choose from {list(NOISE_SOURCES)}")
    for psf_name, psf in (("defocus_psf", defocus_psf), ("motion_psf", motion_psf)):
        if psf is not None:
            _check_blur_psf(psf, psf_name)
    b = clean.shape[0]
    if source_follower_e is not None:
        _check_source_follower(source_follower_e, b)
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
        meta = meta.expand(b)
        if meta.device != dev:
            meta = meta.to(device=dev)
        to_int = _per_sample(meta.gain_factor / meta.full_well_e, wd, dev)  # intensity per electron
        dn_per_e = meta.dn_per_electron.to(wd)
    noise = {}  # per-source realised noise in intensity units (before clipping)
    fused_cat = False  # photon noise returned as cat([x, noise], 1) for the motion blur
    expected = []
    # --- photon shot noise (before motion blur)
    if "photon" in sources:
        with torch.no_grad():
            if rng == "counter":  # with a motion blur to follow (and no gradient), the pass also writes cat([x, n])
                fused_cat = motion_psf is not None and not x.requires_grad
                n_pn = _photon_noise_counter(x.detach(), to_int, generator, poisson_exact_below, with_signal=fused_cat)
            else:
                electrons = x.detach().clamp_min(0).div_(to_int)
                n_pn = sample_poisson(electrons, generator, poisson_exact_below, rng).sub_(electrons).mul_(to_int)
                del electrons
        exp_pn = photon_shot_sigma_patch_dn(x.detach(), meta).to(wd)
    else:
        n_pn, exp_pn = None, zeros
    # --- motion blur of signal (and of the photon noise it carries)
    if motion_psf is not None:
        if n_pn is not None:
            both = apply_psf(n_pn if fused_cat else torch.cat([x, n_pn], dim=1), motion_psf)
            c = x.shape[1]
            x, n_pn = both[:, :c], both[:, c:].detach()
            if both.requires_grad:  # n_pn is scaled in place below: do not touch a tensor autograd may hold
                n_pn = n_pn.clone()
            exp_pn = exp_pn * psf_noise_gain_sq(motion_psf, *x.shape[-2:]).to(device=dev, dtype=wd).sqrt().expand(b)
        else:
            x = apply_psf(x, motion_psf)
    signal = x
    if n_pn is not None:
        noise["photon"] = n_pn
    expected.append(exp_pn)
    # rng="counter" without gradient: dark and readout noise are drawn inside the clipping pass (never written out)
    late: dict[str, tuple[torch.Tensor, ...]] = {}
    fuse = rng == "counter" and not signal.requires_grad
    # --- dark-current shot noise (signal independent, Poisson in the dark electrons)
    if "dark" in sources:
        with torch.no_grad():  # the same dark-electron rate at every pixel of a sample: tabulated CDF per sample
            dark = dark_signal_e(meta).to(device=dev, dtype=torch.float64)
            if fuse:  # the specification of _dark_noise_counter, drawn in the clipping pass
                late["dark"] = _poisson_per_sample_spec(dark, b, signal[0].numel(), generator, poisson_exact_below, wd, to_int)
            elif rng == "counter":
                noise["dark"] = _dark_noise_counter(dark, to_int, signal.shape, generator, poisson_exact_below, wd)
            else:
                drawn = sample_poisson_per_sample(dark, signal.shape, generator, poisson_exact_below, wd, rng)
                noise["dark"] = drawn.sub_(_per_sample(dark, wd, dev)).mul_(to_int)
                del drawn
        expected.append(dark_current_shot_sigma_e(meta).to(wd) * dn_per_e)
    else:
        expected.append(zeros)
    # --- readout noise (Gaussian)
    if "readout" in sources:
        rn_e = readout_sigma_e(meta, source_follower_e).to(wd)
        with torch.no_grad():
            scale = _per_sample(rn_e, wd, dev) * to_int
            if fuse:  # the specification of counter_normal(signal.shape, keys, wd, scale), drawn in the clipping pass
                late["readout"] = (scale.reshape(b, 1), counter_keys(generator, dev))
            elif rng == "counter":
                noise["readout"] = counter_normal(signal.shape, counter_keys(generator, dev), wd, scale)
            else:
                eps = torch.randn(signal.shape, generator=generator, device=dev, dtype=wd)
                noise["readout"] = eps.mul_(scale)
        expected.append(rn_e * dn_per_e)
    else:
        expected.append(zeros)

    # --- gain is folded into to_int; clipping (saturation) and attribution of the clipped noise
    if (noise or late) and rng == "counter":  # the same arithmetic as below, one compiled pass plus row sums
        with torch.no_grad():
            flat = [n.reshape(b, -1) for n in noise.values()]
            y_flat, stats = _noise_clip_and_label(
                signal.detach().reshape(b, -1), tuple(flat), late.get("dark"), late.get("readout"), float(poisson_exact_below)
            )
            names = list(noise) + list(late)
            n_px = signal[0].numel()
            s = stats.double()
            var = ((s[:, 1::2] - s[:, 0:-1:2].square() / n_px) / max(n_px - 1, 1)).clamp_min(0)
            sd_all = var.sqrt().mul(255.0).to(wd)
            sd = dict(zip(names, sd_all.unbind(1)))
            sigma = torch.stack([sd.get(name, zeros) for name in NOISE_SOURCES], 1)
            sigma_total = sd_all[:, len(names)]
            clipped_fraction = stats[:, -1].to(wd) / n_px
        if signal.requires_grad:  # the differentiable path: identity through the additive noise, 0 where clipped
            total_noise = torch.stack(flat).sum(0).view_as(signal)
            y = (signal + total_noise).clamp(0.0, 1.0)
        else:
            y = y_flat.view_as(signal)
    elif noise:
        with torch.no_grad():
            parts = list(noise.values())
            total_noise = parts[0] if len(parts) == 1 else torch.add(parts[0], parts[1])
            for part in parts[2:]:
                total_noise.add_(part)
        unclipped = signal + total_noise
        with torch.no_grad():
            clipped = (unclipped < 0) | (unclipped > 1)
            clipped_fraction = clipped.flatten(1).sum(1).to(wd) / clipped[0].numel()
            any_clipped = bool(clipped_fraction.any())
        if unclipped.requires_grad:
            y = unclipped.clamp(0.0, 1.0)
        else:
            y = unclipped.clamp_(0.0, 1.0)
        with torch.no_grad():
            if any_clipped:
                # each source keeps its own noise at unclipped pixels; at clipped ones it is scaled by the
                # clipped share realised/total (0 where the total noise is exactly 0)
                realised = torch.sub(y, signal)
                ratio = realised / total_noise
                ratio.masked_fill_(~clipped | (total_noise == 0), 1.0)
                for n in noise.values():
                    n.mul_(ratio)
                del ratio
            else:
                realised = total_noise
            sd = {name: _sample_std(n) * 255.0 for name, n in noise.items()}
            sigma = torch.stack([sd.get(name, zeros) for name in NOISE_SOURCES], 1)
            sigma_total = sd[next(iter(noise))] if len(noise) == 1 and not any_clipped else _sample_std(realised) * 255.0
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
        blurred=signal,
    )
