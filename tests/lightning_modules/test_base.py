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


@pytest.mark.parametrize("module, kind, precision", [
    (lambda: NoiseLevelEstimator(patch_size=32, width=8), "noise", "64-true"),
    (lambda: NoiseLevelEstimator(patch_size=32, width=8), "noise", "bf16-true"),
    (lambda: MTFEstimator(patch_size=64, widths=(8, 8, 8), hidden=(8,)), "mtf", "bf16-true"),
    (lambda: NoiseSourceEstimator(patch_size=32, width=8), "noise", "bf16-true"),
])
def test_true_precision_training_summarises_validates_saves_checkpoints_and_exports(module, kind, precision, tmp_path):
    """The documented true precisions with what a ``camhealth.fit`` run does: the model summary (float32 example
    input), validation metrics (float64 accumulators, also under the module's bf16 cast), a checkpoint (its
    description counts FLOPs with float32 inputs), and a weights file that loads."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    from camhealth.export import export_weights
    from camhealth.inference import load_estimator
    from lightning_modules.metrics import AMAEPerFamily, NoiseErrorStats

    m = module()
    trainer = L.Trainer(max_steps=1, val_check_interval=1, limit_val_batches=1, num_sanity_val_steps=0,
                        accelerator="cpu", devices=1, precision=precision, logger=False, enable_progress_bar=False, enable_model_summary=True,
                        callbacks=[ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)])
    from datamodules import BlurDataModule, NoiseDataModule

    small = {"source": "deadleaves", "source_kwargs": {"n_images": 8, "size": (64, 64)}, "batch_size": 2,
             "val_fraction": 0.25, "test_fraction": 0.25}  # a validation split of its own (the metrics run)
    data = (BlurDataModule(patch_size=64, size_range=(1.0, 9.0), **small) if kind == "mtf" else
            NoiseDataModule(patch_size=32, **({"metadata_set": m.metadata_set} if hasattr(m, "loss_weights") else {}), **small))
    trainer.fit(m, datamodule=data)
    dtype = torch.float64 if precision == "64-true" else torch.bfloat16
    assert trainer.global_step == 1 and next(m.parameters()).dtype == dtype
    assert (tmp_path / "ckpt" / "last.ckpt").is_file()
    states = [getattr(metric, k) for metric in m.modules() if isinstance(metric, (NoiseErrorStats, AMAEPerFamily))
              for k in metric._defaults]
    assert states and all(s.dtype == torch.float64 for s in states)
    validated = {k: float(v) for k, v in trainer.callback_metrics.items() if k in ("val/loss", "val/rms_total", "val/amae")}
    assert len(validated) == 2 and all(v == v for v in validated.values()), validated
    est = load_estimator(export_weights(m, tmp_path / "w.pt"))
    assert est.description["flops_per_patch"] > 0
    x = torch.rand(2, 1, m.patch_size, m.patch_size) * 0.5 + 0.25
    out = est.predict(x, "ICX285" if est.metadata_set != "none" else None)
    assert all(bool(torch.isfinite(v).all()) for v in out.values() if isinstance(v, torch.Tensor) and v.is_floating_point()
               and v.numel() and not v.isnan().all())
