"""Shared pytest fixtures: seeded RNG for every test, devices to parametrise over."""

from __future__ import annotations

import pytest
import torch

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(autouse=True)
def _seed_everything():
    torch.manual_seed(0)
    yield


@pytest.fixture(params=DEVICES)
def device(request):
    return torch.device(request.param)


@pytest.fixture
def meta_raw():
    """Raw (3, 11) metadata rows of the EV76C661 at 0, 12 and 24 dB."""
    from camhealth.physics.metadata import CameraMetadata
    from datamodules.noise import metadata_matrix

    return metadata_matrix(CameraMetadata.preset("EV76C661", batch_size=3, gain_db=torch.tensor([0.0, 12.0, 24.0]))).float()
