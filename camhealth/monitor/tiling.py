"""Patch grids and scene-adaptive patch selection for the monitor ("model only what a scene needs").

A frame is tiled into a **centred grid of non-overlapping P×P patches** (P = 128 px for the noise
estimators, 192 px for the MTF estimator, thesis 4.3.1–4.3.3; a remainder narrower than P at the borders
is not used, a frame smaller than one patch gives an empty grid). Before any network runs, cheap
statistics of every patch are computed in one batched pass over a strided view of the frame
(:func:`patch_statistics`, all in DN of 255):

- mean intensity Ī and the fractions of pixels within 0.5 DN of 0 and 255 (clipping);
- a robust noise level σ̂ = median|d| / 0.6745 of the finest diagonal Haar detail
  d = (I₀₀ − I₀₁ − I₁₀ + I₁₁)/2 over 2×2 blocks (Donoho's MAD estimate; var d = σ² for white noise, edges
  barely move the median);
- the structure contrast s = √max(0, var(B₈) − σ̂²/64) of the 8×8 block means B₈ — scene content at
  ≥ 16-px periods, which blur of a few px hardly changes and from which the noise (variance σ²/64 in a
  block mean) is removed;
- the edge energy e = √max(0, ½·mean(Δx² + Δy²) − σ̂²/2) of the 2×2-binned patch (Δ: neighbour
  differences; white noise contributes σ²/2) — a sharpness cue that drops when blur grows;
- the edge kurtosis γ = κ₄ / (mean Δ² − σ̂²/2)² of the same differences (κ₄ = mean Δ⁴ − 3·(mean Δ²)², the
  fourth cumulant, which Gaussian noise does not change; :func:`camhealth._inputs.edge_kurtosis`): ≈ 0 for
  Gaussian-like texture, large where the scene has edges; with its standard error.

**Which patches are worth estimating** (:func:`select_patches`; the thesis showed that over/under-exposed
and homogeneous areas break every blur estimator, Sec. 5.3–5.5):

- noise: skip a patch that is more than half clipped ("black" at 0 DN / "saturated" at 255 DN — the noise
  there is clipped away; the same rule as :func:`camhealth.inference.assess_patches`, so a skip never
  hides a patch the estimator would have called assessable);
- blur (MTF): the same clipping rule plus "featureless" when s < 2 DN (no structure to measure blur on;
  noise-corrected, so a flat but noisy patch is featureless too), and "no edges" unless γ − 2·SE ≥ 0.5 (Gaussian-like
  texture or weak structure under strong noise: the estimator would call the patch not assessable). Every skip
  is counted with its reason.

**Static-region reuse** (:class:`StaticRegions`): a patch whose content has not changed since it was last
estimated keeps its estimate. Frame differencing at block level: the patch is *changed* if any 8×8 block
mean moved by more than max(``block_tol_dn``, k·√2·σ̂/8) (k = ``block_sigmas``; √2·σ̂/8 is the standard
deviation of the difference of two noisy block means), or its noise level σ̂ or edge energy e changed by
more than an absolute-plus-relative tolerance (a gain/temperature or focus change of a static scene). A
static patch is still re-estimated every ``max_age`` frames, staggered over the grid so that the work is
spread evenly: patch i is due when (frame + i) mod ``max_age`` = 0. A reused estimate stands for the frame it is
reused in (the monitor's temporal window takes it as that frame's value).

**Coarse → refine** (:func:`coarse_lattice`, :func:`refine_plan`): the patches that need a fresh estimate
are first estimated on the coarse lattice (even row and even column: a quarter of the grid) and where a
patch has fewer than two informative lattice neighbours; each remaining patch is then **interpolated** (the
mean of its 2 or 4 lattice neighbours) only if those neighbours agree (range of every estimated value
≤ its tolerance) and the patch looks like them (each cue — Ī and σ̂ for noise, e for blur — inside the
neighbours' range widened by a tolerance); otherwise it is estimated as well ("refine only where it
changes"). With a noise-source estimator and metadata the monitor interpolates in physics-normalised
units — σ_s / σ_s,model(M, Ī) per source and ξ / σ_model(M, Ī), with the closed-form noise model at each
patch's own mean intensity (σ_PN = 255·√(g·Ī/FW)) — so that neighbours of different brightness can be
used; the cues are then σ̂ / σ_model (texture) and the clipped fraction.

**Sampling for a frame-level answer** (:func:`sample_patches`, the monitor's ``mode="sampled"``): on a
moving camera nothing can be reused and every patch is new in every frame, but noise is a property of the
camera state (one σ per source at a given intensity) and blur changes slowly over the frame. So only a few
informative patches per frame are estimated and the frame answer is aggregated over time:

- noise: the informative patches are split into ``k`` strata of equal count by their mean intensity Ī
  (so that the samples follow the frame's intensity distribution, σ_PN ∝ √Ī); in each stratum the flatter
  half (lowest s + e: texture least confused with noise) is eligible and the one sampled longest ago is
  taken (rotation over the frame across frames; ties → the flattest); patches far quieter than the camera's
  closed-form noise (``quiet``, :func:`quiet_patches`: a noiseless overlay) are left out while others remain;
- blur: only where there are edges — the informative patches (structure contrast s ≥ ``min_structure_dn``,
  not clipped); the grid is split into ``k`` sectors (rows × columns close to the grid's aspect), so that
  a blur that varies over the frame (depth, field curvature) is seen everywhere; in each sector the
  informative patch sampled longest ago is taken (ties → the most edge energy e). All informative patches
  of a sector are eligible, not only the edgiest: the MTF network reads strongly textured patches as
  sharper, so preferring them would bias the frame's MTF̃ against the every-patch answer.

Strata or sectors without a candidate leave their slot to the remaining candidates sampled longest ago, so
``k`` patches are sampled whenever ``k`` are informative.

Status codes per patch: :data:`STATUS_NAMES`. All functions are batched over patches (no Python loop over
patches); grids are row-major.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import torch

from camhealth._order import lower_median
from camhealth._validation import check_finite, check_float, check_tensor
from camhealth._inputs import MAX_CLIPPED_FRACTION, MIN_CONTRAST_DN, MIN_EDGE_KURTOSIS, edge_kurtosis_from_moments

__all__ = [
    "STATUS_NAMES",
    "ESTIMATED",
    "INTERPOLATED",
    "REUSED",
    "BLACK",
    "SATURATED",
    "FEATURELESS",
    "NOT_ASSESSABLE",
    "UNSAMPLED",
    "SKIP_CODES",
    "PatchGrid",
    "PatchStats",
    "QUIET_FRACTION",
    "quiet_patches",
    "SelectionConfig",
    "patch_statistics",
    "grid_statistics",
    "select_patches",
    "StaticRegions",
    "lattice_mask",
    "coarse_lattice",
    "lattice_neighbours",
    "refine_plan",
    "sample_patches",
    "status_counts",
]

#: Per-patch status, index = code. The first three carry a value; ``unsampled`` (sampled mode: informative,
#: but not among this frame's samples) carries none and is not a skip; the others are skips.
STATUS_NAMES: tuple[str, ...] = (
    "estimated", "interpolated", "reused", "black", "saturated", "featureless", "not_assessable", "unsampled", "no_edges",
)
ESTIMATED, INTERPOLATED, REUSED, BLACK, SATURATED, FEATURELESS, NOT_ASSESSABLE, UNSAMPLED, NO_EDGES = range(len(STATUS_NAMES))
#: Codes of patches without a value (skipped before or after the estimator).
SKIP_CODES: tuple[int, ...] = (BLACK, SATURATED, FEATURELESS, NO_EDGES, NOT_ASSESSABLE)

#: Block side [px] of the block means used for structure contrast and frame differencing.
BLOCK = 8
#: 1 / Φ⁻¹(0.75): median absolute value of a standard normal → σ.
_MAD_NORMAL = 0.6744897501960817


@dataclass(frozen=True)
class PatchGrid:
    """Centred grid of non-overlapping ``patch``×``patch`` tiles of an ``height``×``width`` frame.

    Attributes:
        height, width: frame size [px].
        patch: patch side P [px].
        rows, cols: number of patch rows / columns (0 when the frame is smaller than one patch).
        y0, x0: top-left corner of the grid [px] (the unused remainder is split between the borders).
    """

    height: int
    width: int
    patch: int
    rows: int
    cols: int
    y0: int
    x0: int

    @classmethod
    def fit(cls, height: int, width: int, patch: int) -> "PatchGrid":
        """The grid of ``patch``-px tiles that fits an ``height``×``width`` frame (possibly empty)."""
        for v, name in ((height, "height"), (width, "width"), (patch, "patch")):
            if isinstance(v, bool) or not isinstance(v, int):
                raise TypeError(f"{name} must be an int, got {type(v).__name__}")
            if v < 1:
                raise ValueError(f"{name} = {v} px must be >= 1")
        rows, cols = height // patch, width // patch
        return cls(height, width, patch, rows, cols, (height - rows * patch) // 2, (width - cols * patch) // 2)

    @property
    def n(self) -> int:
        """Number of patches."""
        return self.rows * self.cols

    @property
    def empty(self) -> bool:
        """True when the frame is smaller than one patch in either direction."""
        return self.n == 0

    def row_col(self) -> torch.Tensor:
        """(N, 2) long: row and column of every patch, row-major."""
        r, c = torch.meshgrid(torch.arange(self.rows), torch.arange(self.cols), indexing="ij")
        return torch.stack([r.reshape(-1), c.reshape(-1)], dim=1)

    def boxes(self) -> torch.Tensor:
        """(N, 4) long xyxy pixel boxes of the patches, row-major."""
        rc = self.row_col()
        y = rc[:, 0] * self.patch + self.y0
        x = rc[:, 1] * self.patch + self.x0
        return torch.stack([x, y, x + self.patch, y + self.patch], dim=1)

    def extract(self, frame: torch.Tensor) -> torch.Tensor:
        """(N, 1, P, P) patches of a 1×1×H×W (or 1×H×W / H×W) frame — a strided view, no copy."""
        x = _single_frame(frame, self)
        p = self.patch
        crop = x[self.y0 : self.y0 + self.rows * p, self.x0 : self.x0 + self.cols * p]
        tiles = crop.unfold(0, p, p).unfold(1, p, p)  # rows, cols, P, P
        return tiles.reshape(self.n, 1, p, p)


def _single_frame(frame: object, grid: PatchGrid) -> torch.Tensor:
    """``frame`` (1×1×H×W, 1×H×W or H×W) as an H×W view; ``ValueError`` naming its shape unless it is one frame of the
    grid's size (a batch of frames is refused, not reshaped)."""
    check_tensor(frame, "frame")
    if frame.ndim < 2 or frame.shape[-2:].numel() != frame.numel():
        raise ValueError(f"frame has shape {tuple(frame.shape)}: expected one frame (1×1×H×W, 1×H×W or H×W) of "
                         f"{grid.width}×{grid.height} px (W×H), not a batch")
    x = frame.reshape(frame.shape[-2], frame.shape[-1])
    if tuple(x.shape) != (grid.height, grid.width):
        raise ValueError(f"frame is {x.shape[1]}×{x.shape[0]} px but the grid was made for {grid.width}×{grid.height} px")
    return x


def _check_unit_range(x: torch.Tensor, name: str) -> None:
    """``ValueError`` unless every value of ``x`` is finite and in [0, 1] (naming the count of NaN/inf, or the range
    found): statistics of NaN or of DN values would call such patches informative or clipped."""
    if x.numel() == 0:
        return
    lo, hi = torch.aminmax(x.detach())  # one pass, on any view (NaN propagates into both, ±inf lands in one)
    if not bool(torch.isfinite(lo) & torch.isfinite(hi)):
        check_finite(x, name)
    if lo < 0 or hi > 1:
        raise ValueError(f"{name} must lie in [0, 1] (DN/255), got values in [{lo.item():g}, {hi.item():g}]")


@dataclass
class PatchStats:
    """Cheap per-patch statistics (see the module docstring); all (N,) float32 in DN unless noted.

    Attributes:
        mean_dn: mean intensity Ī.
        clipped_low, clipped_high: fraction of pixels within 0.5 DN of 0 / 255 [–].
        noise_dn: robust noise level σ̂ (Haar-diagonal MAD).
        structure_dn: noise-corrected contrast of the 8×8 block means.
        detail_dn: noise-corrected edge energy of the 2×2-binned patch.
        edge_kurtosis: noise-corrected excess kurtosis γ of the 2×2-binned patch's neighbour differences [–].
        edge_kurtosis_se: its standard error [–] (∞ where the noise explains all the differences).
        blocks_dn: (N, P/8, P/8) 8×8 block means (frame differencing).
    """

    mean_dn: torch.Tensor
    clipped_low: torch.Tensor
    clipped_high: torch.Tensor
    noise_dn: torch.Tensor
    structure_dn: torch.Tensor
    detail_dn: torch.Tensor
    edge_kurtosis: torch.Tensor
    edge_kurtosis_se: torch.Tensor
    blocks_dn: torch.Tensor

    def __len__(self) -> int:
        return int(self.mean_dn.shape[0])


def _clipped_fraction(v: torch.Tensor, extreme: torch.Tensor, level: float, low: bool) -> torch.Tensor:
    """Fraction of pixels <= ``level`` (``low``) or >= ``level`` per patch of (R, P, C, P) ``v``, given the
    per-patch extreme (R, C); counted only on the patches whose extreme reaches the level (one pass over the frame
    where more than half of them do)."""
    r, p, c, _ = v.shape
    reach = ((extreme <= level) if low else (extreme >= level)).reshape(-1)
    n = int(reach.sum())
    if n == 0:
        return torch.zeros(r * c)
    if 2 * n > r * c:
        mask = (v <= level) if low else (v >= level)
        return mask.view(torch.uint8).sum((1, 3), dtype=torch.int32).reshape(r * c).float() / (p * p)
    idx = reach.nonzero()[:, 0]
    sub = v[idx // c, :, idx % c, :]  # (n, P, P): the patches that reach the level
    mask = (sub <= level) if low else (sub >= level)
    out = torch.zeros(r * c)
    out[idx] = mask.view(torch.uint8).sum((1, 2), dtype=torch.int32).float() / (p * p)
    return out


def _statistics(v: torch.Tensor, patch: int) -> PatchStats:
    """Core of :func:`patch_statistics`: ``v`` is (R, P, C, P) in [0, 1] (R·C patches, row-major)."""
    r, _, c, _ = v.shape
    n, h = r * c, patch // 2
    tol = 0.5 / 255.0
    # (two reductions over (P, P) are ~10× faster here than one aminmax along the last dim)
    clipped_low = _clipped_fraction(v, v.amin((1, 3)), tol, low=True)
    clipped_high = _clipped_fraction(v, v.amax((1, 3)), 1.0 - tol, low=False)
    a, b = v[:, 0::2, :, 0::2], v[:, 0::2, :, 1::2]
    cc, d = v[:, 1::2, :, 0::2], v[:, 1::2, :, 1::2]
    ab, cd = a - b, cc - d
    diag = (ab - cd).abs_().mul_(127.5)  # |I00 − I01 − I10 + I11| / 2 in DN, (R, P/2, C, P/2)
    # median over every other row of d (P²/8 samples per patch: ~2 % standard error, half the sort work)
    flat = diag[:, 0::2].permute(0, 2, 1, 3).reshape(n, -1)
    noise = lower_median(flat) / _MAD_NORMAL
    bin2 = (a + b).add_(cc).add_(d).mul_(63.75)  # 2×2 means in DN
    dx = bin2[..., 1:] - bin2[..., :-1]
    dy = bin2[:, 1:] - bin2[:, :-1]
    dx2, dy2 = dx.square_(), dy.square_()  # in place: dx, dy are not used again
    energy = 0.5 * (dx2.sum((1, 3)).reshape(n) / (h * (h - 1)) + dy2.sum((1, 3)).reshape(n) / (h * (h - 1)))
    detail = (energy - 0.5 * noise.pow(2)).clamp_min(0).sqrt()
    m4 = 0.5 * (dx2.square_().sum((1, 3)).reshape(n) / (h * (h - 1)) + dy2.square_().sum((1, 3)).reshape(n) / (h * (h - 1)))
    kurt, kurt_se = edge_kurtosis_from_moments(energy, m4, noise, 2 * h * (h - 1))
    q = h // (BLOCK // 2)
    blocks = bin2.reshape(r, q, BLOCK // 2, c, q, BLOCK // 2).mean((2, 5))  # 8×8 block means (R, P/8, C, P/8)
    blocks = blocks.permute(0, 2, 1, 3).reshape(n, q, q)
    bflat = blocks.reshape(n, -1)
    mean = bflat.mean(1)
    var8 = (bflat - mean[:, None]).pow(2).mean(1)
    structure = (var8 - noise.pow(2) / (BLOCK * BLOCK)).clamp_min(0).sqrt()
    return PatchStats(mean, clipped_low, clipped_high, noise, structure, detail, kurt, kurt_se, blocks.contiguous())


def patch_statistics(patches: torch.Tensor) -> PatchStats:
    """Statistics of N×1×P×P patches in [0, 1] (P divisible by 8), one batched pass; see :class:`PatchStats`.
    ``ValueError`` for NaN/inf or values outside [0, 1] (e.g. DN), naming the count or the range found."""
    x = check_float(check_tensor(patches, "patches"), "patches")
    if x.ndim != 4 or x.shape[1] != 1 or x.shape[2] != x.shape[3] or x.shape[2] % BLOCK or x.shape[2] < BLOCK:
        raise ValueError(f"patches must be N×1×P×P with P a positive multiple of {BLOCK}, got {tuple(x.shape)}")
    n, p = x.shape[0], x.shape[2]
    if n == 0:
        z = torch.zeros(0)
        return PatchStats(z, z, z, z, z, z, z, z, torch.zeros(0, p // BLOCK, p // BLOCK))
    _check_unit_range(x, "patches")
    v = x.float().reshape(n, p, 1, p)
    return _statistics(v, p)


def grid_statistics(frame: torch.Tensor, grid: PatchGrid) -> PatchStats:
    """:func:`patch_statistics` of all patches of ``grid`` in a 1×1×H×W frame, computed on the frame's grid
    region directly (no patch copies); identical results. The frame must be one float frame of the grid's size with
    values in [0, 1] (NaN/inf refused), and the grid's patch a positive multiple of 8 px (``ValueError`` otherwise)."""
    if grid.patch % BLOCK or grid.patch < BLOCK:
        raise ValueError(f"grid.patch = {grid.patch} px: statistics need patches of P×P px with P a positive multiple "
                         f"of {BLOCK}")
    if grid.empty:
        return patch_statistics(torch.zeros(0, 1, grid.patch, grid.patch))
    check_float(check_tensor(frame, "frame"), "frame")
    x = _single_frame(frame, grid)
    _check_unit_range(x, "frame")
    p = grid.patch
    crop = x[grid.y0 : grid.y0 + grid.rows * p, grid.x0 : grid.x0 + grid.cols * p].float()
    return _statistics(crop.reshape(grid.rows, p, grid.cols, p), p)


#: Largest ``SelectionConfig.max_age`` [frames]: 6.8 years of a 10 frames/s stream, "never" in practice (the refresh
#: schedule counts frames in int64 tensors, where a larger age wraps).
MAX_AGE = 2**31 - 1


@dataclass(frozen=True)
class SelectionConfig:
    """Thresholds of the scene-adaptive selection (defaults: module docstring).

    Attributes:
        max_clipped_fraction: a patch with more than this fraction of pixels at 0 (255) DN is "black"
            ("saturated") [–]; default the estimator's own rule.
        min_structure_dn: blur only: a patch with structure contrast below this is "featureless" [DN].
        min_edge_kurtosis: blur only: a patch whose edge kurtosis γ is not two standard errors above this has
            "no edges" [–]; default the estimator's own rule (:data:`camhealth._inputs.MIN_EDGE_KURTOSIS`); ≤ −2 (no
            distribution's excess kurtosis is lower) turns the test off.
        block_sigmas: k of the frame-differencing threshold k·√2·σ̂/8 [–].
        block_tol_dn: smallest block-mean change that counts as a change [DN].
        noise_tol: (absolute [DN], relative [–]) change of σ̂ that counts as a change.
        detail_tol: (absolute [DN], relative [–]) change of the edge energy that counts as a change.
        max_age: a static patch is re-estimated at least every ``max_age`` frames (1 … :data:`MAX_AGE`; 1 = never
            reuse).
        value_tol_noise_dn: coarse → refine: largest range of σ (each source, ξ, total) among the lattice
            neighbours that still allows interpolation [DN] (noise estimators without per-source σ or metadata).
        value_tol_noise_rel: the same for σ_s / σ_s,model and ξ / σ_model when the noise-source estimator has
            metadata: values are compared relative to the closed-form noise model at each patch's mean
            intensity, so patches of different brightness can be interpolated [–].
        value_tol_mtf: the same for each of the 16 MTF values [–].
        cue_tol_mean_dn: a patch is interpolated only if its mean intensity is within the neighbours'
            range ± this [DN] (σ_PN ∝ √Ī).
        cue_tol_noise: (absolute [DN], relative [–]) widening of the neighbours' σ̂ range.
        cue_tol_noise_rel: (absolute, relative) widening of the neighbours' range of σ̂ / σ_model (texture
            cue of the physics-normalised interpolation; clipped fractions must also agree within 0.02).
        cue_tol_detail: (absolute [DN], relative [–]) widening of the neighbours' edge-energy range.
    """

    max_clipped_fraction: float = MAX_CLIPPED_FRACTION
    min_structure_dn: float = MIN_CONTRAST_DN
    min_edge_kurtosis: float = MIN_EDGE_KURTOSIS
    block_sigmas: float = 5.0
    block_tol_dn: float = 4.0
    noise_tol: tuple[float, float] = (0.3, 0.15)
    detail_tol: tuple[float, float] = (0.3, 0.15)
    max_age: int = 16
    value_tol_noise_dn: float = 0.5
    value_tol_noise_rel: float = 0.05
    value_tol_mtf: float = 0.05
    cue_tol_mean_dn: float = 8.0
    cue_tol_noise: tuple[float, float] = (0.3, 0.1)
    cue_tol_noise_rel: tuple[float, float] = (0.05, 0.1)
    cue_tol_detail: tuple[float, float] = (0.3, 0.2)

    def __post_init__(self) -> None:
        def _check(name: str, v: float, lo: float, hi: float | None = None) -> None:
            if not (isinstance(v, (int, float)) and not isinstance(v, bool)) or v != v or v < lo or (hi is not None and v > hi):
                rng = f"[{lo:g}, {hi:g}]" if hi is not None else f">= {lo:g}"
                raise ValueError(f"SelectionConfig.{name} = {v!r} is out of the allowed range {rng}")

        _check("max_clipped_fraction", self.max_clipped_fraction, 0.0, 1.0)
        _check("min_edge_kurtosis", self.min_edge_kurtosis, -3.0)
        for name in ("min_structure_dn", "block_sigmas", "block_tol_dn", "value_tol_noise_dn", "value_tol_noise_rel",
                     "value_tol_mtf", "cue_tol_mean_dn"):
            _check(name, getattr(self, name), 0.0)
        for name in ("noise_tol", "detail_tol", "cue_tol_noise", "cue_tol_noise_rel", "cue_tol_detail"):
            pair = getattr(self, name)
            if not isinstance(pair, (tuple, list)) or len(pair) != 2:
                raise ValueError(f"SelectionConfig.{name} must be a pair (absolute, relative), got {pair!r}")
            _check(f"{name}[0]", pair[0], 0.0)
            _check(f"{name}[1]", pair[1], 0.0)
        if isinstance(self.max_age, bool) or not isinstance(self.max_age, int) or not 1 <= self.max_age <= MAX_AGE:
            raise ValueError(f"SelectionConfig.max_age = {self.max_age!r} must be an integer in [1, {MAX_AGE}] (frames)")


def select_patches(stats: PatchStats, task: str, config: SelectionConfig | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Which patches are informative for ``task`` (``"noise"`` or ``"mtf"``), and why not.

    Returns:
        (mask (N,) bool: informative, code (N,) int8: :data:`ESTIMATED` for informative patches — the
        caller refines it to interpolated/reused — else :data:`BLACK`, :data:`SATURATED` or
        :data:`FEATURELESS` or :data:`NO_EDGES`). Clipping is checked first, black before saturated, then
        featureless before no edges.
    """
    if task not in ("noise", "mtf"):
        raise ValueError(f"task = {task!r} must be 'noise' or 'mtf'")
    cfg = config or SelectionConfig()
    code = torch.full((len(stats),), ESTIMATED, dtype=torch.int8)
    if task == "mtf":
        if cfg.min_edge_kurtosis > -2.0:
            code[~(stats.edge_kurtosis - 2.0 * stats.edge_kurtosis_se >= cfg.min_edge_kurtosis)] = NO_EDGES
        code[stats.structure_dn < cfg.min_structure_dn] = FEATURELESS
    code[stats.clipped_high > cfg.max_clipped_fraction] = SATURATED
    code[stats.clipped_low > cfg.max_clipped_fraction] = BLACK
    return code == ESTIMATED, code


def _changed_by(now: torch.Tensor, ref: torch.Tensor, tol: tuple[float, float]) -> torch.Tensor:
    return (now - ref).abs() > tol[0] + tol[1] * ref.abs()


@dataclass
class StaticRegions:
    """Per-patch references for static-region reuse across frames (see the module docstring).

    Attributes:
        n: number of patches of the grid.
        config: thresholds.
        ref_blocks, ref_noise, ref_detail: statistics of each patch when it was last estimated
            (NaN: never).
        last_frame: frame counter of the last estimate (−1: never).
    """

    n: int
    config: SelectionConfig = field(default_factory=SelectionConfig)
    ref_blocks: torch.Tensor | None = None
    ref_noise: torch.Tensor = field(init=False)
    ref_detail: torch.Tensor = field(init=False)
    last_frame: torch.Tensor = field(init=False)

    def __post_init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget every reference (next frame: everything counts as changed)."""
        self.ref_blocks = None
        self.ref_noise = torch.full((self.n,), float("nan"))
        self.ref_detail = torch.full((self.n,), float("nan"))
        self.last_frame = torch.full((self.n,), -1, dtype=torch.long)

    def changed(self, stats: PatchStats) -> torch.Tensor:
        """(N,) bool: patch content differs from its reference (True where there is none)."""
        if len(stats) != self.n:
            raise ValueError(f"stats describe {len(stats)} patches, the grid has {self.n}")
        if self.ref_blocks is None:
            return torch.ones(self.n, dtype=torch.bool)
        cfg = self.config
        sigma = torch.maximum(stats.noise_dn, torch.nan_to_num(self.ref_noise, nan=0.0))
        limit = torch.clamp_min(cfg.block_sigmas * (2.0**0.5) * sigma / BLOCK, cfg.block_tol_dn)
        moved = (stats.blocks_dn - self.ref_blocks).abs().flatten(1).amax(1) > limit
        noise = _changed_by(stats.noise_dn, self.ref_noise, cfg.noise_tol)
        detail = _changed_by(stats.detail_dn, self.ref_detail, cfg.detail_tol)
        never = self.last_frame < 0
        return never | moved | noise | detail | torch.isnan(self.ref_noise)

    def due(self, frame: int) -> torch.Tensor:
        """(N,) bool: staggered periodic refresh — (frame + i) mod max_age = 0, or older than max_age."""
        m = self.config.max_age
        idx = torch.arange(self.n)
        age = frame - self.last_frame
        return ((frame + idx) % m == 0) | (age >= m)

    def update(self, index: torch.Tensor, stats: PatchStats, frame: int) -> None:
        """Make the current statistics the reference of the patches ``index`` (just estimated)."""
        if self.ref_blocks is None:
            self.ref_blocks = torch.full_like(stats.blocks_dn, float("nan"))
        self.ref_blocks[index] = stats.blocks_dn[index]
        self.ref_noise[index] = stats.noise_dn[index]
        self.ref_detail[index] = stats.detail_dn[index]
        self.last_frame[index] = frame


def lattice_mask(grid: PatchGrid) -> torch.Tensor:
    """(N,) bool: the coarse lattice (even row and even column)."""
    rc = grid.row_col()
    return (rc[:, 0] % 2 == 0) & (rc[:, 1] % 2 == 0)


def _neighbour_maps(grid: PatchGrid, values: torch.Tensor) -> torch.Tensor:
    """(N, 8, K): the values (N, K) of the 8 neighbours of every patch, NaN outside the grid."""
    k = values.shape[1]
    vmap = values.reshape(grid.rows, grid.cols, k)
    pad = torch.full((grid.rows + 2, grid.cols + 2, k), float("nan"), dtype=values.dtype)
    pad[1:-1, 1:-1] = vmap
    shifts = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0)]
    out = [pad[1 + dr : 1 + dr + grid.rows, 1 + dc : 1 + dc + grid.cols] for dr, dc in shifts]
    return torch.stack(out, dim=2).reshape(grid.n, 8, k)


def lattice_neighbours(grid: PatchGrid, values: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(N, 8, K): values (N, K) of the valid coarse-lattice patches among each patch's 8 neighbours, NaN
    elsewhere. For an off-lattice patch these are its 2 (edge-adjacent) or 4 (diagonal) lattice neighbours."""
    if values.ndim != 2 or values.shape[0] != grid.n or valid.shape != (grid.n,):
        raise ValueError(f"values must be ({grid.n}, K) and valid ({grid.n},), got {tuple(values.shape)}, {tuple(valid.shape)}")
    usable = lattice_mask(grid) & valid
    masked = torch.where(usable[:, None], values.float(), torch.full_like(values, float("nan"), dtype=torch.float32))
    return _neighbour_maps(grid, masked)


def coarse_lattice(grid: PatchGrid, candidates: torch.Tensor, informative: torch.Tensor) -> torch.Tensor:
    """(N,) bool: the candidates to estimate first — those on the coarse lattice and those with fewer than
    two informative lattice neighbours (which could never be interpolated)."""
    if grid.empty:
        return candidates.clone()
    ones = torch.ones(grid.n, 1)
    n_nb = torch.isfinite(lattice_neighbours(grid, ones, informative)[..., 0]).sum(1)
    return candidates & (lattice_mask(grid) | (n_nb < 2))


def _nan_range(x: torch.Tensor, dim: int) -> tuple[torch.Tensor, torch.Tensor]:
    finite = torch.isfinite(x)
    lo = torch.where(finite, x, torch.full_like(x, float("inf"))).amin(dim)
    hi = torch.where(finite, x, torch.full_like(x, float("-inf"))).amax(dim)
    return lo, hi


def refine_plan(
    grid: PatchGrid,
    remaining: torch.Tensor,
    values: torch.Tensor,
    valid: torch.Tensor,
    value_tol: torch.Tensor | float,
    cues: Sequence[tuple[torch.Tensor, float, float]],
) -> tuple[torch.Tensor, torch.Tensor]:
    """Which of the ``remaining`` candidates can be interpolated from their lattice neighbours.

    Args:
        grid: the patch grid.
        remaining: (N,) bool, candidates not estimated in the coarse pass.
        values: (N, K) current estimates (NaN where none); components that are NaN for every neighbour
            (e.g. σ per source of a total-noise estimator) are ignored.
        valid: (N,) bool, patches whose ``values`` are current (estimated this frame or reused).
        value_tol: largest allowed range of each value among the neighbours (scalar or (K,)).
        cues: (cue (N,), absolute tolerance, relative tolerance) triples — the patch's cue must lie inside
            [min − tol, max + tol] of its neighbours' cues, tol = absolute + relative·max|neighbour cue|.

    Returns:
        (interpolate (N,) bool, interpolated values (N, K); rows not interpolated are NaN).
    """
    n, k = values.shape
    nb = lattice_neighbours(grid, values, valid)  # N, 8, K
    has = torch.isfinite(nb).any(2)  # N, 8: a usable neighbour
    count = has.sum(1)
    lo, hi = _nan_range(nb, 1)  # N, K
    spread = torch.where(torch.isfinite(hi - lo), hi - lo, torch.zeros_like(hi))
    tol = torch.as_tensor(value_tol, dtype=torch.float32).expand(k)
    agree = (spread <= tol).all(1)
    ok = remaining & (count >= 2) & agree
    for cue, tol_abs, tol_rel in cues:
        c = cue.float().reshape(n, 1)
        cn = _neighbour_maps(grid, c)[..., 0]  # N, 8
        cn = torch.where(has, cn, torch.full_like(cn, float("nan")))
        clo, chi = _nan_range(cn, 1)
        scale = torch.maximum(clo.abs(), chi.abs())
        w = tol_abs + tol_rel * torch.where(torch.isfinite(scale), scale, torch.zeros_like(scale))
        ok &= (c[:, 0] >= clo - w) & (c[:, 0] <= chi + w)
    mean = torch.nanmean(nb, dim=1)
    out = torch.where(ok[:, None], mean, torch.full_like(mean, float("nan")))
    return ok, out


def _sector_ids(grid: PatchGrid, k: int) -> torch.Tensor:
    """(N,) long: sector of every patch for ``k`` sectors — a rows × cols split of the grid with
    rows·cols >= k chosen close to the grid's aspect (the split whose sectors come closest to square: the least
    |rows/r − cols/c|, the fewest sector rows among equals); 1 × k where no split fits the grid; sectors beyond k merge
    into the last."""
    best: tuple[int, int] | None = None
    best_aspect = math.inf
    for r in range(1, k + 1):
        c = -(-k // r)
        if r <= max(grid.rows, 1) and c <= max(grid.cols, 1):
            aspect = abs((grid.rows / r) - (grid.cols / c))
            if best is None or aspect < best_aspect:
                best, best_aspect = (r, c), aspect
    r, c = best if best is not None else (1, k)
    rc = grid.row_col()
    sr = (rc[:, 0] * r) // max(grid.rows, 1)
    sc = (rc[:, 1] * c) // max(grid.cols, 1)
    return (sr * c + sc).clamp_max(k - 1)


#: A patch whose noise level σ̂ (:class:`PatchStats` ``noise_dn``) is below this fraction of the camera's closed-form
#: σ_Total at its mean intensity is "quiet" (:func:`quiet_patches`): a real patch reads so only with a gain about
#: 12 dB below the metadata's, an overlay or masked area with no sensor noise reads 0.
QUIET_FRACTION = 0.25


def quiet_patches(stats: PatchStats, model_sigma_dn: torch.Tensor) -> torch.Tensor:
    """(N,) bool: the patches whose noise level σ̂ is below :data:`QUIET_FRACTION` of ``model_sigma_dn`` (N,), the
    closed-form σ_Total [DN] of the camera's metadata at each patch's mean intensity — patches with (nearly) no
    sensor noise, such as a noiseless overlay; see :func:`sample_patches`."""
    if model_sigma_dn.shape != stats.noise_dn.shape:
        raise ValueError(f"model_sigma_dn must be {tuple(stats.noise_dn.shape)}, got {tuple(model_sigma_dn.shape)}")
    return stats.noise_dn < QUIET_FRACTION * model_sigma_dn.to(stats.noise_dn.dtype)


def sample_patches(
    grid: PatchGrid, stats: PatchStats, informative: torch.Tensor, k: int, task: str, last_sampled: torch.Tensor,
    quiet: torch.Tensor | None = None,
) -> torch.Tensor:
    """Indices (≤ ``k``, long) of the patches to estimate in sampled mode (see the module docstring).

    Args:
        grid: the patch grid.
        stats: statistics of its patches.
        informative: (N,) bool, candidates (from :func:`select_patches`).
        k: number of samples (>= 1).
        task: ``"noise"`` (flattest, spread over intensity) or ``"mtf"`` (edges, spread over the frame).
        last_sampled: (N,) long, frame counter of each patch's last sample (−1: never) — the rotation.
        quiet: (N,) bool or ``None`` — noise only: patches far quieter than the camera's closed-form noise
            (:func:`quiet_patches`: a noiseless overlay, a masked area). Where any other candidate is left they
            are not sampled (strata are formed over the others), so a frame whose flattest patches are an overlay
            samples the camera's own patches and its pooled answer is not outvoted by refused ones; a frame quiet
            everywhere (a denoised stream, a noisier camera's metadata) is sampled as before and reported as such.
    """
    if task not in ("noise", "mtf"):
        raise ValueError(f"task = {task!r} must be 'noise' or 'mtf'")
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise ValueError(f"k = {k!r} must be an integer >= 1 (patches per frame)")
    if informative.shape != (grid.n,) or last_sampled.shape != (grid.n,):
        raise ValueError(f"informative and last_sampled must be ({grid.n},), got {tuple(informative.shape)}, "
                         f"{tuple(last_sampled.shape)}")
    if quiet is not None and (quiet.shape != (grid.n,) or quiet.dtype != torch.bool):
        raise ValueError(f"quiet must be a ({grid.n},) bool tensor, got {tuple(quiet.shape)} {quiet.dtype}")
    if task == "noise" and quiet is not None and bool((informative & ~quiet).any()):
        informative = informative & ~quiet
    cand = informative.nonzero()[:, 0]
    if cand.numel() <= k:
        return cand
    if task == "noise":
        quality = -(stats.structure_dn + stats.detail_dn)  # flatter is better
        order = cand[torch.argsort(stats.mean_dn[cand], stable=True)]
        strata = torch.empty(grid.n, dtype=torch.long)
        strata[order] = (torch.arange(order.numel()) * k) // order.numel()
    else:
        quality = stats.detail_dn.clone()  # more edges is better
        strata = _sector_ids(grid, k)
    eligible = 0.5 if task == "noise" else 1.0  # fraction of a stratum (by quality) that may be sampled
    chosen: list[int] = []
    last = last_sampled.tolist()
    q = quality.tolist()
    s_ids = strata[cand].tolist()
    members: dict[int, list[int]] = {}
    for i, s in zip(cand.tolist(), s_ids):
        members.setdefault(s, []).append(i)
    for s in range(k):
        m = members.get(s)
        if not m:
            continue
        m.sort(key=lambda i: -q[i])
        good = m[: max(1, math.ceil(eligible * len(m)))]
        chosen.append(min(good, key=lambda i: (last[i], -q[i])))
    if len(chosen) < k:  # empty strata/sectors: the best remaining candidates, oldest sample first
        taken = set(chosen)
        rest = sorted((i for i in cand.tolist() if i not in taken), key=lambda i: (last[i], -q[i]))
        chosen.extend(rest[: k - len(chosen)])
    return torch.tensor(sorted(chosen), dtype=torch.long)


def status_counts(code: torch.Tensor) -> dict[str, int]:
    """Number of patches per status name (every name present, 0 if unused); a code outside 0 … len(STATUS_NAMES) − 1
    is a ``ValueError`` naming it."""
    codes = check_tensor(code, "code").long().reshape(-1)
    if codes.numel():
        lo, hi = torch.aminmax(codes)
        if lo < 0 or hi >= len(STATUS_NAMES):
            bad = int(lo) if lo < 0 else int(hi)
            raise ValueError(f"status code {bad} is out of the allowed range [0, {len(STATUS_NAMES) - 1}] "
                             f"(STATUS_NAMES: {list(STATUS_NAMES)})")
    counts = torch.bincount(codes, minlength=len(STATUS_NAMES)).tolist()
    return {name: int(c) for name, c in zip(STATUS_NAMES, counts)}
