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
  (and the reverse), and blur inside the fit band is not seen. Images whose ring power in the fit band does not rise
  above the noise floor (a flat image, pure noise, a texture drowned in noise) have no measurable texture: a
  ``ValueError`` says so instead of returning a meaningless fit. Its error on sources of known blur is measured in
  ``tests/data/test_native_mtf.py``.

Native MTF here is relative to an ideal camera whose pixel integrates the light over its area (an exact 1-px box
aperture): that is what "sharp" means for a label (the applied kernel's MTF alone), and what area-rendered scenes and
area-downsampled photographs are. Per source (:func:`native_mtf_report`, ``python -m camhealth.data.native_mtf``):

- rendered scenes (dead leaves, charts): a pixel is the mean of s×s point samples; :func:`rendered_native_mtf`
  measures that rendering with the slanted edge on a chart rendered the same way (closed form
  sin(πf)/(s·sin(πf/s)) / sinc(f), f = f_n/2: 1/sinc at s = 1 — no aperture, sharper than any camera — and within
  1 % / 0.3 % of the exact area integral at f_n = 0.6 for s = 4 / 8);
- photographs and video frames area-downsampled by k (:class:`camhealth.data.AreaDownsampledSource`): the new pixel
  aperture is an exact box and the original optics shrink by k, so the native MTF at f_n is the full-size native
  MTF at f_n / k (measured where the source has an edge: :func:`street_edge_native_mtf`), and at least the
  full-size value at f_n (an MTF that falls with frequency).

Frequencies are normalised to Nyquist (f_n; f = f_n/2 cycles/px), as everywhere in camhealth.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch

from camhealth._validation import check_image
from camhealth.data._common import check_whole
from camhealth.physics.mtf import NORMALIZED_FREQUENCIES

__all__ = [
    "edge_native_mtf", "spectral_native_mtf", "spectral_blur_recovery", "native_mtf_table", "rendered_native_mtf",
    "street_edge_native_mtf", "native_mtf_report", "SOURCES", "STREET_EDGE_ROIS",
]

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
        fit_band: (low, high) f_n of the power-law fit, 0 < low < high ≤ 0.5, holding at least 3 rings of the tile's
            spectrum (rings are 2 / ``tile`` apart).
        tile: tile side in px, an integer in [32, 512].

    Raises:
        TypeError: ``tile`` is not an integer; an image is not a floating tensor.
        ValueError: an argument out of its range (the message names it and the range); an image that is not
            1×H×W or B×1×H×W, not finite or not in [0, 1], or smaller than ``tile``; images without measurable
            texture: the ring power in ``fit_band``, less the white-noise floor, is not above that floor at every
            ring (a flat image, pure noise, a texture drowned in noise), where the power-law fit, and so the MTF,
            would be meaningless (values from 0 to 1e22).
    """
    if isinstance(images, torch.Tensor):
        if images.ndim not in (3, 4):
            raise ValueError(f"images must be a 1×H×W or B×1×H×W tensor (or a list of them), got shape {tuple(images.shape)}")
        images = [images] if images.ndim == 3 else list(images)
    elif isinstance(images, (str, bytes)):
        raise TypeError(f"images must be a tensor or a list of tensors, got {type(images).__name__}")
    else:
        try:
            images = list(images)
        except TypeError:
            raise TypeError(f"images must be a tensor or a list of tensors, got {type(images).__name__}") from None
    if not images:
        raise ValueError("images must hold at least one image")
    for i, img in enumerate(images):
        if not isinstance(img, torch.Tensor) or img.ndim not in (3, 4):
            shape = tuple(img.shape) if isinstance(img, torch.Tensor) else type(img).__name__
            raise ValueError(f"images[{i}] must be a 1×H×W or B×1×H×W tensor, got {shape}")
    tile = check_whole(tile, "tile", 32, 512)
    try:
        lo, hi = (float(v) for v in fit_band)
    except (TypeError, ValueError):
        raise ValueError(f"fit_band = {fit_band!r} must be a pair (low, high) of f_n with 0 < low < high ≤ 0.5") from None
    if not (0.0 < lo < hi <= 0.5):
        raise ValueError(f"fit_band = {fit_band} must satisfy 0 < low < high ≤ 0.5 (f_n)")
    fn_req = torch.as_tensor(frequencies, dtype=torch.float64).reshape(-1)
    if fn_req.numel() == 0 or bool((~((fn_req > 0) & (fn_req <= 1))).any()):  # (NaN fails both)
        raise ValueError(f"frequencies must lie in (0, 1] (× Nyquist), got {fn_req.tolist()}")
    step = 2.0 / tile
    band = torch.arange(lo, hi + 1e-9, step, dtype=torch.float64)
    if band.numel() < 3:
        raise ValueError(f"fit_band = {fit_band} holds {band.numel()} ring(s) of a {tile}-px tile (rings every "
                         f"{step:.3g} f_n); the power-law fit needs at least 3: widen the band or use larger tiles")
    win1 = torch.hann_window(tile, periodic=False, dtype=torch.float64)
    win = win1[:, None] * win1[None, :]
    power = torch.zeros(tile, tile, dtype=torch.float64)
    noise_power = 0.0
    n_tiles = 0
    grays = [x for img in images for x in check_image(img[None] if img.ndim == 3 else img, "images", 1, (0.0, 1.0))[:, 0]]
    for x in grays:  # every image of every element (a B×1×H×W element gives B images)
        x = x.double()
        h, w = x.shape
        if min(h, w) < tile:
            raise ValueError(f"an image of {h}×{w} px is smaller than tile = {tile} px")
        sigma = _noise_sigma(x)
        t = x[: h // tile * tile, : w // tile * tile].reshape(h // tile, tile, w // tile, tile).permute(0, 2, 1, 3).reshape(-1, tile, tile)
        t = (t - t.mean((1, 2), keepdim=True)) * win
        power += torch.fft.fft2(t).abs().square().sum(0)
        noise_power += sigma**2 * float(win.square().sum()) * t.shape[0]
        n_tiles += t.shape[0]
    floor = noise_power / n_tiles  # expected white-noise power per frequency of one tile
    power = (power - noise_power) / n_tiles
    f = torch.fft.fftfreq(tile, dtype=torch.float64)
    fn = 2.0 * torch.sqrt(f[:, None] ** 2 + f[None, :] ** 2)  # × Nyquist

    def ring(centre: torch.Tensor) -> torch.Tensor:
        m = (fn[None] - centre[:, None, None]).abs() <= 0.75 * step
        return (power[None] * m).sum((1, 2)) / m.sum((1, 2)).clamp_min(1)

    pb = ring(band)
    weakest = float(pb.min())
    if not weakest > floor:  # (also a flat image: 0 power over a 0 floor; NaN fails too)
        raise ValueError(
            f"the {len(grays)} image(s) have no measurable texture above the noise floor in fit_band = ({lo:g}, {hi:g}) "
            f"(f_n): their ring power there, less the white-noise floor, falls to {weakest:.3g}, not above the floor "
            f"{floor:.3g} (mean power per frequency of the {n_tiles} {tile}-px tile(s)); a flat or noise-only image has "
            "no MTF to estimate"
        )
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


def rendered_native_mtf(supersample: int, frequencies: Sequence[float] = NORMALIZED_FREQUENCIES, size: int = 512) -> torch.Tensor:
    """Native MTF (F,) of a scene rendered as the mean of ``supersample``² point samples per pixel (the rule of
    :func:`camhealth.data.dead_leaves.dead_leaves` and of the charts), relative to the exact pixel-area integral:
    the slanted edge (pixel aperture divided out) on the four edges of a chart of ``size`` px rendered that way
    (mean of H and V)."""
    from camhealth.estimators.charts import slanted_edge_chart, slanted_edge_rois

    s = check_whole(supersample, "supersample", 1, 8)
    chart = slanted_edge_chart(size, supersample=s).double()
    rois = slanted_edge_rois(size)
    out = []
    for name in ("left", "right", "top", "bottom"):
        r0, r1, c0, c1 = rois[name]
        roi = chart[:, :, r0:r1, c0:c1]
        if name in ("top", "bottom"):
            roi = roi.transpose(-1, -2)
        out.append(edge_native_mtf(roi, frequencies, aperture=True)[0])
    return torch.stack(out).mean(0).float()


#: ROIs ``(row0, row1, col0, col1)`` of the street clip (full size, 768×576) around the lower edge of the window
#: band of the building (dark frame above, brick below, ≈ 2–5° from the horizontal): the one long straight edge
#: of the scene away from the lamp post. Several ROIs, because the edge is real (a frame, a sill) rather than a
#: step and the neighbouring structure changes the result: their spread is part of the measurement.
STREET_EDGE_ROIS = tuple((r0, r1, c0, c1) for r0, r1 in ((66, 100), (70, 97), (72, 95)) for c0, c1 in ((436, 520), (440, 512), (445, 530)))


def street_edge_native_mtf(frequencies: Sequence[float] = NORMALIZED_FREQUENCIES) -> torch.Tensor:
    """Vertical native MTF of the street clip at full size, slanted edge (pixel aperture divided out) on the median
    of its 50 frames (static scene: the median removes the people and the noise, not the blur) in each of
    :data:`STREET_EDGE_ROIS` → (R, F)."""
    from camhealth.data.street_sample import StreetSampleSource

    src = StreetSampleSource()
    med = torch.stack([src[i][0].double() for i in range(len(src))]).median(0).values  # 1×H×W
    rois = [med[:, r0:r1, c0:c1].transpose(-1, -2)[None] for r0, r1, c0, c1 in STREET_EDGE_ROIS]
    return torch.cat([edge_native_mtf(r.contiguous(), frequencies, aperture=True) for r in rois]).float()


def native_mtf_report(frequency: float = 0.6) -> list[dict[str, object]]:
    """Every source's native MTF at ``frequency`` (f_n) with how it was found: rows ``{"source", "method", "mtf"
    (value or (low, median, high) over the ROIs), "passes"}``; ``passes``: within 5 % of an ideal pixel-aperture
    camera (0.95 ≤ MTF ≤ 1.05 — above 1.05 is a rendering sharper than any camera, aliased), ``None`` when the
    measurement cannot tell."""
    f = float(frequency)
    rows: list[dict[str, object]] = []
    for s in (1, 2, 4, 8):
        v = float(rendered_native_mtf(s, (f,))[0])
        rows.append({"source": f"dead leaves, supersample {s}", "method": "slanted edge on a chart rendered the same way",
                     "mtf": v, "passes": 0.95 <= v <= 1.05})
    street = street_edge_native_mtf((f / 3, f / 2, f))
    for k, col in ((1, 2), (2, 1), (3, 0)):
        v = street[:, col]
        q = (float(v.min()), float(v.median()), float(v.max()))
        how = "slanted edge, window band (V), 9 ROIs" + ("" if k == 1 else f": full-size MTF at f_n {f / k:.2g}")
        rows.append({"source": "street clip" + ("" if k == 1 else f", area-downsampled ×{k}"), "method": how,
                     "mtf": q, "passes": True if q[0] >= 0.95 else False if q[2] < 0.95 else None})
    spec = native_mtf_table(("skimage_photos", "skimage_photos_area2"))
    for name, label in (("skimage_photos", "scikit-image photographs"), ("skimage_photos_area2", "scikit-image photographs, area-downsampled ×2")):
        rows.append({"source": label, "method": "no straight edge: spectral estimate only (not a measurement, see below)",
                     "mtf": spec[name]["mtf_0.6"], "passes": None})
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m camhealth.data.native_mtf [--frequency F]``: the markdown table of :func:`native_mtf_report`."""
    import argparse

    ap = argparse.ArgumentParser(
        prog="python -m camhealth.data.native_mtf",
        description="Native MTF of every built-in image source at one frequency (slanted edge where the source has "
        "an edge or is rendered; the spectral estimate otherwise), as a markdown table (docs/data.md).")
    ap.add_argument("--frequency", type=float, default=0.6, help="normalised frequency f_n in (0, 1] (default 0.6)")
    args = ap.parse_args(argv)
    if not (0.0 < args.frequency <= 1.0):
        ap.error(f"--frequency {args.frequency} is out of the allowed range (0, 1]")
    print(f"| source | native MTF at f_n = {args.frequency:g} | within 5 % of 1 | how |")
    print("|---|---:|:---:|---|")
    for r in native_mtf_report(args.frequency):
        m = r["mtf"]
        val = f"{m[1]:.2f} ({m[0]:.2f}–{m[2]:.2f})" if isinstance(m, tuple) else f"{m:.3f}"
        ok = {True: "yes", False: "no", None: "unknown"}[r["passes"]]
        print(f"| {r['source']} | {val} | {ok} | {r['method']} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
