"""The physics-first noise-source estimator: the closed form where the image agrees, the image where it does not."""

import pytest
import torch
import torch.nn.functional as F

from camhealth.bench.sensor_variants import VARIANTS, simulate_variant
from camhealth.estimators.noise_features import physics_prior_dn
from camhealth.estimators.noise_features import block_details
from camhealth.estimators.physics_noise import (
    MISMATCH_CAUSES, PHYSICS_NOISE_COLUMNS, SCENE_ALLOWANCE_DN, SCENE_ALLOWANCE_MIN_DN, TEXTURE_LIMIT, VALIDATED_SIGMA_DN,
    PATCH_CHUNK, QUANTISATION_SIGMA_DN, PhysicsNoiseEstimator, _clipping_penalty, _kept_variance_factor, beyond_validated_range,
    noise_evidence, physics_noise_posterior, textured,
)
from camhealth.inference import PHYSICS_NOISE_MODEL, load_estimator
from camhealth.physics import CameraMetadata
from camhealth.physics.metadata import FULL_FIELDS


def _ramp(b: int = 4, size: int = 128) -> torch.Tensor:
    """Smooth scenes spanning 0.15…0.85: flat at the 2×2 scale, many intensities."""
    x = torch.linspace(0.15, 0.85, size).view(1, 1, 1, size).expand(b, 1, size, size)
    return x.contiguous()


@pytest.mark.parametrize("variants", [(), *[(v,) for v in VARIANTS], VARIANTS])
def test_do_no_harm_matched_patch_of_every_simulator_variant_is_the_closed_form(variants):
    meta = CameraMetadata.preset("EV76C661", gain_db=12.0, exposure_s=0.05, temperature_c=40.0)
    clean = _ramp()
    noisy, _ = simulate_variant(clean, meta, variants, torch.Generator().manual_seed(3))
    out = physics_noise_posterior(noisy, meta)
    prior = physics_prior_dn(noisy, meta, clipping=True)[:, 4:8]
    assert torch.allclose(out[:, :4], prior, atol=1e-4)
    assert (out[:, 4] == 0).all() and (out[:, 9] == 0).all()
    assert (out[:, 6] > 0.5).all()


@pytest.mark.parametrize("pool", [False, True])
def test_flat_patch_with_40_dn_of_noise_is_caught(pool):
    """ICX285 at 24 dB / 80 °C predicts a few DN; the patch has 40 DN: ξ < 0, σ_Total followed within 5 %."""
    meta = CameraMetadata.preset("ICX285", gain_db=24.0, exposure_s=0.05, temperature_c=80.0)
    clean = torch.full((2, 1, 128, 128), 0.5)
    noisy, sigma = simulate_variant(clean, meta, (), torch.Generator().manual_seed(0), extra_read_noise_dn=40.0)
    out = physics_noise_posterior(noisy, meta, pool=pool)
    truth = ((noisy - clean) * 255).flatten(1).std(1)
    assert (out[:, 4] < -30).all()
    assert torch.allclose(out[:, 3], truth, rtol=0.05)
    assert torch.allclose(out[:, 2], sigma[:, 2], rtol=0.06)  # the excess is readout-like white noise
    assert (out[:, 9] == 1).all() and (out[:, 6] < 0.01).all()


@pytest.mark.parametrize("level, sigma", [(20.0, 15.0), (60.0, 40.0), (128.0, 60.0), (230.0, 12.0)])
def test_kept_variance_factor_matches_the_details_of_unclipped_blocks(level, sigma):
    """Monte Carlo: blocks of N(level, σ²) pixels, clipped and rounded to 8 bit; among the usable blocks (no pixel
    clipped) whose mean lies within 1 DN of ``level``, the diagonal details keep the closed form's share of σ²."""
    g = torch.Generator().manual_seed(0)
    x = ((level + sigma * torch.randn(64, 1, 128, 128, generator=g)).clamp(0, 255).round() / 255.0)
    m, d2, usable, _ = block_details(x)
    sel = usable & ((m - level).abs() < 1.0)
    assert int(sel.sum()) > 2000
    measured = float(d2[0][sel].mean()) / (sigma**2 + 1.0 / 12.0)
    f = float(_kept_variance_factor(torch.tensor(level, dtype=torch.float64), torch.tensor(sigma**2 + 1.0 / 12.0, dtype=torch.float64)))
    assert abs(measured - f) < 0.04
    if level - 2.5 * sigma < 0 or level + 2.5 * sigma > 255:  # near a bound the share is visibly below 1
        assert f < 0.97
    assert float(_kept_variance_factor(torch.tensor(128.0), torch.tensor(1.0))) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("pool", [False, True])
def test_scene_allowance_keeps_the_closed_form_for_a_scene_with_its_own_fine_noise(pool):
    """A scene that carries 1.5 DN of its own fine-scale noise (a recorded frame), metadata right: the closed form
    (without the allowance the image reads as a mismatch); 5 DN of extra noise is still followed."""
    meta = CameraMetadata.preset("ICX285", gain_db=0.0, exposure_s=0.01, temperature_c=25.0)
    g = torch.Generator().manual_seed(5)
    scene = (_ramp(4) + 1.5 / 255.0 * torch.randn(4, 1, 128, 128, generator=g)).clamp(0, 1)
    noisy, _ = simulate_variant(scene, meta, (), torch.Generator().manual_seed(6))
    prior = physics_prior_dn(noisy, meta, clipping=True)[:, 4:8]
    out = physics_noise_posterior(noisy, meta, pool=pool)
    assert torch.allclose(out[:, :4], prior, atol=1e-4) and (out[:, 4] == 0).all()
    bare = physics_noise_posterior(noisy, meta, pool=pool, scene_allowance_dn=0.0)
    assert (bare[:, 6] < out[:, 6]).all()  # without the allowance the scene's noise argues against the metadata
    if pool:
        assert (bare[:, 6] < 0.5).all()  # and decides, on the frame's evidence
    louder, _ = simulate_variant(scene, meta, (), torch.Generator().manual_seed(6), extra_read_noise_dn=5.0)
    followed = physics_noise_posterior(louder, meta, pool=pool)
    assert (followed[:, 9] == 1).all() and (followed[:, 4] < -1.0).all()


def _levels(b: int = 16, size: int = 128) -> torch.Tensor:
    """Flat patches at ``b`` levels spanning 0.15…0.85: no texture and no gradient at any scale."""
    return torch.linspace(0.15, 0.85, b).view(b, 1, 1, 1).expand(b, 1, size, size).contiguous()


_COL = {c: i for i, c in enumerate(PHYSICS_NOISE_COLUMNS)}


def test_pooled_frame_without_texture_reads_with_the_least_allowance_and_shows_a_small_mismatch():
    """A frame of flat patches: its details show no texture, so pooled it is read with τ_min (1 DN) and 1.8 DN of extra
    white noise on a 1.5 DN camera (ξ ≈ −0.9 DN, visible) is caught; with τ fixed at 2 DN, and per patch, it is not.
    With the metadata right the same frame stays the closed form."""
    meta = CameraMetadata.preset("ICX285", gain_db=0.0, exposure_s=0.01, temperature_c=25.0)
    louder, _ = simulate_variant(_levels(), meta, (), torch.Generator().manual_seed(1), extra_read_noise_dn=1.8)
    out = physics_noise_posterior(louder, meta, pool=True)
    assert torch.allclose(out[:, _COL["scene_allowance_dn"]], torch.tensor(SCENE_ALLOWANCE_MIN_DN), atol=0.1)
    assert (out[:, _COL["follows_image"]] == 1).all() and (out[:, _COL["xi_dn"]] < -0.5).all()
    fixed = physics_noise_posterior(louder, meta, pool=True, scene_allowance_min_dn=SCENE_ALLOWANCE_DN)
    assert (fixed[:, _COL["scene_allowance_dn"]] == SCENE_ALLOWANCE_DN).all() and (fixed[:, _COL["follows_image"]] == 0).all()
    per_patch = physics_noise_posterior(louder, meta)
    assert (per_patch[:, _COL["scene_allowance_dn"]] == SCENE_ALLOWANCE_DN).all() and (per_patch[:, _COL["follows_image"]] == 0).all()
    matched, _ = simulate_variant(_levels(), meta, (), torch.Generator().manual_seed(1))
    kept = physics_noise_posterior(matched, meta, pool=True)
    assert torch.allclose(kept[:, :4], physics_prior_dn(matched, meta, clipping=True)[:, 4:8], atol=1e-4)
    assert (kept[:, _COL["xi_dn"]] == 0).all()


@pytest.mark.parametrize("amplitude", [1.0, 2.0, 3.0, 6.0])
def test_pooled_allowance_covers_the_frames_own_fine_texture_up_to_the_per_patch_allowance(amplitude):
    """Fine smooth texture (Gaussian-filtered white noise, σ 0.7 px: 3.8 times as much horizontal and vertical as
    diagonal detail energy) on flat patches, metadata right: the frame's allowance τ² − τ_min² is at least the diagonal
    energy the texture adds, τ stays within [τ_min, 2 DN], and the answer is the closed form."""
    g = torch.Generator().manual_seed(2)
    k = torch.exp(-torch.arange(-4, 5).float().square() / (2 * 0.7**2))
    k = k / k.sum()
    t = F.conv2d(F.conv2d(torch.randn(16, 1, 144, 144, generator=g), k.view(1, 1, 1, -1)), k.view(1, 1, -1, 1))[..., :128, :128]
    scene = (_levels() + amplitude / 255.0 * t / t.std()).clamp(0, 1)
    _, d2, usable, _ = block_details(scene)
    scene_diagonal = float(d2[0][usable].mean())  # [DN²]
    meta = CameraMetadata.preset("ICX285", gain_db=12.0, exposure_s=0.01, temperature_c=25.0)
    noisy, _ = simulate_variant(scene, meta, (), torch.Generator().manual_seed(1))
    out = physics_noise_posterior(noisy, meta, pool=True)
    tau = out[:, _COL["scene_allowance_dn"]]
    assert ((tau >= SCENE_ALLOWANCE_MIN_DN) & (tau <= SCENE_ALLOWANCE_DN + 1e-6)).all()
    assert float(tau[0]) ** 2 - SCENE_ALLOWANCE_MIN_DN**2 >= min(scene_diagonal, SCENE_ALLOWANCE_DN**2 - SCENE_ALLOWANCE_MIN_DN**2) - 1e-4
    assert torch.allclose(out[:, :4], physics_prior_dn(noisy, meta, clipping=True)[:, 4:8], atol=1e-4)
    assert (out[:, _COL["xi_dn"]] == 0).all()


@pytest.mark.parametrize("levels, split", [(1, True), (16, False)])
def test_per_source_uncertainty_is_large_where_the_prior_alone_splits_the_excess(levels, split):
    """4 DN of extra white noise on a 3 DN camera (ICX285 at 12 dB), pooled. On one grey level the image cannot tell a
    gain change (more PN and RN) from extra white noise (more RN): the posterior splits, the answer's PN is off by more
    than 0.5 DN, and ``sigma_std`` says so (u ≥ 0.5 DN, every error within 2u). Over 16 levels the signal dependence
    separates them: PN within 0.1 DN and u below 0.1 DN."""
    meta = CameraMetadata.preset("ICX285", gain_db=12.0, exposure_s=0.01, temperature_c=25.0)
    scene = torch.linspace(0.1, 0.9, 16).view(16, 1, 1, 1).expand(16, 1, 128, 128).contiguous() if levels == 16 else torch.full((16, 1, 128, 128), 0.5)
    noisy, sigma = simulate_variant(scene, meta, (), torch.Generator().manual_seed(3), extra_read_noise_dn=4.0)
    out = PhysicsNoiseEstimator().predict(noisy, meta, pool=True)
    err, u = (out["sigma"] - sigma).abs(), out["sigma_std"]
    assert out["follows_image"].all()
    if split:
        assert (err[:, 0] > 0.5).all() and (u[:, 0] >= 0.5).all() and (err <= 2 * u).all()
    else:
        assert (err[:, 0] < 0.1).all() and (u[:, 0] < 0.1).all()


@pytest.mark.parametrize("pool", [False, True])
def test_clipping_penalty_refuses_hypotheses_that_clip_more_than_the_patch_not_scene_highlights(pool):
    """A 128-DN patch with 30 DN of noise and a saturated highlight in one corner: the true hypothesis costs
    (almost) nothing in the mid-grey bins, a 90 DN one that would clip far more pixels there is refused."""
    g = torch.Generator().manual_seed(4)
    x = ((128.0 + 30.0 * torch.randn(2, 1, 64, 64, generator=g)).clamp(0, 255).round() / 255.0)
    x[..., :16, :16] = 1.0  # the scene clips here, not the noise
    m, _, _, _ = block_details(x)
    bins = 16
    kbin = (m / 255.0 * bins).floor().clamp(0, bins - 1).long().flatten(1)
    idx = (torch.arange(2).view(2, 1) * bins + kbin).flatten()
    a = torch.zeros(2, 2, dtype=torch.float64)
    c = torch.tensor([[30.0**2, 90.0**2]] * 2, dtype=torch.float64)
    pen = _clipping_penalty(x, m, idx, a, c, torch.zeros(2, dtype=torch.float64), bins, pool)
    mid = [7, 8]  # the bins around 128 DN, where the blocks carry NLF evidence
    true_cost, alias_cost = pen[:, 0, mid].sum(-1), pen[:, 1, mid].sum(-1)
    assert (true_cost > -1.0).all() and (alias_cost < -10.0).all()
    assert (pen[:, :, 15] == 0).all() or (pen[:, 0, 15] > -1.0).all()  # the saturated highlight costs the truth nothing


@pytest.mark.parametrize("level, sigma, rtol, near", [
    (128.0, 50.0, 0.05, False), (128.0, 60.0, 0.05, False), (64.0, 30.0, 0.05, False), (100.0, 40.0, 0.05, False),
    (32.0, 10.0, 0.05, False), (40.0, 35.0, 0.08, True), (20.0, 20.0, 0.08, True), (220.0, 35.0, 0.08, True)])
def test_strong_noise_on_flat_patches_near_and_far_from_the_bounds(level, sigma, rtol, near):
    """σ_Total within 5 % (the validated accuracy) on every flat patch up to 60 DN, dark patches with 30 DN included
    (assessable): the blocks kept only where no pixel is clipped read 5–7 % low without the truncation model, and a
    far noisier hypothesis (whose few kept blocks are as quiet) is refused by the clipped-pixel count.

    ``near``: every block lies within 2 σ of a bound (level ≈ σ), too few details at the nominal margin; with the
    fallback margin (1 σ, the clipping of the nearer blocks modelled) the patch is assessable and within 8 %, where
    the nominal margin alone leaves the closed form (a few DN) with "no flat area"."""
    meta = CameraMetadata.preset("ICX285", gain_db=6.0, exposure_s=0.01, temperature_c=25.0)
    g = torch.Generator().manual_seed(2)
    clean = torch.full((4, 1, 128, 128), level / 255.0)
    noisy = ((clean + torch.randn(clean.shape, generator=g) * sigma / 255.0).clamp(0, 1) * 255.0).round() / 255.0
    truth = ((noisy - clean) * 255.0).flatten(1).std(1)
    for pool in (False, True):
        out = PhysicsNoiseEstimator().predict(noisy, meta, pool=pool)
        assert out["assessable"].all(), out["reason"]
        assert torch.allclose(out["sigma_total"], truth, rtol=rtol)
        assert (out["xi"] < 0).all()
    nominal = PhysicsNoiseEstimator(settings={"fallback_margin": 2.0}).predict(noisy, meta)
    assert (nominal["reason"] == ["no flat area"] * 4) is near
    assert bool((nominal["xi"] == 0).all()) is near


@pytest.mark.parametrize("target", [10.0, 30.0, 60.0])
def test_xi_sign_and_size_up_to_60_dn(target):
    meta = CameraMetadata.preset("EV76C661", gain_db=6.0, exposure_s=0.01, temperature_c=20.0)
    clean = _ramp(2)
    noisy, _ = simulate_variant(clean, meta, ("round8",), torch.Generator().manual_seed(1), extra_read_noise_dn=target)
    as_told, _ = simulate_variant(clean, meta, ("round8",), torch.Generator().manual_seed(1))
    truth_xi = ((as_told - clean) * 255).flatten(1).std(1) - ((noisy - clean) * 255).flatten(1).std(1)
    out = physics_noise_posterior(noisy, meta)
    assert (out[:, 4] < 0).all()
    assert torch.allclose(out[:, 4], truth_xi, rtol=0.08)


def test_gain_mismatch_is_followed_and_pooling_shares_the_answer():
    told = CameraMetadata.preset("ICX285", gain_db=6.0, exposure_s=0.02, temperature_c=30.0)
    clean = _ramp(4)
    noisy, sigma = simulate_variant(clean, told, (), torch.Generator().manual_seed(2), overrides={"gain_db": 16.0})
    for pool in (False, True):
        out = physics_noise_posterior(noisy, told, pool=pool)
        assert (out[:, 9] == 1).all()
        # photon noise follows the real gain; the scene allowance (τ² = 4 DN² a scene may add) lets the answer sit
        # below the reading by up to τ² in variance: here σ_Total ≈ 4 DN, 10 % low
        assert torch.allclose(out[:, 0], sigma[:, 0], rtol=0.12)
        assert (out[:, 4] < 0).all()
    pooled = physics_noise_posterior(noisy, told, pool=True)
    assert torch.equal(pooled[:, 6], pooled[:1, 6].expand(4))


def test_predict_in_chunks_gives_the_answer_of_one_call():
    """``predict`` sends the patches through the statistics PATCH_CHUNK at a time: the same answer as one call over
    all of them, with one camera state and with one camera per patch."""
    told = CameraMetadata.preset("ICX285", gain_db=6.0, exposure_s=0.02, temperature_c=30.0)
    b = PATCH_CHUNK + 7
    noisy, _ = simulate_variant(_ramp(b), told, (), torch.Generator().manual_seed(5), overrides={"gain_db": 12.0})
    for meta in (told, told.expand(b)):
        res = PhysicsNoiseEstimator().predict(noisy, meta)
        ref = physics_noise_posterior(noisy, meta)
        assert res["sigma"].shape == (b, 3) and torch.equal(res["follows_image"], ref[:, 9] > 0.5) and res["follows_image"].any()
        assert torch.allclose(res["sigma"], ref[:, :3], rtol=1e-5, atol=1e-5)
        assert torch.allclose(res["xi"], ref[:, 4], rtol=1e-5, atol=1e-5)


def test_one_camera_states_hypotheses_are_reused_unchanged():
    """One camera state's hypotheses are computed once and reused by later calls: the same as computing them afresh,
    and a call (which follows the image here) leaves them as they were."""
    from camhealth.estimators.physics_noise import _camera_hypotheses, _hypotheses

    told = CameraMetadata.preset("ICX285", gain_db=6.0, exposure_s=0.02, temperature_c=30.0)
    noisy, _ = simulate_variant(_ramp(2), told, (), torch.Generator().manual_seed(6), overrides={"gain_db": 16.0})
    _camera_hypotheses.cache_clear()
    first = physics_noise_posterior(noisy, told)
    assert _camera_hypotheses.cache_info().currsize == 1
    second = physics_noise_posterior(noisy, told)
    assert _camera_hypotheses.cache_info().hits >= 1 and torch.equal(first, second) and (first[:, 9] == 1).all()
    fresh = _hypotheses(told, 96, 0.5, 0.125, torch.device("cpu"))
    key = tuple(float(getattr(told, n).reshape(-1)[0]) for n in FULL_FIELDS)
    for cached, recomputed in zip(_camera_hypotheses(key, 96, 0.5, 0.125, "cpu"), fresh):
        assert torch.equal(cached, recomputed)


def test_runs_on_the_patches_device_with_the_cpu_answer(device):
    """The statistics run on the device of the patches (a GPU where there is one) and give the CPU's answer: the
    same decisions, σ within float32 rounding."""
    told = CameraMetadata.preset("ICX285", gain_db=6.0, exposure_s=0.02, temperature_c=30.0)
    noisy, _ = simulate_variant(_ramp(4), told, (), torch.Generator().manual_seed(3), overrides={"gain_db": 16.0})
    for pool in (False, True):
        ref = physics_noise_posterior(noisy, told, pool=pool)
        out = physics_noise_posterior(noisy.to(device), told.to(device), pool=pool)
        assert out.device.type == device.type
        out = out.cpu()
        assert torch.equal(out[:, 9], ref[:, 9]) and (ref[:, 9] == 1).all()
        assert torch.allclose(out, ref, rtol=1e-5, atol=1e-4)


def test_each_patch_is_answered_alone_whatever_shares_its_batch():
    """Per patch (not pooled) a patch's answer depends on it and its metadata only: one camera state for the batch
    (hypotheses computed once, shared), the same state spelled out per patch, and every patch alone agree, also when
    the patches span different intensity bins and one of them follows the image."""
    told = CameraMetadata.preset("ICX285", gain_db=6.0, exposure_s=0.02, temperature_c=30.0)
    clean = torch.cat([_ramp(1), torch.full((1, 1, 128, 128), 0.1), torch.full((1, 1, 128, 128), 0.9), _ramp(1).flip(-1)])
    g = torch.Generator().manual_seed(8)
    noisy, _ = simulate_variant(clean, told, (), g)
    noisy[3:], _ = simulate_variant(clean[3:], told, (), g, overrides={"gain_db": 18.0})
    shared = physics_noise_posterior(noisy, told)
    per_row = physics_noise_posterior(noisy, told.expand(4))
    alone = torch.cat([physics_noise_posterior(noisy[i:i + 1], told) for i in range(4)])
    assert shared[3, 9] == 1 and (shared[:3, 9] == 0).all()  # the last one follows the image
    assert torch.allclose(shared, per_row, rtol=1e-5, atol=1e-6)
    assert torch.allclose(shared, alone, rtol=1e-5, atol=1e-6)
    other = CameraMetadata.preset("ICX285", gain_db=18.0, exposure_s=0.02, temperature_c=30.0)
    mixed = physics_noise_posterior(noisy, CameraMetadata.cat([told, told, told, other]))  # one camera per patch
    assert torch.allclose(mixed[:3], shared[:3], rtol=1e-5, atol=1e-6)
    assert torch.allclose(mixed[3:], physics_noise_posterior(noisy[3:], other), rtol=1e-5, atol=1e-6)
    assert mixed[3, 9] == 0  # told the gain it was made with, the last patch is the closed form


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
@pytest.mark.parametrize("batch", [1, 256])
def test_dtypes_batches_and_hard_patches(dtype, batch):
    meta = CameraMetadata.preset("ICX285", gain_db=12.0)
    x = torch.rand(batch, 1, 128, 128, generator=torch.Generator().manual_seed(0)).to(dtype)
    x[0] = 0.0  # black
    if batch > 1:
        x[1] = 1.0  # saturated
        x[2] = 0.5  # noiseless grey
    out = physics_noise_posterior(x, meta)
    assert out.shape == (batch, len(PHYSICS_NOISE_COLUMNS)) and out.dtype == torch.float32
    assert torch.isfinite(out[:, :5]).all()
    assert out[0, 7] == 0  # no usable detail in a black patch: no evidence, the closed form
    std = out[:, [_COL["pn_std_dn"], _COL["dcsn_std_dn"], _COL["rn_std_dn"]]]
    assert torch.isinf(std[0]).all() and (std >= 0).all() and not torch.isnan(std).any()  # no evidence: no uncertainty bound
    res = PhysicsNoiseEstimator().predict(x.float(), meta)
    assert res["reason"][0] == "black" and not res["assessable"][0]
    if batch > 1:
        assert res["reason"][1] == "saturated"


def test_estimator_interface_reasons_and_loader():
    est = load_estimator(PHYSICS_NOISE_MODEL)
    assert isinstance(est, PhysicsNoiseEstimator) and est.kind == "noise_source" and est.metadata_set == "full"
    meta = CameraMetadata.preset("ICX285", gain_db=24.0, temperature_c=80.0)
    clean = torch.full((3, 1, 128, 128), 0.5)
    u = torch.arange(128.0) * 2 * torch.pi / 6
    clean[1, 0] = 0.5 + 0.2 * torch.sin(u).view(1, -1) + 0.2 * torch.sin(u).view(-1, 1)  # strong fine texture everywhere
    noisy, _ = simulate_variant(clean, meta, (), torch.Generator().manual_seed(0), extra_read_noise_dn=torch.tensor([3.0, 3.0, 90.0]))
    out = est.predict(noisy, meta)
    assert out["reason"][0] == "" and out["assessable"][0]
    assert out["reason"][1] == "no flat area"
    assert out["reason"][2] == "noise beyond validated range" and -out["xi"][2] > VALIDATED_SIGMA_DN - 10
    assert set(out) >= {"sigma", "sigma_std", "sigma_total", "xi", "xi_std", "p_match", "assessable", "reason"}
    assert out["sigma_std"].shape == (3, 3)
    assert torch.isinf(out["xi_std"][1])  # no evidence: ξ unknown
    assert bool(((out["p_match"] >= 0) & (out["p_match"] <= 1)).all())  # a probability, also where it is ~0


def test_uniform_noise_beyond_the_validated_range_is_refused_not_read_low():
    """Uniform noise of σ 73.6 DN (255/√12) is not clipped Gaussian noise: read through the clipped-Gaussian model it
    looks like ≈ 52 DN, within the validated range; its fine-scale fluctuations say otherwise."""
    g = torch.Generator().manual_seed(0)
    noisy = (torch.rand(4, 1, 128, 128, generator=g) * 255).round() / 255
    out = PhysicsNoiseEstimator().predict(noisy, CameraMetadata.preset("ICX285"))
    assert out["reason"] == ["noise beyond validated range"] * 4 and not out["assessable"].any()
    assert bool(beyond_validated_range(noisy).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("level", [0.15, 0.5, 0.85])
def test_clipped_gaussian_noise_within_the_validated_range_is_not_refused_as_beyond_it(dtype, level):
    """60 DN of Gaussian noise, clipped at 0 and 255 DN and 8-bit rounded, on 64 flat patches: the fine-scale check
    never fires (clipping only lowers it), and strong sparse edges do not move its median."""
    g = torch.Generator().manual_seed(1)
    x = (level + 60.0 / 255 * torch.randn(64, 1, 128, 128, generator=g)).clamp(0, 1)
    assert not bool(beyond_validated_range(((x * 255).round() / 255).to(dtype)).any())
    edges = torch.full((8, 1, 128, 128), level)
    edges[..., ::16, :] = 1.0 - level  # a full-contrast line every 16 rows, 2 DN of noise
    edges = (edges + 2.0 / 255 * torch.randn(edges.shape, generator=g)).clamp(0, 1).to(dtype)
    assert not bool(beyond_validated_range(edges).any())


def test_bad_input_is_refused():
    meta = CameraMetadata.preset("ICX285")
    x = torch.rand(2, 1, 32, 32)
    with pytest.raises(ValueError, match="B×1×H×W"):
        physics_noise_posterior(x[:, 0], meta)
    with pytest.raises(TypeError, match="floating-point"):
        physics_noise_posterior((x * 255).to(torch.uint8), meta)
    bad = x.clone()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        physics_noise_posterior(bad, meta)
    with pytest.raises(ValueError, match=r"eta = -0.1 must be in \[0, 10\]"):
        physics_noise_posterior(x, meta, eta=-0.1)
    with pytest.raises(ValueError, match=r"scene_allowance_min_dn = -0.5 must be in \[0, 64\]"):
        physics_noise_posterior(x, meta, scene_allowance_min_dn=-0.5)
    with pytest.raises(ValueError, match=r"scene_allowance_dn = -1.0 must be in \[0, 64\]"):
        physics_noise_posterior(x, meta, scene_allowance_dn=-1.0)
    with pytest.raises(ValueError, match="scene_allowance_dn"):
        physics_noise_posterior(x, meta, scene_allowance_dn=float("nan"))
    with pytest.raises(ValueError, match=r"fallback_margin = -1.0 must be in \[0, 64\]"):
        physics_noise_posterior(x, meta, fallback_margin=-1.0)
    with pytest.raises(ValueError, match=r"bound_margin = nan must be in \[0, 64\]"):
        physics_noise_posterior(x, meta, bound_margin=float("nan"))
    with pytest.raises(ValueError, match="beyond_probability"):
        physics_noise_posterior(x, meta, mismatch_probability=0.1, beyond_probability=0.2)
    with pytest.raises(ValueError, match="metadata batch 3"):
        physics_noise_posterior(x, CameraMetadata.preset("ICX285", batch_size=3))
    with pytest.raises(ValueError, match="pool=True"):
        physics_noise_posterior(x, CameraMetadata.preset("ICX285", batch_size=2), pool=True)
    with pytest.raises(ValueError, match="pass metadata"):
        PhysicsNoiseEstimator().predict(torch.rand(1, 1, 128, 128))
    with pytest.raises(ValueError, match="views"):
        PhysicsNoiseEstimator().predict(torch.rand(1, 1, 128, 128), meta, views=2)


@pytest.mark.parametrize("scale,offset,lo,hi", [(255.0, 0.0, "127.5", "127.5"), (1.0, -0.6, "-0.1", "-0.1")])
def test_intensities_outside_the_unit_range_are_refused(scale, offset, lo, hi):
    """DN-scaled (×255) or shifted patches are refused, not read as a confident match; so is such a reference."""
    meta = CameraMetadata.preset("ICX285")
    x = torch.full((1, 1, 32, 32), 0.5) * scale + offset
    with pytest.raises(ValueError, match=rf"image must lie in \[0, 1\] \(DN/255\), got values in \[{lo}, {hi}\]"):
        physics_noise_posterior(x, meta)
    with pytest.raises(ValueError, match=rf"reference must lie in \[0, 1\] \(DN/255\), got values in \[{lo}, {hi}\]"):
        physics_noise_posterior(torch.full((1, 1, 32, 32), 0.5), meta, reference=x)


@pytest.mark.parametrize("pool", [False, True])
def test_texture_that_only_the_neighbour_check_sees_is_refused(pool):
    """A fine texture (−1)^(x+y+bx+by) · 6 DN (bx, by: the 2×2-block indices) has zero block means and zero horizontal
    and vertical Haar details — the flatness tests and the texture ratio cannot see it — and adds 12 DN to every
    diagonal detail with the sign flipping from block to block, like noise. Under the metadata's few DN it would read as
    a mismatch; adjacent blocks' diagonal details are perfectly anti-correlated, so the patch is "textured": the
    closed form is kept and the patch is not assessable. White noise of the same size is followed."""
    meta = CameraMetadata.preset("ICX285", gain_db=6.0, exposure_s=0.01, temperature_c=25.0)
    y, x = torch.meshgrid(torch.arange(128), torch.arange(128), indexing="ij")
    sign = (-1.0) ** (x + y + x // 2 + y // 2)
    scene = (0.5 + 6.0 / 255.0 * sign).expand(4, 1, 128, 128).contiguous()
    _, d2, _, _ = block_details(scene)
    assert d2[1].abs().max() < 1e-3 and d2[2].abs().max() < 1e-3 and d2[0].sqrt().mean() == pytest.approx(12.0, rel=1e-3)
    noisy, _ = simulate_variant(scene, meta, (), torch.Generator().manual_seed(8))
    out = physics_noise_posterior(noisy, meta, pool=pool)
    prior = physics_prior_dn(noisy, meta, clipping=True)[:, 4:8]
    col = PHYSICS_NOISE_COLUMNS.index("detail_corr_check")
    assert (out[:, col] >= 1.0).all() and (out[:, 9] == 0).all() and (out[:, 4] == 0).all()
    assert torch.allclose(out[:, :4], prior, atol=1e-4)
    res = PhysicsNoiseEstimator().predict(noisy, meta, pool=pool)
    assert not res["assessable"].any() and set(res["reason"]) == {"textured"}
    # 12 DN of white noise instead: uncorrelated neighbours, followed as a mismatch
    white, _ = simulate_variant(torch.full((4, 1, 128, 128), 0.5), meta, (), torch.Generator().manual_seed(8),
                                extra_read_noise_dn=12.0)
    out_w = physics_noise_posterior(white, meta, pool=pool)
    assert (out_w[:, col] < 1.0).all() and (out_w[:, 9] == 1).all() and (out_w[:, 4] < -5.0).all()


def test_textured_adds_the_two_checks_in_quadrature():
    assert not bool(textured(torch.tensor(0.0), torch.tensor(0.0)))
    assert bool(textured(torch.tensor(TEXTURE_LIMIT), torch.tensor(0.0)))  # each alone at its limit
    assert bool(textured(torch.tensor(-1.0), torch.tensor(1.0)))  # a negative texture check counts as 0
    assert not bool(textured(torch.tensor(-1.0), torch.tensor(0.99)))
    both = textured(torch.tensor([0.19, 0.10]), torch.tensor([0.71, 0.30]))  # two marginal signs, two small ones
    assert both.tolist() == [True, False]


def test_matched_patch_with_two_marginal_signs_of_texture_keeps_the_closed_form():
    """A matched patch of the robustness benchmark (seed 7, ``reference``: a photograph at full resolution, σ_Total
    9.8 DN, stored as 16-bit PNG) that is mostly texture: 669 of 4 096 blocks look flat. The texture check (0.22) and
    the neighbour check (0.56 of its limit) each pass, and the evidence alone says "noisier" (P(match) < ½); together
    they are texture, so the answer stays the closed form (the patch once read 14.8 DN, ξ = −4.9 DN)."""
    import cv2
    from pathlib import Path

    raw = cv2.imread(str(Path(__file__).parent / "data" / "textured_matched_patch.png"), cv2.IMREAD_UNCHANGED)
    assert raw is not None and raw.dtype.name == "uint16" and raw.shape == (128, 128)
    x = torch.from_numpy(raw.astype("float32") / 65535.0).view(1, 1, 128, 128)
    told = {"gain_db": 4.591660499572754, "exposure_s": 0.17213797569274902, "temperature_c": 29.604312896728516,
            "dark_fom_na_per_cm2": 0.30853065848350525, "full_well_e": 2979.525634765625, "pixel_clock_hz": 35658232.0,
            "sense_node_gain_v_per_e": 2.9390023428277345e-06, "reset_factor": 0.6148049235343933,
            "pixel_size_um": 8.043506622314453, "is_cmos": 1.0, "white_noise_v_per_rthz": 6.241862582356816e-09}
    meta = CameraMetadata(**{k: torch.tensor([v]) for k, v in told.items()})
    out = physics_noise_posterior(x, meta)[0]
    col = {c: i for i, c in enumerate(PHYSICS_NOISE_COLUMNS)}
    assert out[col["p_match"]] < 0.5 and out[col["details"]] >= 256
    assert 0 < out[col["texture"]] < TEXTURE_LIMIT and out[col["detail_corr_check"]] < 1.0
    assert out[col["follows_image"]] == 0 and out[col["xi_dn"]] == 0
    prior = physics_prior_dn(x, meta, clipping=True)[0, 4:8]
    assert torch.allclose(out[:4], prior, atol=1e-4) and float(prior[3]) == pytest.approx(9.87, abs=0.05)
    res = PhysicsNoiseEstimator().predict(x, meta)
    assert res["reason"] == ["textured"] and not res["assessable"].any()


@pytest.mark.parametrize("kind", ["rows", "columns", "both"])
@pytest.mark.parametrize("pool", [False, True])
def test_row_and_column_noise_counts_in_the_total_and_in_xi(kind, pool):
    """Right metadata, a mid-grey patch, 10 DN of offsets per pixel row and/or column: the per-source σ stay the
    closed form (the banding is no source of the metadata), σ_Total = √(σ_Total(M)² + σ_row² + σ_col²) within 10 %,
    ξ < 0 by as much, P(match) = 0; ``row_column_dn`` gives the banding. The patch is assessable."""
    meta = CameraMetadata.preset("ICX285", gain_db=12.0, exposure_s=0.02, temperature_c=30.0)
    clean = torch.full((8, 1, 128, 128), 0.5)
    noisy, _ = simulate_variant(clean, meta, ("round8",), torch.Generator().manual_seed(2))
    g = torch.Generator().manual_seed(3)
    band = torch.zeros(8, 1, 128, 128)
    if kind in ("rows", "both"):
        band = band + 10.0 * torch.randn(8, 1, 128, 1, generator=g)
    if kind in ("columns", "both"):
        band = band + 10.0 * torch.randn(8, 1, 1, 128, generator=g)
    x = ((noisy + band / 255.0).clamp(0, 1) * 255).round() / 255
    est = PhysicsNoiseEstimator()
    out = est.predict(x, meta, pool=pool)
    prior = physics_prior_dn(x, meta, clipping=True)[:, 4:8]
    assert out["assessable"].all(), out["reason"]
    assert torch.allclose(out["sigma"], prior[:, :3], atol=0.05)
    band_dn = out["row_column_dn"]
    assert band_dn.shape == (8, 2)
    for i, on in enumerate((kind in ("rows", "both"), kind in ("columns", "both"))):
        if on:
            assert band_dn[:, i].median() == pytest.approx(10.0, rel=0.1)
        else:
            assert (band_dn[:, i] == 0).all()
    expect = (prior[:, 3].square() + band_dn.square().sum(1)).sqrt()
    assert torch.allclose(out["sigma_total"], expect, rtol=1e-4)
    truth = ((x - clean) * 255).flatten(1).std(1)
    assert out["sigma_total"].median() == pytest.approx(float(truth.median()), rel=0.1)
    assert torch.allclose(out["xi"], prior[:, 3] - out["sigma_total"], atol=1e-4) and (out["xi"] < -5).all()
    assert (out["p_match"] == 0).all() and out["follows_image"].all()
    assert torch.isfinite(out["xi_std"]).all() and (out["xi_std"] > 0).all()


def test_no_banding_reported_on_matched_patches_of_every_simulator_variant():
    """Do no harm: the matched patches of the do-no-harm test report no row or column noise."""
    meta = CameraMetadata.preset("EV76C661", gain_db=12.0, exposure_s=0.05, temperature_c=40.0)
    noisy, _ = simulate_variant(_ramp(16), meta, VARIANTS, torch.Generator().manual_seed(3))
    for pool in (False, True):
        out = PhysicsNoiseEstimator().predict(noisy, meta, pool=pool)
        assert (out["row_column_dn"] == 0).all()
    assert PhysicsNoiseEstimator().predict(torch.zeros(0, 1, 128, 128), meta)["row_column_dn"].shape == (0, 2)


@pytest.mark.parametrize("pool", [False, True])
def test_defective_pixels_are_reported_apart_and_leave_the_answer_alone(pool):
    """Right metadata (σ ≈ 5 DN), 0.3 % of the pixels hot or dead (60–150 DN): ``defects`` counts them (hot, dark) and
    ``defect_mask`` says where; σ per source, σ_Total and ξ stay the closed form (defects are not noise of the sensor
    model, and the fits are robust to them). Without defects nothing is reported."""
    meta = CameraMetadata.preset("EV76C661", gain_db=12.0, exposure_s=0.05, temperature_c=40.0)
    noisy, _ = simulate_variant(_ramp(8), meta, ("round8",), torch.Generator().manual_seed(4))
    g = torch.Generator().manual_seed(5)
    hit = torch.rand(noisy.shape, generator=g) < 0.003
    hit[..., [0, -1], :] = False
    hit[..., :, [0, -1]] = False
    sign = torch.where(torch.rand(noisy.shape, generator=g) < 0.5, 1.0, -1.0)
    x = (noisy * 255 + hit * sign * (60 + 90 * torch.rand(noisy.shape, generator=g))).clamp(0, 255).round() / 255
    est = PhysicsNoiseEstimator()
    out, ref = est.predict(x, meta, pool=pool), est.predict(noisy, meta, pool=pool)
    assert (ref["defects"] == 0).all() and (ref["defect_mask"] == 0).all()
    found = out["defect_mask"] != 0
    assert int((found & ~hit).sum()) == 0 and int((found & hit).sum()) >= 0.9 * int(hit.sum())
    assert torch.equal(out["defects"][:, 0], (out["defect_mask"] > 0).flatten(1).sum(1))
    assert torch.equal(out["defects"][:, 1], (out["defect_mask"] < 0).flatten(1).sum(1))
    prior = physics_prior_dn(noisy, meta, clipping=True)[:, 4:8]
    assert torch.allclose(out["sigma"], prior[:, :3], atol=0.05) and (out["xi"] == 0).all()
    assert torch.allclose(out["sigma_total"], ref["sigma_total"], rtol=0.02)
    empty = est.predict(torch.zeros(0, 1, 128, 128), meta)
    assert empty["defects"].shape == (0, 2) and empty["defect_mask"].shape == (0, 1, 128, 128)


def _mixed_frame(amplitude: float = 20.0) -> tuple[torch.Tensor, torch.Tensor, CameraMetadata]:
    """12 patches of fine texture (white noise through a Gaussian of σ 0.5 px, ``amplitude`` DN) and 4 flat ones, all
    mid-grey, with the ICX285's own noise, 20 DN of extra white noise and 8-bit rounding: (noisy, clean, told)."""
    g = torch.Generator().manual_seed(1)
    k = torch.exp(-torch.arange(-4, 5).float().square() / (2 * 0.5**2))
    k = k / k.sum()
    t = F.conv2d(F.conv2d(torch.randn(12, 1, 136, 136, generator=g), k.view(1, 1, 1, -1)), k.view(1, 1, -1, 1))
    clean = torch.cat([0.5 + amplitude / 255.0 * t / t.std(), torch.full((4, 1, 128, 128), 0.5)]).clamp(0, 1)
    meta = CameraMetadata.preset("ICX285", gain_db=6.0, exposure_s=0.02, temperature_c=30.0)
    noisy, _ = simulate_variant(clean, meta, ("round8",), torch.Generator().manual_seed(2), extra_read_noise_dn=20.0)
    return noisy, clean, meta


def test_a_textured_frame_still_reads_the_patches_that_are_readable_alone():
    """Pooled, 12 textured patches make the frame's summed details textured; the 4 flat ones pass both checks on their
    own details (the posterior's per-patch columns) and are read alone: σ_Total within 5 %, ξ < 0 (20 DN of white
    noise the metadata do not make). The rest stay refused as textured; each patch read alone gets exactly the
    per-patch answer. Per patch, the per-patch columns repeat the frame columns."""
    noisy, clean, meta = _mixed_frame()
    raw = physics_noise_posterior(noisy, meta, pool=True)
    assert bool(textured(raw[0, _COL["texture"]], raw[0, _COL["detail_corr_check"]]))  # the frame as a whole
    alone = ~textured(raw[:, _COL["patch_texture"]], raw[:, _COL["patch_detail_corr_check"]]) & (raw[:, _COL["patch_details"]] >= 256)
    assert alone[12:].all() and int(alone[:12].sum()) <= 4
    out = PhysicsNoiseEstimator().predict(noisy, meta, pool=True)
    truth = ((noisy - clean) * 255).flatten(1).std(1)
    assert out["assessable"][12:].all()
    assert torch.allclose(out["sigma_total"][12:], truth[12:], rtol=0.05) and (out["xi"][12:] < -15).all()
    per = physics_noise_posterior(noisy[alone], meta)
    assert torch.equal(out["sigma_total"][alone], per[:, 3]) and torch.equal(out["xi"][alone], per[:, 4])
    refused = [r for r, a in zip(out["reason"], alone.tolist()) if not a]
    assert refused and set(refused) == {"textured"}
    own = physics_noise_posterior(noisy, meta)
    for frame_col, patch_col in (("details", "patch_details"), ("texture", "patch_texture"),
                                 ("detail_corr_check", "patch_detail_corr_check")):
        assert torch.equal(own[:, _COL[frame_col]], own[:, _COL[patch_col]])


def test_a_frame_that_is_not_textured_is_read_as_one_camera_state():
    """With weaker texture the frame passes pooled: every patch gets the frame's posterior (no patch read alone)."""
    noisy, _, meta = _mixed_frame(amplitude=5.0)
    raw = physics_noise_posterior(noisy, meta, pool=True)
    assert not bool(textured(raw[0, _COL["texture"]], raw[0, _COL["detail_corr_check"]]))
    out = PhysicsNoiseEstimator().predict(noisy, meta, pool=True)
    assert out["assessable"].all() and torch.equal(out["xi"], raw[:, _COL["xi_dn"]])
    assert (out["p_match"] == out["p_match"][0]).all()  # one posterior (σ after clipping stays per patch)


def test_dilate3_equals_a_3x3_max_pool():
    from camhealth.estimators.physics_noise import _dilate3

    g = torch.Generator().manual_seed(2)
    for shape in [(8, 1, 64, 64), (1, 1, 3, 3), (2, 1, 1, 5), (3, 1, 7, 1), (4, 1, 96, 40)]:
        for share in (0.0, 0.01, 0.2, 1.0):
            mask = torch.rand(*shape, generator=g) < share
            assert torch.equal(_dilate3(mask), F.max_pool2d(mask.float(), 3, 1, 1) > 0), (shape, share)


def test_clip_thresholds_find_pixels_within_half_a_dn_of_the_bounds_exactly():
    """x ≤ t₀ ⟺ 255·x ≤ 0.5 and x ≥ t₂₅₅ ⟺ 255·x ≥ 254.5 (computed exactly in float64) for float32 x around both
    thresholds and for every 8-bit value."""
    from camhealth.estimators.physics_noise import _clip_thresholds

    lo, hi = _clip_thresholds()
    f32 = torch.float32
    near = []
    for bound in (lo, hi):
        t = torch.tensor(bound, dtype=f32)
        for direction in (-1.0, 2.0):
            u = t
            for _ in range(8):
                u = torch.nextafter(u, torch.tensor(direction, dtype=f32))
                near.append(u)
        near.append(t)
    x = torch.cat([torch.stack(near), torch.arange(256, dtype=f32) / 255.0])
    exact = x.double() * 255.0
    assert torch.equal(x <= lo, exact <= 0.5)
    assert torch.equal(x >= hi, exact >= 254.5)


def test_median_variance_equals_a_per_bin_nanmedian():
    from camhealth.estimators.physics_noise import _median_variance

    g = torch.Generator().manual_seed(4)
    for trial in range(40):
        b, bins = int(torch.randint(1, 6, (1,), generator=g)), int(torch.randint(1, 9, (1,), generator=g))
        m = torch.rand(b, 1, 16, 24, generator=g) * 255.0
        d2 = torch.randn(b, 1, 16, 24, generator=g).square() * 30.0
        if trial % 3 == 0:
            d2 = d2.round()  # ties
        usable = torch.rand(b, 1, 16, 24, generator=g) < float(torch.rand(1, generator=g))
        k = (m / 255.0 * bins).floor().clamp(0, bins - 1).long().flatten(1)
        ref = torch.full((b, bins), float("inf"))
        for i in range(b):
            for j in range(bins):
                sel = d2.flatten(1)[i][(k[i] == j) & usable.flatten(1)[i]]
                if sel.numel():
                    ref[i, j] = sel.median() / 0.4549
        want = ref.gather(1, k).view_as(m).clamp_min(1e-6)
        assert torch.equal(_median_variance(m, d2, usable, bins), want), trial


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_quantisation_variance_is_the_exact_verdict_at_the_tolerance(dtype):
    """8-bit patches get 1/12 DN²; a patch whose largest distance to a whole DN lies just below, at or just above
    1e-3 DN gets the verdict of the exact float64 product, not of float32 rounding."""
    from camhealth.estimators.physics_noise import _quantisation_variance

    g = torch.Generator().manual_seed(0)
    base = (torch.rand(6, 1, 16, 16, generator=g) * 255).round()
    base[:, :, 0, 0] = 200.0
    offsets = torch.tensor([0.0, 0.999e-3, 1e-3, 1.001e-3, 0.3, 5e-4], dtype=torch.float64)
    x = base.double()
    x[:, 0, 0, 0] += offsets
    x = (x / 255.0).to(dtype)
    exact = (x.double().flatten(1) * 255.0)
    want = ((exact - exact.round()).abs().amax(1) < 1e-3).double() / 12.0
    got = _quantisation_variance(x)
    assert torch.equal(got, want)
    assert got[0] == 1 / 12 and got[4] == 0 and got[5] == 1 / 12


# --- other exposure times of the same camera: dark-current shot noise ∝ t_exp, readout noise not -------------------

def _two_exposures(override: dict | None, seed: int = 1) -> tuple[CameraMetadata, CameraMetadata, list]:
    """A CMOS camera with much dark current (EV76C661, 6 dB, 30 °C) at 0.2 s and at 0.02 s, the same ramp scene,
    16 patches per frame; each exposure twice (a static pair). ``override``: the field the camera really has."""
    long = CameraMetadata.preset("EV76C661", gain_db=6.0, exposure_s=0.2, temperature_c=30.0)
    short = long.replace(exposure_s=torch.tensor([0.02], dtype=torch.float64))
    clean = _ramp(16)
    sims = [simulate_variant(clean, m, (), torch.Generator().manual_seed(seed + k), override)
            for k, m in enumerate((long, long, short, short))]
    return long, short, sims


@pytest.mark.parametrize("pair", [False, True])
@pytest.mark.parametrize("field, factor", [("temperature_c", None), ("white_noise_v_per_rthz", 3.0)])
def test_two_exposure_times_tell_dark_current_from_readout_noise(field, factor, pair):
    """The camera is 25 K hotter than told (a dark-current excess, ∝ t_exp), or has 3× the thermal white noise (a
    readout excess, the same at every exposure). One exposure shows a signal-independent excess that the prior splits
    between the two sources (the source that did not change reads 30 % high or more); with a second exposure time the
    physics splits it: each within 5 % of the realised σ."""
    long = CameraMetadata.preset("EV76C661", gain_db=6.0, exposure_s=0.2, temperature_c=30.0)
    override = {field: 55.0 if factor is None else float(long.white_noise_v_per_rthz) * factor}
    long, short, sims = _two_exposures(override)
    est = PhysicsNoiseEstimator()
    ref, ref_short = (sims[1][0], sims[3][0]) if pair else (None, None)
    other = [(sims[2][0], short) if ref_short is None else (sims[2][0], short, ref_short)]
    alone = est.predict(sims[0][0], long, pool=True, reference=ref)
    joint = est.predict(sims[0][0], long, pool=True, reference=ref, other_exposures=other)
    truth = sims[0][1][:, 1:3]  # realised σ of DCSN and RN [DN]
    assert joint["exposures_read"] == 1 and (joint["xi"] < 0).all() and joint["assessable"].all()
    assert torch.allclose(joint["sigma"][:, 1:3], truth, rtol=0.05), (joint["sigma"][:, 1:3].mean(0), truth.mean(0))
    unchanged = 2 if field == "temperature_c" else 1  # RN, or DCSN
    assert (alone["sigma"][:, unchanged] > 1.3 * sims[0][1][:, unchanged]).all()
    assert torch.allclose(joint["sigma"][:, 0], alone["sigma"][:, 0], rtol=0.02)  # PN was never in doubt


def test_other_exposures_keep_the_closed_form_of_a_matched_camera():
    """Do no harm: metadata right at both exposure times (an independent simulator variant), the answer is the
    closed form exactly, as without the other exposure."""
    long, short, sims = _two_exposures(None)
    noisy = [simulate_variant(_ramp(16), m, VARIANTS, torch.Generator().manual_seed(k))[0]
             for k, m in ((5, long), (6, short))]
    est = PhysicsNoiseEstimator()
    alone = est.predict(noisy[0], long, pool=True)
    joint = est.predict(noisy[0], long, pool=True, other_exposures=[(noisy[1], short)])
    prior = physics_prior_dn(noisy[0], long, clipping=True)[:, 4:8]
    assert joint["exposures_read"] == 1
    assert torch.equal(joint["sigma"], alone["sigma"]) and (joint["xi"] == 0).all()
    assert torch.allclose(joint["sigma"], prior[:, :3], atol=1e-4)


def test_a_mismatch_the_long_exposure_shows_is_followed_at_the_short_one():
    """The sensor is 25 K hotter than told. At 0.02 s its dark current moves σ_Total too little to see (under
    max(0.5 DN, 15 %)), so that frame alone keeps the closed form (σ_DCSN 0.40 against 1.0 DN realised); the 0.2-s
    frame shows it, and with its evidence the short frame follows it too: each source within 5 %, ξ < 0."""
    long, short, sims = _two_exposures({"temperature_c": 55.0})
    est = PhysicsNoiseEstimator()
    alone = est.predict(sims[2][0], short, pool=True)
    joint = est.predict(sims[2][0], short, pool=True, other_exposures=[(sims[0][0], long)])
    truth = sims[2][1]
    prior = physics_prior_dn(sims[2][0], short, clipping=True)[:, 4:7]
    assert (alone["xi"] == 0).all() and torch.allclose(alone["sigma"][:, :3], prior, atol=1e-4)
    assert (alone["sigma"][:, 1] < 0.5 * truth[:, 1]).all()
    assert torch.allclose(joint["sigma"][:, :3], truth, rtol=0.05), (joint["sigma"].mean(0), truth.mean(0))
    assert (joint["xi"] < 0).all() and (joint["p_match"] < 0.5).all()


def test_noise_evidence_adds_up_and_zero_evidence_adds_nothing():
    long, short, sims = _two_exposures({"temperature_c": 55.0})
    ev = noise_evidence(sims[2][0], short)
    assert ev.shape == (5, 1 + 4 * 96) and ev.dtype == torch.float64 and torch.isfinite(ev).all() and ev.any()
    assert (ev[0] >= 0).all() and (ev[2] > 0).all() and (ev[3] <= 0).all()  # Σr²/D, Σ1/D, the clipping penalty
    assert set(ev[4].tolist()) == {0.0, 1.0} and ev[4, 0] == 0  # visible in this frame; the metadata's own never
    base = physics_noise_posterior(sims[0][0], long, pool=True)
    assert torch.equal(physics_noise_posterior(sims[0][0], long, pool=True, other_evidence=torch.zeros_like(ev)), base)
    # a frame's evidence given twice is the frame read with twice the bins: it moves the answer, it does not break it
    twice = physics_noise_posterior(sims[0][0], long, pool=True, other_evidence=noise_evidence(sims[0][0], long))
    assert torch.isfinite(twice).all()


def test_an_unreadable_other_exposure_adds_nothing():
    """A black frame (nothing to read) and a textured one give no evidence: the answer is the frame's own."""
    long, short, sims = _two_exposures({"temperature_c": 55.0})
    g = torch.Generator().manual_seed(0)
    texture = (0.5 + 0.2 * torch.randn(16, 1, 128, 128, generator=g)).clamp(0, 1)  # white texture of 50 DN …
    texture = F.avg_pool2d(F.pad(texture, (1, 1, 1, 1), mode="replicate"), 3, stride=1)  # … smoothed: correlated details
    black = torch.zeros(16, 1, 128, 128)
    assert not noise_evidence(black, short).any()
    assert not noise_evidence(texture, short).any()
    est = PhysicsNoiseEstimator()
    alone = est.predict(sims[0][0], long, pool=True)
    joint = est.predict(sims[0][0], long, pool=True, other_exposures=[(black, short), (texture, short)])
    assert joint["exposures_read"] == 0 and torch.equal(joint["sigma"], alone["sigma"])


@pytest.mark.parametrize("dtype", [torch.uint8, torch.float16, torch.bfloat16, torch.float64])
def test_other_exposures_take_the_inputs_predict_takes(dtype):
    long, short, sims = _two_exposures({"white_noise_v_per_rthz": 1.2e-7})
    est = PhysicsNoiseEstimator()
    other = sims[2][0]
    given = (other * 255).round().to(torch.uint8) if dtype == torch.uint8 else other.to(dtype)
    a = est.predict(sims[0][0], long, pool=True, other_exposures=[(other, short)])
    fields = {n: float(getattr(long, n)) for n in FULL_FIELDS} | {"exposure_s": 0.02}  # a dict of fields, as predict takes
    b = est.predict(sims[0][0], long, pool=True, other_exposures=[(given, fields)])
    # bf16 holds 8 significant bits: above 128 DN it rounds a frame to 2 DN steps, noise the other frame then carries
    assert torch.allclose(a["sigma"], b["sigma"], rtol=0.03 if dtype == torch.bfloat16 else 0.01, atol=0.01)


def test_other_exposures_bad_input_is_refused():
    long, short, sims = _two_exposures(None)
    est = PhysicsNoiseEstimator()
    x, y = sims[0][0], sims[2][0]
    with pytest.raises(ValueError, match="pass pool=True"):
        est.predict(x, long, other_exposures=[(y, short)])
    hotter_gain = short.replace(gain_db=torch.tensor([12.0], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"other_exposures\[0\]: gain_db = 12 differs from this frame's 6; .* only in exposure_s"):
        est.predict(x, long, pool=True, other_exposures=[(y, hotter_gain)])
    with pytest.raises(ValueError, match="other_exposures is empty"):
        est.predict(x, long, pool=True, other_exposures=[])
    with pytest.raises(TypeError, match=r"other_exposures\[0\] must be \(images, metadata\)"):
        est.predict(x, long, pool=True, other_exposures=[y])
    with pytest.raises(TypeError, match="sequence of"):
        est.predict(x, long, pool=True, other_exposures=y)
    with pytest.raises(ValueError, match=r"other_exposures\[0\]: reference must hold the same patches"):
        est.predict(x, long, pool=True, other_exposures=[(y, short, y[:2])])
    nan = y.clone()
    nan[0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match=r"other_exposures\[0\]: .*non-finite"):
        est.predict(x, long, pool=True, other_exposures=[(nan, short)])
    with pytest.raises(ValueError, match=r"other_evidence must be the \(5, 385\) evidence"):
        physics_noise_posterior(x, long, pool=True, other_evidence=torch.zeros(4, 385))  # the evidence of an older layout
    bad = torch.zeros(5, 385)
    bad[0, 0] = float("inf")
    with pytest.raises(ValueError, match="other_evidence contains NaN or inf"):
        physics_noise_posterior(x, long, pool=True, other_evidence=bad)
    ev = noise_evidence(y, short)
    assert (ev[[0, 2, 4]] >= 0).all() and (ev[1].square() <= ev[0] * ev[2] * (1 + 1e-9)).all() and ev[2].sum() > 0
    for scaled in (-100 * ev, ev * torch.tensor([[1.0], [5.0], [1.0], [1.0], [1.0]], dtype=ev.dtype)):
        # a negative or impossible sum: it read σ_RN 89.7 DN on 5-DN patches
        with pytest.raises(ValueError, match=r"other_evidence is no sum of noise_evidence: .*rows 0, 2, 4"):
            physics_noise_posterior(x, long, pool=True, other_evidence=scaled)
    with pytest.raises(ValueError, match="other_evidence belongs to one camera"):
        physics_noise_posterior(x[:2], CameraMetadata.preset("EV76C661", batch_size=2), other_evidence=torch.zeros(5, 385))
    with pytest.raises(ValueError, match="noise_evidence reads one camera state"):
        noise_evidence(x[:2], CameraMetadata.preset("EV76C661", batch_size=2))
    with pytest.raises(ValueError, match="is read pooled: pool must be True"):
        physics_noise_posterior(x, long, return_evidence=True)
    with pytest.raises(ValueError, match="other_evidence and return_evidence are not arguments of it"):
        noise_evidence(x, long, other_evidence=torch.zeros(5, 385))


@pytest.mark.parametrize("pair", [False, True])
def test_a_frames_own_evidence_comes_back_from_its_reading_and_can_be_kept(pair):
    """``return_evidence``: the frame's evidence from the same pass (what ``noise_evidence`` reads); handed to a later
    frame as ``other_evidence`` it gives what ``other_exposures`` with that frame gives — a monitor reads each frame
    once."""
    long, short, sims = _two_exposures({"temperature_c": 55.0})
    est = PhysicsNoiseEstimator()
    ref_short = sims[3][0] if pair else None
    first = est.predict(sims[2][0], short, pool=True, reference=ref_short, return_evidence=True)
    if not pair:
        assert torch.equal(first["evidence"], noise_evidence(sims[2][0], short))
    assert first["evidence"].shape == (5, 385) and first["evidence"].any()
    ref = sims[1][0] if pair else None
    kept = est.predict(sims[0][0], long, pool=True, reference=ref, other_evidence=first["evidence"])
    given = est.predict(sims[0][0], long, pool=True, reference=ref,
                        other_exposures=[(sims[2][0], short) if not pair else (sims[2][0], short, ref_short)])
    assert torch.equal(kept["sigma"], given["sigma"]) and torch.equal(kept["xi"], given["xi"])
    with pytest.raises(ValueError, match="pass pool=True"):
        est.predict(sims[0][0], long, return_evidence=True)
    with pytest.raises(TypeError, match="other_evidence must be a tensor"):
        est.predict(sims[0][0], long, pool=True, other_evidence=[0.0])


@pytest.mark.parametrize("batch", [1, 256])
def test_other_exposures_of_one_and_of_256_patches(batch):
    """A frame of one patch and its other exposure of one patch, or 256 beside 256: the split as with 16."""
    long = CameraMetadata.preset("EV76C661", gain_db=6.0, exposure_s=0.2, temperature_c=30.0)
    short = long.replace(exposure_s=torch.tensor([0.02], dtype=torch.float64))
    real = {"white_noise_v_per_rthz": float(long.white_noise_v_per_rthz) * 3.0}
    x, truth = simulate_variant(_ramp(batch), long, (), torch.Generator().manual_seed(1), real)
    y, _ = simulate_variant(_ramp(batch), short, (), torch.Generator().manual_seed(2), real)
    out = PhysicsNoiseEstimator().predict(x, long, pool=True, other_exposures=[(y, short)])
    assert out["sigma"].shape == (batch, 3) and torch.isfinite(out["sigma_std"]).all()
    assert out["exposures_read"] == 1 and out["assessable"].all()
    assert torch.allclose(out["sigma"][:, 1:3], truth[:, 1:3], rtol=0.05)  # DCSN and RN


# --- which kind of mismatch the evidence names ---------------------------------------------------------------------

def test_the_cause_names_a_gain_from_one_frame():
    """A gain 10 dB above the told one moves the signal-dependent and the signal-independent noise together: one
    frame names it (pooled and per patch); each row of ``cause`` sums to 1."""
    told = CameraMetadata.preset("ICX285", gain_db=6.0, exposure_s=0.02, temperature_c=30.0)
    noisy, _ = simulate_variant(_ramp(4), told, (), torch.Generator().manual_seed(2), overrides={"gain_db": 16.0})
    est = PhysicsNoiseEstimator()
    for pool in (False, True):
        cause = est.predict(noisy, told, pool=pool)["cause"]
        assert cause.shape == (4, len(MISMATCH_CAUSES)) and torch.allclose(cause.sum(1), torch.ones(4), atol=1e-5)
        assert (cause[:, MISMATCH_CAUSES.index("gain_db")] > 0.9).all(), cause


@pytest.mark.parametrize("field, factor", [("temperature_c", None), ("white_noise_v_per_rthz", 3.0)])
def test_the_cause_of_a_signal_independent_excess_is_named_by_a_second_exposure_time(field, factor):
    """A hotter sensor and more white noise both add a signal-independent variance: one exposure time cannot tell
    them apart (its cause is shared by the prior and the fields' ranges), two can — the temperature, or the readout
    side (the white-noise density, or noise beyond what its range allows)."""
    long = CameraMetadata.preset("EV76C661", gain_db=6.0, exposure_s=0.2, temperature_c=30.0)
    override = {field: 55.0 if factor is None else float(long.white_noise_v_per_rthz) * factor}
    long, short, sims = _two_exposures(override)
    est = PhysicsNoiseEstimator()
    joint = est.predict(sims[0][0], long, pool=True, other_exposures=[(sims[2][0], short)])["cause"]
    readout = joint[:, MISMATCH_CAUSES.index("white_noise_v_per_rthz")] + joint[:, MISMATCH_CAUSES.index("beyond")]
    if field == "temperature_c":
        assert (joint[:, MISMATCH_CAUSES.index("temperature_c")] > 0.9).all(), joint[0]
    else:
        assert (readout > 0.9).all(), joint[0]
    assert (joint[:, MISMATCH_CAUSES.index("gain_db")] < 0.05).all()


def test_the_cause_is_nan_where_a_patch_is_not_readable():
    meta = CameraMetadata.preset("ICX285", gain_db=12.0, exposure_s=0.02, temperature_c=30.0)
    black = torch.zeros(2, 1, 128, 128)  # no unclipped block: no evidence at all
    out = PhysicsNoiseEstimator().predict(black, meta)
    assert torch.isnan(out["cause"]).all() and not out["assessable"].any()
    matched, _ = simulate_variant(_ramp(2), meta, (), torch.Generator().manual_seed(4))
    cause = PhysicsNoiseEstimator().predict(matched, meta)["cause"]  # readable: a distribution even where it matches
    assert torch.isfinite(cause).all() and torch.allclose(cause.sum(1), torch.ones(2), atol=1e-5)


@pytest.mark.parametrize("gain_db", [0.0, 6.0])
@pytest.mark.parametrize("sigma_dn", [0.0, 0.3, 0.75])
def test_a_patch_far_quieter_than_any_camera_state_is_not_a_confident_match(sigma_dn, gain_db):
    """ICX285 at 0 dB makes σ_Total ≈ 1.54 DN at 128 DN, and no gain, temperature or white-noise density in range
    makes much less: a patch of 0–0.75 DN fits no hypothesis. It is not assessable ("less noise than the metadata
    allow", quiet_z far below −QUIET_Z_LIMIT) — the closed form is still returned — with no stated uncertainty (∞) and
    no cause (NaN), instead of P(match) = 1 with a σ_Total uncertainty of 0.0005 DN (0 dB), or ξ = 0 ± 0 DN (6 dB).
    P(match) stays a probability, of the camera states that fit least badly: no verdict."""
    from camhealth.estimators.physics_noise import LESS_NOISE, QUIET_Z_LIMIT

    meta = CameraMetadata.preset("ICX285", gain_db=gain_db)
    g = torch.Generator().manual_seed(0)
    x = (128.0 + sigma_dn * torch.randn(4, 1, 128, 128, generator=g)).round().clamp(0, 255)
    raw = physics_noise_posterior(x / 255.0, meta)
    assert (raw[:, _COL["quiet_z"]] < -QUIET_Z_LIMIT).all()
    out = PhysicsNoiseEstimator().predict(x, meta, input_range="dn")
    assert not out["assessable"].any() and set(out["reason"]) == {LESS_NOISE}
    assert torch.allclose(out["sigma_total"], raw[:, _COL["total_dn"]]) and (out["xi"] == 0).all()
    assert torch.isinf(out["xi_std"]).all() and torch.isinf(out["sigma_std"]).all() and torch.isnan(out["cause"]).all()
    assert ((out["p_match"] >= 0) & (out["p_match"] <= 1)).all() and not out["follows_image"].any()


@pytest.mark.parametrize("variants", [(), VARIANTS])
def test_matched_patches_fit_their_camera(variants):
    """The same camera's own noise (and another simulator's) reads within the model error of its closed form."""
    from camhealth.estimators.physics_noise import QUIET_Z_LIMIT

    for meta in (CameraMetadata.preset("ICX285", gain_db=0.0), CameraMetadata.preset("EV76C661", gain_db=12.0)):
        noisy, _ = simulate_variant(_levels(), meta, variants, torch.Generator().manual_seed(3))
        raw = physics_noise_posterior(noisy, meta)
        assert (raw[:, _COL["quiet_z"]] > -QUIET_Z_LIMIT / 2).all()
        assert PhysicsNoiseEstimator().predict(noisy, meta)["assessable"].all()


def _overlaid_frame(noiseless_rows: int, seed: int = 0) -> tuple[torch.Tensor, CameraMetadata]:
    """The 20 patches (4 × 5 of 128 px) of an ICX285 frame of a ramp whose top ``noiseless_rows`` rows of patches are
    a noiseless mid-grey overlay (128 DN, no sensor noise at all), and its metadata."""
    meta = CameraMetadata.preset("ICX285")
    ramp = torch.linspace(0.25, 0.75, 640).expand(512, 640).clone().view(1, 1, 512, 640)
    frame = simulate_variant(ramp, meta, ("round8",), torch.Generator().manual_seed(seed))[0][0, 0]
    frame[: 128 * noiseless_rows] = 128.0 / 255.0
    return frame.unfold(0, 128, 128).unfold(1, 128, 128).reshape(-1, 1, 128, 128), meta


@pytest.mark.parametrize("noiseless_rows", [1, 2])
def test_pooled_noiseless_overlay_patches_are_refused_alone_and_left_out(noiseless_rows):
    """Pooled, a quarter or half of the frame a noiseless overlay: those patches are refused as quieter than the
    metadata allow (each read alone) and left out of the frame's evidence, so the camera's own patches read exactly
    what the frame without the overlay reads — instead of every patch being given the frame's answer (the overlay's
    patches a confident closed form) with a fit pulled toward 'quieter'."""
    from camhealth.estimators.physics_noise import LESS_NOISE, QUIET_Z_LIMIT

    patches, meta = _overlaid_frame(noiseless_rows)
    clean, _ = _overlaid_frame(0)
    n = 5 * noiseless_rows
    raw = physics_noise_posterior(patches, meta, pool=True)
    alone = physics_noise_posterior(patches[:n], meta)  # the overlay's patches read one by one
    assert torch.allclose(raw[:n, _COL["quiet_z"]], alone[:, _COL["quiet_z"]], rtol=1e-4)
    assert (raw[:n, _COL["quiet_z"]] < -QUIET_Z_LIMIT).all() and (raw[n:, _COL["quiet_z"]].abs() < 1.0).all()
    # the camera's own patches read as from the frame without the overlay
    rest = physics_noise_posterior(clean[n:], meta, pool=True)
    assert torch.allclose(raw[n:, :7], rest[:, :7], atol=1e-5)
    out = PhysicsNoiseEstimator().predict(patches, meta, pool=True)
    assert out["reason"] == [LESS_NOISE] * n + [""] * (20 - n)
    assert (out["xi"][n:] == 0).all() and (out["p_match"][n:] > 0.99).all()


def test_a_pooled_frame_mostly_noiseless_is_refused_as_a_whole():
    """Three quarters of the frame without sensor noise: the frame as a whole is the quiet one (as a denoised frame
    would be), so every patch is refused — none is given a confident answer pooled with the noiseless ones."""
    from camhealth.estimators.physics_noise import LESS_NOISE

    patches, meta = _overlaid_frame(3)
    out = PhysicsNoiseEstimator().predict(patches, meta, pool=True)
    assert out["reason"] == [LESS_NOISE] * 20
    # per patch, the camera's own patches are what they are
    alone = PhysicsNoiseEstimator().predict(patches, meta)
    assert alone["reason"] == [LESS_NOISE] * 15 + [""] * 5


def test_kept_share_of_both_bounds_stays_positive():
    """Noise as wide as the distance to both bounds keeps a positive share of its variance in the kept blocks (each
    bound's share, multiplied): their summed losses floored it at 1e-3 at 128 DN with 128 DN of noise, where a Monte
    Carlo of four pixels kept inside both bounds leaves 0.29."""
    f = _kept_variance_factor(torch.tensor([128.0, 128.0, 20.0, 128.0]), torch.tensor([128.0, 60.0, 15.0, 10.0]) ** 2)
    assert 0.2 < float(f[0]) < 0.35 and 0.85 < float(f[1]) < 0.9 and 0.6 < float(f[2]) < 0.7 and float(f[3]) == 1.0
    # one bound binding: that bound's share alone, the same near either bound
    near = _kept_variance_factor(torch.tensor([20.0, 235.0]), torch.tensor([15.0**2, 15.0**2]))
    assert torch.isclose(near[0], near[1], atol=1e-6)


@pytest.mark.parametrize("level", [100.0, 128.0, 150.0])
def test_a_noiseless_patch_under_a_noisy_cameras_metadata_is_less_noise_with_the_closed_form(level):
    """A constant patch (a denoised or rendered frame) told EV76C661 at 24 dB / 80 °C / 0.2 s (σ_Total 58 DN): far
    quieter than every camera state, refused as such with the closed form and ξ = 0. It read "noise beyond validated
    range" with ξ = −35 DN (noisier), and a quiet patch refused as quieter kept the image's answer (ξ = +52 DN)."""
    from camhealth.estimators.physics_noise import LESS_NOISE

    meta = CameraMetadata.preset("EV76C661", gain_db=24.0, temperature_c=80.0, exposure_s=0.2)
    x = torch.full((2, 1, 128, 128), level / 255.0)
    x[1] += torch.randn(1, 128, 128, generator=torch.Generator().manual_seed(0)) * 0.3 / 255.0  # 0.3 DN: denoised
    x = (x * 255.0).round() / 255.0
    out = load_estimator(PHYSICS_NOISE_MODEL).predict(x, meta)
    assert out["reason"] == [LESS_NOISE, LESS_NOISE]
    prior = physics_prior_dn(x, meta, clipping=True)[:, 4:8]
    assert torch.allclose(out["sigma_total"], prior[:, 3], atol=1e-3) and torch.allclose(out["sigma"], prior[:, :3], atol=1e-3)
    assert (out["xi"] == 0).all() and not out["follows_image"].any()


@pytest.mark.parametrize("pool", [False, True])
@pytest.mark.parametrize("slope", [1.5, 3.0])
def test_a_steep_ramp_is_read_not_called_textured(slope, pool):
    """A smooth ramp of 1.5–3 DN/px (steeper than the camera's σ ≈ 1.4 DN) is no texture: matched it is assessable and
    the closed form, under an 18 dB gain excess the image is followed and reads noisier (the local plane out of the
    horizontal and vertical details, :func:`~camhealth.estimators.noise_features.plane_free_details`)."""
    told = CameraMetadata.preset("ICX285", gain_db=0.0, exposure_s=0.01, temperature_c=20.0)
    x = torch.arange(128, dtype=torch.float32) * slope
    clean = ((40.0 + x % 160.0) / 255.0).view(1, 1, 1, 128).expand(4, 1, 128, 128).contiguous()
    est = PhysicsNoiseEstimator(settings={"pool": pool})
    matched, _ = simulate_variant(clean, told, (), torch.Generator().manual_seed(5))
    out = est.predict(matched, told)
    prior = physics_prior_dn(matched, told, clipping=True)[:, 4:8]
    assert out["assessable"].all(), out["reason"]
    assert torch.allclose(out["sigma_total"].double(), prior[:, 3].double(), atol=1e-4) and (out["xi"] == 0).all()
    noisier, _ = simulate_variant(clean, told, (), torch.Generator().manual_seed(5), overrides={"gain_db": 18.0})
    out = est.predict(noisier, told)
    truth = ((noisier - clean) * 255).flatten(1).std(1)
    assert out["assessable"].all(), out["reason"]
    assert (out["xi"] < -2.0).all()
    assert torch.allclose(out["sigma_total"], truth, rtol=0.12)


def _camera_frame(told, overrides=None, seed=0):
    from camhealth.data.skimage_photos import load_skimage_photo

    img = load_skimage_photo("camera")
    clean = torch.stack([img[:, 128 * (i // 4):128 * (i // 4) + 128, 128 * (i % 4):128 * (i % 4) + 128] for i in range(16)]).float()
    noisy, _ = simulate_variant(clean, told, (), torch.Generator().manual_seed(seed), overrides=overrides)
    return clean, noisy


def _louder(noisy, loud, seed=9):
    out = noisy.clone()
    for k, (i, extra_dn) in enumerate(loud):
        g = torch.Generator().manual_seed(seed + k)
        out[i] = (out[i] + extra_dn / 255.0 * torch.randn(out[i].shape, generator=g)).clamp(0, 1)
    return out


@pytest.mark.parametrize("where", [0, 3])
@pytest.mark.parametrize("overrides", [None, {"gain_db": 14.0}])
def test_pooled_a_far_noisier_patch_is_read_alone(overrides, where):
    """Pooled over a frame (the photograph 'camera', 16 patches), one patch (the first or another) with 30 DN of extra noise (amp glow, a
    pasted area) is left out of the frame's sums and read alone: it reads its own σ and says noisier, and the other
    patches get the answer the other 15 give pooled without it — the closed form where the metadata are right, the
    14 dB gain excess where they are not (with the loud patch in the sums the excess read 30 % low)."""
    told = CameraMetadata.preset("EV76C661", gain_db=6.0, exposure_s=0.02, temperature_c=30.0)
    clean, noisy = _camera_frame(told, overrides)
    est = PhysicsNoiseEstimator(settings={"pool": True})
    rest = torch.arange(16) != where
    base = est.predict(noisy[rest], told)  # the frame's other 15 patches alone
    loud = _louder(noisy, [(where, 30.0)])
    out = est.predict(loud, told)
    truth = ((loud - clean) * 255).flatten(1).std(1)
    assert float(out["xi"][where]) < -20.0 and out["assessable"][where]
    assert float(out["sigma_total"][where]) == pytest.approx(float(truth[where]), rel=0.05)
    assert torch.allclose(out["sigma_total"][rest], base["sigma_total"], atol=0.01)
    assert torch.allclose(out["xi"][rest], base["xi"], atol=0.01)
    if overrides is None:
        assert (out["xi"][rest] == 0).all()
    else:
        assert (out["xi"][rest] < -1.0).all()


@pytest.mark.parametrize("overrides", [None, {"gain_db": 14.0}])
def test_pooled_a_frame_of_two_noise_levels_is_parted(overrides):
    """Pooled, a frame whose patches carry two noise levels in comparable shares (10 of 16 patches with 20 DN of
    extra noise, like a failing tap of a multi-tap sensor) has no one noise level: the noise-like patches above the
    widest-enough gap between the patches' offsets are read alone, each its own σ (within 10 %), and the rest of the
    frame gets what those patches give pooled without them — the closed form where the metadata are right, the gain
    excess where they are not."""
    told = CameraMetadata.preset("EV76C661", gain_db=6.0, exposure_s=0.02, temperature_c=30.0)
    clean, noisy = _camera_frame(told, overrides)
    est = PhysicsNoiseEstimator(settings={"pool": True})
    loud_ids = torch.arange(16) < 10
    base = est.predict(noisy[~loud_ids], told)  # the frame's other 6 patches alone
    loud = _louder(noisy, [(i, 20.0) for i in range(10)])
    out = est.predict(loud, told)
    truth = ((loud - clean) * 255).flatten(1).std(1)
    assert out["assessable"][loud_ids].all(), out["reason"]
    assert (out["xi"][loud_ids] < -10.0).all()
    assert torch.allclose(out["sigma_total"][loud_ids], truth[loud_ids], rtol=0.1)
    assert torch.allclose(out["sigma_total"][~loud_ids], base["sigma_total"], atol=0.01)
    assert torch.allclose(out["xi"][~loud_ids], base["xi"], atol=0.01)


def test_pooled_several_far_noisier_patches_each_read_alone():
    """Three patches of 16 with 10, 20 and 40 DN of extra noise each read their own σ (within 5 %) and say noisier; the
    other patches keep the closed form."""
    told = CameraMetadata.preset("ICX285", gain_db=12.0, exposure_s=0.05, temperature_c=40.0)
    clean, noisy = _camera_frame(told)
    est = PhysicsNoiseEstimator(settings={"pool": True})
    loud = _louder(noisy, [(1, 10.0), (4, 20.0), (9, 40.0)])
    out = est.predict(loud, told)
    truth = ((loud - clean) * 255).flatten(1).std(1)
    for i in (1, 4, 9):
        assert float(out["xi"][i]) < -5.0
        assert float(out["sigma_total"][i]) == pytest.approx(float(truth[i]), rel=0.05)
    quiet = torch.tensor([i not in (1, 4, 9) for i in range(16)])
    assert (out["xi"][quiet] == 0).all()


@pytest.mark.parametrize("level", [30.0, 225.0])
def test_60_dn_of_noise_near_the_bounds_is_read_not_refused_as_beyond_the_validated_range(level):
    """Gaussian noise of 60 DN, inside the validated 64 DN, on 32 flat patches: near 30 and 225 DN the few blocks the
    clipping leaves read up to 68 DN, which is within three of their sampling standard errors (σ/√(2N), N ≈ 380
    details: 2.3 DN) of 64 DN — read, not refused (they were: 6 and 10 of 32). Beyond doubt it still is: 80 DN of
    noise at 128 DN (read ≈ 77 DN, N ≈ 1 400) is refused on every patch."""
    from camhealth.estimators.physics_noise import BEYOND_VALIDATED

    meta = CameraMetadata.preset("ICX285", gain_db=6.0, exposure_s=0.01, temperature_c=25.0)
    g = torch.Generator().manual_seed(int(level))
    x = (level + 60.0 * torch.randn(32, 1, 128, 128, generator=g)).clamp(0, 255).round() / 255
    out = PhysicsNoiseEstimator().predict(x, meta)
    assert out["assessable"].all(), out["reason"]
    truth = ((x * 255 - level).flatten(1).std(1))
    assert (out["xi"] < 0).all() and ((out["sigma_total"] / truth - 1).abs() < 0.15).all()
    louder = ((128.0 + 80.0 * torch.randn(8, 1, 128, 128, generator=g)).clamp(0, 255).round() / 255)
    assert PhysicsNoiseEstimator().predict(louder, meta)["reason"] == [BEYOND_VALIDATED] * 8


def test_noise_known_to_be_beyond_the_validated_range_is_named_so_before_any_flat_area():
    """The reason says what is known: 200 DN of noise trips the fine-scale check (its σ̂ far above 64 DN) and leaves no
    flat block, and a camera whose own closed form makes 520 DN (every field at its loud end) is beyond the range
    whatever the patch shows; both said "no flat area" (texture or clipping), which hid it. Their per-source σ after
    clipping are the attribution rule's (:func:`~camhealth.physics.clipping.clipped_sigma_dn`), which may exceed the
    clipped total and 127.5 DN, as a Monte Carlo of the rule on a flat scene shows — not assessable either way."""
    from camhealth.physics.clipping import clipped_sigma_dn
    from camhealth.estimators.physics_noise import BEYOND_VALIDATED

    told = CameraMetadata.preset("ICX285", gain_db=6.0, exposure_s=0.01, temperature_c=25.0)
    g = torch.Generator().manual_seed(1)
    x = (128.0 + 200.0 * torch.randn(2, 1, 128, 128, generator=g)).clamp(0, 255).round() / 255
    assert bool(beyond_validated_range(x).all())
    out = PhysicsNoiseEstimator().predict(x, told)
    assert out["reason"] == [BEYOND_VALIDATED] * 2 and not out["assessable"].any()
    loud = CameraMetadata.preset("ICX285", gain_db=24.0, exposure_s=0.2, temperature_c=80.0, dark_fom_na_per_cm2=1.0,
                                 full_well_e=2000.0, pixel_clock_hz=150e6, sense_node_gain_v_per_e=1e-6, reset_factor=1.0,
                                 pixel_size_um=10, white_noise_v_per_rthz=60e-9)
    noisy, _ = simulate_variant(torch.full((2, 1, 128, 128), 0.5), loud, ("round8",), torch.Generator().manual_seed(0))
    assert (physics_prior_dn(noisy, loud)[:, 3] > 500).all()
    out = PhysicsNoiseEstimator().predict(noisy, loud)
    assert out["reason"] == [BEYOND_VALIDATED] * 2 and (out["xi"] == 0).all()
    assert torch.allclose(out["sigma"], physics_prior_dn(noisy, loud, clipping=True)[:, 4:7], atol=1e-3)
    # the attribution: source k keeps n_k·y/n of the clipped noise y; on a flat scene y spans 255 DN (σ ≤ 127.5 DN),
    # a source's share does not (where it outweighs n, the others cancelling part of it)
    sig = (8.9, 300.0, 425.0)
    n_k = [s * torch.randn(2_000_000, generator=g, dtype=torch.float64) for s in sig]
    n = sum(n_k)
    y = (128.0 + n).clamp(0, 255) - 128.0
    want = [(nk * y / n).std().item() for nk in n_k] + [y.std().item()]
    got = clipped_sigma_dn(torch.full((1, 1, 4, 4), 128.0), [torch.tensor(s**2) for s in sig])[0].tolist()
    assert got == pytest.approx(want, rel=0.005) and got[3] <= 127.5 < got[2] and got[1] > got[3]


def _quietest_camera(**overrides) -> CameraMetadata:
    """ICX285 with every field at the quiet end of its range: 0.16 DN at 10 DN, 0.57 DN at 128 DN (photon noise)."""
    quiet = dict(gain_db=0.0, exposure_s=0.001, temperature_c=0.0, dark_fom_na_per_cm2=0.0, full_well_e=100000.0,
                 pixel_clock_hz=8e6, sense_node_gain_v_per_e=5e-6, reset_factor=0.0, pixel_size_um=0.9,
                 white_noise_v_per_rthz=1e-9)
    return CameraMetadata.preset("ICX285", **{**quiet, **overrides})


@pytest.mark.parametrize("level", [3.0, 5.0])
def test_a_matched_quiet_8bit_camera_has_a_flat_area(level):
    """ICX285 as preset makes 0.33–0.38 DN at 3–5 DN: in 8 bit most diagonal details are exactly 0, so their median
    is 0. The metadata-free reference is floored at the rounding's 1/12 DN², so the flat blocks are found — the patch
    is read and is the closed form (it was "no flat area": a reference of 1e-6 DN² called nearly every block
    non-flat)."""
    meta = CameraMetadata.preset("ICX285")
    noisy, _ = simulate_variant(torch.full((8, 1, 128, 128), level / 255), meta, ("round8",), torch.Generator().manual_seed(5))
    out = PhysicsNoiseEstimator().predict(noisy, meta)
    assert out["reason"] == [""] * 8
    assert (out["xi"] == 0).all() and torch.allclose(out["sigma_total"], physics_prior_dn(noisy, meta, clipping=True)[:, 7], atol=1e-4)


@pytest.mark.parametrize("level", [10.0, 30.0])
def test_a_quiet_camera_below_the_quantisation_step_is_named_so_not_less_noise(level):
    """The quietest camera in range makes 0.16–0.28 DN at 10–30 DN: rounding a flat area at a whole DN removes most of
    that noise (at 0.16 DN, 99.8 % of the pixels keep the level), so the matched patch reads far below every camera
    state. Not a denoised image — "noise below the quantisation step", with the closed form (it was "less noise than
    the metadata allow"). A noiseless patch told a camera that makes 1.5 DN is still "less noise"."""
    from camhealth.estimators.physics_noise import BELOW_QUANTISATION, LESS_NOISE, QUANTISATION_SIGMA_DN

    meta = _quietest_camera()
    noisy, _ = simulate_variant(torch.full((4, 1, 128, 128), level / 255), meta, ("round8",), torch.Generator().manual_seed(0))
    raw = physics_noise_posterior(noisy, meta)
    assert (raw[:, _COL["quietest_total_dn"]] < QUANTISATION_SIGMA_DN).all()
    out = PhysicsNoiseEstimator().predict(noisy, meta)
    assert out["reason"] == [BELOW_QUANTISATION] * 4 and (out["xi"] == 0).all()
    assert torch.allclose(out["sigma_total"], physics_prior_dn(noisy, meta, clipping=True)[:, 7], atol=1e-4)
    flat = torch.full((1, 1, 128, 128), 128.0 / 255)
    assert PhysicsNoiseEstimator().predict(flat, CameraMetadata.preset("ICX285", gain_db=0.0))["reason"] == [LESS_NOISE]


@pytest.mark.parametrize("pool", [False, True])
def test_an_empty_batch_gives_every_output_a_full_one_gives(pool):
    """No patches: a table of 0 rows (pooled with the frame's evidence: zeros), and from predict every key a batch of
    patches gives for the same arguments — "evidence" and "exposures_read" included — instead of a RuntimeError
    (cannot reshape a tensor of 0 elements) or a missing key."""
    meta = CameraMetadata.preset("ICX285")
    empty = torch.zeros(0, 1, 128, 128)
    raw = physics_noise_posterior(empty, meta, pool=pool)
    assert raw.shape == (0, len(PHYSICS_NOISE_COLUMNS)) and raw.dtype == torch.float32
    one, _ = simulate_variant(_levels(2), meta, (), torch.Generator().manual_seed(0))
    kwargs = {"pool": True, "return_evidence": True,
              "other_exposures": [(one, CameraMetadata.preset("ICX285", exposure_s=0.05))]} if pool else {}
    out = PhysicsNoiseEstimator().predict(empty, meta, **kwargs)
    full = PhysicsNoiseEstimator().predict(one, meta, **kwargs)
    assert set(out) == set(full)
    for k, v in out.items():
        if isinstance(v, torch.Tensor) and k != "evidence":
            assert v.shape[0] == 0 and v.shape[1:] == full[k].shape[1:] and v.dtype == full[k].dtype, k
    if pool:
        assert out["evidence"].shape == full["evidence"].shape and not out["evidence"].any()
        assert out["exposures_read"] == 1
        assert noise_evidence(empty, meta).shape == full["evidence"].shape


def _pair_fixture(stem: str, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The committed still pair ``tests/estimators/data/{stem}_{noisy,second}.png``: n 128-px patches stacked
    vertically, 8-bit → two n×1×128×128 tensors in [0, 1]."""
    import cv2
    from pathlib import Path

    data = Path(__file__).parent / "data"
    x, y = (torch.from_numpy(cv2.imread(str(data / f"{stem}_{k}.png"), cv2.IMREAD_UNCHANGED)).float().view(n, 1, 128, 128)
            / 255 for k in ("noisy", "second"))
    return x, y


def test_pooled_pair_leaves_bins_below_the_quantisation_step_out_of_the_frame():
    """A still pair of 8-bit frames (6 patches of an independent simulator's frame, every variant, metadata right: a
    random sensor at 3 dB with σ_Total 1.0 DN at mid-grey) whose first patch is dark (17 DN, the metadata's σ 0.38 DN:
    below the quantisation step, where rounding moves the noise by an amount that depends on each level's fraction).
    Pooled, that patch's bins stay out of the frame's sums and the frame reads the closed form; with them it read a
    gain excess (ξ −0.59 DN, P(match) 0.12)."""
    x, y = _pair_fixture("pair_dark_quantised", 6)
    told = CameraMetadata.from_dict({
        "gain_db": 3.0448672771453857, "exposure_s": 0.011217026971280575, "temperature_c": 22.59701156616211,
        "dark_fom_na_per_cm2": 0.566319465637207, "full_well_e": 54695.12109375, "pixel_clock_hz": 119327728.0,
        "sense_node_gain_v_per_e": 1.3891069556848379e-06, "reset_factor": 0.2753300964832306,
        "pixel_size_um": 3.9886929988861084, "is_cmos": 0.0, "white_noise_v_per_rthz": 3.312914387265664e-09})
    prior = physics_prior_dn(x, told, clipping=True)[:, 4:8]
    assert float(prior[0, 3]) < QUANTISATION_SIGMA_DN < float(prior[1:, 3].min())
    out = PhysicsNoiseEstimator(settings={"pool": True}).predict(x, told, reference=y)
    assert (out["xi"] == 0).all() and bool((out["p_match"] > 0.5).all())
    assert torch.allclose(out["sigma_total"], prior[:, 3].float(), atol=1e-3)


def _jpeg(x: torch.Tensor, quality: int) -> torch.Tensor:
    """Each B×1×H×W patch in [0, 1] coded as an 8-bit gray JPEG of ``quality`` (OpenCV) and decoded."""
    import cv2
    import numpy as np

    out = []
    for p in x:
        ok, buf = cv2.imencode(".jpg", (p[0].numpy() * 255.0).round().astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, quality])
        assert ok
        out.append(torch.from_numpy(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255.0))
    return torch.stack(out).unsqueeze(1)


def test_a_jpeg_frame_that_would_contradict_its_metadata_keeps_the_closed_form_and_names_the_codec():
    """ICX285 at 12 dB makes 3.1 DN; coded at quality 95 its noise is no longer Gaussian (the coefficients below the
    codec's steps zeroed, the others rounded to them), and the frame's robust NLF reads less of it: its pooled posterior
    would follow a quieter camera (the ``codec`` column is 1 only there). The codec's block grid is there: the closed
    form, no verdict (ξ 0, uncertainties ∞, cause NaN), "a lossy codec changed the noise", and no evidence for other
    exposure times — also where a noiseless overlay (read alone, not followed) is the frame's first patch. A camera
    noisier than its metadata say is followed uncoded and held through the codec, with row noise on top too."""
    from camhealth.estimators.physics_noise import LOSSY_CODEC

    meta = CameraMetadata.preset("ICX285", gain_db=12.0, exposure_s=0.05, temperature_c=40.0)
    noisy, _ = simulate_variant(_levels(), meta, ("round8",), torch.Generator().manual_seed(1))
    coded = _jpeg(noisy, 95)
    raw = physics_noise_posterior(coded, meta, pool=True)
    assert (raw[:, _COL["codec"]] == 1).all() and (raw[:, _COL["follows_image"]] == 0).all()
    assert torch.allclose(raw[:, :4], physics_prior_dn(coded, meta, clipping=True)[:, 4:8], atol=1e-4)
    assert (raw[:, _COL["xi_dn"]] == 0).all() and torch.isinf(raw[:, _COL["xi_std_dn"]]).all()
    assert torch.isinf(raw[:, _COL["pn_std_dn"]]).all() and torch.isnan(raw[:, _COL["p_cause_gain"]]).all()
    out = PhysicsNoiseEstimator().predict(coded, meta, pool=True)
    assert out["reason"] == [LOSSY_CODEC] * 16 and not out["assessable"].any()
    _, evidence = physics_noise_posterior(coded, meta, pool=True, return_evidence=True)
    assert not evidence.any()  # a coded frame lends no evidence to other exposure times
    # uncoded, the frame is its camera's: the closed form, assessable, nothing tested
    plain = physics_noise_posterior(noisy, meta, pool=True)
    assert (plain[:, _COL["codec"]] == 0).all() and (plain[:, _COL["xi_dn"]] == 0).all()
    # a camera 6 dB noisier than told: uncoded, followed (noisier); through the same codec, whose own quantisation
    # error may read as noise as well, no verdict either
    louder, _ = simulate_variant(_levels(), meta, ("round8",), torch.Generator().manual_seed(1), {"gain_db": 18.0})
    loud = physics_noise_posterior(louder, meta, pool=True)
    assert (loud[:, _COL["follows_image"]] == 1).all() and (loud[:, _COL["xi_dn"]] < -0.5).all()
    loud = physics_noise_posterior(_jpeg(louder, 95), meta, pool=True)
    assert (loud[:, _COL["codec"]] == 1).all() and (loud[:, _COL["xi_dn"]] == 0).all()
    # visible row noise does not bring a verdict back on a coded frame
    rows = torch.randn(16, 1, 128, 1, generator=torch.Generator().manual_seed(5)) * 3.0 / 255
    for pool in (True, False):
        banded = physics_noise_posterior(_jpeg(((louder + rows).clamp(0, 1) * 255).round() / 255, 95), meta, pool=pool)
        held = banded[:, _COL["codec"]] == 1
        assert held.sum() >= 12 and (banded[held, _COL["follows_image"]] == 0).all(), pool
        assert (banded[held, _COL["xi_dn"]] == 0).all() and (banded[held, _COL["p_match"]] > 0).all()
    # a noiseless overlay as the first patch (read alone, not followed): the coded frame still lends no evidence
    overlaid = _jpeg(louder, 95)
    overlaid[0] = 100.0 / 255.0
    raw, evidence = physics_noise_posterior(overlaid, meta, pool=True, return_evidence=True)
    assert raw[0, _COL["codec"]] == 0 and (raw[1:, _COL["codec"]] == 1).all() and not evidence.any()


def test_a_camera_quieter_than_told_without_a_codec_is_followed():
    """The codec rule needs the codec's grid: told 18 dB, the camera at 12 dB, 8-bit and uncoded — the image is read
    (ξ > 0, "cleaner"), per patch and pooled, the grid tested and not found."""
    real = CameraMetadata.preset("ICX285", gain_db=12.0, exposure_s=0.05, temperature_c=40.0)
    told = CameraMetadata.preset("ICX285", gain_db=18.0, exposure_s=0.05, temperature_c=40.0)
    noisy, _ = simulate_variant(_levels(), real, ("round8",), torch.Generator().manual_seed(2))
    for pool in (False, True):
        raw = physics_noise_posterior(noisy, told, pool=pool)
        assert (raw[:, _COL["codec"]] == 0).all() and (raw[:, _COL["follows_image"]] == 1).all(), pool
        assert (raw[:, _COL["xi_dn"]] > 0.5).all()


def test_per_patch_the_codec_rule_holds_the_patches_that_would_be_followed():
    """Per patch each coded patch is tested alone: those that would be followed keep the closed form with the
    codec's reason; the others are read as they would be anyway."""
    from camhealth.estimators.physics_noise import LOSSY_CODEC

    meta = CameraMetadata.preset("EV76C661", gain_db=12.0, exposure_s=0.05, temperature_c=40.0)
    noisy, _ = simulate_variant(_ramp(16), meta, ("round8",), torch.Generator().manual_seed(1))
    coded = _jpeg(noisy, 90)
    raw = physics_noise_posterior(coded, meta)
    held = raw[:, _COL["codec"]] == 1
    assert held.any() and (raw[held, _COL["follows_image"]] == 0).all() and (raw[held, _COL["xi_dn"]] == 0).all()
    prior = physics_prior_dn(coded, meta, clipping=True)[:, 4:8]
    assert torch.allclose(raw[held, :4], prior[held], atol=1e-4)
    out = PhysicsNoiseEstimator().predict(coded, meta)
    assert [r == LOSSY_CODEC for r in out["reason"]] == held.tolist()
    # the rule off (no grid found anywhere): the held patches are followed, the others read exactly as here
    import camhealth.estimators.physics_noise as pn
    from camhealth.estimators.jpeg_quantisation import JpegGrid

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pn, "jpeg_grid", lambda p: JpegGrid(torch.zeros(p.shape[0], dtype=torch.bool), *[None] * 4))
        off = physics_noise_posterior(coded, meta)
    assert (off[held, _COL["follows_image"]] == 1).all() and (off[:, _COL["codec"]] == 0).all()
    assert torch.equal(off[~held, :27].nan_to_num(-1.0), raw[~held, :27].nan_to_num(-1.0))


def test_a_jpeg_pair_that_would_declare_a_mismatch_keeps_the_closed_form():
    """Four patches of dense grass from a JPEG frame of the robustness benchmark (seed 0) and its next exposure, coded
    alike, metadata right. The codec quantises each exposure's texture differently, and here the pair passes the
    stillness tests: read from it, every patch would be about 3 DN noisier than its camera. Their block grid says
    JPEG: the closed form, nothing declared, "a lossy codec changed the noise" — per patch and pooled."""
    from camhealth.estimators.physics_noise import LOSSY_CODEC

    x, y = _pair_fixture("pair_jpeg_grass", 4)
    told = CameraMetadata.from_dict({
        "gain_db": 11.573198318481445, "exposure_s": 0.0026963758282363415, "temperature_c": 9.71207046508789,
        "dark_fom_na_per_cm2": 0.9570000171661377, "full_well_e": 8400.0, "pixel_clock_hz": 90000000.0,
        "sense_node_gain_v_per_e": 4.999999873689376e-06, "reset_factor": 0.0, "pixel_size_um": 5.300000190734863,
        "is_cmos": 1.0, "white_noise_v_per_rthz": 5.900000132896821e-08})
    pair = physics_noise_posterior(x, told, reference=y, scene_allowance_dn=0.0, scene_allowance_min_dn=0.0)
    assert (pair[:, _COL["codec"]] == 1).all() and (pair[:, _COL["xi_dn"]] == 0).all()
    for pool in (False, True):
        out = PhysicsNoiseEstimator().predict(x, told, reference=y, pool=pool)
        assert out["static"].all() and (out["xi"] == 0).all() and out["reason"] == [LOSSY_CODEC] * 4, pool
        assert torch.allclose(out["sigma_total"], physics_prior_dn(x, told, clipping=True)[:, 7].float(), atol=1e-3)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_a_jpeg_in_half_precision_is_read_as_the_same_8bit_frame(dtype):
    """8-bit data held in float16/bfloat16 are off whole DN by up to 0.12/0.25 DN; they used to lose their 8-bit
    quantisation term and skip the JPEG test (ξ −21 DN on a coded patch that float32 holds at the closed form). They
    are restored to k/255 and read exactly as the float32 frame; continuous float16 data are left as they are."""
    from camhealth.estimators.physics_noise import LOSSY_CODEC

    meta = CameraMetadata.preset("EV76C661", gain_db=12.0, exposure_s=0.05, temperature_c=40.0)
    noisy, _ = simulate_variant(_ramp(16), meta, ("round8",), torch.Generator().manual_seed(1))
    coded = _jpeg(noisy, 90)
    est = PhysicsNoiseEstimator()
    ref = est.predict(coded, meta)
    half = est.predict(coded.to(dtype), meta)
    assert LOSSY_CODEC in ref["reason"] and half["reason"] == ref["reason"]
    assert torch.equal(half["sigma_total"], ref["sigma_total"]) and torch.equal(half["xi"], ref["xi"])
    from camhealth._inputs import _to_patches

    assert torch.equal(_to_patches(coded.to(dtype), 128, "auto"), coded)  # whole DN again, exactly
    smooth = torch.linspace(0.1, 0.45, 128 * 128).view(1, 1, 128, 128)  # continuous: not whole DN in float16
    assert torch.equal(_to_patches(smooth.half(), 128, "auto"), smooth.half().float())


@pytest.mark.parametrize("kwargs,match", [
    ({"pool": "False"}, "pool = 'False' must be True or False"),
    ({"eta": "0.1"}, "eta = '0.1' must be a real number"),
    ({"bound_margin": None}, "bound_margin = None must be a real number"),
    ({"grid": 2.5}, "grid = 2.5 must be an integer"),
    ({"bins": True}, "bins = True must be an integer"),
])
def test_posterior_settings_of_the_wrong_type_are_named(kwargs, match):
    x = torch.rand(2, 1, 128, 128, generator=torch.Generator().manual_seed(0))
    with pytest.raises(TypeError, match=match):
        physics_noise_posterior(x, CameraMetadata.preset("ICX285"), **kwargs)


def test_posterior_needs_camera_metadata_and_predict_a_preset_name():
    x = torch.rand(2, 1, 128, 128, generator=torch.Generator().manual_seed(0))
    with pytest.raises(TypeError, match="meta must be a CameraMetadata .* got str; PhysicsNoiseEstimator.predict also takes"):
        physics_noise_posterior(x, "ICX285")
    est = PhysicsNoiseEstimator()
    with pytest.raises(TypeError, match="pool = 'no' must be True or False"):
        est.predict(x, "ICX285", pool="no")
    with pytest.raises(TypeError, match=r"base_preset = 5 must be a preset name \(EV76C661, ICX285\) or None, got int"):
        est.predict(x, {"gain_db": 1.0}, base_preset=5)
