"""Clipping in closed form (camhealth.physics.clipping) against its limits, Monte Carlo and form_image's labels."""

from __future__ import annotations

import math

import pytest
import torch

from camhealth.physics import CameraMetadata, form_image
from camhealth.physics.clipping import (
    censored_mean_dn,
    censored_noise_moments,
    clipped_sigma_dn,
    estimate_clean_dn,
)


def test_far_from_the_bounds_nothing_is_clipped():
    x = torch.tensor([60.0, 128.0, 200.0])
    ey, ey2, ef2 = censored_noise_moments(x, torch.full((3,), 25.0))
    assert torch.allclose(ey, torch.zeros(3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(ey2, torch.full((3,), 25.0, dtype=torch.float64), rtol=1e-12)
    assert torch.allclose(ef2, torch.ones(3, dtype=torch.float64), rtol=1e-12)


@pytest.mark.parametrize("x", [0.0, 255.0])
def test_at_a_bound_half_the_noise_survives(x):
    """At x = 0 (or 255) exactly, y = max(n, 0): E[y²] = σ²/2, |E[y]| = σ/√(2π), E[f²] = 1/2, and every source
    keeps half its variance whatever its share of the total."""
    var = torch.tensor([16.0])
    ey, ey2, ef2 = censored_noise_moments(torch.tensor([x]), var)
    assert ey2.item() == pytest.approx(8.0, rel=1e-9)
    assert abs(ey.item()) == pytest.approx(4.0 / math.sqrt(2 * math.pi), rel=1e-9)
    assert ef2.item() == pytest.approx(0.5, rel=1e-9)
    clean = torch.full((1, 1, 16, 16), x)
    sig = clipped_sigma_dn(clean, [torch.tensor([4.0]), torch.tensor([12.0])])
    # per pixel E[(n_k f)²] = σ_k²/2, and the means E[n_k f] = β_k E[y] are the same on every pixel
    mean_y = 4.0 / math.sqrt(2 * math.pi)
    for k, vk in enumerate((4.0, 12.0)):
        beta = vk / 16.0
        assert sig[0, k].item() == pytest.approx(math.sqrt(vk / 2 - (beta * mean_y) ** 2), rel=1e-9)
    assert sig[0, 2].item() == pytest.approx(math.sqrt(8.0 - mean_y**2), rel=1e-9)


@pytest.mark.parametrize("x", [-5.0, 0.0, 3.0, 20.0, 240.0, 254.0, 262.0])
def test_moments_match_monte_carlo(x):
    g = torch.Generator().manual_seed(int(x) + 100)
    var = 64.0
    n = torch.randn(2_000_000, generator=g, dtype=torch.float64) * math.sqrt(var)
    y = n.clamp(-x, 255.0 - x)
    f = torch.where(n != 0, y / n, torch.ones_like(n))
    ey, ey2, ef2 = censored_noise_moments(torch.tensor([x]), torch.tensor([var]))
    assert ey.item() == pytest.approx(y.mean().item(), abs=0.02)
    assert ey2.item() == pytest.approx(y.pow(2).mean().item(), rel=0.01, abs=0.05)
    if 0 <= x <= 255:  # f = y/n is only bounded for clean values in range (E[f²] diverges outside)
        assert ef2.item() == pytest.approx(f.pow(2).mean().item(), abs=0.005)
    assert censored_mean_dn(torch.tensor([x], dtype=torch.float64), torch.tensor([var], dtype=torch.float64)).item() == (
        pytest.approx(x + y.mean().item(), abs=0.02)
    )


def test_attribution_matches_monte_carlo_for_unequal_sources():
    """n_k·f with f = y/n, for two independent Gaussian sources of unequal variance, at a pixel near 0 DN."""
    g = torch.Generator().manual_seed(7)
    v1, v2, x = 9.0, 36.0, 4.0
    n1 = torch.randn(2_000_000, generator=g, dtype=torch.float64) * 3.0
    n2 = torch.randn(2_000_000, generator=g, dtype=torch.float64) * 6.0
    n = n1 + n2
    f = n.clamp(-x, 255 - x) / n
    clean = torch.full((1, 1, 1, 1), x)
    sig = clipped_sigma_dn(clean, [torch.tensor([v1]), torch.tensor([v2])])
    # one pixel: the "patch std" is the std of each attributed noise over the realisations
    assert sig[0, 0].item() == pytest.approx((n1 * f).std().item(), rel=0.005)
    assert sig[0, 1].item() == pytest.approx((n2 * f).std().item(), rel=0.005)
    assert sig[0, 2].item() == pytest.approx(n.clamp(-x, 255 - x).std().item(), rel=0.005)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_predicts_form_image_labels_on_half_black_half_white_scenes(dtype):
    """The closed form, given the clean scene and the metadata, reproduces the realised labels of form_image
    (per-source σ after clipping and attribution) on scenes that clip heavily — within the sampling noise."""
    g = torch.Generator().manual_seed(3)
    b = 6
    clean = torch.zeros(b, 1, 128, 128)
    clean[:, :, :, 64:] = 1.0
    clean[:, :, 40:80, :] = torch.linspace(0, 1, 128)  # a ramp through both bounds
    meta = CameraMetadata.preset("EV76C661", batch_size=b, gain_db=torch.tensor([0.0, 6.0, 12.0, 18.0, 24.0, 24.0]),
                                 temperature_c=torch.tensor([0.0, 20.0, 40.0, 60.0, 80.0, 80.0]))
    formed = form_image(clean, meta, generator=g)
    a = 255.0 * meta.gain_factor / meta.full_well_e
    exp = formed.sigma_expected_dn.double()
    x = clean.to(dtype).double() * 255.0
    sig = clipped_sigma_dn(x, [a.double().view(-1, 1, 1, 1) * x, exp[:, 1] ** 2, exp[:, 2] ** 2])
    truth = torch.cat([formed.sigma_dn, formed.sigma_total_dn[:, None]], 1).double()
    assert sig.dtype == torch.float64 and torch.isfinite(sig).all()
    assert torch.allclose(sig, truth, rtol=0.03, atol=0.05), (sig, truth)
    # and clipping matters here: the unclipped model is far off
    unclipped = torch.cat([exp, exp.pow(2).sum(1, keepdim=True).sqrt()], 1)
    assert ((unclipped - truth).abs() > 0.2 * truth).any()


def test_zero_noise_and_huge_noise_are_finite():
    clean = torch.tensor([0.0, 10.0, 255.0, 128.0]).view(1, 1, 2, 2).repeat(256, 1, 1, 1)
    zero = clipped_sigma_dn(clean, [torch.zeros(256), torch.zeros(256)])
    assert torch.equal(zero, torch.zeros(256, 3, dtype=torch.float64))
    huge = clipped_sigma_dn(clean, [torch.full((256,), 200.0**2)])
    assert torch.isfinite(huge).all() and (huge < 200.0).all() and (huge > 50.0).all()
    x = torch.tensor([-1.0, 0.0, 255.0, 256.0])
    ey, ey2, ef2 = censored_noise_moments(x, torch.zeros(4))  # no noise: out-of-range values are clipped
    assert torch.equal(ey, torch.tensor([1.0, 0.0, 0.0, -1.0], dtype=torch.float64))
    assert torch.equal(ef2, torch.tensor([0.0, 0.0, 0.0, 0.0], dtype=torch.float64))


def test_bad_variances_are_refused():
    with pytest.raises(ValueError, match="at least one"):
        clipped_sigma_dn(torch.zeros(2, 1, 4, 4), [])
    with pytest.raises(ValueError, match="expected 1, one per sample"):
        clipped_sigma_dn(torch.zeros(2, 1, 4, 4), [torch.ones(3)])
    with pytest.raises(ValueError, match="odd"):
        estimate_clean_dn(torch.zeros(1, 1, 4, 4), torch.ones(1), torch.ones(1), window=2)


@pytest.mark.parametrize("level", [0.0, 2.0, 6.0, 249.0, 255.0])
def test_clean_level_is_recovered_near_the_bounds(level):
    """A flat patch near a bound: its 3×3 mean is biased by clipping (toward the middle), the inversion
    through the censored mean recovers the clean level within the noise of the 3×3 mean (the median: at a bound
    half the estimates are clamped into [0, 255])."""
    g = torch.Generator().manual_seed(int(level) + 1)
    a, c = torch.tensor([0.05]), torch.tensor([36.0])  # σ ≈ 6 DN near 0, ≈ 7 DN near 255
    clean = torch.full((1, 1, 96, 96), level)
    sd = (a * clean + c).sqrt()
    img = (clean + sd * torch.randn(clean.shape, generator=g)).clamp(0, 255)
    x = estimate_clean_dn(img, a, c)
    naive = torch.nn.functional.avg_pool2d(img, 3, 1, 1)
    assert (x.median() - level).abs() < 0.3
    assert ((naive.mean() - level).abs() > 1.0) == (level in (0.0, 2.0, 255.0, 249.0))
    assert x.min() >= 0 and x.max() <= 255


def test_clean_estimate_is_the_local_mean_away_from_the_bounds():
    g = torch.Generator().manual_seed(5)
    img = 100.0 + 5.0 * torch.randn(2, 1, 32, 32, generator=g)
    x = estimate_clean_dn(img, torch.tensor([0.01, 0.01]), torch.tensor([25.0, 25.0]))
    ref = torch.nn.functional.avg_pool2d(torch.nn.functional.pad(img.double(), (1, 1, 1, 1), mode="replicate"), 3, 1)
    assert torch.allclose(x, ref)


def test_inversion_solves_the_censored_mean_and_stops_when_converged():
    """Near the bounds the inverted clean level x reproduces the observed 3×3 mean through the censored mean to
    < 1e-3 DN (the Newton steps stop early once converged), and more steps change nothing that matters."""
    g = torch.Generator().manual_seed(3)
    a, c = torch.tensor([0.05, 0.2]), torch.tensor([36.0, 100.0])
    clean = torch.linspace(0.0, 30.0, 48).view(1, 1, 1, 48).expand(2, 1, 48, 48)
    img = (clean + (a.view(2, 1, 1, 1) * clean + c.view(2, 1, 1, 1)).sqrt() * torch.randn(clean.shape, generator=g)).clamp(0, 255)
    x = estimate_clean_dn(img, a, c)
    m = torch.nn.functional.avg_pool2d(torch.nn.functional.pad(img.double(), (1, 1, 1, 1), mode="replicate"), 3, 1)
    inside = (x > 0.5) & (x < 254.5)  # where the inversion has a solution inside [0, 255]
    var = a.double().view(2, 1, 1, 1) * x + c.double().view(2, 1, 1, 1)
    assert inside.sum() > 1000
    assert (censored_mean_dn(x, var) - m)[inside].abs().max() < 1e-3
    assert (estimate_clean_dn(img, a, c, iterations=40) - x).abs().max() < 1e-3
    # a mean beyond what any clean level inside [0, 255] gives (black, saturated) is the bound itself
    bounds = torch.cat([torch.zeros(1, 1, 16, 16), torch.full((1, 1, 16, 16), 255.0)])
    assert torch.equal(estimate_clean_dn(bounds, a, c), bounds)


def test_per_sample_variances_give_the_same_sums_as_per_pixel_ones():
    """A source variance given once per sample is summed without a pass over the pixels: the same result as the
    same variance spelled out per pixel."""
    g = torch.Generator().manual_seed(7)
    x = torch.rand(3, 1, 40, 40, generator=g) * 255.0
    pn = 0.1 * x
    dc, rn = torch.tensor([4.0, 9.0, 0.0]), torch.tensor([25.0, 1.0, 400.0])
    per_sample = clipped_sigma_dn(x, [pn, dc, rn], dtype=torch.float32)
    per_pixel = clipped_sigma_dn(x, [pn, dc.view(3, 1, 1, 1).expand_as(x), rn.view(3, 1, 1, 1).expand_as(x)], dtype=torch.float32)
    assert torch.allclose(per_sample, per_pixel, rtol=1e-12, atol=1e-12)


def test_bad_values_are_named():
    """NaN scenes, negative or non-finite variances and wrong shapes get a ValueError naming the value."""
    with pytest.raises(ValueError, match="clean_dn must be finite"):
        clipped_sigma_dn(torch.tensor([[float("nan"), 1.0]]), [torch.ones(1)])
    with pytest.raises(ValueError, match=r"variance 1 = -2 DN² is out of the allowed range \[0, inf\]"):
        clipped_sigma_dn(torch.zeros(1, 4), [torch.ones(1), torch.tensor([-2.0])])
    with pytest.raises(ValueError, match="B×C×H×W or B×N"):
        clipped_sigma_dn(torch.zeros(4), [torch.ones(1)])
    with pytest.raises(ValueError, match="var must be finite"):
        censored_noise_moments(torch.zeros(2), torch.tensor([1.0, float("inf")]))
    with pytest.raises(ValueError, match="image_dn must be finite"):
        estimate_clean_dn(torch.full((1, 1, 4, 4), float("nan")), torch.ones(1), torch.ones(1))
    with pytest.raises(ValueError, match="offset = -1 DN²"):
        estimate_clean_dn(torch.zeros(1, 1, 4, 4), torch.ones(1), -torch.ones(1))
    with pytest.raises(ValueError, match="one value per sample"):
        estimate_clean_dn(torch.zeros(2, 1, 4, 4), torch.ones(3), torch.ones(2))
    with pytest.raises(ValueError, match="B×1×H×W"):
        estimate_clean_dn(torch.zeros(4, 4), torch.ones(4), torch.ones(4))
