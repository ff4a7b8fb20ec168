"""The noise-source network (Min- and w/o-Meta): shapes, metadata use, precision, training, hard patches."""

from __future__ import annotations

import pytest
import torch

from lightning_modules import NoiseSourceEstimator, ThesisNoiseNet
from lightning_modules.blocks import count_flops


@pytest.mark.parametrize("metadata_set", ["none", "minimal"])
@pytest.mark.parametrize("batch", [1, 3])
def test_outputs_shape_finite(metadata_set, batch, meta_raw):
    torch.manual_seed(0)
    m = NoiseSourceEstimator(patch_size=32, metadata_set=metadata_set).eval()
    x = torch.rand(batch, 1, 32, 32)
    with torch.no_grad():
        out = m(x, meta_raw[:1].expand(batch, -1))
    assert out["sigma"].shape == (batch, 3) and out["xi"].shape == (batch,) and out["sigma_total"].shape == (batch,)
    assert all(torch.isfinite(v).all() for v in out.values())
    assert (out["sigma"] >= 0).all()
    assert torch.allclose(out["sigma_total"], out["sigma"].pow(2).sum(1).sqrt(), rtol=1e-5)  # Eq. 4.2


def test_full_metadata_is_the_closed_form_and_metadata_is_required():
    with pytest.raises(ValueError, match="noise_source_full"):
        NoiseSourceEstimator(metadata_set="full")
    with pytest.raises(ValueError, match="metadata_set"):
        NoiseSourceEstimator(metadata_set="some")
    with pytest.raises(TypeError):
        NoiseSourceEstimator(physics_prior=True)  # retired option: not an argument any more
    m = NoiseSourceEstimator(patch_size=32, metadata_set="minimal")
    with pytest.raises(ValueError, match="pass metadata"):
        m(torch.rand(1, 1, 32, 32), None)


def test_branches_read_only_their_metadata(meta_raw):
    """Min-Meta reads gain, exposure and temperature, not the full-only fields; w/o-Meta ignores all metadata."""
    torch.manual_seed(1)
    x = torch.rand(3, 1, 32, 32)
    changed = meta_raw.clone()
    changed[:, 4] = 50_000.0  # full well: not minimal metadata
    gain = meta_raw.clone()
    gain[:, 0] = 3.0
    for ms in ("none", "minimal"):
        m = NoiseSourceEstimator(patch_size=32, metadata_set=ms).eval()
        with torch.no_grad():
            a, b, c = m(x, meta_raw), m(x, changed), m(x, gain)
        assert torch.equal(a["sigma"], b["sigma"]) and torch.equal(a["xi"], b["xi"])
        assert torch.equal(a["sigma"], c["sigma"]) == (ms == "none")


@pytest.mark.parametrize("fill", [0.0, 1.0])
def test_black_and_saturated_patches_are_finite(fill, meta_raw):
    m = NoiseSourceEstimator(patch_size=32).eval()
    with torch.no_grad():
        out = m(torch.full((3, 1, 32, 32), fill), meta_raw)
    assert all(torch.isfinite(v).all() for v in out.values())


def test_bf16_autocast_agrees_with_fp32(meta_raw):
    torch.manual_seed(2)
    m = NoiseSourceEstimator(patch_size=32).eval()
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
    m = NoiseSourceEstimator(patch_size=32, lr=3e-3)
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


def test_all_zero_loss_weights_are_refused():
    """The loss is the weighted mean of the terms: weights that are all 0 made it 0/0 = NaN at the first step."""
    zero = {k: 0.0 for k in NoiseSourceEstimator.metric_names}
    with pytest.raises(ValueError, match=r"loss_weights = .*at least one loss term needs a weight > 0"):
        NoiseSourceEstimator(patch_size=32, loss_weights=zero)
    # one term left: a finite loss of that term alone
    m = NoiseSourceEstimator(patch_size=32, loss_weights={**zero, "total": 2.0})
    est, truth = torch.rand(4, 5), torch.rand(4, 5)
    loss, terms = m._loss(est, truth)
    assert torch.isfinite(loss) and loss.item() == pytest.approx(terms["total"].item())


@pytest.mark.parametrize("size", [0, 40, 100])
def test_patch_size_must_be_a_multiple_of_16(size):
    with pytest.raises(ValueError, match="multiple of 16"):
        NoiseSourceEstimator(patch_size=size)


def test_trunk_activity_of_a_fresh_network():
    """The model card's trunk check: a fresh trunk's pooled features vary with the image."""
    torch.manual_seed(0)
    assert NoiseSourceEstimator().net.trunk_activity() > 0.5
