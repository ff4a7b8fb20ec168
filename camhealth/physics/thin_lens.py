"""Thin-lens blur geometry: circle of confusion, hyperfocal distance, blur-size conversion, motion length.

Implements, from the thesis (Sec. 3.2.1 and 5.2.2):

* Eq. 3.7, circle of confusion (CoC) of an out-of-focus object point::

      D_I = D_A · f / (d_O − f) · |d_B − d_O| / d_B

  with aperture diameter D_A, focal length f, focused object distance d_O and out-of-focus object
  distance d_B (all in mm). D_I is a diameter on the sensor in mm; divided by the pixel pitch d_p it
  is the defocus kernel diameter d in px (the diameter of :func:`camhealth.physics.defocus_psf`).
* Eq. 3.9, hyperfocal distance ``H = D_A · f / d_p + f`` (mm); a fixed-focus camera focused on H is
  sharp on ``[H/2, ∞)``.
* Eq. 5.2, blur size of camera c1 in the pixel grid of camera c2: ``d' = d · d_p(c1) / d_p(c2)``
  (a blur that is physically the same size on the sensor covers more pixels on a finer-pitched sensor).
* Eq. 3.10, linear motion-blur length ``L = v_rel · t_exp`` (px).

All functions are pure. Arguments are Python numbers or torch tensors (broadcast together): when every
argument is a Python number the result is a ``float``; otherwise it is a tensor on the device of the
first tensor argument, float64 if any tensor argument is float64 and float32 otherwise (computation is
done in float64). Bad input raises ``TypeError`` (wrong type) or ``ValueError`` (value out of range,
naming the value and the allowed range).
"""

from __future__ import annotations

import math
from typing import Union

import torch

from camhealth._validation import check_finite, check_tensor
from camhealth.physics._format import check_range

__all__ = [
    "circle_of_confusion_mm",
    "circle_of_confusion_px",
    "hyperfocal_distance_mm",
    "convert_blur_size_px",
    "motion_length_px",
]

Number = Union[int, float]
TensorOrFloat = Union[torch.Tensor, float]


def _as_tensors(*named: tuple[object, str]) -> tuple[list[torch.Tensor], bool, torch.dtype, torch.device]:
    """Convert ``(value, name)`` pairs to float64 tensors for computation.

    Returns the tensors, whether every input was a Python number, the output dtype (float64 if any
    tensor input is float64, else float32) and the output device (first tensor's device, else CPU).
    """
    tensors: list[torch.Tensor] = []
    all_scalars = True
    out_dtype = torch.float32
    device = None
    for value, name in named:
        if isinstance(value, bool) or not isinstance(value, (int, float, torch.Tensor)):
            raise TypeError(f"{name} must be a real number or a torch.Tensor, got {type(value).__name__}")
        if isinstance(value, torch.Tensor):
            check_tensor(value, name)
            if value.dtype == torch.bool or value.is_complex():
                raise TypeError(f"{name} must be a real-valued tensor, got dtype {value.dtype}")
            all_scalars = False
            if device is None:
                device = value.device
            if value.dtype == torch.float64:
                out_dtype = torch.float64
            tensors.append(value)
        else:
            tensors.append(torch.tensor(float(value), dtype=torch.float64))
    device = device if device is not None else torch.device("cpu")
    work = torch.float64 if device.type != "mps" else torch.float32
    tensors = [t.to(device=device, dtype=work) for t in tensors]
    for t, (_, name) in zip(tensors, named):
        check_finite(t, name)
    return tensors, all_scalars, out_dtype, device


def _finish(x: torch.Tensor, all_scalars: bool, out_dtype: torch.dtype) -> TensorOrFloat:
    if all_scalars:
        return float(x.item())
    return x.to(out_dtype)


def _check_positive(x: torch.Tensor, name: str, unit: str) -> None:
    check_range(x, name, 0.0, math.inf, unit)
    if bool((x <= 0).any()):
        first = x[x <= 0].flatten()[0].item()
        raise ValueError(f"{name} = {first:g} {unit} is out of the allowed range (0, inf) {unit}")


def _coc_mm(d_a: torch.Tensor, f: torch.Tensor, d_o: torch.Tensor, d_b: torch.Tensor) -> torch.Tensor:
    _check_positive(d_a, "aperture_diameter_mm", "mm")
    _check_positive(f, "focal_length_mm", "mm")
    _check_positive(d_o, "focus_distance_mm", "mm")
    _check_positive(d_b, "object_distance_mm", "mm")
    d_o_b, f_b = torch.broadcast_tensors(d_o, f)
    bad = d_o_b <= f_b
    if bool(bad.any()):
        raise ValueError(
            f"focus_distance_mm = {d_o_b[bad].flatten()[0].item():g} mm must be greater than "
            f"focal_length_mm = {f_b[bad].flatten()[0].item():g} mm (range (f, inf) mm): a thin lens cannot "
            "focus on an object at or inside its focal length"
        )
    return d_a * f / (d_o - f) * (d_b - d_o).abs() / d_b


def circle_of_confusion_mm(
    aperture_diameter_mm: TensorOrFloat,
    focal_length_mm: TensorOrFloat,
    focus_distance_mm: TensorOrFloat,
    object_distance_mm: TensorOrFloat,
) -> TensorOrFloat:
    """Circle-of-confusion diameter on the sensor, Eq. 3.7, in mm.

    ``D_I = D_A · f / (d_O − f) · |d_B − d_O| / d_B``.

    Args:
        aperture_diameter_mm: aperture diameter D_A in mm, > 0.
        focal_length_mm: focal length f in mm, > 0.
        focus_distance_mm: focused object distance d_O in mm, > f.
        object_distance_mm: distance d_B of the (out-of-focus) object in mm, > 0.

    Returns:
        D_I in mm (0 when the object is in the focus plane, d_B = d_O).
    """
    (d_a, f, d_o, d_b), scal, dt, _ = _as_tensors(
        (aperture_diameter_mm, "aperture_diameter_mm"),
        (focal_length_mm, "focal_length_mm"),
        (focus_distance_mm, "focus_distance_mm"),
        (object_distance_mm, "object_distance_mm"),
    )
    return _finish(_coc_mm(d_a, f, d_o, d_b), scal, dt)


def circle_of_confusion_px(
    aperture_diameter_mm: TensorOrFloat,
    focal_length_mm: TensorOrFloat,
    focus_distance_mm: TensorOrFloat,
    object_distance_mm: TensorOrFloat,
    pixel_pitch_um: TensorOrFloat,
) -> TensorOrFloat:
    """Circle-of-confusion diameter in pixels: Eq. 3.7 divided by the pixel pitch.

    ``d [px] = D_I [mm] · 1000 / d_p [µm]`` — the defocus-kernel diameter to pass to
    :func:`camhealth.physics.defocus_psf.defocus_psf`. (The thesis writes ``D_I = 2 r d_p + 1``; we use
    the plain geometric conversion ``d = 2r = D_I / d_p``, which is what Eq. 5.2 and the DEFCARS design
    values of Sec. 5.1.2 imply.)

    Args:
        aperture_diameter_mm, focal_length_mm, focus_distance_mm, object_distance_mm: as in
            :func:`circle_of_confusion_mm` (mm).
        pixel_pitch_um: sensor pixel pitch d_p in µm, > 0.

    Returns:
        CoC diameter in px.
    """
    (d_a, f, d_o, d_b, p), scal, dt, _ = _as_tensors(
        (aperture_diameter_mm, "aperture_diameter_mm"),
        (focal_length_mm, "focal_length_mm"),
        (focus_distance_mm, "focus_distance_mm"),
        (object_distance_mm, "object_distance_mm"),
        (pixel_pitch_um, "pixel_pitch_um"),
    )
    _check_positive(p, "pixel_pitch_um", "µm")
    return _finish(_coc_mm(d_a, f, d_o, d_b) * 1000.0 / p, scal, dt)


def hyperfocal_distance_mm(
    aperture_diameter_mm: TensorOrFloat,
    focal_length_mm: TensorOrFloat,
    pixel_pitch_mm: TensorOrFloat,
) -> TensorOrFloat:
    """Hyperfocal distance, Eq. 3.9, in mm: ``H = D_A · f / d_p + f``.

    Focused on H, a camera keeps every object in ``[H/2, ∞)`` within one pixel of blur.

    Args:
        aperture_diameter_mm: aperture diameter D_A in mm, > 0.
        focal_length_mm: focal length f in mm, > 0.
        pixel_pitch_mm: pixel pitch d_p in **mm** (e.g. 0.00645 for 6.45 µm), > 0.
    """
    (d_a, f, p), scal, dt, _ = _as_tensors(
        (aperture_diameter_mm, "aperture_diameter_mm"),
        (focal_length_mm, "focal_length_mm"),
        (pixel_pitch_mm, "pixel_pitch_mm"),
    )
    _check_positive(d_a, "aperture_diameter_mm", "mm")
    _check_positive(f, "focal_length_mm", "mm")
    _check_positive(p, "pixel_pitch_mm", "mm")
    return _finish(d_a * f / p + f, scal, dt)


def convert_blur_size_px(
    size_px: TensorOrFloat,
    pixel_pitch_from_um: TensorOrFloat,
    pixel_pitch_to_um: TensorOrFloat,
) -> TensorOrFloat:
    """Blur size of camera c1 expressed in the pixel grid of camera c2, Eq. 5.2.

    ``d'(c1) = d(c1) · d_p(c1) / d_p(c2)``. Example from the thesis: 21 px on KITTI (4.65 µm) ≈ 41 px on
    the LEICA camera of DEFCARS (2.4 µm).

    Args:
        size_px: blur size (diameter or length) in px of camera c1, >= 0.
        pixel_pitch_from_um: pixel pitch d_p(c1) of the source camera in µm, > 0.
        pixel_pitch_to_um: pixel pitch d_p(c2) of the target camera in µm, > 0.

    Returns:
        The same physical blur in px of camera c2.
    """
    (d, p1, p2), scal, dt, _ = _as_tensors(
        (size_px, "size_px"), (pixel_pitch_from_um, "pixel_pitch_from_um"), (pixel_pitch_to_um, "pixel_pitch_to_um")
    )
    check_range(d, "size_px", 0.0, math.inf, "px")
    _check_positive(p1, "pixel_pitch_from_um", "µm")
    _check_positive(p2, "pixel_pitch_to_um", "µm")
    return _finish(d * p1 / p2, scal, dt)


def motion_length_px(velocity_px_per_s: TensorOrFloat, exposure_s: TensorOrFloat) -> TensorOrFloat:
    """Linear motion-blur length ``L = v_rel · t_exp`` (Eq. 3.10), in px.

    Args:
        velocity_px_per_s: relative image-plane speed in px/s, >= 0 (the direction is the PSF's angle).
        exposure_s: exposure time in s, >= 0.
    """
    (v, t), scal, dt, _ = _as_tensors((velocity_px_per_s, "velocity_px_per_s"), (exposure_s, "exposure_s"))
    check_range(v, "velocity_px_per_s", 0.0, math.inf, "px/s")
    check_range(t, "exposure_s", 0.0, math.inf, "s")
    return _finish(v * t, scal, dt)
