from __future__ import annotations

import pytest
import torch

from lightning_modules import NoiseSourceEstimator, ThesisNoiseNet
from lightning_modules.blocks import count_flops


@pytest.mark.parametrize("metadata_set,prior", [("none", False), ("minimal", False), ("full", False), ("full", True)])
@pytest.mark.parametrize("batch", [1, 3])
def test_outputs_shape_finite(metadata_set, prior, batch, meta_raw):
    torch.manual_seed(0)
    m = NoiseSourceEstimator(metadata_set=metadata_set, physics_prior=prior).eval()
    x = torch.rand(batch, 1, 32, 32)
    with torch.no_grad():
        out = m(x, meta_raw[:1].expand(batch, -1))
    assert out["sigma"].shape == (batch, 3) and out["xi"].shape == (batch,) and out["sigma_total"].shape == (batch,)
    assert all(torch.isfinite(v).all() for v in out.values())
    assert (out["sigma"] >= 0).all()


def test_untrained_hybrid_is_the_noise_model_scaled_to_the_image(meta_raw):
    """Zero-initialised output layers: σ̂_s = σ_s(M)·(σ̂_MAD + 0.1)/(σ_Model(M) + 0.1) — the physics split
    of the sources, scaled to the noise level the image shows; ξ̂ = σ_Model(M) − that total."""
    from camhealth.estimators.noise_features import image_statistics

    m = NoiseSourceEstimator(metadata_set="full", physics_prior=True).eval()
    g = torch.Generator().manual_seed(0)
    x = (0.5 + 4 / 255 * torch.randn(3, 1, 64, 64, generator=g)).clamp(0, 1)
    with torch.no_grad():
        out = m(x, meta_raw)
    prior = out["prior"]
    scale = (image_statistics(x)[:, 5] + 0.1) / (prior[:, 3] + 0.1)
    assert torch.allclose(out["sigma"], prior[:, :3] * scale[:, None], rtol=1e-4)
    assert torch.allclose(out["xi"], prior[:, 3] * (1 - scale), rtol=1e-4, atol=1e-4)
    # the ratios between the sources are exactly the physics
    assert torch.allclose(out["sigma"][:, 1] / out["sigma"][:, 0], prior[:, 1] / prior[:, 0], rtol=1e-4)


def test_untrained_hybrid_anchored_at_the_metadata_is_the_noise_model(meta_raw):
    """prior_anchor='metadata': zero-initialised output layers give the closed-form σ per source exactly and
    ξ̂ = 0, whatever the image shows (texture cannot move the starting point)."""
    m = NoiseSourceEstimator(metadata_set="full", physics_prior=True, prior_anchor="metadata").eval()
    x = torch.rand(3, 1, 64, 64, generator=torch.Generator().manual_seed(1))  # strong texture
    with torch.no_grad():
        out = m(x, meta_raw)
    assert torch.allclose(out["sigma"], out["prior"][:, :3], rtol=1e-5)
    assert torch.allclose(out["xi"], torch.zeros(3), atol=1e-5)
    with pytest.raises(ValueError, match="prior_anchor"):
        NoiseSourceEstimator(prior_anchor="texture")


def test_prior_needs_full_metadata_and_metadata_is_required():
    with pytest.raises(ValueError, match="physics_prior needs metadata_set 'full'"):
        NoiseSourceEstimator(metadata_set="minimal", physics_prior=True)
    with pytest.raises(ValueError, match="metadata_set"):
        NoiseSourceEstimator(metadata_set="some", physics_prior=False)
    m = NoiseSourceEstimator(metadata_set="minimal", physics_prior=False)
    with pytest.raises(ValueError, match="pass metadata"):
        m(torch.rand(1, 1, 32, 32), None)


def test_branches_read_only_their_metadata(meta_raw):
    """Min-Meta ignores the full-only fields; w/o-Meta ignores all metadata."""
    torch.manual_seed(1)
    x = torch.rand(3, 1, 32, 32)
    changed = meta_raw.clone()
    changed[:, 4] = 50_000.0  # full well: not minimal metadata
    for ms in ("none", "minimal"):
        m = NoiseSourceEstimator(metadata_set=ms, physics_prior=False).eval()
        with torch.no_grad():
            a, b = m(x, meta_raw), m(x, changed)
        assert torch.equal(a["sigma"], b["sigma"]) and torch.equal(a["xi"], b["xi"])
    m = NoiseSourceEstimator(metadata_set="full", physics_prior=False).eval()
    with torch.no_grad():
        assert not torch.equal(m(x, meta_raw)["sigma"], m(x, changed)["sigma"])


@pytest.mark.parametrize("fill", [0.0, 1.0])
def test_black_and_saturated_patches_are_finite(fill, meta_raw):
    m = NoiseSourceEstimator().eval()
    with torch.no_grad():
        out = m(torch.full((3, 1, 32, 32), fill), meta_raw)
    assert all(torch.isfinite(v).all() for v in out.values())


def test_bf16_autocast_agrees_with_fp32(meta_raw):
    torch.manual_seed(2)
    m = NoiseSourceEstimator(physics_prior=False).eval()
    x = torch.rand(3, 1, 32, 32)
    with torch.no_grad():
        ref = m(x, meta_raw)["sigma"]
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = m(x, meta_raw)["sigma"]
    assert torch.allclose(low.float(), ref, rtol=0.05, atol=0.05)


def test_ten_times_fewer_flops_than_thesis_trunk():
    m = NoiseSourceEstimator()
    ours = count_flops(m.net, *m.export_inputs(1))
    thesis = count_flops(ThesisNoiseNet(), torch.rand(1, 1, 128, 128))
    assert thesis > 15e9
    assert ours * 10 <= thesis


def test_training_steps_reduce_the_loss(noisy_batch):
    torch.manual_seed(0)
    m = NoiseSourceEstimator(physics_prior=False, lr=3e-3)
    opt = torch.optim.Adam(m.parameters(), lr=3e-3)
    losses = []
    for _ in range(30):
        est, truth, _ = m._estimates_and_truth(noisy_batch)
        loss, _ = m._loss(est, truth)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert all(torch.isfinite(torch.tensor(losses)))
    assert min(losses[-5:]) < 0.5 * losses[0]


def test_loss_weights_are_checked():
    with pytest.raises(ValueError, match="unknown key"):
        NoiseSourceEstimator(loss_weights={"photon": 1.0})


@pytest.mark.parametrize("size", [0, 40, 100])
def test_patch_size_must_be_a_multiple_of_16(size):
    with pytest.raises(ValueError, match="multiple of 16"):
        NoiseSourceEstimator(patch_size=size)


def test_total_head_learns_a_clipping_correction_of_the_quadrature_sum(meta_raw):
    """The total head (total_branch) starts at √(Σ σ̂_s²) and can learn the realised total after clipping,
    which is smaller (tests/physics: ≈ 0.8 × on half-clipped patches); here trained alone towards 0.8 ×."""
    torch.manual_seed(0)
    m = NoiseSourceEstimator(metadata_set="full", physics_prior=True, prior_anchor="metadata").train()
    g = torch.Generator().manual_seed(0)
    x = torch.rand(8, 1, 32, 32, generator=g)
    meta = meta_raw[:1].expand(8, -1)
    with torch.no_grad():
        out0 = m(x, meta)
    quad0 = out0["sigma"].pow(2).sum(1).sqrt()
    assert torch.allclose(out0["sigma_total"], quad0, rtol=1e-5)  # zero-initialised: Eq. 4.2 exactly
    opt = torch.optim.Adam(m.net.total_head.parameters(), lr=1e-2)
    for _ in range(60):
        opt.zero_grad()
        loss = (m(x, meta)["sigma_total"] / quad0 - 0.8).pow(2).mean()
        loss.backward()
        opt.step()
    with torch.no_grad():
        out = m(x, meta)
    assert torch.allclose(out["sigma"], out0["sigma"])  # only the head moved
    assert torch.allclose(out["sigma_total"] / quad0, torch.full((8,), 0.8), atol=0.02)


def test_without_the_total_head_the_network_has_four_outputs(meta_raw):
    m = NoiseSourceEstimator(total_branch=False).eval()
    assert not hasattr(m.net, "total_head")
    with torch.no_grad():
        raw = m.net(*m.network_inputs(torch.rand(2, 1, 32, 32), meta_raw[:1].expand(2, -1)))
    assert raw.shape == (2, 4)


def test_branch_inputs_all_lets_every_branch_read_every_field(meta_raw):
    """``own``: the DCSN branch ignores the white-noise density (a readout field); ``all``: it reads it."""
    torch.manual_seed(5)
    x = torch.rand(3, 1, 32, 32)
    changed = meta_raw.clone()
    changed[:, 10] = 5e-8  # white noise W
    for inputs, moves in (("own", False), ("all", True)):
        m = NoiseSourceEstimator(physics_prior=False, branch_inputs=inputs).eval()
        with torch.no_grad():
            a, b = m(x, meta_raw)["sigma"][:, 1], m(x, changed)["sigma"][:, 1]
        assert (not torch.equal(a, b)) is moves
    with pytest.raises(ValueError, match="branch_inputs"):
        NoiseSourceEstimator(branch_inputs="some")


@pytest.mark.parametrize("inputs,nlf,fit", [("all", False, False), ("own", True, False), ("all", True, False), ("own", False, True)])
def test_state_from_a_network_that_reads_less_starts_as_that_network(inputs, nlf, fit):
    torch.manual_seed(6)
    src = NoiseSourceEstimator(patch_size=32, prior_anchor="metadata", total_branch=False)
    with torch.no_grad():
        for p in src.net.parameters():
            p.add_(0.02 * torch.randn_like(p))
    dst = NoiseSourceEstimator(
        patch_size=32, prior_anchor="metadata", branch_inputs=inputs, nlf_statistics=nlf, noise_fit_statistics=fit,
    )
    dst.net.load_state_dict(dst.net.state_from(src.net))
    g = torch.Generator().manual_seed(0)
    image, meta, prior = torch.rand(4, 1, 32, 32, generator=g), torch.rand(4, 11, generator=g), torch.rand(4, 4, generator=g) * 5
    if fit:  # the fit columns follow the closed-form σ; src reads only the first four
        from camhealth.estimators.noise_features import NOISE_FIT_STATISTICS

        prior = torch.cat([prior, torch.randn(4, len(NOISE_FIT_STATISTICS), generator=g)], 1)
        assert dst.net.prior_width == 4 + len(NOISE_FIT_STATISTICS)
    with torch.no_grad():
        old, new = src.net.eval()(image, meta, prior), dst.net.eval()(image, meta, prior)
    assert torch.equal(new[:, :4], old)
    assert torch.allclose(new[:, 4], old[:, :3].pow(2).sum(1).sqrt(), rtol=1e-5)
    with pytest.raises(ValueError, match="reads inputs this network does not"):
        src.net.state_from(dst.net)  # dropping inputs would change the function


def test_a_dead_trunk_is_found_and_revived_without_changing_the_outputs(meta_raw):
    """A trunk whose last ReLUs are off for every input gives constant features (activity 0); revive_trunk folds
    them into the branches' biases and re-initialises the trunk: same outputs, a live trunk."""
    torch.manual_seed(7)
    m = NoiseSourceEstimator(patch_size=32).eval()
    with torch.no_grad():
        for p in m.net.branches.parameters():
            p.add_(0.02 * torch.randn_like(p))
        for p in m.net.total_head.parameters():
            p.add_(0.02 * torch.randn_like(p))
    assert m.net.trunk_activity() > 0.5  # a fresh trunk is alive
    with pytest.raises(ValueError, match="alive"):
        m.net.revive_trunk()
    last = m.net.trunk.stages[-1]
    with torch.no_grad():  # kill it: the last block's output is ReLU(y + shortcut) with a large negative bias
        last.conv2.bias.fill_(-1e3)
        last.shortcut.bias.fill_(-1e3)
    assert m.net.trunk_activity() == 0.0
    x = torch.rand(5, 1, 32, 32)
    with torch.no_grad():
        before = m(x, meta_raw[:1].expand(5, -1))
        m.net.revive_trunk(seed=1)
        after = m(x, meta_raw[:1].expand(5, -1))
    for k in ("sigma", "sigma_total", "xi"):
        assert torch.allclose(after[k], before[k], rtol=1e-5, atol=1e-6), k
    assert m.net.trunk_activity() > 0.5


def test_leaky_trunk_has_the_same_parameters_and_is_checked():
    relu, leaky = NoiseSourceEstimator(patch_size=32), NoiseSourceEstimator(patch_size=32, trunk_activation="leaky_relu")
    assert list(relu.net.state_dict()) == list(leaky.net.state_dict())
    assert any(isinstance(m, torch.nn.LeakyReLU) for m in leaky.net.trunk.modules())
    assert not any(isinstance(m, torch.nn.ReLU) for m in leaky.net.trunk.modules())
    with pytest.raises(ValueError, match="trunk_activation"):
        NoiseSourceEstimator(trunk_activation="gelu")


def test_prior_clipping_starts_from_the_clipped_model(meta_raw):
    """prior_clipping: zero-initialised branches give the closed-form σ *after clipping* per source and the
    clipped model total; ξ̂ stays anchored at the unclipped model total (its label's definition)."""
    m = NoiseSourceEstimator(metadata_set="full", physics_prior=True, prior_anchor="metadata", prior_clipping=True).eval()
    x = torch.full((3, 1, 64, 64), 0.5)
    x[:, :, :, :32] = 0.0  # half black
    x = (x + 0.02 * torch.randn(x.shape, generator=torch.Generator().manual_seed(2))).clamp(0, 1)
    with torch.no_grad():
        out = m(x, meta_raw)
    prior = out["prior"]
    assert prior.shape == (3, 8)
    assert torch.allclose(out["sigma"], prior[:, 4:7], rtol=1e-5)
    assert torch.allclose(out["sigma_total"], prior[:, 7], rtol=1e-4)
    assert torch.allclose(out["xi"], torch.zeros(3), atol=1e-5)
    assert (prior[:, 4:7] < prior[:, :3]).all()  # half the patch clips
    with pytest.raises(ValueError, match="prior_clipping needs physics_prior"):
        NoiseSourceEstimator(metadata_set="full", physics_prior=False, prior_clipping=True)


def test_noise_fit_statistics_reach_the_branches_and_need_the_prior(meta_raw):
    m = NoiseSourceEstimator(metadata_set="full", physics_prior=True, prior_anchor="metadata", noise_fit_statistics=True).eval()
    x = (0.4 + 3 / 255 * torch.randn(3, 1, 64, 64, generator=torch.Generator().manual_seed(4))).clamp(0, 1)
    with torch.no_grad():
        for branch in m.net.branches:  # move the zero-initialised outputs so the inputs matter
            branch[-1].weight.add_(0.1)
        out = m(x, meta_raw)
        prior = out["prior"].clone()
        prior[:, 4] += 1.0  # another signal-independent fit (the first fit column) changes the estimate
        moved = m.net(x, m.network_inputs(x, meta_raw)[1], prior)
    assert out["prior"].shape == (3, m.net.prior_width) and m.net.prior_width == 10
    assert not torch.allclose(moved[:, :3], out["sigma"])
    with pytest.raises(ValueError, match="noise_fit_statistics needs physics_prior"):
        NoiseSourceEstimator(metadata_set="full", physics_prior=False, noise_fit_statistics=True)


def test_mismatch_posterior_blends_each_output_by_the_learned_trust(meta_raw):
    """mismatch_posterior: ten more prior columns (the posterior's σ, probabilities and details used); each output is
    the network's own estimate moved toward the posterior's by λ: log σ̂ = log σ̂_own + λ·(log σ_post − log σ̂_own),
    λ = sigmoid(−3) at the start, the posterior's σ with full trust, and the network's own where the posterior
    abstains (too few details: a saturated patch)."""
    from camhealth.estimators.mismatch_posterior import MISMATCH_POSTERIOR

    m = NoiseSourceEstimator(metadata_set="full", physics_prior=True, prior_anchor="metadata", prior_clipping=True, mismatch_posterior=True).eval()
    g = torch.Generator().manual_seed(4)
    x = (0.4 + 6 / 255 * torch.randn(3, 1, 64, 64, generator=g)).clamp(0, 1)  # noisier than most metadata say
    x[2] = 1.0  # saturated: the posterior abstains
    with torch.no_grad():
        out = m(x, meta_raw)
    prior = out["prior"]
    assert prior.shape == (3, m.net.prior_width) and m.net.prior_width == 8 + len(MISMATCH_POSTERIOR)
    post, clipped = prior[:, 8:11], prior[:, 4:7]
    assert prior[2, 17] == 0 and (prior[:2, 17] > 32).all()
    lam = torch.sigmoid(torch.tensor(-3.0))
    own = clipped  # zero-initialised branches: the network's own estimate is the clipped closed form
    assert torch.allclose(out["sigma"][:2], own[:2] * ((post[:2] + 1e-6) / (own[:2] + 1e-6)) ** lam, rtol=1e-4)
    assert torch.allclose(out["sigma"][2], own[2], rtol=1e-5, atol=1e-6)
    with torch.no_grad():
        m.net.trust_head[-1].bias.fill_(30.0)  # full trust
        for branch in m.net.branches:  # an own estimate that differs from the closed form
            branch[-1].bias.fill_(0.3)
        trusted = m(x, meta_raw)
    assert torch.allclose(trusted["sigma"][:2], post[:2], rtol=1e-4, atol=1e-3)
    assert torch.allclose(trusted["xi"][:2], prior[:2, 3] - prior[:2, 12], rtol=1e-4, atol=1e-3)
    own_delta = 5.0 * torch.tanh(torch.tensor(0.3 / 5.0))  # the bounded log-correction of the branches
    assert torch.allclose(trusted["sigma"][2], own[2] * torch.exp(own_delta), rtol=1e-4)  # abstained: its own
    with pytest.raises(ValueError, match="mismatch_posterior needs prior_clipping"):
        NoiseSourceEstimator(metadata_set="full", physics_prior=True, mismatch_posterior=True)


def test_state_from_into_a_posterior_network_starts_near_the_source():
    """A file without the posterior carried into a network with it: the branches read what they read before and the
    trust head starts at its initial bias, so with the trust switched off (λ → 0) the outputs are the file's exactly."""
    torch.manual_seed(6)
    src = NoiseSourceEstimator(patch_size=32, prior_anchor="metadata", prior_clipping=True, noise_fit_statistics=True)
    with torch.no_grad():
        for p in src.net.parameters():
            p.add_(0.02 * torch.randn_like(p))
    dst = NoiseSourceEstimator(patch_size=32, prior_anchor="metadata", prior_clipping=True, noise_fit_statistics=True, mismatch_posterior=True)
    dst.net.load_state_dict(dst.net.state_from(src.net))
    g = torch.Generator().manual_seed(0)
    image, meta = torch.rand(4, 1, 32, 32, generator=g), torch.rand(4, 11, generator=g)
    prior = torch.cat([torch.rand(4, 8, generator=g) * 5, torch.randn(4, 6, generator=g), torch.rand(4, 11, generator=g) * 50], 1)
    with torch.no_grad():
        dst.net.trust_head[-1].bias.fill_(-60.0)
        old, new = src.net.eval()(image, meta, prior[:, :14]), dst.net.eval()(image, meta, prior)
    assert torch.allclose(new, old, rtol=1e-6, atol=1e-6)


def test_train_only_freezes_everything_else():
    m = NoiseSourceEstimator(patch_size=32, prior_anchor="metadata", prior_clipping=True, mismatch_posterior=True, train_only=["trust_head"])
    trainable = {n for n, p in m.net.named_parameters() if p.requires_grad}
    assert trainable and all(n.startswith("trust_head.") for n in trainable)
    opt = m.configure_optimizers()
    opt = opt["optimizer"] if isinstance(opt, dict) else opt
    assert sum(p.numel() for g in opt.param_groups for p in g["params"]) == sum(p.numel() for p in m.net.trust_head.parameters())
    with pytest.raises(ValueError, match=r"train_only \['trunk_head'\] match no parameter.*trust_head"):
        NoiseSourceEstimator(patch_size=32, prior_clipping=True, mismatch_posterior=True, train_only=["trunk_head"])
