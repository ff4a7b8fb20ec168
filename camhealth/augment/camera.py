"""The whole camera of thesis Fig. 3.7 as one Kornia-style module."""

from __future__ import annotations

from typing import Dict, Optional

import torch
from kornia.augmentation.random_generator.base import RandomGeneratorBase

from camhealth.augment._base import CorruptionBase
from camhealth.augment.blur import RandomDefocusBlur, RandomMotionBlur
from camhealth.augment.sensor_noise import RandomSensorNoise

__all__ = ["CameraCorruption"]


class _CameraGenerator(RandomGeneratorBase):
    """Union of the components' parameters plus a per-sample gate ``<component>_gate`` from each
    component's own ``p``."""

    def __init__(self, components: Dict[str, Optional[CorruptionBase]]) -> None:
        super().__init__()
        self.components = {k: v for k, v in components.items() if v is not None}

    def __repr__(self) -> str:
        return ", ".join(f"{k}={v!r}" for k, v in self.components.items())

    def make_samplers(self, device: torch.device, dtype: torch.dtype) -> None:
        for comp in self.components.values():
            comp._param_generator.set_rng_device_and_dtype(device, dtype)

    def forward(self, batch_shape: tuple[int, ...], same_on_batch: bool = False) -> Dict[str, torch.Tensor]:
        b = batch_shape[0]
        params: Dict[str, torch.Tensor] = {}
        for name, comp in self.components.items():
            params.update(comp._param_generator(batch_shape, same_on_batch or comp.same_on_batch))
            if comp.p >= 1.0:
                gate = torch.ones(b)
            elif same_on_batch or comp.same_on_batch:
                gate = (torch.rand(1) < comp.p).float().expand(b)
            else:
                gate = (torch.rand(b) < comp.p).float()
            params[f"{name}_gate"] = gate.to(self.device)
        return params


class CameraCorruption(CorruptionBase):
    r"""Defocus → photon noise → motion blur → dark-current noise → readout noise → gain → clip → quantise.

    Chains the components in the order of thesis Fig. 3.7 in one pass (photon noise is realised between
    the two blurs, so it is itself motion blurred — the structured, directional noise of Sec. 5.4).
    Each component keeps its own ranges and its own ``p`` (a per-sample gate); pass ``None`` to leave
    a component out.

    Args:
        defocus: a :class:`RandomDefocusBlur` or ``None``. Default: diameters 1–21 px.
        motion: a :class:`RandomMotionBlur` or ``None``. Default: linear, lengths 1–21 px.
        noise: a :class:`RandomSensorNoise` or ``None``. Default: all sources, metadata sampled. Its
            ``quantize`` and ``rng`` settings apply to the chain.
        p, same_on_batch, keepdim: as in Kornia (``p`` gates the whole camera per sample); keyword-only
            (only the three components are positional). Default p = 1 (Kornia's is 0.5), same_on_batch = False,
            keepdim = False.

    Labels (``aug.labels()``): ``mtf`` (B, 16) of the combined PSF (product of the components' MTFs),
    the noise labels of :class:`RandomSensorNoise`, and ``metadata``.

    The components are fixed at construction (their kernel sizes, noise sources, quantisation and random-number
    source are read then): assigning or deleting ``.defocus``, ``.motion`` or ``.noise`` afterwards raises
    ``AttributeError`` — build a new ``CameraCorruption`` instead. (A component's own ``p`` and ranges may still be
    changed in place; they are read at every call.)

    Shape:
        - Input: :math:`(B, C, H, W)`, :math:`(C, H, W)` or :math:`(H, W)`, floating point in [0, 1] (gray or
          colour; every channel gets the same PSF and metadata, the noise is drawn per pixel and channel).
        - Output: :math:`(B, C, H, W)`, or the input's shape with ``keepdim=True``.

    Examples:
        >>> import torch
        >>> from camhealth.augment import CameraCorruption
        >>> cam = CameraCorruption()
        >>> x = torch.rand(4, 1, 128, 128)
        >>> noisy_blurry = cam(x)
        >>> cam.labels()["sigma_dn"].shape
        torch.Size([4, 3])
        >>> torch.equal(cam(x, params=cam._params), noisy_blurry)  # replay the whole camera
        True
    """

    def __init__(
        self,
        defocus: RandomDefocusBlur | None | str = "default",
        motion: RandomMotionBlur | None | str = "default",
        noise: RandomSensorNoise | None | str = "default",
        *,
        p: float = 1.0,
        same_on_batch: bool = False,
        keepdim: bool = False,
    ) -> None:
        super().__init__(p=p, same_on_batch=same_on_batch, keepdim=keepdim)
        defocus = RandomDefocusBlur() if isinstance(defocus, str) and defocus == "default" else defocus
        motion = RandomMotionBlur() if isinstance(motion, str) and motion == "default" else motion
        noise = RandomSensorNoise() if isinstance(noise, str) and noise == "default" else noise
        for name, comp, cls in (("defocus", defocus, RandomDefocusBlur), ("motion", motion, RandomMotionBlur), ("noise", noise, RandomSensorNoise)):
            if comp is not None and not isinstance(comp, cls):
                raise TypeError(f"{name} must be a {cls.__name__} or None, got {type(comp).__name__}")
        if defocus is None and motion is None and noise is None:
            raise ValueError("CameraCorruption(defocus=None, motion=None, noise=None) corrupts nothing: it needs at least "
                             "one component (defocus, motion or noise)")
        self.defocus, self.motion, self.noise = defocus, motion, noise
        self._defocus_ks = defocus._defocus_ks if defocus is not None else None
        self._motion_ks = motion._motion_ks if motion is not None else None
        self._sources = noise._sources if noise is not None else ()
        self._quantize = noise._quantize if noise is not None else False
        self._rng = noise._rng if noise is not None else "torch"
        self._param_generator = _CameraGenerator({"defocus": defocus, "motion": motion, "noise": noise})
        self.__dict__["_components_fixed"] = True

    def _refuse_component_change(self, name: str, verb: str) -> None:
        if name in _COMPONENTS and self.__dict__.get("_components_fixed", False):
            raise AttributeError(
                f"CameraCorruption.{name} is fixed at construction (its kernel size, noise sources and settings are read "
                f"then): {verb} it would not change the corruption; build a new CameraCorruption({name}=...) instead"
            )

    def __setattr__(self, name: str, value: object) -> None:
        self._refuse_component_change(name, "assigning")
        super().__setattr__(name, value)

    def __delattr__(self, name: str) -> None:
        self._refuse_component_change(name, "deleting")
        super().__delattr__(name)


#: The components of :class:`CameraCorruption`, fixed at construction.
_COMPONENTS = ("defocus", "motion", "noise")
