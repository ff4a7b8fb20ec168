"""Model cards: one template for every shipped file, and the command on each card trains exactly that file."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
import torch
import yaml

from camhealth.export import export_weights
from camhealth.inference import shipped_models
from camhealth.model_card import SECTIONS, card_text, main, read_card
from lightning_modules import NoiseSourceEstimator

ROOT = Path(__file__).resolve().parents[1]
WEIGHTS = ROOT / "camhealth" / "weights"
SHIPPED = sorted(p for p in WEIGHTS.glob("*.pt"))


def _fit_command(command: str) -> list[str]:
    """The arguments of the last ``python -m camhealth.fit`` in a card's command (stages are chained with &&)."""
    stages = [shlex.split(s) for s in command.split("&&")]
    fits = [s for s in stages if s[:3] == ["python", "-m", "camhealth.fit"]]
    assert fits, f"no `python -m camhealth.fit` in {command!r}"
    return fits[-1][3:]


def _config_init_args(args: list[str]) -> dict:
    """model.init_args of the config named by --config with the command's --model.init_args.* overrides applied."""
    config = ROOT / args[args.index("--config") + 1]
    init = dict(yaml.safe_load(config.read_text())["model"]["init_args"])
    for i, a in enumerate(args):
        if a.startswith("--model.init_args."):
            init[a.removeprefix("--model.init_args.")] = yaml.safe_load(args[i + 1])
    return init


def test_every_model_is_shipped_with_a_card():
    assert {p.stem for p in SHIPPED} == set(shipped_models())
    assert {p.stem for p in WEIGHTS.glob("*.md")} == {p.stem for p in SHIPPED}


@pytest.mark.parametrize("weights", SHIPPED, ids=lambda p: p.stem)
def test_shipped_card_follows_the_template(weights):
    text = weights.with_suffix(".md").read_text(encoding="utf-8")
    headings = re.findall(r"^## (.+)$", text, flags=re.M)
    assert headings[: len(SECTIONS) - 1] == list(SECTIONS[:-1]), headings
    assert not re.search(r"session \d", text, flags=re.I)


@pytest.mark.parametrize("weights", SHIPPED, ids=lambda p: p.stem)
def test_card_command_trains_the_shipped_hyper_parameters(weights):
    """The config the card names, with the card's own overrides, gives exactly the stored architecture arguments:
    configs train what ships."""
    command, _ = read_card(weights.with_suffix(".md"))
    args = _fit_command(command)
    assert args[args.index("--export_weights") + 1] == f"camhealth/weights/{weights.name}"
    stored = torch.load(weights, weights_only=True)["description"]
    import json

    stored = json.loads(stored) if isinstance(stored, str) else stored
    expected = _config_init_args(args)
    unknown = set(expected) - set(stored["init_args"])
    assert not unknown, f"config names arguments the shipped file does not have: {unknown}"
    for key, value in expected.items():
        assert stored["init_args"][key] == value, (weights.name, key, stored["init_args"][key], value)
    # every argument the file stores is fixed by the config (patch_size comes from the data, linked)
    assert set(stored["init_args"]) - set(expected) <= {"patch_size"}


def test_card_sections_and_refresh_keep_command_and_notes(tmp_path):
    path = export_weights(NoiseSourceEstimator(patch_size=32), tmp_path / "m.pt", metrics={"test/rms_total": 0.42})
    text = card_text(path, "python -m camhealth.fit --config configs/noise_source.yaml", "two stages",
                     timing={"fp32": 1.0, "bf16": 0.5})
    assert re.findall(r"^## (.+)$", text, flags=re.M) == list(SECTIONS)
    assert "test/rms_total | 0.420" in text and "GFLOP" in text and "1.00 ms/patch fp32" in text
    assert "Trunk activity" in text and "— dead" not in text  # a fresh trunk is alive
    path.with_suffix(".md").write_text(text, encoding="utf-8")
    main([str(path), "--refresh"])
    assert read_card(path.with_suffix(".md")) == ("python -m camhealth.fit --config configs/noise_source.yaml", "two stages")


def test_refresh_of_a_card_without_a_command_names_the_file(tmp_path):
    path = export_weights(NoiseSourceEstimator(patch_size=32), tmp_path / "m.pt")
    path.with_suffix(".md").write_text("# Model card\n\nno command here\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"m\.md.*reproduce command"):
        main([str(path), "--refresh"])


@pytest.mark.parametrize("argv", [[], ["--command", "python -m camhealth.fit", "--refresh"]])
def test_exactly_one_of_command_and_refresh(tmp_path, argv):
    path = export_weights(NoiseSourceEstimator(patch_size=32), tmp_path / "m.pt")
    with pytest.raises(ValueError, match="either --command .* or --refresh"):
        main([str(path), *argv])


@pytest.mark.filterwarnings("ignore:.*found in sys.modules after import of package")  # (runpy: already imported)
def test_cli_bad_weights_file_is_one_line_exit_2(tmp_path, monkeypatch, capsys):
    """``python -m camhealth.model_card`` (run as the module, through the console script's dispatcher): a missing,
    non-checkpoint or code-carrying file is one error line naming it, exit status 2, and nothing in it runs."""
    import sys

    from camhealth.__main__ import main as camhealth_main
    from tests._evil_files import Payload

    monkeypatch.setattr(sys, "argv", list(sys.argv))  # (the dispatcher sets the tool's command line)
    marker = tmp_path / "MARKER"
    torch.save({"state_dict": Payload(marker)}, tmp_path / "evil.pt")
    (tmp_path / "notes.pt").write_text("not a checkpoint")
    for name, message in (("missing.pt", "no estimator named or at"), ("notes.pt", "not a camhealth checkpoint"),
                          ("evil.pt", "camhealth never unpickles")):
        assert camhealth_main(["model-card", str(tmp_path / name), "--command", "python -m camhealth.fit"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("python -m camhealth.model_card: error: ") and name in err[0], err
        assert message in err[0] and "weights_only" not in err[0]
    assert not marker.exists() and not (tmp_path / "evil.md").exists()


def test_card_says_no_samples_for_a_metric_without_data(tmp_path):
    """A blur family with no test sample has no AMAE (null in the file): the card says so instead of a number."""
    from lightning_modules import MTFEstimator

    path = export_weights(MTFEstimator(patch_size=32), tmp_path / "m.pt",
                          metrics={"test/amae": 4.25, "test/amae_nonlinear": float("nan")})
    text = card_text(path, "python -m camhealth.fit --config configs/mtf.yaml", timing={"fp32": 1.0, "bf16": 0.5})
    assert "| test/amae_nonlinear | no samples |" in text and "| test/amae | 4.250 |" in text
    assert re.search(r"\bnan\b", text, flags=re.I) is None


def test_a_shipped_name_means_its_file_in_the_package(tmp_path, monkeypatch):
    """``python -m camhealth.model_card drne`` was refused with "no estimator named or at 'drne': shipped names are
    ['drne', …]", and ``drne --refresh`` looked for ./drne.md. A shipped name now stands for its file in
    camhealth/weights (as load_estimator reads it); nothing is written here (write_card is replaced)."""
    import camhealth.model_card as mc

    monkeypatch.chdir(tmp_path)  # no drne.pt / drne.md here
    written = []

    def fake_write(weights, command, notes=""):
        written.append((Path(weights), command, notes))
        return Path(weights).with_suffix(".md")

    monkeypatch.setattr(mc, "write_card", fake_write)
    command, notes = read_card(WEIGHTS / "drne.md")
    assert mc.main(["drne", "--refresh"]) == WEIGHTS / "drne.md"
    assert written == [(WEIGHTS / "drne.pt", command, notes)]
    mc.main(["mtf", "--command", "python -m camhealth.fit --config configs/mtf_full.yaml"])
    assert written[-1][0] == WEIGHTS / "mtf.pt"
    with pytest.raises(ValueError, match=r"'noise_source_full' is the closed-form noise model: it has no weights file"):
        mc.main(["noise_source_full", "--command", "python -m camhealth.fit"])
    assert mc.weights_path("nosuch") == Path("nosuch")  # left to the loader's "no estimator named or at" error
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("weights", SHIPPED, ids=lambda p: p.stem)
def test_shipped_training_data_section_is_what_a_regenerated_card_writes(weights):
    """The card's "Training data" paragraph is model_card's text for its kind, so a refresh keeps it."""
    from camhealth.model_card import _DATA

    text = weights.with_suffix(".md").read_text(encoding="utf-8")
    kind = re.search(r"^- \*\*Kind\*\*: (\w+) ", text, flags=re.M).group(1)
    section = re.search(r"## Training data\n\n(.*?)\n\n## ", text, flags=re.S).group(1)
    assert section == _DATA[kind]


def test_mtf_card_states_the_noise_order_its_config_uses():
    """The card said "Half of the samples get sensor noise after the blur", but configs/mtf_full.yaml keeps
    noise_order: physical (Fig. 3.7), where a motion-blurred sample's photon noise comes before the blur."""
    from camhealth.model_card import _DATA

    init = yaml.safe_load((ROOT / "configs" / "mtf_full.yaml").read_text())["data"]["init_args"]
    assert init.get("noise", False) and init.get("noise_order", "physical") == "physical"
    command, notes = read_card(WEIGHTS / "mtf.md")
    assert "configs/mtf_full.yaml" in command
    for text in (notes, _DATA["mtf"]):
        assert "after the blur" not in text and "Fig. 3.7 order" in text and "photon noise" in text


def test_card_says_how_a_file_that_is_not_shipped_loads_and_in_which_format(tmp_path):
    """A card of an .onnx file said "Format: camhealth weights (torch.load(weights_only=True) …)" and "Load:
    camhealth.load_estimator('ns')" — wrong for ONNX, and the Load line wrong for any file that is not shipped."""
    from types import SimpleNamespace

    from camhealth.model_card import _format_line

    path = export_weights(NoiseSourceEstimator(patch_size=32), tmp_path / "m.pt")
    text = card_text(path, "python -m camhealth.fit", timing={"fp32": 1.0, "bf16": 0.5})
    assert f"- **Load**: `camhealth.load_estimator({str(path)!r})`." in text
    assert "- **Format**: camhealth weights (`torch.load(weights_only=True)`" in text
    shipped = card_text("drne", "python -m camhealth.fit", timing={"fp32": 1.0, "bf16": 0.5})
    assert "- **Load**: `camhealth.load_estimator('drne')` (no network access)." in shipped
    assert _format_line(SimpleNamespace(backend="onnx", source="x.onnx")).startswith("- **Format**: ONNX (ONNX Runtime")
    assert _format_line(SimpleNamespace(backend="pt2", source="x.pt2")).startswith("- **Format**: exported program")
    assert "Lightning checkpoint" in _format_line(SimpleNamespace(backend="torch", source="run/best.ckpt"))


# ---- --verify: the stored metrics measured again -------------------------------------------------------------------

_TINY_EVALUATION = {
    "data": {"class_path": "datamodules.NoiseDataModule",
             "init_args": {"source": "deadleaves", "source_kwargs": {"n_images": 8, "size": [80, 80]}, "patch_size": 32,
                           "batch_size": 4, "patches_per_image": 1, "val_patches_per_image": 1, "val_fraction": 0.25,
                           "test_fraction": 0.25, "seed": 0, "metadata_set": "none"}},
    "precision": "32-true",
}


def _tiny_drne(tmp_path, metrics, evaluation=_TINY_EVALUATION):
    from lightning_modules import NoiseLevelEstimator

    torch.manual_seed(0)
    return export_weights(NoiseLevelEstimator(patch_size=32, width=4, dilations=(1,)), tmp_path / "drne.pt",
                          metrics=metrics, evaluation=evaluation)


def test_verify_reproduces_the_measured_metrics_and_names_a_stale_one(tmp_path, capsys):
    from camhealth.model_card import verify_metrics

    first = verify_metrics(_tiny_drne(tmp_path, {"test/rms_total": 1.0, "test/bias_total": 0.0}))
    measured = {r["metric"]: r["measured"] for r in first}
    assert all(v is not None and v == v for v in measured.values())
    # the measured values stored: every one reproduced, the CLI exits 0
    path = _tiny_drne(tmp_path, measured)
    assert all(r["ok"] for r in verify_metrics(path))
    assert main([str(path), "--verify"]) == path
    assert "all 2 stored metrics reproduced" in capsys.readouterr().out
    # one number off by more than atol + rtol·|stored|: exit 1, the table and the line name it
    stale = _tiny_drne(tmp_path, {**measured, "test/rms_total": measured["test/rms_total"] * 1.5 + 0.05})
    with pytest.raises(SystemExit) as exc:
        main([str(stale), "--verify"])
    assert exc.value.code == 1
    out = capsys.readouterr().out
    assert "| test/rms_total |" in out and "**NO**" in out and "1 of 2 stored metrics differ" in out
    assert "test/rms_total" in out.splitlines()[-1] and "test/bias_total" not in out.splitlines()[-1]
    # within the tolerance given: reproduced
    assert main([str(stale), "--verify", "--rtol", "0.6", "--atol", "0.1"]) == stale


def test_verify_a_null_metric_must_stay_without_data(tmp_path):
    from camhealth.model_card import verify_metrics

    rows = verify_metrics(_tiny_drne(tmp_path, {"test/rms_total": None, "test/not_logged": None, "test/other": 1.0}))
    by = {r["metric"]: r for r in rows}
    assert not by["test/rms_total"]["ok"] and by["test/rms_total"]["measured"] is not None  # stored null, now data
    assert by["test/not_logged"]["ok"] and by["test/not_logged"]["measured"] is None  # null and not logged: agree
    assert not by["test/other"]["ok"]  # stored a number the run does not log


def test_verify_needs_metrics_and_an_evaluation(tmp_path):
    from camhealth.model_card import verify_metrics

    no_metrics = _tiny_drne(tmp_path, None)
    with pytest.raises(ValueError, match="records no metrics to verify"):
        verify_metrics(no_metrics)
    no_record = _tiny_drne(tmp_path, {"test/rms_total": 1.0}, evaluation=None)
    with pytest.raises(ValueError, match="records no evaluation .*--data-config CONFIG"):
        verify_metrics(no_record)
    with pytest.raises(FileNotFoundError, match="--data-config .*missing.yaml.*no such file"):
        verify_metrics(no_record, tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("trainer: {precision: 32-true}\n")
    with pytest.raises(ValueError, match="has no 'data:' section"):
        verify_metrics(no_record, bad)
    with pytest.raises(ValueError, match="rtol = -0.1 must be a finite number"):
        verify_metrics(no_record, rtol=-0.1)
    with pytest.raises(ValueError, match="--data-config is an option of --verify"):
        main([str(no_record), "--refresh", "--data-config", str(bad)])
    with pytest.raises(ValueError, match="--verify writes no card"):
        main([str(no_record), "--verify", "--refresh"])


def test_verify_with_a_fit_config_for_a_file_that_records_none(tmp_path):
    """``--data-config``: the data and precision of a fit config (the tiny split written as one)."""
    from camhealth.model_card import verify_metrics

    config = tmp_path / "tiny.yaml"
    config.write_text(yaml.safe_dump({"data": _TINY_EVALUATION["data"], "trainer": {"precision": "32-true"}}))
    measured = {r["metric"]: r["measured"] for r in verify_metrics(_tiny_drne(tmp_path, {"test/rms_total": 1.0}))}
    path = _tiny_drne(tmp_path, measured, evaluation=None)
    assert all(r["ok"] for r in verify_metrics(path, config))


@pytest.mark.parametrize("entry, match", [
    ({"data": {"class_path": "os.system", "init_args": {}}, "precision": "32-true"}, "class_path = 'os.system' must be one of"),
    ({"data": {"class_path": "datamodules.PatchDataModule", "init_args": {}}, "precision": "32-true"}, "must be one of"),
    ({"data": {"class_path": "datamodules.NoiseDataModule", "init_args": []}, "precision": "32-true"}, "init_args must be a JSON object"),
    ({"data": {"class_path": "datamodules.NoiseDataModule"}, "precision": "32-true"}, "exactly 'class_path' and 'init_args'"),
    ({"data": {"class_path": "datamodules.NoiseDataModule", "init_args": {}}, "precision": "fp32"}, "precision = 'fp32' must be one of"),
    ({"data": {"class_path": "datamodules.NoiseDataModule", "init_args": {}}, "precision": "32-true", "callback": "x"}, "unknown keys \\['callback'\\]"),
    ({"data": {"class_path": "datamodules.NoiseDataModule", "init_args": {}}, "precision": "32-true", "limit_test_batches": 0}, "limit_test_batches = 0 must be"),
    ({"data": {"class_path": "datamodules.NoiseDataModule", "init_args": {}}, "precision": "32-true", "limit_test_batches": 1.5}, "limit_test_batches = 1.5 must be"),
    (["datamodules.NoiseDataModule"], "must be a JSON object with 'data' and 'precision'"),
])
def test_a_file_names_no_other_evaluation_class_and_no_bad_field(tmp_path, entry, match):
    """The evaluation is checked at export and at every load: a file cannot make the verifier import another class."""
    import json

    from camhealth.export import set_description_entries
    from camhealth.inference import load_estimator

    with pytest.raises(ValueError, match=match):
        _tiny_drne(tmp_path, {"test/rms_total": 1.0}, evaluation=entry)
    with pytest.raises(ValueError, match=match):
        set_description_entries(_tiny_drne(tmp_path, None, evaluation=None), {"evaluation": entry})
    path = _tiny_drne(tmp_path, {"test/rms_total": 1.0}, evaluation=None)
    obj = torch.load(path, weights_only=True)
    desc = json.loads(obj["description"])
    desc["evaluation"] = entry
    obj["description"] = json.dumps(desc)
    torch.save(obj, path)
    with pytest.raises(ValueError, match="description evaluation .*" + match):
        load_estimator(path)


@pytest.mark.parametrize("weights", SHIPPED, ids=lambda p: p.stem)
def test_every_shipped_file_records_the_test_data_of_its_metrics(weights):
    from camhealth.export import check_evaluation

    desc = torch.load(weights, weights_only=True)["description"]
    import json

    desc = json.loads(desc)
    assert desc["metrics"] and check_evaluation(desc["evaluation"])["precision"] == "bf16-mixed"


@pytest.mark.slow
@pytest.mark.parametrize("weights", SHIPPED, ids=lambda p: p.stem)
def test_every_shipped_card_metric_is_reproduced(weights):
    """The numbers a shipped file stores (and its card prints) are what a fresh test of its weights measures
    (``python -m camhealth.model_card NAME --verify``; 10–50 s each on 2 cores)."""
    from camhealth.model_card import verify_metrics

    rows = verify_metrics(weights)
    assert all(r["ok"] for r in rows), [r for r in rows if not r["ok"]]
