"""Noise level from the eigenvalues of the patch covariance (PCA; Chen, Zhu & Heng, ICCV 2015).

The thesis's "PCA" baseline (Sec. 4.3.2, [CZH15]). Decompose the image into all ``p×p`` sub-patches
(sampled with a stride), flattened to r = p² dimensional vectors x_t, t = 1 … n, and take the eigenvalues
λ_1 ≤ … ≤ λ_r of their sample covariance ``Σ = 1/n · Σ_t (x_t − x̄)(x_t − x̄)ᵀ``.

For additive white noise of variance σ² the image patches live (approximately) in a low-dimensional
subspace: the eigenvalues of the remaining "redundant" dimensions are pure noise and, for finite n, are
spread around σ² following the Marchenko–Pastur law — symmetrically enough that their **mean equals
their median**. Signal dimensions add eigenvalues far above the noise ones and pull the mean above the
median. The non-parametric rule of Chen et al. therefore searches the largest m for which the m
smallest eigenvalues are all noise, i.e. for which

    τ_m = 1/m · Σ_{i ≤ m} λ_i   (the mean)   equals the median of {λ_1 … λ_m},

tested, as in the paper, as "as many of the m eigenvalues lie above τ_m as below it". Then
``σ̂ = √τ_m``. m = 1 always satisfies the test, so there is always an answer; a perfectly flat patch
gives σ̂ = 0. The search runs for all m at once as a (r × r) comparison, batched over the images.

σ̂ is returned in **DN** (× 255, as a float, never truncated).
Sub-patch size 8 and stride 3 are the defaults (r = 64 dimensions; a 128×128 patch gives n = 41² = 1681
samples); a stride of 1 uses every position (more samples, slower). The covariance is accumulated by
one batched matmul in float32 (float64 for float64 input) after subtracting the mean, and its eigenvalues
are computed in float64.

**Few samples bias σ̂ low.** With n samples of r dimensions the noise eigenvalues spread over
σ²(1 ± √(r/n))² with a long upper tail, so the mean-equals-median rule stops early and σ̂ falls short by
about 0.7·r/n (relative; pure Gaussian noise, σ = 2–30 DN, 64 patches each, p = 8, s = 3):

=============  =====  ======  ======
patch [px]       n     n/r    bias
=============  =====  ======  ======
32               81    1.3    −65 %
48              196    3.1    −25 %
64              361    5.6    −13 %
80              625    9.8     −7 %
128            1681   26.3     −2 %
=============  =====  ======  ======

The bias follows the nominal n/r even where the sub-patches overlap (64 px at stride 1: n/r = 51, −1.6 %).
:func:`pca_noise_sigma` therefore requires ``n >= MIN_SAMPLES_PER_DIMENSION · r`` (5: at most ≈ 14 % low;
with the defaults H, W >= 59 px) and refuses smaller images, naming the stride that would do;
:func:`patch_covariance_eigenvalues` only needs n >= r.

**Clipped areas.** A sub-patch with more than half of its pixels clipped (within ½ DN of 0 or 255:
:data:`CLIP_MARGIN`) holds little noise, and such sub-patches pull the noise eigenvalues down (20 DN of white noise
with a quarter of the image at 255 DN read 17.3 DN, with half of it 14.0 DN). They are left out of the covariance
(then 19.8 and 19.4 DN; 19.7 unclipped), and n is the number of sub-patches left. An image where fewer than the
required n are left (mostly saturated or black: with the defaults, more than ≈ 80 % of a 128-px patch; an image
that is saturated or black everywhere) reads NaN (not assessable; a constant unclipped image reads 0), as its
eigenvalues from :func:`patch_covariance_eigenvalues` do (there: fewer than r). A sub-patch
with fewer clipped pixels is kept: noise clipped at scattered pixels (strong noise near 0 or 255 DN) keeps nearly
all of them, and leaving out every sub-patch with a clipped pixel would select those whose noise stayed away from
the bound (60 DN at mid-grey, 3.5 % of the pixels clipped: 90 % of the sub-patches would go). Such images read the
noise the clipping left (the std of the clipped noise). An image without a clipped pixel is read exactly as before.
"""

from __future__ import annotations

import numbers

import torch

from camhealth._validation import check_tensor
from camhealth.estimators._common import DN, check_patches, work_dtype

__all__ = ["pca_noise_sigma", "patch_covariance_eigenvalues", "mean_median_noise_eigenvalue", "MIN_SAMPLES_PER_DIMENSION",
           "CLIP_MARGIN"]

#: Sub-patches per dimension (n / p²) that :func:`pca_noise_sigma` requires: below it σ̂ is more than ≈ 14 % low
#: (module docstring).
MIN_SAMPLES_PER_DIMENSION = 5
#: A pixel within this distance of 0 or 1 (½ DN of 8 bits) is clipped; a sub-patch more than half clipped is left out
#: (module docstring).
CLIP_MARGIN = 0.5 / 255.0


def _check_int(v: object, name: str, low: int) -> int:
    if isinstance(v, bool) or not isinstance(v, numbers.Integral):  # NumPy integers are Integral; bool is not a number
        raise TypeError(f"{name} must be an int, got {v!r} ({type(v).__name__})")
    v = int(v)
    if v < low:
        raise ValueError(f"{name} = {v} is out of the allowed range [{low}, inf)")
    return v


def _n_subpatches(h: int, w: int, p: int, s: int) -> int:
    return ((h - p) // s + 1) * ((w - p) // s + 1)


def _eigenvalues(images: object, patch_size: object, stride: object, per_dim: int) -> torch.Tensor:
    p = _check_int(patch_size, "patch_size", 2)
    s = _check_int(stride, "stride", 1)
    x = check_patches(images, "images", min_size=(p + s, p + s))
    h, w = x.shape[-2:]
    n = _n_subpatches(h, w, p, s)
    need = per_dim * p * p
    if n < need:
        fits = [(t, _n_subpatches(h, w, p, t)) for t in range(s - 1, 0, -1)]
        fits = [f"stride={t} (n = {m}), " for t, m in fits if m >= need][:1]
        why = (f"the {need} dimensions" if per_dim == 1 else
               f"the {need} ({per_dim} per dimension of {p * p}) that keep σ̂ within ≈ 14 % (fewer bias it low; module docstring)")
        raise ValueError(
            f"images of {h}×{w} px give only n = {n} sub-patches of {p}×{p} at stride {s}, fewer than {why}; "
            f"use a larger patch, {''.join(fits)}or a smaller patch_size"
        )
    work = work_dtype(x)
    # (B, n, p²) sub-patch vectors from a strided view (one copy); covariance by one batched matmul in the
    # work dtype (float32 unless the input is float64), eigenvalues in float64
    cols = x.to(work).unfold(2, p, s).unfold(3, p, s).reshape(x.shape[0], -1, p * p)
    lo, hi = torch.aminmax(x.detach())
    if not bool((lo <= CLIP_MARGIN) | (hi >= 1.0 - CLIP_MARGIN)):  # nothing clipped (the common case)
        return _covariance_eigenvalues(cols, n)
    clip = ((x.detach() <= CLIP_MARGIN) | (x.detach() >= 1.0 - CLIP_MARGIN)).to(work)
    drop = clip.unfold(2, p, s).unfold(3, p, s).reshape(x.shape[0], -1, p * p).sum(-1) > 0.5 * p * p  # (B, n)
    hit = drop.any(dim=1)
    lam = torch.empty(x.shape[0], p * p, dtype=torch.float64, device=x.device)
    if not bool(hit.all()):
        lam[~hit] = _covariance_eigenvalues(cols[~hit], n)
    if bool(hit.any()):  # the sub-patches more than half clipped left out (module docstring)
        c, keep = cols[hit], (~drop[hit]).to(work).unsqueeze(-1)  # (B', n, p²), (B', n, 1)
        n_keep = keep.sum(dim=1, keepdim=True)  # (B', 1, 1)
        c = (c - (c * keep).sum(dim=1, keepdim=True) / n_keep.clamp_min(1.0)) * keep
        cov = (c.transpose(1, 2) @ c).double() / n_keep.double().clamp_min(1.0)
        part = torch.linalg.eigvalsh(cov).clamp_min(0.0)
        lam[hit] = torch.where(n_keep.view(-1, 1) >= need, part, torch.full_like(part, float("nan")))
    return lam


def _covariance_eigenvalues(cols: torch.Tensor, n: int) -> torch.Tensor:
    """Ascending eigenvalues (float64) of the covariance of the (B, n, p²) sub-patch vectors."""
    cols = cols - cols.mean(dim=1, keepdim=True)
    cov = (cols.transpose(1, 2) @ cols).double() / n
    return torch.linalg.eigvalsh(cov).clamp_min(0.0)


def patch_covariance_eigenvalues(images: torch.Tensor, patch_size: int = 8, stride: int = 3) -> torch.Tensor:
    """Ascending eigenvalues of the covariance of the ``patch_size²`` sub-patches: (B, patch_size²), float64.

    Units: intensity² (images in [0, 1]). ``stride`` is the step between sampled sub-patch positions (px). Needs at
    least as many sub-patches n = (⌊(H − p)/s⌋ + 1)·(⌊(W − p)/s⌋ + 1) as dimensions p². Sub-patches more than half
    clipped are left out (module docstring); an image with fewer than p² left gives NaN eigenvalues.
    """
    return _eigenvalues(images, patch_size, stride, 1)


def mean_median_noise_eigenvalue(eigenvalues: torch.Tensor) -> torch.Tensor:
    """Chen et al.'s non-parametric criterion on ascending eigenvalues (B, r) → τ (B,), same unit.

    τ is the mean of the largest prefix λ_1 … λ_m whose mean has as many members above as below it.

    ``eigenvalues`` must be a real (floating or integer, not bool) tensor of shape (B, r), r ≥ 1, finite, ≥ 0 (a
    covariance's: clamp rounding negatives with ``.clamp_min(0)``) and ascending along each row (the order of
    ``torch.linalg.eigvalsh``); ``TypeError`` for another type or dtype, ``ValueError`` otherwise.
    """
    lam = check_tensor(eigenvalues, "eigenvalues")
    if lam.dtype == torch.bool or lam.is_complex():
        raise TypeError(f"eigenvalues must be a real (floating or integer) tensor, got dtype {lam.dtype}")
    if lam.ndim != 2 or lam.shape[1] < 1:
        raise ValueError(f"eigenvalues must have shape (B, r) with r >= 1 (one row of eigenvalues per image), got "
                         f"{tuple(lam.shape)}")
    lam = lam.double()
    if lam.numel():
        if not bool(torch.isfinite(lam).all()):
            raise ValueError(f"eigenvalues must be finite, got {lam[~torch.isfinite(lam)][0].item()}")
        if bool((lam < 0).any()):
            raise ValueError(f"eigenvalues must be >= 0 (a covariance's; clamp rounding negatives with .clamp_min(0)), "
                             f"got {lam.min().item():g}")
        down = lam[:, 1:] < lam[:, :-1]
        if bool(down.any()):
            i = int(down.any(dim=1).nonzero()[0, 0])
            raise ValueError(f"eigenvalues must be sorted ascending along each row (torch.linalg.eigvalsh's order), "
                             f"row {i} is {[round(v, 6) for v in lam[i, :8].tolist()]}{' …' if lam.shape[1] > 8 else ''}")
    return _mean_median(lam)


def _mean_median(lam: torch.Tensor) -> torch.Tensor:
    """:func:`mean_median_noise_eigenvalue` on checked float64 eigenvalues (B, r)."""
    b, r = lam.shape
    m = torch.arange(1, r + 1, device=lam.device, dtype=lam.dtype)
    tau = torch.cumsum(lam, dim=1) / m  # (B, r): mean of the m smallest
    prefix = torch.ones(r, r, device=lam.device, dtype=torch.bool).tril()  # [m-1, i]: i < m
    above = ((lam[:, None, :] > tau[:, :, None]) & prefix).sum(-1)
    below = ((lam[:, None, :] < tau[:, :, None]) & prefix).sum(-1)
    ok = above == below  # (B, r); m = 1 always satisfies it
    m_star = torch.where(ok, m.long().expand(b, r), torch.zeros_like(above)).amax(dim=1)
    return tau.gather(1, (m_star - 1)[:, None]).squeeze(1)


def pca_noise_sigma(images: torch.Tensor, patch_size: int = 8, stride: int = 3) -> torch.Tensor:
    """Noise level σ̂ [DN] of each image of a batch ``B×1×H×W`` in [0, 1] (Chen, Zhu & Heng 2015).

    Args:
        images: float batch in [0, 1] (DN/255) of at least :data:`MIN_SAMPLES_PER_DIMENSION` · p² sub-patches,
            n = (⌊(H − p)/s⌋ + 1)·(⌊(W − p)/s⌋ + 1) >= 5·p²: with the defaults H = W >= 59 px (64 px: ≈ 13 % low,
            128 px: ≈ 2 % low; module docstring). Smaller images raise ``ValueError``.
        patch_size: side p of the sub-patches (r = p² dimensions), >= 2.
        stride: step s between sub-patch positions in px, >= 1 (1 for small patches: more samples, less bias).

    Returns:
        (B,) σ̂ in DN (float32, float64 for float64 input); NaN for an image whose unclipped sub-patches are too few
        (mostly saturated or black; module docstring).
    """
    lam = _eigenvalues(images, patch_size, stride, MIN_SAMPLES_PER_DIMENSION)
    tau = _mean_median(lam)  # (NaN eigenvalues: too few unclipped sub-patches give NaN)
    out = torch.float64 if images.dtype == torch.float64 else torch.float32
    return (DN * tau.clamp_min(0.0).sqrt()).to(out)
