"""``camhealth.calibrate.statistics`` on input that broke it: code lattices with an offset (a black-level pedestal
added after a digital gain), whose quantisation step is the spacing of the codes, not their greatest common divisor."""

import numpy as np
import pytest

from camhealth.calibrate.statistics import quantisation_step, set_statistics


@pytest.mark.parametrize("top, bits", [(255, None), (255, 8), (4095, 12), (65535, None), (65535, 16)])
@pytest.mark.parametrize("gain, offset", [(2, 9), (2, 11), (4, 10), (4, 9), (4, 13), (3, 7)])
def test_codes_with_a_pedestal_after_a_digital_gain_have_the_gain_as_their_step(top, bits, gain, offset):
    """Codes o + q·k (an ADC, a digital gain q, a pedestal o added after it) lie q codes apart whatever o is; the
    greatest common divisor of the codes themselves (gcd(9, 11, 13, …) = 1) made the step 1 code, so the quantisation
    noise q²/12 was not removed and a set with its noise below half a step was not recognised. ``bits``: the scale the
    frames were read with, as a file gives it (None: found from the values, as for in-memory frames)."""
    rng = np.random.default_rng(100 * gain + offset)
    codes = offset + gain * np.rint(rng.normal(20.0, 3.0, (6, 32, 32)))
    codes[0, 0, :3] = 0  # a few values clipped at 0: off the lattice
    x = (codes / top).astype(np.float32)
    step = 255.0 * gain / top
    assert quantisation_step(x, bits) == pytest.approx(step)
    if bits is None:
        assert set_statistics(x).step_dn == pytest.approx(step)


@pytest.mark.parametrize("gain, offset", [(2, 9), (4, 10)])
def test_a_set_below_half_a_step_of_an_offset_lattice_is_quantisation_limited(gain, offset):
    """σ = 0.35 q on the lattice o + q·k: its raw variance is below 0.3·q², so the set is marked; with a step of 1 code
    it passed as a measurement of σ."""
    rng = np.random.default_rng(gain + offset)
    codes = offset + gain * np.rint(30.0 + 0.35 * rng.standard_normal((20, 32, 32)))
    st = set_statistics((codes / 255).astype(np.float32))
    assert st.step_dn == pytest.approx(gain) and st.method == "temporal"
    assert st.quantisation_limited and st.raw_var_dn2 < 0.3 * gain**2
