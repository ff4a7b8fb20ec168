"""Input conventions shared by every estimator's ``predict``: patches (tensor or array, DN or [0, 1], gray layouts),
metadata (``CameraMetadata``, a dict of fields, a preset name or a metadata file) and the assessability flags of
patches that are black, saturated or featureless. A lower layer than :mod:`camhealth.inference` and
:mod:`camhealth.estimators`, which both use it."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch

from camhealth._order import lower_median
from camhealth.physics.metadata import PRESETS, CameraMetadata

__all__ = [
    "CONTRAST_NOISE_SIGMAS", "MAX_CLIPPED_FRACTION", "MIN_CONTRAST_DN", "MIN_EDGE_KURTOSIS", "STRUCTURE_BLOCK", "assess_patches", "contrast_limit_dn", "edge_kurtosis",
    "edge_kurtosis_from_moments", "has_edges", "structure_contrast_dn",
]

#: Fraction of clipped pixels above which a patch is not assessable: "black" (within 0.5 DN of 0) or "saturated"
#: (of 255) where one of the two shares exceeds it, "clipped" where neither does but both together do.
MAX_CLIPPED_FRACTION = 0.5
#: Noise-corrected structure contrast (DN, :func:`structure_contrast_dn`) below which a patch carries no blur
#: information ("featureless"; MTF only).
MIN_CONTRAST_DN = 2.0
#: Noise-corrected excess kurtosis of the scene's gradients (:func:`edge_kurtosis`) that a patch must exceed by two
#: standard errors to show edges to read blur from (:func:`has_edges`; else "no edges", MTF only). A Gaussian
#: random field — texture whose phases carry no edge, where a steep spectrum and blur look alike — has 0; on the robustness benchmark's random-phase 1/f textures the 192-px
#: patches read −0.15 … 0.9 (10th–90th percentile, with 1–10 DN of noise); dead leaves, line art, polygons and
#: street frames read 2 … 26 (``python -m camhealth.bench robustness --task mtf``).
MIN_EDGE_KURTOSIS = 0.5
#: Sampling standard deviations of the noise's share in the structure contrast² added to :data:`MIN_CONTRAST_DN`²
#: (:func:`contrast_limit_dn`).
CONTRAST_NOISE_SIGMAS = 3.0
#: Block side [px] of the block means whose spread is the structure contrast.
STRUCTURE_BLOCK = 8
#: 1 / Φ⁻¹(0.75): median absolute value of a standard normal → σ.
_MAD_NORMAL = 0.6744897501960817


def structure_contrast_dn(patches: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Noise-corrected structure contrast and robust noise level of B×1×P×P patches in [0, 1] → ((B,), (B,)) DN.

    - noise σ̂ = median|d| / 0.6745 of the finest diagonal Haar detail d = (I₀₀ − I₀₁ − I₁₀ + I₁₁)/2 over the
      2×2 blocks of every other block row (Donoho's MAD estimate: var d = σ² for white noise; edges and texture
      touch few d, so the median ignores them);
    - structure s = √max(0, var(B₈) − σ̂²/64) of the 8×8 block means B₈ (P ≥ 16; the patch cropped to a
      multiple of 8): scene content at ≥ 16-px periods, from which the noise (variance σ²/64 in a block mean)
      is removed. On a flat patch with white noise s is ~0 whatever σ (the spread of var(B₈) over its P²/64
      blocks is σ²/64·√(128/P²), e.g. 0.37 DN² at σ = 20 DN and P = 192, against (2 DN)² = 4 DN²).
      Patches under 16 px use the pixels themselves: s = √max(0, var − σ̂²).

    The monitor's tiling computes the same two statistics frame-wide (:mod:`camhealth.monitor.tiling`)."""
    s, noise, _ = _structure_stats(patches)
    return s, noise


def haar_noise_dn(patches: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Robust noise level σ̂ [DN] of B×1×H×W patches in [0, 1] (H, W ≥ 2) → (B,) ``dtype``: median|d| / 0.6745 of the
    finest diagonal Haar details d over the 2×2 blocks of every other block row (:func:`structure_contrast_dn`)."""
    return _haar_noise(patches[:, 0].float() * 255.0).to(dtype)


def _haar_noise(x: torch.Tensor) -> torch.Tensor:
    """:func:`haar_noise_dn` of B×H×W images in DN → (B,) float64."""
    h2, w2 = x.shape[-2] - x.shape[-2] % 2, x.shape[-1] - x.shape[-1] % 2
    # d of every other row of 2×2 blocks (P²/8 samples: ~2 % standard error of σ̂, half the selection work)
    q = x[:, :h2, :w2]
    step = 4 if h2 >= 8 else 2
    d = 0.5 * (q[:, 0::step, 0::2] - q[:, 0::step, 1::2] - q[:, 1::step, 0::2] + q[:, 1::step, 1::2])
    flat = d.abs().flatten(1)
    return lower_median(flat).double() / _MAD_NORMAL


def _structure_stats(patches: torch.Tensor, noise: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """:func:`structure_contrast_dn`'s (s, σ̂) and the 8×8 block means it read [DN] (B, rows, cols) float64, or ``None``
    for patches under 16 px. ``noise``: σ̂ of :func:`haar_noise_dn` (B,) float64 where the caller has it."""
    x = patches[:, 0].float() * 255.0
    b, h, w = x.shape
    if h < 2 or w < 2:
        return x.double().flatten(1).std(1, unbiased=False).float(), torch.zeros(b, device=x.device), None
    noise = _haar_noise(x) if noise is None else noise.double()
    blk = STRUCTURE_BLOCK
    if min(h, w) >= 2 * blk:
        hb, wb = h - h % blk, w - w % blk
        means = x[:, :hb, :wb].reshape(b, hb // blk, blk, wb // blk, blk).mean((2, 4)).double()
        var = means.flatten(1).var(1, unbiased=False) - noise.square() / (blk * blk)
    else:
        means = None
        var = x.double().flatten(1).var(1, unbiased=False) - noise.square()
    return var.clamp_min(0).sqrt().float(), noise.float(), means


def edge_kurtosis_from_moments(m2: torch.Tensor, m4: torch.Tensor, noise_dn: torch.Tensor, count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """γ = κ₄ / (m₂ − σ_g²)² of ``count`` gradients g with moments m₂ = E g² [DN²] and m₄ = E g⁴ [DN⁴] measured on
    an image with white noise σ̂ = ``noise_dn`` [DN], and its standard error → ((B,), (B,)) [–]; g is a difference
    of neighbouring 2×2-block means, whose noise is N(0, σ_g² = σ̂²/2).

    The fourth cumulant κ₄ = m₄ − 3m₂² is additive over independent parts and 0 for Gaussian noise, so κ₄ is the
    scene's own and γ is the scene gradients' excess kurtosis with the noise removed from numerator and
    denominator alike: 0 for a Gaussian random field, large where the gradients are sparse (edges: most of the
    patch flat, a few large steps). Its standard error where everything is Gaussian is
    √(24/count)·(m₂ / (m₂ − σ_g²))² (the sample excess kurtosis of n Gaussian values has standard error √(24/n);
    neighbouring gradients are treated as independent, so it is a lower bound for correlated texture). Where the
    noise explains all of m₂ there is no scene evidence: γ = 0, standard error ∞."""
    m2, m4, vn = m2.double(), m4.double(), noise_dn.double().square() / 2.0
    scene = m2 - vn
    has = scene > 1e-6 * m2.clamp_min(1e-12)
    gamma = (m4 - 3.0 * m2.square()) / scene.clamp_min(1e-12).square()
    se = math.sqrt(24.0 / max(int(count), 1)) * (m2 / scene.clamp_min(1e-12)).square()
    return (torch.where(has, gamma, torch.zeros_like(gamma)).float(),
            torch.where(has, se, torch.full_like(se, float("inf"))).float())


def edge_kurtosis(patches: torch.Tensor, noise_dn: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Noise-corrected excess kurtosis γ [–] of the scene's gradients in B×1×P×P patches in [0, 1], given their
    white-noise level ``noise_dn`` (B,) [DN] (:func:`structure_contrast_dn`'s σ̂), and its standard error → ((B,), (B,)).

    The gradients are the horizontal and vertical differences of the 2×2-block means (the half-resolution patch:
    the noise is halved, an edge blurred by a few px is still a step), pooled; γ and its standard error:
    :func:`edge_kurtosis_from_moments`. γ tells a scene with edges (γ ≫ 0) from a Gaussian-like texture (γ ≈ 0), on
    which a blind blur estimate cannot tell a smooth scene from a blurred one: a random-phase texture of steep
    spectrum and a blurred flat-spectrum one look the same to every single-patch estimator, and so do a sine
    grating of lower contrast and a blurred one (γ = −1.5). Blur keeps γ of an edge scene large (a blurred step is
    still a few px of gradient among flat ones)."""
    x = patches[:, 0].float()
    b, h, w = x.shape
    h2, w2 = h - h % 2, w - w % 2
    if h2 < 4 or w2 < 4:
        return torch.zeros(b, device=x.device), torch.full((b,), float("inf"), device=x.device)
    # float32 (gradients ≤ 255 DN; the moments' relative rounding ~1e-6 moves γ by ~1e-5), moments summed in float64
    m = 63.75 * (x[:, 0:h2:2, 0:w2:2] + x[:, 0:h2:2, 1:w2:2] + x[:, 1:h2:2, 0:w2:2] + x[:, 1:h2:2, 1:w2:2])
    gx, gy = (m[:, :, 1:] - m[:, :, :-1]).flatten(1), (m[:, 1:, :] - m[:, :-1, :]).flatten(1)
    sx, sy = gx.square(), gy.square()
    m2 = 0.5 * (sx.sum(1, dtype=torch.float64) / gx.shape[1] + sy.sum(1, dtype=torch.float64) / gy.shape[1])
    m4 = 0.5 * (sx.square().sum(1, dtype=torch.float64) / gx.shape[1] + sy.square().sum(1, dtype=torch.float64) / gy.shape[1])
    return edge_kurtosis_from_moments(m2, m4, noise_dn, gx.shape[1] + gy.shape[1])


def has_edges(gamma: torch.Tensor, se: torch.Tensor) -> torch.Tensor:
    """Whether the gradients are shown to be sparser than a Gaussian's: γ − 2·SE ≥ :data:`MIN_EDGE_KURTOSIS`
    (a patch whose γ is too uncertain — weak structure under strong noise — has no edges shown either)."""
    return (gamma - 2.0 * se) >= MIN_EDGE_KURTOSIS


def _interaction_contrast_dn(means: torch.Tensor, noise_dn: torch.Tensor) -> torch.Tensor:
    """The structure contrast of :func:`structure_contrast_dn` without what is constant along block rows or block
    columns: its 8×8 block means ``means`` (B, rows, cols) [DN] less their row and column means (plus the grand
    mean), noise-corrected → (B,) DN. Row and column offsets (banding) have none; neither has a straight edge along a
    row or column."""
    blk = STRUCTURE_BLOCK
    nr, nc = means.shape[1], means.shape[2]
    resid = means - means.mean(2, keepdim=True) - means.mean(1, keepdim=True) + means.mean((1, 2), keepdim=True)
    var = resid.square().mean((1, 2)) - noise_dn.double().square() / (blk * blk) * (1 - 1 / nr) * (1 - 1 / nc)
    return var.clamp_min(0).sqrt().float()


def _without_banding(patches: torch.Tensor, std_dn: torch.Tensor, noise_dn: torch.Tensor,
                     means: torch.Tensor | None) -> torch.Tensor:
    """The structure contrast with detected row and column noise taken out (B,) [DN]: an 8×8 block mean carries
    σ_row²/8 + σ_col²/8 of it, so s² − σ_row²/8 − σ_col²/8 (:mod:`camhealth.estimators.row_column_noise`, per patch),
    each term raised by two of its standard errors (the estimate's and the n block rows' realised spread, √(2/n)).
    Only patches that pass :data:`MIN_CONTRAST_DN` with all but 2 DN of their structure constant along block rows or
    columns (:func:`_interaction_contrast_dn`) are checked: banding adds nothing else, so no other patch could drop
    below the limit. A flat patch with 10 DN of row noise has ≈ 3.5 DN of contrast from it and would otherwise be read
    as a scene, its blur across the rows as "strong" with a confident error bar."""
    from camhealth.estimators.row_column_noise import row_column_noise  # torch only: no import circle

    if means is None:
        return std_dn
    cand = (std_dn >= MIN_CONTRAST_DN).nonzero()[:, 0]
    if cand.numel() == 0:
        return std_dn
    sep = cand[_interaction_contrast_dn(means[cand], noise_dn[cand]) < MIN_CONTRAST_DN]
    if sep.numel() == 0:
        return std_dn
    band = row_column_noise(patches[sep])
    # the banding's share of var(B₈) with two standard errors: that of σ̂² and that of the realised variance of the
    # n block rows' (columns') offsets, √(2/n) relative — the patch must show more than banding could bring
    n = torch.tensor([patches.shape[-2] // STRUCTURE_BLOCK, patches.shape[-1] // STRUCTURE_BLOCK], dtype=torch.float64,
                     device=patches.device)
    var = band.sigma_dn.square()
    rel = ((band.var_se_dn2 / var.clamp_min(1e-12)).square() + 2.0 / n).sqrt()
    band_var = (var * (1.0 + 2.0 * rel) * band.detected).sum(1) / STRUCTURE_BLOCK
    out = std_dn.clone()
    out[sep] = (std_dn[sep].double().square() - band_var).clamp_min(0).sqrt().float()
    return out


def contrast_limit_dn(noise_dn: torch.Tensor, n_means: int, pixels_per_mean: int) -> torch.Tensor:
    """The structure contrast [DN] a patch must reach to count as a scene, (B,) float32: :data:`MIN_CONTRAST_DN`, raised
    in quadrature by :data:`CONTRAST_NOISE_SIGMAS` sampling standard deviations of what the noise leaves in it. The
    contrast² is the variance of ``n_means`` means of ``pixels_per_mean`` pixels less the noise's share
    σ̂²/``pixels_per_mean``; on a flat patch that difference scatters by σ̂²/``pixels_per_mean``·√(2/``n_means``)
    (the sample variance of n normal values). 2.07 DN at σ̂ = 10 DN and 192-px patches, 3.9 DN at 64 DN, where a flat
    patch would otherwise pass 2 DN by chance one time in seven."""
    spread = noise_dn.double().square() / pixels_per_mean * math.sqrt(2.0 / max(int(n_means), 1))
    return (MIN_CONTRAST_DN**2 + CONTRAST_NOISE_SIGMAS * spread).sqrt().float()


#: The estimator kinds :func:`assess_patches` knows (those of :class:`camhealth.inference.Estimator`).
_KINDS: tuple[str, ...] = ("mtf", "drne", "noise_source")


def assess_patches(patches: torch.Tensor, kind: str, noise_dn: torch.Tensor | None = None) -> tuple[torch.Tensor, list[str]]:
    """Which B×1×P×P patches (in [0, 1]) an estimator of ``kind`` can assess, and why not.

    black / saturated: more than half of the pixels within 0.5 DN of 0 / 255 (noise is clipped away,
    blur invisible); clipped: neither alone, but the pixels within 0.5 DN of 0 and of 255 together more than half
    (a patch crushed at one end and blown out at the other reads as little noise and as sharp edges) — for the noise
    kinds, where the patch's finest-scale fluctuations exceed the validated σ beyond doubt
    (:func:`~camhealth.estimators.physics_noise.beyond_validated_range`), the noise itself clipped it, and the reason
    is that one, ``"noise beyond validated range"``;
    featureless (MTF only): noise-corrected structure contrast (:func:`structure_contrast_dn`) below
    :data:`MIN_CONTRAST_DN` = 2 DN, raised by three sampling standard deviations of the noise's share
    (:func:`contrast_limit_dn`: 2.07 DN at 10 DN of noise, 3.9 DN at 64 DN) — no structure to measure blur on,
    however strong the noise (a flat patch with 20 DN of noise has the contrast of its noise, not of a scene), nor
    row and column noise (a flat patch with
    10 DN of it: :func:`_without_banding`); no edges (MTF only): the scene's gradients are
    not shown to be sparser than a random-phase texture's (:func:`has_edges`: :func:`edge_kurtosis` two standard
    errors above :data:`MIN_EDGE_KURTOSIS`), so a steep spectrum and blur cannot be told apart on the patch.
    ``kind``: ``"mtf"``, or one of the noise kinds ``"drne"`` and ``"noise_source"`` (another raises a ``ValueError``).
    ``noise_dn``: the patches' σ̂ of :func:`haar_noise_dn` (B,) (``dtype=torch.float64``) where the caller has it."""
    if kind not in _KINDS:
        raise ValueError(f"kind = {kind!r} must be one of {', '.join(map(repr, _KINDS))} (the estimator's kind)")
    x = patches.flatten(1)
    x = x if x.dtype in (torch.float32, torch.float64) else x.float()
    tol = 0.5 / 255.0
    n = x.shape[1]
    # clipped counts only where a patch reaches 0/255
    none = torch.zeros(x.shape[0], dtype=torch.int32, device=x.device)
    n_low = (x <= tol).sum(1, dtype=torch.int32) if bool((x.amin(1) <= tol).any()) else none
    n_high = (x >= 1 - tol).sum(1, dtype=torch.int32) if bool((x.amax(1) >= 1 - tol).any()) else none
    low, high, both = n_low / n, n_high / n, (n_low + n_high) / n
    if kind == "mtf":
        p = patches.float() if patches.dtype not in (torch.float32, torch.float64) else patches
        std_dn, noise_dn, means = _structure_stats(p, noise_dn)
        std_dn = _without_banding(p, std_dn, noise_dn, means)
        edges = has_edges(*edge_kurtosis(p, noise_dn))
        limit = contrast_limit_dn(noise_dn, means.shape[1] * means.shape[2] if means is not None else p.shape[-2] * p.shape[-1],
                                  STRUCTURE_BLOCK**2 if means is not None else 1)
    else:
        std_dn = torch.full((x.shape[0],), float("inf"))
        edges = torch.ones(x.shape[0], dtype=torch.bool)
        limit = torch.full((x.shape[0],), MIN_CONTRAST_DN)
    low_l, high_l, both_l = low.tolist(), high.tolist(), both.tolist()
    noise_clipped: dict[int, str] = {}
    cand = [i for i, (lo, hi, lh) in enumerate(zip(low_l, high_l, both_l))
            if lo <= MAX_CLIPPED_FRACTION and hi <= MAX_CLIPPED_FRACTION and lh > MAX_CLIPPED_FRACTION]
    if cand and kind != "mtf":  # clipped by noise beyond the validated range: that is what is known (few patches)
        sel = torch.tensor(cand, device=patches.device)
        for i, far in zip(cand, beyond_validated_range(patches[sel]).tolist()):
            if far:
                noise_clipped[i] = BEYOND_VALIDATED
    reason = []
    for i, (lo, hi, lh, s, k, c) in enumerate(zip(low_l, high_l, both_l, std_dn.tolist(), edges.tolist(), limit.tolist())):
        if lo > MAX_CLIPPED_FRACTION:
            reason.append("black")
        elif hi > MAX_CLIPPED_FRACTION:
            reason.append("saturated")
        elif lh > MAX_CLIPPED_FRACTION:
            reason.append(noise_clipped.get(i, "clipped"))
        elif kind == "mtf" and s < c:
            reason.append("featureless")
        elif kind == "mtf" and not k:
            reason.append("no edges")
        else:
            reason.append("")
    return torch.tensor([r == "" for r in reason], dtype=torch.bool), reason


def _to_patches(images: Any, patch_size: int, input_range: str) -> torch.Tensor:
    if isinstance(patch_size, (bool, np.bool_)) or not isinstance(patch_size, (int, np.integer)):
        raise TypeError(f"patch_size = {patch_size!r} must be an integer number of px ≥ 1, got {type(patch_size).__name__}")
    if patch_size < 1:
        raise ValueError(f"patch_size = {patch_size!r} must be an integer number of px ≥ 1")
    if input_range not in ("auto", "unit", "dn"):
        raise ValueError(f"input_range = {input_range!r} must be 'auto', 'unit' or 'dn'")
    if isinstance(images, np.ndarray):
        if images.dtype == object or images.dtype.kind not in "uif":
            raise TypeError(f"images must be a numeric array, got dtype {images.dtype}")
        is_int = images.dtype.kind in "ui"
        wide_int, dtype_name = is_int and images.dtype.itemsize > 1, images.dtype.name
        _check_integer_range(is_int, dtype_name, input_range)
        if not images.dtype.isnative:  # big-endian data (FITS, some TIFF readers): the same values in native order
            images = images.astype(images.dtype.newbyteorder("="))
        if images.dtype.kind == "f" and images.dtype.itemsize > 8:  # long double: torch has no such dtype
            wide = images
            with np.errstate(over="ignore"):
                images = wide.astype(np.float64)
            if not np.isfinite(images).all() and np.isfinite(wide).all():
                raise ValueError(f"images of dtype {wide.dtype} hold values beyond float64's range (min {str(wide.min())}, "
                                 f"max {str(wide.max())}); allowed: DN 0…255 or [0, 1]")
        t = torch.from_numpy(np.ascontiguousarray(images))
    elif isinstance(images, torch.Tensor):
        if images.dtype == torch.bool or images.is_complex():
            raise TypeError(f"images must be a real numeric tensor, got dtype {images.dtype}")
        if images.device.type == "meta":
            raise ValueError(f"images are a tensor on the meta device (shape {_shape_text(images)}, no values); pass a "
                             f"tensor that holds data (CPU or CUDA) or a NumPy array")
        is_int = not images.is_floating_point()
        wide_int, dtype_name = is_int and images.element_size() > 1, str(images.dtype).replace("torch.", "")
        _check_integer_range(is_int, dtype_name, input_range)
        t = images.detach().cpu()
    else:
        raise TypeError(f"images must be a torch.Tensor or numpy.ndarray, got {type(images).__name__}")
    half_dtype = t.dtype  # torch's dtype of the data as given (a NumPy array's is a NumPy dtype, which torch cannot take)
    half = half_dtype in (torch.float16, torch.bfloat16)
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
    if is_int and input_range != "dn" and wide_int:  # ("unit" with integers is refused above)
        raise ValueError(
            f"images of dtype {dtype_name} may hold more than 8 bits (a 10-, 12- or 16-bit camera), which would be read "
            f"as 8-bit DN (min {lo:g}, max {hi:g}); scale them to 8-bit DN (× 255 / (2**bits − 1)) or to floats in "
            f"[0, 1], or pass input_range='dn' if they are 8-bit DN (0…255)"
        )
    if is_int or input_range == "dn":
        if lo < 0 or hi > 255:
            raise ValueError(f"images in DN must lie in [0, 255], got min {lo:g}, max {hi:g} (8-bit DN only)")
        t = t / 255.0
    else:
        if lo < -1e-6 or hi > 1 + 1e-6:
            hint = " (looks like DN: pass input_range='dn')" if hi <= 255 and lo >= 0 else ""
            raise ValueError(f"float images must lie in [0, 1], got min {lo:g}, max {hi:g}{hint}")
        if half:
            t = _unround_8bit(t, half_dtype)
    return t.clamp(0, 1).float()


def _check_integer_range(is_int: bool, dtype_name: str, input_range: str) -> None:
    """Refuse integer images with ``input_range="unit"``: integers are DN, which that setting says they are not (a
    12-bit frame in uint16 would be read as 8-bit DN, a 0/1 mask as 1 DN rather than white)."""
    if is_int and input_range == "unit":
        raise ValueError(
            f"images of dtype {dtype_name} are integers, i.e. DN, but input_range='unit' says they are values in [0, 1]; "
            f"pass input_range='dn' for 8-bit DN (0…255; uint8 is DN by default), or convert to floats in [0, 1] "
            f"(x / 255, or x / (2**bits − 1) for a 10-, 12- or 16-bit camera)"
        )


def _shape_text(t: Any) -> str:
    """A shape as ``B×1×H×W`` text; a 0-d scalar named as such."""
    return "×".join(map(str, t.shape)) if t.ndim else "() (a 0-d scalar)"


def _unround_8bit(t: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """8-bit data (k/255) held in float16 or bfloat16, restored to k/255 exactly; other data as they are.

    Half precision moves k/255 by up to 0.12 DN (float16) or 0.25 DN (bfloat16) — less than half a DN, so
    round(255·x) recovers k — and the noise estimators then no longer see whole DN (their 8-bit quantisation term and
    JPEG test). The values are restored only where every one of them is the half-precision rounding of some k/255: on
    continuous data most of float16's values are not, nor half of bfloat16's below 0.5, so a patch of noise does not
    pass by chance. A bfloat16 patch wholly in [0.5, 1] passes whatever it held: there bfloat16's grid is 1 DN
    (2⁻⁸), one value per k/255 — the data are whole DN, and read as such. ``t``: float32 (B, 1, H, W) in [0, 1]
    holding the half-precision values exactly."""
    k = (t * 255.0).round()
    snapped = k / 255.0
    # per patch: an 8-bit patch passes, a continuous one keeps its values
    exact = (snapped.to(dtype).to(t.dtype) == t).flatten(1).all(1).view(-1, *([1] * (t.dim() - 1)))
    return torch.where(exact, snapped, t)


_LAYOUTS = "B×1×H×W, B×H×W or H×W gray patches"


def _gray_patch_layout(t: torch.Tensor, patch_size: int) -> torch.Tensor:
    """``t`` as B×1×H×W, or a ``ValueError`` that names the layout it looks like: colour with channels last
    (H×W×C, B×H×W×C) or first (B×C×H×W), or C×H×W colour that could as well be a few gray patches."""
    shape = _shape_text(t)
    colour = "convert colour to gray first (camhealth.data.to_gray, BT.601 luma)"
    if t.ndim in (3, 4) and t.shape[-1] in (3, 4) and min(t.shape[-3:-1]) > 4:
        layout = "an H×W×C" if t.ndim == 3 else "a B×H×W×C"
        raise ValueError(f"images of shape {shape} look like {layout} colour image (channels last); the estimators take "
                         f"{_LAYOUTS}: {colour}")
    if t.ndim in (3, 4) and t.shape[-1] == 1 and min(t.shape[-3:-1]) > 4:
        layout = "an H×W×1" if t.ndim == 3 else "a B×H×W×1"
        raise ValueError(f"images of shape {shape} look like {layout} gray image (channels last); the estimators take "
                         f"{_LAYOUTS}: drop the channel axis (x[..., 0])")
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
    if base_preset is not None and not isinstance(base_preset, str):
        raise TypeError(f"base_preset = {base_preset!r} must be a preset name ({', '.join(sorted(PRESETS))}) or None, "
                        f"got {type(base_preset).__name__}")
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


#: Largest σ_Total [DN] the robustness benchmark validates (``python -m camhealth.bench robustness``).
VALIDATED_SIGMA_DN = 64.0
#: The ``reason`` of a patch whose σ_Total (before clipping) is above :data:`VALIDATED_SIGMA_DN`.
BEYOND_VALIDATED = "noise beyond validated range"
#: Relative standard error × √n of Donoho's MAD estimate σ̂ = median|d|/0.6745 over n Gaussian details:
#: 1/(2·f(0.6745)·0.6745) with f = 2φ(0.6745) the density of |d|/σ at its median.
_MAD_RELATIVE_SE = 1.0 / (2.0 * 2.0 * math.exp(-0.5 * _MAD_NORMAL**2) / math.sqrt(2.0 * math.pi) * _MAD_NORMAL)


def _check_noise_patches(patches: Any, name: str = "patches") -> None:
    """:func:`~camhealth.estimators._common.check_patches` of B×1×H×W patches (H, W ≥ 2) for the public patch tests
    (:func:`beyond_validated_range`, :func:`~camhealth.estimators.physics_noise.quieter_than_any_camera`); an empty
    batch passes with its dtype and layout checked, and nothing is checked while the caller is traced or exported."""
    from camhealth._order import _traced
    from camhealth._validation import check_float
    from camhealth.estimators._common import check_patches  # (a lower layer than camhealth.estimators: imported here)

    if _traced():
        return
    if isinstance(patches, torch.Tensor) and patches.ndim == 4 and patches.shape[0] == 0 and patches.shape[1] == 1:
        check_float(patches, name)
        return
    check_patches(patches, name, min_size=(2, 2))


def beyond_validated_range(patches: torch.Tensor, noise_dn: torch.Tensor | None = None) -> torch.Tensor:
    """Whether the finest-scale fluctuations of B×1×H×W patches in [0, 1] exceed :data:`VALIDATED_SIGMA_DN` beyond
    doubt → (B,) bool.

    σ̂ = median|d|/0.6745 of the diagonal Haar details d over the patch's blocks, every one of them
    (:func:`camhealth._inputs.haar_noise_dn`, or ``noise_dn`` where the caller has it: sparse edges do not move a
    median), must exceed the limit by three
    of its standard errors (1.166·σ/√n for n Gaussian details). Clipping only lowers σ̂, so clipped Gaussian noise
    within the limit never trips it. Uniform noise of σ 73 DN does: the clipped-Gaussian model, which reads only
    the blocks away from the bounds, sees it as about 52 DN. Texture that fine and that strong trips it too, and
    no noise estimate can be vouched for under it either.

    The patches are checked as every estimator function checks them
    (:func:`camhealth.estimators._common.check_patches`: a floating tensor, finite, in [0, 1], B×1×H×W with H, W ≥ 2;
    else a ``TypeError`` or ``ValueError`` naming the value) — except while the caller is traced or exported (the
    graph of an exported network, which cannot hold the data-dependent check); an empty batch gives an empty result."""
    _check_noise_patches(patches)
    mad = haar_noise_dn(patches) if noise_dn is None else noise_dn
    h2, w2 = (s - s % 2 for s in patches.shape[-2:])
    step = 4 if h2 >= 8 else 2  # structure_contrast_dn reads the details of every other row of 2×2 blocks
    n = max(-(-h2 // step) * (w2 // 2), 1)
    return mad > VALIDATED_SIGMA_DN * (1.0 + 3.0 * _MAD_RELATIVE_SE / math.sqrt(n))
