"""Noise sources from one patch and its metadata, physics first: the closed form unless the image contradicts it.

The metadata M fix every source's σ in closed form (conventions.md Eq. 3.14–3.19, carried through the clipping
by :func:`~camhealth.estimators.noise_features.clipped_prior_dn`). The patch measures its own noise-level
function (NLF): on flat, unclipped 2×2 blocks the diagonal Haar detail d = (I₀₀ − I₀₁ − I₁₀ + I₁₁)/2 is
N(0, v(m)) with

    v(m) = a·m + σ_DCSN² + σ_RN² + q,   a = 255·g/FW [DN²/DN],   q = 1/12 DN² for 8-bit (integer) input

at the block mean m [DN]. The details are binned by intensity (``bins`` intervals of [0, 255] DN); bin k gives
N_k details and a variance ŝ_k (their truncated second moment). Each hypothesis H for the camera's state
predicts v_k(H), and the evidence is read in log space, where a bin's sampling error is ≈ 2/N_k:

    r_k = ln ŝ_k − ln (f_k·v_k(H)),   ℓ(H) = −½ rᵀ Σ⁻¹ r,   Σ = diag(2/N_k + η_b²) + η²·11ᵀ.

f_k ≤ 1 is the share of the noise a block keeps when it is used only if none of its pixels is clipped: near 0 or
255 DN that drops the blocks whose noise swings widest (:func:`_kept_variance_factor`, a truncated normal; 1 far
from the bounds). Without it a 60 DN patch reads 7 % low; with it, blocks down to 2 σ from the bounds are used, and
down to 1 σ in a patch (pooled: a frame) that keeps fewer than :data:`MIN_FOLLOW_DETAILS` details at 2 σ — a dark or
bright patch under strong noise, whose blocks all lie near a bound (at 40 DN with 35 DN of noise: within 8 %, where
2 σ alone leaves no flat area and the closed form would stand). A far noisier hypothesis, whose few kept blocks would
be as quiet, is refused by the count of clipped pixels (:func:`_clipping_penalty`).

**The scene's own fine-scale content.** A scene adds to the details by itself — texture too fine for the flatness
tests, and in recorded frames their own noise and compression. On the robustness benchmark's scenes that is
0.8 DN at the median as they are and 2 DN area-downsampled 3× (lower quartile of 8×8-px windows;
``camhealth.bench.robustness.scene_floor_dn``) — at 3× as much as a visible mismatch of a 2–4 DN camera. So a bin
that reads *more* than f_k·v_k(H) carries the extra log-variance ln(1 + τ²/v_k)² (τ = ``scene_allowance_dn``) in
Σ's diagonal, one that reads less carries none (a scene cannot remove noise): the
image contradicts the metadata by more noise only where the excess is well beyond what a scene brings, and by less
noise as before. That keeps the closed form on busy matched frames (and on compressed ones whose codec added a few
DN); the price is that a mismatch adding less than a few τ in quadrature on a quiet camera goes unseen (on the
quietest cameras, where ln(1 + τ²/v)² grows without bound as v → 0, several τ: the uncertainty then covers it,
``excess_dn``). The
allowance enters each intensity bin's variance on its own, so in the common offset a patch whose details all fall in
one bin carries it whole and one spread over k bins about 1/k of it: per patch, the verdict on a flat patch near that
threshold depends on where its level falls among the bins (ICX285 at 0 dB, 1.4 DN: a flat patch of 5 DN white noise
keeps the closed form at 104 DN, a bin's centre, P(match) 0.65, and is followed at 110 DN). Pooled, a frame spans
many bins and its own τ is read (below).

Per patch τ is ``scene_allowance_dn`` (2 DN, the 3× floor). Pooled, a frame reads its own: white noise puts as
much energy into the horizontal and vertical Haar details as into the diagonal one, while a scene's fine content
puts at least ``SCENE_DETAIL_RATIO`` (r = 2) times as much (a spectrum ∝ f^−β through the pixel aperture: r = 1.4 at
β = 0, 1.9 at β = 1, 2.9 at β = 2), so on the frame's inliers the excess E[d_HV²] − E[d_D²] bounds what the scene
added to the diagonal detail by (r − 1)⁻¹ times itself: τ² = τ_min² + excess/(r − 1), between τ_min =
``scene_allowance_min_dn`` (1 DN: the white content of a recorded source, which no ratio can see) and the per-patch
τ. A quiet frame thus shows a mismatch that adds 1–2 DN in quadrature, a busy one keeps the allowance it had. Per
patch the same reading is not used: one patch's excess is one texture's, and on the benchmark's photographs some
patches carry near-white fine content of their own (r ≈ 1.5) that it would miss.

η is the **model error** that is common to all bins — what an NLF measured on real data differs by from the
ideal model even when the metadata are right (another simulator's details, compression, demosaicking, slight
texture): a relative error of the variance of about η. η_b is the same per bin (texture that passed the
flatness tests in one intensity range). With them, no number of details makes a 5 % deviation decisive: the
image contradicts the metadata only where it deviates by more than the model error — which is what "do no
harm" needs. Σ⁻¹ is applied in closed form (Sherman–Morrison), so ℓ costs O(bins) per hypothesis.

Hypotheses (the thesis's mismatch model, Sec. 6.3.2: one field of M is wrong at a time):

- H₀: M is right (prior 1 − ``mismatch_probability``, ½);
- gain, temperature or thermal white noise W wrong: each field on a grid of ``grid`` values uniform over its
  range (gain uniform in the linear factor), the σ of every candidate from the physics (Eq. 3.14–3.19), so a
  field explains only what its physical range allows;
- noise that no metadata in range explain: extra white noise of σ_x on a log grid up to 128 DN, counted as
  readout noise (prior ``beyond_probability``). The four kinds of mismatch share the mismatch prior equally
  (⅛ each): a noise source outside the metadata is as likely as any one field being wrong.

The texture check — ln of the horizontal-and-vertical to diagonal detail energy on the inliers, ≈ 0 for white
noise — widens the common model error: η_eff² = η² + max(texture, 0)² (texture adds to the horizontal and vertical
details first, so it bounds what it may have added to the diagonal one). It reads the horizontal and vertical details
with the patch's plane taken out (:func:`~camhealth.estimators.noise_features.plane_free_details`: the medians of the
usable blocks' signed details), as does the inlier test: a smooth ramp puts its slope into them and nothing into the
diagonal detail, so it is no texture. The pooled scene allowance reads them as they are (a scene's gradients are part
of its fine content).

The neighbour check: white noise leaves the diagonal details of adjacent blocks uncorrelated, and a scene's fine
texture does not (grass or gravel seen under strong noise, where the texture ratio is near 0 because the noise
dominates all three details, or a texture without horizontal and vertical energy at all). The correlation ρ of the
standardised diagonal details d/√v_ref over adjacent inlier pairs (horizontal and vertical; over the frame when
pooled) must stay within max(:data:`DETAIL_CORR_LIMIT`, 3/√pairs); its covariance is a lower bound on what the
texture adds to each detail. On the robustness benchmark's strong-noise frames of clean scenes |ρ| ≤ 0.02, on grass
and gravel 0.04–0.11.

The answer: a mismatch too small to see (it moves σ_Total by less than max(0.5 DN, 15 %)) counts as a match, and
P(match) is H₀'s posterior plus theirs. Where P(match) ≥ ½, or fewer than :data:`MIN_FOLLOW_DETAILS` details were
used, or the patch is textured (:func:`textured`: the texture check and the neighbour check, each scaled to its
limit, add up in quadrature to 1 or more — each alone at its limit, or two marginal signs together): the closed form exactly (σ per source after clipping,
ξ = 0). Elsewhere the posterior over the visible mismatch hypotheses: its σ per source after clipping (at the
posterior-mean variances) and ξ = σ_Total(M) − σ_Total(image) (Eq. 4.3, both after clipping). ``xi_std`` is the
posterior standard deviation of σ_Total (∞ without evidence), raised where the closed form is kept although a bin
reads beyond the scene allowance above it (column ``excess_dn`` of :func:`physics_noise_posterior`). Inliers are chosen in two passes — against a
metadata-free per-intensity median of the details, then against the first pass's posterior NLF — so a camera far
noisier than its metadata keeps its details. Where the first pass found no flat block (a ramp steeper than about half
the noise σ per pixel fails the flatness test on its slope), that posterior is the prior, whose wide NLF admits nearly
every block: the texture and neighbour checks then decide whether the patch is read (a ramp is, an edge-filled or
textured patch is not).

**Row and column noise** (banding, :mod:`camhealth.estimators.row_column_noise`): offsets shared by whole pixel rows or
columns, which no source of the metadata makes. The diagonal detail never sees them; the horizontal and vertical ones
do, so the texture check would call a banded flat patch textured. Where they are detected (pooled: over the frame),
they are taken out of the horizontal and vertical details and of the block-mean gradients before the checks, and
where the patch then passes them and the banding moves σ_Total visibly, the image's σ_Total is
√(σ_Total(pixel noise)² + σ_row² + σ_col²): ξ says the image is noisier, P(match) is 0, and the per-source σ stay
the pixel noise's. Columns ``row_dn``/``col_dn`` give the detected σ (0 where none is).

**Defective pixels** (hot, stuck and dead pixels, impulses: :mod:`camhealth.estimators.defective_pixels`): a pixel
that stands above or below all its neighbours by far more than the local noise. The fits here are robust to them and
do not count them in σ_Total; ``predict`` returns their count per patch (``defects``: hot, dark), where they are
(``defect_mask``) and the pixels tested (``defects_checked``: 0 on a patch whose local extremes are a regular pattern).

**Two exposures of a still scene** (``reference``; :mod:`camhealth.estimators.static_pair`): the evidence is read
from the pair's fold J (not clamped to [0, 1]), whose details hold the two frames' noise and nothing of the scene, with
no scene allowance, flatness tested on the difference's block means, the details binned at the average's block mean
(the scene's level, independent of the difference), blocks used where no pixel clips in either frame and the
average's pixels lie ``bound_margin`` σ (at most 100 DN) from the bounds, and the clipping's loss modelled pixel by
pixel: given the average A, neither frame clips exactly where the scaled difference stays within
c = √2·min(A − ½, 254.5 − A), so each used pixel keeps the share h(c/σ) of the variance
(:func:`~camhealth.estimators.noise_features.truncated_second_moment`, :func:`pair_kept_variance_factor`) — exact
for Gaussian noise however strong, so the pair reads σ up to the validated 64 DN (one frame's model infers the loss
from block means instead). The
clipping penalty, the rounding and σ after clipping stay ``image``'s. :meth:`PhysicsNoiseEstimator.predict` tests per
patch that the scene stood still and reads the others alone.

**Other exposure times of the same camera** (``other_evidence``; :func:`noise_evidence`): one camera state cannot split
a signal-independent excess between dark-current shot noise and readout noise — both add a constant to v(m). The
hypotheses are absolute values of the camera's fields, so frames whose metadata differ only in the exposure time share
them, and each predicts σ_DCSN² ∝ t_exp in every frame and the same σ_RN: the frames' per-hypothesis sums Σr²/D, Σr/D,
Σ1/D and clipping penalties add up, η is applied once to the sum (one camera, one model error), and the split follows
the physics. A mismatch that moves σ_Total visibly in any of the frames is visible in all of them: a sensor hotter than
told shows at the long exposure, and the short one, whose σ_Total it moves too little to see, follows it as well.
:meth:`PhysicsNoiseEstimator.predict` takes such frames (``other_exposures``) or their kept evidence.

Not assessable (``assessable=False`` with ``reason``), in this order: black or saturated patches (more than half
clipped); ``"noise beyond validated range"`` where that is known without a reading — the patch's finest-scale
fluctuations, measured over all of its blocks, above :data:`VALIDATED_SIGMA_DN` by more than three of their sampling
standard errors (:func:`beyond_validated_range`: noise that is not clipped Gaussian noise, such as uniform noise, can
read below the limit through the clipped-Gaussian model, and noise so strong that no block is left unclipped reads
nothing), or the metadata's own σ_Total before clipping above it (the closed form, which such a patch returns: there
the clipping takes so much of the noise that the closed-form correction is not validated); ``"no flat area"`` (fewer
than :data:`MIN_FOLLOW_DETAILS` usable details: texture or clipping nearly everywhere — the metadata cannot be
checked; the closed form is still returned); ``"textured"`` (the horizontal and vertical details carry clearly more
energy than the diagonal one on the inliers, or adjacent diagonal details are correlated, so texture leaked into the
evidence: the closed form is returned and ξ is not trusted); ``"noise beyond validated range"`` where the image's
reading of σ_Total before clipping exceeds the limit by three of its sampling standard errors, σ/√(2N) from its N
details (the rule of :func:`beyond_validated_range`; near 0 or 255 DN, where a 128-px patch keeps ≈ 380 details,
60 DN of noise reads up to 68 DN and is read, 80 DN is refused; the posterior's spread, which also carries the model
error η, is 2–4× the estimates' spread there and is not used); ``"less noise than the metadata allow"``
(``quiet_z`` below −:data:`QUIET_Z_LIMIT`: the image's noise reads far below that of every camera state the
hypotheses span — a denoised, compressed, rescaled or rendered image, or the metadata of a noisier camera — which no
hypothesis explains: the closed form is returned, ``xi_std`` and ``sigma_std`` are ∞ (no stated uncertainty) and
``cause`` NaN; ``p_match`` is still the posterior's and only says whether the camera states that fit least badly are
visible mismatches — no verdict on the metadata); and ``"noise below the quantisation step"`` instead of it on
8-bit input where the quietest of those camera states makes less than :data:`QUANTISATION_SIGMA_DN` at the patch's
level (rounding a flat area at a whole DN removes such noise rather than adding 1/12 DN² to it, so a matched quiet
camera reads that quiet; the closed form is returned). Pooled, a patch that reads so
alone (a noiseless overlay, letterbox or masked area) is refused with its own ``quiet_z`` and, where such patches
are at most half of the frame's, left out of the frame's evidence, so the rest of the frame is read as it is; where
they are most of it, every patch of the frame is refused. And ``"a lossy codec changed the noise"``: 8-bit input that
would be followed against its metadata and shows JPEG's quantised 8×8 block grid
(:mod:`camhealth.estimators.jpeg_quantisation`; pooled, on 4 of the frame's patches). The codec zeroes the transform
coefficients below its quantisation steps, noise included, and adds its quantisation error to the others — on a
fine texture that error reads as noise — so a JPEG of a camera as noisy as its metadata say may read cleaner (at
quality 75–95, a 2.6 DN camera's readout noise read as 0.5 DN) or noisier (a fine road surface, 4.3 DN above a
3.3 DN camera). The closed form is returned with no verdict, as for less noise than the metadata allow.

The reference variance of the first pass (the per-intensity median of the details) is floored at the quantisation
variance of 8-bit input: a quiet 8-bit patch (σ ≲ 0.4 DN) has mostly zero details, whose median 0 would call nearly
every block non-flat (ICX285 as preset at 3–5 DN: 0.33–0.38 DN, read as the closed form, not "no flat area").

σ per source after clipping are those of the labels' attribution (:func:`~camhealth.physics.clipping.clipped_sigma_dn`):
each source keeps its share n_k·f of the clipped noise y, f = y/n. On a flat scene y spans at most 255 DN, so the
total's σ is at most 127.5 DN; a source's share is not so confined (where it outweighs the total, the other sources
cancelling part of it), so beyond the validated range a source's σ may exceed the clipped total and 127.5 DN, as the
rule realises (a Monte Carlo of the rule, ``tests/estimators/test_physics_noise.py``). And the scene recovered from a patch with such noise
is not flat (its 3×3 means vary by σ/3), so there even the total may read above 127.5 DN: a camera of 520 DN at
128 DN reads σ_DCSN 164 DN against a total of 145 DN. Such patches are refused (beyond the validated range).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from camhealth._order import sorted_values
from camhealth._inputs import (_MAD_NORMAL, _MAD_RELATIVE_SE, BEYOND_VALIDATED, VALIDATED_SIGMA_DN, _check_noise_patches, _to_metadata,
                               _to_patches, assess_patches, beyond_validated_range, haar_noise_dn)
from camhealth._validation import check_batch_size
from camhealth.estimators.noise_features import (
    _INLIER_Z, _MIN_FIT_BLOCKS, _TEXTURE_CHI2, _TRUNCATED_CHI2, _block_pixels, _clipped_prior_dn, block_details,
    plane_free_details,
    metadata_from_matrix, truncated_second_moment,
)
from camhealth.estimators.defective_pixels import defective_pixels
from camhealth.estimators.jpeg_quantisation import coded_frame, jpeg_grid
from camhealth.estimators.row_column_noise import debanded_details, row_column_noise
from camhealth.estimators.static_pair import pair_fold, pair_stillness
from camhealth.physics.dark_current import dark_current_shot_sigma_e
from camhealth.physics.metadata import FULL_FIELDS, METADATA_RANGES, CameraMetadata, SensorConstants
from camhealth.physics.readout_noise import readout_sigma_e

__all__ = ["physics_noise_posterior", "PhysicsNoiseEstimator", "MISMATCH_CAUSES", "VALIDATED_SIGMA_DN", "BEYOND_VALIDATED", "LESS_NOISE",
           "QUIET_Z_LIMIT", "BELOW_QUANTISATION", "LOSSY_CODEC", "QUANTISATION_SIGMA_DN", "quieter_than_any_camera", "LOUD_RATIO",
           "beyond_validated_range", "PHYSICS_NOISE_COLUMNS", "SCENE_ALLOWANCE_DN",
           "SCENE_ALLOWANCE_MIN_DN", "SCENE_DETAIL_RATIO", "PATCH_CHUNK", "PAIR_SCENE_ALLOWANCE_DN", "textured", "pair_kept_variance_factor",
           "noise_evidence"]

#: τ [DN] of a static pair (:meth:`PhysicsNoiseEstimator.predict` with ``reference``): the difference of two exposures
#: holds nothing of a static scene, so no allowance is made for its fine content.
PAIR_SCENE_ALLOWANCE_DN = 0.0
#: The ``reason`` of a patch that reads far less noise than any camera state in the metadata's ranges makes
#: (``quiet_z`` below −:data:`QUIET_Z_LIMIT`): a denoiser, a codec that removed the noise, a rendered or rescaled
#: image. No hypothesis explains it, so the posterior cannot tell; the closed form is returned, not assessable.
LESS_NOISE = "less noise than the metadata allow"
#: Standard errors below the best-fitting hypothesis (``quiet_z``) from which a patch is :data:`LESS_NOISE`.
QUIET_Z_LIMIT = 5.0
#: σ [DN] below which 8-bit rounding removes noise instead of adding 1/12 DN² to it. A flat area at clean level s
#: rounds to r = round(s + n), whose variance depends on the fractional part φ of s: at σ = 0.6 DN within ±0.3 % of
#: σ² + 1/12 DN² for every φ, at 0.5 DN within ±2.4 %, at 0.4 DN −13…+13 %, at 0.3 DN −45…+37 %, at 0.16 DN
#: 1.6 %…2.3× (Var r = Σₖ k²·pₖ − (Σₖ k·pₖ)², pₖ = Φ((k + ½ − φ)/σ) − Φ((k − ½ − φ)/σ)). Below it a quiet 8-bit patch
#: may read far less noise than its camera makes without anything having removed it.
QUANTISATION_SIGMA_DN = 0.5
#: The ``reason`` of an 8-bit patch that reads :data:`LESS_NOISE` where the quietest camera state the metadata's ranges
#: allow makes less than :data:`QUANTISATION_SIGMA_DN` at the patch's level: the rounding, not a denoiser, may have
#: removed the noise, so the image cannot check the metadata. The closed form is returned, not assessable.
BELOW_QUANTISATION = "noise below the quantisation step"
#: The ``reason`` of an 8-bit patch that would contradict its metadata and shows JPEG's quantised 8×8 block grid
#: (:func:`~camhealth.estimators.jpeg_quantisation.jpeg_grid`; pooled, the frame:
#: :func:`~camhealth.estimators.jpeg_quantisation.coded_frame`): the codec zeroed the coefficients below its
#: quantisation steps, noise included, and added its quantisation error to the others, so the noise the image shows is
#: the codec's as much as the camera's. The image cannot check the metadata; the closed form is returned, not
#: assessable (column ``codec``).
LOSSY_CODEC = "a lossy codec changed the noise"
#: Pooled: a patch whose noise σ reads more than this many times the frame's median patch's (and QUIET_Z_LIMIT
#: standard errors above it) is far noisier than its frame — amp glow, a hot or a pasted region — and is read alone;
#: so is a noise-like patch above a gap of this ratio between the frame's noise-like patches (two noise levels).
LOUD_RATIO = 2.0
#: τ [DN] of :func:`physics_noise_posterior`: what a scene may add to the finest-scale statistic by itself. The lower
#: quartile of the 8×8-px windows' diagonal detail on clean frames (``camhealth.bench.robustness.scene_floor_dn``) is
#: 2.0 DN at the median over the street clip and the photographs, area-downsampled 3× (≈ 2 DN on the street frames,
#: 0.3–1.5 DN on quiet photos, 5–14 DN on grass and gravel, which the texture check refuses); τ was chosen there.
#: As they are (full resolution) the same scenes read 0.83 DN at the median (street frames 0.73 DN).
SCENE_ALLOWANCE_DN = 2.0
#: τ_min [DN]: pooled, the allowance of a frame whose details show no texture — what a recorded source brings of white
#: content of its own (the street clip's own noise and compression: 0.73 DN at the median as recorded). A frame's τ is
#: read from its details between τ_min and :data:`SCENE_ALLOWANCE_DN` (:func:`physics_noise_posterior`).
SCENE_ALLOWANCE_MIN_DN = 1.0
#: Least ratio of horizontal-and-vertical to diagonal Haar detail energy of a scene's own fine content (white noise:
#: 1). Through the pixel aperture a power spectrum ∝ f^−β gives 1.4 at β = 0, 1.9 at β = 1 and 2.9 at β = 2 (natural
#: scenes, β ≈ 2; optics steepen it); the least-textured half of the robustness benchmark's clean frames reads 1.9–3.8.
SCENE_DETAIL_RATIO = 2.0
#: Texture check above which ξ is not trusted: ln(E[d_H² + d_V²]/2 / E[d_D²]) on the inliers (0 for white noise).
TEXTURE_LIMIT = 0.25
#: Largest |correlation| of adjacent blocks' diagonal details (0 for white noise) before ξ is not trusted ("textured").
DETAIL_CORR_LIMIT = 0.03
#: Fewest diagonal details (flat, unclipped 2×2 blocks; a 128-px patch has 4 096) on which the answer may leave the
#: closed form: below it the patch is mostly texture, whose few flat-looking blocks say "noisier" without being noise.
MIN_FOLLOW_DETAILS = 256
#: A mismatch is visible where it moves σ_Total by at least max(VISIBLE_XI_DN, VISIBLE_XI_FRACTION · σ_Total).
VISIBLE_XI_DN = 0.5
VISIBLE_XI_FRACTION = 0.15
#: Fields whose mismatch the posterior weighs (thesis Sec. 6.3.2).
MISMATCH_FIELDS: tuple[str, ...] = ("gain_db", "temperature_c", "white_noise_v_per_rthz")
#: Columns of :func:`physics_noise_posterior`.
PHYSICS_NOISE_COLUMNS: tuple[str, ...] = (
    "pn_dn", "dcsn_dn", "rn_dn", "total_dn", "xi_dn", "xi_std_dn", "p_match", "details", "texture", "follows_image",
    "total_unclipped_dn", "detail_corr_check", "scene_allowance_dn", "pn_std_dn", "dcsn_std_dn", "rn_std_dn",
    "row_dn", "col_dn", "patch_details", "patch_texture", "patch_detail_corr_check",
    "p_cause_gain", "p_cause_temperature", "p_cause_white_noise", "p_cause_beyond", "quiet_z",
    "quietest_total_dn", "codec", "excess_dn",
)
#: What a visible mismatch may be (the hypotheses' kinds, in the order of the ``cause`` output): one of
#: :data:`MISMATCH_FIELDS` wrong, or noise beyond what any field in range explains.
MISMATCH_CAUSES: tuple[str, ...] = (*MISMATCH_FIELDS, "beyond")
#: Patches per call of :func:`physics_noise_posterior` in :meth:`PhysicsNoiseEstimator.predict` (per patch; pooled, the
#: frame is one call): larger chunks outgrow the CPU's caches (1.3 against 1.0 ms per patch at 256 on a 2-core VM; 32 reads as
#: 64).
PATCH_CHUNK = 64
# the bound margin leaves at least 100…155 DN usable however noisy the patch (≥ 2 σ up to 50 DN, 1.7 σ at 60 DN)
_MAX_MARGIN_DN = 100.0
# bins with fewer details than this carry no evidence (their ŝ is too rough for the log-normal approximation)
_MIN_BIN_DETAILS = 8


def textured(texture: torch.Tensor, corr_check: torch.Tensor) -> torch.Tensor:
    """Whether texture leaked into the evidence (bool, broadcast): the texture check (the log ratio of horizontal and
    vertical to diagonal detail energy, ≈ 0 for white noise) over :data:`TEXTURE_LIMIT` and the neighbour check
    (|ρ| of adjacent diagonal details over its limit), added in quadrature, reach 1.

    Each check alone at its limit is texture, as is a patch where both are marginal (say 0.75 and 0.7 of their
    limits): white noise keeps both near 0 at once, so two independent signs of texture that agree are one clear
    sign. Such patches — mostly texture, a few hundred flat-looking blocks — otherwise read several DN noisier than
    their camera (on the robustness benchmark's matched frames, up to 9.5 DN)."""
    t = torch.as_tensor(texture).double().clamp_min(0) / TEXTURE_LIMIT
    return t.square() + torch.as_tensor(corr_check).double().square() >= 1.0


def _grid_values(name: str, low: float, high: float, grid: int, gain_uniform_in: str) -> torch.Tensor:
    """Centres of ``grid`` equal cells of the field's sampling variable, in the field's unit (float64)."""
    t = (torch.arange(grid, dtype=torch.float64) + 0.5) / grid
    if name == "gain_db" and gain_uniform_in == "factor":
        f_lo, f_hi = 10.0 ** (low / 20.0), 10.0 ** (high / 20.0)
        return 20.0 * torch.log10(f_lo + t * (f_hi - f_lo))
    return low + t * (high - low)


@functools.lru_cache(maxsize=1)
def _kept_share_table() -> tuple[torch.Tensor, torch.Tensor]:
    """(t, g(t)) float64: the share of σ² left in a 2×2 block's diagonal detail when the block is kept only if
    all four pixels lie above a bound t·σ below the block mean (Gaussian noise), t = 0, 0.05, …, 8.

    Given the block mean, the pixel deviations are e = σ·(z − z̄) for z ~ N(0, I₄) (independent of the mean), and
    d_D = (e₀₀ − e₀₁ − e₁₀ + e₁₁)/2; g(t) = E[d_D² | min e > −tσ]/σ², a three-dimensional integral evaluated by
    Monte Carlo over 2¹⁸ seeded draws (standard error < 1 % where P(kept) > 1 %, which covers t ≥ 0.4; below,
    g(0.4) stands: such blocks are almost never kept)."""
    g = torch.Generator().manual_seed(0)
    z = torch.randn(1 << 18, 4, generator=g, dtype=torch.float64)
    e = z - z.mean(1, keepdim=True)
    d2 = ((e[:, 0] - e[:, 1] - e[:, 2] + e[:, 3]) / 2.0).square()
    lowest = e.min(1).values
    order = torch.argsort(lowest, descending=True)
    csum = torch.cumsum(d2[order], 0)
    t = torch.linspace(0.0, 8.0, 161, dtype=torch.float64)
    kept = torch.searchsorted(-lowest[order], t, right=False)  # draws with min e > −t
    share = csum[(kept - 1).clamp_min(0)] / kept.clamp_min(1).double()
    share = torch.where(t < 0.4, share[t >= 0.4][0], share)
    return t, share.clamp(1e-3, 1.0)


def _kept_variance_factor(level: torch.Tensor, var: torch.Tensor) -> torch.Tensor:
    """The share of the noise variance ``var`` [DN²] left in the diagonal details of the blocks kept at block mean
    ``level`` [DN]: a block is usable only where none of its four pixels is within ½ DN of 0 or 255 DN, and near
    the bounds that drops the blocks whose noise swings widest, so the kept details are quieter than the noise.

    Each bound at t = distance/σ keeps the share g(t) of :func:`_kept_share_table` (the pixels' deviations from
    the block mean, conditioned on all of them staying inside); both bounds keep the product f = g(t₀)·g(t₂₅₅)
    (where one bound binds, that bound's share; where both do, as for noise comparable to the distance to either,
    a share that stays positive: 0.24 at 128 DN with 128 DN of noise, where a seeded Monte Carlo of four pixels
    kept inside both bounds gives 0.29). Returns f in (0, 1], broadcast over ``level`` and ``var`` (1 far from the
    bounds; 0.87 at 128 DN with 60 DN of noise, 0.66 at 20 DN with 15 DN)."""
    t_grid, share = _kept_share_table()
    t_grid, share = t_grid.to(level.device), share.to(level.device)
    sd = var.double().clamp_min(1e-12).sqrt()

    def kept(dist: torch.Tensor) -> torch.Tensor:
        t = (dist.double() / sd).clamp(0.0, 8.0)
        pos = t / 0.05
        i = pos.floor().long().clamp(0, len(t_grid) - 2)
        w = pos - i
        return share[i] * (1 - w) + share[i + 1] * w

    f = kept(level - 0.5) * kept(254.5 - level)
    return f.clamp(1e-3, 1.0).to(var.dtype)


#: A static pair's per-pixel clipping limits c [DN] (:func:`~camhealth.estimators.static_pair.difference_limits_dn`)
#: are counted on a log grid of this many intervals between _PAIR_C_RANGE[0] and [1] DN (c ≤ √2·127 DN always; each
#: interval spans 11 %, its geometric centre stands for it), the noise σ on a log grid of _PAIR_SIGMA_GRID points.
_PAIR_C_BINS = 64
_PAIR_C_RANGE = (0.25, 180.0)
_PAIR_SIGMA_GRID = (0.05, 400.0, 97)


def _pair_c_index(c: torch.Tensor) -> torch.Tensor:
    """The interval of _PAIR_C_BINS that each limit c [DN] falls in (int32; below the grid: 0, above: the last)."""
    lo, hi = _PAIR_C_RANGE
    pos = (c.clamp(lo, hi).log_() - math.log(lo)).mul_(_PAIR_C_BINS / math.log(hi / lo))
    return pos.int().clamp_(0, _PAIR_C_BINS - 1)


@functools.lru_cache(maxsize=4)
def _pair_share_table(device: str) -> tuple[torch.Tensor, torch.Tensor]:
    """(ln σ grid (G,), h(c_j/σ_g) (J, G)) float64: the share of the variance a pixel keeps whose difference is used
    only within its limit c_j, at each noise σ_g of the grid (:func:`pair_kept_variance_factor`)."""
    lo, hi = _PAIR_C_RANGE
    centres = torch.exp(math.log(lo) + (torch.arange(_PAIR_C_BINS, dtype=torch.float64) + 0.5) * (math.log(hi / lo) / _PAIR_C_BINS))
    s_lo, s_hi, n = _PAIR_SIGMA_GRID
    log_sigma = torch.linspace(math.log(s_lo), math.log(s_hi), n, dtype=torch.float64)
    table = truncated_second_moment(centres.unsqueeze(1) / log_sigma.exp().unsqueeze(0))
    return log_sigma.to(device), table.to(device)


def pair_kept_variance_factor(c_counts: torch.Tensor, var: torch.Tensor) -> torch.Tensor:
    """The share of the noise variance ``var`` [DN²] left in a static pair's diagonal details, (E, H) float64, for E
    intensity bins given (E, _PAIR_C_BINS) counts of their pixels' clipping limits c (:func:`_pair_c_index` of
    :func:`~camhealth.estimators.static_pair.difference_limits_dn`) and (E, H) hypothesised variances.

    A detail is the ± sum of its four pixels' scaled differences over 2, each truncated at its own limit independently
    of the others, so E[d²] = v·mean over the pixels of h(c_i/√v)
    (:func:`~camhealth.estimators.noise_features.truncated_second_moment`); per bin that is the mean over all its used
    pixels. Evaluated on a log grid of σ (every 0.09 in ln σ) and interpolated: within
    0.3 % of the exact mean. 1 where a bin has no counts."""
    if c_counts.ndim != 2 or c_counts.shape[1] != _PAIR_C_BINS or var.ndim != 2 or var.shape[0] != c_counts.shape[0]:
        raise ValueError(f"c_counts must be (E, {_PAIR_C_BINS}) and var (E, H), got {tuple(c_counts.shape)} and {tuple(var.shape)}")
    log_sigma, table = _pair_share_table(str(var.device))
    total = c_counts.sum(1, keepdim=True)
    share = (c_counts.double() / total.clamp_min(1.0)) @ table  # (E, G): the bin's factor at each σ of the grid
    share = torch.where(total > 0, share, torch.ones_like(share))
    step = float(log_sigma[1] - log_sigma[0])
    pos = ((0.5 * var.double().clamp_min(1e-12).log() - float(log_sigma[0])) / step).clamp(0.0, len(log_sigma) - 1.000001)
    i = pos.floor().long()
    w = pos - i
    return (share.gather(1, i) * (1.0 - w) + share.gather(1, i + 1) * w).clamp(1e-3, 1.0)


def _clipping_penalty(
    x: torch.Tensor, m: torch.Tensor, idx: torch.Tensor, a_all: torch.Tensor, c_all: torch.Tensor, q: torch.Tensor,
    bins: int, pool: bool,
) -> torch.Tensor:
    """Log-likelihood terms (rows, hypotheses, bins) ≤ 0 against hypotheses that clip more pixels than the patch shows
    (rows: those of ``a_all``, B, or 1 when ``pool`` makes every row the same).

    Under a hypothesis of noise variance v(m) = a·m + c + q, a pixel of a block at mean m [DN] deviates from m by
    N(0, ¾·v) and is clipped with probability Φ((0.5 − m)/√(¾v)) + Φ((m − 254.5)/√(¾v)). Per intensity bin k
    that predicts a clipped fraction p_k(H) of the bin's pixels, against the observed o_k. The scene may clip more
    (highlights, shadows) but the noise cannot clip less than it predicts, so only p_k > o_k counts:
    Σ_k −½·((p_k − o_k)/s_k)², s_k = 0.1·p_k + √(p_k/N_k) + 10⁻³ (a 10 % model error, the binomial spread over
    the bin's N_k pixels). The caller adds the bins that carry NLF evidence (those at least ``bound_margin`` σ from
    the bounds, where the model holds): without it a very noisy hypothesis, whose few kept blocks are quiet (most
    blocks would have a clipped pixel), could fit the kept details as well as the true one.

    :func:`physics_noise_posterior` evaluates the same terms only at the bins that carry evidence
    (:func:`_clip_bin_stats`, :func:`_clip_cost`)."""
    n_k, m_k, o_k = _clip_bin_stats(x, m, idx, bins, pool, a_all.shape[0])
    return _clip_cost(n_k.unsqueeze(1), m_k.unsqueeze(1), o_k.unsqueeze(1), a_all.unsqueeze(-1), c_all.unsqueeze(-1),
                      q.view(-1, 1, 1))


def _clip_bin_stats(
    x: torch.Tensor, m: torch.Tensor, idx: torch.Tensor, bins: int, pool: bool, rows: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per intensity bin (``rows``, bins) float64: the number of blocks N_k, their mean intensity m_k [DN] and the
    share o_k of their pixels that are clipped (within ½ DN of 0 or 255 DN) (:func:`_clipping_penalty`)."""
    b, f64, dev = x.shape[0], torch.float64, x.device
    h, w = m.shape[-2] * 2, m.shape[-1] * 2
    lo, hi = _clip_thresholds()
    xs = x.detach()[..., :h, :w].float()
    clipped = F.avg_pool2d(((xs <= lo) | (xs >= hi)).float(), 2).flatten().to(f64)  # share of each block's pixels

    def per_bin(values: torch.Tensor) -> torch.Tensor:
        out = torch.zeros(b * bins, dtype=f64, device=dev).index_add_(0, idx, values).view(b, bins)
        return out.sum(0, keepdim=True).expand(b, bins) if pool else out

    n_k = per_bin(torch.ones_like(clipped))[:rows]
    m_k = per_bin(m.flatten().to(f64))[:rows] / n_k.clamp_min(1.0)
    o_k = per_bin(clipped)[:rows] / n_k.clamp_min(1.0)
    return n_k, m_k, o_k


@functools.lru_cache(maxsize=1)
def _clip_thresholds() -> tuple[float, float]:
    """(t₀, t₂₅₅): the float32 values with x ≤ t₀ ⟺ 255·x ≤ 0.5 DN and x ≥ t₂₅₅ ⟺ 255·x ≥ 254.5 DN, exactly, for every
    float32 x (255·x is exact in float64), so that a pixel within ½ DN of a bound is found without a float64 copy."""
    one, f32 = torch.tensor(1.0), torch.float32

    def last(bound: float, below: bool) -> float:
        t = torch.tensor(bound / 255.0, dtype=f32)
        inside = (lambda v: float(v.double()) * 255.0 <= bound) if below else (lambda v: float(v.double()) * 255.0 >= bound)
        toward, away = (-one, one) if below else (one, -one)
        while not inside(t):
            t = torch.nextafter(t, toward.to(f32))
        while inside(torch.nextafter(t, away.to(f32))):
            t = torch.nextafter(t, away.to(f32))
        return float(t)

    return last(0.5, True), last(254.5, False)


def _clip_cost(n_k: torch.Tensor, m_k: torch.Tensor, o_k: torch.Tensor, a: torch.Tensor, c: torch.Tensor,
               q: torch.Tensor) -> torch.Tensor:
    """−½·((p_k − o_k)⁺/s_k)² of :func:`_clipping_penalty`, broadcast over its arguments (bin statistics of
    :func:`_clip_bin_stats`; a hypothesis's slope a [DN²/DN], variance c [DN²] and quantisation variance q [DN²])."""
    sd = (0.75 * (a * m_k + c + q)).clamp_min(1e-9).sqrt()
    p_k = 0.5 * (torch.erfc((m_k - 0.5) / (sd * math.sqrt(2.0))) + torch.erfc((254.5 - m_k) / (sd * math.sqrt(2.0))))
    spread = 0.1 * p_k + (p_k / (4.0 * n_k).clamp_min(1.0)).sqrt() + 1e-3
    z = torch.where(n_k > 0, (p_k - o_k).clamp_min(0) / spread, torch.zeros_like(p_k))
    return -0.5 * z.square()


def _dilate3(mask: torch.Tensor) -> torch.Tensor:
    """Whether any element of each 3×3 neighbourhood of a (…, h, w) bool mask is set (outside the mask: unset) —
    the values of a 3×3 max pool with padding 1, by shifted ors (10× faster on the CPU than ``max_pool2d``)."""
    rows = mask.clone()
    rows[..., 1:, :] |= mask[..., :-1, :]
    rows[..., :-1, :] |= mask[..., 1:, :]
    out = rows.clone()
    out[..., :, 1:] |= rows[..., :, :-1]
    out[..., :, :-1] |= rows[..., :, 1:]
    return out


def _inliers(
    m: torch.Tensor, d2: torch.Tensor, usable: torch.Tensor, g2: torch.Tensor, v_ref: torch.Tensor, bound_margin: float,
    max_margin_dn: float = math.inf, lo_hi: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """Float mask (3, B, 1, h, w) of the details used: usable blocks more than ``bound_margin`` reference σ from
    both bounds (a number, or one per patch as a (B,) tensor; nearer, few blocks are left and the clipping model of
    :func:`_kept_variance_factor` carries the evidence alone), flat at the next coarser scale
    (χ²₂ test at 99 % on the central differences of the block means, whose noise variance is v/2, dilated by one
    block), and within 3 reference σ. The margin is at most ``max_margin_dn`` (for a very noisy patch 2 σ from
    both bounds would leave no intensity at all). ``lo_hi``: each block's smallest and largest pixel [DN], tested
    against the bounds instead of the block mean (a static pair's blocks need not be flat)."""
    margin = torch.as_tensor(bound_margin, dtype=v_ref.dtype, device=v_ref.device)
    margin = margin.view(-1, 1, 1, 1) if margin.ndim else margin
    dist = torch.minimum(v_ref.sqrt() * margin, torch.full_like(v_ref, max_margin_dn))  # ≤ max_margin_dn [DN]
    flat = ~_dilate3(g2 > _TEXTURE_CHI2 * v_ref / 2.0)
    lo, hi = (m, m) if lo_hi is None else lo_hi
    keep = usable & flat & (lo - dist > 0) & (hi + dist < 255.0)
    return (keep & (d2 < _INLIER_Z**2 * v_ref)).float()


def _median_variance(m: torch.Tensor, diag2: torch.Tensor, usable: torch.Tensor, bins: int) -> torch.Tensor:
    """A reference noise variance that does not depend on the metadata, at every block: per intensity bin (``bins``
    equal intervals of [0, 255] DN), the median of the usable blocks' squared diagonal detail / 0.4549 (the median
    of χ²₁; the diagonal detail does not see linear gradients); +inf in a bin without usable blocks."""
    b = m.shape[0]
    k = (m / 255.0 * bins).floor().clamp(0, bins - 1).long().flatten(1)  # (B, n)
    # one sort per patch by (bin, d²): the bits of a float32 ≥ 0 order as the values do, so bin·2³² + bits is an
    # exact key; unusable blocks get bin ``bins`` and sort last. Bin j's median (the lower one, as torch.median's) is
    # then at its start + (N_j − 1) // 2.
    bits = diag2.detach().float().clamp_min(0).flatten(1).view(torch.int32).long()
    j = torch.where(usable.flatten(1), k, torch.full_like(k, bins))
    key = sorted_values(j * (1 << 32) + bits)
    n_j = torch.zeros(b, bins + 1, dtype=torch.long, device=m.device).scatter_add_(1, j, torch.ones_like(j))[:, :bins]
    start = n_j.cumsum(1) - n_j
    pick = key.gather(1, (start + (n_j - 1).clamp_min(0) // 2).clamp_max(key.shape[1] - 1))
    med = (pick & 0xFFFFFFFF).int().view(torch.float32)
    v_bin = torch.where(n_j > 0, med / 0.4549, torch.full_like(med, float("inf")))  # (B, bins); ∞ where a bin has no block
    return v_bin.gather(1, k).view_as(m).clamp_min(1e-6)


def _noise_model(rows: torch.Tensor, constants: SensorConstants | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(slope a [DN²/DN], signal-independent variance c [DN²]) of the raw metadata rows (N, 11) of a camera with the
    fixed sensor constants ``constants`` (None: the defaults), float64."""
    meta = metadata_from_matrix(rows, constants)
    dn = meta.dn_per_electron
    dc = dark_current_shot_sigma_e(meta) * dn
    rn = readout_sigma_e(meta) * dn
    return 255.0 * meta.gain_factor / meta.full_well_e, torch.stack([dc.square(), rn.square()], dim=-1)


def _quantisation_variance(image: torch.Tensor) -> torch.Tensor:
    """1/12 DN² for patches whose values are whole DN (8-bit data), else 0, (B,) float64: every |255·x − round(255·x)|
    below 1e-3, with 255·x exact (float64).

    Read in float32 first, where 255·x is within 8e-6 DN of exact (half an ulp of 255); only a patch whose largest
    distance comes within 1e-5 of the tolerance is read again in float64, so the verdict is the exact one at a fifth
    of the memory traffic."""
    flat = image.detach().flatten(1)
    if torch.compiler.is_exporting() or torch.onnx.is_in_onnx_export():  # a graph: no data-dependent branch
        dn = flat.double() * 255.0
        return ((dn - dn.round()).abs().amax(1) < 1e-3).double() / 12.0
    if flat.dtype != torch.float32:
        flat = flat.double()
    dn = flat * 255.0
    dist = dn.sub_(dn.round()).abs_().amax(1).double()
    close = (dist - 1e-3).abs() < 1e-5
    if bool(close.any()):
        exact = image.detach().flatten(1)[close].double() * 255.0
        dist[close] = (exact - exact.round()).abs().amax(1)
    return (dist < 1e-3).double() / 12.0


def _hypotheses(
    meta: CameraMetadata, grid: int, mismatch_probability: float, beyond_probability: float, dev: torch.device,
) -> tuple[torch.Tensor, ...]:
    """The hypotheses of :func:`physics_noise_posterior` for each row of ``meta`` (M rows: one camera state gets one
    row, shared by its patches), float64: M itself, each field of :data:`MISMATCH_FIELDS` on its grid, and extra white
    noise beyond the ranges (σ_x on a log grid 0.5…128 DN, counted as readout noise).

    Returns (a₀ (M,), var₀ (M, 2), a (M, 1 + 4·grid), var (…, 2), c (…), log prior (…)): the PN slope 255·g/FW
    [DN²/DN], the DCSN and RN variances [DN²] and their sum c of M and of every hypothesis, and the log prior. The noise
    model of M and of every single-field candidate is evaluated in one call, with M's fixed sensor constants
    (``meta.constants``: a hypothesis changes one field, not the sensor)."""
    f64, nm = torch.float64, meta.batch_size
    rows = torch.stack([getattr(meta, n).to(device=dev, dtype=f64).expand(nm) for n in FULL_FIELDS], dim=1)
    cands = [rows]
    for fname in MISMATCH_FIELDS:
        low, high = METADATA_RANGES[fname]
        cand = rows.repeat_interleave(grid, 0)
        cand[:, FULL_FIELDS.index(fname)] = _grid_values(fname, float(low), float(high), grid, "factor").to(dev).repeat(nm)
        cands.append(cand)
    a_c, var_c = _noise_model(torch.cat(cands), meta.constants)
    a0, var0 = a_c[:nm], var_c[:nm]  # (M,), (M, 2) = σ_DCSN², σ_RN² [DN²]
    slopes, variances, logp = [a0.unsqueeze(1)], [var0.unsqueeze(1)], [torch.full((nm, 1), math.log1p(-mismatch_probability), dtype=f64, device=dev)]
    p_field = (mismatch_probability - beyond_probability) / len(MISMATCH_FIELDS)
    for j in range(len(MISMATCH_FIELDS)):
        lo_row = nm + j * nm * grid
        slopes.append(a_c[lo_row:lo_row + nm * grid].view(nm, grid))
        variances.append(var_c[lo_row:lo_row + nm * grid].view(nm, grid, 2))
        logp.append(torch.full((nm, grid), math.log(max(p_field, 1e-300) / grid), dtype=f64, device=dev))
    extra = torch.logspace(math.log10(0.5), math.log10(128.0), grid, dtype=f64, device=dev).square()  # σ_x² [DN²]
    slopes.append(a0.unsqueeze(1).expand(nm, grid))
    variances.append(torch.stack([var0[:, :1].expand(nm, grid), var0[:, 1:] + extra], dim=-1))
    logp.append(torch.full((nm, grid), math.log(max(beyond_probability, 1e-300) / grid), dtype=f64, device=dev))
    a_all, var_all, prior = torch.cat(slopes, 1), torch.cat(variances, 1), torch.cat(logp, 1)
    return a0, var0, a_all, var_all, var_all.sum(-1), prior


@functools.lru_cache(maxsize=16)
def _camera_hypotheses(
    fields: tuple[float, ...], grid: int, mismatch_probability: float, beyond_probability: float, device: str,
    constants: SensorConstants | None = None,
) -> tuple[torch.Tensor, ...]:
    """:func:`_hypotheses` of one camera state given by its :data:`FULL_FIELDS` values (physical units) and its fixed
    sensor constants (None: the defaults; frozen, so part of the key), cached: a monitor asks for the same state frame
    after frame. The tensors are shared between calls and never written to."""
    meta = CameraMetadata(**{n: torch.tensor([v], dtype=torch.float64) for n, v in zip(FULL_FIELDS, fields)},
                          constants=SensorConstants() if constants is None else constants)
    return _hypotheses(meta, grid, mismatch_probability, beyond_probability, torch.device(device))


def _neighbour_check(x: torch.Tensor, v_ref: torch.Tensor, ok: torch.Tensor, pool: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """|ρ| / max(DETAIL_CORR_LIMIT, 3/√pairs) (≥ 1: textured), (over the frame when ``pool``, of each patch), both
    (B,) float64: ρ is the correlation of the standardised diagonal details d/√v_ref of horizontally and vertically
    adjacent inlier blocks (mask ``ok``). White noise leaves them uncorrelated, a scene's fine texture does not (its
    covariance is a lower bound on what it adds to each detail); 0 with fewer than _MIN_FIT_BLOCKS pairs."""
    b, f64, dev = x.shape[0], torch.float64, x.device
    p00, p01, p10, p11 = _block_pixels(x * 255.0)
    z = (p00 - p01 - p10 + p11) / 2.0 / v_ref.sqrt()
    cov, var, pairs = (torch.zeros(b, dtype=f64, device=dev) for _ in range(3))
    for dim in (-1, -2):
        n_d = z.shape[dim] - 1
        za, zb = z.narrow(dim, 0, n_d), z.narrow(dim, 1, n_d)
        both = ok.narrow(dim, 0, n_d) * ok.narrow(dim, 1, n_d)
        cov = cov + (za * zb * both).flatten(1).sum(1).to(f64)
        var = var + (both * (za.square() + zb.square()) / 2.0).flatten(1).sum(1).to(f64)
        pairs = pairs + both.flatten(1).sum(1).to(f64)

    def check(cov: torch.Tensor, var: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
        corr = torch.where(pairs >= _MIN_FIT_BLOCKS, cov / var.clamp_min(1e-12), torch.zeros_like(cov))
        return corr.abs() / torch.maximum(torch.full_like(corr, DETAIL_CORR_LIMIT), 3.0 / pairs.clamp_min(1.0).sqrt())

    own = check(cov, var, pairs)
    return (check(*(t.sum().expand(b) for t in (cov, var, pairs))) if pool else own), own


def _bin_residuals(
    count: torch.Tensor, sq: torch.Tensor, sm: torch.Tensor, a: torch.Tensor, c: torch.Tensor, q: torch.Tensor,
    tau2: torch.Tensor, eta_bin: float, c_counts: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The NLF residuals of the intensity bins that carry evidence (≥ _MIN_BIN_DETAILS details) of ``rows`` rows.

    Args: per bin (rows, bins) float64 the detail count, the sum of the squared diagonal details [DN²] and of the
    block means [DN]; the hypotheses' a [DN/DN] and c [DN²] (rows, hypotheses), the quantisation variance q [DN²] and
    the scene allowance τ² [DN²] per row; a pair's per-bin clipping-limit counts (rows, bins, _PAIR_C_BINS) or None.

    Returns (row, bin) index of each bin e, its log-variance residual r against every hypothesis's kept variance,
    D⁻¹ = 1/(2/n + η_bin² + the scene's one-sided log-variance ln(1 + τ²/v)² where r > 0), and the bin's a and c rows.
    """
    pe, ke = (count >= _MIN_BIN_DETAILS).nonzero(as_tuple=True)
    n_e = count[pe, ke].unsqueeze(1)
    s_hat = sq[pe, ke].unsqueeze(1) / _TRUNCATED_CHI2 / n_e
    mk = (sm[pe, ke].unsqueeze(1) / n_e)
    a_e, c_e = a.index_select(0, pe), c.index_select(0, pe)
    v = (a_e * mk + c_e + q[pe].unsqueeze(1)).clamp_min(1e-9)
    # the details of the blocks kept (no pixel clipped): one frame infers the loss from the block means, a pair
    # knows each pixel's limit
    kept = _kept_variance_factor(mk, v) if c_counts is None else pair_kept_variance_factor(c_counts[pe, ke], v)
    v = v * kept
    r = s_hat.clamp_min(1e-9).log() - v.log()
    # the scene's own fine-scale content adds up to about τ² to a bin (never removes any): a reading above the
    # hypothesis carries the extra log-variance ln(1 + τ²/v)², one below it none
    scene = torch.log1p(kept * tau2[pe].unsqueeze(1) / v).square() * (r > 0)
    return pe, ke, r, 1.0 / (2.0 / n_e + eta_bin**2 + scene), a_e, c_e


def _fit_z(lin: torch.Tensor, inv_sum: torch.Tensor, eta2: torch.Tensor) -> torch.Tensor:
    """Goodness of fit (rows,): the image's common log-variance offset from each hypothesis (its bins' weighted mean
    residual Σr/D / Σ1/D) in standard errors (sampling and the model error η², (rows, 1)), the largest over the
    hypotheses: how far the image reads below every camera state the metadata's ranges allow (negative: quieter)."""
    inv_c = inv_sum.clamp_min(1e-300)
    return ((lin / inv_c) / (1.0 / inv_c + eta2).sqrt()).amax(1)


def physics_noise_posterior(
    image: torch.Tensor,
    meta: CameraMetadata,
    eta: float = 0.12,
    eta_bin: float = 0.05,
    mismatch_probability: float = 0.5,
    beyond_probability: float = 0.125,
    grid: int = 96,
    bins: int = 16,
    bound_margin: float = 2.0,
    fallback_margin: float = 1.0,
    pool: bool = False,
    scene_allowance_dn: float = SCENE_ALLOWANCE_DN,
    scene_allowance_min_dn: float = SCENE_ALLOWANCE_MIN_DN,
    reference: torch.Tensor | None = None,
    other_evidence: torch.Tensor | None = None,
    return_evidence: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Physics-first noise sources of each patch, (B, 29) float32 in the order of :data:`PHYSICS_NOISE_COLUMNS`.

    Columns: σ of PN, DCSN, RN and the total after clipping [DN]; ξ [DN] (0 where the metadata hold); the posterior
    standard deviation of σ_Total [DN]; P(metadata right | patch); the number of diagonal details used; the texture
    check; 1 where the answer follows the image (P(match) < ½), else 0; σ_Total before clipping [DN] of the answer; the
    neighbour check |ρ| / max(DETAIL_CORR_LIMIT, 3/√pairs) (≥ 1: textured); the scene allowance τ [DN] the evidence was
    read with (``scene_allowance_dn`` per patch; pooled, the frame's own, ``scene_allowance_min_dn`` … ``scene_allowance_dn``);
    the uncertainty of PN, DCSN and RN [DN]: the posterior RMS deviation of every hypothesis's σ from the answer's
    (before clipping, scaled to the clipped answer), and in quadrature σ/√(2n), by which the realised σ of a patch's
    n pixels differs from the expected one (∞ without evidence) — large where the image shows an excess that several
    sources explain alike and the prior alone splits it; σ of row and column noise where detected [DN] (else 0; where
    they are, σ_Total, ξ and its uncertainty include them, module docstring); the number of the patch's own
    details used and its own texture and neighbour checks (pooled, read with the frame's noise model; per patch,
    the three columns above again); the cause: P(kind | a visible mismatch) for each of :data:`MISMATCH_CAUSES` — the
    gain, the temperature or the white noise wrong, or noise beyond them — summing to 1 (NaN where the patch is not
    readable: too few flat details, or textured); ``quiet_z``: the goodness of fit, how many standard errors (the
    details' sampling and the model error η) the image's noise reads below that of the best-fitting camera state any
    hypothesis allows (the largest over the hypotheses of their weighted mean log-variance residual; negative: the
    image is quieter than every one; 0 without evidence; pooled, the frame's, except for a patch below
    −:data:`QUIET_Z_LIMIT` alone, which keeps its own, and at most the median patch's where most patches are; below
    −:data:`QUIET_Z_LIMIT` no hypothesis explains the image: the closed form is kept, the uncertainties are ∞ and the
    cause NaN, and P(match) only says whether the camera states that fit least badly are visible mismatches — no
    verdict); and the least σ_Total [DN] before clipping of any
    camera state the hypotheses span, at the patch's mean intensity (what :meth:`PhysicsNoiseEstimator.predict`
    compares with :data:`QUANTISATION_SIGMA_DN`); ``codec``: 1 where an 8-bit patch (pooled: frame) would follow the
    image against the metadata and shows JPEG's quantised block grid
    (:func:`~camhealth.estimators.jpeg_quantisation.jpeg_grid`; pooled, on the frame:
    :func:`~camhealth.estimators.jpeg_quantisation.coded_frame`): the noise is the codec's as much as the camera's, so
    the closed form is kept with no verdict — uncertainties ∞, cause NaN — as below −:data:`QUIET_Z_LIMIT`; 0
    elsewhere (the grid is tested only there); ``excess_dn``: where the closed form is kept on a patch that is read
    (evidence, not textured, a verdict) although one of its intensity bins (pooled: the frame's) reads more than the
    metadata's kept variance by over τ² and three of the bin's sampling standard errors (ŝ_k − f_k·v_k(M) >
    τ² + 3·ŝ_k·√(2/N_k)), the larger of √ŝ_k − σ_Total(M) (the measured variance's σ over the closed form) and
    √(σ_Total(M)² + ŝ_k − f_k·v_k(M)) − σ_Total(M) (the excess carried to the patch's level), the largest over such
    bins [DN], and the uncertainty of σ_Total and of each source is raised to at least it (the answer, ξ and P(match)
    stay the posterior's); 0 elsewhere. The scene allowance's log-variance ln(1 + τ²/v)² grows without
    bound as v → 0, so on a quiet camera such an excess (ICX285 at 0 dB, 0.57 DN, with 7 DN of extra white noise at
    15 DN) can keep the closed form: its error is then within the stated uncertainty, not hidden by it.

    Args:
        image: B×1×H×W noisy patches in [0, 1] (H, W ≥ 8).
        meta: the camera's metadata, batch 1 or B, physical units.
        eta: model error of the NLF common to all bins (relative, of the variance).
        eta_bin: model error of one bin (relative).
        mismatch_probability: prior probability that one field of the metadata is wrong.
        beyond_probability: prior probability of noise no metadata in range explain (part of the mismatch prior). The
            default gives it the share of each single field (0.125 = 0.5 / 4): a noise source outside the metadata
            (interference, a failing amplifier, a white-noise density beyond its range) is as likely as any one field
            being wrong.
        grid: candidate values per field.
        bins: intensity bins of [0, 255] DN.
        bound_margin: blocks nearer than this many σ (at most 100 DN) to 0 or 255 DN are not used; nearer ones are
            kept and their details' loss to the clipping is modelled (:func:`_kept_variance_factor`).
        fallback_margin: the margin [σ] of a patch (pooled: a frame) that keeps fewer than
            :data:`MIN_FOLLOW_DETAILS` details at ``bound_margin`` — a dark or bright patch under strong noise, whose
            blocks all lie within 2 σ of a bound — so that its nearer blocks, with their clipping modelled, carry
            the evidence instead of none (a patch at 40 DN with 35 DN of noise: assessable and within 8 %, where
            ``bound_margin`` alone leaves it without a flat area). Used only where it is smaller than ``bound_margin``.
        scene_allowance_dn: τ [DN], the fine-scale content a scene may add of its own (its texture, the noise and
            compression of a recording it came from): a bin that reads more than a hypothesis predicts carries the
            extra log-variance ln(1 + τ²/v)² (one that reads less, none: a scene cannot remove noise). 0 turns it off.
            Per patch τ is this; pooled it is the most the frame's own reading may give.
        scene_allowance_min_dn: τ_min [DN], pooled: the allowance of a frame whose details show no texture (white
            content a recording brings, which the detail ratio cannot see); the frame's τ² is
            τ_min² + max(E[d_HV²] − E[d_D²], 0)/(SCENE_DETAIL_RATIO − 1) on its inliers, at most
            ``scene_allowance_dn``². Equal to ``scene_allowance_dn``: τ fixed pooled as well.
        pool: the patches show one camera state (``meta`` of batch 1, e.g. the patches of one frame): add up their
            NLF evidence and texture check, so that every patch gets the posterior of the whole frame (noise is a
            property of the camera, not of the scene); σ after clipping stays per patch. Patches far quieter alone
            than every camera state (``quiet_z`` below −:data:`QUIET_Z_LIMIT`: no sensor noise) are left out of the
            sums where they are at most half of the patches with evidence. Patches far noisier than the frame's
            median patch (their σ more than :data:`LOUD_RATIO` times its, and :data:`QUIET_Z_LIMIT` standard errors
            above it: amp glow, a hot or a pasted region) are left out of the sums where they are at most half of
            the others, and read alone (their rows are those of ``pool=False``); so are, in a frame of two noise
            levels (a failing tap), the patches that read like noise above the lowest gap between the noise-like
            patches' offsets wider than :data:`LOUD_RATIO`² and :data:`QUIET_Z_LIMIT` standard errors.
        reference: the same patches from another exposure of a static scene in the same camera state (B×1×H×W in
            [0, 1]), or None. Given, the evidence — the details, their block means, the row and column noise and the
            texture and neighbour checks — is read from :func:`~camhealth.estimators.static_pair.static_pair_image`,
            whose details carry the pair's noise and nothing of the scene; the clipping, the 8-bit rounding and σ
            after clipping stay those of ``image`` (and so does the 8-bit rounding's 1/12 DN², which the difference
            of two rounded frames keeps in its details). The scene must have stood still: a change between the
            exposures enters the difference, and the texture checks see only part of it;
            :meth:`PhysicsNoiseEstimator.predict` tests each patch first (:func:`~camhealth.estimators.static_pair.pair_shift`,
            :func:`~camhealth.estimators.static_pair.scene_leak`).
        other_evidence: the summed :func:`noise_evidence` of other frames of this camera that differ from ``meta`` only
            in the exposure time (5, 1 + 4·grid), or None. Their bins join this frame's (η applied once to all of
            them), so that an excess that grows with the exposure time (dark current: a hotter sensor than told) is
            told apart from one that does not (readout noise); a mismatch hypothesis that moves σ_Total visibly in any
            of them is visible (row 4), so one that the other frames show is followed here too, however little it
            moves this frame's σ_Total (a hotter sensor at a short exposure). ``meta`` must have batch 1; the answer
            is still about ``image``, and where ``image`` itself is not readable it keeps the closed form.
        return_evidence: with ``pool``, return (the table, this frame's own evidence of :func:`noise_evidence` from the
            same reading) instead of the table.
    """
    if not isinstance(image, torch.Tensor) or image.ndim != 4 or image.shape[1] != 1:
        raise ValueError(f"image must be a B×1×H×W tensor, got {tuple(image.shape) if isinstance(image, torch.Tensor) else type(image).__name__}")
    if not image.is_floating_point():
        raise TypeError(f"image must be a floating-point tensor in [0, 1], got {image.dtype}")
    if image.shape[-2] < 8 or image.shape[-1] < 8:
        raise ValueError(f"physics_noise_posterior needs patches of at least 8×8 px, got {tuple(image.shape[-2:])}")
    if not bool(torch.isfinite(image).all()):
        raise ValueError("image contains NaN or inf; physics_noise_posterior needs finite intensities in [0, 1]")
    if image.numel() > 0:
        lo, hi = torch.aminmax(image.detach())
        if lo < 0 or hi > 1:
            raise ValueError(f"image must lie in [0, 1] (DN/255), got values in [{lo.item():g}, {hi.item():g}]")
    if not isinstance(meta, CameraMetadata):
        raise TypeError(f"meta must be a CameraMetadata (CameraMetadata.preset, .from_dict, .cat), got "
                        f"{type(meta).__name__}; PhysicsNoiseEstimator.predict also takes preset names, files and dicts")
    for name, value in (("pool", pool), ("return_evidence", return_evidence)):
        if not isinstance(value, (bool, np.bool_)):
            raise TypeError(f"{name} = {value!r} must be True or False, got {type(value).__name__}")
    for name, value in (("grid", grid), ("bins", bins)):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise TypeError(f"{name} = {value!r} must be an integer, got {type(value).__name__}")
    for name, value in (("eta", eta), ("eta_bin", eta_bin), ("scene_allowance_dn", scene_allowance_dn),
                        ("scene_allowance_min_dn", scene_allowance_min_dn), ("mismatch_probability", mismatch_probability),
                        ("beyond_probability", beyond_probability), ("bound_margin", bound_margin),
                        ("fallback_margin", fallback_margin)):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise TypeError(f"{name} = {value!r} must be a real number, got {type(value).__name__}")
    for name, value, low, high in (("eta", eta, 0.0, 10.0), ("eta_bin", eta_bin, 0.0, 10.0),
                                   ("scene_allowance_dn", scene_allowance_dn, 0.0, 64.0),
                                   ("scene_allowance_min_dn", scene_allowance_min_dn, 0.0, 64.0),
                                   ("mismatch_probability", mismatch_probability, 0.0, 1.0),
                                   ("beyond_probability", beyond_probability, 0.0, 1.0)):
        if not low <= value <= high or not math.isfinite(value):
            raise ValueError(f"{name} = {value!r} must be in [{low:g}, {high:g}]")
    if beyond_probability > mismatch_probability or mismatch_probability >= 1.0:
        raise ValueError(f"beyond_probability = {beyond_probability} must be ≤ mismatch_probability = {mismatch_probability} < 1")
    for name, value in (("bound_margin", bound_margin), ("fallback_margin", fallback_margin)):
        if not 0.0 <= value <= 64.0 or not math.isfinite(value):
            raise ValueError(f"{name} = {value!r} must be in [0, 64] (σ from the bounds)")
    if grid < 2 or bins < 1:
        raise ValueError(f"grid = {grid} must be ≥ 2 and bins = {bins} ≥ 1")
    if reference is not None:
        if not isinstance(reference, torch.Tensor) or reference.shape != image.shape:
            raise ValueError(f"reference must have the image's shape {tuple(image.shape)}, got "
                             f"{tuple(reference.shape) if isinstance(reference, torch.Tensor) else type(reference).__name__}")
        if not reference.is_floating_point():
            raise TypeError(f"reference must be a floating-point tensor in [0, 1], got {reference.dtype}")
        if not bool(torch.isfinite(reference).all()):
            raise ValueError("reference contains NaN or inf; physics_noise_posterior needs finite intensities in [0, 1]")
        if reference.numel() > 0:
            lo, hi = torch.aminmax(reference.detach())
            if lo < 0 or hi > 1:
                raise ValueError(f"reference must lie in [0, 1] (DN/255), got values in [{lo.item():g}, {hi.item():g}]")
    b, dev, f64 = image.shape[0], image.device, torch.float64
    if meta.batch_size not in (1, b):
        raise ValueError(f"metadata batch {meta.batch_size} does not match the {b} patches")
    if pool and meta.batch_size != 1:
        raise ValueError(f"pool=True adds up the evidence of patches of one camera state: metadata must have batch 1, got {meta.batch_size}")
    if other_evidence is not None and meta.batch_size != 1:
        raise ValueError(f"other_evidence belongs to one camera: metadata must have batch 1, got {meta.batch_size}")
    if return_evidence and not pool:
        raise ValueError("a frame's evidence (return_evidence, noise_evidence) is read pooled: pool must be True")
    with torch.autocast(device_type=dev.type, enabled=False):
        x = image.detach().float()
        if meta.batch_size == 1:  # one camera state: its hypotheses are reused from call to call (a monitor's frames)
            key = tuple(float(getattr(meta, n).reshape(-1)[0]) for n in FULL_FIELDS)
            a0, var0, a_all, var_all, c_all, prior = _camera_hypotheses(key, grid, mismatch_probability, beyond_probability, str(dev),
                                                                        meta.constants)
        else:
            a0, var0, a_all, var_all, c_all, prior = _hypotheses(meta, grid, mismatch_probability, beyond_probability, dev)
        other = None
        if other_evidence is not None:
            n_hyp = a_all.shape[1]
            if not isinstance(other_evidence, torch.Tensor) or other_evidence.shape != (5, n_hyp):
                raise ValueError(f"other_evidence must be the (5, {n_hyp}) evidence of noise_evidence with grid = {grid}, got "
                                 f"{tuple(other_evidence.shape) if isinstance(other_evidence, torch.Tensor) else type(other_evidence).__name__}")
            if not bool(torch.isfinite(other_evidence).all()):
                raise ValueError("other_evidence contains NaN or inf")
            ev = other_evidence.detach().double()
            # Σr²/D, Σ1/D and the frame counts are sums of non-negative terms, and (Σr/D)² ≤ Σr²/D · Σ1/D
            if bool((ev[[0, 2, 4]] < 0).any()) or bool((ev[1].square() > ev[0] * ev[2] * (1 + 1e-9) + 1e-300).any()):
                raise ValueError("other_evidence is no sum of noise_evidence: its Σr²/D, Σ1/D and frame counts (rows 0, 2, 4) "
                                 "must be ≥ 0 and (Σr/D)² ≤ Σr²/D · Σ1/D per hypothesis; pass noise_evidence's output "
                                 "(or predict's \"evidence\"), summed over frames")
            other = other_evidence.to(device=dev, dtype=f64)
        if b == 0:  # an empty batch: a table of 0 rows (and, pooled, a frame without evidence)
            empty = torch.zeros(0, len(PHYSICS_NOISE_COLUMNS), device=dev)
            return (empty, torch.zeros(5, a_all.shape[1], dtype=f64, device=dev)) if return_evidence else empty
        a0, var0 = a0.expand(b), var0.expand(b, 2)
        a_all, var_all, c_all, prior = a_all.expand(b, -1), var_all.expand(b, -1, 2), c_all.expand(b, -1), prior.expand(b, -1)
        q = _quantisation_variance(x)
        # the image the evidence is read from: the patch itself, or a static pair's scene-free fold of it
        # (unclamped: the scaled difference swings √2 times as far as a frame's noise, and its tails carry the noise)
        pair = None if reference is None else pair_fold(x, reference.detach().to(x.device))
        x_ev = x if pair is None else pair.fold

        m, d2, usable, g2 = block_details(x_ev, "physics_noise_posterior")
        # the horizontal and vertical details as they are (a scene's fine content: the scene allowance below reads its
        # excess) and with the local plane taken out (a smooth ramp is no texture: the texture check and the inlier
        # test read these); a pair's fold holds no scene and keeps its own
        d2_raw = d2
        if pair is None:
            d2 = plane_free_details(x_ev, d2, usable)
        m_g, lo_hi = m, None  # the block means whose gradients test flatness; each block's pixel range [DN]
        c_index = None  # a pair's per-pixel clipping limits, as intervals of the log grid (B, h·w, 4)
        if pair is not None:  # a pair's details hold no scene: flatness of the difference, the range of the pixels
            m_g, g2, lo_hi = pair.m_d, pair.g2, (pair.lo, pair.hi)
            # the intensity a detail is binned at and its NLF read at: the average's block mean, the scene's level with
            # noise v/8 and independent of the difference (the fold's own block mean adds the difference's, and bins
            # chosen by it select details by their own values: at 60 DN the outer bins read half the variance)
            m = pair.m_avg
            # usable: no pixel clipped in either frame (the fold's own range says nothing: it is not clamped)
            usable = pair.limits.amin(-1) > 0
            usable[..., 0, :] = False  # the border blocks, as block_details leaves them out
            usable[..., -1, :] = False
            usable[..., :, 0] = False
            usable[..., :, -1] = False
            c_index = _pair_c_index(pair.limits).view(b, -1, 4)
        band = row_column_noise(x_ev, pool)  # row and column offsets: out of the details the fits read
        if d2_raw is not d2 and bool(band.detected.any()):
            d2_raw = debanded_details(x_ev, m_g, d2_raw, g2, band.detected)[0]
        d2, g2 = debanded_details(x_ev, m_g, d2, g2, band.detected)
        kbin = (m / 255.0 * bins).floor().clamp(0, bins - 1).long().flatten(1)
        idx = (torch.arange(b, device=dev).view(b, 1) * bins + kbin).flatten()
        m_flat = m.flatten().to(f64)
        # a pair's pixels by (patch, intensity bin, interval of their clipping limit), flattened from (B, h·w, 4)
        c_key = None if c_index is None else (idx.view(b, -1, 1).int() * _PAIR_C_BINS + c_index).flatten()
        # the metadata-free reference, floored at the 8-bit rounding's variance: where most details of a quiet 8-bit
        # patch are exactly 0 (σ well under ½ DN) their median is 0, and a reference of 0 would call every block
        # with a 1 DN step in its block means non-flat (no flat area)
        v_ref = torch.maximum(_median_variance(m, d2[0], usable, 4), q.float().view(b, 1, 1, 1))
        # pooled, every patch has the same evidence and hypotheses (metadata of batch 1): one row is computed for all
        h = 1 if pool else b
        a_h, c_h, prior_h = a_all[:h], c_all[:h], prior[:h]
        q_h = q.mean().view(1) if pool else q
        # (h, bins): the clipping penalty's bins, read from the image's own blocks (a pair's fold has other block means)
        m_x = m if reference is None else sum(_block_pixels(x)) / 4.0
        k_x = kbin if reference is None else (m_x / 255.0 * bins).floor().clamp(0, bins - 1).long().flatten(1)

        def clip_input(rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            """The patches (B,) bool ``rows``, their block means and (patch, bin) index of each block."""
            n = int(rows.sum())
            return x[rows], m_x[rows], (torch.arange(n, device=dev).view(n, 1) * bins + k_x[rows]).flatten()

        clip_n, clip_m, clip_o = _clip_bin_stats(*clip_input(torch.ones(b, dtype=torch.bool, device=dev)), bins, pool, h)
        # pooled: the patches far quieter alone than every camera state, left out of the frame's sums, and their own fit
        quiet_alone = torch.zeros(b, dtype=torch.bool, device=dev)
        loud_alone = torch.zeros(b, dtype=torch.bool, device=dev)  # pooled: patches far noisier than their frame
        own_z, quiet_frame = torch.zeros(b, dtype=f64, device=dev), None
        post = torch.softmax(prior, 1)
        tau2 = torch.full((b,), scene_allowance_dn**2, dtype=f64, device=dev)  # τ² [DN²] per patch
        tau2_min = min(scene_allowance_min_dn, scene_allowance_dn) ** 2
        for step in range(2):
            if step:  # the first pass's posterior NLF
                v_ref = ((post * a_all).sum(1).float().view(b, 1, 1, 1) * m.clamp_min(0)
                         + ((post * c_all).sum(1) + q + tau2).float().view(b, 1, 1, 1)).clamp_min(1e-6)
            inl_all = _inliers(m, d2, usable, g2, v_ref, bound_margin, _MAX_MARGIN_DN, lo_hi)
            # a patch (pooled: a frame) with too few details at the nominal margin — dark or bright under strong
            # noise — reads its blocks nearer the bounds instead, their loss to the clipping modelled
            n_nominal = inl_all[0].flatten(1).sum(1)
            short = (n_nominal.sum().expand(b) if pool else n_nominal) < MIN_FOLLOW_DETAILS
            if fallback_margin < bound_margin and bool(short.any()):
                margin = torch.where(short, fallback_margin, bound_margin).to(v_ref.dtype)
                inl_all = _inliers(m, d2, usable, g2, v_ref, margin, _MAX_MARGIN_DN, lo_hi)
            inl = inl_all[0].flatten().to(f64)

            def per_bin(values: torch.Tensor) -> torch.Tensor:
                return torch.zeros(b * bins, dtype=f64, device=dev).index_add_(0, idx, values).view(b, bins)

            # texture check on the blocks whose three details are all inliers: texture that passed the flatness tests
            # adds to the horizontal and vertical details first; it bounds what it may have added to the diagonal
            # one, so it widens the common model error: η_eff² = η² + max(texture, 0)²
            all3 = inl_all.prod(0)
            hv = ((d2[1] + d2[2]) * all3).flatten(1).sum(1).to(f64) / 2.0
            hv_raw = hv if d2_raw is d2 else ((d2_raw[1] + d2_raw[2]) * all3).flatten(1).sum(1).to(f64) / 2.0
            dd = (d2[0] * all3).flatten(1).sum(1).to(f64)
            n3 = all3.flatten(1).sum(1).to(f64)
            count, sq, sm = per_bin(inl), per_bin(d2[0].flatten().to(f64) * inl), per_bin(m_flat * inl)
            c_counts = None
            if c_key is not None:  # per bin, how many of the used pixels have each clipping limit
                c_counts = torch.bincount(c_key, weights=inl.view(b, -1, 1).expand(-1, -1, 4).flatten(),
                                          minlength=b * bins * _PAIR_C_BINS).view(b, bins, _PAIR_C_BINS)
            own_texture = torch.where(n3 >= _MIN_FIT_BLOCKS, torch.log((hv + 1e-6) / (dd + 1e-6)), torch.zeros_like(hv))
            own_count = count.sum(1)
            if pool and step == 0:
                # a patch far quieter alone than every camera state in the metadata's ranges (an overlay, a letterbox,
                # a rendered or masked area: no sensor noise at all) would pull the whole frame below them, or be
                # given the frame's answer; it is refused alone (quiet_z its own). Where such patches are at most half
                # of those with evidence they are left out of the frame's sums, so the rest of the frame is read as it
                # is; where they are most of it, the frame as a whole is the quiet one (a denoiser, a codec): pooled as
                # it stands, every patch is given the median patch's quiet_z at most
                own_evidence = own_count >= _MIN_FIT_BLOCKS
                pe_o, _, r_o, inv_o, _, _ = _bin_residuals(count, sq, sm, a_all, c_all, q, torch.full_like(tau2, scene_allowance_dn**2),
                                                           eta_bin, c_counts)
                lin_o = torch.zeros(b, a_all.shape[1], dtype=f64, device=dev).index_add_(0, pe_o, r_o * inv_o)
                inv_o = torch.zeros(b, a_all.shape[1], dtype=f64, device=dev).index_add_(0, pe_o, inv_o)
                eta2_own = (eta**2 + own_texture.clamp_min(0).square()).unsqueeze(1)
                own_z = torch.where(own_evidence, _fit_z(lin_o, inv_o, eta2_own), torch.zeros_like(own_texture))
                quiet = own_evidence & (own_z < -QUIET_Z_LIMIT)
                if 2 * int(quiet.sum()) > int(own_evidence.sum()):
                    quiet_frame = own_z[own_evidence].median()
                elif bool(quiet.any()):
                    quiet_alone = quiet
                # a patch far noisier than the rest of its frame (amp glow, a hot or a pasted region) would pull the
                # frame's answer and be given it: its own log-variance offset from the metadata's NLF (the bins'
                # weighted mean residual) lies more than LOUD_RATIO² above the median patch's and QUIET_Z_LIMIT standard
                # errors (its sampling and the model error η) beyond it. Where such patches are at most half of the
                # others they are left out of the frame's sums and read alone
                rest = own_evidence & ~quiet_alone & ~quiet
                if int(rest.sum()) >= 3:
                    off0 = lin_o[:, 0] / inv_o[:, 0].clamp_min(1e-12)
                    excess = off0 - off0[rest].median()
                    loud = rest & (excess > 2.0 * math.log(LOUD_RATIO)) & (
                        excess > QUIET_Z_LIMIT * (1.0 / inv_o[:, 0].clamp_min(1e-12) + eta**2).sqrt())
                    if 2 * int(loud.sum()) <= int(rest.sum()):
                        loud_alone = loud
                    # two noise levels in one frame in comparable shares (a failing tap of a multi-tap sensor, a region
                    # of another readout), where the median patch is itself one of the loud ones: among the patches
                    # whose details read like noise (own texture check under TEXTURE_LIMIT), the lowest gap between
                    # consecutive offsets wider than LOUD_RATIO² and QUIET_Z_LIMIT standard errors of the difference
                    # (their sampling; the model error η is common to one frame) parts them, and the noise-like
                    # patches above it are read alone
                    like_all = rest & (own_texture < TEXTURE_LIMIT)
                    like = like_all.nonzero(as_tuple=True)[0]
                    if like.numel() >= 2:
                        o_l, order = off0[like].sort()
                        v_l = (1.0 / inv_o[like, 0].clamp_min(1e-12))[order]
                        gap = o_l[1:] - o_l[:-1]
                        wide = (gap > 2.0 * math.log(LOUD_RATIO)) & (gap > QUIET_Z_LIMIT * (v_l[1:] + v_l[:-1]).sqrt())
                        if bool(wide.any()):
                            loud_alone = loud_alone | (like_all & (off0 >= o_l[1:][wide][0]))
                if bool((quiet_alone | loud_alone).any()):  # and out of the clipping penalty's bins and the neighbour check
                    clip_n, clip_m, clip_o = _clip_bin_stats(*clip_input(~(quiet_alone | loud_alone)), bins, pool, h)
            if pool:  # one camera state: the frame's evidence for every patch (but the quiet and loud ones above)
                w_in = (~(quiet_alone | loud_alone)).to(f64)
                hv, hv_raw, dd, n3 = ((t * w_in).sum().expand(b) for t in (hv, hv_raw, dd, n3))
                # a patch's bins where the metadata's σ is below the 8-bit quantisation step stay out of the frame's
                # sums: there rounding removes or adds noise by an amount that depends on each level's fraction
                # (−45…+37 % at 0.3 DN), not the 1/12 DN² the model adds, and a few such dark patches would move the
                # whole frame's reading
                v_meta = a0.unsqueeze(1) * (sm / count.clamp_min(1.0)) + var0.sum(-1).unsqueeze(1)
                w_bin = w_in.unsqueeze(1) * ~((q > 0).unsqueeze(1) & (v_meta < QUANTISATION_SIGMA_DN**2))
                count, sq, sm = ((t * w_bin).sum(0, keepdim=True).expand(b, bins) for t in (count, sq, sm))
                c_counts = None if c_counts is None else (c_counts * w_bin.unsqueeze(-1)).sum(0, keepdim=True)
            texture = torch.where(n3 >= _MIN_FIT_BLOCKS, torch.log((hv + 1e-6) / (dd + 1e-6)), torch.zeros_like(hv))
            if pool and tau2_min < scene_allowance_dn**2:
                # the frame's own fine content, read off its inliers: white noise puts as much energy into the
                # horizontal and vertical details as into the diagonal one, a scene at least SCENE_DETAIL_RATIO
                # times as much, so the excess bounds what the scene added to the diagonal detail
                excess = ((hv_raw - dd) / n3.clamp_min(1.0) / _TRUNCATED_CHI2).clamp_min(0.0)
                tau2 = torch.where(n3 >= _MIN_FIT_BLOCKS, (tau2_min + excess / (SCENE_DETAIL_RATIO - 1.0)).clamp_max(scene_allowance_dn**2),
                                   torch.full_like(excess, scene_allowance_dn**2))
            eta2 = (eta**2 + texture.clamp_min(0).square()).unsqueeze(1)[:h]
            evidence = count.sum(1) >= _MIN_FIT_BLOCKS
            # only the bins that carry evidence (≥ _MIN_BIN_DETAILS details; a patch spans a few of the bins) enter
            # ℓ: each such bin e of row pe is one row of (E, hypotheses) arrays, summed back per row
            pe, ke, r, inv, a_e, c_e = _bin_residuals(count[:h], sq[:h], sm[:h], a_h, c_h, q_h, tau2[:h], eta_bin, c_counts)
            per_row = torch.zeros(4, h, a_h.shape[1], dtype=f64, device=dev).index_add_(
                1, pe, torch.stack([r.square() * inv, r * inv, inv,
                                    _clip_cost(clip_n[pe, ke].unsqueeze(1), clip_m[pe, ke].unsqueeze(1),
                                               clip_o[pe, ke].unsqueeze(1), a_e, c_e, q_h[pe].unsqueeze(1))]))
            own = torch.where(evidence[:h].view(1, h, 1), per_row, torch.zeros_like(per_row))  # (4, h, hypotheses)
            # other exposures of this camera add their bins; the model error η is common to all of them (one camera,
            # one scene), so it is applied once, to the sum
            quad, lin, inv_sum, clip_cost = own if other is None else own + other[:4].unsqueeze(1)
            ll = -0.5 * (quad - eta2 * lin.square() / (1.0 + eta2 * inv_sum)) + clip_cost
            post = torch.softmax(ll + prior_h, 1).expand(b, -1)
            # goodness of fit: the image's common log-variance offset from each hypothesis (the bins' weighted mean
            # residual) in standard errors (its sampling and the model error η); the largest over the hypotheses says
            # how far the image reads below every camera state the metadata's ranges allow (negative: quieter)
            fit_z = _fit_z(lin, inv_sum, eta2)
            fit_z = torch.where(evidence[:h], fit_z, torch.zeros_like(fit_z)).expand(b)
            # the patches read as far quieter alone (a noiseless overlay) keep their own goodness of fit; a frame
            # mostly of them reads as its median patch at most
            fit_z = torch.where(quiet_alone, own_z, fit_z if quiet_frame is None else fit_z.clamp_max(quiet_frame))
        # the scene allowance's blind spot: its log-variance term ln(1 + τ²/v)² grows without bound as v → 0, so on a
        # quiet camera a bin may read several τ² above the metadata's kept variance f_k·v_k(M) and H₀ still win. Where
        # the closed form is kept (below), that excess — beyond τ² and three of the bin's sampling standard errors
        # ŝ_k·√(2/N_k) — is what the answer may miss: over the patch's (pooled: the frame's) bins, the largest such
        # excess and the largest such bin's measured variance
        n_e = count[:h][pe, ke]
        s_e = sq[:h][pe, ke] / _TRUNCATED_CHI2 / n_e
        over_e = s_e - s_e.clamp_min(1e-9) * torch.exp(-r[:, 0])  # ŝ_k − f_k·v_k(M) [DN²] (r: ln ŝ_k − ln f_k·v_k)
        beyond_e = over_e > tau2[:h][pe] + 3.0 * s_e * torch.sqrt(2.0 / n_e)
        excess_var, excess_read = (torch.zeros(h, dtype=f64, device=dev).scatter_reduce(
            0, pe, torch.where(beyond_e, t, torch.zeros_like(t)), reduce="amax", include_self=True).expand(b) for t in (over_e, s_e))
        # far quieter than every camera state (LESS_NOISE): no hypothesis explains the image, so the closed form is kept
        # with no stated uncertainty (∞, below) and no cause; P(match) stays the posterior's, which here only says
        # whether the camera states that fit least badly are visible mismatches — no verdict on the metadata
        quiet = fit_z < -QUIET_Z_LIMIT
        # a mismatch too small to see (|Δσ_Total| < max(0.5 DN, 15 %)) is no mismatch: its mass counts for M
        mean_i = x.clamp(0, 1).flatten(1).mean(1).double() * 255.0
        tot = (a_all * mean_i.unsqueeze(1) + c_all).clamp_min(0).sqrt()  # σ_Total before clipping, (B, 1 + H)
        visible = _visible(tot)
        if other is not None:  # a mismatch the other exposure times show is seen, however little it moves this frame
            visible = visible | (other[4] > 0).unsqueeze(0)
        p_match = (1.0 - (post * visible).sum(1)).clamp(0.0, 1.0)  # a probability: no −2e-16 from rounding
        # the visible mismatch hypotheses alone (renormalised): what the image says where it contradicts M
        w = (post * visible)[:, 1:]
        w = w / w.sum(1, keepdim=True).clamp_min(1e-300)
        # which kind of mismatch the evidence names, given that there is a visible one: the visible hypotheses'
        # posterior summed per kind (gain, temperature, white noise, beyond); rows sum to 1 (0 where no hypothesis is visible)
        cause = w.view(b, len(MISMATCH_CAUSES), -1).sum(-1)
        e_a = (w * a_all[:, 1:]).sum(1)
        e_var = (w.unsqueeze(-1) * var_all[:, 1:]).sum(1)
        # neighbour check: white noise leaves the diagonal details of adjacent blocks uncorrelated; a scene's fine
        # texture does not
        corr_check, own_corr_check = _neighbour_check(x_ev, v_ref, inl_all[0] * (~(quiet_alone | loud_alone)).view(b, 1, 1, 1), pool)
        readable = evidence & (count.sum(1) >= MIN_FOLLOW_DETAILS) & ~textured(texture, corr_check)
        follows = readable & (p_match < 0.5) & ~quiet
        # a lossy codec changes the noise: it zeroes the coefficients below its steps, noise included, and adds its
        # quantisation error to the others (on a fine texture it reads as noise), so an 8-bit image that shows
        # JPEG's quantised block grid (jpeg_grid) cannot check the metadata in either direction: the closed form with
        # no verdict, as where it is quieter than every camera state. Tested only where the image would be followed
        # (a pass over the pixels); pooled, the frame is coded where its sampled patches are (coded_frame)
        e_tot_image = (w * tot[:, 1:]).sum(1)
        codec = follows & (q > 0)
        if bool(codec.any()):
            if pool:
                codec = codec & coded_frame(x)
            else:
                sel = codec.nonzero(as_tuple=True)[0]
                codec = torch.zeros_like(codec).index_put_((sel,), jpeg_grid(x[sel]).coded.to(dev))
        follows = follows & ~codec
        no_verdict = quiet | codec
        # σ after clipping of the metadata's model, and of the image's (posterior-mean variances) on the patches that
        # follow it (the only ones that use it): one batched call
        sel = follows.nonzero(as_tuple=True)[0]
        clipped = _clipped_prior_dn(
            torch.cat([x, x[sel]]), torch.cat([a0, e_a[sel]]), torch.cat([var0[:, 0], e_var[sel, 0]]).sqrt(),
            torch.cat([var0[:, 1], e_var[sel, 1]]).sqrt(),
        )
        prior_clipped = clipped[:b]
        image_clipped = prior_clipped.index_copy(0, sel, clipped[b:])
        out_sigma = torch.where(follows.unsqueeze(1), image_clipped, prior_clipped)
        xi = torch.where(follows, prior_clipped[:, 3] - image_clipped[:, 3], torch.zeros_like(p_match))
        # posterior spread of σ_Total (before clipping) over all hypotheses, scaled to the clipped total
        e_tot = (post * tot).sum(1)
        sd_tot = ((post * tot.square()).sum(1) - e_tot.square()).clamp_min(0).sqrt()
        scale = (prior_clipped[:, 3] / tot[:, 0].clamp_min(1e-12)).clamp(0, 1)
        xi_std = torch.where(evidence & ~no_verdict, sd_tot * scale, torch.full_like(sd_tot, float("inf")))
        unclipped_answer = torch.where(follows, e_tot_image, tot[:, 0])
        # per source: the posterior RMS deviation of every hypothesis's σ (before clipping) from the answer's, scaled
        # to the clipped answer — the spread where the image is followed, and what a mismatch would move where the
        # closed form is kept; large where the sources that explain the excess are told apart by the prior alone
        src = torch.stack([(a_all * mean_i.unsqueeze(1)).clamp_min(0).sqrt(), var_all[..., 0].clamp_min(0).sqrt(),
                           var_all[..., 1].clamp_min(0).sqrt()], dim=-1)  # (B, 1 + H, 3) [DN]
        image_src = torch.stack([(e_a * mean_i).clamp_min(0).sqrt(), e_var[:, 0].clamp_min(0).sqrt(), e_var[:, 1].clamp_min(0).sqrt()], 1)
        answer_src = torch.where(follows.unsqueeze(1), image_src, src[:, 0])
        sd_src = (post.unsqueeze(-1) * (src - answer_src.unsqueeze(1)).square()).sum(1).sqrt()
        src_scale = torch.where(answer_src > 1e-12, out_sigma[:, :3] / answer_src.clamp_min(1e-12), torch.ones_like(answer_src)).clamp(0, 1)
        # and the patch's own sampling: the realised σ of n pixels' noise differs from its expected σ by σ/√(2n)
        sd_src = (sd_src.square() * src_scale.square() + out_sigma[:, :3].square() / (2.0 * x.shape[-1] * x.shape[-2])).sqrt()
        sigma_std = torch.where((evidence & ~no_verdict).unsqueeze(1), sd_src, torch.full_like(sd_src, float("inf")))
        # row and column noise, which no source of the metadata makes: where it is detected on a patch that is not
        # textured once it is taken out, and moves σ_Total visibly, it adds to the image's σ_Total and so to ξ (the
        # per-source σ stay the pixel noise's)
        band_sigma = band.sigma_dn * band.detected
        band_var = band_sigma.square().sum(1)
        white_total = out_sigma[:, 3].double()
        banded_total = (white_total.square() + band_var).sqrt()
        prior_total = prior_clipped[:, 3]
        banded = ((band_var > 0) & readable & ~no_verdict
                  & ((banded_total - prior_total).abs() >= torch.clamp_min(VISIBLE_XI_FRACTION * prior_total, VISIBLE_XI_DN)))
        out_sigma = torch.cat([out_sigma[:, :3], torch.where(banded, banded_total, white_total).unsqueeze(1)], 1)
        xi = torch.where(banded, prior_total - banded_total, xi.double())
        p_match = torch.where(banded, torch.zeros_like(p_match), p_match)
        follows = follows | banded
        band_se = (band.var_se_dn2 * band.detected).sum(1) / (2.0 * banded_total.clamp_min(1e-6))
        xi_std = torch.where(banded, (xi_std.square() + band_se.square()).sqrt(), xi_std)
        unclipped_answer = torch.where(banded, (unclipped_answer.square() + band_var).sqrt(), unclipped_answer)
        # where the closed form is kept on a patch whose details are noise (evidence, not textured, a verdict) but a bin
        # reads beyond the scene allowance above it (excess_var, above): the posterior, the decision, σ and ξ stay, and
        # the stated uncertainty covers the excess — xi_std, and each source's sigma_std (any of them could carry it),
        # at least √(measured variance) − σ_Total(M) and √(σ_Total(M)² + excess) − σ_Total(M) (the excess carried to
        # the patch's own level: pooled, or where the bin lies below the patch's mean)
        kept_closed = evidence & ~follows & ~no_verdict & ~textured(texture, corr_check)
        closed_total = out_sigma[:, 3].double()
        excess_dn = torch.where(kept_closed & (excess_var > 0),
                                torch.maximum(excess_read.sqrt(), (closed_total.square() + excess_var).sqrt()) - closed_total,
                                torch.zeros_like(closed_total)).clamp_min(0.0)
        xi_std = torch.maximum(xi_std, excess_dn)
        sigma_std = torch.maximum(sigma_std, excess_dn.unsqueeze(1))
        out = torch.cat([out_sigma, xi.unsqueeze(1), xi_std.unsqueeze(1), p_match.unsqueeze(1), count.sum(1, keepdim=True),
                         texture.unsqueeze(1), follows.to(f64).unsqueeze(1), unclipped_answer.unsqueeze(1),
                         corr_check.unsqueeze(1), tau2.sqrt().unsqueeze(1), sigma_std, band_sigma,
                         own_count.unsqueeze(1), own_texture.unsqueeze(1), own_corr_check.unsqueeze(1),
                         torch.where((readable & ~no_verdict).unsqueeze(1), cause, torch.full_like(cause, float("nan"))),
                         fit_z.unsqueeze(1), tot.amin(1, keepdim=True), codec.to(f64).unsqueeze(1), excess_dn.unsqueeze(1)],
                        dim=1)
    out = out.float()
    if bool(loud_alone.any()):  # the patches far noisier than their frame, read alone
        sel = loud_alone.nonzero(as_tuple=True)[0]
        out[sel] = physics_noise_posterior(
            image[sel], meta, eta=eta, eta_bin=eta_bin, mismatch_probability=mismatch_probability,
            beyond_probability=beyond_probability, grid=grid, bins=bins, bound_margin=bound_margin,
            fallback_margin=fallback_margin, pool=False, scene_allowance_dn=scene_allowance_dn,
            scene_allowance_min_dn=scene_allowance_min_dn, reference=None if reference is None else reference[sel])
    if not return_evidence:
        return out
    # this frame's own bins (row 0: pooled, every row is the frame) and which hypotheses move its σ_Total visibly at
    # the frame's mean level; none where it is not readable
    frame_tot = (a_all[:1] * mean_i.mean() + c_all[:1]).clamp_min(0).sqrt()
    frame_ev = torch.cat([own[:, 0], _visible(frame_tot).to(f64)])
    return out, torch.where(readable[0] & ~codec.any(), frame_ev, torch.zeros_like(frame_ev))


def _visible(tot: torch.Tensor) -> torch.Tensor:
    """Which hypotheses move σ_Total [DN] (column 0: the metadata's) by at least max(:data:`VISIBLE_XI_DN`,
    :data:`VISIBLE_XI_FRACTION` × σ_Total): (R, 1 + H) → (R, 1 + H) bool."""
    return (tot - tot[:, :1]).abs() >= torch.maximum(torch.full_like(tot[:, :1], VISIBLE_XI_DN), VISIBLE_XI_FRACTION * tot[:, :1])


def noise_evidence(image: torch.Tensor, meta: CameraMetadata, reference: torch.Tensor | None = None, **settings: Any) -> torch.Tensor:
    """What one frame's noise says about the hypotheses of :func:`physics_noise_posterior` on its camera, its patches
    pooled (one camera state, ``meta`` of batch 1), (5, 1 + 4·grid) float64: per hypothesis, summed over the frame's
    intensity bins, r²/D, r/D and 1/D (r the bin's log-residual, D its variance without the common model error η), the
    clipping penalty, and 1 where the hypothesis moves the frame's σ_Total visibly (at its mean level; 0 elsewhere —
    summed over frames, the number of frames where it does). Zeros where the frame is not readable (too few flat
    details, or textured).

    The hypotheses are absolute values of the camera's fields (its gain, temperature, white-noise density, extra white
    noise in DN), so two frames of one camera that differ **only in exposure time** share them: hypothesis j predicts
    σ_DCSN² ∝ t_exp in each and the same σ_PN and σ_RN. Their evidence adds up, η is applied once to the sum (one camera,
    one model error), and an excess that grows with the exposure time (a hotter sensor than told) is told apart from
    one that does not (readout noise) — which a single exposure cannot do. Pass the sum of other frames' evidence as
    ``other_evidence`` of :func:`physics_noise_posterior` (:meth:`PhysicsNoiseEstimator.predict` with
    ``other_exposures`` does it).

    Args:
        image: B×1×H×W patches of one frame in [0, 1].
        meta: its camera state, batch 1.
        reference: another exposure of the same still scene in the same state (read as a static pair), or None.
        settings: keyword arguments of :func:`physics_noise_posterior` (``pool`` is always True here).
    """
    settings = {k: v for k, v in settings.items() if k != "pool"}
    if "other_evidence" in settings or "return_evidence" in settings:
        raise ValueError("noise_evidence reads one frame: other_evidence and return_evidence are not arguments of it")
    if meta.batch_size != 1:
        raise ValueError(f"noise_evidence reads one camera state: metadata must have batch 1, got {meta.batch_size}")
    return physics_noise_posterior(image, meta, pool=True, reference=reference, return_evidence=True, **settings)[1]




def quieter_than_any_camera(patches: torch.Tensor, eta: float = 0.12) -> torch.Tensor:
    """Whether B×1×H×W patches in [0, 1] read far less noise than any camera state in ``METADATA_RANGES`` makes,
    whatever its metadata → (B,) bool (the :data:`LESS_NOISE` of estimators that are given no metadata, or only some).

    Photon noise alone bounds every camera's noise from below: σ_PN² = 255²·g·Ī/FW ≥ 255²·Ī/FW_max [DN²] with the
    least gain g = 1 (0 dB) and the largest full well FW_max = 100 000 e⁻, at the patch's mean intensity Ī ∈ [0, 1]
    (white noise of variance a·I per pixel averages a·Ī over the pixels), and the other sources only add to it.
    Only where that bound is at least :data:`QUANTISATION_SIGMA_DN` (Ī ≥ 98 DN: 0.57 DN at 128 DN, 0.81 DN at 255 DN)
    does 8-bit rounding add its q = 1/12 DN² instead of removing noise, so there the blocks' diagonal Haar details
    d = (I₀₀ − I₀₁ − I₁₀ + I₁₁)/2 have E[d²] ≥ v_min = σ_PN,min² + q (q = 0 for input that is not whole DN). It is read
    on the n blocks none of whose pixels lies within ½ DN of a bound and whose mean lies in 5…250 DN (clipping takes
    no noise there: 6·σ_PN,min ≤ 5 DN), as v̂ = mean d² (texture and edges only add to it), and the patch is
    refused where ln(v̂/v_min) lies more than :data:`QUIET_Z_LIMIT` standard errors below 0 — its sampling √(2/n) and
    the model error ``eta`` of :func:`physics_noise_posterior` in quadrature, as ``quiet_z`` there — with at least
    32 such blocks. Below 98 DN a quiet camera's rounded 8-bit patch may hold no noise at all, and nothing is refused.

    The patches are checked as every estimator function checks them
    (:func:`camhealth.estimators._common.check_patches`: a floating tensor, finite, in [0, 1], B×1×H×W with H, W ≥ 2;
    else a ``TypeError`` or ``ValueError`` naming the value), except while the caller is traced or exported.
    """
    _check_noise_patches(patches)
    b = patches.shape[0]
    if b == 0:
        return torch.zeros(0, dtype=torch.bool)
    x = patches.detach().float()
    p00, p01, p10, p11 = _block_pixels(x)  # [DN]
    m = (p00 + p01 + p10 + p11) / 4.0
    lo = torch.minimum(torch.minimum(p00, p01), torch.minimum(p10, p11))
    hi = torch.maximum(torch.maximum(p00, p01), torch.maximum(p10, p11))
    used = ((lo > 0.5) & (hi < 254.5) & (m >= 5.0) & (m <= 250.0)).flatten(1)
    d2 = ((p00 - p01 - p10 + p11) / 2.0).square().flatten(1).double()
    n = used.sum(1).double()
    v = (d2 * used).sum(1) / n.clamp_min(1.0)
    g_fw = 10.0 ** (METADATA_RANGES["gain_db"][0] / 20.0) / METADATA_RANGES["full_well_e"][1]
    sig2 = 255.0**2 * x.flatten(1).mean(1).double() * g_fw
    v_min = sig2 + _quantisation_variance(x)
    z = torch.log(v.clamp_min(1e-300) / v_min) / (2.0 / n.clamp_min(1.0) + eta**2).sqrt()
    return ((sig2.sqrt() >= QUANTISATION_SIGMA_DN) & (n >= _MIN_FIT_BLOCKS) & (z < -QUIET_Z_LIMIT)).cpu()


@dataclass
class PhysicsNoiseEstimator:
    """The shipped Full-Meta noise-source estimator: :func:`physics_noise_posterior` behind the
    :class:`~camhealth.inference.Estimator` interface (``predict(images, metadata)``), no network, no weights.

    Attributes:
        kind: ``"noise_source"``. patch_size: 128 (any integer size ≥ 8 works through :func:`physics_noise_posterior`;
            another is refused at construction, naming it).
        metadata_set: ``"full"`` (every field of :class:`~camhealth.physics.CameraMetadata` enters the closed form).
        settings: keyword arguments of :func:`physics_noise_posterior`.
        source: the name it was loaded by.
        device: where :func:`physics_noise_posterior` runs (the input checks, the assessability and defective-pixel
            checks stay on the CPU); the outputs are CPU tensors either way.
    """

    kind: str = "noise_source"
    patch_size: int = 128
    metadata_set: str = "full"
    settings: dict = field(default_factory=dict)
    source: str = "noise_source_full"
    backend: str = "torch"
    description: dict = field(default_factory=lambda: {
        "kind": "noise_source", "metadata_set": "full", "architecture": "physics_noise_posterior (no network)",
        "params": 0})
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    def __post_init__(self) -> None:
        if isinstance(self.patch_size, (bool, np.bool_)) or not isinstance(self.patch_size, (int, np.integer)):
            raise TypeError(f"patch_size = {self.patch_size!r} must be an integer number of px ≥ 8, got "
                            f"{type(self.patch_size).__name__}")
        if self.patch_size < 8:
            raise ValueError(f"patch_size = {self.patch_size!r} must be an integer number of px ≥ 8 (the noise fits read "
                             f"2×2 blocks of patches of at least 8×8 px)")

    @property
    def name(self) -> str:
        return self.source

    @torch.inference_mode()
    def predict(self, images: Any, metadata: Any = None, *, input_range: str = "auto", base_preset: str | None = None,
                batch_size: int = 256, precision: str = "fp32", views: int = 1, pool: bool = False,
                reference: Any = None, other_exposures: Sequence[Sequence[Any]] | None = None,
                other_evidence: torch.Tensor | None = None, return_evidence: bool = False) -> dict[str, Any]:
        """σ per source, total, ξ, its uncertainty and P(match) of B×1×128×128 patches (module docstring).

        ``pool``: the patches show one camera state (metadata of batch 1): the evidence of all of them decides
        (:func:`physics_noise_posterior`) — except where the frame's summed details are textured, whose patches that
        pass both texture checks on their own details (and keep 256 of them) are read alone, as without ``pool``;
        otherwise the patches go through it :data:`PATCH_CHUNK` (or ``batch_size``, if
        smaller) at a time. ``precision`` is accepted for interface compatibility: the statistics
        always run in float32/float64 (bf16 cannot resolve 1 DN at 255 DN). ``views`` must be 1.

        ``reference``: the same patches from another exposure of a static camera in the same camera state (same
        shape and input conventions as ``images``; e.g. the previous frame). The evidence is then read from the pair's
        difference (:mod:`camhealth.estimators.static_pair`), which holds the noise and nothing of the scene, with no
        allowance for the scene's fine content (:data:`PAIR_SCENE_ALLOWANCE_DN`); the answer is still about
        ``images`` (its clipping, its σ). Patches whose difference carries the scene
        (:func:`~camhealth.estimators.static_pair.scene_leak`, :func:`~camhealth.estimators.static_pair.pair_shift`:
        the scene or the camera moved, or a lossy codec re-quantised the two frames differently) or reads textured or
        without a flat area are read from ``images`` alone (a JPEG pair that passes those tests and would declare a
        mismatch keeps the closed form, as one JPEG frame does: :data:`LOSSY_CODEC`); pooled, a frame of which fewer than half the patches are
        still (the camera moved) is read alone as a whole. The output then has
        ``"static"`` (B,) bool: the answer read the pair.

        ``other_exposures`` (with ``pool``): other frames of the same camera whose metadata differ from ``metadata``
        only in the exposure time, each ``(images, metadata)`` or ``(images, metadata, reference)`` (a static pair,
        read as ``images`` with ``reference`` is: from the pair where the scene stood still, alone elsewhere). Their evidence joins this
        frame's (:func:`noise_evidence`): dark-current shot noise grows with the exposure time and readout noise does
        not, so an excess the frames show is split between them by the physics instead of by the prior. The answer is
        about ``images``; an other frame that is not readable (textured, no flat area) adds nothing. The output then
        has ``"exposures_read"``: how many of them added evidence.

        ``other_evidence``: the same as a (5, 1 + 4·grid) tensor, the summed :func:`noise_evidence` (or ``"evidence"``)
        of such frames, kept by the caller (a monitor) so that each frame is read once; the caller vouches that they
        show this camera at other exposure times. ``return_evidence`` (with ``pool``): the output also has
        ``"evidence"``, this frame's own evidence from the same reading (zeros where it is not readable), for later
        frames at other exposure times.

        ``"cause"`` (B, 4): which kind of mismatch the evidence names, should there be a visible one — the gain, the
        temperature or the white-noise density wrong, or noise beyond what any field in range explains
        (:data:`MISMATCH_CAUSES`); each row sums to 1, NaN where the patch is not readable. A gain changes the
        signal-dependent part of the noise and the signal-independent part together, so one frame names it; a hotter
        sensor, more white noise and noise beyond the fields all add a signal-independent variance, which one exposure
        time shares between them by their priors and physical ranges, and ``other_exposures`` tells apart.

        An empty batch gives every output with 0 rows, and the ``"evidence"`` (zeros) and ``"exposures_read"`` the
        arguments ask for; its arguments are checked as a full batch's are."""
        if precision not in ("fp32", "bf16"):
            raise ValueError(f"precision = {precision!r} must be 'fp32' or 'bf16'")
        batch_size = check_batch_size(batch_size)
        if views != 1:
            raise ValueError(f"views = {views!r}: flipped views are for MTF estimators; {self.name!r} is a noise estimator")
        for name, value in (("pool", pool), ("return_evidence", return_evidence)):
            if not isinstance(value, (bool, np.bool_)):
                raise TypeError(f"{name} = {value!r} must be True or False, got {type(value).__name__}")
        patches = _to_patches(images, self.patch_size, input_range)
        if metadata is None:
            raise ValueError(f"estimator {self.name!r} reads 'full' metadata: pass metadata= (CameraMetadata, a dict of "
                             f"fields in physical units, or a preset name)")
        b = patches.shape[0]
        ref = None
        if reference is not None:
            try:
                ref = _to_patches(reference, self.patch_size, input_range)
            except (TypeError, ValueError) as exc:
                raise type(exc)(f"reference: {exc}") from None
            if ref.shape != patches.shape:
                raise ValueError(f"reference must hold the same patches as images, {tuple(patches.shape)}, got {tuple(ref.shape)}")
        meta = _to_metadata(metadata, b, base_preset)  # checked whatever the number of patches
        settings = {**self.settings, **({"pool": True} if pool else {})}
        exposures_read = None
        if (other_evidence is not None or return_evidence) and not settings.get("pool"):
            raise ValueError("other_evidence and return_evidence are about whole frames of one camera: pass pool=True")
        if other_exposures is not None:
            settings["other_evidence"], exposures_read = self._other_evidence(other_exposures, meta, bool(settings.get("pool")),
                                                                               input_range, base_preset)
        if other_evidence is not None:
            if not isinstance(other_evidence, torch.Tensor):
                raise TypeError(f"other_evidence must be a tensor (noise_evidence), got {type(other_evidence).__name__}")
            given = other_evidence.detach().to(self.device, torch.float64)
            settings["other_evidence"] = given if "other_evidence" not in settings else settings["other_evidence"] + given
        if b == 0:  # an empty batch: every output with 0 rows, and the keys the arguments ask for
            z = torch.zeros(0)
            evidence = None
            if settings.get("pool"):  # a frame without patches adds no evidence (other_evidence checked as for any frame)
                on_device = meta if self.device.type == "cpu" else meta.to(self.device)
                evidence = physics_noise_posterior(patches.to(self.device), on_device, return_evidence=True, **settings)[1]
            return {"assessable": torch.zeros(0, dtype=torch.bool), "reason": [], "sigma": torch.zeros(0, 3), "sigma_std": torch.zeros(0, 3), "sigma_total": z,
                    "xi": z, "xi_std": z, "p_match": z, "follows_image": torch.zeros(0, dtype=torch.bool),
                    "row_column_dn": torch.zeros(0, 2), "cause": torch.zeros(0, len(MISMATCH_CAUSES)),
                    "defects": torch.zeros(0, 2, dtype=torch.int64),
                    "defects_checked": torch.zeros(0, dtype=torch.int64),
                    "defect_mask": torch.zeros(0, 1, *patches.shape[-2:], dtype=torch.int8),
                    **({} if ref is None else {"static": torch.zeros(0, dtype=torch.bool)}),
                    **({} if exposures_read is None else {"exposures_read": exposures_read}),
                    **({"evidence": evidence.cpu()} if return_evidence else {})}
        raw, static, evidence = self._read(patches, ref, meta, settings, batch_size)
        assessable, reason = assess_patches(patches, "noise_source")
        reason = list(reason)
        is_textured = textured(raw[:, 8], raw[:, 11]).tolist()
        noise_dn = haar_noise_dn(patches)
        too_strong = beyond_validated_range(patches, noise_dn).tolist()
        eight_bit = (_quantisation_variance(patches) > 0).tolist()
        for i in range(b):
            if reason[i]:
                continue
            follows = bool(raw[i, 9] > 0.5)
            if too_strong[i] or (not follows and raw[i, 10] > VALIDATED_SIGMA_DN):
                # known without a reading: the patch's finest-scale fluctuations beyond the limit beyond doubt, or the
                # metadata's own σ_Total (the closed form, which a patch that does not follow the image returns)
                reason[i] = BEYOND_VALIDATED
            elif raw[i, 7] < MIN_FOLLOW_DETAILS:
                reason[i] = "no flat area"
            elif is_textured[i]:
                reason[i] = "textured"
            elif raw[i, 10] * (1.0 - 3.0 / math.sqrt(2.0 * float(raw[i, 7]))) > VALIDATED_SIGMA_DN:
                # the image's reading above the limit by three of its sampling standard errors, σ/√(2N) from its N
                # details (beyond_validated_range's rule); a patch that does not follow the image is decided above
                reason[i] = BEYOND_VALIDATED
            elif raw[i, 25] < -QUIET_Z_LIMIT:
                # far quieter than every camera state: a quiet 8-bit camera's rounding may have removed its noise
                reason[i] = BELOW_QUANTISATION if eight_bit[i] and raw[i, 26] < QUANTISATION_SIGMA_DN else LESS_NOISE
            elif raw[i, 27] > 0.5:  # it would contradict the metadata, and the codec's block grid is there
                reason[i] = LOSSY_CODEC
        assessable = torch.tensor([r == "" for r in reason], dtype=torch.bool)
        defects = defective_pixels(patches, noise_dn)  # on every patch: a defect shows in textured and clipped ones too
        return {"assessable": assessable, "reason": reason, "sigma": raw[:, :3], "sigma_std": raw[:, 13:16], "sigma_total": raw[:, 3],
                "xi": raw[:, 4], "xi_std": raw[:, 5], "p_match": raw[:, 6], "follows_image": raw[:, 9] > 0.5,
                "row_column_dn": raw[:, 16:18], "cause": raw[:, 21:25], "defects": torch.stack([defects.hot, defects.dark], 1),
                "defects_checked": defects.checked,
                "defect_mask": defects.mask, **({} if ref is None else {"static": static}),
                **({} if exposures_read is None else {"exposures_read": exposures_read}),
                **({"evidence": evidence.cpu()} if return_evidence else {})}

    def _read(self, patches: torch.Tensor, ref: torch.Tensor | None, meta: CameraMetadata, settings: dict[str, Any],
              batch_size: int) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """The posterior of the patches (CPU, (B, 29)) — read from their static pair where ``ref`` is given and the
        scene stood still, alone elsewhere (:meth:`predict`) — whether each was read from the pair ((B,) bool, None
        without ``ref``), and, pooled, the frame's own evidence summed over the readings (:func:`noise_evidence`)."""
        b = patches.shape[0]
        static, evidence = None, None
        on_device, meta_dev, ref_dev = patches, meta, ref
        if self.device.type != "cpu":
            on_device, meta_dev = patches.to(self.device), meta.to(self.device)
            ref_dev = None if ref is None else ref.to(self.device)
        if ref_dev is None:
            raw, evidence = self._posterior(on_device, meta_dev, settings, batch_size)
            raw = raw.cpu()
        else:
            pair = {"scene_allowance_dn": PAIR_SCENE_ALLOWANCE_DN, "scene_allowance_min_dn": PAIR_SCENE_ALLOWANCE_DN, **settings}
            # a patch whose difference carries the scene (it moved, or a codec re-quantised it) is read alone
            static = pair_stillness(patches, ref, pool=bool(settings.get("pool"))).cpu()
            if settings.get("pool") and 2 * int(static.sum()) < b:  # most of the frame moved: the camera did
                static[:] = False
            raw = torch.zeros(b, len(PHYSICS_NOISE_COLUMNS))
            sel = static.nonzero(as_tuple=True)[0]
            if sel.numel():
                sel_dev = sel.to(on_device.device)
                raw_sel, evidence = self._posterior(on_device[sel_dev], meta_dev if meta.batch_size == 1 else meta_dev[sel_dev],
                                                    pair, batch_size, ref_dev[sel_dev])
                raw[sel] = raw_sel.cpu()
                # a pair that is still textured or without a flat area (clipped nearly everywhere) is read alone too
                static[sel] = ~textured(raw[sel, 8], raw[sel, 11]) & (raw[sel, 7] >= MIN_FOLLOW_DETAILS)
            moved = (~static).nonzero(as_tuple=True)[0]
            if moved.numel():
                moved_dev = moved.to(on_device.device)
                raw_moved, moved_evidence = self._posterior(on_device[moved_dev], meta_dev if meta.batch_size == 1 else meta_dev[moved_dev],
                                                            settings, batch_size)
                raw[moved] = raw_moved.cpu()
                # (a pair read as textured or without a flat area gave no evidence: its patches' come from here)
                evidence = moved_evidence if evidence is None else evidence + moved_evidence
        return raw, static, evidence

    def _other_evidence(self, frames: Any, meta: CameraMetadata, pool: bool, input_range: str,
                        base_preset: str | None) -> tuple[torch.Tensor, int]:
        """The summed :func:`noise_evidence` of ``other_exposures`` (:meth:`predict`) on the estimator's device, and how
        many of the frames were readable. Each must show this camera (``meta``, batch 1) at another exposure time."""
        if not pool:
            raise ValueError("other_exposures adds up the evidence of whole frames of one camera: pass pool=True")
        if meta.batch_size != 1:
            raise ValueError(f"other_exposures needs one camera state for this frame: metadata of batch 1, got {meta.batch_size}")
        if isinstance(frames, (torch.Tensor, str)) or not isinstance(frames, Sequence):
            raise TypeError(f"other_exposures must be a sequence of (images, metadata[, reference]) tuples, got {type(frames).__name__}")
        total, read = None, 0
        for k, item in enumerate(frames):
            if not isinstance(item, Sequence) or isinstance(item, (str, torch.Tensor)) or len(item) not in (2, 3):
                raise TypeError(f"other_exposures[{k}] must be (images, metadata) or (images, metadata, reference), got "
                                f"{type(item).__name__}{f' of length {len(item)}' if isinstance(item, Sequence) else ''}")
            try:
                patches = _to_patches(item[0], self.patch_size, input_range)
                ref = None if len(item) < 3 or item[2] is None else _to_patches(item[2], self.patch_size, input_range)
            except (TypeError, ValueError) as exc:
                raise type(exc)(f"other_exposures[{k}]: {exc}") from None
            if ref is not None and ref.shape != patches.shape:
                raise ValueError(f"other_exposures[{k}]: reference must hold the same patches as images, {tuple(patches.shape)}, "
                                 f"got {tuple(ref.shape)}")
            other = _to_metadata(item[1], 1, base_preset)
            if other.batch_size != 1:
                raise ValueError(f"other_exposures[{k}]: metadata must have batch 1, got {other.batch_size}")
            for name in FULL_FIELDS:
                if name == "exposure_s":
                    continue
                mine, theirs = float(getattr(meta, name).reshape(-1)[0]), float(getattr(other, name).reshape(-1)[0])
                if not math.isclose(mine, theirs, rel_tol=1e-6, abs_tol=1e-12):
                    raise ValueError(f"other_exposures[{k}]: {name} = {theirs:g} differs from this frame's {mine:g}; the frames "
                                     f"may differ only in exposure_s (their evidence is about one camera)")
            if other.constants != meta.constants:  # the fixed sensor constants are the camera's too
                diff = ", ".join(f"{f.name} = {getattr(other.constants, f.name)!r} (this frame's {getattr(meta.constants, f.name)!r})"
                                 for f in dataclasses.fields(SensorConstants)
                                 if getattr(other.constants, f.name) != getattr(meta.constants, f.name))
                raise ValueError(f"other_exposures[{k}]: its SensorConstants differ from this frame's: {diff}; the frames may "
                                 f"differ only in exposure_s (their evidence is about one camera)")
            # read as the frame itself is: from its static pair where the scene stood still, alone elsewhere
            _, _, evidence = self._read(patches, ref, other, {**self.settings, "pool": True}, patches.shape[0])
            read += int(bool(evidence.any()))
            total = evidence if total is None else total + evidence
        if total is None:
            raise ValueError("other_exposures is empty: pass None, or at least one (images, metadata) frame")
        return total, read

    def _posterior(self, patches: torch.Tensor, meta: CameraMetadata, settings: dict[str, Any], batch_size: int,
                   reference: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:func:`physics_noise_posterior` of a batch on the estimator's device, (B, 29): pooled in one call (with the
        patches of a textured frame that pass both checks on their own details read alone), else in chunks; and,
        pooled, the frame's own evidence of that call (:func:`noise_evidence`; None per patch)."""
        b = patches.shape[0]
        if settings.get("pool"):  # the whole batch is one frame: one call, whatever batch_size says
            raw, evidence = physics_noise_posterior(patches, meta, reference=reference, return_evidence=True, **settings)
            # texture the frame's summed details show may live in a few of its patches: where the frame as a whole is
            # textured, the patches whose own details pass both checks are read on their own
            # (the frame's row: the checks every pooled patch shares; a patch far noisier than its frame has its own)
            f = int((raw[:, 8] == raw[:, 8].mode().values).nonzero()[0, 0]) if b > 1 else 0
            if b > 1 and bool(textured(raw[f, 8], raw[f, 11])):
                alone = ((raw[:, 18] >= MIN_FOLLOW_DETAILS) & ~textured(raw[:, 19], raw[:, 20])).nonzero(as_tuple=True)[0]
                if alone.numel():
                    own = {**settings, "pool": False}
                    raw[alone] = torch.cat([physics_noise_posterior(
                        patches[alone[i:i + PATCH_CHUNK]], meta,
                        reference=None if reference is None else reference[alone[i:i + PATCH_CHUNK]], **own)
                        for i in range(0, alone.numel(), PATCH_CHUNK)])
            return raw, evidence
        step = min(batch_size, PATCH_CHUNK)
        return torch.cat([physics_noise_posterior(patches[i:i + step], meta if meta.batch_size == 1 else meta[i:i + step],
                                                  reference=None if reference is None else reference[i:i + step], **settings)
                          for i in range(0, b, step)]), None
