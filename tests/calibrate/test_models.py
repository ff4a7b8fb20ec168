"""Closed forms of the calibration's models: censored and well-clipped fits, Alg. 1, the dark law, photon
transfer and the W inversion."""

import math

import numpy as np
import pytest
import torch

from camhealth.calibrate.dark_signal import DarkPoint, arrhenius_factor, dfm_from_c, fit_dark, fit_read_noise_law
from camhealth.calibrate.photon_transfer import FlatPoint, fit_photon_transfer
from camhealth.calibrate.readout import white_noise_from_sigma
from camhealth.calibrate.statistics import (
    mirrored_histogram_fit, poisson_gaussian_cdf, poisson_gaussian_group_fit, quantisation_step, set_statistics,
)
from camhealth.physics import CameraMetadata
from camhealth.physics.dark_current import dark_current_e_per_s
from camhealth.physics.readout_noise import source_follower_sigma_e


@pytest.mark.parametrize("sigma", [0.7, 3.0])
@pytest.mark.parametrize("quantised", [False, True])
def test_censored_fit_recovers_a_half_clipped_normal(sigma, quantised):
    rng = np.random.default_rng(1)
    x = np.clip(rng.normal(0.0, sigma, (8, 64, 64)), 0, 255)
    if quantised:
        x = np.rint(x)
    st = set_statistics((x / 255).astype(np.float32))
    assert st.method == "censored" and 0.3 < st.clipped_low < 0.9  # rounding adds [0, 0.5) DN to the 0 code
    assert st.step_dn == (1.0 if quantised else 0.0)
    assert st.sigma_dn == pytest.approx(sigma, rel=0.03)
    assert abs(st.mean_dn) < 0.05 * sigma
    assert st.var_err_dn2 / st.var_dn2 < 0.03
    # the plain sample std of the clipped values (Eq. 3.27 without rectification) is far too small
    assert x.std() < 0.7 * sigma


def test_temporal_estimator_ignores_fixed_pattern_and_subtracts_quantisation():
    rng = np.random.default_rng(2)
    pattern = rng.normal(0, 5.0, (64, 64))
    x = 100 + pattern + rng.normal(0, 2.0, (10, 64, 64))
    st = set_statistics((np.rint(x) / 255).astype(np.float32))
    assert st.method == "temporal"
    assert st.sigma_dn == pytest.approx(2.0, rel=0.03)  # σ² − 1/12 DN² of the 8-bit step
    assert math.sqrt(st.spatial_var_dn2) == pytest.approx(5.0, rel=0.05)


def test_alg1_histogram_mirroring_recovers_sigma():
    rng = np.random.default_rng(3)
    v = np.clip(rng.normal(20.0, 4.0, 200_000) - 17.0, 0, 255)  # mean 3, σ 4: the lower side clipped at 0
    mu, sigma = mirrored_histogram_fit(v, 0.0)
    assert sigma == pytest.approx(4.0, rel=0.1) and mu == pytest.approx(3.0, abs=0.5)


def test_quantisation_step():
    assert quantisation_step(np.array([0, 1, 7]) / 255.0) == pytest.approx(1.0)
    assert quantisation_step(np.array([0, 16, 48]) / 65535.0) == pytest.approx(255 * 16 / 65535)
    assert quantisation_step(np.array([0.1234567, 0.5])) == 0.0


@pytest.mark.parametrize("clip_charge", [False, True])
def test_poisson_gaussian_model_matches_monte_carlo_and_recovers_dark_current(clip_charge):
    rng = np.random.default_rng(4)
    k, sr, dc = 0.08, 0.9, 600.0  # DN/e⁻, DN, e⁻/s
    s = dc * 0.2
    q = k * (rng.poisson(s, 400_000) - s)
    y = (np.maximum(q, 0) if clip_charge else q) + rng.normal(0, sr, q.size)
    for x in (-1.0, 0.0, 0.5, 2.0):
        assert float(poisson_gaussian_cdf(np.array([x]), 0.0, sr, s, k, clip_charge)[0]) == pytest.approx((y <= x).mean(), abs=3e-3)
    hists, ts = [], [0.001, 0.1, 0.2]
    for t in ts:
        q = k * (rng.poisson(dc * t, (8, 64, 64)) - dc * t)
        frames = np.clip((np.maximum(q, 0) if clip_charge else q) + rng.normal(0, sr, q.shape), 0, 255)
        st = set_statistics((frames / 255).astype(np.float32))
        hists.append((st.hist_edges_dn, st.hist_counts))
    p, cov, _ = poisson_gaussian_group_fit(hists, ts, k, clip_charge, (0.0, 1.0, 300.0))
    assert p[1] == pytest.approx(sr, rel=0.02)
    assert abs(p[2] - dc) < 4 * math.sqrt(cov[2, 2]) + 0.02 * dc


def test_dark_fit_recovers_read_noise_and_dfm_exactly():
    k0, rn, c = 0.02, 10.0, 1e7  # C [e⁻/s/K^1.5]: DC(25 °C) ≈ 21 e⁻/s
    pts = [DarkPoint(t, tk, 2.0, 4.0 * k0**2 * (rn**2 + c * float(arrhenius_factor(tk)) * t), 1e-4)
           for tk in (298.15, 323.15, 348.15) for t in (0.001, 0.05, 0.2)]
    fit = fit_dark(pts)
    assert fit.c_dn2 / k0**2 == pytest.approx(c, rel=1e-6)
    assert np.sqrt(fit.intercept_dn2 / k0**2) == pytest.approx(rn, rel=1e-6)
    law = fit_read_noise_law(fit, k0, 0.0, False, 5e-6, None)
    assert math.sqrt(law.sf_var_e2) == pytest.approx(rn, rel=1e-6)
    # D_FM against the physics core's dark current at one temperature
    meta = CameraMetadata.preset("ICX285", temperature_c=50.0, dark_fom_na_per_cm2=dfm_from_c(c, 6.45)).to(dtype=torch.float64)
    assert float(dark_current_e_per_s(meta)) == pytest.approx(c * float(arrhenius_factor(323.15)), rel=1e-6)


def test_dark_fit_needs_a_span_of_exposures():
    with pytest.raises(ValueError, match="at least 2 exposures at one temperature"):
        fit_dark([DarkPoint(0.01, 300.0, 1.0, 1.0, 0.01), DarkPoint(0.01, 320.0, 1.0, 1.0, 0.01)])
    with pytest.raises(ValueError, match="span only 2.00×.*at least 4×"):
        fit_dark([DarkPoint(0.01, 300.0, 1.0, 1.0, 0.01), DarkPoint(0.02, 300.0, 1.0, 1.1, 0.01)])


def test_photon_transfer_slope_is_k0():
    k0 = 255.0 / 12000.0
    pts = []
    for gdb in (0.0, 12.0):
        g = 10 ** (gdb / 20)
        for mu in (10.0, 50.0, 120.0):
            pts.append(FlatPoint(f"{gdb}-{mu}", 0.01, 298.15, g, mu, 0.01, g * k0 * mu + 0.3 * g * g, 1e-3, 0.0, 0.0, gdb))
    fit = fit_photon_transfer(pts, lambda t, tk, g: (0.3 * g * g, 1e-4))
    assert fit.k0 == pytest.approx(k0, rel=1e-6)
    assert all(v[0] == pytest.approx(k0, rel=1e-6) for v in fit.per_gain.values())


@pytest.mark.parametrize("preset", ["ICX285", "EV76C661"])
def test_white_noise_inversion_round_trips_eq_3_17(preset):
    meta = CameraMetadata.preset(preset).to(dtype=torch.float64)
    sf = float(source_follower_sigma_e(meta))
    inv = white_noise_from_sigma(sf, 0.01 * sf, float(meta.pixel_clock_hz), float(meta.sense_node_gain_v_per_e), bool(meta.is_cmos))
    assert inv.white_noise_v_per_rthz == pytest.approx(float(meta.white_noise_v_per_rthz), rel=1e-6)
    assert inv.white_noise_err / inv.white_noise_v_per_rthz == pytest.approx(0.01, rel=0.05)


def test_dead_pixels_against_the_local_median_survive_vignetting():
    """A flat with 50 % vignetting and 1 % PRNU has no dead pixel; a pixel at half its neighbours' response in the
    centre, one at 20 % and one at 0 are found — the first one a global rule misses (the shading makes its MAD
    ~19 DN); hot pixels excluded are never flagged."""
    from camhealth.calibrate.statistics import DEAD_PIXEL_SIGMAS, detect_dead_pixels

    rng = np.random.default_rng(0)
    h, w = 200, 300
    yy, xx = np.mgrid[:h, :w]
    r2 = ((yy - h / 2) ** 2 + (xx - w / 2) ** 2) / ((h / 2) ** 2 + (w / 2) ** 2)
    flat = 150.0 * (1.0 - 0.5 * r2) * (1.0 + 0.01 * rng.standard_normal((h, w)))
    assert not detect_dead_pixels(flat, 2.0, 16, 0.0).any()
    flat[100, 100] *= 0.5
    med = np.median(flat)
    assert flat[100, 100] > med - DEAD_PIXEL_SIGMAS * 1.4826 * np.median(np.abs(flat - med))  # global: not dead
    flat[10, 10] *= 0.2
    flat[100, 150] = 0.0
    exclude = np.zeros((h, w), dtype=bool)
    exclude[50, 60] = True
    flat[50, 60] = 0.0  # excluded: not flagged
    found = detect_dead_pixels(flat, 2.0, 16, 0.0, exclude)
    assert {tuple(p) for p in np.argwhere(found)} == {(100, 100), (10, 10), (100, 150)}


def test_identical_or_constant_frames_are_refused_and_one_code_gives_no_step():
    """A constant set (one code) is not a quantisation step of 128 DN with a variance of −1365 DN², and a frame
    repeated N times has no temporal noise: both are refused naming the set."""
    const = np.full((6, 32, 32), 128 / 255, np.float32)
    assert quantisation_step(const) == pytest.approx(255 / 65535)  # the finest step, not the code's own value
    with pytest.raises(ValueError, match=r"^bias 7: its 6 frames are identical .*every value is 128 DN"):
        set_statistics(const, name="bias 7")
    rng = np.random.default_rng(0)
    frame = np.clip(np.rint(100 + 3 * rng.standard_normal((32, 32))), 0, 255) / 255
    with pytest.raises(ValueError, match="frames are identical"):
        set_statistics(np.repeat(frame[None], 6, 0).astype(np.float32))
    assert quantisation_step(np.array([0, 1]) / 255.0) == pytest.approx(1.0)  # 0 and one code: still 8-bit


@pytest.mark.parametrize("level", [10.0, 10.5])
def test_noise_below_half_a_code_step_is_quantisation_limited(level):
    """σ = 0.25 DN in 8-bit data: q²/12 is no correction there (σ² − q²/12 comes out 0 or 3× too large, depending on
    where the level sits between codes); the set is marked, and σ = 0.7 DN is not."""
    rng = np.random.default_rng(5)
    st = set_statistics((np.rint(level + 0.25 * rng.standard_normal((20, 32, 32))) / 255).astype(np.float32))
    assert st.method == "temporal" and st.quantisation_limited and st.raw_var_dn2 < 0.3
    st = set_statistics((np.rint(level + 0.7 * rng.standard_normal((20, 32, 32))) / 255).astype(np.float32))
    assert not st.quantisation_limited and st.sigma_dn == pytest.approx(0.7, rel=0.03)


def test_temporal_variance_removes_each_frames_mean():
    """A light that changes by 2 % rms from frame to frame (4 DN² at 100 DN) does not enter the temporal variance."""
    rng = np.random.default_rng(6)
    flicker = 1 + 0.02 * rng.standard_normal((10, 1, 1))
    x = (100 + rng.normal(0, 5.0, (64, 64))) * flicker + rng.normal(0, 2.0, (10, 64, 64))
    st = set_statistics((x / 255).astype(np.float32))
    assert st.method == "temporal" and st.sigma_dn == pytest.approx(2.0, rel=0.03)


def test_values_piling_up_below_255_dn_are_clipped_there():
    """A pixel full well at 230 DN and 12-bit data MSB-aligned in 16 bits (top code 254.94 DN) clip below 255 DN; a
    coarse 8-bit set whose highest code holds 0.3 % of its values by chance (σ = 0.72 DN) does not."""
    from camhealth.calibrate.statistics import top_clip_level

    rng = np.random.default_rng(7)
    clipped = np.minimum(np.rint(225 + 2.5 * rng.standard_normal((8, 64, 64))), 230.0)
    assert top_clip_level(clipped, 1.0) == 230.0
    st = set_statistics((clipped / 255).astype(np.float32))
    assert st.upper_dn == pytest.approx(230.0) and st.method == "censored" and st.clipped_high == pytest.approx((clipped == 230).mean())
    assert st.sigma_dn == pytest.approx(2.5, rel=0.03)  # the censored fit with the values at 230 DN as "≥ 230"
    msb = np.minimum(np.rint(np.clip(250 + 3 * rng.standard_normal((8, 64, 64)), 0, 255) / 255 * 4095), 4095) * 16 / 65535
    assert top_clip_level(msb * 255, 255 * 16 / 65535) == pytest.approx(65520 / 65535 * 255)
    coarse = np.rint(25.5 + 0.72 * rng.standard_normal((20, 64, 64)))
    assert top_clip_level(coarse, 1.0) == 255.0 and set_statistics((coarse / 255).astype(np.float32)).method == "temporal"


def _flats(k0, gains=(0.0, 12.0), mus=(10.0, 50.0, 120.0), k_of_gain=None):
    pts = []
    for gdb in gains:
        g = 10 ** (gdb / 20)
        k = (k_of_gain or {}).get(gdb, k0)
        for mu in mus:
            pts.append(FlatPoint(f"{gdb:g}dB-{mu:g}", 0.01, 298.15, g, mu, 0.01, g * k * mu + 0.3 * g * g, 0.01 * g * k * mu, 0.0, 0.0, gdb))
    return pts


def test_photon_transfer_leaves_out_partly_clipped_quantisation_limited_and_saturating_flats():
    k0 = 255.0 / 12000.0
    pts = _flats(k0)
    pts[2].method, pts[2].clipped_high = "censored", 0.0025  # 0 dB, 120 DN: 0.25 % at the top code
    pts[3].quantisation_limited = True
    pts.append(FlatPoint("12dB-200", 0.01, 298.15, 10 ** 0.6, 200.0, 0.01, 0.5 * 10 ** 0.6 * k0 * 200, 0.01, 0.0, 0.0, 12.0))
    fit = fit_photon_transfer(pts, lambda t, tk, g: (0.3 * g * g, 1e-4))
    why = {p.name: w for p, w in fit.excluded}
    assert set(why) == {"0dB-120", "12dB-10", "12dB-120", "12dB-200"}
    assert why["0dB-120"].startswith("partly clipped") and why["12dB-10"].startswith("quantisation-limited")
    # the variance falls beyond 120 DN at 12 dB: that flat and the one at the maximum are saturated (EMVA 1288)
    assert why["12dB-200"].startswith("at or beyond the maximum of the variance at 12 dB") and why["12dB-120"] == why["12dB-200"]
    assert fit.k0 == pytest.approx(k0, rel=1e-6)


def test_gains_whose_k0_contradict_k_proportional_to_g_are_refused():
    k0 = 255.0 / 12000.0
    with pytest.raises(ValueError, match=r"flats at 0 dB and 12 dB give K0 0\.02125 and 0\.03188 DN/e⁻, [\d.]+σ apart .*check the flats' gain_db"):
        fit_photon_transfer(_flats(k0, k_of_gain={12.0: 1.5 * k0}), lambda t, tk, g: (0.3 * g * g, 1e-4))
    fit = fit_photon_transfer(_flats(k0, k_of_gain={12.0: 1.001 * k0}), lambda t, tk, g: (0.3 * g * g, 1e-4))  # within its σ
    assert set(fit.per_gain) == {0.0, 12.0}


@pytest.mark.parametrize("bits", [10, 12, 14])
def test_quantisation_step_of_b_bit_data_read_as_value_over_2b_minus_1(bits):
    """b-bit codes read as k/(2^b − 1) (a PNG's sBIT chunk, 10/12-bit data in the low bits) are off the 16-bit grid;
    their step 255/(2^b − 1) DN was lost (0: "continuous"), so no q²/12 was removed and clipped sets were not fitted
    as code intervals."""
    q = 2**bits - 1
    rng = np.random.default_rng(bits)
    x = (np.clip(np.rint(rng.normal(0.3 * q, 0.01 * q, (4, 16, 16))), 0, q) / q).astype(np.float32)
    assert quantisation_step(x) == pytest.approx(255 / q)
    assert quantisation_step(x, bits) == pytest.approx(255 / q)
    assert quantisation_step((np.rint(x * q) * 3 / q).astype(np.float32) / 3) == pytest.approx(255 / q)  # same codes
    assert quantisation_step(rng.random((4, 16, 16)).astype(np.float32)) == 0.0  # continuous values stay continuous


def test_a_flat_at_one_code_below_255_dn_is_saturated_not_frozen():
    """Every value of a flat at 200 DN (a full well below the ADC's range): saturated (method "clipped", every value at
    the top code), where it was refused as a frozen image; a bias set so is still refused."""
    const = np.full((6, 16, 16), 200 / 255, np.float32)
    st = set_statistics(const, flat=True)
    assert st.method == "clipped" and st.clipped_high == 1.0 and st.upper_dn == pytest.approx(200.0)
    with pytest.raises(ValueError, match="frames are identical"):
        set_statistics(const)


def test_pixels_at_0_dn_in_every_frame_of_a_lit_set_are_stuck_but_not_in_a_clipped_dark():
    from camhealth.calibrate.statistics import stuck_at_zero

    rng = np.random.default_rng(8)
    flat = np.clip(rng.normal(100, 3, (6, 64, 64)), 0, 255)
    flat[:, 20, 30] = 0.0
    stuck = stuck_at_zero((flat / 255).astype(np.float32))
    assert {tuple(p) for p in np.argwhere(stuck)} == {(20, 30)}
    st = set_statistics((flat / 255).astype(np.float32), stuck, flat=True)
    assert st.method == "temporal" and st.clipped_low == 0.0 and st.sigma_dn == pytest.approx(3.0, rel=0.03)
    # a zero-offset dark clips half of its values: a pixel at 0 DN in all frames is part of its distribution
    dark = np.clip(rng.normal(0, 2, (2, 64, 64)), 0, 255)
    assert (dark <= 0).all(0).any() and not stuck_at_zero((dark / 255).astype(np.float32)).any()


def _dark_group(offset_dn, k=0.204, sr_e=12.5, dc=700.0, temps=(0.001, 0.1, 0.2), seed=1):
    """Dark sets at one temperature: offset + K·(Poisson(DC·t) − DC·t) + N(0, K·σ_R), 16-bit, clipped at 0."""
    from camhealth.calibrate.frames import FrameSet

    rng = np.random.default_rng(seed)
    out = []
    for t in temps:
        s = dc * t
        y = offset_dn + k * (rng.poisson(s, (8, 64, 64)) - s) + k * sr_e * rng.standard_normal((8, 64, 64))
        x = (np.rint(np.clip(y, 0, 255) / 255 * 65535) / 65535).astype(np.float32)
        fs = FrameSet("bias" if t == temps[0] else "dark", t, 12.0, 75.0, frames=x, name=f"d{t:g}")
        out.append((fs, set_statistics(x)))
    return out


@pytest.mark.parametrize("offset", [6.0, 10.0])
def test_dark_refit_starts_at_the_offset_and_keeps_the_temporal_sets(offset):
    """Offsets of a few σ: the refit started at o = 0, where every bin's likelihood is floored, and converged to no dark
    current (−100 % at 6 DN, −43 % at 10 DN, the read noise +7…9 %), and wrote that over the sets the temporal estimator
    had measured. It starts at the sets' offset now and replaces the variance of the clipped (censored) sets only."""
    from camhealth.calibrate.pipeline import _refit_censored_darks

    k0 = 0.204 / 10 ** (12 / 20)
    stats = _dark_group(offset)
    methods = [st.method for _, st in stats]
    assert "censored" in methods and ("temporal" in methods) == (offset == 10.0)
    out = _refit_censored_darks(stats, k0)
    var, _, o = out["latent"][id(stats[-1][1])]
    assert o == pytest.approx(offset, abs=0.05)
    assert var == pytest.approx(0.204**2 * (12.5**2 + 700.0 * 0.2), rel=0.03)
    assert set(out["latent"]) == {id(st) for _, st in stats if st.method == "censored"}  # temporal sets keep theirs
    assert not out.get("warnings") and out["model"] == "end"


def test_a_dark_refit_stuck_at_no_dark_current_is_not_used(monkeypatch):
    """A refit that converges to DC = 0 (here: forced to start at o = 0 with the offset at 6 DN) is worse than the sets'
    own Gaussian fits: it is not used, with a warning, and the sets keep their censored variance."""
    import camhealth.calibrate.statistics as statistics
    from camhealth.calibrate.pipeline import _refit_censored_darks

    fit = statistics.poisson_gaussian_group_fit
    monkeypatch.setattr(statistics, "poisson_gaussian_group_fit", lambda h, t, k, c, start: fit(h, t, k, c, (0.0, *start[1:])))
    out = _refit_censored_darks(_dark_group(6.0), 0.204 / 10 ** (12 / 20))
    assert out["latent"] == {} and len(out["warnings"]) == 1
    assert out["warnings"][0].startswith("the Poisson refit of the clipped dark sets at 75 °C, 12 dB ('d0.001', 'd0.1', 'd0.2') is not used")
