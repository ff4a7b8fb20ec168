"""Train an estimator from a YAML file: ``python -m camhealth.fit --config configs/noise_source.yaml``.

A :class:`lightning.pytorch.cli.LightningCLI` over any :class:`lightning_modules.EstimatorModule` (``model:``)
and any :class:`datamodules.PatchDataModule` (``data:``), with the ``trainer:`` section of Lightning. Everything
LightningCLI offers works: ``--print_config``, several ``--config`` files merged in order, dotted overrides
(``--trainer.max_steps 200 --model.init_args.metadata_set minimal``), ``--seed_everything``.
Defaults set here (each config can override them): TensorBoard logging under ``runs/``, a checkpoint of
the best model on the validation metric (``--monitor``/``--mode``), the last checkpoint, a learning-rate
monitor, Lightning's progress bar. After fitting, the best checkpoint is evaluated on the held-out test
split (``--test_after_fit false`` skips it) and, with ``--export_weights PATH``, written as a camhealth
weights file (tensors + JSON description, loadable by :func:`camhealth.load_estimator`).

**Resuming.** ``last.ckpt`` (next to the best checkpoint) is written after every validation
(``ModelCheckpoint(save_last=True)``) and also when training stops on an exception or Ctrl-C/SIGINT, at the step
reached (as Lightning's ``OnExceptionCheckpoint``; a plain run never resumes by itself). ``--ckpt_path PATH`` (as LightningCLI's ``fit --ckpt_path``)
continues from it: weights, optimiser, learning-rate schedule, step/epoch and the ``max_time`` clock are restored;
``--ckpt_path last`` takes the newest ``last.ckpt`` under the logger's folder. The file must load with
``torch.load(weights_only=True)`` (plain data, as camhealth's own checkpoints do) before Lightning opens it.

**Checks before training.** The ``--monitor`` metric must be one the model logs: a validation metric is looked for
in the metrics of Lightning's sanity-check validation (before the first step; with ``num_sanity_val_steps: 0`` at
the first validation), a ``train/`` metric after the first step — a typo is refused there, naming the metrics
that are logged, not when the first checkpoint would be written.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Sequence

import torch
from lightning.pytorch.callbacks import Callback, OnExceptionCheckpoint
from lightning.pytorch.cli import LightningCLI

from camhealth._cli import add_debug_flag, run_cli
from camhealth.runtime import keep_freed_memory
from datamodules.patches import PatchDataModule
from lightning_modules.base import EstimatorModule

__all__ = ["FitCLI", "main"]


class _LastCheckpointOnException(Callback):
    """``last.ckpt`` in the ``ModelCheckpoint`` folder when training stops on an exception (Ctrl-C/SIGINT included),
    at the step reached — what Lightning's ``OnExceptionCheckpoint`` does, without two of its side effects that would
    change a plain run: a trainer holding one resumes ``fit(ckpt_path=None)`` from the newest last checkpoint it
    finds (an earlier run's, where a checkpoint folder is reused), and it deletes its file on a normal end (here
    ``ModelCheckpoint``'s ``last.ckpt``)."""

    def __init__(self) -> None:
        self.saved: str | None = None

    def on_exception(self, trainer, pl_module, exception: BaseException) -> None:  # noqa: D102
        ckpt = _model_checkpoint(trainer)
        if ckpt is None or not ckpt.dirpath or trainer.global_step == 0 or trainer.sanity_checking:
            return
        path = str(Path(ckpt.dirpath) / f"{ckpt.CHECKPOINT_NAME_LAST}{ckpt.FILE_EXTENSION}")
        trainer.save_checkpoint(path)
        self.saved = path
        if isinstance(exception, KeyboardInterrupt):
            print(f"camhealth.fit: interrupted at step {trainer.global_step}; resume with --ckpt_path {path}", file=sys.stderr)


def _model_checkpoint(trainer):
    """The trainer's first ``ModelCheckpoint`` (``trainer.checkpoint_callback`` may be another ``Checkpoint``)."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    return next((c for c in trainer.checkpoint_callbacks if isinstance(c, ModelCheckpoint)), None)


class _MonitoredMetricCheck(Callback):
    """Refuse a ``--monitor`` metric the model does not log: after the sanity-check validation (validation metrics;
    at the first validation when there is no sanity check) or the first training step (``train/`` metrics)."""

    def __init__(self, monitor: str) -> None:
        self.monitor = monitor
        self.checked = False

    def _check(self, trainer, when: str) -> None:
        if self.checked:
            return
        logged = sorted(k for k in trainer.callback_metrics if not k.startswith("train/") or self.monitor.startswith("train/"))
        if self.monitor not in trainer.callback_metrics:
            raise ValueError(
                f"--monitor {self.monitor!r} names no metric the model logs ({when}: {logged}); "
                f"set monitor: to one of them"
            )
        self.checked = True

    def on_sanity_check_end(self, trainer, pl_module) -> None:  # noqa: D102
        if not self.monitor.startswith("train/"):
            self._check(trainer, "sanity-check validation")

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:  # noqa: D102
        if self.monitor.startswith("train/"):
            self._check(trainer, "first training step")

    def on_validation_end(self, trainer, pl_module) -> None:  # noqa: D102
        if not trainer.sanity_checking and not self.monitor.startswith("train/"):
            self._check(trainer, "first validation")


class FitCLI(LightningCLI):
    """LightningCLI with camhealth's defaults (see module docstring)."""

    def before_instantiate_classes(self) -> None:
        _sync_metadata_set(self.config)

    def add_arguments_to_parser(self, parser) -> None:  # noqa: D401
        # The network's input size is the DataModule's patch size.
        parser.link_arguments("data.init_args.patch_size", "model.init_args.patch_size")
        parser.add_argument("--monitor", type=str, default="val/loss", help="validation metric of the best checkpoint")
        parser.add_argument("--mode", type=str, default="min", help="min or max for --monitor")
        parser.add_argument("--test_after_fit", type=bool, default=True, help="test the best checkpoint after fit")
        parser.add_argument("--export_weights", type=str | None, default=None, help="write the best model as camhealth weights here")
        parser.add_argument("--threads", type=int | None, default=None, help="torch intra-op threads (default: torch's)")
        parser.add_argument(
            "--init_from", type=str | None, default=None,
            help="fine-tune: start from the weights of this camhealth weights file or checkpoint (same architecture; "
                 "optimiser and schedule start afresh)",
        )
        parser.add_argument(
            "--ckpt_path", type=str | None, default=None,
            help="resume training from this checkpoint (a last.ckpt or best-*.ckpt of camhealth.fit, or 'last': the newest "
                 "last.ckpt under the logger's folder): weights, optimiser, LR schedule, step/epoch and the max_time clock "
                 "are restored (LightningCLI's fit --ckpt_path)",
        )
        add_debug_flag(parser)
        parser.set_defaults(  # plain defaults; every config may override them
            {
                "trainer.logger": {
                    "class_path": "lightning.pytorch.loggers.TensorBoardLogger",
                    "init_args": {"save_dir": "runs", "name": "estimator"},
                },
                "trainer.log_every_n_steps": 10,
            }
        )


def _sync_metadata_set(config) -> None:
    """The DataModule's ``metadata_set`` (which normalised metadata it puts in ``meta``) follows the model's."""
    model_args = (config.get("model") or {}).get("init_args") or {}
    data_args = (config.get("data") or {}).get("init_args") or {}
    if "metadata_set" in model_args and "metadata_set" in data_args:
        data_args["metadata_set"] = model_args["metadata_set"]


def _add_default_callbacks(cli: FitCLI) -> None:
    """Replace Lightning's default (unmonitored) checkpoint callback by one that keeps the best model on
    ``--monitor`` and the last one; add a learning-rate monitor when logging, ``last.ckpt`` on an exception or
    interrupt and the check of ``--monitor``. Callbacks configured in ``trainer.callbacks`` are kept as they are."""
    from lightning.pytorch.callbacks import LearningRateMonitor, ModelCheckpoint

    trainer = cli.trainer
    cfg = cli.config
    trainer.callbacks.append(_MonitoredMetricCheck(cfg["monitor"]))
    configured = [c for c in trainer.callbacks if isinstance(c, ModelCheckpoint) and c.monitor is not None]
    if not configured:
        trainer.callbacks = [c for c in trainer.callbacks if not isinstance(c, ModelCheckpoint)]
        trainer.callbacks.append(
            ModelCheckpoint(
                monitor=cfg["monitor"], mode=cfg["mode"], save_last=True, save_top_k=1,
                filename="best-step{step}", auto_insert_metric_name=False,
            )
        )
    if trainer.logger is not None and not any(isinstance(c, LearningRateMonitor) for c in trainer.callbacks):
        trainer.callbacks.append(LearningRateMonitor(logging_interval="step"))
    if not any(isinstance(c, (OnExceptionCheckpoint, _LastCheckpointOnException)) for c in trainer.callbacks):
        trainer.callbacks.append(_LastCheckpointOnException())


def _init_from(model: EstimatorModule, path: str) -> None:
    """Load the network weights of a camhealth weights file or Lightning checkpoint (tensors only) into
    ``model``; the architectures must match (a clear error names the first mismatch). One exception: an MTF network
    with ``joint_directions`` starts from a one-direction file exactly (:meth:`~lightning_modules.mtf.MTFNet.state_from`)."""
    from camhealth.export import load_module

    source, _ = load_module(Path(path))
    if type(source) is not type(model):
        raise ValueError(f"--init_from {path}: holds a {type(source).__name__}, the config trains a {type(model).__name__}")
    try:
        state = model.net.state_from(source.net) if hasattr(model.net, "state_from") else source.net.state_dict()
        model.net.load_state_dict(state)
    except (RuntimeError, ValueError) as exc:
        raise ValueError(f"--init_from {path}: architecture differs from the config's: {str(exc).splitlines()[0]}") from None


def _resume_path(cli: FitCLI) -> str | None:
    """The checkpoint ``--ckpt_path`` names (``last``: the newest ``last.ckpt`` under the logger's folder), checked
    to hold plain data only; ``None`` without the option."""
    value = cli.config["ckpt_path"]
    if not value:
        return None
    if value == "last":
        logger = cli.trainer.logger
        root = Path(getattr(logger, "root_dir", None) or cli.trainer.default_root_dir)
        found = sorted(root.rglob("last*.ckpt"), key=lambda p: p.stat().st_mtime)
        if not found:
            raise ValueError(f"--ckpt_path last: no last.ckpt under {root}")
        path = found[-1]
    else:
        path = Path(value)
        if not path.is_file():
            raise FileNotFoundError(f"--ckpt_path {value}: no such checkpoint file")
    try:  # a checkpoint that holds more than plain data (pickled code) is refused before Lightning unpickles it
        saved = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        from camhealth.export import _load_refusal

        raise ValueError(f"--ckpt_path {path}: not a checkpoint of plain data ({_load_refusal(exc)})") from None
    # the learning-rate schedule is restored with the step: it cannot run past the steps it was made for
    schedules = saved.get("lr_schedulers") if isinstance(saved, dict) else None
    total = schedules[0].get("total_steps") if schedules and isinstance(schedules[0], dict) else None
    max_steps = cli.trainer.max_steps
    if isinstance(total, int) and max_steps is not None and max_steps >= total:
        raise ValueError(
            f"--ckpt_path {path}: its learning-rate schedule ends at step {total - 1} (the run's max_steps), "
            f"trainer.max_steps = {max_steps} goes beyond it; resume with max_steps ≤ {total - 1}, or fine-tune from "
            f"the weights with --init_from (a new schedule)"
        )
    return str(path)


def main(args: Sequence[str] | None = None) -> FitCLI:
    """Parse ``args`` (default: ``sys.argv[1:]``), fit, test the best checkpoint, optionally export it."""
    cli = FitCLI(
        EstimatorModule,
        PatchDataModule,
        subclass_mode_model=True,
        subclass_mode_data=True,
        run=False,
        args=list(args) if args is not None else None,
        seed_everything_default=0,
        save_config_kwargs={"overwrite": True},
        parser_kwargs={"prog": "python -m camhealth.fit", "description": __doc__},
    )
    if cli.config["threads"]:
        torch.set_num_threads(int(cli.config["threads"]))
    # reuse freed tensor memory instead of page-faulting it in again every step (glibc; camhealth.runtime):
    # the on-the-fly corruption and the training step allocate the same large buffers every batch
    keep_freed_memory()
    _add_default_callbacks(cli)
    ckpt_path = _resume_path(cli)
    if cli.config["init_from"]:
        if ckpt_path:
            raise ValueError("--init_from starts a new training from weights, --ckpt_path resumes one; give one of them")
        _init_from(cli.model, cli.config["init_from"])
    cli.trainer.fit(cli.model, datamodule=cli.datamodule, ckpt_path=ckpt_path)
    checkpoint = _model_checkpoint(cli.trainer)
    best = checkpoint.best_model_path if checkpoint is not None else ""
    results: dict = {"best_checkpoint": best}
    if cli.config["test_after_fit"]:
        tested = cli.trainer.test(cli.model, datamodule=cli.datamodule, ckpt_path=best or None)
        results["test"] = {k: float(v) for k, v in (tested[0] if tested else {}).items()}
    # trainer.log_dir is a collective in a multi-process run: every rank reads it; only rank zero writes files
    log_dir = Path(cli.trainer.log_dir or ".")
    if cli.config["export_weights"] and cli.trainer.is_global_zero:
        from camhealth.export import export_weights

        source = best or None
        path = export_weights(source if source else cli.model, cli.config["export_weights"], metrics=results.get("test"))
        results["weights"] = str(path)
    if cli.trainer.is_global_zero:
        log_dir.mkdir(parents=True, exist_ok=True)
        (log_dir / "fit_results.json").write_text(json.dumps(results, indent=2))
        print(json.dumps(results, indent=2))
    return cli


if __name__ == "__main__":  # pragma: no cover
    sys.exit(run_cli(main, "python -m camhealth.fit"))
