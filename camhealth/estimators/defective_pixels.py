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

with σ_n the patch's pixel noise (1.4826·MAD of its diagonal Haar details, with the 8-bit rounding's 1/12 DN²) and s
the scatter of the other pixels of the pixel's :data:`WINDOW`×:data:`WINDOW` window about the plane that fits them
best (shading and gradients do not raise it; signal-dependent noise, texture and edges do, so a defect in a textured
area must stand out further). The pixels that are themselves candidates (a step above k·σ_n) are left out of every
window's fit, so that defects a few pixels apart do not hide each other. For Gaussian noise alone the chance that a
pixel exceeds the largest of 8 like it by 6 σ is 2.5·10⁻¹¹; no pixel of 256 patches of white noise (σ 0.5–30 DN,
8-bit) is flagged. Two defects side by side (a cluster) hide each other from this test, and a hot pixel in a
saturated area or a dead one in a black area has nothing to stand out from.

What it cannot tell from one frame: a scene's own isolated point (a specular glint, a distant light, a star) or a
pixel-sized peak of a fine texture reads as a defect. On the robustness benchmark's photographs and street frames
with their right noise (``python -m camhealth.bench robustness``) that is 5 pixels per million tested on average, at
most 95 per million on a frame; a defect hidden in texture, next to an edge or pushed into clipping is missed
(the benchmark's share found). A defect stays at its pixel from frame to frame while the scene moves;
:class:`camhealth.monitor.Monitor` counts the pixels flagged at the same place in several frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

__all__ = ["DefectivePixels", "defective_pixels", "DEFECT_SIGMAS", "MIN_DEFECT_DN", "WINDOW"]

#: Step above the largest (below the smallest) of the 8 neighbours, in local σ, from which a pixel is a defect.
DEFECT_SIGMAS = 6.0
#: Smallest step [DN] reported as a defect: below it a pixel's offset hardly changes what a task sees.
MIN_DEFECT_DN = 8.0
#: Side [px] of the window whose other pixels give the local scatter s.
WINDOW = 5
_QUANT_VAR = 1.0 / 12.0  # DN²: rounding to whole DN


@dataclass
class DefectivePixels:
    """Defective pixels of B patches.

    Attributes:
        hot: (B,) int64, pixels above all 8 neighbours by more than the threshold.
        dark: (B,) int64, pixels below all 8 neighbours by more than the threshold.
        checked: (B,) int64, pixels tested (all but the one-pixel border).
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


def _max_min8(q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Largest and smallest of each interior pixel's 8 neighbours (B×1×(H−2)×(W−2)): the 3-wide row maxima above
    and below, and the left and right neighbours."""
    row_max = torch.maximum(torch.maximum(q[..., :-2], q[..., 1:-1]), q[..., 2:])  # (…, H, W−2)
    row_min = torch.minimum(torch.minimum(q[..., :-2], q[..., 1:-1]), q[..., 2:])
    left, right = q[..., 1:-1, :-2], q[..., 1:-1, 2:]
    mx = torch.maximum(torch.maximum(row_max[..., :-2, :], row_max[..., 2:, :]), torch.maximum(left, right))
    mn = torch.minimum(torch.minimum(row_min[..., :-2, :], row_min[..., 2:, :]), torch.minimum(left, right))
    return mx, mn


def _noise_floor_dn(q: torch.Tensor) -> torch.Tensor:
    """(B,) robust σ [DN] of each patch's pixel noise: 1.4826·MAD of its diagonal 2×2 Haar details (edges and shading
    barely reach them, a median ignores the rest), with the 8-bit rounding's 1/12 DN² added."""
    h, w = q.shape[-2] // 2 * 2, q.shape[-1] // 2 * 2
    x = q[:, 0, :h, :w]
    d = ((x[:, 0::2, 0::2] - x[:, 0::2, 1::2] - x[:, 1::2, 0::2] + x[:, 1::2, 1::2]) / 2.0).flatten(1)
    mad = (d - d.median(1, keepdim=True).values).abs().median(1).values * 1.4826
    return (mad.square() + _QUANT_VAR).sqrt()


def _window_scale(q: torch.Tensor, keep: torch.Tensor, where: torch.Tensor) -> torch.Tensor:
    """σ [DN] about the plane that fits best the pixels of each WINDOW×WINDOW window around ``where`` ((N, 3): b,
    y, x) that ``keep`` marks, the centre left out (weighted least squares, Σ weights − 3 degrees of freedom; ∞ where
    fewer than 8 pixels remain): the local noise and texture, with the scene's shading and gradients taken out."""
    pad = WINDOW // 2
    qp = F.pad(q[:, 0], (pad, pad, pad, pad))
    kp = F.pad(keep[:, 0].to(q.dtype), (pad, pad, pad, pad))
    off = torch.arange(-pad, pad + 1, device=q.device)
    dy, dx = (t.reshape(-1) for t in torch.meshgrid(off, off, indexing="ij"))
    ring = (dy != 0) | (dx != 0)
    dy, dx = dy[ring], dx[ring]
    bi, yi, xi = where[:, 0:1], where[:, 1:2] + pad + dy, where[:, 2:3] + pad + dx  # (N, WINDOW² − 1), padded coords
    v, wt = qp[bi, yi, xi], kp[bi, yi, xi]
    design = torch.stack([torch.ones_like(dy), dy, dx], 1).to(q.dtype)  # (M, 3)
    xw = design.unsqueeze(0) * wt.unsqueeze(-1)  # (N, M, 3)
    normal = xw.transpose(1, 2) @ design + 1e-6 * torch.eye(3, dtype=q.dtype, device=q.device)
    beta = torch.linalg.solve(normal, (xw * v.unsqueeze(-1)).sum(1))  # (N, 3)
    ss = (wt * (v - beta @ design.t()).square()).sum(1)
    dof = wt.sum(1) - 3.0
    return torch.where(dof >= 5.0, (ss / dof.clamp_min(1.0)).sqrt(), torch.full_like(ss, float("inf")))


def defective_pixels(patches: torch.Tensor) -> DefectivePixels:
    """Hot, stuck and dead pixels of B×1×H×W patches in [0, 1] (H, W ≥ 3; module docstring). Any float dtype; computed
    in float32 (float64 input in float64). The window's fit is made only at the candidates, the pixels whose step
    exceeds k·σ_n and :data:`MIN_DEFECT_DN` (few in most patches). Returns :class:`DefectivePixels`."""
    if patches.ndim != 4 or patches.shape[1] != 1 or min(patches.shape[-2:]) < 3:
        raise ValueError(f"defective_pixels needs B×1×H×W patches with H, W ≥ 3, got {tuple(patches.shape)}")
    if not patches.is_floating_point():
        raise ValueError(f"defective_pixels needs floating-point patches in [0, 1], got dtype {patches.dtype}")
    if not bool(torch.isfinite(patches).all()):
        raise ValueError("defective_pixels: the patches hold NaN or infinite values")
    dtype = torch.float64 if patches.dtype == torch.float64 else torch.float32
    q = patches.detach().to(dtype) * 255.0
    b, _, h, w = q.shape
    c = q[..., 1:-1, 1:-1]
    mx, mn = _max_min8(q)
    step = torch.maximum(c - mx, mn - c)  # > 0 only where the pixel stands above or below every neighbour
    mask = torch.zeros(b, 1, h, w, dtype=torch.int8, device=q.device)
    floor = _noise_floor_dn(q).view(b, 1, 1, 1)
    # candidates: the step beats the floor and k times the patch's noise (a lower bound of the threshold)
    cand = (step > torch.clamp(DEFECT_SIGMAS * floor, min=MIN_DEFECT_DN)).nonzero()  # (N, 4): b, 0, y − 1, x − 1
    if cand.shape[0]:
        where = torch.stack([cand[:, 0], cand[:, 2] + 1, cand[:, 3] + 1], 1)
        keep = torch.ones_like(q, dtype=torch.bool)  # the window's fit leaves out every candidate
        keep[where[:, 0], 0, where[:, 1], where[:, 2]] = False
        scale = torch.maximum(_window_scale(q, keep, where), floor.view(b)[cand[:, 0]])
        found = step[cand[:, 0], 0, cand[:, 2], cand[:, 3]] > DEFECT_SIGMAS * scale
        hit, at = where[found], cand[found]
        up = c[at[:, 0], 0, at[:, 2], at[:, 3]] > mx[at[:, 0], 0, at[:, 2], at[:, 3]]  # above every neighbour: hot
        mask[hit[:, 0], 0, hit[:, 1], hit[:, 2]] = torch.where(up, 1, -1).to(torch.int8)
        hot = torch.bincount(hit[up, 0], minlength=b)
        dark = torch.bincount(hit[~up, 0], minlength=b)
    else:
        hot = dark = torch.zeros(b, dtype=torch.int64, device=q.device)
    checked = torch.full((b,), (h - 2) * (w - 2), dtype=torch.int64, device=q.device)
    return DefectivePixels(hot, dark, checked, mask)
