"""Parameter generators: all randomness of the corruption modules lives here (Kornia convention).

Each generator returns a dict of per-sample tensors (first dim B). Replaying a corruption with
``aug(x, params=aug._params)`` reproduces it exactly, including the noise field (drawn from torch
generators seeded with ``params["noise_seed"]``: the samples that share a seed draw their noise together, a
sample with a seed of its own draws it alone). Sampling uses torch's global RNG, so ``torch.manual_seed`` makes
a run reproducible, as in Kornia.
"""

from __future__ import annotations

import dataclasses
import numbers
from typing import Any, Mapping

import numpy as np
import torch
from kornia.augmentation.random_generator.base import RandomGeneratorBase
from kornia.augmentation.utils import _adapted_rsampling
from torch.distributions import Uniform

from camhealth.physics.metadata import FULL_FIELDS, CameraMetadata, SensorConstants, check_sensor_constant
from camhealth.physics.motion_psf import sample_shake_noise

__all__ = [
    "DefocusGenerator",
    "MotionGenerator",
    "SensorNoiseGenerator",
    "CONSTANT_FIELDS",
    "as_range",
    "metadata_to_params",
    "params_to_constants",
    "params_to_metadata",
]


def _is_number(v: Any) -> bool:
    """Whether ``v`` is one real number: a Python/NumPy int or float, or a 0-d real tensor/array (a bool, a string or a
    bool tensor is none)."""
    if isinstance(v, torch.Tensor):
        return v.ndim == 0 and v.dtype != torch.bool and not v.is_complex()
    if isinstance(v, np.ndarray):
        return v.ndim == 0 and (np.issubdtype(v.dtype, np.integer) or np.issubdtype(v.dtype, np.floating))
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def as_range(value: float | tuple[float, float] | list[float], name: str, bounds: tuple[float, float]) -> tuple[float, float]:
    """A scalar → (value, value); a pair is checked to lie ordered inside ``bounds``. A bool or a string (alone or in
    the pair) is no number: ``TypeError``."""
    if isinstance(value, bool) or isinstance(value, (str, bytes)):
        raise TypeError(f"{name} must be a number or a (low, high) pair, got {type(value).__name__} {value!r:.60}")
    if _is_number(value):
        lo = hi = float(value)
    else:
        try:
            if len(value) != 2:
                raise ValueError
            pair = (value[0], value[1])
        except (TypeError, ValueError, IndexError, KeyError):
            raise ValueError(f"{name} must be a number or a (low, high) pair, got {value!r:.60}") from None
        for v in pair:
            if not _is_number(v):
                raise TypeError(f"{name} must be a number or a (low, high) pair, got {value!r:.60} "
                                f"({type(v).__name__} {v!r:.20} is no number)")
        lo, hi = float(pair[0]), float(pair[1])
    if not (bounds[0] <= lo <= hi <= bounds[1]):
        ok = lambda a, b: bounds[0] <= a <= b <= bounds[1]  # noqa: E731 (does the short form read as allowed?)
        short = (f"{lo:g}", f"{hi:g}")
        shown = short if not ok(float(short[0]), float(short[1])) else (repr(lo), repr(hi))
        raise ValueError(f"{name} = ({shown[0]}, {shown[1]}) must satisfy {bounds[0]:g} ≤ low ≤ high ≤ {bounds[1]:g}")
    return lo, hi


class _UniformFieldsGenerator(RandomGeneratorBase):
    """Samples named scalar parameters uniformly from their (low, high) ranges."""

    def __init__(self, ranges: Mapping[str, tuple[float, float]]) -> None:
        super().__init__()
        self.ranges = dict(ranges)

    def __repr__(self) -> str:
        return ", ".join(f"{k}={v}" for k, v in self.ranges.items())

    def make_samplers(self, device: torch.device, dtype: torch.dtype) -> None:
        self._samplers = {}
        for k, (lo, hi) in self.ranges.items():
            lo_t = torch.tensor(lo, device=device, dtype=dtype)
            hi_t = torch.tensor(hi, device=device, dtype=dtype)
            self._samplers[k] = None if lo == hi else Uniform(lo_t, hi_t, validate_args=False)

    def _sample(self, batch_size: int, same_on_batch: bool) -> dict[str, torch.Tensor]:
        out = {}
        for k, (lo, _) in self.ranges.items():
            sampler = self._samplers[k]
            if sampler is None:
                out[k] = torch.full((batch_size,), lo, device=self.device, dtype=self.dtype)
            else:
                out[k] = _adapted_rsampling((batch_size,), sampler, same_on_batch)
        return out

    def forward(self, batch_shape: tuple[int, ...], same_on_batch: bool = False) -> dict[str, torch.Tensor]:
        return self._sample(batch_shape[0], same_on_batch)


class DefocusGenerator(_UniformFieldsGenerator):
    """``diameter`` [px] per sample, uniform in ``diameter_px``."""

    def __init__(self, diameter_px: tuple[float, float]) -> None:
        super().__init__({"diameter": diameter_px})


class MotionGenerator(_UniformFieldsGenerator):
    """``length`` [px], ``angle`` [deg], ``intensity`` [0, 1] and ``shake_noise`` (B, n_steps, 2)."""

    def __init__(
        self, length_px: tuple[float, float], angle_deg: tuple[float, float], intensity: tuple[float, float], n_steps: int = 64
    ) -> None:
        super().__init__({"length": length_px, "angle": angle_deg, "intensity": intensity})
        self.n_steps = n_steps

    def forward(self, batch_shape: tuple[int, ...], same_on_batch: bool = False) -> dict[str, torch.Tensor]:
        out = self._sample(batch_shape[0], same_on_batch)
        n = 1 if same_on_batch or batch_shape[0] == 0 else batch_shape[0]
        noise = sample_shake_noise(n, self.n_steps, device=self.device, dtype=torch.float32)
        out["shake_noise"] = noise.expand(batch_shape[0], -1, -1).contiguous()
        return out


class SensorNoiseGenerator(RandomGeneratorBase):
    """Camera metadata per sample (keys ``meta_<field>``, and the fixed :class:`SensorConstants` as
    ``const_<field>``) and the ``noise_seed`` of the noise field: one seed per call, the same for every sample
    (the whole batch draws its noise together).

    Args:
        metadata: fixed metadata (a preset name, :class:`CameraMetadata` of batch 1, or a dict of
            fields). Fields named in ``ranges`` are sampled instead. ``None`` samples every field.
        ranges: per-field (low, high) sampling ranges inside ``METADATA_RANGES``.
        gain_uniform_in: ``"factor"`` (thesis) or ``"db"``.
    """

    def __init__(
        self,
        metadata: CameraMetadata | str | Mapping[str, Any] | None = None,
        ranges: Mapping[str, tuple[float, float]] | None = None,
        gain_uniform_in: str = "factor",
    ) -> None:
        super().__init__()
        if ranges is not None and not isinstance(ranges, Mapping):  # (dict("gain_db") fails with a riddle)
            raise TypeError(f"ranges must be a mapping of field: (low, high), e.g. {{'gain_db': (0.0, 24.0)}}, got "
                            f"{type(ranges).__name__} {ranges!r:.60}")
        if isinstance(metadata, CameraMetadata) and metadata.batch_size != 1:
            raise ValueError(
                f"RandomSensorNoise takes metadata of batch size 1 (got {metadata.batch_size}); to corrupt with "
                "per-sample metadata, pass params=RandomSensorNoise.params_from_metadata(meta)"
            )
        self.metadata = metadata
        self.ranges = dict(ranges or {})
        self.gain_uniform_in = gain_uniform_in
        # Validate eagerly (a bad range or preset should fail at construction, not at the first batch).
        CameraMetadata.sample(1, ranges=self.ranges, fixed=self.metadata, gain_uniform_in=gain_uniform_in)

    def __repr__(self) -> str:
        return f"metadata={self.metadata!r}, ranges={self.ranges}, gain_uniform_in={self.gain_uniform_in!r}"

    def make_samplers(self, device: torch.device, dtype: torch.dtype) -> None:
        pass

    def forward(self, batch_shape: tuple[int, ...], same_on_batch: bool = False) -> dict[str, torch.Tensor]:
        b = batch_shape[0]
        n = 1 if same_on_batch or b == 0 else b  # an empty batch: one draw, expanded to none
        meta = CameraMetadata.sample(n, ranges=self.ranges, fixed=self.metadata, gain_uniform_in=self.gain_uniform_in)
        params = metadata_to_params(meta.expand(b) if n == 1 else meta, device=self.device)
        seed = torch.randint(0, 2**62, (1,), dtype=torch.int64)
        params["noise_seed"] = seed.expand(b).to(self.device)
        return params


#: The fields of :class:`SensorConstants`, carried in the parameters as ``const_<field>``.
CONSTANT_FIELDS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(SensorConstants))


def metadata_to_params(meta: CameraMetadata, device: torch.device | str | None = None) -> dict[str, torch.Tensor]:
    """Flatten metadata into parameter tensors of shape (B,): ``meta_<field>`` (float32) for the 11 fields and
    ``const_<field>`` (float64, the same value in every row: the fixed :class:`SensorConstants` of the batch)."""
    params = {f"meta_{n}": getattr(meta, n).to(device=device, dtype=torch.float32) for n in FULL_FIELDS}
    b = meta.batch_size
    for n in CONSTANT_FIELDS:
        params[f"const_{n}"] = torch.full((b,), float(getattr(meta.constants, n)), dtype=torch.float64, device=device)
    return params


def params_to_constants(params: Mapping[str, torch.Tensor], prefix: str = "") -> SensorConstants:
    """The :class:`SensorConstants` of ``const_<field>`` parameters (the defaults where params carry none; a batch
    has one set of constants, so each entry must hold one value, else ``ValueError`` naming it)."""
    keys = [f"{prefix}const_{n}" for n in CONSTANT_FIELDS]
    present = [k for k in keys if k in params]
    if not present:
        return SensorConstants()
    if len(present) != len(keys):
        missing = [k for k in keys if k not in params]
        raise ValueError(f"params carry some fixed sensor constants but lack {missing}; give all of {keys} or none")
    for k in keys:  # (a bool would read as 0 or 1)
        dtype = torch.as_tensor(params[k]).dtype
        if dtype == torch.bool or dtype.is_complex:
            raise TypeError(f"params {k} must hold real numbers (the fixed sensor constant of the batch), got dtype {dtype}")
    try:
        table = torch.stack([torch.as_tensor(params[k]).detach().reshape(-1) for k in keys]).to("cpu", torch.float64)
    except RuntimeError:
        raise ValueError(f"params {keys} must each hold one value per sample, got shapes "
                         f"{[tuple(torch.as_tensor(params[k]).shape) for k in keys]}") from None
    if table.shape[1] == 0:
        return SensorConstants()  # an empty batch: no value to read
    bad = ~torch.isfinite(table).all(1) | (table != table[:, :1]).any(1)
    if bool(bad.any()):
        j = int(bad.nonzero()[0, 0])
        raise ValueError(f"params {keys[j]} = {table[j].tolist()} must hold one finite value for the whole batch (the "
                         "fixed SensorConstants are shared by all samples)")
    values = dict(zip(CONSTANT_FIELDS, table[:, 0].tolist()))
    for n, k in zip(CONSTANT_FIELDS, keys):  # the checks of SensorConstants, naming the params entry
        check_sensor_constant(n, values[n], where=f"params {k}")
    return SensorConstants(**values)


def params_to_metadata(params: Mapping[str, torch.Tensor], prefix: str = "") -> CameraMetadata:
    """Rebuild :class:`CameraMetadata` from ``meta_<field>`` parameters (validated) and the ``const_<field>``
    constants (:func:`params_to_constants`)."""
    try:
        data = {n: params[f"{prefix}meta_{n}"] for n in FULL_FIELDS}
    except KeyError as err:
        raise ValueError(f"params lack the metadata entry {err.args[0]!r}; expected keys meta_<field> for {list(FULL_FIELDS)}") from None
    return CameraMetadata(**data, constants=params_to_constants(params, prefix))

