"""Shared images for the estimator tests: flat and textured (smooth dead leaves) clean patches."""

from __future__ import annotations

import pytest
import torch

from camhealth.data import dead_leaves


@pytest.fixture(autouse=True)
def _one_thread():
    """Small-tensor work: one torch thread avoids OpenMP stalls on a shared 2-core machine."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def textured() -> torch.Tensor:
    """4 dead-leaves patches 128×128 (r_min 8 px, anti-aliased, contrast 0.5): textured but not busy."""
    return torch.stack([dead_leaves(128, seed=i, r_min=8.0, supersample=4, contrast=0.5) for i in range(4)])


@pytest.fixture(scope="session")
def flat() -> torch.Tensor:
    return torch.full((4, 1, 128, 128), 0.5)


def add_noise(clean: torch.Tensor, sigma_dn: float, seed: int) -> torch.Tensor:
    """Clean + white Gaussian noise of σ DN, clipped to [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    return (clean + torch.randn(clean.shape, generator=g, dtype=clean.dtype) * sigma_dn / 255.0).clamp(0.0, 1.0)
