"""Kornia-style random blur modules with physically defined PSFs and MTF labels."""

from __future__ import annotations

import math
from typing import Any

from camhealth._validation import check_odd_kernel_size
from camhealth.augment._base import CorruptionBase
from camhealth.augment._generators import DefocusGenerator, MotionGenerator, as_range
from camhealth.physics.defocus_psf import default_kernel_size

__all__ = ["RandomDefocusBlur", "RandomMotionBlur", "motion_kernel_size"]

#: Largest kernel of the blur modules [px], and the largest disk diameter / motion length it holds (a defocus
#: kernel needs d + 2 px, a motion kernel L + 3 px: :func:`~camhealth.physics.defocus_psf.default_kernel_size`,
#: :func:`motion_kernel_size`).
MAX_KERNEL_PX = 255
MAX_DIAMETER_PX = 253.0
MAX_LENGTH_PX = 252.0


def motion_kernel_size(max_length_px: float, nonlinear: bool) -> int:
    """Smallest odd kernel that holds a motion path of arc length ``max_length_px`` with 1 px margin.

    A path of arc length L centred on its bounding box never reaches further than L/2 from the centre
    (straight or curved), so L + 3 px suffice for both; ``nonlinear`` is kept for API symmetry.
    """
    del nonlinear
    k = int(math.ceil(float(max_length_px))) + 3
    return k if k % 2 == 1 else k + 1


def _odd_at_least(size_px: float) -> int:
    """The smallest odd integer ≥ ``size_px``."""
    k = int(math.ceil(size_px))
    return k if k % 2 == 1 else k + 1


class RandomDefocusBlur(CorruptionBase):
    r"""Defocus blur with a uniform-disk PSF of random diameter (circle of confusion, thesis Eq. 3.6).

    Args:
        diameter: disk diameter [px], a number or (low, high) sampled uniformly per sample, in [0, 253] (the
            largest disk whose kernel fits 255 px); sub-pixel diameters are anti-aliased. Default (1, 21).
        kernel_size: odd kernel size in [1, 255], at least the largest diameter; default: the smallest that holds the
            largest disk with 1 px margin.
        p: probability to blur a sample. Default 1 (a camera always images through its optics).
        same_on_batch: one diameter for the whole batch. Default False.
        keepdim: keep the input's shape (C×H×W in → C×H×W out). Default False.

    Parameters (``aug._params``): ``diameter`` (B,). Labels (``aug.labels()``): ``mtf`` (B, 16).
    The transform is differentiable w.r.t. the image (a convolution).

    Shape:
        - Input: :math:`(B, C, H, W)`, :math:`(C, H, W)` or :math:`(H, W)`, floating point in [0, 1] (gray or
          colour; every channel gets the same PSF).
        - Output: :math:`(B, C, H, W)`, or the input's shape with ``keepdim=True``.

    Examples:
        >>> import torch
        >>> from camhealth.augment import RandomDefocusBlur
        >>> aug = RandomDefocusBlur(diameter=(3.0, 11.0))
        >>> x = torch.rand(8, 1, 64, 64)
        >>> y = aug(x)
        >>> aug.labels()["mtf"].shape
        torch.Size([8, 16])
        >>> torch.equal(aug(x, params=aug._params), y)  # replay the same diameters
        True
        >>> RandomDefocusBlur(5.0, p=0.5, keepdim=True)(torch.rand(1, 32, 32)).shape
        torch.Size([1, 32, 32])
    """

    def __init__(
        self,
        diameter: float | tuple[float, float] = (1.0, 21.0),
        *,
        kernel_size: int | None = None,
        p: float = 1.0,
        same_on_batch: bool = False,
        keepdim: bool = False,
    ) -> None:
        super().__init__(p=p, same_on_batch=same_on_batch, keepdim=keepdim)
        lo, hi = as_range(diameter, "diameter", (0.0, MAX_DIAMETER_PX))
        self._defocus_ks = check_odd_kernel_size(kernel_size) if kernel_size is not None else default_kernel_size(hi)
        if hi > self._defocus_ks:
            need = _odd_at_least(hi)
            raise ValueError(f"diameter up to {hi:g} px does not fit kernel_size = {self._defocus_ks}, which holds diameters "
                             f"up to {self._defocus_ks} px: pass an odd kernel_size ≥ {need}, or leave it unset (then "
                             f"{default_kernel_size(hi)})")
        self._param_generator = DefocusGenerator((lo, hi))

    def _repr_settings(self) -> dict[str, Any]:
        return {**super()._repr_settings(), "kernel_size": self._defocus_ks}


class RandomMotionBlur(CorruptionBase):
    r"""Linear or non-linear (camera-shake) motion blur with sub-pixel PSFs (thesis Eq. 3.10).

    Args:
        length: path length L = v·t_exp [px], number or (low, high), in [0, 252] (the longest path whose kernel
            fits 255 px). Default (1, 21).
        angle: direction Φ [deg], number or (low, high), in [-360, 360]; 0° horizontal, 90° vertical. Default (0, 180).
        intensity: shake intensity in [0, 1]: 0 → straight line, 1 → strongly curved, jerky path.
            Default 0 (linear motion).
        kernel_size: odd kernel size in [1, 255], longer than the largest length by at least 1 px; default from the
            largest length (see :func:`motion_kernel_size`).
        p, same_on_batch, keepdim: as in Kornia. Default p = 1 (Kornia's is 0.5: every sample is blurred and
            labelled), same_on_batch = False, keepdim = False.

    Parameters: ``length``, ``angle``, ``intensity`` (B,) and ``shake_noise`` (B, 64, 2).
    Labels: ``mtf`` (B, 16). Differentiable w.r.t. the image.

    Shape:
        - Input: :math:`(B, C, H, W)`, :math:`(C, H, W)` or :math:`(H, W)`, floating point in [0, 1] (gray or
          colour; every channel gets the same PSF).
        - Output: :math:`(B, C, H, W)`, or the input's shape with ``keepdim=True``.

    Examples:
        >>> import torch
        >>> from camhealth.augment import RandomMotionBlur
        >>> aug = RandomMotionBlur(length=(3.0, 15.0), angle=(0.0, 180.0), intensity=0.5)
        >>> x = torch.rand(4, 1, 64, 64)
        >>> y = aug(x)
        >>> aug._params["length"].shape, aug._params["shake_noise"].shape
        (torch.Size([4]), torch.Size([4, 64, 2]))
        >>> torch.equal(aug(x, params=aug._params), y)  # replay: the same paths
        True
        >>> RandomMotionBlur(3, 35.0, 0.5)  # Kornia's positional (kernel, angle, direction) is refused
        Traceback (most recent call last):
        ...
        TypeError: RandomMotionBlur.__init__() takes from 1 to 2 positional arguments but 4 were given
    """

    def __init__(
        self,
        length: float | tuple[float, float] = (1.0, 21.0),
        *,
        angle: float | tuple[float, float] = (0.0, 180.0),
        intensity: float | tuple[float, float] = 0.0,
        kernel_size: int | None = None,
        p: float = 1.0,
        same_on_batch: bool = False,
        keepdim: bool = False,
    ) -> None:
        super().__init__(p=p, same_on_batch=same_on_batch, keepdim=keepdim)
        length_r = as_range(length, "length", (0.0, MAX_LENGTH_PX))
        angle_r = as_range(angle, "angle", (-360.0, 360.0))
        intensity_r = as_range(intensity, "intensity", (0.0, 1.0))
        nonlinear = intensity_r[1] > 0
        self._motion_ks = (
            check_odd_kernel_size(kernel_size) if kernel_size is not None else motion_kernel_size(length_r[1], nonlinear)
        )
        if length_r[1] > self._motion_ks - 1:
            need = _odd_at_least(length_r[1] + 1.0)
            raise ValueError(f"length up to {length_r[1]:g} px does not fit kernel_size = {self._motion_ks}, which holds "
                             f"lengths up to {self._motion_ks - 1} px: pass an odd kernel_size ≥ {need}, or leave it unset "
                             f"(then {motion_kernel_size(length_r[1], nonlinear)})")
        self._param_generator = MotionGenerator(length_r, angle_r, intensity_r)

    def _repr_settings(self) -> dict[str, Any]:
        return {**super()._repr_settings(), "kernel_size": self._motion_ks}
