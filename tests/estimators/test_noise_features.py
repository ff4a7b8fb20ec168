from __future__ import annotations

import math

import pytest
import torch

from camhealth.physics.dark_current import dark_current_shot_sigma_dn
from camhealth.physics.metadata import CameraMetadata
from camhealth.physics.readout_noise import readout_sigma_dn
from camhealth.estimators.noise_features import (
    NLF_STATISTICS, NOISE_FIT_STATISTICS, image_statistics, metadata_from_matrix, nlf_statistics, noise_fit_statistics,
    physics_prior_dn,
)


@pytest.mark.parametrize("temperature_c", [0.0, 80.0])
@pytest.mark.parametrize("gain_db", [0.0, 24.0])
def test_prior_matches_closed_forms(gain_db, temperature_c):
    meta = CameraMetadata.preset("EV76C661", gain_db=gain_db, temperature_c=temperature_c, exposure_s=0.05)
    image = torch.full((1, 1, 16, 16), 0.4)
    prior = physics_prior_dn(image, meta)[0].double()
    g = 10 ** (gain_db / 20)
    assert prior[0].item() == pytest.approx(255 * math.sqrt(g * 0.4 / 8400), rel=1e-5)
    assert prior[1].item() == pytest.approx(dark_current_shot_sigma_dn(meta.to(dtype=torch.float64)).item(), rel=1e-5)
    assert prior[2].item() == pytest.approx(readout_sigma_dn(meta.to(dtype=torch.float64)).item(), rel=1e-4)
    assert prior[3].item() == pytest.approx(prior[:3].pow(2).sum().sqrt().item(), rel=1e-6)
    assert torch.isfinite(prior).all()


def test_prior_full_well_2000_black_and_white():
    meta = CameraMetadata.preset("ICX285", batch_size=2, full_well_e=2000.0, gain_db=24.0)
    image = torch.stack([torch.zeros(1, 8, 8), torch.ones(1, 8, 8)])
    prior = physics_prior_dn(image, meta)
    assert torch.isfinite(prior).all()
    assert prior[0, 0] == 0  # no light, no photon noise
    assert prior[1, 0] == pytest.approx(255 * math.sqrt(10 ** (24 / 20) / 2000), rel=1e-5)


def test_metadata_from_matrix_rejects_bad_shape_and_range(meta_raw):
    with pytest.raises(ValueError, match=r"\(B, 11\)"):
        metadata_from_matrix(meta_raw[:, :5])
    bad = meta_raw.clone()
    bad[0, 0] = 30.0  # gain 30 dB
    with pytest.raises(ValueError, match="gain_db"):
        metadata_from_matrix(bad)


@pytest.mark.parametrize("sigma_dn", [0.0, 2.0, 5.0, 35.0])
def test_immerkaer_recovers_gaussian_sigma_on_flat_image(sigma_dn):
    g = torch.Generator().manual_seed(3)
    x = 0.5 + sigma_dn / 255 * torch.randn(2, 1, 128, 128, generator=g, dtype=torch.float64)
    stats = image_statistics(x.float())
    assert stats[:, 4].tolist() == pytest.approx([sigma_dn] * 2, rel=0.03, abs=1e-3)
    assert stats[:, 0].tolist() == pytest.approx([0.5] * 2, abs=0.01)


def test_image_statistics_clip_fractions_and_bf16_autocast():
    x = torch.zeros(1, 1, 10, 10)
    x[..., :3, :] = 1.0
    s = image_statistics(x)
    assert s[0, 2].item() == pytest.approx(0.7) and s[0, 3].item() == pytest.approx(0.3)
    g = torch.Generator().manual_seed(0)
    y = (0.8 + 3 / 255 * torch.randn(1, 1, 64, 64, generator=g)).clamp(0, 1)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        s_bf = image_statistics(y)
    assert s_bf.dtype == torch.float32
    assert torch.allclose(s_bf, image_statistics(y))


@pytest.mark.parametrize("sigma_dn", [1.0, 5.0, 35.0])
def test_haar_mad_is_robust_to_edges(sigma_dn):
    g = torch.Generator().manual_seed(4)
    x = torch.zeros(1, 1, 128, 128, dtype=torch.float64)
    x[..., :, 64:] = 0.6  # a strong vertical edge
    x = x + 0.2 + sigma_dn / 255 * torch.randn(x.shape, generator=g, dtype=torch.float64)
    stats = image_statistics(x.float())
    assert stats[0, 5].item() == pytest.approx(sigma_dn, rel=0.06)


def test_prior_of_repeated_metadata_equals_per_row_prior():
    """Distinct metadata rows are integrated once; the result is identical to evaluating every row."""
    base = CameraMetadata.preset("EV76C661", batch_size=2, gain_db=torch.tensor([3.0, 18.0]))
    meta = base[torch.tensor([0, 1, 0, 0, 1])]
    image = torch.rand(5, 1, 16, 16, generator=torch.Generator().manual_seed(0))
    fast = physics_prior_dn(image, meta)
    slow = torch.cat([physics_prior_dn(image[i : i + 1], meta[i : i + 1]) for i in range(5)])
    assert torch.allclose(fast, slow, rtol=1e-6)


def test_prior_cache_gives_the_uncached_values_and_tracks_the_metadata():
    x = torch.rand(5, 1, 32, 32, generator=torch.Generator().manual_seed(0))
    cache: dict = {}
    for gain in (0.0, 12.0, 0.0):
        m = CameraMetadata.preset("EV76C661", gain_db=gain)
        assert torch.equal(physics_prior_dn(x, m, cache), physics_prior_dn(x, m))
    assert len(cache) == 2
    many = CameraMetadata.preset("ICX285", batch_size=5, temperature_c=[0.0, 20.0, 20.0, 60.0, 80.0])
    assert torch.allclose(physics_prior_dn(x, many, cache), physics_prior_dn(x, many))
    assert len(cache) == 6


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_nlf_statistics_recover_a_poisson_gaussian_noise_level_function(dtype):
    """On a ramp with σ² = a·I + b (I in DN), each tercile's σ̂ is √(a·Ī + b) of its mean intensity Ī (to the
    MAD's spread over 1 365 blocks and its bias on a mixture of σ within the tercile: ≈ 5 %)."""
    g = torch.Generator().manual_seed(3)
    a, b = 0.2, 4.0  # DN per DN, DN²
    clean = torch.linspace(20, 235, 128, dtype=torch.float64).view(1, 1, 1, 128).expand(4, 1, 128, 128)
    noisy = clean + torch.randn(clean.shape, generator=g, dtype=torch.float64) * (a * clean + b).sqrt()
    stats = nlf_statistics((noisy / 255).to(dtype))
    assert stats.shape == (4, len(NLF_STATISTICS)) and stats.dtype == torch.float32
    sigma = stats[:, :3].double().exp() - 0.1
    mean_dn = stats[:, 3:].double() * 255
    assert torch.allclose(mean_dn.mean(0), torch.tensor([56.0, 127.5, 199.0], dtype=torch.float64), atol=1.5)
    expected = (a * mean_dn + b).sqrt()
    assert torch.allclose(sigma, expected, rtol=0.1)
    assert torch.allclose(sigma.mean(0), expected.mean(0), rtol=0.05)
    assert (sigma[:, 0] < sigma[:, 1]).all() and (sigma[:, 1] < sigma[:, 2]).all()  # photon noise grows with I


def test_nlf_statistics_flat_black_saturated_bf16_and_too_small():
    g = torch.Generator().manual_seed(4)
    flat = 0.5 + torch.randn(2, 1, 128, 128, generator=g) * (3 / 255)
    sigma = nlf_statistics(flat)[:, :3].exp() - 0.1
    assert torch.allclose(sigma, torch.full_like(sigma, 3.0), rtol=0.1)  # white noise: the same in every tercile
    ends = nlf_statistics(torch.stack([torch.zeros(1, 16, 16), torch.ones(1, 16, 16)]))
    assert torch.isfinite(ends).all() and torch.allclose(ends[:, :3], torch.full((2, 3), math.log(0.1)))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        low = nlf_statistics(flat.bfloat16())
    assert low.dtype == torch.float32 and torch.allclose(low[:, 3:], nlf_statistics(flat)[:, 3:], atol=0.01)
    with pytest.raises(ValueError, match="at least 3 blocks"):
        nlf_statistics(torch.rand(1, 1, 2, 4))


def test_clipped_prior_predicts_the_labels_of_a_clipped_patch():
    """physics_prior_dn(clipping=True): columns 0–3 are the unclipped model, 4–7 the model after clipping,
    recovered from the noisy patch alone (clean scene estimated near the bounds). On a patch half black and
    half mid-grey it is within a few % of form_image's realised labels, where the unclipped model is not."""
    from camhealth.physics import form_image

    g = torch.Generator().manual_seed(11)
    clean = torch.full((2, 1, 128, 128), 0.5)
    clean[:, :, :, :64] = 0.0
    meta = CameraMetadata.preset("EV76C661", batch_size=2, gain_db=torch.tensor([12.0, 24.0]), temperature_c=torch.tensor([60.0, 80.0]))
    formed = form_image(clean, meta, generator=g)
    prior = physics_prior_dn(formed.image, meta, clipping=True)
    assert prior.shape == (2, 8) and torch.isfinite(prior).all()
    assert torch.equal(prior[:, :4], physics_prior_dn(formed.image, meta))
    truth = torch.cat([formed.sigma_dn, formed.sigma_total_dn[:, None]], 1)
    assert torch.allclose(prior[:, 4:], truth, rtol=0.04), (prior[:, 4:], truth)
    assert ((prior[:, 1:4] - truth[:, 1:]).abs() > 0.08 * truth[:, 1:]).all()  # the unclipped DCSN, RN, total: 9–17 % off


@pytest.mark.parametrize("fill", [0.0, 0.5, 1.0])
def test_clipped_prior_on_flat_black_grey_and_saturated_patches(fill):
    meta = CameraMetadata.preset("ICX285", batch_size=1, full_well_e=2000.0, gain_db=24.0)
    image = torch.full((1, 1, 32, 32), fill)
    prior = physics_prior_dn(image, meta, clipping=True)
    assert torch.isfinite(prior).all() and (prior >= 0).all()
    if fill == 0.5:  # far from the bounds for this camera? then nothing changes
        sd = prior[0, 3].item()
        if 6 * sd < 127:
            assert torch.allclose(prior[:, 4:], prior[:, :4], rtol=1e-5)
    else:  # a fully clipped flat patch: its clean level sits beyond the reach of the noise, all σ collapse
        assert (prior[:, 4:] < prior[:, :4] + 1e-6).all()



def _leaves(b: int, seed: int) -> torch.Tensor:
    """Piecewise-constant scenes [DN] with strong edges (a coarse random grid of grey levels, upsampled)."""
    g = torch.Generator().manual_seed(seed)
    levels = 30 + 190 * torch.rand(b, 1, 8, 8, generator=g, dtype=torch.float64)
    return torch.nn.functional.interpolate(levels, size=(128, 128), mode="nearest")


@pytest.mark.parametrize("case", ["match", "signal_independent", "gain"])
def test_noise_fits_recover_the_mismatch(case):
    """σ² = a·I + c on edged scenes. Metadata right: both logs ≈ 0. Signal-independent noise 2× the metadata's σ:
    the first fit reads log((2√c + 0.1)/(√c + 0.1)). Gain 2× the metadata's (a·2, c·4): the second reads log 2.
    Photon noise dominates here (a·I ≫ c at mid-grey), so the likelihood ratio of the two fits is decisive."""
    a, c = 0.4, 9.0
    clean = _leaves(4, 2)
    true_a, true_c = {"match": (a, c), "signal_independent": (a, 4 * c), "gain": (2 * a, 4 * c)}[case]
    g = torch.Generator().manual_seed(5)
    noisy = (clean + torch.randn(clean.shape, generator=g, dtype=torch.float64) * (true_a * clean + true_c).sqrt()).clamp(0, 255)
    stats = noise_fit_statistics((noisy / 255).float(), torch.full((4,), a), torch.full((4,), math.sqrt(c / 2)), torch.full((4,), math.sqrt(c / 2)))
    assert stats.shape == (4, len(NOISE_FIT_STATISTICS)) and stats.dtype == torch.float32
    assert (stats[:, 2] > 0.15).all()  # a good share of the blocks is flat (edges and their neighbours are dropped)
    expect_ratio = math.log((math.sqrt(true_c) + 0.1) / (math.sqrt(c) + 0.1)) if case != "gain" else None
    if expect_ratio is not None:
        assert torch.allclose(stats[:, 0], torch.full((4,), expect_ratio), atol=0.1)  # c is small beside a·I here
    expect_gain = math.log(2.0) if case == "gain" else 0.0
    if case != "signal_independent":
        assert torch.allclose(stats[:, 1], torch.full((4,), expect_gain), atol=0.03)
    # the likelihood ratio tells a gain change (noise growing with intensity) from a signal-independent one
    if case == "gain":
        assert (stats[:, 3] < -1).all()
    elif case == "signal_independent":
        assert (stats[:, 3] > 1).all()
        # one source alone taking up the change: σ_DCSN = √(4c − c/2) (σ_RN = √(c/2) kept), and vice versa
        alone = math.log((math.sqrt(3.5 * c) + 0.1) / (math.sqrt(c / 2) + 0.1))
        assert torch.allclose(stats[:, 4:], torch.full((4, 2), alone), atol=0.1)
    else:
        assert torch.allclose(stats[:, 4:], torch.zeros(4, 2), atol=0.2)  # (ĉ − σ² of the other source amplifies the noise of ĉ)


def test_noise_fits_without_evidence_bf16_and_too_small():
    one = torch.ones(4)
    ends = noise_fit_statistics(torch.stack([torch.zeros(1, 32, 32), torch.ones(1, 32, 32)]), one[:2], one[:2], one[:2])
    assert torch.equal(ends, torch.zeros(2, len(NOISE_FIT_STATISTICS)))  # fully clipped: no usable block, no evidence
    noisy = (0.5 + torch.randn(4, 1, 64, 64, generator=torch.Generator().manual_seed(1)) * 4 / 255).clamp(0, 1)
    ref = noise_fit_statistics(noisy, one * 1e-6, one * math.sqrt(8), one * math.sqrt(8))
    assert torch.allclose(ref[:, :2], torch.zeros(4, 2), atol=0.05)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        low = noise_fit_statistics(noisy, one * 1e-6, one * math.sqrt(8), one * math.sqrt(8))
    assert low.dtype == torch.float32 and torch.equal(low, ref)
    with pytest.raises(ValueError, match="at least 8×8"):
        noise_fit_statistics(torch.rand(1, 1, 4, 16), one[:1], one[:1], one[:1])
