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
    m = NoiseLevelEstimator().eval()
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
    m = NoiseLevelEstimator(map_weight=0.5)
    loss, est, truth = m._step(noisy_batch)
    assert loss.ndim == 0 and torch.isfinite(loss)
    loss.backward()
    assert all(p.grad is not None for p in m.net.parameters())
    assert est.shape == truth.shape == (4, 1)
