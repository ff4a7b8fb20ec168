"""Modulation transfer function of blur kernels (thesis Sec. 3.3.1, Eq. 3.20–3.21; labels of Sec. 4.3.1).

``MTF(f) = |OTF(f)| / |OTF(0)|`` with the OTF the Fourier transform of the PSF (Eq. 3.20), normalised so
MTF(0) = 1 (Eq. 3.21). Frequencies are **normalised to Nyquist** (f_n ∈ [0, 1]; f = f_n / 2 cycles/px),
in pixel units. The MTF estimator's 16 labels are the MTF at the 8 :data:`NORMALIZED_FREQUENCIES` in the
horizontal (H, along columns / x) and vertical (V, along rows / y) direction. The blur indicator of the
IOPCs is the mean of H and V at f_n = 0.1.

Direction convention (same as :mod:`camhealth.physics.motion_psf`): angle θ in degrees, counter-clockwise
with the image y axis pointing down, i.e. the frequency vector in (x = column, y = row) coordinates is
``f·(cos θ, −sin θ)``. The DFT is evaluated **exactly** at the requested frequencies (a direct sum over the
kernel pixels, not FFT bins)::

    MTF_θ(f) = |Σ_{x,y} h(x, y) · exp(−2πi f (x cos θ − y sin θ))| / |Σ_{x,y} h(x, y)|

with (x, y) pixel offsets from the kernel centre (the magnitude does not depend on the origin).

Pixel aperture: the kernels of :mod:`~camhealth.physics.defocus_psf` and :mod:`~camhealth.physics.motion_psf`
are the continuous PSF p integrated over each 1×1 px pixel square, i.e. samples of ``g = p ⊗ box`` at the
pixel centres. By the Poisson summation formula their DFT along x is

    ``Σ_n P(f − n) · sinc(f − n)``  (n ∈ ℤ; for the y-aliases only m = 0 survives since sinc(m) = 0),

so the kernel's MTF ≈ continuous MTF × :func:`pixel_aperture_mtf` (the n = 0 term) plus aliasing terms
that are small when P has decayed at |f − n| >= 1 − f (large blur, low frequency). The n-sum is exact and
is what the tests check against the closed forms :func:`disk_mtf` and :func:`line_mtf`.
"""

from __future__ import annotations

import math
from functools import reduce
from typing import Sequence, Union

import torch

from camhealth._validation import check_finite, check_float, check_tensor
from camhealth.physics._format import check_range
from camhealth.physics.thin_lens import _as_tensors, _finish

__all__ = [
    "NORMALIZED_FREQUENCIES",
    "mtf_from_psf",
    "mtf_hv",
    "combine_mtf",
    "disk_mtf",
    "line_mtf",
    "pixel_aperture_mtf",
    "mtf_indicator",
]

#: MTF sampling frequencies as a fraction of Nyquist (cycles/px = f_n / 2).
NORMALIZED_FREQUENCIES: tuple[float, ...] = (0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6)
_INDICATOR_INDEX = NORMALIZED_FREQUENCIES.index(0.1)

TensorOrFloat = Union[torch.Tensor, float]


def _as_vector(x: object, name: str, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    if isinstance(x, bool) or not isinstance(x, (int, float, list, tuple, torch.Tensor)):
        raise TypeError(f"{name} must be a sequence of numbers or a torch.Tensor, got {type(x).__name__}")
    try:
        t = torch.as_tensor(x, dtype=dtype, device=device).reshape(-1)
    except (TypeError, ValueError, RuntimeError) as err:
        raise TypeError(f"{name} must hold real numbers, got {x!r}") from err
    if t.numel() == 0:
        raise ValueError(f"{name} must hold at least one value")
    return check_finite(t, name)


def mtf_from_psf(
    psf: torch.Tensor,
    angles_deg: Union[Sequence[float], torch.Tensor] = (0.0, 90.0),
    frequencies: Union[Sequence[float], torch.Tensor] = NORMALIZED_FREQUENCIES,
) -> torch.Tensor:
    """MTF of blur kernels at exact normalised frequencies and directions (direct DFT).

    Args:
        psf: (B, H, W) kernels (odd or even sides; the centre is ``((H−1)/2, (W−1)/2)``), finite, with a
            non-zero sum.
        angles_deg: A directions θ in degrees (0 = H, along x/columns; 90 = V, along y/rows).
        frequencies: F normalised frequencies f_n in [0, 1] (fraction of Nyquist; f = f_n/2 cycles/px).

    Returns:
        (B, A, F) MTF values, dimensionless (in [0, 1] for non-negative kernels), in ``psf``'s dtype.
        Computed in float64 (one matmul against a (H·W, A·F) cos/sin basis).
    """
    psf = check_float(check_tensor(psf, "psf"), "psf")
    if psf.ndim != 3 or psf.shape[0] == 0 or psf.shape[1] == 0 or psf.shape[2] == 0:
        raise ValueError(f"psf must have shape (B, H, W) with non-zero sizes, got {tuple(psf.shape)}")
    check_finite(psf, "psf")
    dev = psf.device
    work = torch.float32 if dev.type == "mps" else torch.float64
    theta = torch.deg2rad(_as_vector(angles_deg, "angles_deg", dev, work))
    fn = _as_vector(frequencies, "frequencies", dev, work)
    check_range(fn, "frequencies", 0.0, 1.0, "× Nyquist")
    b, h, w = psf.shape
    y = torch.arange(h, device=dev, dtype=work) - 0.5 * (h - 1)
    x = torch.arange(w, device=dev, dtype=work) - 0.5 * (w - 1)
    # Projection of each pixel offset on each direction: x cos θ − y sin θ  → (A, H, W)
    proj = x[None, None, :] * torch.cos(theta)[:, None, None] - y[None, :, None] * torch.sin(theta)[:, None, None]
    phase = 2.0 * math.pi * (0.5 * fn)[None, :, None, None] * proj[:, None]  # (A, F, H, W)
    basis = torch.cat([torch.cos(phase), torch.sin(phase)], dim=0).reshape(2 * theta.numel() * fn.numel(), h * w)
    flat = psf.to(work).reshape(b, h * w)
    total = flat.sum(dim=1)
    if bool((total.abs() <= 1e-30).any()):
        raise ValueError(
            "psf must have a non-zero sum (the MTF is normalised by the DC value); got a kernel summing to 0"
        )
    proj_re_im = (flat @ basis.T).reshape(b, 2, theta.numel(), fn.numel())
    mag = torch.sqrt(proj_re_im[:, 0].square() + proj_re_im[:, 1].square())
    return (mag / total.abs()[:, None, None]).to(psf.dtype)


def mtf_hv(psf: torch.Tensor) -> torch.Tensor:
    """The 16 MTF labels: ``[H at the 8 NORMALIZED_FREQUENCIES, V at the 8]`` → (B, 16), in [0, 1].

    ``psf``: (B, H, W) blur kernels — light spread over pixels, so non-negative (values below −10⁻⁶ of the
    kernel's largest magnitude raise ``ValueError``; :func:`mtf_from_psf` takes signed kernels)."""
    psf = check_float(check_tensor(psf, "psf"), "psf")
    if psf.ndim == 3 and psf.numel() > 0:
        check_finite(psf, "psf")
        flat = psf.detach().reshape(psf.shape[0], -1)
        low, at = flat.min(dim=1)
        tol = 1e-6 * flat.abs().amax(dim=1)
        bad = low < -tol
        if bool(bad.any()):
            i = int(torch.nonzero(bad)[0, 0])
            r, c = divmod(int(at[i]), psf.shape[2])
            raise ValueError(
                f"psf must be non-negative (a blur kernel spreads light, its MTF labels lie in [0, 1]); kernel {i} has "
                f"{float(low[i]):g} at row {r}, column {c}"
            )
    m = mtf_from_psf(psf, (0.0, 90.0), NORMALIZED_FREQUENCIES)
    return m.reshape(m.shape[0], 2 * len(NORMALIZED_FREQUENCIES))


def combine_mtf(*mtfs: torch.Tensor) -> torch.Tensor:
    """MTF of a cascade of blurs: the element-wise product (the OTF of a convolution is the product)."""
    if not mtfs:
        raise ValueError("combine_mtf needs at least one MTF tensor, got none")
    for i, m in enumerate(mtfs):
        check_float(check_tensor(m, f"mtfs[{i}]"), f"mtfs[{i}]")
    return reduce(torch.mul, mtfs)


def disk_mtf(diameter_px: TensorOrFloat, f_cycles_per_px: TensorOrFloat) -> TensorOrFloat:
    """Continuous MTF of a uniform disk of diameter d px: ``|2·J1(π d f) / (π d f)|`` (jinc), 1 at f = 0.

    Args:
        diameter_px: d in px, >= 0. f_cycles_per_px: frequency in cycles/px (NOT normalised).
    """
    (d, f), scal, dt, _ = _as_tensors((diameter_px, "diameter_px"), (f_cycles_per_px, "f_cycles_per_px"))
    check_range(d, "diameter_px", 0.0, math.inf, "px")
    z = math.pi * d * f
    small = z.abs() < 1e-8
    z_safe = torch.where(small, torch.ones_like(z), z)
    val = torch.where(small, torch.ones_like(z), 2.0 * torch.special.bessel_j1(z_safe) / z_safe)
    return _finish(val.abs(), scal, dt)


def line_mtf(length_px: TensorOrFloat, f_cycles_per_px: TensorOrFloat) -> TensorOrFloat:
    """Continuous MTF of a uniform line of length L px along the frequency direction: ``|sinc(L f)|``.

    ``sinc(u) = sin(πu)/(πu)``. Across the line (perpendicular direction) the MTF is 1.
    """
    (length, f), scal, dt, _ = _as_tensors((length_px, "length_px"), (f_cycles_per_px, "f_cycles_per_px"))
    check_range(length, "length_px", 0.0, math.inf, "px")
    return _finish(torch.sinc(length * f).abs(), scal, dt)


def pixel_aperture_mtf(f_cycles_per_px: TensorOrFloat) -> TensorOrFloat:
    """MTF of the 1 px square pixel aperture along an axis: ``|sinc(f)|`` (f in cycles/px).

    A pixel-area-integrated kernel (continuous PSF ⊗ 1 px box, sampled) has DFT
    ``Σ_n P(f−n)·sinc(f−n)``, i.e. ≈ continuous MTF × this factor when aliasing (n ≠ 0) is negligible.
    """
    (f,), scal, dt, _ = _as_tensors((f_cycles_per_px, "f_cycles_per_px"))
    return _finish(torch.sinc(f).abs(), scal, dt)


def mtf_indicator(mtf_hv: torch.Tensor) -> torch.Tensor:
    """IOPC blur indicator MTF̃: mean of the H and V MTF at f_n = 0.1, from (..., 16) labels → (...)."""
    m = check_float(check_tensor(mtf_hv, "mtf_hv"), "mtf_hv")
    n = len(NORMALIZED_FREQUENCIES)
    if m.ndim < 1 or m.shape[-1] != 2 * n:
        raise ValueError(f"mtf_hv must have shape (..., {2 * n}) ([H×{n}, V×{n}]), got {tuple(m.shape)}")
    return 0.5 * (m[..., _INDICATOR_INDEX] + m[..., n + _INDICATOR_INDEX])
