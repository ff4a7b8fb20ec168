"""Shared machinery of the camhealth corruption modules (one deterministic ``apply_transform``)."""

from __future__ import annotations

import dataclasses
import math
import numbers
from typing import Any, Dict, Iterable, Mapping, Optional, Sequence

import numpy as np
import torch
from kornia.augmentation import IntensityAugmentationBase2D

from camhealth._validation import check_finite, check_float, check_tensor
from camhealth.augment._generators import params_to_metadata
from camhealth.physics.defocus_psf import defocus_psf
from camhealth.physics.image_formation import NOISE_SOURCES, ImageFormation, form_image
from camhealth.physics.metadata import CameraMetadata, SensorConstants
from camhealth.physics.motion_psf import linear_motion_psf, nonlinear_motion_psf
from camhealth.physics.mtf import mtf_hv
from camhealth.physics.readout_noise import source_follower_sigma_e

__all__ = ["CorruptionBase"]


class CorruptionBase(IntensityAugmentationBase2D):
    """Base of every camhealth corruption: builds PSFs and noise from ``params`` deterministically.

    Subclasses set ``_defocus_ks`` / ``_motion_ks`` (kernel sizes, ``None`` = component absent) and
    ``_sources`` (noise sources, empty = no noise) and provide a parameter generator. Per-component
    gates ``<component>_gate`` in ``params`` (used by :class:`CameraCorruption`) switch a component off
    per sample; Kornia's ``batch_prob`` switches the whole module off per sample.
    """

    _defocus_ks: Optional[int] = None
    _motion_ks: Optional[int] = None
    _sources: tuple[str, ...] = ()
    _quantize: bool = False
    _rng: str = "torch"

    def __init__(self, p: float, same_on_batch: bool, keepdim: bool) -> None:
        if isinstance(p, torch.Tensor) and p.ndim == 0 and not p.dtype.is_complex and p.dtype != torch.bool:
            p = p.item()  # a 0-d tensor holding a number
        # (NumPy's floats and ints are Real; a bool is no probability)
        if isinstance(p, bool) or not isinstance(p, numbers.Real) or not 0.0 <= float(p) <= 1.0:
            raise ValueError(f"p = {p!r} must be a probability in [0, 1] (a number), got {type(p).__name__} {p!r}")
        same_on_batch = check_flag(same_on_batch, "same_on_batch")
        keepdim = check_flag(keepdim, "keepdim")
        super().__init__(p=float(p), same_on_batch=same_on_batch, p_batch=1.0, keepdim=keepdim)
        self._formation: ImageFormation | None = None
        self._formation_params: Dict[str, torch.Tensor] | None = None  # the params the formation was made with
        self._sf_cache: tuple[torch.Tensor, torch.Tensor, SensorConstants] | None = None
        self._untouched_clipped: torch.Tensor | None = None  # (B,) clipped fraction of the samples left without noise

    def _repr_settings(self) -> Dict[str, Any]:
        """The settings the repr names after Kornia's ``p, p_batch, same_on_batch`` (subclasses add theirs)."""
        return {"keepdim": self.keepdim}

    def __repr__(self) -> str:
        base = super().__repr__()
        return base[:-1] + "".join(f", {k}={v!r}" for k, v in self._repr_settings().items()) + ")"

    # ------------------------------------------------------------------ helpers
    def forward(self, input: torch.Tensor, params: Optional[Dict[str, torch.Tensor]] = None,
                **kwargs: Any) -> torch.Tensor:  # noqa: D102 (Kornia's)
        # Kornia reads input.shape and params["batch_prob"] before any hook runs: a list as the image, or params that
        # are no dict, would fail inside Kornia with an AttributeError or an indexing error
        check_tensor(input, "input")
        if params is not None and not isinstance(params, Mapping):
            raise TypeError(f"params must be a dict of parameter tensors (aug._params, aug.forward_parameters(shape)), "
                            f"got {type(params).__name__}")
        return super().forward(input, params, **kwargs)

    def validate_tensor(self, input: torch.Tensor) -> None:  # noqa: D102 (Kornia hook)
        # Kornia calls this hook for images and for the masks of AugmentationSequential (which pass through an
        # intensity augmentation unchanged and may hold any labels): only the layout is checked here, the image's
        # values in transform_inputs.
        if input.ndim != 4:
            raise ValueError(f"input must have shape B×C×H×W (or C×H×W / H×W), got {tuple(input.shape)}")

    def transform_tensor(self, input: torch.Tensor, **kwargs: Any) -> torch.Tensor:  # noqa: D102 (Kornia hook)
        # Kornia refuses integer images here with its own message, before transform_inputs runs: give camhealth's
        # (with its hint to divide DN by 255). Masks (shape given) keep Kornia's handling.
        if kwargs.get("shape") is None:
            check_float(input, "input")
            if input.ndim not in (2, 3, 4):  # (Kornia's own message offers "(*, C, H, W)", then refuses 5-D)
                raise ValueError(f"input must have shape B×C×H×W, C×H×W or H×W (2 to 4 dims), got shape "
                                 f"{tuple(input.shape)}")
        return super().transform_tensor(input, **kwargs)

    @staticmethod
    def _check_image(input: torch.Tensor) -> torch.Tensor:
        """``input`` checked: floating point, finite and in [0, 1] — within :func:`range_tolerance` of it, the
        rounding a preceding filter leaves (Kornia's blurs return 1.0000001 on white), which is clamped away. An empty
        batch passes (it comes back empty); an empty height or width, or no channel in a non-empty batch, is a
        ``ValueError``, a sparse tensor a ``TypeError``."""
        check_float(input, "input")
        if input.layout != torch.strided:
            raise TypeError(f"input must be a dense tensor, got layout {input.layout}; convert it with x.to_dense()")
        if input.ndim >= 2 and (input.shape[-1] == 0 or input.shape[-2] == 0):
            raise ValueError(f"input must have a non-empty height and width (an empty batch is allowed), got shape "
                             f"{tuple(input.shape)}")
        if input.ndim == 4 and input.shape[0] > 0 and input.shape[1] == 0:
            raise ValueError(f"input must have at least one channel (C ≥ 1; an empty batch is allowed), got shape "
                             f"{tuple(input.shape)}")
        if input.numel() == 0:
            return input
        lo, hi = (float(v) for v in torch.aminmax(input.detach()))  # one pass; NaN propagates into lo/hi
        if not (math.isfinite(lo) and math.isfinite(hi)):
            check_finite(input, "input")
        if lo < 0 or hi > 1:
            tol = range_tolerance(input.dtype)
            if lo < -tol or hi > 1 + tol:
                raise ValueError(f"input must lie in [0, 1] (DN/255; {tol:.1e} of rounding beyond it is clamped), got "
                                 f"values in [{lo!r}, {hi!r}]")
            input = input.clamp(0, 1)
        return input

    def transform_inputs(self, input: torch.Tensor, params: Dict[str, torch.Tensor], flags: Dict[str, Any],
                         transform: Optional[torch.Tensor] = None, **kwargs: Any) -> torch.Tensor:  # noqa: D102
        input = self._check_image(input)
        if params is not None:
            _check_param_rows(params, input.shape[0] if input.ndim == 4 else 1)
            _check_batch_prob(params)
        return super().transform_inputs(input, params, flags, transform=transform, **kwargs)

    @staticmethod
    def _param_gate(params: Dict[str, torch.Tensor], name: str, device: torch.device | None = None) -> torch.Tensor | None:
        """The gate ``<name>_gate`` of ``params`` as a bool tensor (1 or B values; ``None`` where params carry none),
        or ``ValueError`` naming it unless every value is 0 (the component off) or 1 (on)."""
        key = f"{name}_gate"
        if key not in params:
            return None
        raw = params[key]
        g = raw if isinstance(raw, torch.Tensor) else torch.as_tensor(raw)
        _check_zero_one(g, key, f"0 ({name} off) or 1 ({name} on)")
        return (g if device is None else g.to(device)) != 0

    def _component_gate(self, params: Dict[str, torch.Tensor], name: str, b: int, device: torch.device) -> torch.Tensor:
        """(b,) bool: the samples whose component ``name`` is applied — its gate in ``params`` and, where Kornia blends
        by it (p < 1), ``batch_prob``; at p = 1 Kornia applies the transform to every sample whatever ``batch_prob``
        says (replayed params of a p < 1 module), and so do the labels."""
        g = torch.ones(b, dtype=torch.bool, device=device)
        gate = self._param_gate(params, name, device)
        if gate is not None:
            g = g & gate
        if "batch_prob" in params and self._blends():
            g = g & (params["batch_prob"].to(device).reshape(-1).expand(b) > 0.5)
        return g

    def _blends(self) -> bool:
        """Whether Kornia blends the output by ``batch_prob`` (p < 1 or p_batch < 1), rather than transforming every
        sample."""
        return not (float(self.p) == 1.0 and float(self.p_batch) == 1.0)

    def defocus_psf(self, params: Dict[str, torch.Tensor], device: torch.device | None = None,
                    dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """(B, k, k) defocus kernels of ``params`` (delta where the component is gated off), in ``dtype``
        (float32, or float64 for float64 images)."""
        self._require(params, ("diameter",), "defocus")
        d = _real_param(params, "diameter").to(device=device, dtype=dtype)
        gate = self._param_gate(params, "defocus", d.device)
        if gate is not None:
            d = torch.where(gate, d, torch.zeros_like(d))
        return defocus_psf(d, self._defocus_ks)

    def motion_psf(self, params: Dict[str, torch.Tensor], device: torch.device | None = None,
                   dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """(B, k, k) motion kernels of ``params`` (delta where the component is gated off), in ``dtype``
        (float32, or float64 for float64 images)."""
        self._require(params, ("length", "angle", "intensity"), "motion")
        length = _real_param(params, "length").to(device=device, dtype=dtype)
        gate = self._param_gate(params, "motion", length.device)
        if gate is not None:
            length = torch.where(gate, length, torch.zeros_like(length))
        angle = _real_param(params, "angle").to(device=length.device, dtype=dtype)
        intensity = _real_param(params, "intensity").to(device=length.device, dtype=dtype)
        if bool((intensity == 0).all()):
            return linear_motion_psf(length, angle, self._motion_ks)
        self._require(params, ("shake_noise",), "non-linear motion (intensity > 0)")
        shake = _real_param(params, "shake_noise").to(device=length.device, dtype=dtype)
        return nonlinear_motion_psf(length, angle, intensity, shake, self._motion_ks)

    def _source_follower(self, meta: CameraMetadata) -> torch.Tensor:
        """σ_SF depends only on (W, f_clock, A_SN, sensor type) and the fixed constants: cache it across batches
        with fixed sensors."""
        key = torch.stack([meta.white_noise_v_per_rthz, meta.pixel_clock_hz, meta.sense_node_gain_v_per_e, meta.is_cmos])
        cache = self._sf_cache
        if (cache is not None and cache[2] == meta.constants and cache[0].shape == key.shape
                and cache[0].dtype == key.dtype and torch.equal(cache[0], key)):
            return cache[1]
        sf = source_follower_sigma_e(meta)
        self._sf_cache = (key, sf, meta.constants)
        return sf

    def _require(self, params: Dict[str, torch.Tensor], keys: Sequence[str], what: str) -> None:
        """``ValueError`` naming the keys of ``keys`` that ``params`` lack (``what`` needs them)."""
        missing = [k for k in keys if k not in params]
        if missing:
            raise ValueError(
                f"params lack {missing}: the {what} of {type(self).__name__} is made from {list(keys)}; pass the params "
                "of a call (aug._params, aug.forward_parameters(shape)) or give every key"
            )

    @staticmethod
    def _noise_seed_groups(params: Dict[str, torch.Tensor], b: int) -> list[tuple[int, torch.Tensor | None]]:
        """The samples of each noise seed: ``[(seed, indices)]`` (int64 indices on the CPU), or ``[(seed, None)]``
        when the whole batch shares one seed (one scalar, or the same value in every row)."""
        if "noise_seed" not in params:
            raise ValueError("params lack 'noise_seed': the noise is drawn from it (one int64 seed for the batch, or one "
                             "per sample) together with the meta_<field> and const_<field> entries; pass the params of a "
                             "call (aug._params, RandomSensorNoise.params_from_metadata(meta, seed=...))")
        seeds = torch.as_tensor(params["noise_seed"]).detach().reshape(-1).cpu()
        if seeds.dtype == torch.bool or seeds.is_floating_point() or seeds.is_complex():
            raise TypeError(f"noise_seed must hold integers (a torch.int64 tensor, one seed or one per sample), got "
                            f"{seeds.dtype} {seeds.tolist()[:4]}: a fractional seed would be truncated, and samples with "
                            "different seeds would share their noise")
        if seeds.numel() not in (1, b):
            raise ValueError(f"noise_seed has {seeds.numel()} values for a batch of {b}: give one seed, or one per sample")
        if seeds.numel() == 1 or bool((seeds == seeds[0]).all()):
            return [(int(seeds[0]), None)]
        uniq, inverse = torch.unique(seeds, return_inverse=True)
        return [(int(u), (inverse == j).nonzero().squeeze(1)) for j, u in enumerate(uniq.tolist())]

    # ------------------------------------------------------------------ the transform
    def apply_transform(
        self,
        input: torch.Tensor,
        params: Dict[str, torch.Tensor],
        flags: Dict[str, Any],
        transform: Optional[torch.Tensor] = None,
    ) -> torch.Tensor:
        dev = input.device
        self._formation_params = _snapshot(params)
        self._untouched_clipped = None
        if input.shape[0] == 0:  # an empty batch comes back empty, with empty labels
            self._formation = _empty_formation(input)
            return input.clone()
        # the kernels in the physics' work dtype: float64 for float64 images, float32 otherwise
        pdt = torch.float64 if input.dtype == torch.float64 else torch.float32
        dpsf = self.defocus_psf(params, dev, pdt) if self._defocus_ks is not None else None
        mpsf = self.motion_psf(params, dev, pdt) if self._motion_ks is not None else None
        if not self._sources:
            result = form_image(input, None, defocus_psf=dpsf, motion_psf=mpsf, sources=(), quantize=self._quantize)
        else:
            meta = params_to_metadata(params)
            if meta.device != dev:
                meta = meta.to(device=dev)
            sf = self._source_follower(meta)
            groups = self._noise_seed_groups(params, input.shape[0])
            parts, order = [], []
            for seed, idx in groups:  # one group (the whole batch) unless the samples carry different seeds
                generator = torch.Generator(device=dev)
                generator.manual_seed(seed)
                sel = (lambda t: t) if idx is None else (lambda t, i=idx.to(dev): t.index_select(0, i))
                parts.append(form_image(
                    sel(input),
                    meta if idx is None else meta[idx.to(meta.device)],
                    defocus_psf=None if dpsf is None else sel(dpsf),
                    motion_psf=None if mpsf is None else sel(mpsf),
                    sources=self._sources,
                    generator=generator,
                    quantize=self._quantize,
                    source_follower_e=sel(sf),
                    rng=self._rng,
                ))
                if idx is not None:
                    order.append(idx)
            result = parts[0] if len(parts) == 1 else _merge_formations(parts, torch.cat(order).to(dev))
        out = result.image
        if self._sources:
            on = self._component_gate(params, "noise", input.shape[0], dev)
            if not bool(on.all()):  # (p = 1, the default, keeps every sample: no pass needed)
                # a sample whose noise is gated off gets the blurred image, with the blur's gradient; one that Kornia
                # leaves untouched (batch_prob 0) gets its input: their clipped fraction is that of what they get
                out = torch.where(on.view(-1, 1, 1, 1), out, result.blurred.clamp(0, 1).to(out.dtype))
                applied = (params["batch_prob"].to(dev).reshape(-1).expand(input.shape[0]) > 0.5
                           if "batch_prob" in params and self._blends() else torch.ones_like(on)).view(-1, 1, 1, 1)
                got = torch.where(applied, result.blurred.detach(), input.detach().to(result.blurred.dtype))
                self._untouched_clipped = ((got <= 0) | (got >= 1)).flatten(1).to(result.clipped_fraction.dtype).mean(1)
        self._formation = dataclasses.replace(result, blurred=result.blurred.detach())
        return out

    # ------------------------------------------------------------------ labels
    def labels(self, params: Dict[str, torch.Tensor] | None = None) -> Dict[str, Any]:
        """Labels of the last call (or of ``params``): what a learner needs.

        Returns a dict with, as present: ``mtf`` (B, 16) — H then V at the 8 normalised frequencies of
        the applied PSF (1 where no blur was applied); ``sigma_dn`` (B, 3) realised σ of (PN, DCSN, RN)
        after clipping; ``sigma_total_dn`` (B,); ``sigma_expected_dn`` (B, 3) and
        ``sigma_total_expected_dn`` (B,) analytic; ``clipped_fraction`` (B,); ``metadata``
        (:class:`CameraMetadata`). Noise labels need the last forward call (they depend on the image): for a
        noise module ``params`` must hold the values of that call (else ``ValueError``: replay them first with
        ``aug(x, params=params)``); blur labels follow ``params`` alone. An empty batch gives labels with 0 rows.
        """
        params = self._params if params is None else params
        if not params:
            raise RuntimeError("no parameters yet: call the module on a batch first, or pass params")
        if "forward_input_shape" in params:
            b = int(params["forward_input_shape"][0])
        elif "batch_prob" in params:
            b = int(params["batch_prob"].numel())
        else:
            raise ValueError(f"params {sorted(params)} hold neither 'forward_input_shape' nor 'batch_prob': pass the params "
                             "of a call (aug._params, aug.forward_parameters(shape)), which hold the batch size")
        f = self._formation
        if f is not None and self._formation_params is not None and _same_params(params, self._formation_params):
            # the params of the last call: their labels are of the batch they were applied to (params of one row, e.g.
            # params_from_metadata of batch-1 metadata, apply to every sample; forward_input_shape then says 1)
            b = int(f.image.shape[0])
        _check_param_rows(params, b)
        _check_batch_prob(params)
        if self._sources and not _same_params(params, self._formation_params):
            raise ValueError(
                "labels(params=...): the noise labels depend on the image and are those of the last call, which used other "
                "params; replay that call first (aug(x, params=params)), then call aug.labels()"
            )
        out: Dict[str, Any] = {}
        if b == 0:
            return self._empty_labels(params)
        if self._defocus_ks is not None or self._motion_ks is not None:
            mtf = None
            if self._defocus_ks is not None:
                mtf = mtf_hv(self.defocus_psf(params))
                mtf = torch.where(self._component_gate(params, "defocus", b, mtf.device)[:, None], mtf, torch.ones_like(mtf))
            if self._motion_ks is not None:
                m = mtf_hv(self.motion_psf(params))
                m = torch.where(self._component_gate(params, "motion", b, m.device)[:, None], m, torch.ones_like(m))
                mtf = m if mtf is None else mtf * m
            out["mtf"] = mtf.expand(b, -1).contiguous() if mtf.shape[0] != b else mtf
        if self._sources:
            meta = params_to_metadata(params)
            out["metadata"] = meta.expand(b) if meta.batch_size == 1 and b != 1 else meta
            if f is None or f.sigma_dn.shape[0] != b:
                raise RuntimeError(
                    f"noise labels need a forward call on this batch before labels(): the params are of a batch of {b}, "
                    + ("no call was made yet" if f is None else f"the last call had {int(f.sigma_dn.shape[0])} samples")
                )
            on = self._component_gate(params, "noise", b, f.sigma_dn.device)
            for name in ("sigma_dn", "sigma_total_dn", "sigma_expected_dn", "sigma_total_expected_dn", "clipped_fraction"):
                v = getattr(f, name)
                mask = on.view(-1, *([1] * (v.ndim - 1)))
                if name == "clipped_fraction":  # of the output each sample got (its blurred image or its input where off)
                    off = self._untouched_clipped
                    out[name] = v if off is None else torch.where(on, v, off.to(v.device, v.dtype))
                else:
                    out[name] = torch.where(mask, v, torch.zeros_like(v))
        return out

    def _empty_labels(self, params: Dict[str, torch.Tensor]) -> Dict[str, Any]:
        """The labels of an empty batch: every entry with 0 rows."""
        out: Dict[str, Any] = {}
        if self._defocus_ks is not None or self._motion_ks is not None:
            out["mtf"] = torch.ones(0, 16)
        if self._sources:
            out["metadata"] = params_to_metadata(params)
            f = self._formation
            assert f is not None
            out.update(sigma_dn=f.sigma_dn, sigma_total_dn=f.sigma_total_dn, sigma_expected_dn=f.sigma_expected_dn,
                       sigma_total_expected_dn=f.sigma_total_expected_dn, clipped_fraction=f.clipped_fraction)
        return out


def range_tolerance(dtype: torch.dtype) -> float:
    """How far beyond [0, 1] an image of ``dtype`` may lie and be clamped into it: two units in the last place at 1
    (bfloat16 0.016, float16 0.002), at least 1e-5 (a few float32 roundings of a filter)."""
    return max(1e-5, 2.0 * torch.finfo(dtype).eps)


def _snapshot(params: Dict[str, torch.Tensor]) -> Dict[str, torch.Tensor]:
    """Copies of the tensors of ``params`` (what a call's labels were made from)."""
    return {k: v.detach().clone() for k, v in params.items() if isinstance(v, torch.Tensor) and k != "forward_input_shape"}


def _same_params(params: Dict[str, torch.Tensor], snapshot: Dict[str, torch.Tensor] | None) -> bool:
    """Whether ``params`` holds the values ``snapshot`` was taken of (same keys, equal tensors)."""
    if snapshot is None:
        return True  # no call yet: labels() says so itself
    mine = {k: v for k, v in params.items() if isinstance(v, torch.Tensor) and k != "forward_input_shape"}
    if mine.keys() != snapshot.keys():
        return False
    return all(
        mine[k].shape == v.shape and torch.equal(mine[k].detach().to(v.device, v.dtype), v) for k, v in snapshot.items()
    )


def _merge_formations(parts: Sequence[ImageFormation], order: torch.Tensor) -> ImageFormation:
    """One :class:`ImageFormation` of the batch from results of its sample groups: ``parts`` hold the samples
    ``order`` (their batch indices, concatenated in the parts' order). Differentiable (a gather)."""
    inverse = torch.empty_like(order)
    inverse[order] = torch.arange(order.numel(), device=order.device)
    return ImageFormation(*(torch.cat([getattr(p, f.name) for p in parts]).index_select(0, inverse)
                            for f in dataclasses.fields(ImageFormation)))


def _empty_formation(input: torch.Tensor) -> ImageFormation:
    z = input.new_zeros(0, dtype=torch.float64 if input.dtype == torch.float64 else torch.float32)
    return ImageFormation(image=input.clone(), sigma_dn=z.reshape(0, 3), sigma_total_dn=z, sigma_expected_dn=z.reshape(0, 3),
                          sigma_total_expected_dn=z, clipped_fraction=z, blurred=input.clone())


def check_flag(value: Any, name: str) -> bool:
    """``value`` if it is a bool (Python or NumPy), else ``TypeError`` naming ``name`` (``"no"`` would read as True)."""
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} = {value!r:.40} must be True or False (a bool), got {type(value).__name__}")
    return bool(value)


def _check_param_rows(params: Dict[str, torch.Tensor], b: int) -> None:
    """``ValueError`` naming the first per-sample entry of ``params`` whose rows are neither 1 (the whole batch) nor
    ``b`` (one per sample)."""
    for key, v in params.items():
        if key == "forward_input_shape":
            continue
        if isinstance(v, (list, tuple, np.ndarray)):  # (per-sample values given as a list: their rows count too)
            try:
                v = torch.as_tensor(v)
            except (TypeError, ValueError, RuntimeError):
                continue  # (not numbers: the entry's own check names it)
        if not isinstance(v, torch.Tensor) or v.ndim == 0:
            continue
        if v.shape[0] not in (1, b):
            what = "values" if v.ndim == 1 else "rows"
            raise ValueError(f"params {key} has {v.shape[0]} {what} for a batch of {b} (shape {tuple(v.shape)}): give one "
                             f"per sample ({b}), or one for the whole batch")


def _check_batch_prob(params: Dict[str, torch.Tensor]) -> None:
    """``ValueError`` unless the ``batch_prob`` of ``params`` (where present) holds 0 (sample left untouched) or 1
    (transformed) per sample: Kornia applies a sample where it is above 0.5, so NaN would leave it untouched."""
    if "batch_prob" not in params:
        return
    bp = params["batch_prob"]
    if not isinstance(bp, torch.Tensor):  # (Kornia compares it with 0.5 as a tensor)
        raise TypeError(f"params batch_prob must be a tensor of 0 or 1 per sample, got {type(bp).__name__} {bp!r:.40}")
    _check_zero_one(bp, "batch_prob", "0 (sample left untouched) or 1 (transformed)")


def _check_zero_one(g: torch.Tensor, key: str, meaning: str) -> None:
    """``TypeError`` for a complex ``g``, ``ValueError`` naming the first value of ``g`` (params entry ``key``) that is
    neither 0 nor 1 (NaN included); ``meaning`` says what 0 and 1 stand for."""
    if g.is_complex():
        raise TypeError(f"params {key} must hold 0 or 1 per sample, got dtype {g.dtype}")
    if g.dtype != torch.bool:
        bad = (g != 0) & (g != 1)  # (NaN included)
        if bool(bad.any()):
            first = g[bad].flatten()[0].item()
            raise ValueError(f"params {key} must hold {meaning} per sample, got {first!r} "
                             f"({int(bad.sum())} of {g.numel()} values are neither)")


def _real_param(params: Dict[str, torch.Tensor], key: str) -> torch.Tensor:
    """``params[key]`` as a tensor of real numbers (a number, list or array is converted), else ``TypeError`` naming
    the key (a bool would read as 0 or 1 px)."""
    raw = params[key]
    try:
        v = raw if isinstance(raw, torch.Tensor) else torch.as_tensor(raw)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"params {key} must be a tensor of real numbers (one per sample, or one for the batch), got "
                        f"{type(raw).__name__} {raw!r:.40}") from None
    if v.dtype == torch.bool or v.is_complex():
        raise TypeError(f"params {key} must hold real numbers (one per sample, or one for the batch), got dtype {v.dtype}")
    return v


def check_sources(sources: Sequence[str]) -> tuple[str, ...]:
    """Validate a selection of noise sources (subset of ``("photon", "dark", "readout")``)."""
    if isinstance(sources, str):
        sources = (sources,)
    if sources is None or not isinstance(sources, Iterable):
        raise TypeError(f"sources must be a noise source name or a sequence of them (from {list(NOISE_SOURCES)}), got "
                        f"{type(sources).__name__} {sources!r:.40}")
    sources = tuple(sources)
    bad = [s for s in sources if s not in NOISE_SOURCES]
    if bad:
        raise ValueError(f"unknown noise source(s) {bad}; choose from {list(NOISE_SOURCES)}")
    return tuple(s for s in NOISE_SOURCES if s in sources)
