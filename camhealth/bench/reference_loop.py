"""A straightforward per-image NumPy/SciPy implementation of the camera corruption, for timing.

This is the *slow reference* the batched torch pipeline (:func:`camhealth.physics.image_formation.form_image`
behind :class:`camhealth.augment.CameraCorruption`) is measured against. It computes the same physics the
way a plain research script does (and the way the thesis's code does it): one image at a time, PSFs built
by Python loops over the kernel pixels, ``scipy.ndimage.convolve`` for the blurs, NumPy Poisson/Gaussian
draws per noise source, and the source-follower noise integral (Eq. 3.17–3.19) as a **Python loop over
~15 000 frequencies** per image. It is deliberately unoptimised, but it must be correct: the tests check
its PSFs against :mod:`camhealth.physics.defocus_psf` / :mod:`~camhealth.physics.motion_psf`, its σ_SF
against :func:`camhealth.physics.readout_noise.source_follower_sigma_e` and its realised noise σ against
the torch pipeline.

Chain (conventions.md, Fig. 3.7): clean → defocus → photon shot noise → motion blur (signal and photon
noise) → dark-current shot noise → readout noise → gain (folded into the electron → intensity scale
g/FW) → clip to [0, 1]. Images are float64 H×W in [0, 1] (= DN/255); σ labels are in DN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
from scipy import ndimage

from camhealth.physics.metadata import (
    BOLTZMANN_EV_PER_K,
    BOLTZMANN_J_PER_K,
    ELEMENTARY_CHARGE_C,
    FULL_FIELDS,
    SensorConstants,
)

__all__ = [
    "N_FREQUENCIES",
    "ReferenceResult",
    "disk_psf_loop",
    "linear_motion_psf_loop",
    "source_follower_sigma_e_loop",
    "corrupt_image",
    "corrupt_batch",
    "params_from_torch",
]

#: Number of frequencies of the source-follower noise sum (the reference script's loop length).
N_FREQUENCIES = 15_000


# ----------------------------------------------------------------------------------------------- PSFs
def _quadrant_area(x: float, y: float, r: float) -> float:
    """Signed area of disk(0, r) ∩ [0, x] × [0, y] (sign(x)·sign(y) times the area for |x|, |y|)."""
    if r <= 0.0 or x == 0.0 or y == 0.0:
        return 0.0
    sign = math.copysign(1.0, x) * math.copysign(1.0, y)
    ax, ay = min(abs(x), r), min(abs(y), r)
    # the circle is at height ay for |u| <= t_star; beyond it the column height is sqrt(r² − u²)
    t_star = math.sqrt(max(r * r - ay * ay, 0.0))
    xm = min(ax, t_star)

    def primitive(t: float) -> float:  # ∫_0^t sqrt(r² − u²) du
        return 0.5 * (t * math.sqrt(max(r * r - t * t, 0.0)) + r * r * math.asin(max(-1.0, min(1.0, t / r))))

    return sign * (ay * xm + primitive(ax) - primitive(xm))


def disk_psf_loop(diameter_px: float, kernel_size: int) -> np.ndarray:
    """Uniform-disk defocus PSF: each pixel's value is the exact area of the pixel square covered by the
    disk of diameter ``diameter_px`` centred on the kernel centre, normalised to sum 1 (delta if the disk
    covers nothing). Python loop over the k×k pixels."""
    k = int(kernel_size)
    r = 0.5 * float(diameter_px)
    c = (k - 1) / 2.0
    psf = np.zeros((k, k))
    for i in range(k):
        y0, y1 = i - c - 0.5, i - c + 0.5
        for j in range(k):
            x0, x1 = j - c - 0.5, j - c + 0.5
            psf[i, j] = (
                _quadrant_area(x1, y1, r) - _quadrant_area(x0, y1, r) - _quadrant_area(x1, y0, r) + _quadrant_area(x0, y0, r)
            )
    total = psf.sum()
    if total <= 0.0:
        psf[:] = 0.0
        psf[k // 2, k // 2] = 1.0
        return psf
    return psf / total


def _clip_length(ax: float, ay: float, bx: float, by: float, x0: float, x1: float, y0: float, y1: float) -> float:
    """Length of the segment a→b inside the rectangle [x0, x1]×[y0, y1] (Liang–Barsky clipping)."""
    dx, dy = bx - ax, by - ay
    t0, t1 = 0.0, 1.0
    for p, q in ((-dx, ax - x0), (dx, x1 - ax), (-dy, ay - y0), (dy, y1 - ay)):
        if p == 0.0:
            if q < 0.0:
                return 0.0
            continue
        t = q / p
        if p < 0.0:
            t0 = max(t0, t)
        else:
            t1 = min(t1, t)
        if t0 > t1:
            return 0.0
    return (t1 - t0) * math.hypot(dx, dy)


def linear_motion_psf_loop(length_px: float, angle_deg: float, kernel_size: int) -> np.ndarray:
    """Linear motion PSF: a segment of length L at angle Φ (0° horizontal, counter-clockwise with the y
    axis pointing down) centred on the kernel; each pixel's value is the segment length inside its square,
    normalised to sum 1 (delta for L = 0). Python loop over the k×k pixels."""
    k = int(kernel_size)
    c = (k - 1) / 2.0
    phi = math.radians(float(angle_deg))
    hx, hy = 0.5 * float(length_px) * math.cos(phi), -0.5 * float(length_px) * math.sin(phi)
    psf = np.zeros((k, k))
    if length_px <= 0.0:
        psf[k // 2, k // 2] = 1.0
        return psf
    for i in range(k):
        for j in range(k):
            psf[i, j] = _clip_length(-hx, -hy, hx, hy, j - c - 0.5, j - c + 0.5, i - c - 0.5, i - c + 0.5)
    return psf / psf.sum()


# ------------------------------------------------------------------------------------- noise physics
def source_follower_sigma_e_loop(
    white_noise_v_per_rthz: float,
    pixel_clock_hz: float,
    sense_node_gain_v_per_e: float,
    is_cmos: bool,
    constants: SensorConstants = SensorConstants(),
    n_frequencies: int = N_FREQUENCIES,
) -> float:
    """Source-follower noise σ_SF [e⁻] (Eq. 3.17–3.19) as a Python loop over ``n_frequencies`` midpoints
    of a uniform grid from 0 to the pixel clock: Σ S_SF(f)·H_CDS(f)·Δf, with S_SF = W²(1 + f_c/f)
    (+ RTN for CMOS) and H_CDS = (2 − 2cos 2πf t_s)/(1 + (2πf τ_D)²)."""
    t_s = constants.cds_sample_time_s
    tau_d = constants.cds_time_constant_s
    tau_rtn = constants.rtn_time_constant_s
    f_c = constants.flicker_corner_hz
    d_i2 = constants.rtn_current_a**2
    w2 = white_noise_v_per_rthz**2
    df = pixel_clock_hz / n_frequencies
    variance = 0.0
    for n in range(n_frequencies):
        f = (n + 0.5) * df
        psd = w2 * (1.0 + f_c / f)
        if is_cmos:
            psd += 2.0 * d_i2 * tau_rtn / (4.0 + (2.0 * math.pi * f * tau_rtn) ** 2)
        h_cds = (2.0 - 2.0 * math.cos(2.0 * math.pi * f * t_s)) / (1.0 + (2.0 * math.pi * f * tau_d) ** 2)
        variance += psd * h_cds * df
    gain = sense_node_gain_v_per_e * constants.source_follower_gain * (1.0 - math.exp(-t_s / tau_d))
    return math.sqrt(variance) / gain


def _dark_signal_e(m: Mapping[str, float]) -> float:
    """Mean dark signal DC·t_exp [e⁻] (Eq. 3.14, Varshni band gap)."""
    t = m["temperature_c"] + 273.15
    e_gap = 1.1557 - 7.021e-4 * t * t / (t + 1108.0)
    area_cm2 = (m["pixel_size_um"] * 1e-4) ** 2
    dc = 2.55e15 * area_cm2 * m["dark_fom_na_per_cm2"] * t**1.5 * math.exp(-e_gap / (2.0 * BOLTZMANN_EV_PER_K * t))
    return dc * m["exposure_s"]


def _reset_sigma_e(m: Mapping[str, float]) -> float:
    """kTC residue after CDS [e⁻] (CMOS only): reset_factor·√(kT/(q·A_SN))."""
    if m["is_cmos"] < 0.5:
        return 0.0
    t = m["temperature_c"] + 273.15
    return m["reset_factor"] * math.sqrt(BOLTZMANN_J_PER_K * t / (ELEMENTARY_CHARGE_C * m["sense_node_gain_v_per_e"]))


def _convolve(image: np.ndarray, psf: np.ndarray) -> np.ndarray:
    k = psf.shape[0]
    if k == 1:
        return image * psf[0, 0]
    mode = "mirror" if k // 2 < min(image.shape) else "nearest"  # = torch 'reflect' / 'replicate'
    return ndimage.convolve(image, psf, mode=mode)


@dataclass
class ReferenceResult:
    """Output of :func:`corrupt_batch`: images (B, H, W) in [0, 1]; ``sigma_dn`` (B, 3) realised σ of
    (PN, DCSN, RN) before clipping [DN]; ``sigma_total_dn`` (B,) after clipping [DN]; ``sigma_sf_e`` (B,)."""

    image: np.ndarray
    sigma_dn: np.ndarray
    sigma_total_dn: np.ndarray
    sigma_sf_e: np.ndarray


def corrupt_image(
    image: np.ndarray,
    meta: Mapping[str, float],
    rng: np.random.Generator,
    diameter_px: float | None = None,
    defocus_kernel: int | None = None,
    length_px: float | None = None,
    angle_deg: float = 0.0,
    motion_kernel: int | None = None,
    constants: SensorConstants = SensorConstants(),
    n_frequencies: int = N_FREQUENCIES,
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Corrupt one H×W image in [0, 1]; returns (image, σ per source [DN], σ total [DN], σ_SF [e⁻])."""
    x = np.asarray(image, dtype=np.float64)
    if diameter_px is not None and defocus_kernel is not None:
        x = _convolve(x, disk_psf_loop(diameter_px, defocus_kernel))
    gain = 10.0 ** (meta["gain_db"] / 20.0)
    e_to_int = gain / meta["full_well_e"]  # intensity per electron (the gain is applied here)
    # photon shot noise, in electrons, before motion blur
    electrons = np.clip(x, 0.0, None) / e_to_int
    n_pn = (rng.poisson(electrons) - electrons) * e_to_int
    if length_px is not None and motion_kernel is not None:
        psf = linear_motion_psf_loop(length_px, angle_deg, motion_kernel)
        x = _convolve(x, psf)
        n_pn = _convolve(n_pn, psf)
    # dark-current shot noise
    dark = _dark_signal_e(meta)
    n_dc = (rng.poisson(dark, size=x.shape) - dark) * e_to_int
    # readout noise: source follower (loop over frequencies) + kTC residue
    sf = source_follower_sigma_e_loop(
        meta["white_noise_v_per_rthz"], meta["pixel_clock_hz"], meta["sense_node_gain_v_per_e"],
        meta["is_cmos"] >= 0.5, constants, n_frequencies,
    )
    rn = math.sqrt(sf**2 + _reset_sigma_e(meta) ** 2)
    n_rn = rng.normal(0.0, rn, size=x.shape) * e_to_int
    y = np.clip(x + n_pn + n_dc + n_rn, 0.0, 1.0)
    sigma = np.array([n.std(ddof=1) * 255.0 for n in (n_pn, n_dc, n_rn)])
    return y, sigma, float((y - x).std(ddof=1) * 255.0), sf


def corrupt_batch(
    images: np.ndarray,
    meta: Mapping[str, Sequence[float]],
    seed: int = 0,
    diameter_px: Sequence[float] | None = None,
    defocus_kernel: int | None = None,
    length_px: Sequence[float] | None = None,
    angle_deg: Sequence[float] | None = None,
    motion_kernel: int | None = None,
    n_frequencies: int = N_FREQUENCIES,
) -> ReferenceResult:
    """Corrupt a batch (B, H, W) (or B×1×H×W) image by image, with per-image metadata ``meta`` (field →
    B values, the fields of :class:`~camhealth.physics.metadata.CameraMetadata`) and per-image blur
    parameters (``None`` = that blur is absent)."""
    imgs = np.asarray(images, dtype=np.float64)
    if imgs.ndim == 4:
        imgs = imgs[:, 0]
    rng = np.random.default_rng(seed)
    out, sig, tot, sfs = [], [], [], []
    for i in range(imgs.shape[0]):
        m = {name: float(np.asarray(meta[name]).reshape(-1)[i]) for name in FULL_FIELDS}
        y, s, t, sf = corrupt_image(
            imgs[i], m, rng,
            diameter_px=None if diameter_px is None else float(diameter_px[i]), defocus_kernel=defocus_kernel,
            length_px=None if length_px is None else float(length_px[i]),
            angle_deg=0.0 if angle_deg is None else float(angle_deg[i]), motion_kernel=motion_kernel,
            n_frequencies=n_frequencies,
        )
        out.append(y)
        sig.append(s)
        tot.append(t)
        sfs.append(sf)
    return ReferenceResult(np.stack(out), np.stack(sig), np.array(tot), np.array(sfs))


def params_from_torch(params: Mapping[str, object], defocus_kernel: int | None, motion_kernel: int | None) -> dict:
    """Keyword arguments of :func:`corrupt_batch` from the ``_params`` of a camhealth corruption module
    (gated-off components get diameter/length 0), so the reference redoes the same corruption."""

    def arr(key: str) -> np.ndarray:
        return np.asarray(params[key].detach().cpu().double().numpy())  # type: ignore[union-attr]

    kw: dict = {"meta": {name: arr(f"meta_{name}") for name in FULL_FIELDS}}
    if defocus_kernel is not None:
        d = arr("diameter")
        if "defocus_gate" in params:
            d = np.where(arr("defocus_gate") > 0.5, d, 0.0)
        kw.update(diameter_px=d, defocus_kernel=defocus_kernel)
    if motion_kernel is not None:
        length = arr("length")
        if "motion_gate" in params:
            length = np.where(arr("motion_gate") > 0.5, length, 0.0)
        kw.update(length_px=length, angle_deg=arr("angle"), motion_kernel=motion_kernel)
    return kw
