"""Lightning DataModules that turn clean images into labelled, physically corrupted training patches.

- :class:`NoiseDataModule` — noisy 128 px patches, camera metadata, per-source σ labels and the residual ξ.
- :class:`BlurDataModule` — blurred 192 px patches with 16 MTF labels, blur family and size.
- :class:`PatchDataset` — the patch extraction both use (random crops + augmentation for training, fixed
  seeded crops for validation/test, rejection of near-uniform/clipped patches).

The loaders yield clean patches; the corruption runs in ``on_after_batch_transfer`` on the batch's device.
:func:`throughput` measures patches/s delivered including the corruption. See ``docs/data.md``.
"""

from __future__ import annotations

from datamodules.blur import FAMILIES, BlurDataModule, blur_psf
from datamodules.noise import XI_FIELDS, NoiseDataModule, expected_sigma_dn, metadata_matrix
from datamodules.patches import PatchDataModule, PatchDataset, is_hard_patch, rank_seed, sample_seed

__all__ = [
    "NoiseDataModule",
    "BlurDataModule",
    "PatchDataModule",
    "PatchDataset",
    "FAMILIES",
    "XI_FIELDS",
    "blur_psf",
    "expected_sigma_dn",
    "is_hard_patch",
    "metadata_matrix",
    "rank_seed",
    "sample_seed",
    "throughput",
]


def throughput(dm: PatchDataModule, n_batches: int = 10, stage: str = "train", device: str = "cpu", warmup: int = 1) -> dict[str, float]:
    """Patches/s delivered by ``dm``'s ``stage`` loader including the corruption on ``device``
    (:meth:`PatchDataModule.measure_throughput`)."""
    return dm.measure_throughput(n_batches=n_batches, stage=stage, device=device, warmup=warmup)
