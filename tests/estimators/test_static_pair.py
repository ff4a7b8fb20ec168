"""A static camera's pair of exposures: the difference holds the noise and nothing of the scene."""

import math

import pytest
import torch
import torch.nn.functional as F

from camhealth.bench.sensor_variants import simulate_variant
from camhealth.estimators.noise_features import block_details, physics_prior_dn, truncated_second_moment
from camhealth.estimators.physics_noise import (
    PHYSICS_NOISE_COLUMNS, PhysicsNoiseEstimator, _pair_c_index, pair_kept_variance_factor,
    physics_noise_posterior,
)
from camhealth.estimators.static_pair import (
    PAIR_SHIFT_LIMIT, SCENE_LEAK_LIMIT, _block_max, _block_mean, _block_min, difference_limits_dn, pair_fold, pair_shift,
    pair_stillness, scene_leak, static_pair_blocks, static_pair_image,
)
from camhealth.physics import CameraMetadata


def _busy(b: int, size: int = 128, seed: int = 0) -> torch.Tensor:
    """Busy scenes: random-phase 1/f² texture with 30 DN of contrast plus sharp-edged blocks, within 0.2…0.8: as much
    fine content as a 3× downsampled street frame (one image's estimator keeps the closed form on them)."""
    g = torch.Generator().manual_seed(seed)
    w = torch.fft.rfft2(torch.randn(b, 1, size, size, generator=g).double())
    f = torch.sqrt(torch.fft.fftfreq(size).view(-1, 1) ** 2 + torch.fft.rfftfreq(size).view(1, -1) ** 2)
    x = torch.fft.irfft2(w / w.abs().clamp_min(1e-30) * torch.where(f > 0, 1.0 / f.clamp_min(1e-9), 0.0), s=(size, size))
    x = (x - x.mean((-2, -1), keepdim=True)) / x.std((-2, -1), keepdim=True)
    blocks = (torch.rand(b, 1, size // 16, size // 16, generator=g) > 0.5).double()
    x = 0.5 + 30.0 / 255.0 * x + 0.15 * (F.interpolate(blocks, scale_factor=16.0) - 0.5)
    return x.clamp(0.2, 0.8).float()


def _pair(clean: torch.Tensor, meta: CameraMetadata, seed: int, extra_dn: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    a, _ = simulate_variant(clean, meta, (), torch.Generator().manual_seed(seed), extra_read_noise_dn=extra_dn)
    b, _ = simulate_variant(clean, meta, (), torch.Generator().manual_seed(seed + 1), extra_read_noise_dn=extra_dn)
    return a, b


META = CameraMetadata.preset("ICX285", gain_db=6.0, exposure_s=0.02, temperature_c=30.0)


def test_the_fold_has_the_differences_details_and_the_averages_block_means():
    g = torch.Generator().manual_seed(1)
    x1, x2 = torch.rand(3, 1, 16, 18, generator=g) * 0.6 + 0.2, torch.rand(3, 1, 16, 18, generator=g) * 0.6 + 0.2
    j = static_pair_image(x1, x2)
    m_j, d_j, _, _ = block_details(j)
    m_avg, _, _, _ = block_details((x1 + x2) / 2)
    m_diff, d_diff, _, g2_diff = block_details((x1 - x2) / math.sqrt(2.0) + 0.5)
    assert torch.allclose(d_j, d_diff, atol=1e-3)  # every Haar detail: the difference's alone
    assert torch.allclose(m_j, m_avg + (m_diff - 127.5), atol=1e-3)
    m_d, g2, lo, hi = static_pair_blocks(x1, x2)
    assert torch.allclose(m_d, m_diff - 127.5, atol=1e-3)
    assert (lo <= m_avg + 1e-4).all() and (hi >= m_avg - 1e-4).all()
    assert torch.allclose(g2, g2_diff, rtol=1e-4, atol=1e-2)  # the flatness of the difference, not of the scene


def test_a_pixel_clipped_in_either_frame_is_clipped_in_the_fold():
    x1 = torch.full((1, 1, 8, 8), 0.5)
    x2 = x1.clone()
    x1[0, 0, 2, 3], x2[0, 0, 5, 5], x2[0, 0, 1, 1] = 1.0, 0.0, 1.0
    j = static_pair_image(x1, x2)
    assert j[0, 0, 2, 3] == 1.0 and j[0, 0, 5, 5] == 0.0 and j[0, 0, 1, 1] == 1.0
    assert ((j > 0) & (j < 1)).sum() == 61


@pytest.mark.parametrize("bad, match", [
    (lambda x: x[:, :, :-2], "same patches|image's shape"),
    (lambda x: (x * 255).to(torch.uint8), "floating point"),
])
@pytest.mark.parametrize("fn", [static_pair_image, static_pair_blocks, difference_limits_dn, pair_fold, scene_leak,
                                pair_shift, pair_stillness])
def test_every_pair_function_refuses_mismatched_frames(bad, match, fn):
    """A reference of another shape (also one that would broadcast), an integer frame or a frame of the wrong rank is
    a clear error from every function of the pair, never a silently broadcast answer."""
    x = torch.rand(2, 1, 16, 16)
    with pytest.raises((ValueError, TypeError), match=match):
        fn(x, bad(x))
    with pytest.raises(ValueError, match=r"reference must have the image's shape \(2, 1, 16, 16\) .*, got \(1, 1, 16, 16\)"):
        fn(x, x[:1])
    with pytest.raises(ValueError, match="B×1×H×W"):
        fn(x[:, 0], x[:, 0])
    with pytest.raises(TypeError, match="must be tensors"):
        fn(x, x.numpy())


@pytest.mark.parametrize("pool", [False, True])
def test_a_still_pair_is_read_and_a_moved_one_is_not(pool):
    clean = _busy(8, seed=2)
    a, b = _pair(clean, META, 10)
    leak, se = scene_leak(a, b, pool=pool)
    assert ((leak - 1).abs() <= torch.clamp_min(4 * se, SCENE_LEAK_LIMIT)).all()
    shift, n = pair_shift(a, b)
    assert (shift.abs().amax(1) <= torch.clamp_min(4 / n.sqrt(), PAIR_SHIFT_LIMIT)).all()
    # the scene moved by a third of a pixel between the exposures (bilinear), the noise is the second exposure's own
    moved_scene = (2 * clean + torch.roll(clean, 1, -1)) / 3
    b_moved = (b + moved_scene - clean).clamp(0, 1)
    shift_m, n_m = pair_shift(a, b_moved)
    assert (shift_m.abs().amax(1) > torch.clamp_min(4 / n_m.sqrt(), PAIR_SHIFT_LIMIT)).all()
    # a change of the light between the exposures moves block means, not details: still
    leak_l, se_l = scene_leak(a, (b * 1.05).clamp(0, 1), pool=pool)
    assert ((leak_l - 1).abs() <= torch.clamp_min(4 * se_l, SCENE_LEAK_LIMIT)).float().mean() >= 0.75


def test_scene_leak_sees_a_change_that_lives_where_the_scene_has_edges():
    """The focus changed between the exposures (the second one's scene 3×3-box blurred): the difference sits at the
    photograph's edges and fine detail and follows no gradient, so the shift test cannot see it; the leak test does."""
    from camhealth.data.skimage_photos import load_skimage_photo

    img = load_skimage_photo("camera")
    clean = torch.stack([img[:, y:y + 128, x:x + 128] for y, x in [(100, 100), (200, 250), (300, 150), (50, 300)]]).float()
    a, b = _pair(clean, META, 20)
    soft = F.avg_pool2d(F.pad(clean, (1, 1, 1, 1), mode="replicate"), 3, stride=1)
    leak, se = scene_leak(a, (b + soft - clean).clamp(0, 1))
    assert ((leak - 1).abs() > torch.clamp_min(4 * se, SCENE_LEAK_LIMIT)).all()
    shift, n = pair_shift(a, (b + soft - clean).clamp(0, 1))
    assert (shift.abs().amax(1) <= torch.clamp_min(4 / n.sqrt(), PAIR_SHIFT_LIMIT)).all()
    leak, se = scene_leak(a, b)
    assert ((leak - 1).abs() <= torch.clamp_min(4 * se, SCENE_LEAK_LIMIT)).all()


def test_a_pair_on_a_busy_scene_reads_the_noise_the_single_image_cannot():
    """Busy static scenes, white noise 3 DN above what the metadata allow: one image keeps the closed form (it cannot
    tell the excess from the scene's own fine content); the pair finds it, σ_Total within 5 %."""
    clean = _busy(16, seed=4)
    a, b = _pair(clean, META, 30, extra_dn=3.0)
    truth = ((a - clean) * 255).flatten(1).std(1)
    alone = physics_noise_posterior(a, META, pool=True)
    pair = physics_noise_posterior(a, META, pool=True, reference=b, scene_allowance_dn=0.0, scene_allowance_min_dn=0.0,
                                   bound_margin=3.0)
    col = PHYSICS_NOISE_COLUMNS.index
    assert (alone[:, col("xi_dn")] == 0).all()
    assert (pair[:, col("xi_dn")] < -0.5).all() and (pair[:, col("follows_image")] == 1).all()
    assert torch.allclose(pair[:, col("total_dn")], truth, rtol=0.05)
    assert pair[0, col("details")] > 10 * alone[0, col("details")]  # the pair keeps the busy blocks


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_block_reductions_are_torchs_pooling(dtype):
    x = torch.rand(3, 1, 18, 34, dtype=dtype)
    assert torch.equal(_block_max(x), F.max_pool2d(x, 2)) and torch.equal(_block_min(x), -F.max_pool2d(-x, 2))
    assert torch.allclose(_block_mean(x), F.avg_pool2d(x, 2), rtol=0, atol=4 * torch.finfo(dtype).eps)


@pytest.mark.parametrize("pool", [False, True])
def test_stillness_is_both_tests_at_their_limits(pool):
    """pair_stillness on one pass gives what scene_leak and pair_shift give at their limits, on still, shifted and
    partly clipped pairs."""
    clean = torch.cat([_busy(4, seed=11), torch.full((2, 1, 128, 128), 0.5)])
    clean[-1, :, :, :40] = 1.0  # a clipped band: its pixels and their neighbours are left out
    a, b = _pair(clean, META, 110)
    b[[1, 4]] = torch.roll(b[[1, 4]], 1, -2)  # two patches shifted by a pixel (one busy, one flat)
    leak, se = scene_leak(a, b, pool=pool)
    shift, n = pair_shift(a, b)
    expect = (((leak - 1).abs() <= (4 * se).clamp_min(SCENE_LEAK_LIMIT))
              & (shift.abs().amax(1) <= (4 / n.sqrt()).clamp_min(PAIR_SHIFT_LIMIT)))
    got = pair_stillness(a, b, pool=pool)
    assert torch.equal(got, expect)
    assert got.tolist() == [True, False, True, True, True, True]  # the flat patch's roll is still noise: nothing moved
    assert n[-1] < n[-2] - 39 * 126  # the band and the column beside it


def test_the_shift_correlation_is_the_sample_correlation():
    """pair_shift against the textbook correlation of the difference with the average's central difference, on a
    grating over a steep ramp (a large mean gradient: no cancellation) shifted by 0.3 px."""
    g = torch.Generator().manual_seed(12)
    col = torch.arange(64.0)

    def scene(dx: float) -> torch.Tensor:
        return (0.1 + 0.6 * (col - dx) / 63 + 0.1 * torch.sin(2 * math.pi * (col - dx) / 16)).view(1, 1, 1, 64).expand(1, 1, 64, 64)

    a = scene(0.0) + 0.5 / 255 * torch.randn(1, 1, 64, 64, generator=g)
    b = scene(0.3) + 0.5 / 255 * torch.randn(1, 1, 64, 64, generator=g)
    x1, x2 = a.double() * 255, b.double() * 255
    d = (x1 - x2)[0, 0, 1:-1, 1:-1].flatten()
    avg = (x1 + x2)[0, 0] / 2
    gx = ((avg[1:-1, 2:] - avg[1:-1, :-2]) / 2).flatten()
    ref = torch.corrcoef(torch.stack([d, gx]))[0, 1]
    shift, n = pair_shift(a, b)
    assert n.item() == 62 * 62 and abs(shift[0, 0].item() - ref.item()) < 1e-5 and abs(shift[0, 0]) > 0.5


@pytest.mark.parametrize("pool", [False, True])
def test_do_no_harm_a_matched_still_pair_is_the_closed_form(pool):
    clean = _busy(8, seed=5)
    a, b = _pair(clean, META, 40)
    out = PhysicsNoiseEstimator().predict(a, META, reference=b, pool=pool)
    prior = physics_prior_dn(a, META, clipping=True)[:, 4:8]
    assert out["static"].all()
    assert torch.allclose(out["sigma"], prior[:, :3], atol=1e-4) and (out["xi"] == 0).all()


@pytest.mark.parametrize("pool", [False, True])
def test_a_moved_pair_gives_the_single_image_answer(pool):
    clean = _busy(8, seed=6)
    a, b = _pair(clean, META, 50, extra_dn=3.0)
    est = PhysicsNoiseEstimator()
    alone = est.predict(a, META, pool=pool)
    moved = est.predict(a, META, reference=torch.roll(b, 1, -1), pool=pool)
    assert not moved["static"].any()
    for k in ("sigma", "sigma_total", "xi", "p_match", "assessable"):
        assert torch.equal(moved[k], alone[k]), k
    assert moved["reason"] == alone["reason"]


def test_pooled_a_frame_most_of_which_moved_is_read_alone_as_a_whole():
    clean = _busy(8, seed=7)
    a, b = _pair(clean, META, 60)
    b_moved = b.clone()
    b_moved[:5] = torch.roll(b[:5], 1, -1)  # the camera moved: five of eight patches show it (three are flat-ish here)
    out = PhysicsNoiseEstimator().predict(a, META, reference=b_moved, pool=True)
    assert not out["static"].any()


def test_difference_limits_are_where_either_frame_clips():
    """|D| < c ⇔ neither frame within ½ DN of a bound, pixel by pixel (D = (I₁ − I₂)/√2, c from the average alone);
    0 on a pixel that clips; the four pixels of each 2×2 block."""
    g = torch.Generator().manual_seed(3)
    x1 = ((torch.rand(2, 1, 16, 18, generator=g) * 1.4 - 0.2) * 255).round().clamp(0, 255) / 255
    x2 = ((torch.rand(2, 1, 16, 18, generator=g) * 1.4 - 0.2) * 255).round().clamp(0, 255) / 255
    c = difference_limits_dn(x1, x2)
    assert c.shape == (2, 1, 8, 9, 4)
    d = ((x1 - x2) * 255 / math.sqrt(2.0))[..., :16, :18]
    blocks = torch.stack([d[..., 0::2, 0::2], d[..., 0::2, 1::2], d[..., 1::2, 0::2], d[..., 1::2, 1::2]], -1)
    lo = torch.minimum(x1, x2)[..., :16, :18] * 255
    hi = torch.maximum(x1, x2)[..., :16, :18] * 255
    clipped = (lo <= 0.5) | (hi >= 254.5)
    clipped = torch.stack([clipped[..., 0::2, 0::2], clipped[..., 0::2, 1::2], clipped[..., 1::2, 0::2], clipped[..., 1::2, 1::2]], -1)
    assert clipped.any() and (~clipped).any()
    assert torch.equal(c == 0, clipped)
    assert (blocks.abs()[~clipped] < c[~clipped] + 1e-4).all()  # every used pixel's difference within its limit
    avg = ((x1 + x2) * 127.5)[..., 0:16:2, 0:18:2]
    expected = math.sqrt(2.0) * torch.minimum(avg - 0.5, 254.5 - avg)
    ok = ~clipped[..., 0]
    assert torch.allclose(c[..., 0][ok], expected[ok], atol=1e-3)


@pytest.mark.parametrize("shape", [(3, 1, 16, 18), (2, 1, 17, 9)])
def test_the_posteriors_one_pass_agrees_with_the_fold_and_the_average(shape):
    """pair_fold's fold equals static_pair_image (unclamped; formed on its own), and its block means of the average the
    block means of (x₁ + x₂)/2, odd sizes and clipped pixels included."""
    g = torch.Generator().manual_seed(5)
    x1 = ((torch.rand(*shape, generator=g) * 1.6 - 0.3) * 255).round().clamp(0, 255) / 255
    x2 = ((torch.rand(*shape, generator=g) * 1.6 - 0.3) * 255).round().clamp(0, 255) / 255
    f = pair_fold(x1, x2)
    assert torch.allclose(f.fold, static_pair_image(x1, x2, clamp=False), atol=1e-6)
    assert ((f.fold < 0) | (f.fold > 1)).any()  # unclamped where neither frame clips
    h2, w2 = shape[-2] // 2 * 2, shape[-1] // 2 * 2
    assert torch.allclose(f.m_avg, _block_mean(((x1 + x2) * 127.5)[..., :h2, :w2]), atol=1e-3)


def test_the_pairs_kept_variance_is_the_truncated_normals():
    """Gaussian noise of σ 60 DN on a mid-grey scene, both frames clipped and rounded: given the average, the kept
    pixels' differences have the variance σ²·mean h(c/σ) the model predicts, and the binned factor is within 0.3 % of
    that exact mean."""
    g = torch.Generator().manual_seed(0)
    sigma = 60.0
    x1, x2 = (((127.5 + sigma * torch.randn(2, 1, 512, 512, generator=g)).round().clamp(0, 255) / 255) for _ in range(2))
    c = difference_limits_dn(x1, x2).flatten()
    d = torch.stack([((x1 - x2) * 255 / math.sqrt(2.0))[..., i::2, j::2] for i, j in ((0, 0), (0, 1), (1, 0), (1, 1))], -1).flatten()
    used = c > 0
    exact = float(truncated_second_moment(c[used].double() / sigma).mean())
    assert 0.75 < exact < 0.9  # the clipping takes a fifth of the variance here
    measured = float(d[used].double().square().mean()) - 1.0 / 12.0  # the 8-bit rounding's 1/12 DN²
    assert measured / sigma**2 == pytest.approx(exact, rel=0.01)
    counts = torch.bincount(_pair_c_index(c[used]), minlength=64).view(1, 64).double()
    factor = pair_kept_variance_factor(counts, torch.tensor([[sigma**2, (0.5 * sigma) ** 2]], dtype=torch.float64))
    assert float(factor[0, 0]) == pytest.approx(exact, rel=3e-3)
    assert float(factor[0, 1]) == pytest.approx(float(truncated_second_moment(c[used].double() / (0.5 * sigma)).mean()), rel=3e-3)
    assert pair_kept_variance_factor(torch.zeros(1, 64), torch.ones(1, 3)).eq(1.0).all()  # no counts: nothing lost
    with pytest.raises(ValueError, match=r"c_counts must be \(E, 64\) and var \(E, H\), got \(2, 32\) and \(2, 3\)"):
        pair_kept_variance_factor(torch.zeros(2, 32), torch.ones(2, 3))
    with pytest.raises(ValueError, match="got \\(2, 64\\) and \\(3, 3\\)"):
        pair_kept_variance_factor(torch.zeros(2, 64), torch.ones(3, 3))


def test_the_fold_left_unclamped_keeps_the_differences_tails():
    x1 = torch.full((1, 1, 8, 8), 0.5)
    x2 = x1.clone()
    x1[0, 0, 0, 0], x2[0, 0, 0, 0] = 0.9, 0.1  # neither clips; J = 0.5 + 0.8/√2 > 1
    x1[0, 0, 3, 3] = 1.0  # clipped in one frame
    assert static_pair_image(x1, x2)[0, 0, 0, 0] == 1.0
    j = static_pair_image(x1, x2, clamp=False)
    assert float(j[0, 0, 0, 0]) == pytest.approx(0.5 + 0.8 / math.sqrt(2.0), abs=1e-6) and j[0, 0, 3, 3] == 1.0


@pytest.mark.parametrize("level, extra", [(0.5, 40.0), (0.5, 60.0), (0.2, 40.0), (0.2, 60.0)])
def test_a_pair_under_strong_noise_is_read_from_the_pair(level, extra):
    """A frame (16 patches, pooled) with 40–60 DN of extra noise on the told camera, also near a bound: the pair reads
    it (static, assessable) within 5 % of the realised σ_Total with ξ < 0 — the clipping of both frames modelled pixel
    by pixel (read from the clamped fold at its own block means, a flat frame read 9–18 % low at 40–60 DN)."""
    clean = torch.full((16, 1, 128, 128), level)
    a, b = _pair(clean, META, 70, extra_dn=extra)
    out = PhysicsNoiseEstimator().predict(a, META, reference=b, pool=True)
    assert out["static"].all() and out["assessable"].all(), out["reason"]
    truth = (a - clean).mul(255).flatten(1).std(1)  # the realised σ_Total after clipping (no scene: clean is flat)
    assert torch.allclose(out["sigma_total"], truth, rtol=0.05), (out["sigma_total"], truth)
    assert (out["xi"] < -30).all()


@pytest.mark.parametrize("level, reason", [(0.0, "black"), (1.0, "saturated")])
@pytest.mark.parametrize("pool", [False, True])
def test_a_black_or_saturated_pair_is_not_read(level, reason, pool):
    """Every pixel clipped in both frames: the stillness tests have nothing to read, so the pair is not shown still
    ("cannot tell" is not "still") and is read alone — and a clipped patch is not assessable, with finite numbers."""
    x = torch.full((3, 1, 128, 128), level)
    assert not pair_stillness(x, x.clone(), pool=pool).any()
    out = PhysicsNoiseEstimator().predict(x, META, reference=x.clone(), pool=pool)
    assert not out["static"].any() and out["reason"] == [reason] * 3
    assert torch.isfinite(out["sigma"]).all() and torch.isfinite(out["xi"]).all()


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
@pytest.mark.parametrize("batch", [1, 256])
def test_reference_dtypes_and_batches(dtype, batch):
    clean = _busy(1, seed=8).expand(batch, 1, 128, 128)
    a, b = _pair(clean, META, 80, extra_dn=3.0)
    out = PhysicsNoiseEstimator().predict(a.to(dtype), META, reference=b.to(dtype))
    assert out["static"].shape == (batch,) and out["sigma"].dtype == torch.float32
    assert torch.isfinite(out["sigma"]).all()
    assert out["static"].float().mean() > 0.9 and (out["xi"][out["static"]] < 0).float().mean() > 0.9


def test_reference_is_checked_like_the_images():
    est = PhysicsNoiseEstimator()
    x = torch.rand(2, 1, 128, 128)
    with pytest.raises(ValueError, match=r"reference must hold the same patches as images, \(2, 1, 128, 128\), got \(1, 1, 128, 128\)"):
        est.predict(x, META, reference=x[:1])
    with pytest.raises(ValueError, match="reference: images contain 32768 non-finite"):
        est.predict(x, META, reference=torch.full_like(x, float("nan")))
    with pytest.raises(TypeError, match="reference: images must be a real numeric tensor"):
        est.predict(x, META, reference=x > 0.5)
    empty = est.predict(x[:0], META, reference=x[:0])
    assert empty["static"].shape == (0,) and empty["sigma"].shape == (0, 3)
    with pytest.raises(ValueError, match="reference must have the image's shape"):
        physics_noise_posterior(x, META, reference=x[:, :, :64])
    out = est.predict((x * 255).round().to(torch.uint8), META, reference=(x.flip(0) * 255).round().to(torch.uint8))
    assert "static" in out and "static" not in est.predict(x, META)


def test_a_pair_on_each_device_gives_the_cpu_answer(device):
    """The posterior runs on the estimator's device with the pair there too; the stillness tests and the answer are
    the CPU's (σ within float rounding)."""
    from camhealth.inference import load_estimator

    clean = _busy(8, seed=9)
    a, b = _pair(clean, META, 90, extra_dn=3.0)
    cpu = load_estimator("noise_source_full").predict(a, META, reference=b, pool=True)
    dev = load_estimator("noise_source_full", device=str(device)).predict(a, META, reference=b, pool=True)
    assert torch.equal(cpu["static"], dev["static"]) and dev["sigma"].device.type == "cpu"
    assert torch.allclose(cpu["sigma"], dev["sigma"], atol=1e-3) and torch.allclose(cpu["xi"], dev["xi"], atol=1e-3)


_PAIR_FUNCTIONS = {
    "static_pair_image": lambda a, b: static_pair_image(a, b),
    "pair_fold": lambda a, b: pair_fold(a, b).fold,
    "scene_leak": lambda a, b: scene_leak(a, b)[0],
    "pair_shift": lambda a, b: pair_shift(a, b)[0],
    "pair_stillness": lambda a, b: pair_stillness(a, b),
    "pair_stillness_pooled": lambda a, b: pair_stillness(a, b, pool=True),
}


@pytest.mark.parametrize("fn", sorted(_PAIR_FUNCTIONS))
@pytest.mark.parametrize("bad, match", [
    (float("nan"), r"image must be finite, but 1 of 8192 values are NaN/inf \(first: nan\)"),
    (float("inf"), r"image must be finite, but 1 of 8192 values are NaN/inf \(first: inf\)"),
    ("dn", r"image must lie in \[0, 1\] \(DN/255\), got values in \["),
])
def test_bad_pair_values_are_refused(fn, bad, match):
    """NaN and inf went through (a NaN patch "moved", the fold held NaN), and DN-scale frames read every pixel as
    clipped ("still", a fold of 1.0): each public function refuses them, naming the value."""
    g = torch.Generator().manual_seed(0)
    a = 0.5 + 0.02 * torch.randn(2, 1, 64, 64, generator=g)
    b = a + 0.01 * torch.randn(2, 1, 64, 64, generator=g)
    if bad == "dn":
        a = a * 255.0
    else:
        a[1, 0, 5, 5] = bad
    with pytest.raises(ValueError, match=match):
        _PAIR_FUNCTIONS[fn](a, b)
    with pytest.raises(ValueError, match=match.replace("image must", "reference must")):
        _PAIR_FUNCTIONS[fn](b, a)


def test_an_empty_pair_gives_empty_results():
    """An empty batch crashed pair_stillness (``reshape`` of 0 elements); every function returns empty results."""
    e = torch.zeros(0, 1, 32, 32)
    assert static_pair_image(e, e).shape == (0, 1, 32, 32) and pair_fold(e, e).fold.shape == (0, 1, 32, 32)
    for pool in (False, True):
        assert pair_stillness(e, e, pool=pool).shape == (0,)
        leak, se = scene_leak(e, e, pool=pool)
        assert leak.shape == se.shape == (0,)
    shift, n = pair_shift(e, e)
    assert shift.shape == (0, 2) and n.shape == (0,)


@pytest.mark.parametrize("case", ["small_and_moved", "saturated_vs_black"])
def test_a_pair_without_evidence_is_not_shown_still(case):
    """Fewer than 64 usable blocks (scene_leak's error is infinite) or 64 usable pixels (pair_shift reads 0): the tests
    cannot tell, and the pair is not called still. An 8-px pair moved by 3 px and a white frame against a black one
    were both reported still."""
    g = torch.Generator().manual_seed(1)
    if case == "small_and_moved":
        scene = torch.rand(1, 1, 8, 14, generator=g) * 0.6 + 0.2
        a, b = scene[..., :8], scene[..., 3:11]
    else:
        a, b = torch.ones(1, 1, 64, 64), torch.zeros(1, 1, 64, 64)
    leak, se = scene_leak(a, b)
    _, n = pair_shift(a, b)
    assert not bool(torch.isfinite(se).all()) or int(n.min()) < 64  # no evidence
    assert not pair_stillness(a, b).any()


@pytest.mark.parametrize("sigmas,balanced", [((5.0, 5.0), True), ((5.0, 20.0), False), ((20.0, 5.0), False), ((10.0, 11.0), True)])
def test_a_reference_of_another_noise_level_is_not_read_as_a_pair(sigmas, balanced):
    """The fold assumes one noise variance in both frames; a reference at 20 DN beside a 5 DN image read the pair's
    mean, 14.6 DN, for the image. pair_noise_balance measures (v₁ − v₂)/(v₁ + v₂) from the details' cross product,
    free of the scene; such a pair is not still, and the image is read alone."""
    from camhealth.estimators.static_pair import PAIR_NOISE_LIMIT, pair_noise_balance, pair_stillness

    g = torch.Generator().manual_seed(0)
    scene = 0.3 + 0.4 * torch.rand(8, 1, 1, 128, generator=g).expand(8, 1, 128, 128)  # a stripe scene: texture
    a = (scene + sigmas[0] / 255 * torch.randn(8, 1, 128, 128, generator=g)).clamp(0, 1)
    b = (scene + sigmas[1] / 255 * torch.randn(8, 1, 128, 128, generator=g)).clamp(0, 1)
    rho, z = pair_noise_balance(a, b)
    truth = (sigmas[0] ** 2 - sigmas[1] ** 2) / (sigmas[0] ** 2 + sigmas[1] ** 2)
    assert torch.allclose(rho, torch.full_like(rho, truth), atol=0.05)
    assert ((rho.abs() <= PAIR_NOISE_LIMIT) | (z.abs() <= 4)).all() == balanced
    out = PhysicsNoiseEstimator().predict(a, "ICX285", reference=b)
    if not balanced:
        assert not out["static"].any() and not pair_stillness(a, b).any()
        alone = PhysicsNoiseEstimator().predict(a, "ICX285")
        assert torch.equal(out["sigma_total"], alone["sigma_total"])
