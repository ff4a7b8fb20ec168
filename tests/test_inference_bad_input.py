"""The shipped estimators of camhealth.inference on input beyond what they were validated on: patches whose noise
lies beyond the validated range are refused by the MTF network too, not answered with an error bar that no longer
holds."""

from __future__ import annotations

import pytest
import torch

from camhealth import load_estimator
from camhealth.data import dead_leaves
from camhealth.estimators.physics_noise import BEYOND_VALIDATED


@pytest.fixture(scope="module")
def mtf():
    return load_estimator("mtf")


@pytest.fixture(scope="module")
def scenes():
    """8 dead-leaves patches of 192 px with strong edges (contrast 1): assessable for blur when clean."""
    return torch.stack([dead_leaves(192, seed=i, r_min=4.0, supersample=2, contrast=1.0) for i in range(8)])


def test_the_mtf_network_refuses_noise_beyond_the_validated_range(mtf, scenes):
    """100 DN of white noise on edge scenes: every patch was assessable, its MTF 0.15 off the clean patch's on average
    while mtf_std stated 0.076 (28 % of the values beyond two of it; its error table was measured with at most 10 DN
    of noise). Now each is refused with the noise estimators' reason."""
    g = torch.Generator().manual_seed(5)
    x = (scenes + 100 / 255 * torch.randn(scenes.shape, generator=g)).clamp(0, 1)
    out = mtf.predict(x)
    assert not out["assessable"].any()
    assert out["reason"] == [BEYOND_VALIDATED] * 8
    assert torch.isfinite(out["mtf"]).all() and torch.isfinite(out["mtf_std"]).all()  # numbers all the same (not trusted)


@pytest.mark.parametrize("views", [1, 4])
def test_the_mtf_network_keeps_patches_within_the_validated_range(mtf, scenes, views):
    """5 and 40 DN of noise leave the same patches assessable as before, with the same numbers."""
    g = torch.Generator().manual_seed(6)
    for sigma in (5.0, 40.0):
        x = (scenes + sigma / 255 * torch.randn(scenes.shape, generator=g)).clamp(0, 1)
        out = mtf.predict(x, views=views)
        assert out["assessable"].all() and out["reason"] == [""] * 8, sigma
