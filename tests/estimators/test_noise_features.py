from __future__ import annotations

import math

import pytest
import torch

from camhealth.physics.dark_current import dark_current_shot_sigma_dn
from camhealth.physics.metadata import CameraMetadata
from camhealth.physics.readout_noise import readout_sigma_dn
from camhealth.estimators.noise_features import (
    _TRUNCATED_CHI2, block_details, image_statistics, metadata_from_matrix, physics_prior_dn, plane_free_details,
    truncated_second_moment,
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
    x = (0.5 + sigma_dn / 255 * torch.randn(2, 1, 128, 128, generator=g, dtype=torch.float64)).clamp(0, 1)  # 35 DN: 3.6 σ
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
    x = (x + 0.2 + sigma_dn / 255 * torch.randn(x.shape, generator=g, dtype=torch.float64)).clamp(0, 1)
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


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_clipped_prior_far_from_the_bounds_equals_the_per_pixel_path(dtype):
    """clipped_prior_dn reads a patch whose every pixel lies > 6 σ from both bounds from its mean alone; that must be
    what the per-pixel censored moments give there (the unclipped model at the mean), and a batch that mixes such
    patches with clipped ones must give each the value it gets alone."""
    from camhealth.estimators.noise_features import clipped_prior_dn
    from camhealth.physics.clipping import clipped_sigma_dn, estimate_clean_dn

    g = torch.Generator().manual_seed(5)
    ramp = torch.linspace(60.0, 190.0, 64).view(1, 1, 1, 64)
    far = ((ramp + 3.0 * torch.randn(3, 1, 64, 64, generator=g)).round() / 255.0).to(dtype)
    near = ((torch.linspace(-20.0, 300.0, 64).view(1, 1, 1, 64) + 9.0 * torch.randn(2, 1, 64, 64, generator=g))
            .clamp(0, 255).round() / 255.0).to(dtype)
    a = torch.tensor([0.05, 0.1, 0.0, 0.3, 1.2], dtype=torch.float64)
    dc = torch.tensor([0.2, 1.0, 0.0, 0.5, 2.0], dtype=torch.float64)
    rn = torch.tensor([1.0, 2.0, 0.5, 3.0, 4.0], dtype=torch.float64)
    x = torch.cat([far, near])
    got = clipped_prior_dn(x, a, dc, rn)
    # the per-pixel path, written out
    img = x.float().clamp(0, 1) * 255.0
    clean = estimate_clean_dn(img, a.float(), (dc.square() + rn.square()).float(), dtype=torch.float32)
    ref = clipped_sigma_dn(clean, [a.float().view(-1, 1, 1, 1) * clean, dc.float().square(), rn.float().square()], dtype=torch.float32)
    assert got.dtype == torch.float64 and got.shape == (5, 4)
    assert torch.allclose(got, ref, rtol=0, atol=1e-5), (got - ref).abs().max()
    mean = x.double().flatten(1).mean(1)[:3] * 255.0
    assert torch.allclose(got[:3, 0], (a[:3] * mean).sqrt(), rtol=1e-9, atol=0), got[:3, 0] - (a[:3] * mean).sqrt()  # far: the unclipped model at the mean
    assert torch.equal(got[:3, 1:3], torch.stack([dc[:3], rn[:3]], 1))
    assert (got[3:, 3] < (a[3:] * x[3:].double().flatten(1).mean(1) * 255 + dc[3:] ** 2 + rn[3:] ** 2).sqrt()).all()
    for i in range(5):  # each patch alone: the same value as in the mixed batch
        assert torch.allclose(clipped_prior_dn(x[i:i + 1], a[i:i + 1], dc[i:i + 1], rn[i:i + 1]), got[i:i + 1], atol=1e-12)


def test_clipped_prior_names_bad_metadata_on_the_fast_path_too():
    from camhealth.estimators.noise_features import clipped_prior_dn

    x = torch.full((1, 1, 16, 16), 0.5)
    with pytest.raises(ValueError, match="nan|NaN|finite"):
        clipped_prior_dn(x, torch.tensor([float("nan")]), torch.tensor([1.0]), torch.tensor([1.0]))
    with pytest.raises(ValueError):
        clipped_prior_dn(x, torch.tensor([-1.0]), torch.tensor([1.0]), torch.tensor([1.0]))
    with pytest.raises(ValueError):
        clipped_prior_dn(torch.full((1, 1, 16, 16), float("nan")), torch.tensor([0.1]), torch.tensor([1.0]), torch.tensor([1.0]))


def test_truncated_second_moment_is_the_truncated_normals_variance():
    """h(u) = E[z² | |z| < u]: against a numerical integral of the normal density, its small-u limit u²/3 and 1 at ∞."""
    u = torch.tensor([0.0, 1e-3, 0.05, 0.5, 1.0, 2.0, 3.0, 6.0, 40.0], dtype=torch.float64)
    z = torch.linspace(0.0, 1.0, 200_001, dtype=torch.float64)
    for ui, hi in zip(u.tolist(), truncated_second_moment(u).tolist()):
        if ui == 0.0:
            assert hi == 0.0
            continue
        t = z * ui
        pdf = torch.exp(-0.5 * t * t)
        assert hi == pytest.approx(float(torch.trapezoid(t * t * pdf, t) / torch.trapezoid(pdf, t)), rel=1e-6, abs=1e-12)
    assert float(truncated_second_moment(torch.tensor(1e-3))) == pytest.approx(1e-6 / 3.0, rel=1e-3)
    assert truncated_second_moment(torch.tensor([3.0], dtype=torch.float32)).dtype == torch.float32
    assert _TRUNCATED_CHI2 == pytest.approx(0.97333692, rel=1e-7)  # the inlier cut at 3 σ


def test_image_statistics_docstring_states_its_shape():
    """The docstring promised (B, 5); it returns one column per name of IMAGE_STATISTICS, (B, 6)."""
    from camhealth.estimators.noise_features import IMAGE_STATISTICS

    out = image_statistics(torch.rand(3, 1, 32, 32))
    assert out.shape == (3, len(IMAGE_STATISTICS)) == (3, 6)
    assert f"(B, {len(IMAGE_STATISTICS)})" in image_statistics.__doc__


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_plane_free_details_hold_no_plane(dtype):
    """A plane of any slope (here up to ±1.5 DN/px in both directions, one per patch) leaves the horizontal and vertical
    details at 0, which block_details gives as the squared slopes; the diagonal detail is block_details'. A step edge
    through the plane does not move the slopes read (the median of the blocks)."""
    g = torch.Generator().manual_seed(0)
    sy, sx = (torch.rand(4, 1, 1, 1, generator=g, dtype=dtype) * 3.0 - 1.5 for _ in range(2))
    r = torch.arange(64, dtype=dtype).view(1, 1, 64, 1)
    c = torch.arange(64, dtype=dtype).view(1, 1, 1, 64)
    plane = (128.0 + sy * r + sx * c) / 255.0
    _, d2, usable, _ = block_details(plane)
    inner = usable.expand_as(d2[0])
    assert torch.allclose(d2[1][inner], sy.float().square().expand(4, 1, 32, 32)[inner], rtol=1e-3, atol=1e-4)
    out = plane_free_details(plane, d2, usable)
    assert float(out[1:].abs().amax()) < 1e-3
    assert torch.equal(out[0], d2[0].float())
    edge = plane.clone()
    edge[..., 33:, :] += 40.0 / 255.0  # an edge inside a block row: one row of blocks carries it
    _, d2e, usable_e, _ = block_details(edge)
    out = plane_free_details(edge, d2e, usable_e)
    assert float(out[1:, ..., :16, :].abs().amax()) < 1e-3  # blocks away from the edge: no plane left
    clipped = plane.clone()
    clipped[..., :20, :] = 1.0  # a saturated band: its blocks are not usable and do not count in the slopes
    _, d2c, usable_c, _ = block_details(clipped)
    assert int((~usable_c[..., 1:-1, 1:-1]).sum()) > 0
    out = plane_free_details(clipped, d2c, usable_c)
    assert float((out[1:] * usable_c).abs().amax()) < 1e-3
    black = torch.zeros(2, 1, 64, 64, dtype=dtype)  # nothing usable: the raw details
    _, d2b, usable_b, _ = block_details(black)
    assert not usable_b.any() and torch.equal(plane_free_details(black, d2b, usable_b), d2b.float())


def test_plane_free_details_keep_white_noise_variance():
    """White noise of σ = 5 DN on a 1.2 DN/px ramp: each detail's mean square is σ² (the median slope adds ~πσ²/(2n))."""
    g = torch.Generator().manual_seed(1)
    ramp = 1.2 * torch.arange(128, dtype=torch.float64).view(1, 1, 1, 128)
    x = (40.0 + ramp + 5.0 * torch.randn(16, 1, 128, 128, generator=g, dtype=torch.float64)) / 255.0
    _, d2, usable, _ = block_details(x)
    assert float(d2[2][usable.expand_as(d2[2])].mean()) > 25.0 + 0.9  # the raw vertical detail carries the slope² (1.44)
    out = plane_free_details(x, d2, usable)
    inner = torch.stack([out[k][usable.expand_as(out[k])].mean() for k in range(3)])
    assert torch.allclose(inner, torch.full_like(inner, 25.0), rtol=0.02)


def test_truncated_second_moment_is_one_at_infinity_and_keeps_nan():
    """h(∞) = 1, the limit the docstring states (∞·e^−∞ gave NaN); beyond u = 40 it is 1 exactly, NaN stays NaN."""
    for dtype in (torch.float32, torch.float64):
        h = truncated_second_moment(torch.tensor([40.0, 41.0, 1e30, float("inf"), float("nan"), -1.0], dtype=dtype))
        assert h[:4].tolist() == [1.0] * 4 and math.isnan(h[4]) and h[5] == 0.0 and h.dtype == dtype


@pytest.mark.parametrize("batch", [1, 3])
@pytest.mark.parametrize("bad, kind, message", [
    (lambda x: x * 255.0, ValueError, r"image must lie in \[0, 1\] \(DN/255\), got values in \[127.5, 127.5\]"),
    (lambda x: (x * 255.0).to(torch.uint8), TypeError, "image must be a floating tensor.*got dtype torch.uint8.*x.float\\(\\) / 255"),
    (lambda x: x.clone().fill_(float("nan")), ValueError, "image must be finite"),
    (lambda x: x.expand(-1, 3, -1, -1), ValueError, "C = 1 channel"),
    (lambda x: x[:, 0], ValueError, r"B×C×H×W \(4 dims\)"),
])
def test_image_statistics_and_the_prior_refuse_what_is_not_a_patch_in_the_unit_range(bad, kind, message, batch):
    """DN values (mean 127.5, "100 % saturated"), uint8 (Immerkær ≈ 5 000 DN) or NaN were read silently or failed deep
    inside (NaN named as ``image_dn`` by the clipping); both name the value and the allowed range now."""
    x = bad(torch.full((batch, 1, 16, 16), 0.5))
    meta = CameraMetadata.preset("ICX285")
    for call in (lambda: image_statistics(x), lambda: physics_prior_dn(x, meta), lambda: physics_prior_dn(x, meta, clipping=True)):
        with pytest.raises(kind, match=message):
            call()


@pytest.mark.parametrize("size", [1, 2])
def test_image_statistics_need_a_3x3_window(size):
    """Immerkær's 3×3 mask needs one full window: a 1×1 patch raised an IndexError from inside ``median`` and a 2×2 one
    gave NaN; both name the size and the least one. The prior reads only the mean: any size."""
    x = torch.full((2, 1, size, size), 0.5)
    with pytest.raises(ValueError, match=rf"image must be at least 3×3 px, got {size}×{size}"):
        image_statistics(x)
    assert torch.isfinite(physics_prior_dn(x, CameraMetadata.preset("ICX285"), clipping=True)).all()
    assert torch.isfinite(image_statistics(torch.full((2, 1, 3, 3), 0.5))).all()
