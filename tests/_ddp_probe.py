"""A callback for the multi-process test of ``camhealth.fit``: each rank saves the corruption of its first
training batch (``meta_raw`` and the corrupted image) to ``<out>/rank<R>.pt``."""

from __future__ import annotations

from pathlib import Path

import torch
from lightning.pytorch.callbacks import Callback


class RecordFirstTrainingBatch(Callback):
    def __init__(self, out: str) -> None:
        self.out = Path(out)
        self.saved = False

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:  # noqa: D102
        if self.saved:
            return
        self.out.mkdir(parents=True, exist_ok=True)
        torch.save(
            {"meta_raw": batch["meta_raw"].cpu(), "image": batch["image"].cpu(), "index": batch["index"].cpu(),
             "world_size": trainer.world_size},
            self.out / f"rank{trainer.global_rank}.pt",
        )
        self.saved = True
