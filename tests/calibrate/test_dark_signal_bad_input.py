"""``camhealth.calibrate.dark_signal`` on input that broke it: a predicted dark variance at an absurd exposure."""

import math

import pytest

from camhealth.calibrate.dark_signal import DarkPoint, arrhenius_factor, fit_dark


def _fit():
    c = 4.0 / (0.2 * float(arrhenius_factor(313.15)))  # DN²/s/K^1.5: a dark signal of 4 DN² at 0.2 s and 40 °C
    pts = []
    for t_k in (313.15, 348.15):
        for t in (0.001, 0.1, 0.2):
            v = 4.0 + c * float(arrhenius_factor(t_k)) * t
            pts.append(DarkPoint(t, t_k, 1.0, v * 1.01 if t == 0.1 else v, 0.02 * v, f"{t:g} s {t_k:g} K"))
    return fit_dark(pts)


@pytest.mark.parametrize("exposure_s", [1e160, 1e200, 1e300])
def test_the_predicted_dark_variance_at_a_huge_exposure_does_not_overflow(exposure_s):
    """(C_err·f)² overflowed (OverflowError: Numerical result out of range) for a flat given 1e160 s; the uncertainty is
    now the hypotenuse of its two parts, which does not square them."""
    fit = _fit()
    value, err = fit.predict_dn2(exposure_s, 313.15, 1.0)
    assert value > 0 and err > 0 and not math.isnan(err)
