import math

import pytest
import torch

from camhealth.physics.dark_current import (
    band_gap_ev,
    dark_current_e_per_s,
    dark_current_shot_sigma_dn,
    dark_current_shot_sigma_e,
    dark_signal_e,
)
from camhealth.physics.metadata import BOLTZMANN_EV_PER_K, CameraMetadata


def _closed_form(t_k, d_p_um, dfm):
    eg = 1.1557 - 7.021e-4 * t_k**2 / (t_k + 1108)
    return 2.55e15 * (d_p_um * 1e-4) ** 2 * dfm * t_k**1.5 * math.exp(-eg / (2 * 8.617343e-5 * t_k))


@pytest.mark.parametrize("t_c", [0.0, 25.0, 80.0])
@pytest.mark.parametrize("preset", ["ICX285", "EV76C661"])
def test_arrhenius_law_closed_form(t_c, preset):
    m = CameraMetadata.preset(preset, temperature_c=t_c).to(dtype=torch.float64)
    expected = _closed_form(t_c + 273.15, m.pixel_size_um.item(), m.dark_fom_na_per_cm2.item())
    assert dark_current_e_per_s(m).item() == pytest.approx(expected, rel=1e-9)


def test_band_gap_silicon():
    assert band_gap_ev(torch.tensor(0.0)).item() == pytest.approx(1.1557)
    assert band_gap_ev(torch.tensor(300.0)).item() == pytest.approx(1.1108, abs=2e-4)


def test_doubling_temperature_near_room():
    """Dark current doubles every ~7–9 K near room temperature (Arrhenius with E_g/2kT): compare the
    numerical doubling step with the closed-form logarithmic derivative."""
    t = torch.linspace(15.0, 35.0, 81, dtype=torch.float64)
    m = CameraMetadata.preset("ICX285", batch_size=81, temperature_c=t).to(dtype=torch.float64)
    dc = dark_current_e_per_s(m)
    t_k = t + 273.15
    eg = band_gap_ev(t_k)
    deg = -7.021e-4 * (t_k**2 + 2 * 1108 * t_k) / (t_k + 1108) ** 2
    dlog = 1.5 / t_k + (eg - deg * t_k) / (2 * BOLTZMANN_EV_PER_K * t_k**2)
    doubling = math.log(2) / dlog
    numeric = math.log(2) / torch.diff(torch.log(dc)) * (t[1] - t[0])
    assert torch.allclose(numeric, 0.5 * (doubling[1:] + doubling[:-1]), rtol=1e-3)
    assert 6.0 < doubling.min() and doubling.max() < 9.5
    assert torch.all(torch.diff(dc) > 0)


def test_dcsn_sigma_is_sqrt_of_signal_and_scales_with_exposure():
    m = CameraMetadata.preset("EV76C661", batch_size=2, exposure_s=[0.05, 0.2], temperature_c=60.0)
    s = dark_signal_e(m)
    assert torch.allclose(dark_current_shot_sigma_e(m), s.sqrt())
    assert s[1] / s[0] == pytest.approx(4.0, rel=1e-5)
    assert torch.allclose(dark_current_shot_sigma_dn(m), s.sqrt() * m.dn_per_electron)


def test_dark_current_zero_fom_and_extremes_are_finite():
    m = CameraMetadata.preset("EV76C661", batch_size=4, dark_fom_na_per_cm2=[0.0, 1.0, 1.0, 0.0],
                              temperature_c=[0.0, 80.0, 0.0, 80.0], full_well_e=2000.0, gain_db=24.0)
    sig = dark_current_shot_sigma_dn(m)
    assert torch.isfinite(sig).all()
    assert sig[0] == 0 and sig[3] == 0 and sig[1] > sig[2] > 0
