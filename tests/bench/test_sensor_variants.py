"""The independent sensor model of the robustness benchmark against camhealth's closed form and its own labels."""

import numpy as np
import pytest
import torch

from camhealth.bench.sensor_variants import VARIANTS, expected_sigma_e, metadata_arrays, simulate_variant
from camhealth.physics import CameraMetadata
from camhealth.physics.dark_current import dark_current_shot_sigma_e
from camhealth.physics.readout_noise import readout_sigma_e


@pytest.mark.parametrize("preset", ["ICX285", "EV76C661"])
@pytest.mark.parametrize("temperature", [0.0, 80.0])
def test_expectations_match_camhealth_closed_form(preset, temperature):
    """Two implementations of Eq. 3.14–3.19 (quadrature, units) agree to 0.01 %."""
    meta = CameraMetadata.preset(preset, gain_db=6.0, exposure_s=0.1, temperature_c=temperature).to(dtype=torch.float64)
    s = expected_sigma_e(metadata_arrays(meta, 1))
    assert s["dark"][0] == pytest.approx(dark_current_shot_sigma_e(meta).item(), rel=1e-4)
    assert np.hypot(s["sf"][0], s["ktc"][0]) == pytest.approx(readout_sigma_e(meta).item(), rel=1e-4)


@pytest.mark.parametrize("variants", [(), ("whole_electrons",), VARIANTS])
def test_realised_sigma_matches_expectation_on_unclipped_flat_patch(variants):
    meta = CameraMetadata.preset("EV76C661", gain_db=12.0, exposure_s=0.05, temperature_c=60.0)
    clean = torch.full((1, 1, 256, 256), 0.5)
    noisy, sigma = simulate_variant(clean, meta, variants, torch.Generator().manual_seed(1))
    m = metadata_arrays(meta, 1)
    s = expected_sigma_e(m)
    dn = 255.0 * 10 ** (12 / 20) / 8400.0
    expect = np.array([255.0 * np.sqrt(10 ** (12 / 20) * 0.5 / 8400.0), s["dark"][0] * dn, np.hypot(s["sf"][0], s["ktc"][0]) * dn])
    np.testing.assert_allclose(sigma[0].numpy(), expect, rtol=0.03)
    total = (noisy - clean).flatten().std().item() * 255.0
    extra = 1 / 12 if "round8" in variants else 0.0  # rounding adds 1/12 DN²
    assert total == pytest.approx(float(np.sqrt((expect**2).sum() + extra)), rel=0.03)


def test_clipping_is_attributed_and_extra_noise_counted_as_readout():
    meta = CameraMetadata.preset("ICX285", gain_db=24.0, exposure_s=0.2, temperature_c=80.0)
    clean = torch.full((2, 1, 128, 128), 0.02)
    y, sigma = simulate_variant(clean, meta, (), torch.Generator().manual_seed(0), extra_read_noise_dn=torch.tensor([0.0, 40.0]))
    assert sigma[1, 2] > 5 * sigma[0, 2]  # 40 DN of white noise (half clipped away at 5 DN) is readout noise
    assert (y >= 0).all() and (y <= 1).all()
    # clipping at 0 takes a large part of the noise: the realised total is far below √(Σσ²) of the unclipped model
    realised = (y[1] - clean[1]).std().item() * 255.0
    assert realised < 40.0 and realised == pytest.approx(float(sigma[1].norm()), rel=0.35)


def test_overrides_leave_the_ranges_and_change_the_noise():
    meta = CameraMetadata.preset("ICX285", gain_db=12.0)
    clean = torch.full((1, 1, 128, 128), 0.5)
    _, base = simulate_variant(clean, meta, (), torch.Generator().manual_seed(0))
    _, more = simulate_variant(clean, meta, (), torch.Generator().manual_seed(0), overrides={"white_noise_v_per_rthz": 4 * 30.8e-9})
    assert more[0, 2] == pytest.approx(4 * base[0, 2], rel=0.05)


def test_bad_input_is_refused():
    meta = CameraMetadata.preset("ICX285")
    with pytest.raises(ValueError, match="unknown variant"):
        simulate_variant(torch.zeros(1, 1, 8, 8), meta, ("jpeg",))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        simulate_variant(torch.full((1, 1, 8, 8), 2.0), meta)
    with pytest.raises(ValueError, match="B×1×H×W"):
        simulate_variant(torch.zeros(8, 8), meta)
    with pytest.raises(ValueError, match="not a metadata field"):
        simulate_variant(torch.zeros(1, 1, 8, 8), meta, overrides={"gain": 3})
    with pytest.raises(ValueError, match="≥ 0"):
        simulate_variant(torch.zeros(1, 1, 8, 8), meta, overrides={"full_well_e": -1})
