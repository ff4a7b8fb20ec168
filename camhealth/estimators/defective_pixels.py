"""Defective pixels (hot, stuck and dead pixels) and impulse noise, from one patch.

Model: I(y, x) = S(y, x) + n(y, x) + D·δ(y − y₀, x − x₀) [DN]: besides the scene S and the pixel noise n
(conventions.md), a pixel carries an offset D of its own that none of its neighbours shares — a hot pixel (a dark
current far above the sensor's mean, D > 0, growing with exposure and temperature), a pixel stuck bright or dark, a
dead pixel (D < 0), or a transient impulse (a particle hit, a transmission error). None of the sensor model's sources
makes it, so the metadata never predict it; the noise-level fits of :mod:`camhealth.estimators.physics_noise` are
robust to it (medians and midmeans) and do not count it in σ_Total.

The scene reaches the pixels through the lens, whose point-spread function covers more than one pixel, and natural
scenes rarely hold a structure one pixel wide that stands above or below *every* neighbour by much more than the
noise; a defect does. **Detected** where the pixel exceeds the largest of its 8 neighbours (hot), or falls below the
smallest (dark), by more than

    t = k·max(s, σ_n),   k = :data:`DEFECT_SIGMAS`, and at least :data:`MIN_DEFECT_DN`,

with σ_n the patch's pixel noise (median |d| / 0.6745 of its diagonal Haar details d, with the 8-bit rounding's 1/12
DN²) and s the scatter of the other pixels of the pixel's :data:`WINDOW`×:data:`WINDOW` window about the plane that
fits them best (shading and gradients do not raise it; signal-dependent noise, texture and edges do, so a defect in a
textured area must stand out further). The pixels that are themselves candidates (a step above k·σ_n) are left out of
every window's fit, so that defects a few pixels apart do not hide each other. For Gaussian noise alone the chance that a
pixel exceeds the largest of 8 like it by 6 σ is 2.5·10⁻¹¹; no pixel of 256 patches of white noise (σ 0.5–30 DN,
8-bit) is flagged.

**Clipped noise.** At 0 DN (a black level at or below zero) and at 255 DN (saturation) the noise is censored: the
clipped pixels carry no spread, so σ_n and s read it too low (on a black frame with σ = 3 DN, σ_n ≈ 1.5 DN) and noise
peaks amid clipped pixels would pass the test. Where a candidate's :data:`CENSOR_WINDOW`×:data:`CENSOR_WINDOW` window
(candidates left out) holds pixels at the bound its step departs from (0 DN for a hot candidate, 255 DN for a dark
one), the local noise is taken as that of a flat N(μ, σ) censored at the bound b: with the share p₀ of the window's
pixels at b and the mean distance m₁ = E[|v − b| | v not at b] of the others,

    p₀ = Φ(α),   m₁ = σ·(λ(α) − α)   ⇒   σ_c = m₁ / (λ(α) − α),   α = Φ⁻¹(p₀),  λ(α) = φ(α) / (1 − Φ(α)),

and the threshold uses max(s, σ_n, σ_c). Scene structure in the window raises σ_c (a defect next to clipped
structure must stand out further), and measuring m₁ from b rather than from the rounding step b ± 0.5 DN raises it a
little more: both err towards a miss. Measured, pixels flagged per million tested (64 patches of 128 px of white
noise, 8-bit): σ 2–8 DN at mean −6…1 DN and σ 5–40 DN at mean 251…262 DN: 0–1; at mean −10 DN 16 (σ 5 DN, 98 % of
the pixels at 0 DN) and 2 (σ 8 DN); at mean 265 DN 14 (σ 5 DN) and 0 (σ 20, 40 DN). With σ_n and s alone the same
frames gave up to 5800. A window whose pixels are *all* at the bound shows no noise at all; there the test uses σ_n
(a hot pixel on a noiseless black frame is found), so noise that is almost entirely clipped can still yield such
peaks. The price is sensitivity where the noise is clipped: on a black frame with σ = 3 DN a hot pixel is found in
90 % of cases at 30 DN (10 σ) and always at 60 DN, and on a saturated one with σ = 5 DN a dead pixel 30 DN below
255 DN in 5 % and at 60 DN always.

Two defects side by side (a cluster) hide each other from this test, and a hot pixel in a
saturated area or a dead one in a black area has nothing to stand out from. A patch where more than
:data:`MAX_CANDIDATE_SHARE` of the pixels are candidates holds a regular pattern of local extremes (a raw Bayer mosaic
read as gray), not isolated defects: it is not tested.

What it cannot tell from one frame: a scene's own isolated point (a specular glint, a distant light, a star) or a
pixel-sized peak of a fine texture reads as a defect. On the robustness benchmark's photographs and street frames
with their right noise (``python -m camhealth.bench robustness``) that is 5 pixels per million tested on average, at
most 95 per million on a frame; a defect hidden in texture, next to an edge or pushed into clipping is missed
(the benchmark's share found). A defect stays at its pixel from frame to frame while the scene moves;
:class:`camhealth.monitor.Monitor` counts the pixels flagged at the same place in several frames.

:func:`repair_defective_pixels` replaces each one by the mean of its neighbours (what a camera's defect-pixel
correction does). The MTF estimator reads its patches so repaired: its edge check reads isolated impulses as sparse
edges and its network as fine detail (``python -m camhealth.bench robustness --task mtf``, the defects table).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch

from camhealth._inputs import haar_noise_dn
from camhealth._validation import check_float, check_image

__all__ = ["DefectivePixels", "defective_pixels", "repair_defective_pixels", "DEFECT_SIGMAS", "MIN_DEFECT_DN", "WINDOW",
           "MAX_CANDIDATE_SHARE", "CENSOR_WINDOW"]

#: Step above the largest (below the smallest) of the 8 neighbours, in local σ, from which a pixel is a defect.
DEFECT_SIGMAS = 6.0
#: Smallest step [DN] reported as a defect: below it a pixel's offset hardly changes what a task sees.
MIN_DEFECT_DN = 8.0
#: Side [px] of the window whose other pixels give the local scatter s.
WINDOW = 5
#: The largest share of a patch's tested pixels that may be candidates (a step over all 8 neighbours beyond k·σ_n):
#: above it the local extremes are a regular pattern, not isolated defects — a 1-px grid whose steps the diagonal
#: details do not see (a raw Bayer mosaic read as gray makes one) has half of its pixels so — and the patch is not
#: tested (``checked`` 0). The robustness benchmark's densest defects, 1 % of the pixels, stay far below.
MAX_CANDIDATE_SHARE = 0.05
#: Side [px] of the window whose pixels give the censored-noise level σ_c next to clipped pixels (module docstring):
#: 120 pixels, so that p₀ and m₁ are measured where most of the noise is clipped.
CENSOR_WINDOW = 11
_QUANT_VAR = 1.0 / 12.0  # DN²: rounding to whole DN


@dataclass
class DefectivePixels:
    """Defective pixels of B patches.

    Attributes:
        hot: (B,) int64, pixels above all 8 neighbours by more than the threshold.
        dark: (B,) int64, pixels below all 8 neighbours by more than the threshold.
        checked: (B,) int64, pixels tested (all but the one-pixel border; 0 where more than
            :data:`MAX_CANDIDATE_SHARE` of them are candidates: a regular pattern, not isolated defects).
        mask: (B, 1, H, W) int8: +1 hot, −1 dark, 0 otherwise (the border 0).
    """

    hot: torch.Tensor
    dark: torch.Tensor
    checked: torch.Tensor
    mask: torch.Tensor

    @property
    def fraction(self) -> torch.Tensor:
        """(B,) float64, (hot + dark) / checked."""
        return (self.hot + self.dark).double() / self.checked.clamp_min(1).double()


@functools.lru_cache(maxsize=8)
def _ring_offsets(device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """(dy, dx) (8,) long of the 8 neighbours."""
    ring = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))
    return torch.tensor([r[0] for r in ring], device=device), torch.tensor([r[1] for r in ring], device=device)


def _gather(q: torch.Tensor, where: torch.Tensor, dy: torch.Tensor, dx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Values of B×1×H×W ``q`` at ``where`` ((N, 3): b, y, x) shifted by (dy, dx) (M,) → (N, M), and whether each
    shifted pixel lies inside the patch (outside: value of the nearest border pixel, flagged False)."""
    h, w = q.shape[-2:]
    y, x = where[:, 1:2] + dy, where[:, 2:3] + dx
    inside = (y >= 0) & (y < h) & (x >= 0) & (x < w)
    flat = where[:, 0:1] * (h * w) + y.clamp(0, h - 1) * w + x.clamp(0, w - 1)
    return q.reshape(-1)[flat], inside


@functools.lru_cache(maxsize=8)
def _window_offsets(device: torch.device, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(dy, dx) (M,) long of a WINDOW×WINDOW window without its centre, and the plane's design [1, dy, dx] (M, 3)."""
    pad = WINDOW // 2
    off = torch.arange(-pad, pad + 1, device=device)
    dy, dx = (t.reshape(-1) for t in torch.meshgrid(off, off, indexing="ij"))
    ring = (dy != 0) | (dx != 0)
    dy, dx = dy[ring], dx[ring]
    return dy, dx, torch.stack([torch.ones_like(dy), dy, dx], 1).to(dtype)


@functools.lru_cache(maxsize=8)
def _RIDGE(device: torch.device, dtype: torch.dtype) -> torch.Tensor:  # noqa: N802 - a constant
    """1e-6·I (3×3): keeps the normal equations solvable where a window has few pixels left."""
    return 1e-6 * torch.eye(3, dtype=dtype, device=device)


def _window_scale(q: torch.Tensor, keep: torch.Tensor, where: torch.Tensor) -> torch.Tensor:
    """σ [DN] about the plane that fits best the pixels of each WINDOW×WINDOW window around ``where`` ((N, 3): b,
    y, x) that ``keep`` marks, the centre left out (weighted least squares, Σ weights − 3 degrees of freedom; ∞ where
    fewer than 8 pixels remain): the local noise and texture, with the scene's shading and gradients taken out."""
    dy, dx, design = _window_offsets(q.device, q.dtype)
    v, inside = _gather(q, where, dy, dx)  # (N, WINDOW² − 1)
    wt = (_gather(keep, where, dy, dx)[0] & inside).to(q.dtype)
    xw = design * wt.unsqueeze(-1)  # (N, M, 3)
    normal = torch.baddbmm(_RIDGE(q.device, q.dtype), xw.transpose(1, 2), design.expand(xw.shape[0], -1, -1))
    beta = torch.linalg.solve(normal, (xw * v.unsqueeze(-1)).sum(1))  # (N, 3)
    ss = (wt * (v - beta @ design.t()).square()).sum(1)
    dof = wt.sum(1) - 3.0
    return torch.where(dof >= 5.0, (ss / dof.clamp_min(1.0)).sqrt(), torch.full_like(ss, float("inf")))


@functools.lru_cache(maxsize=8)
def _censor_offsets(device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """(dy, dx) (M,) long of a CENSOR_WINDOW×CENSOR_WINDOW window without its centre."""
    pad = CENSOR_WINDOW // 2
    off = torch.arange(-pad, pad + 1, device=device)
    dy, dx = (t.reshape(-1) for t in torch.meshgrid(off, off, indexing="ij"))
    ring = (dy != 0) | (dx != 0)
    return dy[ring], dx[ring]


def _censored_scale(q: torch.Tensor, keep: torch.Tensor, where: torch.Tensor, hot: torch.Tensor) -> torch.Tensor:
    """σ_c [DN] of a flat N(μ, σ) censored at the bound each candidate departs from (0 DN where ``hot``, else 255 DN),
    from the pixels of its CENSOR_WINDOW×CENSOR_WINDOW window that ``keep`` marks (module docstring): σ_c = m₁ / (λ(α) −
    α), α = Φ⁻¹(p₀). 0 where no window pixel is at the bound (nothing censored) or every one is (no noise to see)."""
    dy, dx = _censor_offsets(q.device)
    v, inside = _gather(q, where, dy, dx)  # (N, CENSOR_WINDOW² − 1)
    wt = _gather(keep, where, dy, dx)[0] & inside
    dist = torch.where(hot.unsqueeze(1), v, 255.0 - v)  # distance from the bound, ≤ 0 at it
    at = (wt & (dist <= 0)).sum(1).to(q.dtype)
    free = wt & (dist > 0)
    n_free = free.sum(1).to(q.dtype)
    censored = (at > 0) & (n_free > 0)
    p0 = (at / (at + n_free).clamp_min(1.0)).clamp(1e-6, 1.0 - 1e-6)
    alpha = torch.special.ndtri(p0)
    mills = torch.exp(-0.5 * alpha * alpha) / (math.sqrt(2.0 * math.pi) * torch.special.ndtr(-alpha))  # λ(α)
    m1 = (dist * free).sum(1) / n_free.clamp_min(1.0)
    return torch.where(censored, m1 / (mills - alpha), torch.zeros_like(m1))


#: Offsets (y, x) of a pixel's 8 neighbours.
_RING_DY = torch.tensor([-1, -1, -1, 0, 0, 1, 1, 1])
_RING_DX = torch.tensor([-1, 0, 1, -1, 1, -1, 0, 1])
#: Share of the pixels above which :func:`_candidates` reads every pixel's 8 neighbours at once instead of gathering
#: them at the pixels its prefilter keeps (a regular pattern whose steps the noise estimate does not see).
_DENSE_SHARE = 0.05


def _candidates(q: torch.Tensor, lower: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The interior pixels of B×1×H×W images ``q`` [DN] whose step over all 8 neighbours exceeds ``lower`` (B,) [DN]:
    (where (N, 3): patch, y, x; step (N,): the larger of c − max₈ and min₈ − c; up (N,): c − max₈), in row-major order.

    A step over all 8 is one over the left and the upper neighbour first, so the 8 are read only where both are
    (edges and corners; few pixels), unless more than :data:`_DENSE_SHARE` of them are: then for every pixel at once
    (3-wide row extremes above and below, and the left and right neighbours). Both give the same values."""
    b = q.shape[0]
    c, low = q[..., 1:-1, 1:-1], lower.view(b, 1, 1, 1)
    pre = torch.minimum((c - q[..., 1:-1, :-2]).abs_(), (c - q[..., :-2, 1:-1]).abs_()) > low
    n_pre = int(pre.sum())
    if n_pre <= _DENSE_SHARE * pre.numel():
        at = pre.nonzero()  # (P, 4): b, 0, y − 1, x − 1
        pb, py, px = at[:, 0], at[:, 2] + 1, at[:, 3] + 1
        ring = q[pb.unsqueeze(1), 0, py.unsqueeze(1) + _RING_DY.to(q.device), px.unsqueeze(1) + _RING_DX.to(q.device)]
        centre = q[pb, 0, py, px]
        up, down = centre - ring.amax(1), ring.amin(1) - centre
        step = torch.maximum(up, down)
        keep = step > lower[pb]
        return torch.stack([pb[keep], py[keep], px[keep]], 1), step[keep], up[keep]
    left, right = q[..., 1:-1, :-2], q[..., 1:-1, 2:]
    row_max = torch.maximum(torch.maximum(q[..., :-2], q[..., 1:-1]), q[..., 2:])
    row_min = torch.minimum(torch.minimum(q[..., :-2], q[..., 1:-1]), q[..., 2:])
    up_all = c - torch.maximum(torch.maximum(row_max[..., :-2, :], row_max[..., 2:, :]), torch.maximum(left, right))
    down_all = torch.minimum(torch.minimum(row_min[..., :-2, :], row_min[..., 2:, :]), torch.minimum(left, right)) - c
    step_all = torch.maximum(up_all, down_all)
    at = (step_all > low).nonzero()
    flat = at[:, 0] * c[0].numel() + at[:, 2] * c.shape[-1] + at[:, 3]
    return (torch.stack([at[:, 0], at[:, 2] + 1, at[:, 3] + 1], 1), step_all.reshape(-1)[flat], up_all.reshape(-1)[flat])


def defective_pixels(patches: torch.Tensor, noise_dn: torch.Tensor | None = None) -> DefectivePixels:
    """Hot, stuck and dead pixels of B×1×H×W patches in [0, 1] (DN/255; H, W ≥ 3; module docstring). Any float dtype;
    computed in float32 (float64 input in float64). The window's fit is made only at the candidates, the pixels whose
    step over all 8 neighbours exceeds k·σ_n and :data:`MIN_DEFECT_DN` (few in most patches). ``noise_dn``: the patches'
    σ̂ [DN] (B,) of :func:`camhealth._inputs.haar_noise_dn` where the caller has it already (computed here otherwise); a
    real tensor (or sequence) of one finite σ ≥ 0 per patch (``TypeError`` for a string, a bool or a non-numeric type).
    An empty batch (B = 0) gives empty counts. Returns :class:`DefectivePixels`.

    Raises ``TypeError`` for a non-tensor or a non-float dtype, ``ValueError`` for a wrong shape, NaN/inf or values
    outside [0, 1] (DN-scaled input would shrink :data:`MIN_DEFECT_DN` to 8/255 DN)."""
    if not isinstance(patches, torch.Tensor):
        raise TypeError(f"patches must be a torch.Tensor, got {type(patches).__name__}")
    if patches.ndim != 4 or patches.shape[1] != 1 or min(patches.shape[-2:]) < 3:
        raise ValueError(f"defective_pixels needs B×1×H×W patches with H, W ≥ 3, got {tuple(patches.shape)}")
    if patches.shape[0] == 0:
        check_float(patches, "patches")
    else:
        check_image(patches, "patches", channels=1, value_range=(0.0, 1.0))
    dtype = torch.float64 if patches.dtype == torch.float64 else torch.float32
    q = patches.detach().to(dtype) * 255.0
    b, _, h, w = q.shape
    mask = torch.zeros(b, 1, h, w, dtype=torch.int8, device=q.device)
    if noise_dn is None:
        sigma = haar_noise_dn(patches.detach())
    else:
        if isinstance(noise_dn, (bool, str, bytes)) or (isinstance(noise_dn, torch.Tensor)
                                                        and (noise_dn.dtype == torch.bool or noise_dn.is_complex())):
            raise TypeError(f"defective_pixels: noise_dn must be a real tensor of σ [DN] per patch, got {noise_dn!r} "
                            f"({type(noise_dn).__name__})")
        try:
            sigma = torch.as_tensor(noise_dn, device=q.device)
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(f"defective_pixels: noise_dn must be a real tensor of σ [DN] per patch, got "
                            f"{type(noise_dn).__name__}") from None
        if sigma.dtype == torch.bool or sigma.is_complex():
            raise TypeError(f"defective_pixels: noise_dn must be a real tensor of σ [DN] per patch, got dtype {sigma.dtype}")
        if sigma.numel() != b or not bool(torch.isfinite(sigma).all()) or bool((sigma < 0).any()):
            raise ValueError(f"defective_pixels: noise_dn must hold one finite σ ≥ 0 [DN] per patch ({b}), got shape "
                             f"{tuple(sigma.shape)} with values {sigma.flatten()[:4].tolist()}")
        sigma = sigma.reshape(b)
    floor = (sigma.to(q.dtype).square() + _QUANT_VAR).sqrt()
    # candidates: a step over all 8 neighbours beyond k σ_n and MIN_DEFECT_DN (a lower bound of the threshold)
    lower = torch.clamp(DEFECT_SIGMAS * floor, min=MIN_DEFECT_DN)
    where, step, up = _candidates(q, lower)
    tested = (h - 2) * (w - 2)
    pattern = torch.bincount(where[:, 0], minlength=b) > MAX_CANDIDATE_SHARE * tested
    if bool(pattern.any()):  # a regular pattern of local extremes: those patches cannot tell a defect
        alone = ~pattern[where[:, 0]]
        where, step, up = where[alone], step[alone], up[alone]
    hot = dark = torch.zeros(b, dtype=torch.int64, device=q.device)
    if where.shape[0]:
        keep = torch.ones_like(q, dtype=torch.bool)  # the window's fit leaves out every candidate
        keep[where[:, 0], 0, where[:, 1], where[:, 2]] = False
        scale = torch.maximum(_window_scale(q, keep, where), floor[where[:, 0]])
        scale = torch.maximum(scale, _censored_scale(q, keep, where, up > 0))  # noise clipped at 0 or 255 DN
        found = step > DEFECT_SIGMAS * scale
        hit, bright = where[found], up[found] > 0  # above every neighbour: hot
        mask[hit[:, 0], 0, hit[:, 1], hit[:, 2]] = torch.where(bright, 1, -1).to(torch.int8)
        hot = torch.bincount(hit[bright, 0], minlength=b)
        dark = torch.bincount(hit[~bright, 0], minlength=b)
    checked = torch.where(pattern, 0, tested).to(device=q.device, dtype=torch.int64)
    return DefectivePixels(hot, dark, checked, mask)


def repair_defective_pixels(patches: torch.Tensor, noise_dn: torch.Tensor | None = None) -> tuple[torch.Tensor, DefectivePixels]:
    """B×1×H×W patches in [0, 1] with every defective pixel (:func:`defective_pixels`, ``noise_dn`` as there) replaced
    by the mean of its 8 neighbours that are not defective themselves (of all 8 where every one is), in the patches'
    dtype; the input is returned unchanged (the same tensor) where none is found. Returns (patches,
    :class:`DefectivePixels`)."""
    found = defective_pixels(patches, noise_dn)
    bad = found.mask != 0
    at = bad.nonzero()  # (N, 4): patch, 0, y, x — only these pixels change, so only their neighbours are read
    if not at.shape[0]:
        return patches, found
    x = patches.detach().to(torch.float64 if patches.dtype == torch.float64 else torch.float32)
    h, w = x.shape[-2:]
    ny, nx = at[:, 2:3] + _RING_DY.to(x.device), at[:, 3:4] + _RING_DX.to(x.device)  # (N, 8)
    inside = (ny >= 0) & (ny < h) & (nx >= 0) & (nx < w)
    ny, nx = ny.clamp(0, h - 1), nx.clamp(0, w - 1)  # out of the patch: the edge pixel's value (replicate)
    b = at[:, :1].expand_as(ny)
    vals = x[b, 0, ny, nx]
    good = (inside & ~bad[b, 0, ny, nx]).to(x.dtype)
    count = good.sum(1)
    fill = torch.where(count > 0, (vals * good).sum(1) / count.clamp_min(1.0), vals.mean(1))
    out = patches.detach().clone()
    out[at[:, 0], 0, at[:, 2], at[:, 3]] = fill.to(patches.dtype)
    return out, found
