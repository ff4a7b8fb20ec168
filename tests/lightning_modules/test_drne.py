from __future__ import annotations

import math

import pytest
import torch

from camhealth.physics.metadata import CameraMetadata
from datamodules.noise import metadata_matrix
from lightning_modules import NoiseLevelEstimator
from lightning_modules.drne import sigma_map_target_dn


@pytest.mark.parametrize("batch", [1, 4])
def test_map_shape_and_patch_statistics(batch):
    m = NoiseLevelEstimator(patch_size=32).eval()
    x = torch.rand(batch, 1, 32, 32)
    with torch.no_grad():
        out = m(x)
    assert out["sigma_map"].shape == (batch, 1, 32, 32)
    assert (out["sigma_map"] >= 0).all()
    rms = out["sigma_map"].flatten(1).pow(2).mean(1).sqrt()
    assert torch.allclose(out["sigma_total"], rms)
    assert torch.isfinite(out["sigma_median"]).all()


def test_sigma_map_target_closed_form():
    meta = CameraMetadata.preset("ICX285", batch_size=1, gain_db=12.0)
    clean = torch.tensor([0.0, 0.25, 1.0]).view(1, 1, 1, 3)
    target = sigma_map_target_dn(clean, metadata_matrix(meta))
    g = 10 ** (12 / 20)
    const = target[0, 0, 0, 0].item() ** 2  # dark + readout variance (no light)
    for j, i in enumerate([0.0, 0.25, 1.0]):
        expected = math.sqrt(255**2 * g * i / 14000 + const)
        assert target[0, 0, 0, j].item() == pytest.approx(expected, rel=1e-5)


def test_step_uses_map_and_patch_targets(noisy_batch):
    m = NoiseLevelEstimator(patch_size=32, map_weight=0.5)
    loss, est, truth = m._step(noisy_batch)
    assert loss.ndim == 0 and torch.isfinite(loss)
    loss.backward()
    assert all(p.grad is not None for p in m.net.parameters())
    assert est.shape == truth.shape == (4, 1)


@pytest.mark.parametrize("sources", [["photon", "dark", "readout"], ["photon"], ["dark"], ["dark", "readout"]])
def test_map_target_holds_only_the_realised_noise_sources(sources):
    """``noise_sources`` a subset: the RMS of the map target over each patch is the analytic σ of the noise in the
    image (``sigma_expected``), not that of all three sources (['dark']: 7.38 against 2.11 DN before)."""
    from datamodules import NoiseDataModule

    g = torch.Generator().manual_seed(0)
    clean = torch.rand(4, 1, 32, 32, generator=g) * 0.6 + 0.2
    meta = CameraMetadata.preset("ICX285", batch_size=4, gain_db=torch.tensor([0.0, 6.0, 12.0, 24.0]),
                                 temperature_c=60.0, exposure_s=0.2)
    dm = NoiseDataModule(source="deadleaves", source_kwargs={"n_images": 2, "size": (64, 64)}, patch_size=32,
                         noise_sources=sources)
    batch = dm.corrupt_with(clean, meta, meta, noise_seed=1)
    target = sigma_map_target_dn(clean, batch["meta_image_raw"], batch["sigma_expected"])
    rms = target.flatten(1).pow(2).mean(1).sqrt()
    expected = batch["sigma_expected"].pow(2).sum(1).sqrt()
    assert torch.allclose(rms, expected, rtol=0.01), (rms, expected)
    # the training step uses the same target: with all sources it is the one without sigma_expected
    if len(sources) == 3:
        assert torch.equal(target, sigma_map_target_dn(clean, batch["meta_image_raw"]))


def test_step_map_target_follows_the_batch_noise_sources(monkeypatch):
    """``_step`` passes the batch's ``sigma_expected``: a photon-only batch gives a map target without the
    dark-current and readout terms."""
    from datamodules import NoiseDataModule
    from lightning_modules import drne

    g = torch.Generator().manual_seed(0)
    clean = torch.rand(2, 1, 32, 32, generator=g) * 0.6 + 0.2
    meta = CameraMetadata.preset("ICX285", batch_size=2, gain_db=12.0, temperature_c=60.0, exposure_s=0.2)
    dm = NoiseDataModule(source="deadleaves", source_kwargs={"n_images": 2, "size": (64, 64)}, patch_size=32,
                         noise_sources=["dark"])
    batch = dm.corrupt_with(clean, meta, meta, noise_seed=1)
    batch["clean"] = clean
    seen = []
    real = drne.sigma_map_target_dn
    monkeypatch.setattr(drne, "sigma_map_target_dn", lambda *a, **k: seen.append(real(*a, **k)) or seen[-1])
    NoiseLevelEstimator(patch_size=32)._step(batch)
    rms = seen[0].flatten(1).pow(2).mean(1).sqrt()
    assert torch.allclose(rms, batch["sigma_expected"].pow(2).sum(1).sqrt(), rtol=0.01)


@pytest.mark.parametrize("patch_size, dilations, large", [(128, [64, 64, 64], 64), (128, [1, 2, 200], 200),
                                                          (16, [64], 64), (32, [1, 16], 16)])
def test_dilations_that_reach_only_the_padding_are_refused(patch_size, dilations, large):
    """``dilations: [64, 64, 64]`` at 128 px was accepted: the blocks run at 64×64 px, so the eight outer taps of every
    dilated convolution saw only zero padding (the output was that of the centre taps alone)."""
    half = patch_size // 2
    with pytest.raises(ValueError, match=rf"dilations = \({', '.join(map(str, dilations))},?\): {large} is too large for "
                                         rf"patch_size = {patch_size}: the residual blocks run at half resolution "
                                         rf"\({half}×{half} px\).*each dilation must be an integer in \[1, {half - 1}\]"):
        NoiseLevelEstimator(patch_size=patch_size, dilations=dilations)
    assert NoiseLevelEstimator(patch_size=patch_size, dilations=[half - 1]).net.body[0] is not None


def test_the_largest_allowed_dilation_reaches_the_image_with_its_outer_taps():
    m = NoiseLevelEstimator(patch_size=32, dilations=[15]).eval()
    x = torch.rand(1, 1, 32, 32)
    with torch.no_grad():
        before = m(x)["sigma_map"]
    convs = [c for c in m.net.body.modules() if isinstance(c, torch.nn.Conv2d) and c.dilation == (15, 15)]
    assert convs
    with torch.no_grad():
        for c in convs:
            centre = c.weight[..., 1, 1].clone()
            c.weight.zero_()
            c.weight[..., 1, 1] = centre
        after = m(x)["sigma_map"]
    assert not torch.equal(before, after)  # the outer taps matter at dilation 15 < 16
