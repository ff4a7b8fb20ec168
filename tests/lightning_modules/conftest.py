from __future__ import annotations

import pytest
import torch

from camhealth.physics.metadata import CameraMetadata
from datamodules.noise import metadata_matrix


@pytest.fixture
def noisy_batch():
    """A small labelled batch from the NoiseDataModule's corruption (no loader), 32-px patches."""
    from datamodules import NoiseDataModule

    g = torch.Generator().manual_seed(0)
    clean = (torch.rand(4, 1, 32, 32, generator=g) * 0.6 + 0.2)
    dm = NoiseDataModule(source="deadleaves", source_kwargs={"n_images": 2, "size": (64, 64)}, patch_size=32)
    meta = CameraMetadata.preset("ICX285", batch_size=4, gain_db=torch.tensor([0.0, 6.0, 12.0, 24.0]))
    batch = dm.corrupt_with(clean, meta, meta, noise_seed=1)
    batch["clean"] = clean
    return batch
