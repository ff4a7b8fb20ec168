"""ExposurePolicy on σ̂ beyond its look-up table: the decision is the direct objective's, not the table end's."""

import numpy as np
import pytest

from camhealth.control import ExposurePolicy
from tests.control.test_policy import FAST, NOISE_HATER, _mtf_of_length, synthetic_iopc

#: AP = (1 − σ/30) · clip(2·(MTF − 0.5)): noise and blur both cost AP, so the best α moves with σ̂
MIX = synthetic_iopc(lambda s, m: np.clip(1 - s / 30, 0, 1) * np.clip((m - 0.5) * 2.0, 0, 1), "mix")


def _direct(pol, sigma, mtf, exposure_s, gain_db):
    """The argmax of the objective over the grid α the limits allow, and the exact α that put a limit on."""
    lo, hi = pol._alpha_limits(exposure_s, gain_db)
    feasible = pol.alphas[pol.feasible(exposure_s, gain_db)]
    cand = np.concatenate([feasible, [max(lo, pol.alphas[0]), min(hi, pol.alphas[-1])]])
    ap = pol.objective(sigma, mtf, cand)
    return float(cand[int(np.argmax(ap))]), float(ap.max())


@pytest.mark.parametrize("sigma_hat", [40.0, 60.0, 100.0])
def test_sigma_beyond_the_table_decides_as_the_objective(sigma_hat):
    """The table ends at 35 DN; σ̂ = 100 DN was read as 35 DN: α 0.354 and expected AP 0.425, where the objective
    gives α 0.177 and AP 0.123 (and 0.000 at the α decided)."""
    pol = ExposurePolicy(MIX, **FAST)
    assert pol.sigma_grid[-1] < sigma_hat
    m = _mtf_of_length(3.0)
    d = pol.decide(sigma_hat, m, 0.01, 20.0)
    alpha, ap = _direct(pol, sigma_hat, m, 0.01, 20.0)
    assert d.alpha == pytest.approx(alpha, rel=1e-9)
    assert d.expected_ap == pytest.approx(ap, abs=1e-9)
    assert d.expected_ap == pytest.approx(float(pol.objective(sigma_hat, m, d.alpha)), abs=1e-9)
    assert d.current_ap == pytest.approx(float(pol.objective(sigma_hat, m, 1.0)), abs=1e-9)
    assert d.details["sigma_beyond_table"] and "evaluated directly" in d.explanation


@pytest.mark.parametrize("sigma_hat", [60.0, 100.0])
def test_expected_ap_beyond_the_table_matches_the_explanation(sigma_hat):
    """With the noise-only IOPC, σ̂ = 100 DN reported an expected AP of 0.707 while the same decision's details gave
    0.163 for the application."""
    pol = ExposurePolicy(NOISE_HATER, **FAST)
    d = pol.decide(sigma_hat, _mtf_of_length(3.0), 0.01, 12.0)
    assert d.expected_ap == pytest.approx(d.details["applications"][0]["ap_new"], abs=1e-9)
