"""Which metadata field is wrong, and by how much: a Bayesian posterior over single-field mismatches.

The residual noise ξ (conventions.md Eq. 4.3) exists because the metadata M a camera reports can disagree
with the metadata M' its image was made with. camhealth's noise data model that disagreement the way the
thesis does: with probability ``mismatch_probability`` ONE field of ``fields`` (default gain, temperature and
thermal white noise, ``datamodules.noise.XI_FIELDS``) is redrawn from its range (gain uniform in the linear
factor, the others uniform). Given M, the noise model fixes, for every candidate M', the variance of white
noise at every intensity m [DN]:

    v(m | M') = a'·m + c',   a' = 255·g'/FW  [DN²/DN],   c' = σ_DCSN(M')² + σ_RN(M')²  [DN²]

and the patch measures it: the Haar details of each flat, unclipped 2×2 block are N(0, v(m)) at the block mean
m; the likelihood reads the diagonal one (linear gradients do not reach it; with all three, texture leaked into
the estimate about twice as often on the held-out patches), the horizontal and vertical ones serve as a texture check. Inliers are chosen without the metadata — a first pass against a per-intensity median of the
diagonal detail (which linear gradients do not reach), a second against the first pass's posterior noise-level
function — and blocks within ``bound_margin`` σ of 0 or 255 DN are dropped (the clipping of their neighbours
biases them low). Binned by block mean
(``bins`` equal intervals of [0, 255] DN; per bin the number of inlier details N_k, Σd² and the mean intensity M_k),
the Gaussian log-likelihood of a candidate is

    ℓ(M') = −½ Σ_k [ Σd²_k / v(M_k | M') + N_k · ln v(M_k | M') ]

and the posterior over {M' = M} ∪ {field f of M set to θ: f ∈ fields, θ on a ``grid`` of cells uniform in f's
sampling variable} is ∝ prior × exp(ℓ). No network is involved: every candidate's σ comes from the physics
(Eq. 3.14–3.19), so the feasible range of each field — a dark current that no temperature in 0–80 °C can
produce, a readout noise beyond what any white-noise level gives — is respected exactly, which a network
has to learn from examples.

From the posterior: the expected σ_PN, σ_DCSN, σ_RN and total in DN before clipping (E[σ], the estimate
with the least squared error), the same after clipping to [0, 255] DN (the closed form of
:func:`camhealth.physics.clipping.clipped_sigma_dn` at the posterior-mean variances, rescaled by E[σ]/√E[σ²]),
and the posterior probability of "metadata match" and of each field. A patch with fewer than 32 usable
details carries no evidence: the posterior abstains (the metadata's σ, P(match) = 1, and the count says so).

The model's assumptions are the data model's: one field wrong at a time, uniform priors over the ranges,
white Gaussian-like noise on flat regions. A camera whose noise is wrong in another way (another field, two
fields, fixed-pattern noise) gets the nearest single-field explanation; its ξ is still measured, because the
unclipped total follows the image's noise level whichever field explains it.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F

from camhealth.physics.clipping import clipped_sigma_dn, estimate_clean_dn
from camhealth.physics.dark_current import dark_current_shot_sigma_e
from camhealth.physics.metadata import FULL_FIELDS, METADATA_RANGES, CameraMetadata
from camhealth.physics.readout_noise import readout_sigma_e
from camhealth.estimators.noise_features import (
    _INLIER_Z, _MIN_FIT_BLOCKS, _TEXTURE_CHI2, _TRUNCATED_CHI2, block_details, metadata_from_matrix,
)

__all__ = ["mismatch_posterior", "MISMATCH_POSTERIOR", "POSTERIOR_FIELDS"]

#: The fields the data's mismatches redraw by default (``datamodules.noise.XI_FIELDS``).
POSTERIOR_FIELDS: tuple[str, ...] = ("gain_db", "temperature_c", "white_noise_v_per_rthz")

#: Columns of :func:`mismatch_posterior` for the default fields.
MISMATCH_POSTERIOR: tuple[str, ...] = (
    "posterior_pn_clipped_dn", "posterior_dcsn_clipped_dn", "posterior_rn_clipped_dn", "posterior_total_clipped_dn",
    "posterior_total_dn", "p_match", *(f"p_{f}" for f in POSTERIOR_FIELDS), "posterior_details", "posterior_texture",
)


# Intensity bins of the metadata-free reference variance of the first pass (a per-bin median).
_REFERENCE_BINS = 4


def _grid_values(field: str, low: float, high: float, grid: int, gain_uniform_in: str) -> torch.Tensor:
    """Centres of ``grid`` equal cells of the field's sampling variable, in the field's unit (float64)."""
    t = (torch.arange(grid, dtype=torch.float64) + 0.5) / grid
    if field == "gain_db" and gain_uniform_in == "factor":
        f_lo, f_hi = 10.0 ** (low / 20.0), 10.0 ** (high / 20.0)
        return 20.0 * torch.log10(f_lo + t * (f_hi - f_lo))
    return low + t * (high - low)


def _inliers(
    m: torch.Tensor, d2: torch.Tensor, usable: torch.Tensor, g2: torch.Tensor, v_ref: torch.Tensor, bound_margin: float,
    max_margin_dn: float = math.inf,
) -> torch.Tensor:
    """Float mask (3, B, 1, h, w) of the details used: usable blocks more than ``bound_margin`` reference σ from
    both bounds (nearer, the clipping of the noise biases the kept details low), flat at the next coarser scale
    (χ²₂ test at 99 % on the central differences of the block means, whose noise variance is v/2, dilated by one
    block), and within 3 reference σ. The margin is at most ``max_margin_dn`` (for a very noisy patch 3 σ from
    both bounds would leave no intensity at all)."""
    sd = v_ref.sqrt().clamp_max(max_margin_dn / bound_margin) if bound_margin > 0 else v_ref.sqrt()
    flat = F.max_pool2d((g2 > _TEXTURE_CHI2 * v_ref / 2.0).float(), 3, 1, 1) == 0
    keep = usable & flat & (m - bound_margin * sd > 0) & (m + bound_margin * sd < 255.0)
    return (keep & (d2 < _INLIER_Z**2 * v_ref)).float()


def _median_variance(m: torch.Tensor, diag2: torch.Tensor, usable: torch.Tensor, bins: int) -> torch.Tensor:
    """A reference noise variance that does not depend on the metadata, at every block: per intensity bin (``bins``
    equal intervals of [0, 255] DN), the median of the usable blocks' squared diagonal detail / 0.4549 (the median
    of χ²₁; the diagonal detail does not see linear gradients); +inf in a bin without usable blocks."""
    b = m.shape[0]
    k = (m / 255.0 * bins).floor().clamp(0, bins - 1).long().flatten(1)  # (B, n)
    diag = torch.where(usable.flatten(1), diag2.flatten(1), torch.full_like(m.flatten(1), float("nan")))
    per_bin = torch.full((b, bins, diag.shape[1]), float("nan"), device=m.device)
    per_bin.scatter_(1, k.unsqueeze(1), diag.unsqueeze(1))
    v_bin = torch.nanmedian(per_bin, dim=2).values / 0.4549  # (B, bins); NaN where a bin has no block
    return v_bin.gather(1, k).view_as(m).nan_to_num(float("inf")).clamp_min(1e-6)


def _noise_model(rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(slope a [DN²/DN], signal-independent variance c [DN²]) of the raw metadata rows (N, 11), float64."""
    meta = metadata_from_matrix(rows)
    dn = meta.dn_per_electron
    dc = dark_current_shot_sigma_e(meta) * dn
    rn = readout_sigma_e(meta) * dn
    return 255.0 * meta.gain_factor / meta.full_well_e, torch.stack([dc.square(), rn.square()], dim=-1)


def mismatch_posterior(
    image: torch.Tensor,
    meta: CameraMetadata,
    fields: Sequence[str] = POSTERIOR_FIELDS,
    mismatch_probability: float = 0.5,
    grid: int = 256,
    bins: int = 16,
    ranges: dict[str, tuple[float, float]] | None = None,
    gain_uniform_in: str = "factor",
    bound_margin: float = 3.0,
    passes: int = 2,
) -> torch.Tensor:
    """Posterior noise model of each patch given its metadata, (B, 8 + len(fields)) float32.

    Columns (:data:`MISMATCH_POSTERIOR` for the default fields): posterior σ [DN] of PN, DCSN, RN and the
    total after clipping to [0, 255] DN; the posterior total before clipping (E[σ_Total(M')], what ξ compares the
    metadata's total with, Eq. 4.3); P(metadata match); P(field f is wrong) for each of ``fields``; the number of
    diagonal Haar details the likelihood used (below 32 the posterior abstains: the metadata's σ and P(match) = 1);
    a texture check, log of the horizontal-and-vertical to diagonal detail energy on the blocks where all three are
    inliers (≈ 0 for white noise, > 0 where texture passed the flatness tests; 0 with fewer than 32 such blocks).

    Args:
        image: B×1×H×W noisy patches in [0, 1] (H, W ≥ 8).
        meta: the metadata the camera reports, batch 1 or B, physical units.
        fields: the fields a mismatch may redraw (one at a time).
        mismatch_probability: prior probability that one field is wrong (the data's ``xi_probability``, 0.5).
        grid: candidate values per field (cells uniform in the sampling variable).
        bins: intensity bins of the likelihood's sufficient statistics.
        ranges: per-field sampling ranges (default: conventions.md Table 4.1, ``METADATA_RANGES``).
        gain_uniform_in: ``"factor"`` (the data's default: the linear gain factor is uniform) or ``"db"``.
        bound_margin: blocks nearer than this many reference σ to 0 or 255 DN are dropped (default 3).
        passes: inlier masks: the first against a metadata-free per-bin median, each further one against the
            previous pass's posterior noise-level function (default 2).
    """
    if not isinstance(image, torch.Tensor) or image.ndim != 4 or image.shape[1] != 1:
        raise ValueError(f"image must be a B×1×H×W tensor, got {tuple(image.shape) if isinstance(image, torch.Tensor) else type(image).__name__}")
    if not image.is_floating_point():
        raise TypeError(f"image must be a floating-point tensor in [0, 1], got {image.dtype}")
    if not bool(torch.isfinite(image).all()):
        raise ValueError("image contains NaN or inf; mismatch_posterior needs finite intensities in [0, 1]")
    bad = [f for f in fields if f not in FULL_FIELDS]
    if bad or not fields:
        raise ValueError(f"fields {list(fields)} must be a non-empty list of fields from {list(FULL_FIELDS)}")
    if not 0.0 <= mismatch_probability < 1.0:
        raise ValueError(f"mismatch_probability = {mismatch_probability!r} must be in [0, 1)")
    if grid < 2 or bins < 1 or passes < 1:
        raise ValueError(f"grid = {grid} must be ≥ 2, bins = {bins} ≥ 1 and passes = {passes} ≥ 1")
    if gain_uniform_in not in ("factor", "db"):
        raise ValueError(f"gain_uniform_in = {gain_uniform_in!r} must be 'factor' or 'db'")
    b, dev = image.shape[0], image.device
    if meta.batch_size not in (1, b):
        raise ValueError(f"metadata batch {meta.batch_size} does not match the {b} patches")
    f64 = torch.float64
    with torch.autocast(device_type=dev.type, enabled=False):
        rows = torch.stack([getattr(meta, n).to(device=dev, dtype=f64).expand(b) for n in FULL_FIELDS], dim=1)
        a0, dcrn0 = _noise_model(rows)
        # candidates: the metadata themselves, then each field on its grid
        lim = dict(METADATA_RANGES, **(ranges or {}))
        slopes, variances, logp = [a0.unsqueeze(1)], [dcrn0.unsqueeze(1)], [torch.full((b, 1), math.log1p(-mismatch_probability), dtype=f64, device=dev)]
        for f in fields:
            values = _grid_values(f, float(lim[f][0]), float(lim[f][1]), grid, gain_uniform_in).to(dev)
            cand = rows.repeat_interleave(grid, 0)
            cand[:, FULL_FIELDS.index(f)] = values.repeat(b)
            a, dcrn = _noise_model(cand)
            slopes.append(a.view(b, grid))
            variances.append(dcrn.view(b, grid, 2))
            logp.append(torch.full((b, grid), math.log(max(mismatch_probability, 1e-300) / len(fields)) - math.log(grid), dtype=f64, device=dev))
        a_all, var_all, prior = torch.cat(slopes, 1), torch.cat(variances, 1), torch.cat(logp, 1)
        m, d2, usable, g2 = block_details(image, "mismatch_posterior")
        kbin = (m / 255.0 * bins).floor().clamp(0, bins - 1).long().flatten(1)  # (B, h·w)
        idx = (torch.arange(b, device=dev).view(b, 1) * bins + kbin).flatten()
        m_flat = m.flatten()
        v_ref = _median_variance(m, d2[0], usable, _REFERENCE_BINS)
        w = torch.softmax(prior, dim=1)  # replaced by each pass's posterior
        for step in range(passes):
            if step:  # the posterior's own noise-level function v = E[a′]·m + E[c′]
                v_ref = ((w * a_all).sum(1).float().view(b, 1, 1, 1) * m.clamp_min(0)
                         + (w * var_all.sum(-1)).sum(1).float().view(b, 1, 1, 1)).clamp_min(1e-6)
            inl_all = _inliers(m, d2, usable, g2, v_ref, bound_margin)
            inl = inl_all[0]  # the likelihood reads the diagonal detail only (linear gradients do not reach it)
            n_det = inl.flatten().to(f64)  # 1 where the block's diagonal detail is an inlier
            sq_det = (d2[0] * inl).flatten().to(f64)

            def per_bin(values: torch.Tensor) -> torch.Tensor:
                return torch.zeros(b * bins, dtype=f64, device=dev).index_add_(0, idx, values).view(b, bins)

            count, sq = per_bin(n_det), per_bin(sq_det) / _TRUNCATED_CHI2
            mk = (per_bin(m_flat.to(f64) * n_det) / count.clamp_min(1.0)).clamp_min(0.0)
            evidence = count.sum(1) >= _MIN_FIT_BLOCKS

            def loglik(a: torch.Tensor, c: torch.Tensor) -> torch.Tensor:  # a, c: (B, G) → (B, G)
                v = (a.unsqueeze(-1) * mk.unsqueeze(1) + c.unsqueeze(-1)).clamp_min(1e-6)
                return -0.5 * (sq.unsqueeze(1) / v + count.unsqueeze(1) * v.log()).sum(-1)

            ll = loglik(a_all, var_all.sum(-1))
            ll = torch.where(evidence.unsqueeze(1), ll, torch.zeros_like(ll))
            w = torch.softmax(ll + prior, dim=1)  # (B, 1 + F·G)
        # no evidence: the posterior abstains — all weight on the metadata themselves (their σ, P(match) = 1)
        metadata_only = torch.zeros_like(w)
        metadata_only[:, 0] = 1.0
        w_sigma = torch.where(evidence.unsqueeze(1), w, metadata_only)
        group = torch.cat([w_sigma[:, :1], w_sigma[:, 1:].view(b, len(fields), grid).sum(-1)], dim=1)
        mean_i = image.detach().to(f64).clamp(0, 1).flatten(1).mean(1) * 255.0
        var_src = torch.stack([a_all * mean_i.unsqueeze(1), var_all[..., 0], var_all[..., 1]], dim=-1)  # (B, G', 3)
        e_sigma = (w_sigma.unsqueeze(-1) * var_src.sqrt()).sum(1)
        e_var = (w_sigma.unsqueeze(-1) * var_src).sum(1)
        e_total = (w_sigma * var_src.sum(-1).sqrt()).sum(1)
        e_slope = (w_sigma * a_all).sum(1)
        f32 = torch.float32
        img = image.detach().to(f32).clamp(0, 1) * 255.0
        x = estimate_clean_dn(img, e_slope.to(f32), (e_var[:, 1] + e_var[:, 2]).to(f32), dtype=f32)
        clipped = clipped_sigma_dn(x, [e_slope.to(f32).view(-1, 1, 1, 1) * x, e_var[:, 1].to(f32), e_var[:, 2].to(f32)], dtype=f32).to(f64)
        # E[σ] rather than √E[σ²] where the posterior is spread over candidates
        scale = e_sigma / e_var.clamp_min(1e-12).sqrt()
        clipped_src = clipped[:, :3] * scale
        total_scale = e_total / e_var.sum(1).clamp_min(1e-12).sqrt()
        clipped_total = clipped[:, 3] * total_scale
        # texture check: on blocks whose three details are all inliers, the horizontal and vertical details of white
        # noise carry the same energy as the diagonal one; texture that passed the tests adds to them first
        both = inl_all.prod(0)
        hv = ((d2[1] + d2[2]) * both).flatten(1).sum(1).to(f64) / 2.0
        dd = (d2[0] * both).flatten(1).sum(1).to(f64)
        texture = torch.where(both.flatten(1).sum(1) >= _MIN_FIT_BLOCKS, torch.log((hv + 1e-6) / (dd + 1e-6)), torch.zeros_like(hv))
        out = torch.cat([clipped_src, clipped_total.unsqueeze(1), e_total.unsqueeze(1), group, count.sum(1, keepdim=True),
                         texture.unsqueeze(1)], dim=1)
    return out.float()
