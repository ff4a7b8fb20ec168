"""Packaging: the configs ship inside the wheel and resolve by name, the ``camhealth`` console script dispatches to
the ``python -m`` tools, and a user's own ``datamodules/`` folder that shadows camhealth's is named in one line."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from camhealth.__main__ import main as camhealth_main
from camhealth._packaging import CONFIG_DIR, config_names, packaged_config, resolve_config_args

ROOT = Path(__file__).resolve().parents[1]


def test_the_wheel_holds_the_configs_the_console_script_and_the_declared_dependencies(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path)],
        capture_output=True, text=True, timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    (wheel,) = tmp_path.glob("camhealth-*.whl")
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        meta = next(z.read(n).decode() for n in names if n.endswith(".dist-info/METADATA"))
        entry = next(z.read(n).decode() for n in names if n.endswith(".dist-info/entry_points.txt"))
    shipped = {Path(n).stem for n in names if n.startswith("camhealth/configs/") and n.endswith(".yaml")}
    assert shipped == set(config_names()) and {"noise_source", "mtf", "drne", "iopc"} <= shipped
    assert "camhealth = camhealth.__main__:main" in entry
    assert "Requires-Dist: tqdm" in meta and "Requires-Dist: torch<2.14,>=2.13" in meta
    assert "Requires-Dist: kornia<0.10,>=0.9" in meta
    assert 'Requires-Dist: camhealth[docs,onnx]; extra == "test"' in meta


def test_a_config_name_resolves_to_the_packaged_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # another folder: configs/ is not here
    assert packaged_config("noise_source") == CONFIG_DIR / "noise_source.yaml"
    assert resolve_config_args(["fit", "--config", "noise_source", "-c", "mtf.yaml", "--config=drne"]) == [
        "fit", "--config", str(CONFIG_DIR / "noise_source.yaml"), "-c", str(CONFIG_DIR / "mtf.yaml"),
        f"--config={CONFIG_DIR / 'drne.yaml'}",
    ]
    own = tmp_path / "noise_source"
    own.write_text("seed_everything: 1\n")  # a file of that name in the current folder is the user's
    assert resolve_config_args(["--config", "noise_source", "--config", "sub/x.yaml"]) == [
        "--config", "noise_source", "--config", "sub/x.yaml"]
    with pytest.raises(ValueError, match="noise_sourse: no such file.*packaged: .*noise_source"):
        resolve_config_args(["--config", "noise_sourse"])


def test_console_script_dispatches_to_the_tools(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert camhealth_main(["fit", "--config", "noise_source", "--print_config"]) == 0
    assert "class_path: lightning_modules.NoiseSourceEstimator" in capsys.readouterr().out
    assert camhealth_main(["--help"]) == 0 and "monitor" in capsys.readouterr().out
    assert camhealth_main(["fitt"]) == 2 and "unknown tool 'fitt'" in capsys.readouterr().err
    for name in ("model-card", "model_card"):  # the tool's name, and its module's (python -m camhealth.model_card)
        assert camhealth_main([name, "--help"]) == 0 and "usage: python -m camhealth.model_card" in capsys.readouterr().out


def test_a_users_datamodules_folder_is_named_in_one_line(tmp_path):
    (tmp_path / "datamodules").mkdir()
    (tmp_path / "datamodules" / "__init__.py").write_text("")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-m", "camhealth.fit", "--help"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and f"{tmp_path / 'datamodules'}" in lines[0] and "shadows camhealth's" in lines[0]
