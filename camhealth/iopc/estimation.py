"""Patch-wise blur/noise estimation on the regions that matter, and the Eq. 4.4 median.

"Model only what a scene needs": an image is tiled into non-overlapping square patches (128 px for
noise, 192 px for the MTF estimator, thesis 4.3.1–4.3.3; the tile grid is centred, a remainder narrower
than a patch at the borders is not used) and only the tiles that overlap an object box (ground truth in
the sweep, detections in the closed loop) with positive area are estimated (I_jk ∩ B_GT ≠ ∅). The
per-cell/per-frame values are the medians over all those tiles of all images (Eq. 4.4):

    MTF̃ = median{ MTF̂_jk : tile jk overlaps an object },   σ̃ = median{ σ̂_lm : tile lm overlaps an object }

with MTF̂_jk reduced to the blur indicator (mean of H and V at f_n = 0.1) per tile before the median, and
only tiles the estimator calls ``assessable`` (not black, saturated or flat).

Estimators follow the inference contract of :mod:`camhealth.inference` (issue 4): an object with
``kind`` (``"mtf"``/``"drne"``/``"noise_source"``), ``patch_size``, ``metadata_set`` and
``predict(patches B×1×P×P in [0, 1], metadata) -> dict`` of CPU tensors (``mtf`` (B, 16),
``sigma_total`` (B,), ``sigma`` (B, 3) [noise_source], ``assessable`` (B,)). :func:`resolve_estimator`
accepts such an object, a name for ``load_estimator`` (default ``"noise_source_min"`` / ``"mtf"``), or
one of two documented non-learned stand-ins:

* ``"physics"`` — the **physics labels** (an oracle, not an estimator): σ̂ of a tile is the standard
  deviation of the realised noise (corrupted − noise-free blurred image) in that tile [DN]; MTF̂ is the
  exact MTF of the applied PSF (:func:`camhealth.physics.mtf_hv`). Only possible where the images were
  rendered by the physics core (sweep, simulated camera).
* ``"immerkaer"`` — :class:`ImmerkaerNoiseEstimator`, the classical blind noise estimator of
  Immerkær (1996) on each tile (noise only).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np
import torch

from camhealth._validation import check_image, check_range
from camhealth.estimators._common import check_patches
from camhealth.physics.metadata import CameraMetadata
from camhealth.physics.mtf import mtf_indicator

__all__ = [
    "PHYSICS",
    "NOISE_KINDS",
    "ImmerkaerNoiseEstimator",
    "resolve_estimator",
    "estimator_name",
    "estimator_fingerprint",
    "tile_grid",
    "overlap_mask",
    "extract_tiles",
    "RegionEstimates",
    "estimate_regions",
    "median_estimates",
]

#: Spec of the physics-label oracle (see the module docstring).
PHYSICS = "physics"
#: Estimator kinds that give σ̂.
NOISE_KINDS = ("drne", "noise_source")
#: Default estimator names of the inference contract.
DEFAULT_NOISE = "noise_source_min"
DEFAULT_MTF = "mtf"


class ImmerkaerNoiseEstimator:
    """Classical blind noise estimator (Immerkær 1996, "Fast noise variance estimation"), per patch.

    The difference of two Laplacian masks, ``N = [[1, −2, 1], [−2, 4, −2], [1, −2, 1]]``, cancels locally
    linear image structure; for white Gaussian noise of std σ, E|I∗N| = σ·√(2/π)·6 (the mask's L2 norm
    is 6). Hence

        σ̂ = √(π/2) · 1 / (6 (W − 2)(H − 2)) · Σ_valid |I ∗ N|      [DN, with I in DN]

    Biased upwards on strongly textured patches (edges leak through N). Follows the inference contract
    (``kind = "drne"``, ``metadata_set = "none"``); ``assessable`` is False for patches with more than
    5 % of pixels at 0 or 255 DN or a standard deviation below 0.5 DN.
    """

    kind = "drne"
    patch_size = 128
    metadata_set = "none"
    name = "immerkaer1996"
    #: Smallest patch side [px] read: 36 coefficients of I∗N (σ̂ within about 10 % on white noise).
    MIN_SIZE = 8

    def __init__(self, patch_size: int = 128) -> None:
        # predict refuses patches smaller than MIN_SIZE: a smaller tile size would make every tile unreadable
        if isinstance(patch_size, (bool, np.bool_)) or not isinstance(patch_size, numbers.Integral) \
                or patch_size < self.MIN_SIZE:
            raise ValueError(f"patch_size = {patch_size!r} is out of the allowed range: an integer >= {self.MIN_SIZE} px "
                             "(the smallest patch predict reads)")
        self.patch_size = int(patch_size)

    def predict(self, patches: torch.Tensor, metadata: CameraMetadata | None = None) -> dict[str, torch.Tensor]:
        """σ̂_total [DN] (B,) and ``assessable`` (B,) of patches B×1×P×P in [0, 1] (or uint8 DN)."""
        if isinstance(patches, torch.Tensor) and patches.dtype == torch.uint8:
            patches = patches.float() / 255.0
        # [0, 1] (a float image in DN would read 255× too noisy) and at least MIN_SIZE px (a 3×3 patch has one
        # coefficient of I∗N; a 2×2 one none)
        check_patches(patches, "patches", min_size=(self.MIN_SIZE, self.MIN_SIZE))
        x = patches.detach().float().cpu() * 255.0
        k = torch.tensor([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]]).view(1, 1, 3, 3)
        r = torch.nn.functional.conv2d(x, k)  # valid: (H−2)×(W−2)
        sigma = math.sqrt(math.pi / 2.0) * r.abs().mean(dim=(1, 2, 3)) / 6.0
        clipped = ((x <= 0.5) | (x >= 254.5)).float().mean(dim=(1, 2, 3))
        assessable = (clipped <= 0.05) & (x.std(dim=(1, 2, 3)) >= 0.5)
        return {"sigma_total": sigma, "assessable": assessable}


def _load_named(name: str) -> Any:
    try:
        from camhealth.inference import load_estimator  # issue 4
    except ImportError as err:
        raise ImportError(
            f"estimator {name!r} needs camhealth.inference.load_estimator (the trained estimators of issue 4), "
            f"which is not importable here ({err}); inject an estimator object, or use the documented "
            f"stand-ins '{PHYSICS}' (physics labels) or 'immerkaer' (classical noise estimator)"
        ) from err
    return load_estimator(name)


def resolve_estimator(spec: Any, role: str) -> Any:
    """An estimator for ``role`` (``"noise"`` or ``"mtf"``) from a spec.

    ``spec``: ``None`` (the default trained estimator, ``"noise_source_min"``/``"mtf"``), ``"physics"``,
    ``"immerkaer"`` (noise only), another name or path for ``load_estimator``, or an object with the
    predict contract. Raises ``ValueError``/``TypeError`` if the object does not fit the role.
    """
    if role not in ("noise", "mtf"):
        raise ValueError(f"role = {role!r} must be 'noise' or 'mtf'")
    if spec is None:
        spec = DEFAULT_NOISE if role == "noise" else DEFAULT_MTF
    if isinstance(spec, str):
        key = spec.strip()
        if key.lower() == PHYSICS:
            return PHYSICS
        if key.lower() == "immerkaer":
            if role != "noise":
                raise ValueError("'immerkaer' is a noise estimator; it cannot estimate the MTF")
            return ImmerkaerNoiseEstimator()
        spec = _load_named(key)
    for attr in ("kind", "patch_size", "metadata_set", "predict"):
        if not hasattr(spec, attr):
            raise TypeError(
                f"the {role} estimator {type(spec).__name__} lacks {attr!r}; estimators need kind, patch_size, "
                "metadata_set and predict(patches, metadata) (camhealth.inference contract)"
            )
    if not callable(spec.predict):
        raise TypeError(f"the {role} estimator's predict = {spec.predict!r:.60} is not callable; estimators need a method "
                        "predict(patches, metadata) (camhealth.inference contract)")
    kinds = NOISE_KINDS if role == "noise" else ("mtf",)
    if spec.kind not in kinds:
        raise ValueError(f"the {role} estimator has kind {spec.kind!r}; expected one of {list(kinds)}")
    if spec.metadata_set not in ("none", "minimal", "full"):
        raise ValueError(f"estimator metadata_set = {spec.metadata_set!r} must be 'none', 'minimal' or 'full'")
    _patch_size(spec)
    return spec


#: Smallest estimator patch side [px] (Immerkær's estimator reads no less, and the networks are trained on 128/192).
MIN_PATCH_SIZE = 8


def _patch_size(est: Any) -> int:
    """An estimator's ``patch_size`` as an int: an integer (Python or NumPy, not a bool) >= 8 px, else ``ValueError``
    naming the value (a fractional size would be truncated to another tile grid)."""
    p = est.patch_size
    if isinstance(p, (bool, np.bool_)) or not isinstance(p, numbers.Integral) or p < MIN_PATCH_SIZE:
        raise ValueError(f"estimator patch_size = {p!r:.40} is out of the allowed range: an integer >= {MIN_PATCH_SIZE} px")
    return int(p)


def estimator_name(est: Any) -> str:
    """Short description for provenance."""
    if est is None:
        return "none"
    if isinstance(est, str):
        return est
    name = getattr(est, "name", None) or type(est).__name__
    return f"{name} (kind={getattr(est, 'kind', '?')}, patch={getattr(est, 'patch_size', '?')}, " \
           f"metadata={getattr(est, 'metadata_set', '?')})"


def estimator_fingerprint(est: Any) -> str:
    """:func:`estimator_name` plus a hash of the weights a learned estimator was loaded from (the file's bytes; for an
    estimator in memory — a training's LightningModule, a network — its current parameters and buffers; else its
    ``description``), so that retrained weights under the same name never match an old cache entry."""
    import hashlib
    import json
    from pathlib import Path

    name = estimator_name(est)
    if est is None or isinstance(est, str):
        return name
    h = hashlib.blake2b(digest_size=8)
    source = getattr(est, "source", None)
    module = next((m for m in (est, getattr(est, "_net", None), getattr(est, "net", None), getattr(est, "module", None))
                   if isinstance(m, torch.nn.Module)), None)
    if source and Path(source).is_file():
        h.update(Path(source).read_bytes())
    elif module is not None:  # in memory (a training's module, an injected network): its current weights
        for key, t in sorted(module.state_dict().items()):
            h.update(key.encode())
            h.update(t.detach().cpu().reshape(-1).contiguous().view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    else:  # no file and no network: its description (an object whose answers depend on other state must say so there)
        h.update(json.dumps(getattr(est, "description", {}), sort_keys=True, default=str).encode())
    return f"{name} [weights {h.hexdigest()}]"


def tile_grid(height: int, width: int, patch: int, device: torch.device | None = None) -> torch.Tensor:
    """Non-overlapping ``patch``×``patch`` tiles of an H×W image, centred: (T, 4) long xyxy [px], row-major."""
    if patch < 1 or patch > min(height, width):
        raise ValueError(f"patch size {patch} px does not fit a {width}×{height} px image")
    nh, nw = height // patch, width // patch
    y0, x0 = (height - nh * patch) // 2, (width - nw * patch) // 2
    ys = torch.arange(nh, device=device) * patch + y0
    xs = torch.arange(nw, device=device) * patch + x0
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    gy, gx = gy.reshape(-1), gx.reshape(-1)
    return torch.stack([gx, gy, gx + patch, gy + patch], dim=1)


def overlap_mask(tiles: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """(T,) bool: tile overlaps at least one box with positive area (boxes (N, 4) xyxy px)."""
    if boxes.numel() == 0:
        return torch.zeros(tiles.shape[0], dtype=torch.bool, device=tiles.device)
    t = tiles.to(torch.float64)[:, None, :]
    b = boxes.to(device=tiles.device, dtype=torch.float64)[None, :, :]
    iw = torch.minimum(t[..., 2], b[..., 2]) - torch.maximum(t[..., 0], b[..., 0])
    ih = torch.minimum(t[..., 3], b[..., 3]) - torch.maximum(t[..., 1], b[..., 1])
    return ((iw > 0) & (ih > 0)).any(dim=1)


def extract_tiles(images: torch.Tensor, patch: int, image_index: torch.Tensor, tile_index: torch.Tensor) -> torch.Tensor:
    """Gather tiles (of :func:`tile_grid`'s row-major order) → (P, C, patch, patch), one strided view."""
    b, c, h, w = images.shape
    nh, nw = h // patch, w // patch
    y0, x0 = (h - nh * patch) // 2, (w - nw * patch) // 2
    crop = images[:, :, y0 : y0 + nh * patch, x0 : x0 + nw * patch]
    tiles = crop.unfold(2, patch, patch).unfold(3, patch, patch)  # B, C, nh, nw, p, p
    tiles = tiles.permute(0, 2, 3, 1, 4, 5).reshape(b, nh * nw, c, patch, patch)
    return tiles[image_index.to(images.device), tile_index.to(images.device)]


@dataclass
class RegionEstimates:
    """Patch-wise estimates on object tiles of a batch of images.

    Attributes:
        sigma: (Pn,) σ̂_total per assessable noise tile [DN].
        sigma_sources: (Pn, 3) σ̂ of PN/DCSN/RN per tile [DN] (noise-source estimators and physics
            labels), else ``None``.
        sigma_image: (Pn,) image index of each noise tile.
        mtf: (Pm,) blur indicator MTF̂ per assessable blur tile.
        mtf_image: (Pm,) image index of each blur tile.
        n_noise_tiles, n_mtf_tiles: object tiles considered (before the ``assessable`` filter).
    """

    sigma: torch.Tensor
    sigma_sources: torch.Tensor | None
    sigma_image: torch.Tensor
    mtf: torch.Tensor
    mtf_image: torch.Tensor
    n_noise_tiles: int
    n_mtf_tiles: int


def _is_physics(est: Any) -> bool:
    return isinstance(est, str) and est == PHYSICS


def _select(images: torch.Tensor, regions: Sequence[torch.Tensor], patch: int, fallback_all: bool) -> tuple[torch.Tensor, torch.Tensor]:
    h, w = images.shape[-2:]
    tiles = tile_grid(h, w, patch)
    img_idx, tile_idx = [], []
    for i, boxes in enumerate(regions):
        m = overlap_mask(tiles, boxes.detach().cpu())
        if not bool(m.any()) and fallback_all:
            m = torch.ones_like(m)
        k = torch.nonzero(m).reshape(-1)
        img_idx.append(torch.full_like(k, i))
        tile_idx.append(k)
    return torch.cat(img_idx), torch.cat(tile_idx)


#: The predict outputs :func:`estimate_regions` reads, per role, with their shape per patch (contract of
#: :mod:`camhealth.inference`): σ_total [DN], σ of PN/DCSN/RN [DN], 16 MTF values, the assessable flag.
_OUTPUTS: dict[str, dict[str, tuple[int, ...]]] = {
    "noise": {"sigma_total": (), "sigma": (3,), "assessable": ()},
    "MTF": {"mtf": (16,), "assessable": ()},
}


def _predict(est: Any, patches: torch.Tensor, meta: CameraMetadata | None, batch_size: int,
             role: str) -> dict[str, torch.Tensor]:
    """Run ``est`` on ``patches`` in batches; return the outputs of ``role`` (``"noise"`` or ``"MTF"``, see
    ``_OUTPUTS``) concatenated. Each output must be a tensor of shape (P, ...) for the P patches of its call, and σ
    values must be >= 0 DN (NaN: no estimate); otherwise ``ValueError``/``TypeError`` naming the output, its shape or
    value and what is expected."""
    dev = getattr(est, "device", None)
    wanted = _OUTPUTS[role]
    outs: list[dict[str, torch.Tensor]] = []
    for s in range(0, patches.shape[0], batch_size):
        p = patches[s : s + batch_size]
        p = p.to(dev) if isinstance(dev, (torch.device, str)) else p.cpu()
        m = None
        if est.metadata_set != "none":
            if meta is None:
                raise ValueError(
                    f"the estimator needs camera metadata (metadata_set = {est.metadata_set!r}) but none was given"
                )
            m = meta[s : s + batch_size]
        out = est.predict(p.float(), m)
        if not isinstance(out, Mapping):
            raise TypeError(f"estimator predict must return a dict of tensors, got {type(out).__name__}")
        n = int(p.shape[0])
        required = "sigma_total" if role == "noise" else "mtf"
        if required not in out:
            raise ValueError(f"{role if role == 'MTF' else 'noise'} estimator output lacks {required!r}; it has "
                             f"{sorted(map(str, out))}")
        got = {}
        for key, trailing in wanted.items():
            if key not in out:
                continue
            v = out[key]
            if not isinstance(v, torch.Tensor):
                raise TypeError(f"{role} estimator returned {key} of type {type(v).__name__}; expected a tensor of shape "
                                f"{(n, *trailing)}")
            if tuple(v.shape) != (n, *trailing):
                raise ValueError(f"{role} estimator returned {key} of shape {tuple(v.shape)} for {n} patches; expected "
                                 f"{(n, *trailing)}")
            if v.is_complex():
                raise TypeError(f"{role} estimator returned {key} of dtype {v.dtype}; expected real numbers")
            v = v.detach().cpu()
            if key in ("sigma_total", "sigma") and v.numel():
                neg = v < 0  # (NaN is no estimate: such a patch is dropped)
                if bool(neg.any()):
                    raise ValueError(f"{role} estimator returned {key} = {float(v[neg][0]):g} DN, out of the allowed "
                                     "range: >= 0 DN (or NaN: no estimate)")
            got[key] = v
        outs.append(got)
    return {k: torch.cat([o[k] for o in outs]) for k in outs[0]} if outs else {}


def _check_regions(regions: Any, n_images: int) -> None:
    """``regions``: a list/tuple of B tensors of xyxy boxes [px], each (N, 4) (or empty), finite, x1 <= x2 and
    y1 <= y2; else ``TypeError``/``ValueError`` naming the image, the shape or value and what is allowed."""
    if isinstance(regions, torch.Tensor):
        if regions.ndim != 3:
            raise ValueError(f"regions as one tensor must have shape (B, N, 4) [xyxy px], got {tuple(regions.shape)}")
    elif not isinstance(regions, (list, tuple)):
        raise TypeError(f"regions must be a list of (N, 4) xyxy box tensors, one per image, got {type(regions).__name__}")
    if len(regions) != n_images:
        raise ValueError(f"{len(regions)} region lists for {n_images} images")
    for i, boxes in enumerate(regions):
        if not isinstance(boxes, torch.Tensor):
            raise TypeError(f"regions[{i}] must be a tensor of shape (N, 4) (xyxy boxes [px]), got "
                            f"{type(boxes).__name__} {boxes!r:.60}")
        if boxes.numel() == 0 and boxes.ndim <= 2 and (boxes.ndim < 2 or boxes.shape[-1] in (0, 4)):
            continue  # no boxes
        if boxes.ndim != 2 or boxes.shape[1] != 4:
            raise ValueError(f"regions[{i}] has shape {tuple(boxes.shape)}; allowed: (N, 4) xyxy boxes [px]")
        if boxes.dtype == torch.bool or boxes.is_complex():
            raise TypeError(f"regions[{i}] has dtype {boxes.dtype}; allowed: real numbers (xyxy boxes [px])")
        b = boxes.detach().cpu().double()
        if not bool(torch.isfinite(b).all()):
            raise ValueError(f"regions[{i}] holds a non-finite box {b[~torch.isfinite(b).all(1)][0].tolist()}; allowed: "
                             "finite xyxy boxes [px]")
        bad = (b[:, 2] < b[:, 0]) | (b[:, 3] < b[:, 1])
        if bool(bad.any()):
            raise ValueError(f"regions[{i}] holds the box {b[bad][0].tolist()} with x2 < x1 or y2 < y1; allowed: xyxy "
                             "boxes [px] (x1 <= x2, y1 <= y2)")


def _check_physics(physics: Any, images: torch.Tensor, noise: bool, mtf: bool) -> None:
    """The physics labels the ``"physics"`` oracle reads: ``blurred`` shaped like ``images`` (B×1×H×W, finite),
    ``mtf`` (B, 16) in [0, 1], ``sigma_dn`` (B, 3) >= 0 DN; a ``ValueError`` names the entry, its shape or value and
    what is allowed."""
    if physics is None:
        return
    if not isinstance(physics, Mapping):
        raise TypeError(f"physics must be a dict of tensors (blurred, mtf, sigma_dn), got {type(physics).__name__}")
    b = int(images.shape[0])
    if noise and "blurred" in physics:
        bl = check_image(physics["blurred"], "physics['blurred']")
        if tuple(bl.shape) != tuple(images.shape):
            raise ValueError(f"physics['blurred'] has shape {tuple(bl.shape)}; allowed: the images' shape "
                             f"{tuple(images.shape)} (B×1×H×W)")
    for key, trailing, low, high, unit, use in (("mtf", 16, 0.0, 1.0 + 1e-6, "", mtf),
                                                ("sigma_dn", 3, 0.0, math.inf, "DN", noise)):
        if not use or key not in physics:
            continue
        v = physics[key]
        if not isinstance(v, torch.Tensor):
            raise TypeError(f"physics['{key}'] must be a tensor of shape ({b}, {trailing}), got {type(v).__name__}")
        if tuple(v.shape) != (b, trailing):
            raise ValueError(f"physics['{key}'] has shape {tuple(v.shape)} for {b} images; allowed: ({b}, {trailing})")
        if v.dtype == torch.bool or v.is_complex():
            raise TypeError(f"physics['{key}'] has dtype {v.dtype}; allowed: real numbers")
        check_range(v.detach(), f"physics['{key}']", low, high, unit)


def estimate_regions(
    images: torch.Tensor,
    regions: Sequence[torch.Tensor],
    noise_estimator: Any,
    mtf_estimator: Any,
    metadata: CameraMetadata | None = None,
    physics: Mapping[str, torch.Tensor] | None = None,
    fallback_all: bool = False,
    batch_size: int = 64,
) -> RegionEstimates:
    """Estimate σ̂ and MTF̂ on the tiles that overlap ``regions`` (one (N, 4) xyxy box tensor per image).

    Args:
        images: B×1×H×W in [0, 1].
        regions: object boxes per image (ground truth or detections).
        noise_estimator, mtf_estimator: resolved estimators (:func:`resolve_estimator`), ``"physics"``,
            or ``None`` to skip.
        metadata: camera metadata (batch 1 or B) in physical units, for estimators that need it.
        physics: for ``"physics"``: ``blurred`` (B×1×H×W noise-free image after blur, the images' shape), ``mtf``
            (B, 16) of the applied PSF, in [0, 1], and optionally ``sigma_dn`` (B, 3) per-source σ of each image
            [DN], >= 0.
        fallback_all: images without any region use all tiles (closed loop) instead of none (sweep).
        batch_size: tiles per estimator call.

    Bad input is refused before any estimate, naming the argument, its shape or value and what is allowed: images
    outside [0, 1] (e.g. DN), regions that are not B (N, 4) finite xyxy box tensors, metadata of another batch than
    1 or B, physics labels of another shape or range. An estimator's outputs must have its patches' count and shape
    (``sigma_total`` (P,), ``sigma`` (P, 3), ``mtf`` (P, 16), ``assessable`` (P,)) and σ >= 0 DN.
    """
    check_image(images, "images", value_range=(0.0, 1.0))
    b = int(images.shape[0])
    _check_regions(regions, b)
    if metadata is not None:
        if not isinstance(metadata, CameraMetadata):
            raise TypeError(f"metadata must be a CameraMetadata, got {type(metadata).__name__}")
        if metadata.batch_size == 1:
            metadata = metadata.expand(b)
        if metadata.batch_size != b:
            raise ValueError(f"metadata has batch {metadata.batch_size} for {b} images; allowed: 1 or {b}")
    _check_physics(physics, images, _is_physics(noise_estimator), _is_physics(mtf_estimator))
    empty = torch.zeros(0)
    empty_i = torch.zeros(0, dtype=torch.long)
    sigma, sources, s_img, n_noise = empty, None, empty_i, 0
    mtf, m_img, n_mtf = empty, empty_i, 0
    if noise_estimator is not None:
        patch = 128 if _is_physics(noise_estimator) else _patch_size(noise_estimator)
        ii, tt = _select(images, regions, patch, fallback_all)
        n_noise = int(ii.numel())
        if n_noise:
            if _is_physics(noise_estimator):
                if physics is None or "blurred" not in physics:
                    raise ValueError("the 'physics' noise labels need physics={'blurred': noise-free image, ...}")
                diff = images.to(physics["blurred"].dtype) - physics["blurred"].to(images.device)
                t = extract_tiles(diff, patch, ii, tt).flatten(1).double()
                sigma = (t.std(dim=1) * 255.0).float().cpu()
                ok = torch.ones_like(sigma, dtype=torch.bool)
                if "sigma_dn" in physics:  # per-source split of the image, scaled to the tile's total
                    src = physics["sigma_dn"].detach().double().cpu()[ii.cpu()]
                    tot = src.pow(2).sum(1).sqrt().clamp_min(1e-12)
                    sources = (src * (sigma.double() / tot)[:, None]).float()
            else:
                tiles = extract_tiles(images, patch, ii, tt)
                meta = metadata[ii.cpu()] if metadata is not None else None
                out = _predict(noise_estimator, tiles, meta, batch_size, "noise")
                if "sigma_total" not in out:
                    raise ValueError(f"noise estimator output lacks 'sigma_total'; it has {sorted(out)}")
                sigma = out["sigma_total"].float().reshape(-1)
                ok = out.get("assessable", torch.ones_like(sigma, dtype=torch.bool)).reshape(-1).bool()
                if "sigma" in out:
                    sources = out["sigma"].float().reshape(-1, 3)
            ok = ok & torch.isfinite(sigma)
            sigma, s_img = sigma[ok], ii.cpu()[ok]
            sources = sources[ok] if sources is not None else None
    if mtf_estimator is not None:
        patch = 192 if _is_physics(mtf_estimator) else _patch_size(mtf_estimator)
        ii, tt = _select(images, regions, patch, fallback_all)
        n_mtf = int(ii.numel())
        if n_mtf:
            if _is_physics(mtf_estimator):
                if physics is None or "mtf" not in physics:
                    raise ValueError("the 'physics' MTF labels need physics={'mtf': (B, 16) MTF of the PSF, ...}")
                mtf = mtf_indicator(physics["mtf"].detach().float().cpu())[ii.cpu()]
                ok = torch.ones_like(mtf, dtype=torch.bool)
            else:
                tiles = extract_tiles(images, patch, ii, tt)
                meta = metadata[ii.cpu()] if metadata is not None else None
                out = _predict(mtf_estimator, tiles, meta, batch_size, "MTF")
                if "mtf" not in out:
                    raise ValueError(f"MTF estimator output lacks 'mtf'; it has {sorted(out)}")
                mtf = mtf_indicator(out["mtf"].float().reshape(-1, 16))
                ok = out.get("assessable", torch.ones_like(mtf, dtype=torch.bool)).reshape(-1).bool()
            ok = ok & torch.isfinite(mtf)
            mtf, m_img = mtf[ok], ii.cpu()[ok]
    return RegionEstimates(sigma, sources, s_img, mtf, m_img, n_noise, n_mtf)


def median_estimates(est: RegionEstimates) -> dict[str, float | list[float] | None]:
    """Eq. 4.4: medians (mid-point of the two middle values for an even count) over all assessable object tiles → ``sigma_tilde`` [DN], ``mtf_tilde``,
    ``sigma_sources_tilde`` (3 per-source medians [DN] or ``None``); NaN where no tile was assessable."""
    nan = float("nan")
    s = float(torch.quantile(est.sigma.double(), 0.5)) if est.sigma.numel() else nan
    m = float(torch.quantile(est.mtf.double(), 0.5)) if est.mtf.numel() else nan
    src = None
    if est.sigma_sources is not None and est.sigma.numel():
        src = torch.quantile(est.sigma_sources.double(), 0.5, dim=0).tolist()
    return {"sigma_tilde": s, "mtf_tilde": m, "sigma_sources_tilde": src}
