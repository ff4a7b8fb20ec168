"""An independent implementation of the Konnik–Welsh sensor model, with the variants that real simulators differ by.

The robustness benchmark (``python -m camhealth.bench robustness``) scores camhealth's noise estimators on data
camhealth's own simulator (:mod:`camhealth.physics`) did not make: this module is written from the model's
equations (conventions.md, thesis Eq. 3.14–3.19) in NumPy float64 and imports no camhealth physics — only the
:class:`~camhealth.physics.CameraMetadata` container for the field values. Its random numbers come from NumPy,
its readout-noise integral from its own quadrature, its photon and dark-current shot noise from the normal
approximation or exact Poisson counts, and the variants change details in which implementations of the same
model differ:

=====================  ====================================================================================
variant                what changes
=====================  ====================================================================================
``whole_electrons``    photon and dark electrons are whole numbers (exact Poisson counts) instead of the
                       normal approximation N + √N·z
``rn_whole_electrons`` the readout noise is rounded to whole electrons
``ktc_lognormal``      CMOS reset (kTC) noise as a log-normal factor on the sense-node reference voltage,
                       V_ref·(exp(s·z) − 1)/A_SN electrons with s = σ_kTC·A_SN/V_ref, instead of additive
                       Gaussian electrons
``sequential_clip``    the charge is clipped to [0, FW/g] e⁻ (0…255 DN) after every source, not once at the end
``reverse_order``      the sources are applied in the other order, readout → dark current → photon, and the
                       charge is clipped to [0, FW/g] e⁻ (0…255 DN) after every source (so it implies
                       ``sequential_clip``): a stage that clips takes away charge that a later stage would have
                       moved back into range, so the image depends on the order. Without a clip between the stages
                       the order would change nothing but which random numbers each stage gets (no stage reads the
                       running charge: photon shot noise is drawn from the clean signal N, not from the charge
                       after readout), so the variant is this order *with* clipping; where no stage's running
                       charge leaves [0, FW/g] the image equals the reference order's for the same random numbers
``round8``             the output is rounded to whole DN (8-bit quantisation) at the end
=====================  ====================================================================================

Model (per pixel, in electrons; g = 10^(gain_dB/20), FW the full well, the ADC maps FW/g e⁻ to 255 DN):
signal N = I·FW/g for an output intensity I ∈ [0, 1]; photon shot noise of variance N; dark-current shot noise
of variance S = DC·t_exp with DC = 2.55e15·d_p²·D_FM·T^1.5·exp(−E_g(T)/(2kT)) e⁻/s, E_g = 1.1557 −
7.021e-4·T²/(T + 1108) eV (its mean removed: offset 0 DN); readout noise of variance σ_SF² + (reset·σ_kTC)²
(CMOS) with σ_SF² = ∫₀^{f_clock} S_SF(f)·H_CDS(f) df / (A_SN·A_SF·(1 − e^{−t_s/τ_D}))², S_SF = W²(1 + f_c/f) +
[CMOS]·2ΔI²τ_RTN/(4 + (2πfτ_RTN)²), H_CDS = (2 − 2cos 2πf t_s)/(1 + (2πfτ_D)²), σ_kTC = √(kT/(q·A_SN)).

Labels: each source's realised noise in DN after clipping. With clipping only at the end, the clipped part of
a pixel's total noise is shared among the sources in proportion to their realised noise (the conventions'
rule); with ``sequential_clip`` or ``reverse_order`` a source's contribution is what its stage changed after that
stage's clip. The 8-bit rounding error is part of the total but of no source.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from camhealth.physics.metadata import FULL_FIELDS, CameraMetadata

__all__ = ["VARIANTS", "simulate_variant", "expected_sigma_e", "metadata_arrays"]

VARIANTS: tuple[str, ...] = (
    "whole_electrons", "rn_whole_electrons", "ktc_lognormal", "sequential_clip", "reverse_order", "round8",
)

_Q = 1.602176634e-19  # C
_K_J = 1.380649e-23  # J/K
_K_EV = 8.617343e-5  # eV/K

#: Largest Poisson mean [e⁻] ``whole_electrons`` draws (NumPy's Poisson sampler refuses means above ≈ 9.2e18).
_POISSON_MAX_E = 1e18
#: Lowest frequency of the readout-noise quadrature [Hz]: a pixel clock must lie above it.
_F_LOW_HZ = 1e-3
#: Most periods of the CDS cosine, f_clock·t_s, the readout-noise quadrature integrates over (128 nodes each): 2e4
#: (2.6e6 nodes; a camera in the metadata's ranges needs at most 1.5e4).
_MAX_CDS_PERIODS = 2e4


def _override_range(name: str, t_s: float) -> tuple[float, float, bool, str]:
    """``(low, high, low_open, text)``: the values an override of ``name`` may take (beyond the metadata's ranges, but
    where the model is defined and computable), with the range as the message writes it."""
    if name == "gain_db":
        return -np.inf, np.inf, False, "(-inf, inf) dB, finite (whole_electrons also bounds the full scale)"
    if name == "temperature_c":
        return -273.15, np.inf, True, "(-273.15, inf) °C (above absolute zero)"
    if name in ("full_well_e", "sense_node_gain_v_per_e", "pixel_size_um"):
        return 0.0, np.inf, True, "(0, inf), finite"
    if name == "pixel_clock_hz":
        high = _MAX_CDS_PERIODS / t_s
        return _F_LOW_HZ, high, True, (f"({_F_LOW_HZ:g}, {high:g}] Hz (the readout-noise integral runs from {_F_LOW_HZ:g} Hz "
                                      f"over at most {_MAX_CDS_PERIODS:g} periods of the CDS sample time t_s = {t_s:g} s)")
    return 0.0, np.inf, False, "[0, inf), finite (≥ 0)"


def metadata_arrays(meta: CameraMetadata, batch: int, overrides: dict | None = None) -> dict[str, np.ndarray]:
    """The metadata's fields as float64 NumPy arrays of length ``batch``; ``overrides`` replace fields by values
    that need not lie in the metadata's ranges (an altered camera: white noise ×4, a gain beyond 24 dB), but must lie
    where the model is defined: finite; ``full_well_e``, ``sense_node_gain_v_per_e``, ``pixel_size_um`` > 0;
    ``temperature_c`` > −273.15 °C; ``pixel_clock_hz`` in (1e-3 Hz, 2e4 / t_s] (the readout-noise quadrature); the
    others ≥ 0. ``ValueError`` naming the field, the value and its allowed range otherwise."""
    if meta.batch_size not in (1, batch):
        raise ValueError(f"metadata batch {meta.batch_size} does not match the {batch} images")
    out = {n: np.broadcast_to(getattr(meta, n).detach().cpu().double().numpy(), (batch,)).copy() for n in FULL_FIELDS}
    c = meta.constants
    for name, value in (overrides or {}).items():
        if name not in out:
            raise ValueError(f"override {name!r} is not a metadata field; fields: {list(FULL_FIELDS)}")
        v = np.broadcast_to(np.asarray(value, dtype=np.float64), (batch,)).copy()
        low, high, low_open, text = _override_range(name, float(c.cds_sample_time_s))
        ok = np.isfinite(v) & (v <= high) & ((v > low) if low_open else (v >= low))
        if not ok.all():
            raise ValueError(f"override {name} = {v[~ok][0]:g} is out of the allowed range {text}"
                             + (f" (values {v.min():g} … {v.max():g})" if batch > 1 else ""))
        out[name] = v
    out.update(
        t_s=np.full(batch, c.cds_sample_time_s), tau_d=np.full(batch, c.cds_time_factor * c.cds_sample_time_s),
        f_c=np.full(batch, c.flicker_corner_hz), d_i=np.full(batch, c.rtn_current_a),
        tau_rtn=np.full(batch, c.rtn_time_factor * c.cds_time_factor * c.cds_sample_time_s),
        a_sf=np.full(batch, c.source_follower_gain), v_ref=np.full(batch, c.reference_voltage_v),
    )
    return out


def _cds_integrals(f_clock: float, t_s: float, tau_d: float, f_c: float, tau_rtn: float) -> tuple[float, float]:
    """∫₀^{f_clock} (1 + f_c/f)·H_CDS df [Hz] and ∫₀^{f_clock} 2τ_RTN/(4 + (2πfτ_RTN)²)·H_CDS df [s·Hz] by Simpson's
    rule on a grid geometric below 1 MHz (the 1/f part; H_CDS ∝ f² near 0, so the integrand vanishes there) and
    uniform above with 64 nodes per period of the CDS cosine."""
    f_split = min(f_clock, 1e6)
    low = np.geomspace(1e-3, f_split, 6001)
    parts = [low]
    if f_clock > f_split:
        n = int(np.ceil((f_clock - f_split) * t_s * 64)) * 2 + 1
        parts.append(np.linspace(f_split, f_clock, max(n, 3)))
    i_w = i_r = 0.0
    for f in parts:
        w = 2.0 * np.pi * f
        h = (2.0 - 2.0 * np.cos(w * t_s)) / (1.0 + (w * tau_d) ** 2)
        g_w = (1.0 + f_c / f) * h
        g_r = 2.0 * tau_rtn / (4.0 + (w * tau_rtn) ** 2) * h
        i_w += _simpson(g_w, f)
        i_r += _simpson(g_r, f)
    return i_w, i_r


def _simpson(y: np.ndarray, x: np.ndarray) -> float:
    """Composite Simpson on an odd number of nodes (trapezoid on the last interval if even)."""
    if len(x) % 2 == 0:
        return _simpson(y[:-1], x[:-1]) + 0.5 * (y[-1] + y[-2]) * (x[-1] - x[-2])
    h0, h1 = np.diff(x)[0::2], np.diff(x)[1::2]
    y0, y1, y2 = y[:-2:2], y[1:-1:2], y[2::2]
    hs = h0 + h1
    return float(np.sum(hs / 6.0 * (y0 * (2.0 - h1 / h0) + y1 * hs * hs / (h0 * h1) + y2 * (2.0 - h0 / h1))))


def expected_sigma_e(m: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per-sample σ in electrons of dark-current shot noise (``dark``), source-follower noise (``sf``) and the CMOS kTC
    residue (``ktc``), and the dark signal S [e⁻] (``dark_signal``), from :func:`metadata_arrays`."""
    t = m["temperature_c"] + 273.15
    e_g = 1.1557 - 7.021e-4 * t**2 / (t + 1108.0)
    area_cm2 = (m["pixel_size_um"] * 1e-4) ** 2
    dc = 2.55e15 * area_cm2 * m["dark_fom_na_per_cm2"] * t**1.5 * np.exp(-e_g / (2.0 * _K_EV * t))
    s = dc * m["exposure_s"]
    cache: dict[tuple, tuple[float, float]] = {}
    sf = np.empty_like(t)
    for i in range(len(t)):
        key = (m["pixel_clock_hz"][i], m["t_s"][i], m["tau_d"][i], m["f_c"][i], m["tau_rtn"][i])
        if key not in cache:
            cache[key] = _cds_integrals(*key)
        i_w, i_r = cache[key]
        var_v2 = m["white_noise_v_per_rthz"][i] ** 2 * i_w + m["is_cmos"][i] * m["d_i"][i] ** 2 * i_r
        sf[i] = np.sqrt(var_v2) / (m["sense_node_gain_v_per_e"][i] * m["a_sf"][i] * (1.0 - np.exp(-m["t_s"][i] / m["tau_d"][i])))
    ktc = m["is_cmos"] * m["reset_factor"] * np.sqrt(_K_J * t / (_Q * m["sense_node_gain_v_per_e"]))
    return {"dark": np.sqrt(s), "sf": sf, "ktc": ktc, "dark_signal": s}


def _check_computable(m: dict[str, np.ndarray], sig: dict[str, np.ndarray], full: np.ndarray, dn_per_e: np.ndarray,
                      whole: bool, overrides: dict | None) -> None:
    """``ValueError`` where the camera (with ``overrides``) gives numbers the model cannot use: a full scale or noise
    that is not finite, or, with whole electrons, a Poisson mean beyond what can be drawn (naming the fields)."""
    given = f"; overrides: {overrides}" if overrides else ""
    bad = [what for what, v in (("full scale full_well_e / 10^(gain_db/20) [e⁻]", full), ("DN per electron", dn_per_e),
                                ("dark-current shot noise", sig["dark"]), ("source-follower noise", sig["sf"]),
                                ("kTC noise", sig["ktc"])) if not np.isfinite(v).all()]
    if bad:
        raise ValueError(f"the camera gives a non-finite {', '.join(bad)} (gain_db = {m['gain_db'].max():g}, "
                         f"full_well_e = {m['full_well_e'].min():g}, temperature_c = {m['temperature_c'].max():g}, "
                         f"exposure_s = {m['exposure_s'].max():g}){given}")
    if not whole:
        return
    if full.max() > _POISSON_MAX_E:
        i = int(np.argmax(full))
        g_min = 20.0 * np.log10(m["full_well_e"][i] / _POISSON_MAX_E)
        raise ValueError(
            f"whole_electrons draws Poisson counts of at most {_POISSON_MAX_E:g} e⁻, but gain_db = {m['gain_db'][i]:g} "
            f"gives a full scale of {full[i]:g} e⁻ (full_well_e = {m['full_well_e'][i]:g} / 10^(gain_db/20)): gain_db "
            f"must be ≥ {g_min:.4g} dB for this full well{given}")
    dark = sig["dark_signal"]
    if dark.max() > _POISSON_MAX_E:
        i = int(np.argmax(dark))
        raise ValueError(
            f"whole_electrons draws Poisson counts of at most {_POISSON_MAX_E:g} e⁻, but the dark signal is {dark[i]:g} e⁻ "
            f"(temperature_c = {m['temperature_c'][i]:g}, exposure_s = {m['exposure_s'][i]:g}, dark_fom_na_per_cm2 = "
            f"{m['dark_fom_na_per_cm2'][i]:g}, pixel_size_um = {m['pixel_size_um'][i]:g}): lower them{given}")


def simulate_variant(
    clean: torch.Tensor,
    meta: CameraMetadata,
    variants: Sequence[str] = (),
    generator: torch.Generator | None = None,
    overrides: dict | None = None,
    extra_read_noise_dn: torch.Tensor | float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Corrupt clean images with the sensor model of this module (module docstring).

    Args:
        clean: B×1×H×W output intensities in [0, 1] (what the image would be without noise).
        meta: the camera the image is made with (batch 1 or B).
        variants: any of :data:`VARIANTS`, combined.
        generator: seeds NumPy's generator (one draw from it), for reproducible noise.
        overrides: field → value(s) replacing ``meta``'s, also outside the metadata's ranges (a camera outside the
            ranges), where the model is defined (:func:`metadata_arrays`).

    Raises:
        TypeError: ``variants`` is a single string.
        ValueError: ``clean`` not B×1×H×W, empty, not finite or not in [0, 1]; an unknown variant; an override out of
            its allowed range (naming the field, the value and the range); a camera whose full scale or noise is not
            finite, or, with ``whole_electrons``, whose full scale or dark signal exceeds 1e18 e⁻ (naming the fields).
        extra_read_noise_dn: (B,) or scalar σ [DN] of extra white Gaussian noise added with the readout noise
            (a noise level no metadata in range explains), counted as readout noise.

    Returns:
        (noisy B×1×H×W in [0, 1] float32, realised σ (B, 3) of photon, dark-current and readout noise [DN] float32)
    """
    if not isinstance(clean, torch.Tensor) or clean.ndim != 4 or clean.shape[1] != 1:
        raise ValueError(f"clean must be a B×1×H×W tensor, got {tuple(clean.shape) if isinstance(clean, torch.Tensor) else type(clean).__name__}")
    if clean.numel() == 0:
        raise ValueError(f"clean must hold at least one pixel, got shape {tuple(clean.shape)}")
    if isinstance(variants, (str, bytes)):
        raise TypeError(f"variants = {variants!r} must be a sequence of variant names, not a single string "
                        f"(e.g. ({variants!r},)); choose from {list(VARIANTS)}")
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise ValueError(f"unknown variant(s) {unknown}; choose from {list(VARIANTS)}")
    x = clean.detach().cpu().double().numpy()[:, 0]
    if not np.isfinite(x).all() or x.min() < 0 or x.max() > 1:
        raise ValueError("clean images must be finite and lie in [0, 1]")
    b = x.shape[0]
    seed = int(torch.randint(0, 2**62, (1,), generator=generator).item())
    rng = np.random.default_rng(seed)
    m = metadata_arrays(meta, b, overrides)
    sig = expected_sigma_e(m)
    g = 10.0 ** (m["gain_db"] / 20.0)
    full = (m["full_well_e"] / g)[:, None, None]  # e⁻ at 255 DN
    dn_per_e = 255.0 / full
    extra = np.zeros(b) if extra_read_noise_dn is None else np.broadcast_to(
        torch.as_tensor(extra_read_noise_dn, dtype=torch.float64).cpu().numpy(), (b,))
    if (extra < 0).any() or not np.isfinite(extra).all():
        raise ValueError("extra_read_noise_dn must be finite and ≥ 0")
    whole = "whole_electrons" in variants
    _check_computable(m, sig, full[:, 0, 0], dn_per_e[:, 0, 0], whole, overrides)
    shape = x.shape

    def photon(q: np.ndarray) -> np.ndarray:
        mean = x * full
        if whole:
            return rng.poisson(mean).astype(np.float64) - mean
        return np.sqrt(mean) * rng.standard_normal(shape)

    def dark(q: np.ndarray) -> np.ndarray:
        s = sig["dark_signal"][:, None, None] * np.ones(shape)
        if whole:
            return rng.poisson(s).astype(np.float64) - s
        return np.sqrt(s) * rng.standard_normal(shape)

    def readout(q: np.ndarray) -> np.ndarray:
        n = sig["sf"][:, None, None] * rng.standard_normal(shape)
        if "ktc_lognormal" in variants:
            a_sn, v_ref = m["sense_node_gain_v_per_e"][:, None, None], m["v_ref"][:, None, None]
            s = sig["ktc"][:, None, None] * a_sn / v_ref
            n = n + v_ref * np.expm1(s * rng.standard_normal(shape)) / a_sn
        else:
            n = n + sig["ktc"][:, None, None] * rng.standard_normal(shape)
        n = n + (extra[:, None, None] / dn_per_e) * rng.standard_normal(shape)
        return np.round(n) if "rn_whole_electrons" in variants else n

    stages = [("pn", photon), ("dc", dark), ("rn", readout)]
    if "reverse_order" in variants:  # another order only matters with a clip between the stages (module docstring)
        stages = stages[::-1]
    signal = x * full
    q = signal.copy()
    contrib = {}
    sequential = "sequential_clip" in variants or "reverse_order" in variants
    for name, draw in stages:
        before = q
        q = q + draw(q)
        if sequential:
            q = np.clip(q, 0.0, full)
        contrib[name] = q - before
    y = np.clip(q, 0.0, full)
    if not sequential:  # clipped part shared in proportion to each source's realised noise
        total = q - signal
        ratio = np.where(total != 0, (y - signal) / np.where(total != 0, total, 1.0), 1.0)
        contrib = {k: v * ratio for k, v in contrib.items()}
    out = y * dn_per_e
    if "round8" in variants:
        out = np.round(out)
    sigma = np.stack([(contrib[k] * dn_per_e).reshape(b, -1).std(1) for k in ("pn", "dc", "rn")], axis=1)
    noisy = torch.from_numpy(np.clip(out / 255.0, 0.0, 1.0)).float().unsqueeze(1)
    return noisy, torch.from_numpy(sigma).float()
