"""`python -m camhealth.fit` on tiny configs: a few optimiser steps of each estimator, best checkpoint,
test after fit, exported weights that load."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import pytest
import torch
from lightning.pytorch.callbacks import Callback

from camhealth.fit import main

TINY = {
    "noise_source.yaml": ["--data.init_args.source_kwargs", "{n_images: 8, size: [80, 80]}"],
    "drne.yaml": ["--data.init_args.source_kwargs", "{n_images: 8, size: [80, 80]}"],
    # blur up to 9 px (13-px kernel): a 32-px patch must be >= 2·kernel_size − 1 (BlurDataModule refuses smaller ones)
    "mtf.yaml": ["--data.init_args.source_kwargs", "{n_images: 8, size: [80, 80]}", "--data.init_args.size_range", "[1.0, 9.0]"],
}


def tiny_args(config: str, tmp: Path, *extra: str) -> list[str]:
    return [
        "--config", f"configs/{config}",
        "--data.init_args.source", "deadleaves",
        *TINY[config],
        "--data.init_args.patch_size", "32",
        "--data.init_args.batch_size", "4",
        "--data.init_args.patches_per_image", "1",
        "--data.init_args.val_patches_per_image", "1",
        "--data.init_args.val_fraction", "0.25",
        "--data.init_args.test_fraction", "0.25",
        "--trainer.max_steps", "2",
        "--trainer.val_check_interval", "2",
        "--trainer.limit_val_batches", "1",
        "--trainer.limit_test_batches", "1",
        "--trainer.precision", "32-true",
        "--trainer.enable_progress_bar", "false",
        "--trainer.logger.init_args.save_dir", str(tmp / "runs"),
        "--trainer.default_root_dir", str(tmp),
        *extra,
    ]


def _no_constants(token):
    raise ValueError(f"{token} in a JSON file")


@pytest.mark.parametrize("config", sorted(TINY))
def test_tiny_fit_writes_checkpoint_results_and_weights(config, tmp_path):
    weights = tmp_path / "model.pt"
    cli = main(tiny_args(config, tmp_path, "--export_weights", str(weights)))
    best = Path(cli.trainer.checkpoint_callback.best_model_path)
    assert best.is_file()
    # strict JSON: a metric without data (the AMAE of a blur family no test patch has) is null, never NaN
    results = json.loads((Path(cli.trainer.log_dir) / "fit_results.json").read_text(), parse_constant=_no_constants)
    assert results["test"] and all(v is None or v == v for v in results["test"].values())
    from camhealth.inference import load_estimator

    est = load_estimator(weights)
    assert est.patch_size == 32
    assert est.description["metrics"] == pytest.approx(results["test"])
    # the file records the test data of its metrics, and a fresh test of the weights measures them again
    evaluation = est.description["evaluation"]
    assert evaluation["precision"] == "32-true" and evaluation.get("limit_test_batches", 1.0) == cli.trainer.limit_test_batches
    assert evaluation["data"]["init_args"]["patch_size"] == 32
    from camhealth.model_card import verify_metrics

    rows = verify_metrics(weights)
    assert rows and all(r["ok"] for r in rows), rows
    if config == "mtf.yaml":  # this tiny test split has no non-linear motion patch
        assert results["test"]["test/amae_nonlinear"] is None and results["test"]["test/amae"] is not None
    # TensorBoard event files were written
    assert list((tmp_path / "runs").rglob("events.out.tfevents.*"))


def test_print_config_and_link(capsys):
    with pytest.raises(SystemExit):
        main(["--config", "configs/noise_source.yaml", "--data.init_args.patch_size", "64", "--print_config"])
    out = capsys.readouterr().out
    assert "class_path: lightning_modules.NoiseSourceEstimator" in out
    assert "patch_size: 64" in out
    # the callbacks are part of the configuration (and so of the config.yaml saved with each run)
    import yaml

    cfg = yaml.safe_load(out)
    assert cfg["checkpoint"]["save_last"] is True and cfg["checkpoint"]["filename"] == "best-step{step}"
    assert cfg["lr_monitor"]["logging_interval"] == "step"
    assert cfg["monitor"] == "val/rms_total"


def test_subcommands_validate_and_test_a_checkpoint_and_the_saved_config_reproduces_the_run(tmp_path):
    cli = main(["fit", *tiny_args("noise_source.yaml", tmp_path, "--test_after_fit", "false")])
    best = cli.trainer.checkpoint_callback.best_model_path
    saved = Path(cli.trainer.log_dir) / "config.yaml"
    import yaml

    cfg = yaml.safe_load(saved.read_text())
    assert cfg["checkpoint"]["save_last"] is True and cfg["monitor"] == "val/rms_total"
    val = cli.trainer.callback_metrics["val/rms_total"].item()
    again = main(["validate", "--config", str(saved), "--ckpt_path", best, "--trainer.logger", "false"])
    assert again.trainer.callback_metrics["val/rms_total"].item() == pytest.approx(val, rel=1e-5)
    tested = main(["test", "--config", str(saved), "--ckpt_path", best, "--trainer.logger", "false"])
    assert "test/rms_total" in tested.trainer.callback_metrics
    # TensorBoard: the monitored metric is the hparams metric
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    (events,) = [e for e in Path(cli.trainer.log_dir).glob("events.out.tfevents.*") if e.stat().st_size > 200][:1]
    acc = EventAccumulator(str(events))
    acc.Reload()
    hp = [e.value for e in acc.Scalars("hp_metric")]
    assert hp[-1] == pytest.approx(val, rel=1e-5)


@pytest.mark.parametrize("cls,n", [("NoiseSourceEstimator", 2), ("MTFEstimator", 1), ("NoiseLevelEstimator", 1)])
def test_example_input_array_runs_through_forward(cls, n):
    import lightning_modules

    model = getattr(lightning_modules, cls)(patch_size=32)
    x = model.example_input_array
    assert len(x) == n and x[0].shape == (1, 1, 32, 32)
    out = model(*x)
    assert all(v.shape[0] == 1 and bool(v.isfinite().all()) for v in out.values())


@pytest.mark.parametrize("name", ["noise_source", "mtf", "drne"])
def test_configs_parse_with_full_variants(name, capsys):
    for cfg in (f"configs/{name}.yaml", *([f"configs/{name}_full.yaml"] if name == "mtf" else [])):
        with pytest.raises(SystemExit):
            main(["--config", cfg, "--print_config"])
        assert "trainer:" in capsys.readouterr().out


def test_threads_below_one_is_refused_before_training(tmp_path):
    """``--threads 0`` was silently torch's default; refused before the model and data are built."""
    for threads in ("0", "-2"):
        with pytest.raises(ValueError, match=f"--threads {threads}: must be >= 1, or null for torch's default"):
            main(tiny_args("noise_source.yaml", tmp_path, "--threads", threads))
    assert not (tmp_path / "runs").exists()


def test_an_empty_config_file_is_named(tmp_path):
    """jsonargparse alone says ``Unexpected config:`` and nothing after it (and prints the usage)."""
    path = tmp_path / "empty.yaml"
    for content in ("", "# nothing yet\n"):
        path.write_text(content)
        for option, argv in (("--config", ["--config", str(path)]), ("-c", ["fit", "-c", str(path)]),
                             ("--config", ["--config", "configs/noise_source.yaml", f"--config={path}"])):
            with pytest.raises(ValueError, match=f"{option} {path}: the file is empty"):
                main(argv)


def test_init_from_fine_tunes_from_weights_and_rejects_another_kind(tmp_path):
    import torch

    from camhealth.export import export_weights
    from lightning_modules import MTFEstimator, NoiseSourceEstimator

    torch.manual_seed(1)
    start = NoiseSourceEstimator(patch_size=32, metadata_set="minimal")
    path = export_weights(start, tmp_path / "start.pt")
    cli = main(tiny_args("noise_source.yaml", tmp_path, "--init_from", str(path), "--trainer.max_steps", "0",
                         "--test_after_fit", "false"))
    for a, b in zip(cli.model.net.state_dict().values(), start.net.state_dict().values()):
        assert torch.equal(a, b)  # no step taken: the weights are the ones loaded
    other = export_weights(MTFEstimator(patch_size=32), tmp_path / "mtf.pt")
    with pytest.raises(ValueError, match="MTFEstimator"):
        main(tiny_args("noise_source.yaml", tmp_path, "--init_from", str(other), "--trainer.max_steps", "0"))


def test_init_from_refuses_another_architecture_whose_shapes_match(tmp_path):
    """Dilations change the network, not its tensor shapes: weights of (1, 2, 4) loaded into a (8, 8, 8) config
    were accepted and answered differently. The network arguments are compared first (lists and tuples alike)."""
    from camhealth.export import export_weights
    from lightning_modules import NoiseLevelEstimator

    path = export_weights(NoiseLevelEstimator(patch_size=32, dilations=(1, 2, 4)), tmp_path / "drne.pt")
    with pytest.raises(ValueError, match=r"--init_from .*drne\.pt: architecture differs from the config's: the file's "
                                         r"network has dilations = \(1, 2, 4\), the config's dilations = \(8, 8, 8\)"):
        main(tiny_args("drne.yaml", tmp_path, "--init_from", str(path), "--model.init_args.dilations", "[8, 8, 8]",
                       "--trainer.max_steps", "0", "--test_after_fit", "false"))
    cli = main(tiny_args("drne.yaml", tmp_path, "--init_from", str(path), "--model.init_args.dilations", "[1, 2, 4]",
                         "--trainer.max_steps", "0", "--test_after_fit", "false"))  # the same network: accepted
    assert cli.trainer.global_step == 0


def _checkpoint_of(module, path: Path) -> Path:
    """A Lightning checkpoint of ``module`` as camhealth.fit writes one (weights, hyperparameters, description)."""
    import lightning
    import torch

    torch.save({"state_dict": {f"net.{k}": v for k, v in module.net.state_dict().items()},
                "pytorch-lightning_version": lightning.__version__, "hyper_parameters": dict(module.hparams),
                "camhealth": {"format": "camhealth-estimator", "version": 1, **module.describe()}}, path)
    return path


@pytest.mark.parametrize("sub", ["test", "fit", "validate"])
def test_ckpt_path_of_another_network_is_refused_naming_the_argument(tmp_path, sub):
    """A checkpoint trained with ``--model.init_args.metadata_set none``, given to the config's Min-Meta model: the
    first network argument that differs, with both values, instead of the first line of Lightning's state-dict
    error."""
    from lightning_modules import NoiseLevelEstimator, NoiseSourceEstimator

    ckpt = _checkpoint_of(NoiseSourceEstimator(patch_size=32, metadata_set="none"), tmp_path / "none.ckpt")
    with pytest.raises(ValueError, match=r"--ckpt_path .*none\.ckpt: the checkpoint's network has metadata_set = "
                                         r"'none', the config's model metadata_set = 'minimal'.*--model\.init_args\.metadata_set none"):
        main([sub, *tiny_args("noise_source.yaml", tmp_path, "--ckpt_path", str(ckpt))])
    ckpt = _checkpoint_of(NoiseLevelEstimator(patch_size=32, dilations=[1, 2, 8]), tmp_path / "drne.ckpt")
    with pytest.raises(ValueError, match=r"dilations = \(1, 2, 8\), the config's model dilations = \(1, 2, 4\)"):
        main([sub, *tiny_args("drne.yaml", tmp_path, "--ckpt_path", str(ckpt))])
    with pytest.raises(ValueError, match=r"holds a 'drne' estimator .*the config's model is a 'noise_source' estimator"):
        main([sub, *tiny_args("noise_source.yaml", tmp_path, "--ckpt_path", str(ckpt))])


def test_ckpt_path_of_the_same_network_is_accepted_lists_and_tuples_alike(tmp_path):
    import torch

    from camhealth.fit import _check_ckpt_network
    from lightning_modules import NoiseLevelEstimator

    path = _checkpoint_of(NoiseLevelEstimator(patch_size=32, dilations=[1, 2, 4]), tmp_path / "d.ckpt")
    saved = torch.load(path, weights_only=True)
    cfg = {"model": {"class_path": "lightning_modules.NoiseLevelEstimator", "init_args": {"dilations": (1, 2, 4)}}}
    _check_ckpt_network(saved, cfg, path)  # no error
    cfg["model"]["init_args"] = {}  # the config gives no dilations: the LightningModule's default, (1, 2, 4)
    _check_ckpt_network(saved, cfg, path)


def test_fit_without_checkpointing_tests_and_exports_the_final_weights(tmp_path):
    """``--trainer.enable_checkpointing false`` (Lightning refuses a ModelCheckpoint then): the configuration's
    checkpoint callback is dropped, no checkpoint is written, and the final weights are tested and exported."""
    import torch

    weights = tmp_path / "final.pt"
    cli = main(tiny_args("noise_source.yaml", tmp_path, "--trainer.enable_checkpointing", "false",
                         "--export_weights", str(weights)))
    assert cli.trainer.global_step == 2
    assert not any(type(c).__name__ == "ModelCheckpoint" for c in cli.trainer.callbacks)
    assert not list(tmp_path.rglob("*.ckpt"))
    results = json.loads((Path(cli.trainer.log_dir) / "fit_results.json").read_text())
    assert results["best_checkpoint"] == "" and results["test"]["test/rms_total"] > 0
    state = torch.load(weights, weights_only=True)["state_dict"]
    final = cli.model.net.state_dict()
    assert state.keys() == final.keys() and all(torch.equal(state[k], final[k]) for k in state)


@pytest.mark.parametrize("config,precision", [("drne.yaml", "64-true"), ("mtf.yaml", "bf16-true")])
def test_true_precisions_train_save_checkpoints_and_export(config, precision, tmp_path):
    """The documented ``--trainer.precision 64-true`` / ``bf16-true`` through the CLI: model summary, validation,
    checkpoints, test after fit and the exported weights."""
    weights = tmp_path / "model.pt"
    cli = main(tiny_args(config, tmp_path, "--trainer.precision", precision, "--export_weights", str(weights)))
    assert Path(cli.trainer.checkpoint_callback.best_model_path).is_file()
    from camhealth.inference import load_estimator

    assert load_estimator(weights).description["metrics"]


def test_mtf_files_with_a_one_direction_regressor_are_refused_naming_what_replaced_them(tmp_path):
    import torch

    from camhealth.export import export_weights, load_net
    from camhealth.inference import load_estimator
    from lightning_modules import MTFEstimator

    path = export_weights(MTFEstimator(patch_size=32), tmp_path / "mtf.pt")
    blob = torch.load(path, weights_only=True)
    # the layout of files written before every regressor read both directions: 3 × 96 inputs, flag False or absent
    blob["state_dict"]["head.0.weight"] = blob["state_dict"]["head.0.weight"][:, : 3 * 96].clone()
    desc = json.loads(blob["description"])
    for flag in (False, None):
        if flag is None:
            desc["init_args"].pop("joint_directions", None)
        else:
            desc["init_args"]["joint_directions"] = flag
        blob["description"] = json.dumps(desc)
        torch.save(blob, tmp_path / "one.pt")
        for load in (load_net, load_estimator):
            with pytest.raises(ValueError, match=r"one direction only.*configs/mtf_full.yaml"):
                load(tmp_path / "one.pt")
    with pytest.raises(ValueError, match=r"one direction only.*configs/mtf_full.yaml"):
        main(tiny_args("mtf.yaml", tmp_path, "--init_from", str(tmp_path / "one.pt"), "--trainer.max_steps", "0"))
    for gone in ("joint_directions", "train_only"):  # the options are gone from the LightningModule
        with pytest.raises(SystemExit):
            main(tiny_args("mtf.yaml", tmp_path, f"--model.init_args.{gone}", "true", "--trainer.max_steps", "0"))


def test_fit_keeps_freed_memory_for_reuse(tmp_path, monkeypatch):
    import camhealth.fit as fit

    calls = []
    monkeypatch.setattr(fit, "keep_freed_memory", lambda: calls.append(1) or True)
    fit.main(tiny_args("noise_source.yaml", tmp_path, "--trainer.max_steps", "0", "--test_after_fit", "false"))
    assert calls == [1]  # the allocator setting of camhealth.runtime, once per run


# ------------------------------------------------------------------ resuming, and checks before training
@pytest.fixture
def sigint_raises():
    """SIGINT raises KeyboardInterrupt during the test (a shell may start a job with SIGINT ignored; Lightning
    ignores it after one), and the handler is restored afterwards."""
    import signal

    before = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def _sigint_at(step: int) -> str:
    return '--trainer.callbacks+={"class_path": "tests._interrupt.SigintAt", "init_args": {"step": %d}}' % step


def test_sigint_writes_last_ckpt_at_that_step_and_ckpt_path_resumes_everything(tmp_path, sigint_raises, capsys):
    import torch

    run = ["--trainer.max_steps", "6", "--trainer.val_check_interval", "4", "--test_after_fit", "false"]
    with pytest.raises(KeyboardInterrupt):  # (Lightning ends it with sys.exit(1); run_cli then says "interrupted", 130)
        main(tiny_args("noise_source.yaml", tmp_path, *run, _sigint_at(3)))
    (last,) = list(tmp_path.rglob("last.ckpt"))
    assert f"resume with --ckpt_path {last}" in capsys.readouterr().err
    saved = torch.load(last, weights_only=True)  # plain data only
    assert saved["global_step"] == 3  # the step reached, not the last validation (there was none yet)
    assert saved["optimizer_states"][0]["state"][0]["step"].item() == 3
    assert saved["lr_schedulers"][0]["last_epoch"] == 3
    elapsed = saved["callbacks"]["Timer"]["time_elapsed"]["train"]
    assert elapsed > 0
    cli = main(tiny_args("noise_source.yaml", tmp_path, *run, "--ckpt_path", str(last)))
    trainer = cli.trainer
    assert trainer.global_step == 6
    assert trainer.optimizers[0].state_dict()["state"][0]["step"].item() == 6  # optimiser continued, not restarted
    assert trainer.lr_scheduler_configs[0].scheduler.last_epoch == 6  # schedule continued
    timer = next(c for c in trainer.callbacks if type(c).__name__ == "Timer")
    assert timer.time_elapsed("train") >= elapsed  # the max_time clock counts the first run too


def test_ckpt_path_last_takes_the_newest_last_ckpt(tmp_path, sigint_raises):
    run = ["--trainer.max_steps", "4", "--test_after_fit", "false"]
    main(tiny_args("noise_source.yaml", tmp_path, *run))  # a finished run: its last.ckpt is at step 4
    with pytest.raises(KeyboardInterrupt):
        main(tiny_args("noise_source.yaml", tmp_path, *run, _sigint_at(3)))  # the newest: step 3
    newest = max(tmp_path.rglob("last.ckpt"), key=lambda p: p.stat().st_mtime)
    assert "version_1" in str(newest)
    cli = main(tiny_args("noise_source.yaml", tmp_path, *run, "--ckpt_path", "last", "--trainer.max_steps", "4"))
    assert cli.trainer.ckpt_path == str(newest) and cli.trainer.global_step == 4
    with pytest.raises(ValueError, match="schedule ends at step 4"):
        main(tiny_args("noise_source.yaml", tmp_path, *run, "--ckpt_path", "last", "--trainer.max_steps", "9"))
    # an epoch-limited resume (max_steps -1) could run past the schedule too: refused before training, not mid-run
    with pytest.raises(ValueError, match=r"max_steps = -1 \(an epoch- or time-limited run\) may go beyond it"):
        main(tiny_args("noise_source.yaml", tmp_path, *run, "--ckpt_path", "last", "--trainer.max_steps", "-1",
                       "--trainer.max_epochs", "1"))


def test_ckpt_path_is_checked(tmp_path):
    import torch

    from tests._evil_files import Payload

    with pytest.raises(FileNotFoundError, match="no such checkpoint"):
        main(tiny_args("noise_source.yaml", tmp_path, "--ckpt_path", str(tmp_path / "missing.ckpt")))
    evil = tmp_path / "evil.ckpt"
    marker = tmp_path / "MARKER"
    torch.save({"state_dict": Payload(marker)}, evil)
    with pytest.raises(ValueError, match="not a checkpoint of plain data") as info:
        main(tiny_args("noise_source.yaml", tmp_path, "--ckpt_path", str(evil)))
    assert not marker.exists() and "weights_only" not in str(info.value)
    with pytest.raises(ValueError, match="no last.ckpt"):
        main(tiny_args("noise_source.yaml", tmp_path / "fresh", "--ckpt_path", "last"))
    weights = tmp_path / "weights.pt"  # plain data, but no trainer state: a weights file
    torch.save({"format": "camhealth-weights", "state_dict": {}}, weights)
    for sub in ([], ["test"]):
        with pytest.raises(ValueError, match="not a Lightning checkpoint .* with --init_from"):
            main([*sub, *tiny_args("noise_source.yaml", tmp_path, "--ckpt_path", str(weights))])


@pytest.mark.parametrize(
    "monitor,extra,when",
    [
        ("val/rms_totl", [], "sanity-check validation"),
        ("val/rms_totl", ["--trainer.num_sanity_val_steps", "0"], "first validation"),
        ("train/lss", [], "first training step"),
    ],
)
def test_a_monitor_that_names_no_logged_metric_is_refused_early(tmp_path, monitor, extra, when):
    with pytest.raises(ValueError, match=f"--monitor '{monitor}' names no metric the model logs \\({when}") as info:
        main(tiny_args("noise_source.yaml", tmp_path, "--monitor", monitor, "--trainer.max_steps", "50", *extra))
    assert ("val/rms_total" if monitor.startswith("val") else "train/loss") in str(info.value)
    import torch

    steps = [torch.load(p, weights_only=True)["global_step"] for p in tmp_path.rglob("*.ckpt")]
    # refused before the first step, after the first step, or at the first validation (step 2), not at step 50
    assert steps == ([2] if when == "first validation" else [1] if when == "first training step" else [])


def test_an_empty_validation_split_is_named_not_blamed_on_the_monitor(tmp_path):
    """``val_fraction 0``: no validation batches. The error said that ``val/rms_total`` (a metric the model logs)
    'names no metric the model logs' and to 'set monitor: to one of them' (an empty list)."""
    with pytest.raises(ValueError, match=r"--monitor 'val/rms_total' is a validation metric, but the validation split "
                                         r"is empty \(0 validation batches\)") as info:
        main(tiny_args("noise_source.yaml", tmp_path, "--data.init_args.val_fraction", "0"))
    assert "names no metric" not in str(info.value)
    assert not list(tmp_path.rglob("*.ckpt"))  # before the first step
    # what the message offers works: a train/ metric without validation
    cli = main(tiny_args("noise_source.yaml", tmp_path, "--data.init_args.val_fraction", "0", "--trainer.limit_val_batches",
                         "0", "--monitor", "train/loss", "--test_after_fit", "false"))
    assert cli.trainer.global_step == 2


def test_fit_only_options_are_refused_by_the_other_subcommands(tmp_path):
    """``test --export_weights PATH`` exited 0 and wrote nothing; ``--test_after_fit`` did nothing outside fit. Given
    on the command line of test/validate/predict they are refused, before anything runs (a run's saved config.yaml,
    which holds the fit's values: the next test)."""
    out = tmp_path / "exported.pt"
    for sub in ("test", "validate", "predict"):
        with pytest.raises(ValueError, match=f"--export_weights is an option of fit; {sub} writes no weights"):
            main([sub, *tiny_args("noise_source.yaml", tmp_path, "--export_weights", str(out))])
    with pytest.raises(ValueError, match="--test_after_fit is an option of fit .*; test does not fit"):
        main(["test", *tiny_args("noise_source.yaml", tmp_path, "--test_after_fit=false")])
    assert not out.exists() and not list(tmp_path.rglob("*.ckpt"))


def test_the_saved_config_of_a_run_tests_its_checkpoint_whatever_fit_options_it_holds(tmp_path):
    """A run's config.yaml holds its ``export_weights`` and, for a fine-tuning run, ``init_from``: ``test --config``
    that file takes the weights from ``--ckpt_path`` and writes none (``--init_from`` on test's command line is
    refused)."""
    import yaml

    weights = tmp_path / "fit.pt"
    cli = main(tiny_args("noise_source.yaml", tmp_path, "--test_after_fit", "false", "--export_weights", str(weights)))
    best = cli.trainer.checkpoint_callback.best_model_path
    saved = Path(cli.trainer.log_dir) / "config.yaml"
    tuned = tmp_path / "tuned.yaml"  # the config.yaml of a run started with --init_from
    tuned.write_text(yaml.safe_dump({**yaml.safe_load(saved.read_text()), "init_from": str(weights)}))
    before = weights.stat().st_mtime_ns
    for config in (saved, tuned):
        tested = main(["test", "--config", str(config), "--ckpt_path", best, "--trainer.logger", "false"])
        assert "test/rms_total" in tested.trainer.callback_metrics and weights.stat().st_mtime_ns == before
    with pytest.raises(ValueError, match="--init_from is an option of fit; test takes the weights from --ckpt_path"):
        main(["test", "--config", str(saved), "--ckpt_path", best, "--trainer.logger", "false", "--init_from", str(weights)])


def test_fit_without_a_logger_runs_without_the_learning_rate_monitor(tmp_path):
    cli = main(tiny_args("noise_source.yaml", tmp_path, "--trainer.logger", "false", "--test_after_fit", "false"))
    assert cli.trainer.global_step == 2
    assert not any(type(c).__name__ == "LearningRateMonitor" for c in cli.trainer.callbacks)


def test_a_train_metric_can_be_monitored(tmp_path):
    cli = main(tiny_args("noise_source.yaml", tmp_path, "--monitor", "train/loss", "--test_after_fit", "false"))
    assert cli.trainer.global_step == 2


# ------------------------------------------------------------------ several processes (DDP)
def _ddp_args(tmp: Path) -> list[str]:
    """Tiny data with an odd number of test patches (3 images × 3), so a padding sampler would repeat one."""
    return [
        "--config", "configs/noise_source.yaml",
        "--data.init_args.source", "deadleaves",
        "--data.init_args.source_kwargs", "{n_images: 12, size: [80, 80]}",
        "--data.init_args.patch_size", "32",
        "--data.init_args.batch_size", "4",
        "--data.init_args.patches_per_image", "2",
        "--data.init_args.val_patches_per_image", "3",
        "--data.init_args.val_fraction", "0.25",
        "--data.init_args.test_fraction", "0.25",
        "--trainer.max_steps", "2",
        "--trainer.val_check_interval", "2",
        "--trainer.precision", "32-true",
        "--trainer.enable_progress_bar", "false",
        "--trainer.logger.init_args.save_dir", str(tmp / "runs"),
        "--trainer.default_root_dir", str(tmp),
        "--model.init_args.log_figures", "false",
        "--threads", "1",
    ]


def test_ddp_on_two_cpu_processes_exits_0_with_own_corruption_per_rank_and_single_process_test_metrics(tmp_path):
    import os
    import subprocess
    import sys

    import torch

    probe = tmp_path / "probe"
    weights = tmp_path / "ddp.pt"
    cmd = [
        sys.executable, "-m", "camhealth.fit", *_ddp_args(tmp_path),
        "--trainer.strategy", "ddp", "--trainer.devices", "2", "--trainer.accelerator", "cpu",
        "--export_weights", str(weights),
        '--trainer.callbacks+={"class_path": "tests._ddp_probe.RecordFirstTrainingBatch", "init_args": {"out": "%s"}}' % probe,
    ]
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-3000:]
    # each rank corrupted its own training batch differently (not the same metadata and noise twice)
    ranks = [torch.load(probe / f"rank{r}.pt", weights_only=True) for r in (0, 1)]
    assert all(r["world_size"] == 2 for r in ranks)
    assert not torch.equal(ranks[0]["meta_raw"], ranks[1]["meta_raw"])
    # side effects once, on rank zero: one results file, the weights file
    (results_file,) = list((tmp_path / "runs").rglob("fit_results.json"))
    results = json.loads(results_file.read_text())
    best = results["best_checkpoint"]
    assert Path(best).is_file() and weights.is_file()
    # the held-out metrics of the best checkpoint equal a single-process test of the same weights
    cli = main(["test", *_ddp_args(tmp_path / "single"), "--ckpt_path", best])
    single = {k: float(v) for k, v in cli.trainer.callback_metrics.items() if k.startswith("test/")}
    assert set(single) == set(results["test"])
    for k, v in single.items():
        assert results["test"][k] == pytest.approx(v, rel=1e-5, abs=1e-6), k


def test_every_config_names_itself_in_its_usage_line():
    """A config's usage line names the config itself, not the one it was copied from."""
    root = Path(__file__).resolve().parents[1] / "configs"
    for config in sorted(root.glob("*.yaml")):
        header = [ln for ln in config.read_text().splitlines() if ln.startswith("#")]
        usage = [ln for ln in header if "--config configs/" in ln]
        if usage:
            assert any(f"--config configs/{config.name}" in ln for ln in usage), (config.name, usage)


def test_an_interrupted_fit_says_so_and_exits_130(tmp_path, sigint_raises, capsys):
    from camhealth._cli import run_cli

    run = ["--trainer.max_steps", "6", "--test_after_fit", "false", _sigint_at(2)]
    assert run_cli(main, "python -m camhealth.fit", tiny_args("noise_source.yaml", tmp_path, *run)) == 130
    err = capsys.readouterr().err
    assert "resume with --ckpt_path" in err and "python -m camhealth.fit: interrupted" in err


@pytest.mark.parametrize("option, value, message", [
    ("--data.init_args.batch_size", "-4", "batch_size = -4 must be a positive int"),
    ("--model.init_args.lr", "-1", "lr = -1.0 must be > 0"),
    ("--data.init_args.xi_probability", "1.5", "xi_probability = 1.5 must be a finite number in [0, 1]"),
    ("--model.init_args.width", "0", "width = 0 must be an integer >= 1"),
    ("--model.init_args.hidden", "[0]", "hidden = (0,) must be integers >= 1"),
])
def test_an_out_of_range_config_value_is_named_in_one_line(tmp_path, capsys, option, value, message):
    """jsonargparse wraps what a DataModule or LightningModule raises in "Does not validate against any of the Union
    subtypes"; the one line is the class's own message, which names the option and its range."""
    from camhealth._cli import run_cli

    code = run_cli(main, "python -m camhealth.fit", tiny_args("noise_source.yaml", tmp_path, option, value))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0] and "Union" not in err[0], err


# ------------------------------------------------------------------ patch size, metadata set, test split, resuming
def test_a_model_patch_size_that_differs_from_the_datas_is_refused_naming_both(tmp_path, capsys):
    """``--model.init_args.patch_size 64`` (or ``model: {init_args: {patch_size: 64}}`` in a config file) was dropped
    by the link from the data's patch size without a word: the run trained at 128 px."""
    match = (r"model.init_args.patch_size = 64 differs from data.init_args.patch_size = 128: the model's patch size is "
             r"the data's; set --data.init_args.patch_size 64 instead")
    with pytest.raises(ValueError, match=match):
        main(["--config", "configs/noise_source.yaml", "--model.init_args.patch_size", "64", "--print_config"])
    extra = tmp_path / "model_patch.yaml"
    extra.write_text("model:\n  init_args:\n    patch_size: 64\n")
    with pytest.raises(ValueError, match=match):
        main(["--config", "configs/noise_source.yaml", "--config", str(extra), "--print_config"])
    with pytest.raises(ValueError, match=match):
        main(["--config", "configs/noise_source.yaml", "--model",
              '{"class_path": "lightning_modules.NoiseSourceEstimator", "init_args": {"patch_size": 64}}'])
    capsys.readouterr()
    with pytest.raises(SystemExit):  # the same value as the data's: nothing is lost
        main(["--config", "configs/noise_source.yaml", "--model.init_args.patch_size", "128", "--print_config"])
    assert capsys.readouterr().out.count("patch_size: 128") == 1


def test_print_config_shows_the_metadata_set_the_run_uses(capsys):
    """``--config noise_source.yaml --config data_noise.yaml --print_config`` showed the data's ``metadata_set: full``
    while the run used the model's ``minimal``."""
    import yaml

    with pytest.raises(SystemExit):
        main(["--config", "configs/noise_source.yaml", "--config", "configs/data_noise.yaml", "--print_config"])
    cfg = yaml.safe_load(capsys.readouterr().out)
    assert cfg["model"]["init_args"]["metadata_set"] == cfg["data"]["init_args"]["metadata_set"] == "minimal"


def _test_split_name(prefix: str) -> str:
    """A file name that tiny_args' split (seed 0, 25 % test) puts in the test split."""
    from camhealth.data.sources import _unit_hash

    return next(f"{prefix}{k}.png" for k in range(1000) if _unit_hash(0, f"{prefix}{k}.png") < 0.25)


def test_a_bad_test_image_stops_the_fit_before_the_first_step(tmp_path):
    """An unreadable image in the test split was found only by the test after the whole training, and the run wrote
    neither fit_results.json nor its --export_weights file."""
    from tests.datamodules.conftest import save_png, textured

    folder = tmp_path / "images"
    for i in range(12):
        save_png(folder / f"img{i:02d}.png", textured(80, i))
    bad = _test_split_name("bad")
    (folder / bad).write_bytes(b"not an image")
    args = ["--data.init_args.source", str(folder), "--data.init_args.source_kwargs", "null"]
    with pytest.raises(ValueError, match=f"cannot load image '{bad}'"):
        main(tiny_args("noise_source.yaml", tmp_path, *args, "--export_weights", str(tmp_path / "w.pt")))
    assert not list(tmp_path.rglob("*.ckpt"))  # before the first step
    cli = main(tiny_args("noise_source.yaml", tmp_path, *args, "--test_after_fit", "false"))  # no test: not read
    assert cli.trainer.global_step == 2


class CopyLastAt(Callback):
    """Copies the run's last.ckpt (ModelCheckpoint's, written at the end of a validation) when step ``step`` begins."""

    def __init__(self, step: int, dest: str) -> None:
        self.step, self.dest = step, dest

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if trainer.global_step == self.step:
            import shutil

            (last,) = list(Path(trainer.log_dir).rglob("last.ckpt"))
            shutil.copy(last, self.dest)


def _resume_args(steps: int = 20) -> list[str]:
    # 4 training images × 5 patches: 5 batches of 4 per epoch; validations after steps 5, 10, 15, 20
    return ["--trainer.max_steps", str(steps), "--trainer.val_check_interval", "5", "--test_after_fit", "false",
            "--data.init_args.patches_per_image", "5", "--trainer.enable_model_summary", "false",
            "--model.init_args.log_figures", "false"]


def _same_weights(a, b) -> bool:
    a, b = a.model.state_dict(), b.model.state_dict()
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("stop", [10, 7])
def test_an_interrupted_and_resumed_fit_ends_with_the_weights_of_an_uninterrupted_one(tmp_path, sigint_raises, stop):
    """The checkpoint held no state of the data stream: the resumed run restarted torch's generator from the seed and
    repeated the crops and corruption of the first steps (max |Δw| 0.14 after 400 steps). Stopped at step 10 (an epoch's
    end, a validation due) and at step 7 (within an epoch), the resumed run ends with the uninterrupted run's weights."""
    full = main(tiny_args("noise_source.yaml", tmp_path / "full", *_resume_args()))
    with pytest.raises(KeyboardInterrupt):
        main(tiny_args("noise_source.yaml", tmp_path / "cut", *_resume_args(), _sigint_at(stop)))
    (last,) = list((tmp_path / "cut").rglob("last.ckpt"))
    saved = torch.load(last, weights_only=True)
    assert saved["global_step"] == stop and saved["NoiseDataModule"]["train_stream"]["step"] == stop
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        resumed = main(tiny_args("noise_source.yaml", tmp_path / "cut", *_resume_args(), "--ckpt_path", str(last)))
    assert resumed.trainer.global_step == 20 and _same_weights(resumed, full)
    # neither camhealth's warning of a stream drawn afresh nor Lightning's of a loader that is not resumable
    assert not [str(w.message) for w in caught if "afresh" in str(w.message) or "not resumable" in str(w.message)]
    if stop == 7:  # a checkpoint without the stream (an older camhealth, workers): resumed afresh, with a warning
        del saved["NoiseDataModule"]
        torch.save(saved, tmp_path / "old.ckpt")
        with pytest.warns(UserWarning, match="holds no state of the training data stream .* draws its batches afresh"):
            afresh = main(tiny_args("noise_source.yaml", tmp_path / "old", *_resume_args(), "--ckpt_path",
                                    str(tmp_path / "old.ckpt")))
        assert afresh.trainer.global_step == 20 and not _same_weights(afresh, full)


def test_a_run_resumed_from_the_last_checkpoint_of_a_validation_ends_with_the_uninterrupted_runs_weights(tmp_path):
    copy = tmp_path / "at10.ckpt"
    callback = '--trainer.callbacks+={"class_path": "tests.test_fit.CopyLastAt", "init_args": {"step": 11, "dest": "%s"}}'
    full = main(tiny_args("noise_source.yaml", tmp_path / "full", *_resume_args(), callback % copy))
    assert torch.load(copy, weights_only=True)["global_step"] == 10  # written after the validation of step 10
    resumed = main(tiny_args("noise_source.yaml", tmp_path / "resumed", *_resume_args(), "--ckpt_path", str(copy)))
    assert resumed.trainer.global_step == 20 and _same_weights(resumed, full)
