"""Inference with trained estimators: :func:`load_estimator` → :class:`Estimator` with ``predict``.

``load_estimator(path_or_name)`` accepts

- a **shipped model name** (no network access): ``"mtf"``, ``"drne"``, ``"noise_source_full"``,
  ``"noise_source_min"`` (see :func:`shipped_models`; files in ``camhealth/weights/`` with model cards);
- a **weights file** (``.pt``, :func:`camhealth.export.export_weights`) or a **Lightning checkpoint**
  (``.ckpt``) written by ``python -m camhealth.fit`` — loaded with ``torch.load(weights_only=True)``:
  tensors only, never arbitrary pickled code; anything else is rejected with a clear error;
- an **exported program** (``.pt2``, run with :func:`torch.export.load`) or an **ONNX** file (``.onnx``,
  run with ONNX Runtime).

``Estimator.predict(images, metadata=None)``:

- ``images``: B×1×P×P patches (also B×P×P or P×P) as a torch tensor or NumPy array, P = ``patch_size``
  (128 for noise, 192 for MTF). Integer arrays (uint8/uint16 …) are **DN**; floating arrays are
  **[0, 1]** (= DN/255) unless ``input_range="dn"``; a float input above 1 with the default
  ``input_range="auto"`` is refused with a hint, never silently rescaled.
- ``metadata``: required when ``metadata_set`` is ``"minimal"`` or ``"full"``:
  a :class:`~camhealth.physics.CameraMetadata` (batch 1 or B), a dict of fields in physical units
  (missing fields from ``base_preset``, e.g. ``{"gain_db": 12, "exposure_s": 0.01, "temperature_c": 40}``
  with ``base_preset="ICX285"``), a preset name, or the path of a ``.yaml``/``.json`` metadata file (the
  ``camera.yaml`` of ``python -m camhealth.calibrate``). Out-of-range values raise, naming field and range.
- returns a dict of float32 CPU tensors: ``mtf`` (B, 16) H then V [kind ``mtf``]; ``sigma_total`` (B,) DN
  [noise kinds; for noise-source networks √(Σ σ_s²), or the learned realised total after clipping when the
  network has the total head, ``total_branch``]; ``sigma`` (B, 3) σ of PN, DCSN, RN in DN and ``xi`` (B,) DN [``noise_source``];
  ``sigma_map`` (B, 1, P, P) [``drne``]; ``assessable`` (B,) bool and ``reason`` (list of str: ``""``,
  ``"black"``, ``"saturated"``, ``"featureless"``). Not-assessable patches still get finite numbers; do not
  trust them.
- ``views`` (MTF models): 1 (default), 2 or 4 — also run the patch flipped (2: rotated by 180°; 4: flipped
  left–right, up–down and both) and average the estimates. A flip leaves the MTF along H and V unchanged
  (|OTF(−u, v)| = |OTF(u, v)| for a real PSF), so the views are estimates of the same 16 values with partly
  independent errors: AMAE 4–6 % lower for 2–4× the time (``docs/estimators.md``, session 10).
- ``posterior_split`` (Full-Meta noise-source models with the physics prior): a probability τ in (0, 1), default
  ``None`` (off). Where the closed-form mismatch posterior
  (:func:`~lightning_modules.mismatch_posterior.mismatch_posterior`) gives more than τ to "temperature or thermal
  white noise is wrong" and has evidence (≥ 32 flat-block details), the network's signal-independent noise
  σ̂_DCSN² + σ̂_RN² is kept and split between dark-current and readout noise in the posterior's ratio; everything
  else is the network's. Adds ``resplit`` (B,) bool to the output and ≈ 2 ms per patch. τ = 0.9 (chosen on the
  validation split): DCSN / RN RMS 0.56 / 0.56 → 0.48 / 0.41 DN on the 592-patch held-out set with mismatches of
  any field, unchanged within 0.01 DN with gain-only mismatches (``docs/estimators.md``, session 11).
- ``posterior_blend`` (Full-Meta noise-source models with the physics prior): ``"auto"`` (default: the setting stored
  in the weights file, off where it has none), ``None``/``False`` (off), ``True`` (:class:`PosteriorBlend`'s
  defaults), or a :class:`PosteriorBlend` / dict of its fields. Every output — σ per source, total, ξ — moves toward
  the closed-form mismatch posterior by a per-patch weight that is high only where the posterior has evidence (many
  flat-block details) and its texture check says the details are white noise: log σ̂ ← log σ̂ + w·(log σ_post −
  log σ̂), ξ̂ ← ξ̂ + w·(ξ_post − ξ̂). Adds ``posterior_weight`` (B,) (w; 0 = the network alone) and ≈ 2–3 ms per patch.
  ``noise_source_full_gain`` ships with it on (gain-only posterior, chosen on the validation split; session 14).
"""

from __future__ import annotations

import copy
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import torch

from camhealth.export import FORMAT_TAG, load_module
from camhealth.physics.metadata import FULL_FIELDS, CameraMetadata

__all__ = ["Estimator", "load_estimator", "shipped_models", "WEIGHTS_DIR", "assess_patches", "bucket_size",
           "posterior_resplit", "posterior_split_applies", "check_posterior_split", "PosteriorBlend", "blend_with_posterior"]

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"

#: Fraction of clipped pixels above which a patch is "black"/"saturated" (not assessable).
MAX_CLIPPED_FRACTION = 0.5
#: Contrast (std, DN) below which a patch carries no blur information ("featureless"; MTF only).
MIN_CONTRAST_DN = 2.0


def shipped_models() -> dict[str, Path]:
    """Names and files of the weights shipped inside the package (``camhealth/weights/*.pt``)."""
    return {p.stem: p for p in sorted(WEIGHTS_DIR.glob("*.pt"))}


def assess_patches(patches: torch.Tensor, kind: str) -> tuple[torch.Tensor, list[str]]:
    """Which B×1×P×P patches (in [0, 1]) an estimator of ``kind`` can assess, and why not.

    black / saturated: more than half of the pixels within 0.5 DN of 0 / 255 (noise is clipped away,
    blur invisible); featureless (MTF only): contrast below 2 DN (no edges to measure blur on)."""
    x = patches.flatten(1)
    x = x if x.dtype in (torch.float32, torch.float64) else x.float()
    tol = 0.5 / 255.0
    n = x.shape[1]
    # clipped counts only where a patch reaches 0/255; variance from two sums (Welford's var_mean is ~30×
    # slower here; values lie in [0, 1], so E[x²] − E[x]² in float64 cannot cancel below 1e-9)
    low = (x <= tol).sum(1, dtype=torch.int32) / n if bool((x.amin(1) <= tol).any()) else torch.zeros(x.shape[0])
    high = (x >= 1 - tol).sum(1, dtype=torch.int32) / n if bool((x.amax(1) >= 1 - tol).any()) else torch.zeros(x.shape[0])
    mean = x.sum(1).double() / n
    var = torch.linalg.vector_norm(x, dim=1).double().square() / n - mean.square()
    std_dn = var.clamp_min(0).sqrt() * 255.0
    reason = []
    for lo, hi, s in zip(low.tolist(), high.tolist(), std_dn.tolist()):
        if lo > MAX_CLIPPED_FRACTION:
            reason.append("black")
        elif hi > MAX_CLIPPED_FRACTION:
            reason.append("saturated")
        elif kind == "mtf" and s < MIN_CONTRAST_DN:
            reason.append("featureless")
        else:
            reason.append("")
    return torch.tensor([r == "" for r in reason], dtype=torch.bool), reason


def _to_patches(images: Any, patch_size: int, input_range: str) -> torch.Tensor:
    if input_range not in ("auto", "unit", "dn"):
        raise ValueError(f"input_range = {input_range!r} must be 'auto', 'unit' or 'dn'")
    if isinstance(images, np.ndarray):
        if images.dtype == object or images.dtype.kind not in "uif":
            raise TypeError(f"images must be a numeric array, got dtype {images.dtype}")
        is_int = images.dtype.kind in "ui"
        t = torch.from_numpy(np.ascontiguousarray(images))
    elif isinstance(images, torch.Tensor):
        if images.dtype == torch.bool or images.is_complex():
            raise TypeError(f"images must be a real numeric tensor, got dtype {images.dtype}")
        is_int = not images.is_floating_point()
        t = images.detach().cpu()
    else:
        raise TypeError(f"images must be a torch.Tensor or numpy.ndarray, got {type(images).__name__}")
    if t.ndim == 2:
        t = t[None, None]
    elif t.ndim == 3:
        t = t[:, None]
    if t.ndim != 4 or t.shape[1] != 1:
        raise ValueError(f"images must be B×1×H×W (or B×H×W, H×W) gray patches, got shape {tuple(t.shape)}")
    if tuple(t.shape[-2:]) != (patch_size, patch_size):
        raise ValueError(
            f"patches must be {patch_size}×{patch_size} px for this estimator, got {t.shape[-2]}×{t.shape[-1]}; "
            f"tile larger images (camhealth.monitor does)"
        )
    if t.shape[0] == 0:
        raise ValueError("images is an empty batch")
    t = t.to(torch.float64 if t.dtype == torch.float64 else torch.float32)
    lo_t, hi_t = torch.aminmax(t)  # one pass; NaN propagates into both, ±inf shows as an extreme
    lo, hi = float(lo_t), float(hi_t)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        bad = int((~torch.isfinite(t)).sum())
        raise ValueError(f"images contain {bad} non-finite value(s) (NaN/Inf); allowed: finite DN 0…255 or [0, 1]")
    if is_int or input_range == "dn":
        if lo < 0 or hi > 255:
            raise ValueError(f"images in DN must lie in [0, 255], got min {lo:g}, max {hi:g} (8-bit DN only)")
        t = t / 255.0
    else:
        if lo < -1e-6 or hi > 1 + 1e-6:
            hint = " (looks like DN: pass input_range='dn')" if hi <= 255 and lo >= 0 else ""
            raise ValueError(f"float images must lie in [0, 1], got min {lo:g}, max {hi:g}{hint}")
    return t.clamp(0, 1).float()


def _to_metadata(metadata: Any, batch: int, base_preset: str | None) -> CameraMetadata:
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


@dataclass
class Estimator:
    """A loaded estimator (see the module docstring for :meth:`predict`).

    Attributes:
        kind: ``"mtf"``, ``"drne"`` or ``"noise_source"``.
        patch_size: patch side in px the network was trained on.
        metadata_set: metadata :meth:`predict` needs: ``"none"``, ``"minimal"`` or ``"full"``.
        physics_prior: whether the closed-form σ per source is computed and passed to the network.
        prior_clipping: whether that prior also carries the σ after clipping (``prior_clipping`` models).
        noise_fit_statistics: whether it also carries the noise fits (``noise_fit_statistics`` models).
        mismatch_posterior: whether it also carries the mismatch posterior (``mismatch_posterior`` models).
        posterior_blend: the :class:`PosteriorBlend` :meth:`predict` applies by default (``posterior_blend="auto"``),
            from the file's ``inference`` settings; ``None`` where it has none.
        description: the file's JSON description (architecture, params, FLOPs, metrics, ...).
        source: where it was loaded from.
        backend: ``"torch"``, ``"pt2"`` or ``"onnx"``.
    """

    kind: str
    patch_size: int
    metadata_set: str
    physics_prior: bool
    description: dict
    source: str
    backend: str
    _run: Callable[..., torch.Tensor] = field(repr=False)
    _module: Any = field(default=None, repr=False)
    _prior_cache: dict = field(default_factory=dict, repr=False)  # (σ_DCSN, σ_RN) per metadata row
    prior_clipping: bool = False
    noise_fit_statistics: bool = False
    mismatch_posterior: bool = False
    posterior_blend: PosteriorBlend | None = None

    @property
    def name(self) -> str:
        return Path(self.source).stem

    def network_inputs(self, patches: torch.Tensor, meta: CameraMetadata | None) -> tuple[torch.Tensor, ...]:
        """Inputs of the bare network: patches, and for noise-source models normalised metadata + prior."""
        if self.kind != "noise_source":
            return (patches,)
        from lightning_modules.noise_features import physics_prior_dn

        b = patches.shape[0]
        if meta is None:
            return patches, patches.new_zeros(b, len(FULL_FIELDS)), patches.new_zeros(b, 4)
        if meta.batch_size not in (1, b):
            raise ValueError(f"metadata has batch size {meta.batch_size}; it must be 1 or the number of patches {b}")
        norm = meta.normalize("full").float().expand(b, -1)
        prior = (
            physics_prior_dn(
                patches, meta, self._prior_cache, clipping=self.prior_clipping, noise_fit=self.noise_fit_statistics,
                posterior=self.mismatch_posterior,
            )
            if self.physics_prior else patches.new_zeros(b, 4)
        )
        return patches, norm, prior

    @torch.inference_mode()
    def predict(
        self,
        images: Any,
        metadata: Any = None,
        *,
        input_range: str = "auto",
        base_preset: str | None = None,
        batch_size: int = 256,
        precision: str = "fp32",
        views: int = 1,
        posterior_split: float | None = None,
        posterior_blend: Any = "auto",
    ) -> dict[str, Any]:
        """Estimate blur or noise of patches; see the module docstring for inputs and outputs.

        ``precision``: ``"fp32"`` or ``"bf16"`` (CPU autocast; torch backend only). ``views`` (MTF only): 1, 2 or
        4 flipped copies of each patch whose estimates are averaged (module docstring). ``posterior_split``
        (Full-Meta noise-source models with the physics prior): τ in (0, 1), the mismatch-posterior probability of a
        temperature or white-noise error above which the DCSN/RN split follows the posterior (module docstring).
        ``posterior_blend`` (the same models): ``"auto"`` (the file's setting, :attr:`posterior_blend`), ``None``/
        ``False`` (off), ``True`` or a :class:`PosteriorBlend`/dict — every output moves toward the closed-form
        mismatch posterior where it has evidence and no texture (module docstring); applied before
        ``posterior_split``."""
        if precision not in ("fp32", "bf16"):
            raise ValueError(f"precision = {precision!r} must be 'fp32' or 'bf16'")
        if batch_size < 1:
            raise ValueError(f"batch_size = {batch_size} must be ≥ 1")
        if views not in (1, 2, 4):
            raise ValueError(f"views = {views!r} must be 1, 2 or 4")
        if views > 1 and self.kind != "mtf":
            raise ValueError(f"views = {views} averages flipped copies of MTF patches; estimator {self.name!r} is {self.kind!r}")
        if posterior_split is not None:
            check_posterior_split(posterior_split, self)
        blend = self.posterior_blend if isinstance(posterior_blend, str) and posterior_blend == "auto" else PosteriorBlend.from_value(posterior_blend)
        if blend is not None and not posterior_split_applies(self):
            raise ValueError(
                f"posterior_blend blends the outputs of a Full-Meta noise-source estimator with the physics prior with the "
                f"mismatch posterior; estimator {self.name!r} is {self.kind!r} with {self.metadata_set!r} metadata"
            )
        patches = _to_patches(images, self.patch_size, input_range)
        if views > 1:  # estimates of flipped copies are averaged below; the MTF along H and V is flip-invariant
            flips = [(-2, -1)] if views == 2 else [(-1,), (-2,), (-2, -1)]
            assessed = patches
            patches = torch.cat([patches] + [patches.flip(d) for d in flips])
        b = patches.shape[0]
        meta = None
        if self.metadata_set != "none":
            if metadata is None:
                raise ValueError(
                    f"estimator {self.name!r} reads {self.metadata_set!r} metadata: pass metadata= (CameraMetadata, "
                    f"a dict of fields in physical units, or a preset name)"
                )
            # Min-Meta networks read only gain, exposure and temperature: other fields may come from any preset.
            base = base_preset or ("ICX285" if self.metadata_set == "minimal" else None)
            meta = _to_metadata(metadata, b, base)
        outs, prior_totals = [], []
        for start in range(0, b, batch_size):
            sl = slice(start, start + batch_size)
            chunk = patches[sl]
            n = chunk.shape[0]
            if self.backend == "torch":  # pad to a bucket size: oneDNN reuses its kernels per batch shape
                chunk = _pad_batch(chunk, bucket_size(n))
            chunk_meta = meta if meta is None or meta.batch_size == 1 else _pad_meta(meta[sl], chunk.shape[0])
            inputs = self.network_inputs(chunk, chunk_meta)
            if blend is not None:  # σ_Total(M) before clipping: the prior's total column, for the blend's ξ
                prior_totals.append(inputs[2][:n, 3])
            if precision == "bf16" and self.backend == "torch":
                with torch.autocast("cpu", dtype=torch.bfloat16):
                    outs.append(self._run(*inputs, bf16=True)[:n].float())
            else:
                outs.append(self._run(*inputs)[:n].float())
        raw = torch.cat(outs)
        if not bool(torch.isfinite(raw).all()):
            raise FloatingPointError(f"estimator {self.name!r} produced non-finite outputs; please report this input")
        if views > 1:
            raw = raw.view(views, -1, *raw.shape[1:]).mean(0)
            patches = assessed
        assessable, reason = assess_patches(patches, self.kind)
        result: dict[str, Any] = {"assessable": assessable, "reason": reason}
        if self.kind == "mtf":
            result["mtf"] = raw.clamp(0, 1)
        elif self.kind == "drne":
            flat = raw.flatten(1)
            result.update(sigma_map=raw, sigma_total=flat.pow(2).mean(1).sqrt(), sigma_median=flat.median(1).values)
        else:
            sigma = raw[:, :3].clamp_min(0)
            # networks with the total head (total_branch) give the realised total after clipping as a fifth output
            total = raw[:, 4].clamp_min(0) if raw.shape[1] > 4 else sigma.pow(2).sum(1).sqrt()
            xi = raw[:, 3]
            if blend is not None:
                sigma, total, xi, result["posterior_weight"] = blend_with_posterior(
                    patches, meta, sigma, total, xi, blend, batch_size, total_model=torch.cat(prior_totals))
            if posterior_split is not None:
                sigma, result["resplit"] = posterior_resplit(patches, meta, sigma, float(posterior_split))
            result.update(sigma=sigma, sigma_total=total, xi=xi)
        return result


def posterior_split_applies(est: Any) -> bool:
    """Whether :meth:`Estimator.predict` ``posterior_split`` applies to ``est``: a Full-Meta noise-source estimator with
    the physics prior (the posterior needs every metadata field, and the re-split the network's per-source σ)."""
    return (getattr(est, "kind", "") == "noise_source" and getattr(est, "metadata_set", "") == "full"
            and bool(getattr(est, "physics_prior", False)))


def check_posterior_split(value: Any, est: Any, name: str = "posterior_split") -> float:
    """``value`` as a float τ in (0, 1) for estimator ``est``, or ``ValueError`` naming the value and the allowed
    range, or why ``est`` cannot take it (:func:`posterior_split_applies`)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 < float(value) < 1.0:
        raise ValueError(f"{name} = {value!r} must be a probability in (0, 1) (e.g. 0.9) or None")
    if not posterior_split_applies(est):
        desc = (f"{getattr(est, 'name', type(est).__name__)!r} ({getattr(est, 'kind', '?')!r}, "
                f"{getattr(est, 'metadata_set', '?')!r} metadata, physics prior {bool(getattr(est, 'physics_prior', False))})"
                if est is not None else "None")
        raise ValueError(
            f"{name} re-splits the dark-current and readout σ of a Full-Meta noise-source estimator with the physics "
            f"prior (e.g. 'noise_source_full_meta'); the estimator is {desc}"
        )
    return float(value)


def posterior_resplit(
    patches: torch.Tensor, meta: CameraMetadata, sigma: torch.Tensor, threshold: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Re-split the estimated σ_DCSN and σ_RN [DN] where the mismatch posterior is sure the temperature or the
    thermal white noise is wrong. Returns the new (B, 3) σ (PN, DCSN, RN) and the (B,) bool mask of re-split patches.

    ``patches``: B×1×P×P in [0, 1]; ``meta``: the metadata the estimator was given (batch 1 or B); ``sigma``: (B, 3)
    the network's σ [DN]; ``threshold``: τ in (0, 1). A temperature or white-noise error changes only the
    signal-independent noise, and which of the two sources took the change is what the network finds hardest (the
    DCSN/RN split floor, docs/estimators.md session 6); where the posterior
    (:func:`~lightning_modules.mismatch_posterior.mismatch_posterior`) puts more than τ on those two fields together
    and has evidence (≥ 32 flat-block details), σ̂_DCSN² + σ̂_RN² is kept and divided in the posterior's DCSN : RN
    variance ratio. PN, the total and ξ are not touched."""
    from lightning_modules.mismatch_posterior import MISMATCH_POSTERIOR, mismatch_posterior
    from lightning_modules.noise_features import _MIN_FIT_BLOCKS

    col = {name: i for i, name in enumerate(MISMATCH_POSTERIOR)}
    post = mismatch_posterior(patches.float(), meta).to(sigma.device)
    p_signal_independent = post[:, col["p_temperature_c"]] + post[:, col["p_white_noise_v_per_rthz"]]
    moved = (p_signal_independent > threshold) & (post[:, col["posterior_details"]] >= _MIN_FIT_BLOCKS)
    d2, r2 = post[:, col["posterior_dcsn_clipped_dn"]].double().square(), post[:, col["posterior_rn_clipped_dn"]].double().square()
    share = torch.where(d2 + r2 > 0, d2 / (d2 + r2).clamp_min(1e-300), torch.full_like(d2, 0.5))
    level = sigma[:, 1].double().square() + sigma[:, 2].double().square()
    out = sigma.clone()
    out[:, 1] = torch.where(moved, (level * share).sqrt(), sigma[:, 1].double()).to(sigma.dtype)
    out[:, 2] = torch.where(moved, (level * (1.0 - share)).sqrt(), sigma[:, 2].double()).to(sigma.dtype)
    return out, moved


@dataclass(frozen=True)
class PosteriorBlend:
    """How far a noise-source estimate follows the closed-form mismatch posterior, per patch.

    The posterior (:func:`~lightning_modules.mismatch_posterior.mismatch_posterior`, the physics of Eq. 3.14–3.19 and
    a Gaussian likelihood of the diagonal Haar details of the patch's flat blocks) is better than the network where its
    assumptions hold — enough flat blocks, white noise in them — and worse where texture passes its flatness tests
    (fine grass reads as noise) or clipping leaves few blocks. The weight w ∈ [0, ``weight``] of a patch is

        w = weight · ramp(texture; texture_hi → texture_lo) · ramp(details; details_lo → details_hi),

    with ``ramp`` linear from 0 to 1 between the two values and constant outside; ``details`` is the number of
    diagonal Haar details the likelihood used (the posterior abstains below 32), ``texture`` its texture check,
    log(horizontal-and-vertical / diagonal detail energy) on the kept blocks (≈ 0 for white noise). The outputs then
    move toward the posterior's: log σ̂_s ← log σ̂_s + w·(log σ_post,s − log σ̂_s) for PN, DCSN, RN and the total
    after clipping, ξ̂ ← ξ̂ + w·(ξ_post − ξ̂) with ξ_post = σ_Total(M) − E[σ_Total(M′)] (DN).

    Attributes:
        fields: the metadata fields the posterior may find wrong (one at a time): those a mismatch of the data can
            alter — ``("gain_db",)`` under the thesis's protocol (the default), all three of
            :data:`~lightning_modules.mismatch_posterior.POSTERIOR_FIELDS` for the configs' default data.
        weight: the largest w, in (0, 1] (default 0.7).
        texture_lo, texture_hi: texture check [log energy ratio] below which the ramp is 1 and above which it is 0
            (defaults 0.1 and 0.25).
        details_lo, details_hi: details count at or below which the ramp is 0 (≥ 32) and from which it is 1
            (defaults 100 and 150).

    The defaults were chosen for ``noise_source_full_gain`` on the validation split (1 536 patches with gain-only
    mismatches; ``docs/estimators.md``, session 14).
    """

    fields: tuple[str, ...] = ("gain_db",)
    weight: float = 0.7
    texture_lo: float = 0.1
    texture_hi: float = 0.25
    details_lo: float = 100.0
    details_hi: float = 150.0

    def __post_init__(self) -> None:
        from lightning_modules.noise_features import _MIN_FIT_BLOCKS

        fields = (self.fields,) if isinstance(self.fields, str) else tuple(self.fields)
        bad = [f for f in fields if f not in FULL_FIELDS]
        if bad or not fields or len(set(fields)) != len(fields):
            raise ValueError(f"PosteriorBlend fields = {list(fields)} must be distinct names from {list(FULL_FIELDS)} (at least one)")
        object.__setattr__(self, "fields", fields)
        for name in ("weight", "texture_lo", "texture_hi", "details_lo", "details_hi"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
                raise ValueError(f"PosteriorBlend {name} = {v!r} must be a finite number")
            object.__setattr__(self, name, float(v))
        if not 0.0 < self.weight <= 1.0:
            raise ValueError(f"PosteriorBlend weight = {self.weight!r} must be in (0, 1]")
        if not self.texture_lo < self.texture_hi:
            raise ValueError(f"PosteriorBlend texture_lo = {self.texture_lo!r} must be below texture_hi = {self.texture_hi!r}")
        if not _MIN_FIT_BLOCKS <= self.details_lo < self.details_hi:
            raise ValueError(
                f"PosteriorBlend details_lo = {self.details_lo!r} must be in [{_MIN_FIT_BLOCKS}, details_hi = {self.details_hi!r})"
                f" (the posterior abstains below {_MIN_FIT_BLOCKS} details)"
            )

    @classmethod
    def from_value(cls, value: Any) -> PosteriorBlend | None:
        """A :class:`PosteriorBlend` from ``True`` (the defaults), a dict of its fields or an instance; ``None`` for
        ``None``/``False``. Anything else is a ``ValueError`` naming the value."""
        if value is None or value is False:
            return None
        if value is True:
            return cls()
        if isinstance(value, cls):
            return value
        if isinstance(value, Mapping):
            unknown = sorted(set(value) - set(cls.__dataclass_fields__))
            if unknown:
                raise ValueError(f"posterior_blend has unknown key(s) {unknown}; allowed: {sorted(cls.__dataclass_fields__)}")
            return cls(**dict(value))
        raise ValueError(f"posterior_blend = {value!r} must be 'auto', None/False, True, a PosteriorBlend or a dict of its fields")

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready fields (what a weights file stores under ``inference.posterior_blend``)."""
        return {"fields": list(self.fields), "weight": self.weight, "texture_lo": self.texture_lo,
                "texture_hi": self.texture_hi, "details_lo": self.details_lo, "details_hi": self.details_hi}

    def weights(self, details: torch.Tensor, texture: torch.Tensor) -> torch.Tensor:
        """Per-patch w (float64) from the posterior's details count and texture check."""
        d, t = details.double(), texture.double()
        ramp_t = ((self.texture_hi - t) / (self.texture_hi - self.texture_lo)).clamp(0.0, 1.0)
        ramp_d = ((d - self.details_lo) / (self.details_hi - self.details_lo)).clamp(0.0, 1.0)
        return self.weight * ramp_t * ramp_d


def blend_with_posterior(
    patches: torch.Tensor, meta: CameraMetadata, sigma: torch.Tensor, total: torch.Tensor, xi: torch.Tensor,
    blend: PosteriorBlend, batch_size: int = 256, total_model: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Move noise-source estimates toward the mismatch posterior by :class:`PosteriorBlend`'s per-patch weight.

    ``patches``: B×1×P×P in [0, 1]; ``meta``: the metadata the estimator was given (batch 1 or B); ``sigma`` (B, 3)
    σ of PN, DCSN, RN, ``total`` (B,) the realised total after clipping and ``xi`` (B,) ξ, all in DN;
    ``total_model`` (B,): σ_Total(M) [DN] before clipping, the closed-form prior's total column — :meth:`Estimator.predict`
    passes the one its network inputs already hold; computed here when ``None``. Returns the blended (sigma, total,
    xi) in their dtypes and the weights w (B,) float32."""
    from lightning_modules.mismatch_posterior import mismatch_posterior
    from lightning_modules.noise_features import physics_prior_dn

    b = patches.shape[0]
    posts, totals_m = [], []
    for start in range(0, b, batch_size):
        sl = slice(start, start + batch_size)
        m = meta if meta.batch_size == 1 else meta[sl]
        posts.append(mismatch_posterior(patches[sl].float(), m, fields=blend.fields).double())
        if total_model is None:
            totals_m.append(physics_prior_dn(patches[sl].float(), m)[:, 3].double())
    post = torch.cat(posts)
    total_m = torch.cat(totals_m) if total_model is None else total_model.double()
    w = blend.weights(post[:, -2], post[:, -1])
    tiny = 1e-3  # DN; σ below it are zero for every purpose here, and the log stays finite
    original = torch.cat([sigma.double(), total.double().unsqueeze(1)], dim=1)
    own = original.clamp_min(tiny)
    target = post[:, :4].clamp_min(tiny)
    mixed = torch.where(w.unsqueeze(1) > 0, (own.log() + w.unsqueeze(1) * (target.log() - own.log())).exp(), original)
    xi_post = total_m - post[:, 4]
    xi_new = xi.double() + w * (xi_post - xi.double())
    return mixed[:, :3].to(sigma.dtype), mixed[:, 3].to(total.dtype), xi_new.to(xi.dtype), w.float()


def bucket_size(n: int) -> int:
    """Batch size a chunk of ``n`` patches is padded to before the network (torch backend): the next
    multiple of 4 up to 32, of 16 beyond. oneDNN builds (JIT-compiles) its convolution kernels per input
    shape and keeps ~1024 of them; a monitor whose per-frame patch counts vary from 1 to 80 would otherwise
    build new kernels on many frames (20–40 ms extra per new batch size here) and cycle the cache. The
    padding rows repeat the last patch and are dropped from the outputs."""
    if n <= 0:
        raise ValueError(f"batch of {n} patches")
    step = 4 if n <= 32 else 16
    return -(-n // step) * step


def _pad_batch(x: torch.Tensor, size: int) -> torch.Tensor:
    if x.shape[0] == size:
        return x
    return torch.cat([x, x[-1:].expand(size - x.shape[0], *x.shape[1:])])


def _pad_meta(meta: CameraMetadata, size: int) -> CameraMetadata:
    if meta.batch_size == size:
        return meta
    return meta[torch.cat([torch.arange(meta.batch_size), torch.full((size - meta.batch_size,), meta.batch_size - 1)])]


def _torch_runner(module) -> Callable[..., torch.Tensor]:
    net = module.export_module().float()
    if getattr(module, "channels_last", False):
        net = net.to(memory_format=torch.channels_last)
    nets: dict[bool, torch.nn.Module] = {False: net}

    def run(*inputs: torch.Tensor, bf16: bool = False) -> torch.Tensor:
        """``bf16=True`` (call it under CPU bf16 autocast): a copy of the network whose weights are stored in
        bf16 once, instead of being cast by autocast on every call (~10–15 % faster at monitor batch sizes;
        activations and arithmetic are what autocast gives either way)."""
        if bf16 and True not in nets:
            nets[True] = copy.deepcopy(net).to(torch.bfloat16)
        x = list(inputs)
        if getattr(module, "channels_last", False):
            x[0] = x[0].contiguous(memory_format=torch.channels_last)
        return nets[bf16](*x)

    return run


def _read_pt2(path: Path) -> tuple[dict, Callable[..., torch.Tensor]]:
    extra = {"camhealth.json": ""}
    try:
        ep = torch.export.load(str(path), extra_files=extra)
    except Exception as exc:
        raise ValueError(f"{path} is not a readable torch.export archive: {str(exc).splitlines()[0][:200]}") from None
    if not extra["camhealth.json"]:
        raise ValueError(f"{path} is an exported program but not a camhealth estimator (no camhealth.json inside)")
    desc = json.loads(extra["camhealth.json"])
    module = ep.module()
    return desc, lambda *x: module(*x)


def _read_onnx(path: Path) -> tuple[dict, Callable[..., torch.Tensor]]:
    import onnxruntime as ort

    try:
        session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    except Exception as exc:
        raise ValueError(f"{path} is not a readable ONNX model: {str(exc).splitlines()[0][:200]}") from None
    meta = session.get_modelmeta().custom_metadata_map
    if "camhealth.json" not in meta:
        raise ValueError(f"{path} is an ONNX model but not a camhealth estimator (no camhealth.json metadata)")
    names = [i.name for i in session.get_inputs()]

    def run(*inputs: torch.Tensor) -> torch.Tensor:
        feeds = {n: t.detach().cpu().float().numpy() for n, t in zip(names, inputs)}
        return torch.from_numpy(session.run(None, feeds)[0])

    return json.loads(meta["camhealth.json"]), run


def load_estimator(path_or_name: str | Path) -> Estimator:
    """Load a shipped model by name, or a weights/checkpoint/pt2/onnx file (see the module docstring)."""
    shipped = shipped_models()
    if isinstance(path_or_name, str) and path_or_name in shipped:
        path = shipped[path_or_name]
    else:
        path = Path(path_or_name)
        if not path.exists():
            raise FileNotFoundError(
                f"no estimator named or at {str(path_or_name)!r}: shipped names are {sorted(shipped)}; "
                f"files may be .pt/.ckpt (weights, Lightning checkpoint), .pt2 or .onnx"
            )
        if path.is_dir():
            raise ValueError(f"{path} is a folder; give a .pt, .ckpt, .pt2 or .onnx file")
    suffix = path.suffix.lower()
    module = None
    if suffix == ".pt2":
        desc, run = _read_pt2(path)
        backend = "pt2"
    elif suffix == ".onnx":
        desc, run = _read_onnx(path)
        backend = "onnx"
    else:
        module, desc = load_module(path)
        run = _torch_runner(module)
        backend = "torch"
    if desc.get("format", FORMAT_TAG) != FORMAT_TAG or desc.get("kind") not in ("mtf", "drne", "noise_source"):
        raise ValueError(f"{path}: unknown estimator description (kind {desc.get('kind')!r})")
    init_args = desc.get("init_args", {})
    inference = desc.get("inference") or {}
    if not isinstance(inference, Mapping):
        raise ValueError(f"{path}: 'inference' settings must be a mapping, got {type(inference).__name__}")
    try:
        blend = PosteriorBlend.from_value(inference.get("posterior_blend"))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: bad inference.posterior_blend: {exc}") from None
    return Estimator(
        kind=desc["kind"],
        patch_size=int(desc["patch_size"]),
        metadata_set=str(desc.get("metadata_set", "none")),
        physics_prior=bool(init_args.get("physics_prior", False)),
        prior_clipping=bool(init_args.get("prior_clipping", False)),
        noise_fit_statistics=bool(init_args.get("noise_fit_statistics", False)),
        mismatch_posterior=bool(init_args.get("mismatch_posterior", False)),
        posterior_blend=blend,
        description=desc,
        source=str(path),
        backend=backend,
        _run=run,
        _module=module,
    )
