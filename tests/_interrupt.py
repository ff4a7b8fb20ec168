"""A training callback that sends this process SIGINT (what Ctrl-C does) after a given step."""

from __future__ import annotations

import os
import signal

from lightning.pytorch.callbacks import Callback


class SigintAt(Callback):
    def __init__(self, step: int) -> None:
        self.step = step

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if trainer.global_step == self.step:
            os.kill(os.getpid(), signal.SIGINT)
