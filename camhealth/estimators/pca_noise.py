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
"""

from __future__ import annotations

import torch

from camhealth.estimators._common import DN, check_patches, work_dtype

__all__ = ["pca_noise_sigma", "patch_covariance_eigenvalues", "mean_median_noise_eigenvalue", "MIN_SAMPLES_PER_DIMENSION"]

#: Sub-patches per dimension (n / p²) that :func:`pca_noise_sigma` requires: below it σ̂ is more than ≈ 14 % low
#: (module docstring).
MIN_SAMPLES_PER_DIMENSION = 5


def _check_int(v: object, name: str, low: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise TypeError(f"{name} must be an int, got {type(v).__name__}")
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
    cols = cols - cols.mean(dim=1, keepdim=True)
    cov = (cols.transpose(1, 2) @ cols).double() / n
    return torch.linalg.eigvalsh(cov).clamp_min(0.0)


def patch_covariance_eigenvalues(images: torch.Tensor, patch_size: int = 8, stride: int = 3) -> torch.Tensor:
    """Ascending eigenvalues of the covariance of the ``patch_size²`` sub-patches: (B, patch_size²), float64.

    Units: intensity² (images in [0, 1]). ``stride`` is the step between sampled sub-patch positions (px). Needs at
    least as many sub-patches n = (⌊(H − p)/s⌋ + 1)·(⌊(W − p)/s⌋ + 1) as dimensions p².
    """
    return _eigenvalues(images, patch_size, stride, 1)


def mean_median_noise_eigenvalue(eigenvalues: torch.Tensor) -> torch.Tensor:
    """Chen et al.'s non-parametric criterion on ascending eigenvalues (B, r) → τ (B,), same unit.

    τ is the mean of the largest prefix λ_1 … λ_m whose mean has as many members above as below it.
    """
    lam = eigenvalues.double()
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
        (B,) σ̂ in DN (float32, float64 for float64 input).
    """
    lam = _eigenvalues(images, patch_size, stride, MIN_SAMPLES_PER_DIMENSION)
    tau = mean_median_noise_eigenvalue(lam)
    out = torch.float64 if images.dtype == torch.float64 else torch.float32
    return (DN * tau.clamp_min(0.0).sqrt()).to(out)
