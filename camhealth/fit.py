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
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import torch
from lightning.pytorch.cli import LightningCLI

from camhealth.runtime import keep_freed_memory
from datamodules.patches import PatchDataModule
from lightning_modules.base import EstimatorModule

__all__ = ["FitCLI", "main"]


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
    ``--monitor`` and the last one; add a learning-rate monitor when logging. Callbacks configured in
    ``trainer.callbacks`` are kept as they are."""
    from lightning.pytorch.callbacks import LearningRateMonitor, ModelCheckpoint

    trainer = cli.trainer
    cfg = cli.config
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
    if cli.config["init_from"]:
        _init_from(cli.model, cli.config["init_from"])
    cli.trainer.fit(cli.model, datamodule=cli.datamodule)
    best = cli.trainer.checkpoint_callback.best_model_path if cli.trainer.checkpoint_callback else ""
    results: dict = {"best_checkpoint": best}
    if cli.config["test_after_fit"]:
        tested = cli.trainer.test(cli.model, datamodule=cli.datamodule, ckpt_path=best or None)
        results["test"] = {k: float(v) for k, v in (tested[0] if tested else {}).items()}
    if cli.config["export_weights"]:
        from camhealth.export import export_weights

        source = best or None
        path = export_weights(source if source else cli.model, cli.config["export_weights"], metrics=results.get("test"))
        results["weights"] = str(path)
    if cli.trainer.is_global_zero:
        log_dir = Path(cli.trainer.log_dir or ".")
        log_dir.mkdir(parents=True, exist_ok=True)
        (log_dir / "fit_results.json").write_text(json.dumps(results, indent=2))
        print(json.dumps(results, indent=2))
    return cli


if __name__ == "__main__":  # pragma: no cover
    main()
