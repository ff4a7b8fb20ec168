"""The estimators' shared LightningModule behaviour: TensorBoard's graph of the bare network (``log_graph: true``)."""

import lightning as L
import pytest
import torch
from lightning.pytorch.loggers import TensorBoardLogger

from lightning_modules import MTFEstimator, NoiseLevelEstimator, NoiseSourceEstimator


def _data(kind: str, module):
    from datamodules import BlurDataModule, NoiseDataModule

    small = {"source": "deadleaves", "source_kwargs": {"n_images": 2, "size": (64, 64)}, "batch_size": 2}
    if kind == "mtf":
        return BlurDataModule(patch_size=64, size_range=(1.0, 9.0), **small)
    ms = getattr(module, "metadata_set", None)
    return NoiseDataModule(patch_size=32, **({"metadata_set": ms} if ms else {}), **small)


@pytest.mark.parametrize("module, kind", [
    (lambda: MTFEstimator(patch_size=64), "mtf"),
    (lambda: NoiseSourceEstimator(patch_size=32), "noise"),
    (lambda: NoiseLevelEstimator(patch_size=32), "noise"),
])
def test_log_graph_draws_the_bare_network_and_fit_goes_on(module, kind, tmp_path):
    """``TensorBoardLogger(log_graph=True)``: Lightning would trace forward(), whose dict output (and, for the noise
    sources, metadata handling) the tracer refuses, and the fit died before its first step; the module draws its
    exported network instead, and training runs in train mode."""
    m = module()
    logger = TensorBoardLogger(tmp_path, name="tb", log_graph=True)
    trainer = L.Trainer(max_steps=1, limit_val_batches=1, num_sanity_val_steps=0, accelerator="cpu", devices=1,
                        logger=logger, enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False)
    trainer.fit(m, datamodule=_data(kind, m))
    assert trainer.global_step == 1 and m.training
    events = list((tmp_path / "tb").rglob("events.out.tfevents*"))
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(events[0].parent))
    acc.Reload()
    assert acc.Graph() is not None  # the graph was written


@pytest.mark.parametrize("module, kind", [
    (lambda: MTFEstimator(patch_size=64), "mtf"),
    (lambda: NoiseSourceEstimator(patch_size=32), "noise"),
])
def test_true_precision_training_runs(module, kind, tmp_path):
    """``precision="64-true"``: the module's weights and batches are float64; the networks follow their weights' dtype
    (they cast their float32 statistics to it)."""
    m = module()
    trainer = L.Trainer(max_steps=1, limit_val_batches=1, num_sanity_val_steps=0, accelerator="cpu", devices=1,
                        precision="64-true", logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False)
    trainer.fit(m, datamodule=_data(kind, m))
    assert trainer.global_step == 1 and next(m.parameters()).dtype == torch.float64
