"""Kornia-style physical sensor noise (Konnik & Welsh): photon, dark-current and readout noise."""

from __future__ import annotations

import numbers
from typing import Any, Mapping, Sequence

import numpy as np
import torch

from camhealth.augment._base import CorruptionBase, check_sources
from camhealth.augment._generators import SensorNoiseGenerator, metadata_to_params
from camhealth.physics.image_formation import NOISE_SOURCES, check_rng
from camhealth.physics.metadata import CameraMetadata

__all__ = ["RandomSensorNoise"]


class RandomSensorNoise(CorruptionBase):
    r"""Add physically modelled sensor noise, then gain, clipping and (optionally) quantisation.

    Photon shot noise (Poisson in the photo-electrons, signal dependent), dark-current shot noise
    (Poisson in the dark electrons) and readout noise (Gaussian: source follower through CDS, plus the
    kTC residue for CMOS), amplified by the gain and clipped to [0, 255] DN (conventions.md).

    Args:
        sources: which sources to realise, subset of ``("photon", "dark", "readout")``. Default: all three.
        metadata: fixed camera metadata: a preset name (``"ICX285"``, ``"EV76C661"``), a
            :class:`CameraMetadata` of batch 1 (its :class:`~camhealth.physics.SensorConstants` are used), or a
            dict of fields read as :meth:`CameraMetadata.from_dict` reads one (``sensor_type: CCD|CMOS`` accepted,
            an unknown key is a ``ValueError``); ``None`` (default) samples every field from its range (thesis
            Table 4.1).
        ranges: per-field (low, high) ranges to sample instead of the fixed value, e.g.
            ``{"gain_db": (0, 24), "temperature_c": (0, 80)}``.
        quantize: round to whole DN (straight-through gradient). Default False.
        gain_uniform_in: sample the gain uniformly in ``"factor"`` (thesis; default) or ``"db"``.
        rng: random numbers of the noise fields: ``"torch"`` (default; torch's generator) or ``"counter"``
            (compiled counter-based draws, :mod:`camhealth.physics.counter_rng`: the same distributions in
            about half the time on CPU; a different stream, so the same ``noise_seed`` gives other draws than
            ``"torch"``). The first call compiles its kernels (~10 s).
        p, same_on_batch, keepdim: as in Kornia; ``same_on_batch`` shares the metadata, the noise field
            stays independent per sample (as two frames of one camera would be). Default p = 1 (Kornia's is 0.5:
            every sample is corrupted and labelled), same_on_batch = False, keepdim = False.

    Parameters: ``meta_<field>`` (B,) for the 11 metadata fields, ``const_<field>`` (B,) for the fixed
    :class:`~camhealth.physics.SensorConstants` (one value repeated: a batch has one set) and ``noise_seed`` (B,).
    Replaying with ``aug(x, params=aug._params)`` reproduces the noise exactly. To corrupt with your own per-sample
    metadata use ``aug(x, params=RandomSensorNoise.params_from_metadata(meta))``.

    Noise seeds: the samples that share a ``noise_seed`` draw their noise together, as one batch in batch order
    (one torch generator seeded with it); a sample with a seed of its own draws it alone, from a generator seeded
    with its seed. The parameter generator draws one seed per call for the whole batch (the fastest: one pass), so
    a replay reproduces the batch, or any set of whole seed groups, exactly; a sub-batch of it gets other noise.
    For samples that replay alone, give each its own seed (``params_from_metadata(meta, seed=[s₀, s₁, …])`` or
    ``params["noise_seed"] = …``): sample i is then ``form_image(x[i:i+1], meta[i], generator=
    torch.Generator().manual_seed(s_i))``, whatever else is in its batch (one form_image pass per seed).

    Labels (``aug.labels()`` after a call): ``sigma_dn`` (B, 3) realised σ of (PN, DCSN, RN) in DN after
    gain and clipping, ``sigma_total_dn``, the analytic ``sigma_expected_dn``/``sigma_total_expected_dn``,
    ``clipped_fraction`` and ``metadata``.

    Gradient: identity w.r.t. the input on unclipped pixels (noise draws are constants: Gaussian parts
    reparameterised, Poisson parts straight-through), zero on clipped pixels.

    Shape:
        - Input: :math:`(B, C, H, W)`, :math:`(C, H, W)` or :math:`(H, W)`, floating point in [0, 1] (gray or
          colour; every channel gets the same camera metadata, the noise is drawn per pixel and channel).
        - Output: :math:`(B, C, H, W)`, or the input's shape with ``keepdim=True``.

    Examples:
        >>> import torch
        >>> from camhealth.augment import RandomSensorNoise
        >>> aug = RandomSensorNoise(metadata="ICX285", ranges={"gain_db": (0.0, 24.0)})
        >>> x = torch.rand(4, 1, 64, 64)
        >>> y = aug(x)
        >>> aug.labels()["sigma_dn"].shape  # realised σ of PN, DCSN, RN [DN]
        torch.Size([4, 3])
        >>> torch.equal(aug(x, params=aug._params), y)  # replay: the same metadata and noise
        True
    """

    def __init__(
        self,
        sources: Sequence[str] = NOISE_SOURCES,
        *,
        metadata: CameraMetadata | str | Mapping[str, Any] | None = None,
        ranges: Mapping[str, tuple[float, float]] | None = None,
        quantize: bool = False,
        gain_uniform_in: str = "factor",
        rng: str = "torch",
        p: float = 1.0,
        same_on_batch: bool = False,
        keepdim: bool = False,
    ) -> None:
        super().__init__(p=p, same_on_batch=same_on_batch, keepdim=keepdim)
        self._sources = check_sources(sources)
        if not self._sources:
            raise ValueError(f"RandomSensorNoise needs at least one source from {list(NOISE_SOURCES)}")
        if not isinstance(quantize, bool):  # ("no" would read as True)
            raise TypeError(f"quantize = {quantize!r} must be True or False")
        self._quantize = quantize
        self._rng = check_rng(rng)
        self._param_generator = SensorNoiseGenerator(metadata, ranges, gain_uniform_in)

    def _repr_settings(self) -> dict[str, Any]:
        return {**super()._repr_settings(), "sources": list(self._sources), "quantize": self._quantize, "rng": self._rng}

    @staticmethod
    def params_from_metadata(
        meta: CameraMetadata, seed: int | Sequence[int] | torch.Tensor | None = None,
        device: torch.device | str | None = None,
    ) -> dict[str, torch.Tensor]:
        """Noise parameters for given per-sample metadata (with its fixed constants), to corrupt with
        ``aug(x, params=...)``.

        ``seed``: one integer for the whole batch (``None``: a random one), or one per sample (B,) — then every
        sample's noise depends on its own seed only and a sub-batch replays exactly (class docstring).

        A noise-only module's parameters; for :class:`~camhealth.augment.CameraCorruption` update the
        ``meta_<field>`` (and ``const_<field>``) entries of its ``forward_parameters`` output instead.
        """
        if not isinstance(meta, CameraMetadata):
            raise TypeError(f"meta must be a CameraMetadata (e.g. CameraMetadata.preset('ICX285'), "
                            f"CameraMetadata.from_dict({{...}}, base='ICX285')), got {type(meta).__name__}")
        b = meta.batch_size
        params = metadata_to_params(meta, device=device)
        if seed is None:
            seeds = torch.full((b,), int(torch.randint(0, 2**62, (1,))), dtype=torch.int64)
        else:
            seeds = _seed_vector(seed)
            if seeds.numel() == 1:
                seeds = seeds.expand(b)
            elif seeds.numel() != b:
                raise ValueError(f"seed has {seeds.numel()} values for metadata of batch size {b}: give one seed, or one "
                                 "per sample")
        params["noise_seed"] = seeds.contiguous().to(device)
        params["batch_prob"] = torch.ones(meta.batch_size, device=device)
        params["forward_input_shape"] = torch.tensor([meta.batch_size, 1, 0, 0])
        return params


_SEED_LOW, _SEED_HIGH = -(2**63), 2**63 - 1  # noise seeds are stored as int64


def _seed_vector(seed: Any) -> torch.Tensor:
    """``seed`` (an integer, a 1-D sequence of integers or an integer tensor/array) as a 1-D int64 CPU tensor, else
    ``TypeError`` (not integers: a float, bool or string) / ``ValueError`` (an integer beyond int64) naming it."""
    what = "seed must be an integer or a 1-D sequence of integers (one per sample)"
    if isinstance(seed, np.ndarray):
        if not np.issubdtype(seed.dtype, np.integer):
            raise TypeError(f"{what}, got an array of dtype {seed.dtype}")
        if seed.size and seed.dtype == np.uint64 and int(seed.max()) > _SEED_HIGH:
            raise ValueError(f"seed = {int(seed.max())} is out of the allowed range [-2**63, 2**63 - 1] (seeds are int64)")
        seed = torch.as_tensor(seed.astype(np.int64))
    if isinstance(seed, torch.Tensor):
        raw = seed
        if raw.is_floating_point() or raw.is_complex() or raw.dtype == torch.bool or raw.ndim > 1:
            raise TypeError(f"{what}, got {seed!r:.60}")
        if raw.dtype == torch.uint64 and raw.numel() and int(raw.max()) > _SEED_HIGH:
            raise ValueError(f"seed = {int(raw.max())} is out of the allowed range [-2**63, 2**63 - 1] (seeds are int64)")
        return raw.detach().to("cpu", torch.int64).reshape(-1)
    items = list(seed) if isinstance(seed, (list, tuple, range)) else [seed]
    values = []
    for v in items:
        if isinstance(v, torch.Tensor) and v.ndim == 0 and not v.is_floating_point() and not v.is_complex() \
                and v.dtype != torch.bool:
            v = int(v)
        if isinstance(v, bool) or not isinstance(v, numbers.Integral):
            raise TypeError(f"{what}, got {seed!r:.60} ({type(v).__name__} {v!r:.20} is no integer)")
        if not _SEED_LOW <= int(v) <= _SEED_HIGH:
            raise ValueError(f"seed = {int(v)} is out of the allowed range [-2**63, 2**63 - 1] (seeds are int64)")
        values.append(int(v))
    return torch.tensor(values, dtype=torch.int64)
