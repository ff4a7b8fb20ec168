import math

import numpy as np
import pytest
import torch
from scipy import integrate

from camhealth.physics.metadata import CameraMetadata, SensorConstants
from camhealth.physics.readout_noise import (
    cds_transfer,
    readout_sigma_dn,
    readout_sigma_e,
    reset_noise_sigma_e,
    source_follower_psd,
    source_follower_sigma_e,
)


def _reference_sigma_sf(w, f_clock, a_sn, cmos, c=SensorConstants()):
    """Dense float64 reference with scipy.integrate.quad over sub-intervals (slow, exact)."""
    def integrand(f):
        ff = torch.tensor([f], dtype=torch.float64)
        return float(source_follower_psd(ff, torch.tensor(w, dtype=torch.float64), torch.tensor(float(cmos), dtype=torch.float64), c)
                     * cds_transfer(ff, c.cds_sample_time_s, c.cds_time_constant_s))
    edges = np.concatenate([[0.0, 1.0], np.geomspace(10, 1e6, 12), np.arange(2e6, f_clock, 1e6), [f_clock]])
    edges = np.unique(edges[edges <= f_clock])
    total = sum(integrate.quad(integrand, a, b, limit=200)[0] for a, b in zip(edges[:-1], edges[1:]))
    return math.sqrt(total) / (a_sn * c.source_follower_gain * (1 - math.exp(-c.cds_sample_time_s / c.cds_time_constant_s)))


@pytest.mark.parametrize("preset", ["ICX285", "EV76C661"])
def test_source_follower_matches_quadrature(preset):
    m = CameraMetadata.preset(preset).to(dtype=torch.float64)
    ref = _reference_sigma_sf(m.white_noise_v_per_rthz.item(), m.pixel_clock_hz.item(), m.sense_node_gain_v_per_e.item(), m.is_cmos.item())
    assert source_follower_sigma_e(m).item() == pytest.approx(ref, rel=1e-3)


def test_presets_reproduce_measured_read_noise():
    """Thesis / conventions.md: ICX285 ≈ 12.5 e⁻, EV76C661 ≈ 24 e⁻."""
    assert readout_sigma_e(CameraMetadata.preset("ICX285")).item() == pytest.approx(12.5, rel=0.03)
    assert readout_sigma_e(CameraMetadata.preset("EV76C661")).item() == pytest.approx(24.0, rel=0.03)


def test_white_noise_closed_form_without_flicker():
    """With f_c = 0 and a clock far above the CDS pole, ∫W²H df = W²(1 − e^{−t_s/τ})/(2τ)."""
    c = SensorConstants(flicker_corner_hz=1e-30)
    base = CameraMetadata.preset("ICX285", pixel_clock_hz=150e6)
    m = CameraMetadata(**{n: getattr(base, n) for n in base.to_dict()}, constants=c).to(dtype=torch.float64)
    tau, ts, w = c.cds_time_constant_s, c.cds_sample_time_s, m.white_noise_v_per_rthz.item()
    # tail above f_clock: ∫ 2W²/(2πfτ)² df ≈ 2W²/((2πτ)² f_clock) (the cosine averages out)
    var = w**2 * (1 - math.exp(-ts / tau)) / (2 * tau) - 2 * w**2 / ((2 * math.pi * tau) ** 2 * 150e6)
    expected = math.sqrt(var) / (m.sense_node_gain_v_per_e.item() * (1 - math.exp(-ts / tau)))
    assert source_follower_sigma_e(m).item() == pytest.approx(expected, rel=2e-3)


def test_ktc_closed_form_and_ccd_has_none():
    m = CameraMetadata.preset("EV76C661", batch_size=2, reset_factor=[0.0, 1.0], temperature_c=26.85)
    ktc = reset_noise_sigma_e(m)[0].item()
    assert ktc == pytest.approx(math.sqrt(1.380649e-23 * 300.0 / (1.602176634e-19 * 5e-6)), rel=1e-6)
    sf = source_follower_sigma_e(m)
    rn = readout_sigma_e(m)
    assert rn[0].item() == pytest.approx(sf[0].item(), rel=1e-6)
    assert rn[1].item() == pytest.approx(math.hypot(sf[1].item(), ktc), rel=1e-6)
    ccd = m.replace(is_cmos=0.0)
    assert torch.allclose(readout_sigma_e(ccd), source_follower_sigma_e(ccd))


@pytest.mark.parametrize("batch", [1, 256])
def test_vectorised_over_batch_and_monotone(batch):
    m = CameraMetadata.sample(batch, torch.Generator().manual_seed(2))
    s = source_follower_sigma_e(m)
    assert s.shape == (batch,) and torch.isfinite(s).all() and (s > 0).all()
    # doubling W doubles σ_SF (RTN is negligible against W² at these scales)
    w = m.white_noise_v_per_rthz.clamp(1e-9, 30e-9)
    s1 = source_follower_sigma_e(m.replace(white_noise_v_per_rthz=w))
    s2 = source_follower_sigma_e(m.replace(white_noise_v_per_rthz=2 * w))
    assert torch.allclose(s1 * 2, s2, rtol=1e-3)


def test_readout_dn_extremes_finite():
    m = CameraMetadata.preset("EV76C661", batch_size=2, gain_db=[0.0, 24.0], full_well_e=2000.0, temperature_c=[0.0, 80.0],
                              reset_factor=1.0)
    s = readout_sigma_dn(m)
    assert torch.isfinite(s).all() and s[1] > s[0]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tabulated_integral_equals_the_per_sample_integral(dtype):
    m = CameraMetadata.sample(64, torch.Generator().manual_seed(3)).to(dtype=dtype)
    ends = CameraMetadata.preset("EV76C661", batch_size=2, pixel_clock_hz=[8e6, 150e6]).to(dtype=dtype)
    for meta in (m, ends):
        tab = source_follower_sigma_e(meta)
        ref = source_follower_sigma_e(meta, tabulated=False)
        assert tab.dtype == dtype and torch.allclose(tab, ref, rtol=1e-5)
    custom = SensorConstants(flicker_corner_hz=5e3)  # another set of constants gets its own table
    mc = CameraMetadata(**{n: getattr(ends, n) for n in ends.to_dict()}, constants=custom)
    assert torch.allclose(source_follower_sigma_e(mc), source_follower_sigma_e(mc, tabulated=False), rtol=1e-5)
    assert not torch.allclose(source_follower_sigma_e(mc), source_follower_sigma_e(ends), rtol=1e-3)
