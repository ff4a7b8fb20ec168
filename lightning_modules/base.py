"""Common LightningModule plumbing of the three estimators: optimiser and schedule, channels_last,
TensorBoard figures, export hooks and the description stored with checkpoints and shipped weights.

Each estimator trains one network of :mod:`camhealth.nets` (``self.net``, a plain ``torch.nn.Module``); its
arguments are split there (:data:`camhealth.nets.NETWORKS`) into those that shape the network and those that only
shape training, so inference rebuilds the network from a file without this module."""

from __future__ import annotations

from typing import Any, Mapping

import lightning as L
import torch
from torch import nn

from camhealth._order import _traced
from camhealth.estimators._common import check_patches
from camhealth.nets import NETWORKS, check_patch_size
from camhealth.nets.blocks import count_flops, count_parameters

__all__ = ["EstimatorModule"]


class EstimatorModule(L.LightningModule):
    """Base class: subclasses set ``kind``, ``patch_size``, build ``self.net`` and implement
    :meth:`export_inputs` (example inputs of ``self.net``) and the steps.

    Args:
        lr: peak learning rate of AdamW (one-cycle schedule over the run's optimiser steps).
        weight_decay: AdamW weight decay.
        channels_last: train and run the convolutions in channels-last memory format (faster on CPU).
        log_figures: log figures (estimate vs truth) to TensorBoard after each validation epoch.
        max_figure_samples: validation samples kept for the figures.
    """

    kind: str = ""
    metadata_set: str = "none"

    def __init__(
        self,
        lr: float = 2e-3,
        weight_decay: float = 1e-4,
        channels_last: bool = True,
        log_figures: bool = True,
        max_figure_samples: int = 512,
    ) -> None:
        super().__init__()
        if self.kind in NETWORKS:  # each value named (a str lr would fail the comparisons below unnamed)
            NETWORKS[self.kind].check_training_args({
                "lr": lr, "weight_decay": weight_decay, "channels_last": channels_last, "log_figures": log_figures,
                "max_figure_samples": max_figure_samples})
        if not lr > 0:
            raise ValueError(f"lr = {lr!r} must be > 0")
        if weight_decay < 0:
            raise ValueError(f"weight_decay = {weight_decay!r} must be ≥ 0")
        self.lr = float(lr)
        self.weight_decay = float(weight_decay)
        self.channels_last = bool(channels_last)
        self.log_figures = bool(log_figures)
        self.max_figure_samples = int(max_figure_samples)
        self._figure_cache: dict[str, list[torch.Tensor]] = {}

    # ------------------------------------------------------------------ optimisation
    def configure_optimizers(self) -> Any:
        params = [p for p in self.parameters() if p.requires_grad]
        opt = torch.optim.AdamW(params, lr=self.lr, weight_decay=self.weight_decay)
        total = None
        if self._trainer is not None:
            total = self.trainer.estimated_stepping_batches
        if total is None or not (0 < float(total) < float("inf")):
            return opt
        sched = torch.optim.lr_scheduler.OneCycleLR(
            opt, max_lr=self.lr, total_steps=int(total) + 1, pct_start=0.15, div_factor=10.0, final_div_factor=100.0
        )
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        """Log ``train/fallback_fraction``, the share of the training patches (mean over the epoch) that are near-uniform
        or clipped crops kept after ``max_tries`` draws (their ``fallback`` entry, :class:`datamodules.PatchDataset`):
        near 1, the images have too little texture for the hard-patch check."""
        fallback = batch.get("fallback") if isinstance(batch, Mapping) else None
        if isinstance(fallback, torch.Tensor) and fallback.numel():
            self.log("train/fallback_fraction", fallback.float().mean(), on_step=False, on_epoch=True,
                     batch_size=fallback.numel(), sync_dist=True)

    def _check_training_args(self) -> None:
        """The training arguments' values, checked as the loaders check a file's
        (:meth:`camhealth.nets.NetworkSpec.check_training_args`): what trains also loads."""
        NETWORKS[self.kind].check_training_args(self.hparams)

    def _set_patch_size(self, patch_size: int) -> None:
        self.patch_size = check_patch_size(patch_size)

    def _prepare(self, image: torch.Tensor) -> torch.Tensor:
        return image.contiguous(memory_format=torch.channels_last) if self.channels_last else image

    def _check_image(self, image: Any, stack: bool = False, values: bool = True) -> None:
        """The input of :meth:`forward`: ``B×1×P×P`` patches (``stack``: ``B×T×P×P``, T ≥ 1 patches of one location) of
        this estimator's ``patch_size`` P, else a ``ValueError`` naming the shape; with ``values`` also a floating
        tensor (``TypeError`` for integer DN images), finite and in [0, 1] (:func:`camhealth.estimators._common.check_patches`,
        as the noise-source network's image statistics check it; two reductions of the batch, skipped while traced
        or exported and for an empty batch, B = 0)."""
        if not isinstance(image, torch.Tensor):
            raise TypeError(f"image must be a torch.Tensor of B×1×P×P patches in [0, 1], got {type(image).__name__}")
        p, shape = self.patch_size, tuple(image.shape)
        if len(shape) != 4 or shape[2:] != (p, p) or (shape[1] < 1 if stack else shape[1] != 1):
            form = f"B×T×{p}×{p} (T ≥ 1 patches of one location; one patch: T = 1)" if stack else f"B×1×{p}×{p}"
            raise ValueError(f"image has shape {shape}; this {type(self).__name__} (patch_size = {p}) takes {form} "
                             "patches in [0, 1]")
        if values and shape[0] and not _traced():
            check_patches(image if shape[1] == 1 else image.reshape(-1, 1, p, p), "image")

    @staticmethod
    def _label(batch: Mapping[str, Any], key: str, shape: tuple[int, ...]) -> torch.Tensor:
        """``batch[key]``, a label of the batch, as a tensor of ``shape``; a ``ValueError`` naming the key, its shape and
        the expected one otherwise (a (B, 1) label against (B,) estimates would broadcast to B×B pairs)."""
        value = batch[key]
        if not isinstance(value, torch.Tensor) or tuple(value.shape) != tuple(shape):
            got = f"shape {tuple(value.shape)}" if isinstance(value, torch.Tensor) else f"type {type(value).__name__}"
            raise ValueError(f"label batch[{key!r}] has {got}; it must be a tensor of shape {tuple(shape)}, one entry "
                             f"per patch of the batch of {shape[0]}")
        return value

    @staticmethod
    def _refuse_non_finite(labels: Mapping[str, torch.Tensor], batch_idx: int | None) -> None:
        """``ValueError`` naming the first of ``labels`` (what to call it → tensor) that holds NaN/inf, how many and the
        first bad value, and the batch; called once a single reduction found one (a non-finite label makes the loss
        NaN/inf and the optimiser step useless)."""
        where = f" (batch {batch_idx})" if batch_idx is not None else ""
        for name, value in labels.items():
            bad = ~torch.isfinite(value.detach())
            if bool(bad.any()):
                raise ValueError(f"label {name} must be finite, but {int(bad.sum())} of {value.numel()} values are "
                                 f"NaN/inf (first: {value.detach()[bad].flatten()[0].item()}){where}")
        raise ValueError(f"a label of the batch is not finite{where}")

    # ------------------------------------------------------------------ figures
    def _cache_for_figures(self, **tensors: torch.Tensor) -> None:
        if not self.log_figures:
            return
        n_have = sum(t.shape[0] for t in self._figure_cache.get(next(iter(tensors)), []))
        if n_have >= self.max_figure_samples:
            return
        for k, v in tensors.items():
            self._figure_cache.setdefault(k, []).append(v.detach().float().cpu())

    def _take_figure_cache(self) -> dict[str, torch.Tensor]:
        cache = {k: torch.cat(v)[: self.max_figure_samples] for k, v in self._figure_cache.items() if v}
        self._figure_cache = {}
        return cache

    def _tensorboard(self):
        logger = self.logger
        if logger is None or getattr(self._trainer, "sanity_checking", False):
            return None
        exp = getattr(logger, "experiment", None)
        return exp if hasattr(exp, "add_figure") else None

    @property
    def example_input_array(self) -> tuple[torch.Tensor, ...]:
        """One patch in [0, 1] (B = 1, ``patch_size`` px) as :meth:`forward` takes it: Lightning's model summary
        shows the input/output sizes with it."""
        g = torch.Generator().manual_seed(0)
        return (torch.rand(1, 1, self.patch_size, self.patch_size, generator=g),)

    def on_fit_start(self) -> None:
        """``TensorBoardLogger(log_graph=True)``: draw the graph of the bare network (:meth:`export_module` on
        :meth:`export_inputs`, what is exported) instead of this module's :meth:`forward`, whose dict output and
        metadata handling the tracer cannot follow; the logger's own attempt, which comes right after this hook,
        is then skipped."""
        from lightning.pytorch.loggers import TensorBoardLogger

        for logger in self.loggers:
            if isinstance(logger, TensorBoardLogger) and getattr(logger, "_log_graph", False):
                if self.global_rank == 0:
                    net = self.export_module()  # (eval mode while traced)
                    was_training = self.training
                    inputs = tuple(t.to(self.device) for t in self.export_inputs(1))
                    try:
                        logger.experiment.add_graph(net, inputs)
                    finally:
                        self.train(was_training)
                logger._log_graph = False  # Lightning's log_graph(module) would trace forward() and fail

    # ------------------------------------------------------------------ export / description
    def export_inputs(self, batch_size: int = 2) -> tuple[torch.Tensor, ...]:  # pragma: no cover - abstract
        raise NotImplementedError

    def export_module(self) -> nn.Module:
        """The bare network that is exported (eval mode; inputs :meth:`export_inputs`)."""
        return self.net.eval()

    def describe(self) -> dict[str, Any]:
        """Plain-data description stored in checkpoints, exported files and shipped weights."""
        inputs = self.export_inputs(1)
        return {
            "kind": self.kind,
            "class_path": f"{type(self).__module__}.{type(self).__name__}",
            "init_args": {k: v for k, v in self.hparams.items() if not str(k).startswith("_")},
            "patch_size": self.patch_size,
            "metadata_set": self.metadata_set,
            "params": count_parameters(self.net),
            "flops_per_patch": count_flops(self.net, *inputs),
        }

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["camhealth"] = {"format": "camhealth-estimator", "version": 1, **self.describe()}
