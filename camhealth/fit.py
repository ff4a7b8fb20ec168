"""Train an estimator from a YAML file: ``python -m camhealth.fit --config configs/noise_source.yaml``.

A :class:`lightning.pytorch.cli.LightningCLI` over any :class:`lightning_modules.EstimatorModule` (``model:``)
and any :class:`datamodules.PatchDataModule` (``data:``), with the ``trainer:`` section of Lightning and its
subcommands ``fit``, ``validate``, ``test``, ``predict`` (``python -m camhealth.fit test --config … --ckpt_path
best.ckpt``; a command line without a subcommand is ``fit``). Everything LightningCLI offers works:
``--print_config``, several ``--config`` files merged in order, dotted overrides (``--trainer.max_steps 200
--model.init_args.metadata_set minimal``), ``--seed_everything``, ``--trainer.devices N --trainer.num_nodes M``.
Defaults set here (each config can override them): TensorBoard logging under ``runs/``; the callbacks as
configuration (saved in each run's ``config.yaml``, shown by ``--print_config``): ``checkpoint:`` a
``ModelCheckpoint`` of the best model on ``monitor:``/``mode:`` and the last one, ``lr_monitor:`` a
``LearningRateMonitor``; the monitored metric is TensorBoard's hparams metric (``hp_metric``). After fitting, the
best checkpoint is evaluated on the held-out test split (``--test_after_fit false`` skips it) and, with
``--export_weights PATH``, written as a camhealth weights file (tensors + JSON description, loadable by
:func:`camhealth.load_estimator`); in a multi-process run only rank zero writes files.

**Patch size and metadata set.** The model's ``patch_size`` is the data's (``data.init_args.patch_size``); a
model ``patch_size`` given as well (on the command line or in a config file) that differs from it is refused, naming
both. The data's ``metadata_set`` follows the model's (``--print_config`` shows the value the run uses).

**Resuming.** ``last.ckpt`` (next to the best checkpoint) is written after every validation
(``ModelCheckpoint(save_last=True)``) and also when training stops on an exception or Ctrl-C/SIGINT, at the step
reached (as Lightning's ``OnExceptionCheckpoint``; a plain run never resumes by itself). ``--ckpt_path PATH`` (LightningCLI's ``fit --ckpt_path``)
continues from it: weights, optimiser, learning-rate schedule, step/epoch and the ``max_time`` clock are restored,
and so is the training data stream (torch's CPU generator, which draws the crops, augmentation and corruption, and
the epoch's order of the patches): with ``num_workers: 0`` on one process (the configs' setting) the resumed run
trains on the batches the uninterrupted run would have seen and ends with its weights. With DataLoader workers,
several processes or gradient accumulation the stream is not saved, and a resumed run draws its batches afresh (a
warning says so when it starts). ``--ckpt_path last`` takes the newest ``last.ckpt`` under the logger's folder. The
file must load with ``torch.load(weights_only=True)`` (plain data, as camhealth's own checkpoints do) before
Lightning opens it.

**Checks before training.** The ``--monitor`` metric must be one the model logs: a validation metric is looked for
in the metrics of Lightning's sanity-check validation (before the first step; with ``num_sanity_val_steps: 0`` at
the first validation), a ``train/`` metric after the first step — a typo is refused there, naming the metrics
that are logged, not when the first checkpoint would be written; an empty validation split (no validation batches)
is named as such. With ``--test_after_fit`` (the default) the test split's images are read and checked before the
first step too, so an unreadable or too small test image stops the run there, not after the training.
``--export_weights``, ``--test_after_fit`` and ``--init_from`` are options of ``fit``: on the
command line of ``validate``, ``test`` or ``predict`` they are refused; a run's saved ``config.yaml``, which holds the
fit's values of them, configures those subcommands as it is (they ignore the three).
"""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path
from typing import Mapping, Sequence

import torch
from lightning.pytorch.callbacks import Callback, OnExceptionCheckpoint
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI

from camhealth._cli import add_debug_flag, run_cli
from camhealth._packaging import check_top_level_packages, resolve_config_args
from camhealth.runtime import keep_freed_memory

__all__ = ["FitCLI", "main"]


#: The steps at which a run of this process was interrupted (Ctrl-C/SIGINT), set by :class:`_LastCheckpointOnException`.
_INTERRUPTED: list[int] = []


class _LastCheckpointOnException(Callback):
    """``last.ckpt`` in the ``ModelCheckpoint`` folder when training stops on an exception (Ctrl-C/SIGINT included),
    at the step reached — what Lightning's ``OnExceptionCheckpoint`` does, without two of its side effects that would
    change a plain run: a trainer holding one resumes ``fit(ckpt_path=None)`` from the newest last checkpoint it
    finds (an earlier run's, where a checkpoint folder is reused), and it deletes its file on a normal end (here
    ``ModelCheckpoint``'s ``last.ckpt``)."""

    def __init__(self) -> None:
        self.saved: str | None = None

    def on_exception(self, trainer, pl_module, exception: BaseException) -> None:  # noqa: D102
        if isinstance(exception, KeyboardInterrupt):  # Lightning then exits with status 1: main says interrupted (130)
            _INTERRUPTED.append(trainer.global_step)
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
    at the first validation when there is no sanity check) or the first training step (``train/`` metrics). After
    each validation the monitored value is also logged as ``hp_metric`` (TensorBoard's hparams metric)."""

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

    def _check_validation_data(self, batches) -> None:
        """A validation metric needs validation batches: an empty validation split is named as such, not as a
        misspelt ``--monitor``."""
        if self.checked or self.monitor.startswith("train/"):
            return
        if not any(batches or []):  # (a count per validation loader)
            raise ValueError(
                f"--monitor {self.monitor!r} is a validation metric, but the validation split is empty (0 validation "
                f"batches): give the data module a validation split (val_fraction > 0, more images) or monitor a "
                f"train/ metric with --trainer.limit_val_batches 0"
            )

    def on_sanity_check_end(self, trainer, pl_module) -> None:  # noqa: D102
        if not self.monitor.startswith("train/"):
            self._check_validation_data(trainer.num_sanity_val_batches)
            self._check(trainer, "sanity-check validation")

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:  # noqa: D102
        if self.monitor.startswith("train/"):
            self._check(trainer, "first training step")

    def on_validation_end(self, trainer, pl_module) -> None:  # noqa: D102
        if trainer.sanity_checking:
            return
        if not self.monitor.startswith("train/"):
            self._check(trainer, "first validation")
        value = trainer.callback_metrics.get(self.monitor)
        if value is not None:  # TensorBoard's HPARAMS tab shows the monitored metric as hp_metric
            for logger in trainer.loggers:
                logger.log_metrics({"hp_metric": float(value)}, step=trainer.global_step)


#: LightningCLI's subcommands; a command line that starts with none of them is a ``fit``.
SUBCOMMANDS = ("fit", "validate", "test", "predict")

#: Lightning's warning on resuming mid-epoch from a loader that is not itself resumable; camhealth's DataModule
#: continues the stream instead (its ``state_dict``), so the warning is not shown where the checkpoint holds it.
_NOT_RESUMABLE_WARNING = "You're resuming from a checkpoint that ended before the epoch ended"


class _FitArgumentParser(LightningArgumentParser):
    """The parser of each subcommand: before jsonargparse prints (``--print_config``) or applies the link of the
    patch size, a model ``patch_size`` given besides the data's is checked against it (:func:`_check_patch_size`), and
    the data's ``metadata_set`` follows the model's (:func:`_sync_metadata_set`), so the printed configuration is the
    one that runs."""

    def _parse_common(self, cfg, *args, **kwargs):  # noqa: D102 (jsonargparse's last step of every parse)
        _check_patch_size(cfg)
        _sync_metadata_set(cfg)
        return super()._parse_common(cfg, *args, **kwargs)


class FitCLI(LightningCLI):
    """LightningCLI with camhealth's defaults (see module docstring)."""

    def __init__(self, *args, parser_class=_FitArgumentParser, **kwargs) -> None:
        self._stream_in_checkpoint = False
        super().__init__(*args, parser_class=parser_class, **kwargs)

    def _cfg(self):
        """The parsed configuration of the running subcommand."""
        return self.config[self.subcommand] if self.subcommand else self.config

    def parse_arguments(self, parser, args) -> None:  # noqa: D102
        # the command line as given: fit-only options are refused there for other subcommands (a --config file, e.g.
        # a run's saved config.yaml, carries the fit's values of them, which test/validate/predict ignore)
        self._argv = [str(a) for a in (sys.argv[1:] if args is None else args)] if not isinstance(args, Mapping) else []
        super().parse_arguments(parser, args)

    def _given(self, option: str) -> bool:
        """``--option`` is on the command line (as ``--option VALUE`` or ``--option=VALUE``)."""
        return any(a == f"--{option}" or a.startswith(f"--{option}=") for a in getattr(self, "_argv", []))

    def _refuse_fit_options(self) -> None:
        """``--export_weights`` and ``--test_after_fit`` act after ``fit`` only: another subcommand refuses them on
        its command line (``--init_from``: :meth:`after_instantiate_classes`)."""
        if self.subcommand in (None, "fit"):
            return
        if self._given("export_weights") and self._cfg().get("export_weights"):
            raise ValueError(f"--export_weights is an option of fit; {self.subcommand} writes no weights: export the "
                             f"checkpoint with python -m camhealth.export CKPT --format weights --out PATH")
        if self._given("test_after_fit"):
            raise ValueError(f"--test_after_fit is an option of fit (the test of the best checkpoint after fitting); "
                             f"{self.subcommand} does not fit")

    def before_instantiate_classes(self) -> None:
        self._refuse_fit_options()
        cfg = self._cfg()
        _sync_metadata_set(cfg)  # (done at parsing already: _FitArgumentParser)
        threads = cfg["threads"]
        if threads is not None:  # (0 would silently keep torch's default)
            if threads < 1:
                raise ValueError(f"--threads {threads}: must be >= 1, or null for torch's default")
            torch.set_num_threads(int(threads))
        # reuse freed tensor memory instead of page-faulting it in again every step (glibc; camhealth.runtime):
        # the on-the-fly corruption and the training step allocate the same large buffers every batch
        keep_freed_memory()

    def after_instantiate_classes(self) -> None:
        from lightning.pytorch.callbacks import LearningRateMonitor

        cfg = self._cfg()
        if self.trainer.logger is None:  # nothing to log the learning rate to (Lightning would refuse the run)
            self.trainer.callbacks = [c for c in self.trainer.callbacks if not isinstance(c, LearningRateMonitor)]
        self.trainer.callbacks.insert(0, _MonitoredMetricCheck(cfg["monitor"]))  # before ModelCheckpoint looks for it
        if not any(isinstance(c, (OnExceptionCheckpoint, _LastCheckpointOnException)) for c in self.trainer.callbacks):
            self.trainer.callbacks.append(_LastCheckpointOnException())
        if cfg.get("init_from") and self.subcommand not in (None, "fit"):
            if self._given("init_from"):
                raise ValueError(f"--init_from is an option of fit; {self.subcommand} takes the weights from --ckpt_path")
            # (from a --config file: a fine-tuning run's saved config.yaml; the weights are --ckpt_path's)
        elif cfg.get("init_from"):
            if cfg.get("ckpt_path"):
                raise ValueError("--init_from starts a new training from weights, --ckpt_path resumes one; give one of them")
            _init_from(self.model, cfg["init_from"])

    def instantiate_trainer(self, **kwargs):
        """The trainer, with the callbacks of the configuration; ``--trainer.enable_checkpointing false`` drops the
        ``checkpoint:`` callback (Lightning refuses a ``ModelCheckpoint`` then): the run writes no checkpoints, and
        after fitting the final weights are tested and exported."""
        from lightning.pytorch.callbacks import ModelCheckpoint

        parser = self._parser(self.subcommand)
        extra = [self._get(self.config_init, c) for c in parser.callback_keys]
        config = {**self._get(self.config_init, "trainer", default={}), **kwargs}
        if config.get("enable_checkpointing") is False:
            extra = [c for c in extra if not isinstance(c, ModelCheckpoint)]
        return self._instantiate_trainer(config, extra)

    def _parse_ckpt_path(self) -> None:
        """``--ckpt_path``: ``last`` is the newest ``last.ckpt`` under the logger's folder; the file must hold plain
        data. The model is the config's (the checkpoint gives the weights, not the hyperparameters)."""
        sub = self.config.get("subcommand")
        if sub and self.config[sub].get("ckpt_path"):
            self.config[sub]["ckpt_path"], self._stream_in_checkpoint = _checked_ckpt_path(self.config[sub], sub,
                                                                                           with_stream=True)

    def before_fit(self) -> None:
        """With ``--test_after_fit``: read (and check) the test split's images now, before the first step — an
        unreadable or too small test image would otherwise stop the run only after the training, without its
        results or exported weights. (The images are kept for the test; nothing is drawn from torch's generator.)"""
        from datamodules.patches import PatchDataModule

        if self._cfg()["test_after_fit"] and isinstance(self.datamodule, PatchDataModule):
            self.datamodule.setup("test")

    def _run_subcommand(self, subcommand: str) -> None:
        with warnings.catch_warnings():
            if self._stream_in_checkpoint:  # the DataModule continues the data stream (see _NOT_RESUMABLE_WARNING)
                warnings.filterwarnings("ignore", message=_NOT_RESUMABLE_WARNING)
            super()._run_subcommand(subcommand)

    def add_arguments_to_parser(self, parser) -> None:  # noqa: D401
        from lightning.pytorch.callbacks import LearningRateMonitor, ModelCheckpoint

        # The network's input size is the DataModule's patch size.
        parser.link_arguments("data.init_args.patch_size", "model.init_args.patch_size")
        parser.add_argument("--monitor", type=str, default="val/loss", help="validation metric of the best checkpoint")
        parser.add_argument("--mode", type=str, default="min", help="min or max for --monitor")
        parser.add_argument("--test_after_fit", type=bool, default=True, help="fit: test the best checkpoint after fit")
        parser.add_argument("--export_weights", type=str | None, default=None, help="fit: write the best model as camhealth weights here")
        parser.add_argument("--threads", type=int | None, default=None, help="torch intra-op threads, >= 1 (default: torch's)")
        parser.add_argument(
            "--init_from", type=str | None, default=None,
            help="fit: start from the weights of this camhealth weights file or checkpoint (same architecture; "
                 "optimiser and schedule start afresh)",
        )
        add_debug_flag(parser)
        # the callbacks live in the config (saved with each run, shown by --print_config)
        parser.add_lightning_class_args(ModelCheckpoint, "checkpoint")
        parser.add_lightning_class_args(LearningRateMonitor, "lr_monitor")
        parser.link_arguments("monitor", "checkpoint.monitor")
        parser.link_arguments("mode", "checkpoint.mode")
        parser.set_defaults(  # plain defaults; every config may override them
            {
                "trainer.logger": {
                    "class_path": "lightning.pytorch.loggers.TensorBoardLogger",
                    "init_args": {"save_dir": "runs", "name": "estimator"},
                },
                "trainer.log_every_n_steps": 10,
                "checkpoint.save_last": True,
                "checkpoint.save_top_k": 1,
                "checkpoint.filename": "best-step{step}",
                "checkpoint.auto_insert_metric_name": False,
                "lr_monitor.logging_interval": "step",
            }
        )

    def after_fit(self) -> None:
        """Test the best checkpoint (``--test_after_fit``), export it (``--export_weights``), write
        ``fit_results.json`` — files on rank zero only."""
        cfg = self._cfg()
        trainer = self.trainer
        checkpoint = _model_checkpoint(trainer)
        best = checkpoint.best_model_path if checkpoint is not None else ""
        results: dict = {"best_checkpoint": best}
        if cfg["test_after_fit"]:
            tested = trainer.test(self.model, datamodule=self.datamodule, ckpt_path=best or None)
            # a metric without data (NaN: e.g. a blur family with no test sample) is written as null
            results["test"] = {k: _metric_value(v) for k, v in (tested[0] if tested else {}).items()}
        # trainer.log_dir is a collective in a multi-process run: every rank reads it; only rank zero writes files
        log_dir = Path(trainer.log_dir or ".")
        if cfg["export_weights"] and trainer.is_global_zero:
            from camhealth.export import export_weights

            evaluation = _evaluation_entry(self.datamodule, trainer) if cfg["test_after_fit"] else None
            path = export_weights(best or self.model, cfg["export_weights"], metrics=results.get("test"),
                                  evaluation=evaluation)
            results["weights"] = str(path)
        if trainer.is_global_zero:
            log_dir.mkdir(parents=True, exist_ok=True)
            (log_dir / "fit_results.json").write_text(json.dumps(results, indent=2))
            print(json.dumps(results, indent=2))
        self.results = results


def _evaluation_entry(datamodule, trainer) -> dict | None:
    """The test data of the fit's metrics, for the weights file (:func:`camhealth.export.check_evaluation`): the
    datamodule's class and arguments and the trainer's precision; None where they cannot be recorded (a datamodule
    of another class, arguments that are not JSON), so that ``model_card --verify`` says the file records none."""
    from camhealth.export import EVALUATION_DATAMODULES, EVALUATION_PRECISIONS

    cls = type(datamodule)
    class_path = f"datamodules.{cls.__name__}"
    if class_path not in EVALUATION_DATAMODULES or cls.__module__.split(".")[0] != "datamodules":
        return None
    precision = str(trainer.precision)
    if precision not in EVALUATION_PRECISIONS:
        return None
    try:
        # (LightningCLI adds its own ``_class_path`` to the saved hyper-parameters: not an argument)
        hparams = {k: v for k, v in dict(datamodule.hparams).items() if not str(k).startswith("_")}
        init_args = json.loads(json.dumps(hparams, allow_nan=False))
    except (TypeError, ValueError):
        return None
    entry = {"data": {"class_path": class_path, "init_args": init_args}, "precision": precision}
    limit = trainer.limit_test_batches
    if limit is not None and not (isinstance(limit, float) and limit == 1.0):
        entry["limit_test_batches"] = limit
    return entry


def _metric_value(value) -> float | None:
    """A logged metric as a JSON number; None (null) for NaN, a metric without data."""
    value = float(value)
    return None if value != value else value


def _sync_metadata_set(config) -> None:
    """The DataModule's ``metadata_set`` (which normalised metadata it puts in ``meta``) follows the model's."""
    model_args = (config.get("model") or {}).get("init_args") or {}
    data_args = (config.get("data") or {}).get("init_args") or {}
    if "metadata_set" in model_args and "metadata_set" in data_args:
        data_args["metadata_set"] = model_args["metadata_set"]


def _check_patch_size(config) -> None:
    """The model's patch size is the data's (``parser.link_arguments``, applied after this check): a model
    ``patch_size`` given as well (command line, config file, ``--model`` mapping) that differs from the data's is a
    ``ValueError`` naming both — the link would drop it silently."""
    model_args = (config.get("model") or {}).get("init_args") or {}
    data_args = (config.get("data") or {}).get("init_args") or {}
    if "patch_size" not in model_args or "patch_size" not in data_args:
        return
    model, data = model_args["patch_size"], data_args["patch_size"]
    if model is not None and model != data:
        raise ValueError(
            f"model.init_args.patch_size = {model!r} differs from data.init_args.patch_size = {data!r}: the model's patch "
            f"size is the data's; set --data.init_args.patch_size {model} instead (and leave the model's out)"
        )


def _init_from(model, path: str) -> None:
    """Load the network weights of a camhealth weights file or Lightning checkpoint (tensors only) into
    ``model``; the architectures must match (a clear error names the first mismatch)."""
    from camhealth.export import load_module

    source, _ = load_module(Path(path))
    if type(source) is not type(model):
        raise ValueError(f"--init_from {path}: holds a {type(source).__name__}, the config trains a {type(model).__name__}")
    differs = _network_difference(type(model), source.hparams, model.hparams)
    if differs:
        key, theirs, ours = differs
        raise ValueError(f"--init_from {path}: architecture differs from the config's: the file's network has "
                         f"{key} = {theirs!r}, the config's {key} = {ours!r}")
    try:
        model.net.load_state_dict(source.net.state_dict())
    except (RuntimeError, ValueError) as exc:
        raise ValueError(f"--init_from {path}: architecture differs from the config's: {str(exc).splitlines()[0]}") from None


def _plain(value):
    """A network argument for comparison: lists and tuples alike (nested too)."""
    if isinstance(value, (list, tuple)):
        return tuple(_plain(v) for v in value)
    return value


def _network_difference(cls, theirs, ours) -> tuple[str, object, object] | None:
    """The first argument that shapes the network (:data:`camhealth.nets.NETWORKS`) of the LightningModule ``cls``
    whose value differs between the argument mappings ``theirs`` and ``ours`` (an argument one of them does not give
    takes ``cls``'s default), as ``(name, theirs, ours)``; None when the networks are the same."""
    import inspect

    from camhealth.nets import NETWORKS

    spec = NETWORKS.get(getattr(cls, "kind", ""))
    if spec is None:
        return None
    params = inspect.signature(cls.__init__).parameters
    for key in spec.network_args:
        default = params[key].default if key in params else None
        a = theirs.get(key, default) if hasattr(theirs, "get") else default
        b = ours.get(key, default) if hasattr(ours, "get") else default
        if _plain(a) != _plain(b):
            return key, _plain(a), _plain(b)
    return None


def _config_model_class(cfg):
    """The LightningModule class the configuration's ``model:`` names (None where it names none that imports)."""
    import importlib

    model = cfg.get("model") if hasattr(cfg, "get") else None
    class_path = model.get("class_path") if hasattr(model, "get") else None
    if not isinstance(class_path, str) or "." not in class_path:
        return None
    module, name = class_path.rsplit(".", 1)
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError):
        return None


def _check_ckpt_network(saved, cfg, path: Path) -> None:
    """Refuse a checkpoint whose network is not the one the configuration builds, naming the first argument that
    differs (the checkpoint's arguments: its camhealth description's ``init_args``, else Lightning's
    ``hyper_parameters``) — before Lightning's state-dict error, which names no argument."""
    from camhealth.export import ALLOWED_CLASSES

    cls = _config_model_class(cfg)
    if cls is None or getattr(cls, "kind", "") not in ALLOWED_CLASSES.values():
        return
    info = saved.get("camhealth")
    args = info.get("init_args") if isinstance(info, dict) else None
    if not isinstance(args, dict):
        args = saved.get("hyper_parameters")
    if not isinstance(args, dict):
        return
    kind = info.get("kind") if isinstance(info, dict) else None
    if kind is not None and kind != cls.kind:
        raise ValueError(f"--ckpt_path {path}: holds a {kind!r} estimator ({info.get('class_path')}), the config's "
                         f"model is a {cls.kind!r} estimator ({cls.__name__})")
    model_args = (cfg.get("model") or {}).get("init_args") or {}
    differs = _network_difference(cls, args, model_args)
    if differs:
        key, theirs, ours = differs
        raise ValueError(f"--ckpt_path {path}: the checkpoint's network has {key} = {theirs!r}, the config's model "
                         f"{key} = {ours!r}; give the configuration it was trained with (its run's config.yaml) or "
                         f"--model.init_args.{key} {_cli_value(theirs)}")


def _cli_value(value) -> str:
    """``value`` as a command-line argument (a string as it is, lists as JSON; quoted for the shell where needed)."""
    import shlex

    return shlex.quote(value if isinstance(value, str) else json.dumps(value))


def _logger_root(cfg) -> Path:
    """The folder the configured logger writes its versions under (TensorBoard/CSV: ``save_dir/name``)."""
    trainer = cfg.get("trainer") or {}
    logger = trainer.get("logger")
    init = (logger.get("init_args") or {}) if hasattr(logger, "get") else {}
    if init.get("save_dir"):
        return Path(init["save_dir"]) / str(init.get("name") or "")
    return Path(trainer.get("default_root_dir") or ".")


def _checked_ckpt_path(cfg, subcommand: str, with_stream: bool = False) -> str | tuple[str, bool]:
    """The checkpoint ``--ckpt_path`` names (``last``: the newest ``last.ckpt`` under the logger's folder), checked
    to hold plain data only and a network with the configuration's arguments (:func:`_check_ckpt_network`), and for
    ``fit`` to end its learning-rate schedule after ``trainer.max_steps``. For ``fit`` a checkpoint without the state
    of the training data stream (:meth:`datamodules.PatchDataModule.state_dict`) is named in a warning: the resumed
    run draws its batches afresh. ``with_stream``: also return whether the checkpoint holds that state."""
    value = str(cfg["ckpt_path"])
    if value == "last":
        root = _logger_root(cfg)
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
    if not (isinstance(saved, dict) and "state_dict" in saved and "pytorch-lightning_version" in saved):
        raise ValueError(f"--ckpt_path {path}: not a Lightning checkpoint (a weights file, e.g. from --export_weights or "
                         "camhealth.export, has no trainer state to resume); start from its weights with --init_from")
    _check_ckpt_network(saved, cfg, path)
    stream = any(isinstance(v, dict) and isinstance(v.get("train_stream"), dict) for v in saved.values())

    def result(p):
        return (str(p), stream) if with_stream else str(p)

    if subcommand != "fit":
        return result(path)
    # the learning-rate schedule is restored with the step: it cannot run past the steps it was made for
    schedules = saved.get("lr_schedulers")
    total = schedules[0].get("total_steps") if schedules and isinstance(schedules[0], dict) else None
    max_steps = (cfg.get("trainer") or {}).get("max_steps")
    if isinstance(total, int) and (max_steps is None or max_steps < 0 or max_steps >= total):
        beyond = ("trainer.max_steps = -1 (an epoch- or time-limited run) may go beyond it" if max_steps is None or max_steps < 0
                  else f"trainer.max_steps = {max_steps} goes beyond it")
        raise ValueError(
            f"--ckpt_path {path}: its learning-rate schedule ends at step {total - 1} (the run's max_steps), "
            f"{beyond}; resume with max_steps ≤ {total - 1}, or fine-tune from the weights with --init_from (a new "
            f"schedule)"
        )
    if not stream:
        warnings.warn(
            f"--ckpt_path {path}: the checkpoint holds no state of the training data stream (it was written by a run "
            "with DataLoader workers, several processes or gradient accumulation, or by an older camhealth): the "
            "resumed run draws its batches afresh, so it will not end with the weights of an uninterrupted run",
            UserWarning,
            stacklevel=2,
        )
    return result(path)


def with_subcommand(args: Sequence[str]) -> list[str]:
    """``args`` with ``fit`` in front when they start with no subcommand (the bare form is ``fit``; a bare
    ``--help`` stays the overview of the subcommands) and ``--config NAME`` resolved to the packaged config."""
    args = resolve_config_args(args)
    if not args or (args[0] not in SUBCOMMANDS and args[0] not in ("-h", "--help")):
        return ["fit", *args]
    return args


def main(args: Sequence[str] | None = None) -> FitCLI:
    """Parse ``args`` (default: ``sys.argv[1:]``; a subcommand first, else ``fit``) and run the subcommand:
    ``fit`` also tests the best checkpoint and optionally exports it."""
    check_top_level_packages()  # a user's own datamodules/ folder would shadow ours: say so in one line
    from datamodules.patches import PatchDataModule
    from lightning_modules.base import EstimatorModule

    if args is None:  # the command line itself (DDP starts the other ranks with it: they see the subcommand too)
        sys.argv[1:] = with_subcommand(sys.argv[1:])
        argv = None
    else:
        argv = with_subcommand(args)
    _INTERRUPTED.clear()
    try:
        return FitCLI(
            EstimatorModule,
            PatchDataModule,
            subclass_mode_model=True,
            subclass_mode_data=True,
            args=argv,
            seed_everything_default=0,
            save_config_kwargs={"overwrite": True},
            parser_kwargs={"prog": "python -m camhealth.fit", "description": __doc__},
        )
    except SystemExit as exc:
        # Lightning ends a run stopped by Ctrl-C with sys.exit(1) after its graceful shutdown: an interruption, which
        # the command reports as such (run_cli: "interrupted", exit status 130)
        if _INTERRUPTED and exc.code == 1:
            raise KeyboardInterrupt(f"interrupted at step {_INTERRUPTED[-1]}") from None
        raise


if __name__ == "__main__":  # pragma: no cover
    sys.exit(run_cli(main, "python -m camhealth.fit"))
