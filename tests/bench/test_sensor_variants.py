"""The independent sensor model of the robustness benchmark against camhealth's closed form and its own labels."""

import sys
import zlib

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
    with pytest.raises(ValueError, match=r"full_well_e = -1 is out of the allowed range \(0, inf\)"):  # (a full well > 0)
        simulate_variant(torch.zeros(1, 1, 8, 8), meta, overrides={"full_well_e": -1})



_REAL_RNG = np.random.default_rng


def _stage_numbers(stage: str, kind: str, k: int, shape) -> np.ndarray:
    """The k-th draw of kind ``kind`` ("n" normal, "p" Poisson, not used here) of one stage, whatever the stage order."""
    return _REAL_RNG(zlib.crc32(f"{stage}/{kind}/{k}".encode())).standard_normal(shape)


class _StageNumbers:
    """NumPy generator stand-in: the k-th normal draw of each stage (the calling function: photon, dark or readout)
    gets the same numbers whatever the order the stages run in."""

    def __init__(self, seed=None):
        self.calls: dict[str, int] = {}

    def standard_normal(self, shape):
        stage = sys._getframe(1).f_code.co_name
        k = self.calls.get(stage, 0)
        self.calls[stage] = k + 1
        return _stage_numbers(stage, "n", k, shape)


def test_reverse_order_clips_after_every_stage_so_the_order_matters(monkeypatch):
    """With the same random numbers per stage, ``reverse_order`` is readout → dark → photon with the charge clipped to
    [0, FW/g] after each stage: exactly that hand computation; equal to the reference order (clipped once, at the end)
    wherever no running charge leaves the range, different where a clip between the stages binds."""
    meta = CameraMetadata.preset("EV76C661", gain_db=12.0, exposure_s=0.15, temperature_c=50.0)
    clean = torch.linspace(0, 1, 96 * 96).reshape(1, 1, 96, 96)  # dark and bright pixels: clipping binds at both ends
    monkeypatch.setattr(np.random, "default_rng", _StageNumbers)
    ref, _ = simulate_variant(clean, meta, (), torch.Generator().manual_seed(0))
    rev, sigma = simulate_variant(clean, meta, ("reverse_order",), torch.Generator().manual_seed(0))
    monkeypatch.undo()
    # each stage's electrons from those numbers (the model of the module docstring, written out; CMOS kTC additive)
    m = metadata_arrays(meta, 1)
    s = expected_sigma_e(m)
    full = m["full_well_e"][0] / 10 ** (m["gain_db"][0] / 20)
    signal = clean[0, 0].double().numpy() * full
    shape = (1, *signal.shape)
    pn = (np.sqrt(signal) * _stage_numbers("photon", "n", 0, shape))[0]
    dc = (np.sqrt(s["dark_signal"][0]) * _stage_numbers("dark", "n", 0, shape))[0]
    rn = (s["sf"][0] * _stage_numbers("readout", "n", 0, shape) + s["ktc"][0] * _stage_numbers("readout", "n", 1, shape))[0]
    clip = lambda v: np.clip(v, 0.0, full)  # noqa: E731
    q1 = clip(signal + rn)
    q2 = clip(q1 + dc)
    q3 = clip(q2 + pn)
    np.testing.assert_allclose(rev[0, 0].double().numpy(), q3 / full, atol=1e-6)
    np.testing.assert_allclose(ref[0, 0].double().numpy(), clip(signal + pn + dc + rn) / full, atol=1e-6)
    inside = ((signal + rn >= 0) & (signal + rn <= full) & (q1 + dc >= 0) & (q1 + dc <= full)
              & (q2 + pn >= 0) & (q2 + pn <= full))
    d = (rev - ref)[0, 0].double().numpy() * 255.0
    assert inside.mean() > 0.5 and (~inside).sum() > 100
    assert np.abs(d[inside]).max() < 1e-3  # nothing clips between the stages: the order changes nothing
    assert (np.abs(d[~inside]) > 0.5).mean() > 0.2 and np.abs(d).max() > 3.0  # a clip between the stages binds
    # the labels are the stages' changes after their own clips (as sequential_clip's), readout first
    dn = 255.0 / full
    np.testing.assert_allclose(sigma[0].numpy(), [((q3 - q2) * dn).std(), ((q2 - q1) * dn).std(), ((q1 - signal) * dn).std()],
                               rtol=1e-4)
