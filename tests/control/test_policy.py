"""ExposurePolicy (Eq. 4.5–4.8): direction of the trade-off, limits, LUT = direct argmax, weights."""

import math

import numpy as np
import pytest

from camhealth.control import Application, CameraLimits, ExposurePolicy, noise_scale
from camhealth.iopc import IOPC

LENGTHS = (0.0, 3.0, 7.0, 11.0, 15.0, 21.0)
LEVELS = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0)


def _mtf_of_length(L):
    return 0.5 * (1.0 + abs(np.sinc(0.05 * L)))  # horizontal motion: H sinc, V = 1


def synthetic_iopc(ap, name="synthetic"):
    """IOPC from a grid of cells whose AP is ap(σ [DN], MTF̃)."""
    recs = []
    for s in LEVELS:
        for L in LENGTHS:
            m = _mtf_of_length(L)
            recs.append({"index": len(recs), "key": f"L{L}_s{s}", "length_px": L, "angle_deg": 0.0,
                         "noise_level_dn": s, "sigma_tilde": s, "mtf_tilde": m, "ap": float(ap(s, m))})
    return IOPC.from_records(recs, name=name)


#: a coarser table for the tests that only check the direction of a decision (faster to build)
FAST = {"sigma_step_dn": 1.0, "mtf_step": 0.02, "rho_levels": 3}

BLUR_HATER = synthetic_iopc(lambda s, m: np.clip((m - 0.5) * 2.0, 0, 1), "blur-sensitive")
NOISE_HATER = synthetic_iopc(lambda s, m: 1.0 - s / 30.0, "noise-sensitive")


def test_blur_penalised_means_shorter_exposure():
    pol = ExposurePolicy(BLUR_HATER)
    d = pol.decide(sigma_hat=5.0, mtf_hat=_mtf_of_length(15.0), exposure_s=0.02, gain_db=0.0)
    assert d.alpha > 1 and d.exposure_s < 0.02 and d.gain_db > 0 and d.changed
    assert d.expected_gain > 0.2
    assert d.exposure_s * 10 ** (d.gain_db / 20) == pytest.approx(0.02)  # intensity kept


def test_noise_penalised_means_longer_exposure():
    pol = ExposurePolicy(NOISE_HATER)
    d = pol.decide(sigma_hat=10.0, mtf_hat=_mtf_of_length(3.0), exposure_s=0.01, gain_db=12.0)
    assert d.alpha < 1 and d.exposure_s > 0.01 and d.gain_db < 12.0
    assert d.gain_db == pytest.approx(0.0, abs=1e-6)  # all the way to the gain limit (exactly)
    assert d.details["limits_reached"] == ["lowest gain"]
    assert d.sigma_new_dn < 10.0 and d.expected_gain > 0


@pytest.mark.parametrize("limits", [
    CameraLimits((0.001, 0.2), (0.0, 6.0)),
    CameraLimits((0.008, 0.2), (0.0, 24.0)),
    CameraLimits((0.0005, 0.05), (3.0, 9.0)),
])
@pytest.mark.parametrize("iopc", [BLUR_HATER, NOISE_HATER], ids=["blur", "noise"])
def test_limits_respected(limits, iopc):
    pol = ExposurePolicy(iopc, limits, **FAST)
    for t, g in ((0.02, 3.0), (0.01, 6.0), (0.03, 4.0)):
        d = pol.decide(8.0, _mtf_of_length(11.0), t, g)
        assert limits.exposure_s[0] * (1 - 1e-6) <= d.exposure_s <= limits.exposure_s[1] * (1 + 1e-6)
        assert limits.gain_db[0] - 1e-6 <= d.gain_db <= limits.gain_db[1] + 1e-6


def test_infeasible_and_bad_inputs():
    pol = ExposurePolicy(BLUR_HATER, CameraLimits((0.001, 0.01), (0.0, 24.0)), alpha_range=(0.5, 2.0), n_alpha=9)
    with pytest.raises(ValueError, match="no α"):
        pol.decide(1.0, 0.9, 0.1, 0.0)  # 100 ms can only get to 50 ms within α >= 0.5
    with pytest.raises(ValueError, match="sigma_hat"):
        pol.decide(-1.0, 0.9, 0.01, 0.0)
    with pytest.raises(ValueError, match="mtf_hat"):
        pol.decide(1.0, 1.5, 0.01, 0.0)
    with pytest.raises(ValueError, match="exposure_s"):
        pol.decide(1.0, 0.9, float("nan"), 0.0)
    with pytest.raises(ValueError, match="odd"):
        ExposurePolicy(BLUR_HATER, n_alpha=10)
    with pytest.raises(ValueError, match="0 < low <= high"):
        CameraLimits((0.0, 0.1), (0.0, 24.0))


def test_table_agrees_with_direct_argmax():
    pol = ExposurePolicy([BLUR_HATER, (NOISE_HATER, 0.7)])
    rng = np.random.default_rng(0)
    for _ in range(25):
        s = float(rng.choice(pol.sigma_grid[:50]))  # on the table grid: no rounding of the inputs
        m = float(rng.choice(pol.mtf_grid[pol.mtf_grid >= 0.53]))  # within the MTF → length relation
        t, g = float(rng.uniform(0.002, 0.05)), float(rng.uniform(0, 20))
        rho = float(rng.choice(pol.rho_grid))
        d = pol.decide(s, m, t, g, rho=rho)
        direct = pol.objective(s, m, pol.alphas, rho)
        ok = pol.feasible(t, g)
        assert d.expected_ap >= float(direct[ok].max()) - 1e-5  # grid candidates (+ the exact limits)
        on_grid = bool(np.isclose(pol.alphas, d.alpha, rtol=1e-12, atol=0).any())
        tol = 1e-5 if on_grid else 0.02  # off-grid: the limit α, interpolated in log α
        assert d.expected_ap == pytest.approx(float(pol.objective(s, m, d.alpha, rho)), abs=tol)


def test_off_grid_inputs_read_the_table_between_its_nodes():
    """σ̂, MTF̂ and ρ between the table's nodes: the decision is within a small loss of the direct objective's best α
    (rounding to the nearest node lost up to 0.07 AP here, and chose α the direct objective rules out), and its
    expected AP is the direct objective's at that α."""
    pol = ExposurePolicy([BLUR_HATER, (NOISE_HATER, 0.7)])
    rng = np.random.default_rng(1)
    losses, errors = [], []
    for _ in range(200):
        s, m, rho = float(rng.uniform(0, 25)), float(rng.uniform(0.53, 1.0)), float(rng.uniform(0, 1))
        t, g = float(rng.uniform(0.002, 0.05)), float(rng.uniform(0, 20))
        d = pol.decide(s, m, t, g, rho=rho)
        direct = pol.objective(s, m, pol.alphas, rho)
        at_choice = float(pol.objective(s, m, d.alpha, rho))
        assert np.isfinite(at_choice)  # never an α predicting σ beyond what the IOPC measured
        losses.append(float(direct[pol.feasible(t, g)].max()) - at_choice)
        if np.isclose(pol.alphas, d.alpha, rtol=1e-12, atol=0).any():
            errors.append(abs(d.expected_ap - at_choice))
    assert max(losses) < 0.02 and float(np.mean(losses)) < 0.002
    assert max(errors) < 0.03 and float(np.mean(errors)) < 0.003


def test_multi_application_weights():
    args = (8.0, _mtf_of_length(11.0), 0.02, 6.0)
    blur_first = ExposurePolicy([Application(BLUR_HATER, 1.0), Application(NOISE_HATER, 0.0)], **FAST).decide(*args)
    noise_first = ExposurePolicy([Application(BLUR_HATER, 0.0), Application(NOISE_HATER, 1.0)], **FAST).decide(*args)
    assert blur_first.alpha > 1 > noise_first.alpha
    both = ExposurePolicy([(BLUR_HATER, 1.0), (NOISE_HATER, 1.0)], **FAST).decide(*args)
    assert len(both.details["applications"]) == 2
    with pytest.raises(ValueError, match="at least one application weight"):
        ExposurePolicy([(BLUR_HATER, 0.0)])


def test_noise_scaling_per_source():
    assert noise_scale(4.0, 1.0) == pytest.approx(4.0)  # readout (gain-linear): σ ∝ α
    assert noise_scale(4.0, 0.0) == pytest.approx(2.0)  # photon / dark: σ ∝ √α (σ²_DCSN ∝ t_exp)
    pol = ExposurePolicy(NOISE_HATER)
    d_rn = pol.decide(10.0, 0.99, 0.01, 12.0, sigma_sources=[0.0, 0.0, 10.0])
    assert d_rn.details["rho"] == 1.0
    d_pn = pol.decide(10.0, 0.99, 0.01, 12.0, sigma_sources=[8.0, 6.0, 0.0])
    assert d_pn.details["rho"] == 0.0
    # lengthening the exposure removes less noise when it is photon/dark noise (√α) than readout (α)
    assert d_pn.sigma_new_dn > d_rn.sigma_new_dn
    with pytest.raises(ValueError, match="either sigma_sources or rho"):
        pol.decide(1.0, 0.9, 0.01, 0.0, sigma_sources=[1, 1, 1], rho=0.5)


def test_flat_curve_and_hysteresis_keep_the_parameters():
    flat = synthetic_iopc(lambda s, m: 0.5)
    d = ExposurePolicy(flat).decide(5.0, 0.8, 0.01, 6.0)
    assert d.alpha == 1.0 and not d.changed and d.expected_gain == 0.0
    d = ExposurePolicy(BLUR_HATER, min_gain=0.9).decide(5.0, _mtf_of_length(7.0), 0.02, 0.0)
    assert not d.changed and "min_gain" in d.explanation


def test_explanation_names_bins_curve_and_limit():
    pol = ExposurePolicy(BLUR_HATER, CameraLimits((0.001, 0.2), (0.0, 6.0)))
    d = pol.decide(5.0, _mtf_of_length(15.0), 0.02, 0.0)
    text = d.explanation
    assert "blur-sensitive" in text and "σ̃ 5 DN" in text and "[measured]" in text
    assert "highest gain" in text and d.details["limits_reached"] == ["highest gain"]
    assert d.length_px == pytest.approx(15.0, abs=0.5) and d.length_new_px < d.length_px
    assert math.isfinite(d.mtf_new[0]) and d.mtf_new[0] > _mtf_of_length(15.0)


@pytest.mark.parametrize("mtf_step", [0.01, 0.03, 0.15, 0.3, 0.5])
def test_mtf_axis_ends_at_one_for_any_step(mtf_step):
    """With mtf_step 0.03 (0.3) the axis ended at 0.99 (0.90): a sharp, noise-free frame (MTF̂ = 1) was looked up as
    a blurred one, and the policy cut the exposure 16× (α = 15.8) where nothing was to gain."""
    pol = ExposurePolicy(BLUR_HATER, CameraLimits((0.001, 0.2), (0.0, 24.0)), mtf_step=mtf_step)
    assert pol.mtf_grid[0] == 0.0 and pol.mtf_grid[-1] == 1.0
    assert pol.mtf_step <= mtf_step and np.allclose(np.diff(pol.mtf_grid), pol.mtf_step)
    d = pol.decide(0.0, 1.0, 0.02, 0.0)
    assert d.alpha == 1.0 and not d.changed
    assert d.current_ap == pytest.approx(float(pol.objective(0.0, 1.0, 1.0)), abs=1e-6)


@pytest.mark.parametrize("kwargs, match", [
    ({"mtf_step": 0.0}, r"mtf_step = 0.0 is out of the allowed range \(0, 0.5\]"),
    ({"mtf_step": 0.6}, r"mtf_step = 0.6 is out of the allowed range \(0, 0.5\]"),
    ({"mtf_step": float("nan")}, r"mtf_step = nan is out of the allowed range \(0, 0.5\]"),
    ({"sigma_step_dn": -1.0}, r"sigma_step_dn = -1.0 DN is out of the allowed range: a finite number > 0"),
    ({"rho_levels": 1}, r"rho_levels = 1 is out of the allowed range: an integer >= 2"),
])
def test_table_steps_are_refused_naming_the_value_and_the_range(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ExposurePolicy(BLUR_HATER, **kwargs)


def test_decisions_on_a_limit_are_exactly_on_it():
    """The ±1e-9 feasibility tolerance was baked into the limit candidates: "the shortest exposure" came out as
    0.000999999999 s < t_min = 1 ms (and 20.0000000087 dB), "the lowest gain" as -8.69e-09 dB < g_min = 0 dB — values
    a camera SDK that checks its range strictly refuses."""
    lim = CameraLimits((0.001, 0.2), (0.0, 24.0))
    d = ExposurePolicy(BLUR_HATER, lim).decide(2.0, _mtf_of_length(15.0), 0.010, 0.0)  # α = 10: not on the grid
    assert d.exposure_s == 0.001 and d.gain_db == pytest.approx(20.0, abs=1e-9)
    assert lim.exposure_s[0] <= d.exposure_s and lim.gain_db[0] <= d.gain_db <= lim.gain_db[1]
    d = ExposurePolicy(NOISE_HATER, lim).decide(10.0, _mtf_of_length(3.0), 0.01, 5.0)  # wants the lowest gain
    assert d.gain_db == 0.0 and lim.exposure_s[0] <= d.exposure_s <= lim.exposure_s[1]
    rng = np.random.default_rng(1)
    for iopc in (BLUR_HATER, NOISE_HATER):
        pol = ExposurePolicy(iopc, CameraLimits((0.0005, 0.05), (3.0, 9.0)), **FAST)
        for _ in range(40):
            t, g = float(rng.uniform(0.0006, 0.04)), float(rng.uniform(3.0, 9.0))
            d = pol.decide(float(rng.uniform(0, 20)), float(rng.uniform(0.53, 1.0)), t, g)  # (the relation's range)
            assert 0.0005 <= d.exposure_s <= 0.05 and 3.0 <= d.gain_db <= 9.0


def test_a_tuple_of_two_iopcs_is_two_applications_and_a_pair_needs_a_number():
    """(iopc_a, iopc_b) was read as one (IOPC, λ) pair and failed with float(IOPC)'s TypeError."""
    assert [a.iopc for a in ExposurePolicy((BLUR_HATER, NOISE_HATER), **FAST).apps] == [BLUR_HATER, NOISE_HATER]
    pair = ExposurePolicy((BLUR_HATER, 0.5), **FAST).apps
    assert len(pair) == 1 and pair[0].weight == 0.5 and pair[0].iopc is BLUR_HATER
    assert [a.weight for a in ExposurePolicy([(BLUR_HATER, 0.5), NOISE_HATER], **FAST).apps] == [0.5, 1.0]
    with pytest.raises(TypeError, match=r"application weight λ = '0.5' is not allowed: a real number >= 0"):
        ExposurePolicy([(BLUR_HATER, "0.5")], **FAST)
    with pytest.raises(TypeError, match=r"applications must be an IOPC, .*; got str"):
        ExposurePolicy("curves.json", **FAST)


def test_more_blur_than_the_relation_measured_is_refused_not_clamped():
    """MTF̂ below the relation's end (0.524 at 21 px) was read as 21 px: under the heaviest blur the policy kept the
    exposure (it expected the AP of 21 px). It cannot tell how a shorter exposure would change an unmeasured blur."""
    pol = ExposurePolicy(BLUR_HATER, **FAST)
    with pytest.raises(ValueError, match=r"mtf_hat = 0.300 is blurrier than the MTF → motion-length relation of IOPC "
                                         r"'blur-sensitive' reaches \(MTF̃ 0.524 at 21 px\)"):
        pol.decide(2.0, 0.3, 0.008, 0.0)
    assert pol.decide(2.0, 0.53, 0.008, 0.0).alpha > 1  # just inside it: shorten
    flat = synthetic_iopc(lambda s, m: 0.5, "flat")
    flat.blur_mtf[:] = 1.0
    with pytest.raises(ValueError, match="does not fall with the motion length"):
        ExposurePolicy(flat, **FAST)


def test_a_change_never_predicts_a_sigma_beyond_what_the_iopc_measured():
    """Beyond the last σ bin (30 DN, measured up to 32.5) the AP was read as flat, so the policy raised σ into
    unmeasured territory (29 DN → 63 DN); such α are no candidates, and the direct objective says so too."""
    pol = ExposurePolicy(BLUR_HATER, **FAST)
    d = pol.decide(29.0, _mtf_of_length(21.0), 0.02, 0.0)
    assert d.details["sigma_new_dn"] <= 32.5 + 1e-9
    assert not np.isfinite(pol.objective(29.0, _mtf_of_length(21.0), [2.0], 1.0)[0])
    d = pol.decide(40.0, _mtf_of_length(15.0), 0.02, 0.0)  # already beyond: never noisier
    assert d.alpha <= 1.0
    with pytest.raises(ValueError, match="must be a number, got bool"):
        pol.decide(True, 0.9, 0.02, 0.0)


@pytest.mark.parametrize("make, match", [
    (lambda: ExposurePolicy(NOISE_HATER, min_gain=True, **FAST), r"min_gain = True is out of the allowed range"),
    (lambda: ExposurePolicy(NOISE_HATER, alpha_range=("0.5", "2"), **FAST), r"alpha_range .* must be a pair of numbers"),
    (lambda: ExposurePolicy(NOISE_HATER, sigma_max_dn="40", **FAST), r"sigma_max_dn = '40' DN is out of the allowed range"),
    (lambda: ExposurePolicy(NOISE_HATER, sigma_max_dn=True, **FAST), r"sigma_max_dn = True DN is out of the allowed range"),
    (lambda: ExposurePolicy(NOISE_HATER, limits={"exposure_s": (0.001, 0.1)}, **FAST), r"limits must be a CameraLimits"),
    (lambda: CameraLimits((True, 5.0)), r"exposure limits \(True, 5.0\) must be a pair of numbers"),
    (lambda: CameraLimits(("0.001", "0.2")), r"exposure limits .* must be a pair of numbers"),
    (lambda: CameraLimits((0.001, 0.2), (0.0,)), r"gain limits \(0.0,\) must be a pair of numbers"),
    (lambda: Application(NOISE_HATER, weight=True), r"application weight λ = True must be a finite number"),
])
def test_booleans_and_text_are_no_numbers_of_the_policy(make, match):
    """min_gain=True read as 1 AP (the policy never changed anything), limits of (True, 5) s as 1–5 s."""
    with pytest.raises((ValueError, TypeError), match=match):
        make()


def test_decide_refuses_booleans_and_text_for_rho_and_the_sources():
    pol = ExposurePolicy(NOISE_HATER, **FAST)
    with pytest.raises(ValueError, match=r"rho = True must lie in \[0, 1\]"):
        pol.decide(10.0, 0.9, 0.01, 12.0, rho=True)
    for src in (["1", "1", "1"], [True, False, True], "abc"):
        with pytest.raises(ValueError, match="sigma_sources = .* must be three numbers"):
            pol.decide(10.0, 0.9, 0.01, 12.0, sigma_sources=src)


def test_a_table_shorter_than_the_iopc_is_refused():
    """σ̂ beyond the table is read at its end: a table to 5 DN on an IOPC to 30 DN read σ̂ = 20 DN as 5 DN (expected AP
    0.958 where the direct objective gives 0.333)."""
    with pytest.raises(ValueError, match=r"sigma_max_dn = 5.0 DN is out of the allowed range: .* last σ bin, 30 DN"):
        ExposurePolicy(NOISE_HATER, sigma_max_dn=5.0, **FAST)
    pol = ExposurePolicy(NOISE_HATER, sigma_max_dn=30.0, **FAST)
    d = pol.decide(20.0, 0.9, 0.02, 12.0)
    assert d.current_ap == pytest.approx(float(pol.objective(20.0, 0.9, 1.0)), abs=0.01)


def test_a_table_too_large_to_build_is_refused_before_it_is_built():
    with pytest.raises(ValueError, match=r"the table would hold .* entries .* more than the allowed"):
        ExposurePolicy(NOISE_HATER, sigma_step_dn=1e-4)
    with pytest.raises(ValueError, match=r"the table would hold"):
        ExposurePolicy(NOISE_HATER, sigma_max_dn=1e12)


def test_a_gain_no_camera_has_is_refused_not_overflowed():
    pol = ExposurePolicy(BLUR_HATER, **FAST)
    for g in (-1e308, 1e4):
        with pytest.raises(ValueError, match=r"gain_db = .* is out of the allowed range: a finite gain in \[-200, 200\] dB"):
            pol.decide(5.0, 0.8, 0.02, g)
