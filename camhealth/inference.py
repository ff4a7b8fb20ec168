"""Inference with trained estimators: :func:`load_estimator` → :class:`Estimator` with ``predict``.

``load_estimator(path_or_name, device="cpu")`` accepts

- a **shipped model name** (a ``str``; no network access): ``"mtf"``, ``"drne"``, ``"noise_source_full"`` (physics-first, no
  weights), ``"noise_source_min"``, ``"noise_source_none"`` (see :func:`shipped_models`; files in
  ``camhealth/weights/`` with model cards);
- a **weights file** (``.pt``, :func:`camhealth.export.export_weights`) or a **Lightning checkpoint**
  (``.ckpt``) written by ``python -m camhealth.fit`` — loaded with ``torch.load(weights_only=True)``:
  tensors only, never arbitrary pickled code; anything else is rejected with a clear error;
- an **exported program** (``.pt2``, run with :func:`torch.export.load` after
  :func:`camhealth._pt2_check.check_pt2_archive` has refused pickled entries, non-operator call targets, guard code
  and symbolic shapes that are not plain arithmetic) or an **ONNX** file (``.onnx``, run with ONNX Runtime); the
  graph's inputs and outputs (their number, names in ONNX, and shapes) must be those of the estimator its
  ``camhealth.json`` description names (kind, patch size, metadata fields), else a ``ValueError`` names the file.

``Estimator.predict(images, metadata=None)``:

- ``images``: B×1×P×P gray patches (also B×P×P or P×P) as a torch tensor or NumPy array, P = ``patch_size``
  (128 for noise, 192 for MTF); an empty batch gives outputs with 0 rows. Colour is refused with a message naming
  the layout it looks like (H×W×C or B×H×W×C channels last, B×C×H×W), and so is a 3×P×P or 4×P×P array, which could
  be gray patches or one colour image (pass B×1×P×P). uint8 arrays are **DN**; floating arrays are
  **[0, 1]** (= DN/255) unless ``input_range="dn"``; a float input above 1 with the default
  ``input_range="auto"`` is refused with a hint, never silently rescaled. Integers wider than 8 bits (uint16,
  int32 …) are 8-bit DN only with ``input_range="dn"``: by default they are refused, as a 10–16-bit camera's dark
  frame holds values ≤ 255 too and would be read as 8-bit DN (scale such data to 8 bits or to [0, 1] first).
  Integers of any width with ``input_range="unit"`` are refused: integers are DN, not values in [0, 1].
- ``metadata``: required when ``metadata_set`` is ``"minimal"`` or ``"full"``, and checked alike where it is given to
  an estimator that reads none (``mtf``, ``drne``, ``noise_source_none``: a dict's missing fields from ``base_preset``
  or ICX285; the values are not used), so a bad preset name, file or value is an error everywhere:
  a :class:`~camhealth.physics.CameraMetadata` (batch 1 or B), a dict of fields in physical units
  (missing fields from ``base_preset``, e.g. ``{"gain_db": 12, "exposure_s": 0.01, "temperature_c": 40}``
  with ``base_preset="ICX285"``; without ``base_preset`` the dict must hold every field the network reads —
  gain, exposure and temperature for Min-Meta, whose other fields come from ICX285 — and a missing one is a
  ``ValueError`` naming it), a preset name, or the path of a ``.yaml``/``.json`` metadata file (the
  ``camera.yaml`` of ``python -m camhealth.calibrate``). Out-of-range values raise, naming field and range.
- returns a dict of float32 CPU tensors: ``mtf`` (B, 16) H then V, ``mtf_std`` and ``mtf_spread`` (B, 16) [kind ``mtf``]; ``sigma_total`` (B,) DN
  [noise kinds; for noise-source networks √(Σ σ_s²)]; ``sigma`` (B, 3) σ of PN, DCSN, RN in DN and ``xi`` (B,) DN [``noise_source``];
  ``sigma_map`` (B, 1, P, P) [``drne``]; ``assessable`` (B,) bool and ``reason`` (list of str: ``""``,
  ``"black"``, ``"saturated"``, ``"clipped"`` [neither more than half, but both together],
  ``"featureless"``, ``"no edges"`` [MTF: Gaussian-like texture, :func:`camhealth._inputs.has_edges`];
  every kind also ``"noise beyond validated range"`` (the patch's finest-scale fluctuations
  above 64 DN beyond doubt, :func:`~camhealth.estimators.physics_noise.beyond_validated_range`: the rule of every
  noise estimator, and of the MTF network, whose error outgrows its ``mtf_std`` there), the noise-source networks
  ``"less noise than the metadata allow"`` (far less noise than photon noise alone makes for any camera in the
  metadata's ranges, from 98 DN up, :func:`~camhealth.estimators.physics_noise.quieter_than_any_camera`)).
  Not-assessable patches still get finite numbers; do not trust them.
- noise-source networks (``noise_source_min``, ``noise_source_none``) state **no uncertainty**: ``xi_std`` (B,) is NaN
  (the physics-first estimator's is a number, ∞ where it has no evidence). Their ξ is the network's regression, which
  stayed near 0 on every mismatch tried (``noise_source_min`` on an ICX285 ramp told 6 dB: at 24 dB ξ −0.08 DN
  against a true −4.8 DN, with 10–60 DN of extra noise −0.10…−0.15 DN against −8…−53 DN); read a ξ alarm from
  ``noise_source_full`` where the full metadata are known.
- ``views`` (MTF models): 1 (default), 2 or 4 (an integer) — also run the patch flipped (2: rotated by 180°; 4: flipped
  left–right, up–down and both) and average the estimates. A flip leaves the MTF along H and V unchanged
  (|OTF(−u, v)| = |OTF(u, v)| for a real PSF), so the views are estimates of the same 16 values with partly
  independent errors: AMAE 4–6 % lower for 2–4× the time (``docs/estimators.md``). ``mtf_spread`` (B, 16) is the
  standard deviation of the views' estimates (unbiased, over 2 or 4 views; NaN with ``views=1``). ``mtf_std``
  (B, 16) is the 1-σ uncertainty of each value, √(r(Ĥ)² + spread²) (spread 0 with one view): r is the file's
  error table (description entry ``mtf_error``, :mod:`camhealth.estimators.mtf_error`), the RMS error at each
  estimate Ĥ measured by ``python -m camhealth.bench mtf_error`` on scenes unlike training's. A file without a table
  gives the spread alone (a lower bound of the error: it does not see what all views get wrong alike).
  MTF models read each patch with its defective pixels (hot, stuck, dead; :mod:`camhealth.estimators.defective_pixels`)
  replaced by their neighbours' mean, and return how many they replaced, ``defects`` (B, 2) int64 (bright, dark).
- ``noise_source_full`` is no network: the physics-first estimator
  (:class:`~camhealth.estimators.physics_noise.PhysicsNoiseEstimator`, same ``predict`` interface, plus ``xi_std``,
  ``p_match``, ``row_column_dn`` (B, 2): σ of row and column noise [DN] where detected, else 0,
  :mod:`camhealth.estimators.row_column_noise`; ``defects`` (B, 2) int64 and ``defect_mask`` (B, 1, P, P) int8:
  defective pixels, bright and dark, :mod:`camhealth.estimators.defective_pixels`; and ``pool``). The noise-source networks (``noise_source_min``, ``noise_source_none``) are for cameras
  with fewer metadata. Names and files of retired variants are refused with a message naming what replaced them.

``device``: where the network runs (``"cpu"``, ``"cuda"`` or ``"cuda:N"``; the torch backend — shipped names,
``.pt``, ``.ckpt``): each chunk of patches goes there and its outputs come back. The input checks, the
defective-pixel repair and the assessability checks stay on the CPU (cheap statistics, NumPy-backed there);
``noise_source_full`` runs its posterior (:func:`~camhealth.estimators.physics_noise.physics_noise_posterior`) on
the device. ``predict`` takes CPU or device tensors alike and returns CPU tensors either way. ``.pt2`` and
``.onnx`` files run on the CPU.
"""

from __future__ import annotations

import copy
import numbers
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch

from camhealth.estimators.defective_pixels import repair_defective_pixels
from camhealth._inputs import MAX_CLIPPED_FRACTION, MIN_CONTRAST_DN, _to_metadata, _to_patches, assess_patches, haar_noise_dn  # noqa: F401
from camhealth._validation import check_batch_size
from camhealth.estimators.mtf_error import MTFErrorTable, mtf_uncertainty
from camhealth.export import (BY_PHYSICS, FORMAT_TAG, MAX_EXPORT_BATCH, ONNX_NOISE_OUTPUTS, _check_description,
                              check_retired, load_net, network_metadata_set, parse_description)
from camhealth.nets import NetworkSpec
from camhealth.physics.metadata import FULL_FIELDS, METADATA_SETS, CameraMetadata

__all__ = ["Estimator", "load_estimator", "check_device", "shipped_models", "WEIGHTS_DIR", "assess_patches", "bucket_size",
           "PHYSICS_NOISE_MODEL", "RETIRED"]

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"

#: The Full-Meta noise-source estimator, which has no weights: the physics-first posterior
#: (:class:`~camhealth.estimators.physics_noise.PhysicsNoiseEstimator`).
PHYSICS_NOISE_MODEL = "noise_source_full"

#: Names of retired shipped models → what replaced them.
RETIRED: dict[str, str] = {
    "noise_source_full_gain": BY_PHYSICS, "noise_source_full_meta": BY_PHYSICS, "noise_source_full_pure": BY_PHYSICS,
    "noise_source_physics": "renamed 'noise_source_full'",
}


def shipped_models() -> dict[str, Path]:
    """Names and files of the weights shipped inside the package (``camhealth/weights/*.pt``); ``noise_source_full``
    has no file (:data:`PHYSICS_NOISE_MODEL`)."""
    return {p.stem: p for p in sorted(WEIGHTS_DIR.glob("*.pt"))}


@dataclass
class Estimator:
    """A loaded estimator (see the module docstring for :meth:`predict`).

    Attributes:
        kind: ``"mtf"``, ``"drne"`` or ``"noise_source"``.
        patch_size: patch side in px the network was trained on.
        metadata_set: metadata :meth:`predict` needs: ``"none"`` or ``"minimal"`` (noise-source networks).
        description: the file's JSON description (architecture, params, FLOPs, metrics, ...).
        source: where it was loaded from.
        backend: ``"torch"``, ``"pt2"`` or ``"onnx"``.
        device: where the network runs (the torch backend; module docstring).

    With the torch backend the network is a plain ``torch.nn.Module`` of :mod:`camhealth.nets` (no Lightning).
    """

    kind: str
    patch_size: int
    metadata_set: str
    description: dict
    source: str
    backend: str
    _run: Callable[..., torch.Tensor] = field(repr=False)
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    _net: Any = field(default=None, repr=False)
    _mtf_error: Any = field(default=None, repr=False)

    @property
    def name(self) -> str:
        return Path(self.source).stem

    @property
    def mtf_error(self) -> Any:
        """MTF models: the error table of the weights file (:class:`camhealth.estimators.mtf_error.MTFErrorTable`,
        behind ``mtf_std``), or None where the file has none."""
        return self._mtf_error

    def network_inputs(self, patches: torch.Tensor, meta: CameraMetadata | None) -> tuple[torch.Tensor, ...]:
        """Inputs of the bare network: patches, and for noise-source networks the normalised metadata (zeros without)."""
        if self.kind != "noise_source":
            return (patches,)
        b = patches.shape[0]
        graph = self.description.get("onnx_graph") or {}
        if self.backend == "onnx" and graph.get("self_contained"):  # raw metadata in physical units, own fields
            fields = graph.get("metadata_fields", [])
            if not fields:
                return (patches,)
            if meta is None:
                raise ValueError(f"estimator {self.name!r} reads metadata {fields}; pass metadata=")
            if meta.batch_size not in (1, b):
                raise ValueError(f"metadata has batch size {meta.batch_size}; it must be 1 or the number of patches {b}")
            return patches, torch.stack([getattr(meta, f).float() for f in fields], dim=1).expand(b, -1)
        if meta is None:
            return patches, patches.new_zeros(b, len(FULL_FIELDS))
        if meta.batch_size not in (1, b):
            raise ValueError(f"metadata has batch size {meta.batch_size}; it must be 1 or the number of patches {b}")
        return patches, meta.normalize("full").float().expand(b, -1)

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
    ) -> dict[str, Any]:
        """Estimate blur or noise of patches; see the module docstring for inputs and outputs.

        ``precision``: ``"fp32"`` or ``"bf16"`` (CPU autocast; torch backend only). ``views`` (MTF only): 1, 2 or
        4 flipped copies of each patch whose estimates are averaged (module docstring). ``batch_size``: patches per
        call of the network (≥ 1; a ``.pt2`` program, exported for at most
        :data:`~camhealth.export.MAX_EXPORT_BATCH` = 4096, runs chunks of at most that many)."""
        if precision not in ("fp32", "bf16"):
            raise ValueError(f"precision = {precision!r} must be 'fp32' or 'bf16'")
        batch_size = check_batch_size(batch_size)
        if isinstance(views, bool) or not isinstance(views, numbers.Integral) or int(views) not in (1, 2, 4):
            raise ValueError(f"views = {views!r} must be 1, 2 or 4 (an integer)")
        views = int(views)
        if views > 1 and self.kind != "mtf":
            raise ValueError(f"views = {views} averages flipped copies of MTF patches; estimator {self.name!r} is {self.kind!r}")
        patches = _to_patches(images, self.patch_size, input_range)
        if patches.shape[0] == 0:
            return self._empty_result(metadata, base_preset)
        if self.metadata_set == "none" and metadata is not None:
            self._unread_metadata(metadata, patches.shape[0], base_preset)
        defects = noise_dn = None
        if self.kind == "mtf":  # isolated impulses read as sparse edges and fine detail: the neighbours' mean instead
            noise_dn = haar_noise_dn(patches, torch.float64)  # σ̂ for the defect check and assess_patches alike
            patches, defects = repair_defective_pixels(patches, noise_dn)
            fixed = ((defects.hot + defects.dark) > 0).nonzero(as_tuple=True)[0]
            if fixed.numel():  # the repaired patches' own σ̂
                noise_dn = noise_dn.index_copy(0, fixed, haar_noise_dn(patches[fixed], torch.float64))
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
            meta = self._metadata(metadata, b, base_preset)
        outs = []
        # a .pt2 program's batch dimension ends at MAX_EXPORT_BATCH (its guard refuses more): chunks no larger
        step = min(batch_size, MAX_EXPORT_BATCH) if self.backend == "pt2" else batch_size
        for start in range(0, b, step):
            sl = slice(start, start + step)
            chunk = patches[sl]
            n = chunk.shape[0]
            if self.backend == "torch":  # pad to a bucket size: oneDNN reuses its kernels per batch shape
                chunk = _pad_batch(chunk, bucket_size(n))
            chunk_meta = meta if meta is None or meta.batch_size == 1 else _pad_meta(meta[sl], chunk.shape[0])
            if self.device.type != "cpu":
                chunk = chunk.to(self.device, non_blocking=True)
                chunk_meta = None if chunk_meta is None else chunk_meta.to(self.device)
            inputs = self.network_inputs(chunk, chunk_meta)
            if precision == "bf16" and self.backend == "torch":
                with torch.autocast(self.device.type, dtype=torch.bfloat16):
                    outs.append(self._run(*inputs, bf16=True)[:n].float().cpu())
            else:
                outs.append(self._run(*inputs)[:n].float().cpu())
        raw = torch.cat(outs)
        if not bool(torch.isfinite(raw).all()):
            bad = int((~torch.isfinite(raw)).sum())
            raise FloatingPointError(
                f"estimator {self.name!r} produced {bad} non-finite output value(s) of {raw.numel()} from finite input: "
                f"the network's arithmetic left float32's range. Its weights ({self.source}) were finite when loaded; "
                f"weights far larger than a trained network's would do this on any input — if they are the shipped or "
                f"your trained ones, please report this input"
            )
        spread = None
        if views > 1:
            per_view = raw.view(views, -1, *raw.shape[1:])
            raw, spread = per_view.mean(0), per_view.std(0)
            patches = assessed
        assessable, reason = assess_patches(patches, self.kind, noise_dn)
        if self.kind == "noise_source":  # what the network cannot vouch for: noise beyond the range, or none at all
            assessable, reason = _noise_source_limits(patches, reason)
        else:  # the validated noise range of every estimator (drne was validated to 60 DN; the MTF network's error
            # table, behind mtf_std, was measured with at most 10 DN of noise: beyond 64 DN the error outgrows mtf_std)
            assessable, reason = _noise_source_limits(patches, reason, quiet=False)
        result: dict[str, Any] = {"assessable": assessable, "reason": reason}
        if self.kind == "mtf":
            result["mtf"] = raw.clamp(0, 1)
            result["mtf_std"] = mtf_uncertainty(result["mtf"], self._mtf_error, spread)
            result["mtf_spread"] = spread if spread is not None else torch.full_like(result["mtf"], float("nan"))
            result["defects"] = torch.stack([defects.hot, defects.dark], 1)
        elif self.kind == "drne":
            flat = raw.flatten(1)
            result.update(sigma_map=raw, sigma_total=flat.pow(2).mean(1).sqrt(), sigma_median=flat.median(1).values)
        else:
            sigma = raw[:, :3].clamp_min(0)
            # the network states no uncertainty of its ξ (NaN: not known, unlike the physics-first estimator's)
            result.update(sigma=sigma, sigma_total=sigma.pow(2).sum(1).sqrt(), xi=raw[:, 3],
                          xi_std=torch.full((raw.shape[0],), float("nan")))
        return result


    def _metadata(self, metadata: Any, batch: int, base_preset: str | None) -> CameraMetadata:
        """``metadata`` as :class:`CameraMetadata` for ``batch`` patches. A dict without ``base_preset`` must give
        every field the network reads (``METADATA_SETS[metadata_set]``; a ``ValueError`` names the missing ones);
        the fields a Min-Meta network does not read come from the ICX285 preset."""
        if isinstance(metadata, Mapping) and base_preset is None:
            given = set(metadata) | ({"is_cmos"} if "sensor_type" in metadata else set())
            missing = [f for f in METADATA_SETS[self.metadata_set] if f not in given]
            if missing:
                raise ValueError(
                    f"estimator {self.name!r} reads {self.metadata_set!r} metadata {list(METADATA_SETS[self.metadata_set])}; "
                    f"metadata= lacks {missing}: give them, or base_preset= (e.g. 'ICX285') to take them from a preset"
                )
        # Min-Meta networks read only gain, exposure and temperature: the other fields may come from any preset.
        base = base_preset or ("ICX285" if self.metadata_set == "minimal" else None)
        return _to_metadata(metadata, batch, base)

    def _unread_metadata(self, metadata: Any, batch: int, base_preset: str | None) -> None:
        """Check ``metadata`` given to an estimator that reads none, as for one that reads it (type, preset name, file,
        ranges, unknown fields, batch size), and drop it: a typo or an impossible value is an error everywhere. A
        dict's missing fields come from ``base_preset`` or ICX285 (the network reads none of them)."""
        _to_metadata(metadata, batch, base_preset or "ICX285")

    def _empty_result(self, metadata: Any, base_preset: str | None = None) -> dict[str, Any]:
        """The outputs of :meth:`predict` for an empty batch: every entry with 0 rows (the metadata checked as for
        a full batch: a field out of range is an error whatever the number of patches)."""
        if self.metadata_set != "none":
            if metadata is None:
                raise ValueError(f"estimator {self.name!r} reads {self.metadata_set!r} metadata: pass metadata=")
            self._metadata(metadata, 0, base_preset)
        elif metadata is not None:
            self._unread_metadata(metadata, 0, base_preset)
        z = torch.zeros(0)
        result: dict[str, Any] = {"assessable": torch.zeros(0, dtype=torch.bool), "reason": []}
        if self.kind == "mtf":
            result["mtf"] = torch.zeros(0, 16)
            result["mtf_std"] = torch.zeros(0, 16)
            result["mtf_spread"] = torch.zeros(0, 16)
            result["defects"] = torch.zeros(0, 2, dtype=torch.int64)
        elif self.kind == "drne":
            result.update(sigma_map=torch.zeros(0, 1, self.patch_size, self.patch_size), sigma_total=z, sigma_median=z)
        else:
            result.update(sigma=torch.zeros(0, 3), sigma_total=z, xi=z, xi_std=z)
        return result


def _noise_source_limits(patches: torch.Tensor, reason: list[str], quiet: bool = True) -> tuple[torch.Tensor, list[str]]:
    """The assessability of a noise-source network's patches (B×1×P×P in [0, 1]) given the ``reason`` of
    :func:`assess_patches`: also refused, with the physics-first estimator's reasons, are patches whose finest-scale
    fluctuations exceed the validated σ beyond doubt (:func:`~camhealth.estimators.physics_noise.beyond_validated_range`:
    ``"noise beyond validated range"``) and patches far quieter than any camera state in the metadata's ranges makes
    (:func:`~camhealth.estimators.physics_noise.quieter_than_any_camera`: ``"less noise than the metadata allow"``) —
    the network was trained on neither and answers them with a number near its training range. ``quiet=False``
    (DRNE, which estimates the total noise of any source, camera or not, and the MTF network): the range alone."""
    from camhealth.estimators.physics_noise import BEYOND_VALIDATED, LESS_NOISE, beyond_validated_range, quieter_than_any_camera

    beyond = beyond_validated_range(patches).tolist()
    too_quiet = quieter_than_any_camera(patches).tolist() if quiet else [False] * len(beyond)
    out = list(reason)
    for i, r in enumerate(out):
        if not r:
            out[i] = BEYOND_VALIDATED if beyond[i] else LESS_NOISE if too_quiet[i] else ""
    return torch.tensor([r == "" for r in out], dtype=torch.bool), out


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


def _torch_runner(net: torch.nn.Module, channels_last: bool, device: torch.device) -> Callable[..., torch.Tensor]:
    net = net.eval().float().to(device)
    if channels_last:
        net = net.to(memory_format=torch.channels_last)
    nets: dict[bool, torch.nn.Module] = {False: net}

    def run(*inputs: torch.Tensor, bf16: bool = False) -> torch.Tensor:
        """``bf16=True`` (call it under CPU bf16 autocast): a copy of the network whose weights are stored in
        bf16 once, instead of being cast by autocast on every call (~10–15 % faster at monitor batch sizes;
        activations and arithmetic are what autocast gives either way)."""
        if bf16 and True not in nets:
            nets[True] = copy.deepcopy(net).to(torch.bfloat16)
        x = list(inputs)
        if channels_last:
            x[0] = x[0].contiguous(memory_format=torch.channels_last)
        return nets[bf16](*x)

    return run


def _exported_description(text: str, path: Path) -> dict:
    """The ``camhealth.json`` description of a ``.pt2`` or ``.onnx`` file, checked as a weights file's is
    (:func:`camhealth.export._check_description`); a ``ValueError`` naming the file and the field otherwise (also
    for JSON nested deeper than Python's recursion limit or an integer of more digits than Python reads)."""
    desc = _check_description(parse_description(text, path, "the camhealth.json description"), path)
    graph = desc.get("onnx_graph")
    if graph is not None and not isinstance(graph, dict):
        raise ValueError(f"{path}: description onnx_graph must be a JSON object, got {type(graph).__name__}")
    return desc


#: A graph's signature: (name or None, shape with None for a symbolic dimension) per input or output.
_Signature = list[tuple[str | None, tuple[int | None, ...]]]


def _expected_signature(desc: dict, onnx: bool) -> tuple[_Signature, _Signature]:
    """The inputs and outputs (names, shapes; batch None) that the graph of the estimator ``desc`` describes has:
    the bare network in a ``.pt2`` (names not checked), the named graph of :func:`camhealth.export.export_onnx`."""
    p, kind = int(desc["patch_size"]), desc["kind"]
    patch = ("patch" if onnx else None, (None, 1, p, p))
    if kind == "mtf":
        return [patch], [("mtf" if onnx else None, (None, 16))]
    if kind == "drne":
        return [patch], [("sigma_map" if onnx else None, (None, 1, p, p))]
    graph = desc.get("onnx_graph") or {}
    if onnx and graph.get("self_contained"):  # SelfContainedNoiseSource: raw metadata of the network's own fields
        k = len(METADATA_SETS[network_metadata_set(kind, desc.get("init_args", {}))])
        shapes = {"sigma": (None, 3)}
        return ([patch] + ([("metadata", (None, k))] if k else []),
                [(n, shapes.get(n, (None,))) for n in ONNX_NOISE_OUTPUTS])
    # the bare NoiseSourceNet: patches and the normalised (B, 11) metadata → σ_PN, σ_DCSN, σ_RN, ξ
    return [patch, (None, (None, len(FULL_FIELDS)))], [(None, (None, 4))]


def _signature_text(sig: _Signature) -> str:
    return ", ".join(f"{n or ''}[{', '.join('B' if d is None else str(d) for d in shape)}]" for n, shape in sig)


def _check_signature(path: Path, desc: dict, inputs: _Signature, outputs: _Signature, onnx: bool) -> None:
    """Refuse an exported graph whose inputs or outputs are not those of the estimator its description names (kind,
    patch size, metadata): a ``ValueError`` naming the file, what the graph has and what the description needs.
    A symbolic dimension of the graph matches any size; the batch dimension is not compared."""
    if onnx and desc["kind"] == "noise_source":
        graph = desc.get("onnx_graph") or {}
        if "self_contained" in graph and not isinstance(graph["self_contained"], bool):
            raise ValueError(f"{path}: description onnx_graph self_contained = {graph['self_contained']!r} must be "
                             "true or false")
        if graph.get("self_contained"):
            fields = list(METADATA_SETS[network_metadata_set(desc["kind"], desc.get("init_args", {}))])
            if graph.get("metadata_fields") != fields:
                raise ValueError(f"{path}: description onnx_graph metadata_fields = {graph.get('metadata_fields')!r} "
                                 f"must be {fields} (the fields the network reads, in the graph's column order)")
    want_in, want_out = _expected_signature(desc, onnx)

    def same(got: _Signature, want: _Signature) -> bool:
        return len(got) == len(want) and all(
            (wn is None or gn == wn) and len(gs) == len(ws)
            and all(g is None or w is None or g == w for g, w in zip(gs[1:], ws[1:]))
            for (gn, gs), (wn, ws) in zip(got, want)
        )

    if not (same(inputs, want_in) and same(outputs, want_out)):
        raise ValueError(
            f"{path}: the graph's inputs ({_signature_text(inputs)}) and outputs ({_signature_text(outputs)}) do not "
            f"match a {desc['kind']!r} estimator of patch size {desc['patch_size']}, as its description says (inputs "
            f"{_signature_text(want_in)}, outputs {_signature_text(want_out)}; B: the batch)"
        )


def _dims(shape) -> tuple[int | None, ...]:
    """A shape's dimensions: ints where fixed, None where symbolic (a SymInt, an ONNX dimension name or unknown)."""
    return tuple(d if isinstance(d, int) and not isinstance(d, bool) else None for d in shape)


def _pt2_signature(ep, path: Path) -> tuple[_Signature, _Signature]:
    """The user inputs and outputs of an exported program with the shapes the exporter recorded."""
    sig = ep.graph_signature
    nodes = {n.name: n for n in ep.graph.nodes}
    out_node = next((n for n in ep.graph.nodes if n.op == "output"), None)
    try:
        inputs = [(None, _dims(nodes[name].meta["val"].shape)) for name in sig.user_inputs]
        returned = {getattr(a, "name", None): a for a in (out_node.args[0] if out_node is not None else ())}
        outputs = [(None, _dims(returned[name].meta["val"].shape)) for name in sig.user_outputs]
    except (KeyError, AttributeError, TypeError):
        raise ValueError(f"{path}: the exported program does not record the shapes of its inputs and outputs; "
                         "re-export it with python -m camhealth.export") from None
    return inputs, outputs


def _read_pt2(path: Path) -> tuple[dict, Callable[..., torch.Tensor]]:
    from camhealth._pt2_check import check_pt2_archive

    check_pt2_archive(path)  # before torch opens it: torch's loader unpickles some entries without weights_only
    extra = {"camhealth.json": ""}
    try:
        ep = torch.export.load(str(path), extra_files=extra)
    except Exception as exc:
        raise ValueError(f"{path} is not a readable torch.export archive: {str(exc).splitlines()[0][:200]}") from None
    if not extra["camhealth.json"]:
        raise ValueError(f"{path} is an exported program but not a camhealth estimator (no camhealth.json inside)")
    desc = _exported_description(extra["camhealth.json"], path)
    _check_signature(path, desc, *_pt2_signature(ep, path), onnx=False)
    for what, tensors in (("weight", ep.state_dict), ("constant", ep.constants)):
        for key, value in tensors.items():
            _check_finite(path, f"the exported program's {what} {key!r}", value)
    module = ep.module()
    return desc, lambda *x: module(*x)


def _check_finite(path: Path, what: str, value: Any) -> None:
    """Refuse a floating-point tensor or array of a file that holds NaN or ±inf (the network would answer NaN)."""
    import numpy as np

    if isinstance(value, torch.Tensor):
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            n, total = int((~torch.isfinite(value)).sum()), value.numel()
        else:
            return
    elif isinstance(value, np.ndarray) and value.dtype.kind in "fc":
        if bool(np.isfinite(value).all()):
            return
        n, total = int((~np.isfinite(value)).sum()), value.size
    else:
        return
    raise ValueError(f"{path}: {what} holds {n} NaN or infinite value(s) of {total}; weights must be finite")


def _onnx_weights_finite(path: Path) -> None:
    """Refuse an ONNX file whose initializers or ``Constant`` nodes hold NaN or ±inf (read after ONNX Runtime accepted
    the file, so external data lie inside its folder)."""
    import onnx
    from onnx import numpy_helper

    try:
        model = onnx.load(str(path))
    except Exception as exc:
        raise ValueError(f"{path} is not a readable ONNX model: {str(exc).splitlines()[0][:200]}") from None

    def graphs(g):
        yield g
        for node in g.node:
            for attr in node.attribute:
                if attr.type == onnx.AttributeProto.GRAPH:
                    yield from graphs(attr.g)
                elif attr.type == onnx.AttributeProto.GRAPHS:
                    for sub in attr.graphs:
                        yield from graphs(sub)

    for g in graphs(model.graph):
        for init in g.initializer:
            _check_finite(path, f"the ONNX initializer {init.name!r}", numpy_helper.to_array(init))
        for node in g.node:
            if node.op_type == "Constant":
                for attr in node.attribute:
                    if attr.type == onnx.AttributeProto.TENSOR:
                        _check_finite(path, f"the ONNX constant {node.name or node.output[0]!r}",
                                      numpy_helper.to_array(attr.t))


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
    desc = _exported_description(meta["camhealth.json"], path)
    _check_signature(path, desc, [(i.name, _dims(i.shape)) for i in session.get_inputs()],
                     [(o.name, _dims(o.shape)) for o in session.get_outputs()], onnx=True)
    _onnx_weights_finite(path)
    self_contained = bool((desc.get("onnx_graph") or {}).get("self_contained"))

    def run(*inputs: torch.Tensor) -> torch.Tensor:
        feeds = {n: t.detach().cpu().float().numpy() for n, t in zip(names, inputs)}
        if self_contained:  # (sigma, xi, …): the (B, 4) σ_PN, σ_DCSN, σ_RN, ξ that predict reads
            sigma, xi = session.run(["sigma", "xi"], feeds)
            return torch.cat([torch.from_numpy(sigma), torch.from_numpy(xi)[:, None]], dim=1)
        return torch.from_numpy(session.run(None, feeds)[0])

    return desc, run


def check_device(device: torch.device | str | None) -> torch.device:
    """``device`` as a :class:`torch.device`: ``None``/``"cpu"``, or a CUDA device this machine has; anything else
    raises a ``ValueError`` that names the value and what is allowed."""
    if device is None:
        return torch.device("cpu")
    if not isinstance(device, (str, torch.device)):
        raise TypeError(f"device must be a str or torch.device, got {type(device).__name__}")
    try:
        dev = torch.device(device)
    except (RuntimeError, ValueError):
        raise ValueError(f"device = {device!r} is not a device name; allowed: 'cpu', 'cuda' or 'cuda:N'") from None
    if dev.type == "cpu":
        return torch.device("cpu")
    if dev.type != "cuda":
        raise ValueError(f"device = {device!r}: allowed are 'cpu', 'cuda' or 'cuda:N', got device type {dev.type!r}")
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if count == 0:
        raise ValueError(f"device = {device!r}: this machine has no CUDA device (torch.cuda.is_available() is False); "
                         f"use device='cpu'")
    index = 0 if dev.index is None else dev.index
    if not 0 <= index < count:
        raise ValueError(f"device = {device!r}: CUDA device index {index} is out of the allowed range [0, {count - 1}]")
    return torch.device("cuda", index)


def load_estimator(path_or_name: str | Path, device: torch.device | str | None = "cpu") -> Estimator:
    """Load a shipped model by name, or a weights/checkpoint/pt2/onnx file, with its network on ``device``
    (see the module docstring)."""
    if isinstance(path_or_name, bytes) or not isinstance(path_or_name, (str, os.PathLike)):
        names = sorted([*shipped_models(), PHYSICS_NOISE_MODEL])
        raise TypeError(f"path_or_name = {path_or_name!r} must be a shipped model's name (a str: {names}) or the path of a "
                        f".pt/.ckpt/.pt2/.onnx file (str or pathlib.Path), got {type(path_or_name).__name__}")
    if not isinstance(path_or_name, str):
        path_or_name = Path(path_or_name)
    if isinstance(path_or_name, (str, Path)) and Path(path_or_name).suffix.lower() in (".pt2", ".onnx") \
            and device is not None and str(device).split(":")[0] != "cpu":
        raise ValueError(f"device = {str(device)!r}: {Path(path_or_name).name} is a {Path(path_or_name).suffix} file, "
                         f"which runs on the CPU only; load a weights file (.pt) or a shipped name for device='cuda'")
    dev = check_device(device)
    if isinstance(path_or_name, str) and path_or_name == PHYSICS_NOISE_MODEL:
        from camhealth.estimators.physics_noise import PhysicsNoiseEstimator

        return PhysicsNoiseEstimator(source=PHYSICS_NOISE_MODEL, device=dev)
    if isinstance(path_or_name, str) and path_or_name in RETIRED:
        raise ValueError(f"the shipped model {path_or_name!r} is retired: {RETIRED[path_or_name]}")
    shipped = shipped_models()
    if isinstance(path_or_name, str) and path_or_name in shipped:
        path = shipped[path_or_name]
    else:
        path = Path(path_or_name)
        if not path.exists():
            raise FileNotFoundError(
                f"no estimator named or at {str(path_or_name)!r}: shipped names are {sorted([*shipped, PHYSICS_NOISE_MODEL])}; "
                f"files may be .pt/.ckpt (weights, Lightning checkpoint), .pt2 or .onnx"
            )
        if path.is_dir():
            raise ValueError(f"{path} is a folder; give a .pt, .ckpt, .pt2 or .onnx file")
    suffix = path.suffix.lower()
    net = None
    if suffix == ".pt2":
        desc, run = _read_pt2(path)
        backend = "pt2"
    elif suffix == ".onnx":
        desc, run = _read_onnx(path)
        backend = "onnx"
    else:
        net, desc = load_net(path)
        run = _torch_runner(net, NetworkSpec.channels_last(desc.get("init_args", {})), dev)
        backend = "torch"
    if desc.get("format", FORMAT_TAG) != FORMAT_TAG or desc.get("kind") not in ("mtf", "drne", "noise_source"):
        raise ValueError(f"{path}: unknown estimator description (kind {desc.get('kind')!r})")
    check_retired(desc, path)
    error = None
    if desc["kind"] == "mtf" and desc.get("mtf_error") is not None:
        error = MTFErrorTable.from_dict(desc["mtf_error"], str(path))
    return Estimator(
        kind=desc["kind"],
        patch_size=int(desc["patch_size"]),
        metadata_set=str(network_metadata_set(desc["kind"], desc.get("init_args", {}))),  # what the network reads
        description=desc,
        source=str(path),
        backend=backend,
        _run=run,
        _net=net,
        _mtf_error=error,
        device=dev,
    )
