"""Native MTF of image sources: how much blur a "clean" training or test image carries before any kernel is applied.

A clean source is only a valid blur-free input if its own MTF is close to 1 at the frequencies the labels cover
(f_n ≤ 0.6); otherwise the label of a blurred patch is the product of the kernel's MTF and the source's
(:func:`camhealth.physics.mtf.combine_mtf`). Two measurements:

- :func:`edge_native_mtf` — the ISO 12233 slanted edge (:func:`camhealth.estimators.slanted_edge.slanted_edge_mtf`)
  on a region holding a straight, slightly slanted edge: the reference method, where a source has such an edge.
- :func:`spectral_native_mtf` — for sources without straight edges (photographs, video frames, procedural
  textures), the texture (spectral-ratio) estimate of the dead-leaves method (Cao, Guichard & Hornung 2010;
  IEEE 1858): natural scenes and dead leaves have a power spectrum close to a power law, P(f) ≈ c·f^(−β). The
  mean power of Hann-windowed, mean-removed tiles is averaged over rings of |f| (H = V assumed), the white-noise
  floor σ̂²·Σw² (σ̂: Haar-diagonal MAD of the image) is subtracted, a power law is fitted in log–log to the ring
  powers over ``fit_band`` (f_n 0.05–0.2, where the MTF is taken as 1), and the MTF is √(P(f) / (c·f^(−β))).
  It is an estimate: a scene whose spectrum falls faster than its power law at high frequencies reads as soft
  (and the reverse), and blur inside the fit band is not seen. Its error on sources of known blur is measured in
  ``tests/data/test_native_mtf.py``.

Frequencies are normalised to Nyquist (f_n; f = f_n/2 cycles/px), as everywhere in camhealth.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch

from camhealth._validation import check_image
from camhealth.physics.mtf import NORMALIZED_FREQUENCIES

__all__ = ["edge_native_mtf", "spectral_native_mtf", "spectral_blur_recovery", "native_mtf_table", "SOURCES"]

_MAD_NORMAL = 0.6744897501960817


def edge_native_mtf(roi: torch.Tensor, frequencies: Sequence[float] = NORMALIZED_FREQUENCIES, aperture: bool = False) -> torch.Tensor:
    """MTF across a slanted edge (ISO 12233) in ``roi`` (B×1×H×W, near-vertical edge) → (B, F).

    ``aperture=True`` divides out the 1-px pixel aperture (for edges rendered by pixel-area integration, so the
    result is the blur applied on top of the rendering)."""
    from camhealth.estimators.slanted_edge import slanted_edge_mtf

    return slanted_edge_mtf(roi, frequencies, aperture=aperture).mtf


def _noise_sigma(x: torch.Tensor) -> float:
    h, w = x.shape[-2] // 2 * 2, x.shape[-1] // 2 * 2
    q = x[..., :h, :w]
    d = 0.5 * (q[..., 0::2, 0::2] - q[..., 0::2, 1::2] - q[..., 1::2, 0::2] + q[..., 1::2, 1::2])
    return float(d.abs().median()) / _MAD_NORMAL


def spectral_native_mtf(
    images: torch.Tensor | Sequence[torch.Tensor],
    frequencies: Sequence[float] = NORMALIZED_FREQUENCIES,
    fit_band: tuple[float, float] = (0.05, 0.2),
    tile: int = 128,
) -> torch.Tensor:
    """Spectral estimate of the native MTF of a source (module docstring) → (F,) at ``frequencies`` (f_n).

    Args:
        images: one or more 1×H×W (or B×1×H×W) gray images in [0, 1], each at least ``tile`` px on each side; the
            power of all their tiles is pooled (one MTF for the source).
        frequencies: normalised frequencies f_n in (0, 1].
        fit_band: (low, high) f_n of the power-law fit, 0 < low < high ≤ 0.5.
        tile: tile side in px (32..512).
    """
    if isinstance(images, torch.Tensor):
        images = [images] if images.ndim == 3 else list(images)
    if not images:
        raise ValueError("images must hold at least one image")
    if not (32 <= int(tile) <= 512):
        raise ValueError(f"tile = {tile} is out of the allowed range [32, 512]")
    lo, hi = fit_band
    if not (0.0 < lo < hi <= 0.5):
        raise ValueError(f"fit_band = {fit_band} must satisfy 0 < low < high ≤ 0.5 (f_n)")
    fn_req = torch.as_tensor(frequencies, dtype=torch.float64).reshape(-1)
    if bool(((fn_req <= 0) | (fn_req > 1)).any()):
        raise ValueError(f"frequencies must lie in (0, 1] (× Nyquist), got {fn_req.tolist()}")
    win1 = torch.hann_window(tile, periodic=False, dtype=torch.float64)
    win = win1[:, None] * win1[None, :]
    power = torch.zeros(tile, tile, dtype=torch.float64)
    noise_power = 0.0
    n_tiles = 0
    for img in images:
        x = check_image(img[None] if img.ndim == 3 else img, "images")[0, 0].double()
        h, w = x.shape
        if min(h, w) < tile:
            raise ValueError(f"an image of {h}×{w} px is smaller than tile = {tile} px")
        sigma = _noise_sigma(x)
        t = x[: h // tile * tile, : w // tile * tile].reshape(h // tile, tile, w // tile, tile).permute(0, 2, 1, 3).reshape(-1, tile, tile)
        t = (t - t.mean((1, 2), keepdim=True)) * win
        power += torch.fft.fft2(t).abs().square().sum(0)
        noise_power += sigma**2 * float(win.square().sum()) * t.shape[0]
        n_tiles += t.shape[0]
    power = (power - noise_power) / n_tiles
    f = torch.fft.fftfreq(tile, dtype=torch.float64)
    fn = 2.0 * torch.sqrt(f[:, None] ** 2 + f[None, :] ** 2)  # × Nyquist
    step = 2.0 / tile

    def ring(centre: torch.Tensor) -> torch.Tensor:
        m = (fn[None] - centre[:, None, None]).abs() <= 0.75 * step
        return (power[None] * m).sum((1, 2)) / m.sum((1, 2)).clamp_min(1)

    band = torch.arange(lo, hi + 1e-9, step, dtype=torch.float64)
    pb = ring(band).clamp_min(1e-30)
    a = torch.stack([torch.ones_like(band), torch.log(band)], 1)
    coef = torch.linalg.lstsq(a, torch.log(pb)[:, None]).solution[:, 0]
    fit = torch.exp(coef[0] + coef[1] * torch.log(fn_req))
    return torch.sqrt(ring(fn_req).clamp_min(0) / fit).float()


#: Sources whose native MTF :func:`native_mtf_table` reports: name → (description, loader of a list of 1×H×W images).
SOURCES = ("deadleaves", "deadleaves_aa2", "skimage_photos", "street", "skimage_photos_area2", "street_area2", "held_out_photos")


def _load(source: str) -> list[torch.Tensor]:
    import torch.nn.functional as F

    from camhealth.data.dead_leaves import dead_leaves
    from camhealth.data.skimage_photos import SKIMAGE_PHOTOS, load_skimage_photo
    from camhealth.data.street_sample import StreetSampleSource

    area2 = lambda xs: [F.avg_pool2d(x[None], 2)[0] for x in xs]  # noqa: E731
    if source == "deadleaves":
        return [torch.as_tensor(dead_leaves((256, 256), seed=i)).float().reshape(1, 256, 256) for i in range(8)]
    if source == "deadleaves_aa2":
        return [torch.as_tensor(dead_leaves((256, 256), seed=i, supersample=2)).float().reshape(1, 256, 256) for i in range(8)]
    if source.startswith("skimage_photos"):
        xs = [load_skimage_photo(n) for n in SKIMAGE_PHOTOS]
        return area2(xs) if source.endswith("area2") else xs
    if source.startswith("street"):
        s = StreetSampleSource(stride=5)
        xs = [s[i][0].float() for i in range(len(s))]
        return area2(xs) if source.endswith("area2") else xs
    if source == "held_out_photos":
        from camhealth.bench.robustness_mtf import HELD_OUT_IMAGES, SCENE_DOWNSAMPLE, _area, _gray
        import numpy as np
        import skimage.data

        return [_area(_gray(np.asarray(getattr(skimage.data, n)())), SCENE_DOWNSAMPLE[n]) for n in HELD_OUT_IMAGES]
    raise ValueError(f"unknown source {source!r}; known: {SOURCES}")


def native_mtf_table(sources: Sequence[str] = SOURCES) -> dict[str, dict[str, float]]:
    """Median over each source's images of :func:`spectral_native_mtf` at f_n = 0.3 and 0.6 (tile 128)."""
    out = {}
    for s in sources:
        per = torch.stack([spectral_native_mtf(x, (0.3, 0.6)) for x in _load(s) if min(x.shape[-2:]) >= 128])
        med = per.median(0).values
        out[s] = {"n": int(per.shape[0]), "mtf_0.3": float(med[0]), "mtf_0.6": float(med[1])}
    return out


def spectral_blur_recovery(sigmas: Sequence[float] = (0.5, 0.8, 1.2), frequency: float = 0.6) -> dict[float, tuple[float, float]]:
    """How well :func:`spectral_native_mtf` measures a known blur: the 2×-supersampled dead leaves of
    :func:`native_mtf_table` blurred with a Gaussian of each σ (px) → {σ: (estimate, the kernel's MTF)} at
    ``frequency`` (f_n, H)."""
    from camhealth.physics import apply_psf, gaussian_psf, mtf_from_psf

    xs = _load("deadleaves_aa2")
    out = {}
    for s in sigmas:
        k = gaussian_psf(torch.tensor([float(s)], dtype=torch.float64), 2 * int(math.ceil(4 * s)) + 1)
        ys = [apply_psf(x[None].double(), k)[0].float() for x in xs]
        est = float(spectral_native_mtf(ys, (frequency,))[0])
        out[float(s)] = (est, float(mtf_from_psf(k, (0.0,), (frequency,))[0, 0, 0]))
    return out
