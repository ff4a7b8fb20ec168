"""Inference imports no training framework: loading every shipped estimator, the monitor API on one frame and the
monitor CLI on one image leave ``lightning``, ``lightning_modules`` and ``datamodules`` out of ``sys.modules``.

Each check runs in a fresh interpreter (the test session itself imports Lightning)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.monitor.test_api import noise_sensitive_iopc

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = ("lightning", "lightning_modules", "datamodules", "pytorch_lightning")
FRAME = ROOT / "camhealth" / "data" / "street" / "vtest_0100.png"

API_SCRIPT = r"""
import json, sys
import torch
import camhealth
from camhealth.data import street_sequence
from camhealth.inference import PHYSICS_NOISE_MODEL, shipped_models
from camhealth.monitor import Monitor

names = sorted([*shipped_models(), PHYSICS_NOISE_MODEL])
g = torch.Generator().manual_seed(0)
outputs = {}
for name in names:
    est = camhealth.load_estimator(name)
    p = est.patch_size
    patches = (0.3 + 0.4 * torch.rand(2, 1, p, p, generator=g)).clamp(0, 1)
    meta = None if est.metadata_set == "none" else "ICX285"
    out = est.predict(patches, meta)
    key = "mtf" if est.kind == "mtf" else "sigma_total"
    outputs[name] = [est.kind, getattr(est, "backend", "physics"), list(out[key].shape), bool(torch.isfinite(out[key]).all())]
frame = next(iter(street_sequence(max_frames=1)))[0][:, :384, :384]
reports = []
for noise in ("noise_source_full", "noise_source_min", "drne"):
    report = Monitor(noise_model=noise, sensor="ICX285", precision="fp32", warmup=False).process(frame)
    reports.append(json.loads(report.to_json()))
loaded = sorted({m.split(".")[0] for m in sys.modules})
print(json.dumps({"names": names, "outputs": outputs, "reports": reports, "top_level_modules": loaded}))
"""


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def test_loading_every_shipped_estimator_and_the_monitor_api_import_no_lightning():
    run = subprocess.run([sys.executable, "-c", API_SCRIPT], cwd=ROOT, env=_env(), capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert {"mtf", "drne", "noise_source_min", "noise_source_none", "noise_source_full"} <= set(result["names"])
    for name, (kind, backend, shape, finite) in result["outputs"].items():
        assert finite, name
        assert shape[0] == 2, (name, shape)
        assert backend in ("torch", "physics"), (name, backend)
    assert result["outputs"]["mtf"][2] == [2, 16]
    for report in result["reports"]:
        assert report["size"] == [384, 384]
        assert "noise" in report and "mtf" in report
    leaked = set(FORBIDDEN) & set(result["top_level_modules"])
    assert not leaked, sorted(leaked)
    assert "camhealth" in result["top_level_modules"]  # the check looks at the right list


@pytest.mark.parametrize("policy", [False, True])
def test_monitor_cli_imports_no_lightning(tmp_path, policy):
    """The real CLI process: ``python -X importtime`` lists every module it imports (on stderr). With ``--iopc`` the
    monitor also gives exposure/gain advice from an IOPC file (camhealth.control, camhealth.iopc's curves)."""
    extra = ["--iopc", str(noise_sensitive_iopc(tmp_path))] if policy else []
    run = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "camhealth.monitor", str(FRAME), "--sensor", "ICX285",
         "--noise-model", "noise_source_min", "--precision", "fp32", "--threads", "1", "--no-progress", *extra],
        cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=600,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    lines = [json.loads(line) for line in run.stdout.splitlines() if line.startswith("{")]
    assert len(lines) == 1 and lines[0]["frame"] == 0 and "noise" in lines[0]
    assert (lines[0]["advice"] is not None) == policy
    imported = {line.rsplit("|", 1)[1].strip() for line in run.stderr.splitlines() if line.startswith("import time:")}
    imported.discard("imported package")  # the header line
    assert "camhealth.monitor.api" in imported and "camhealth.nets" in imported  # the list is the CLI's imports
    if policy:
        assert "camhealth.control" in imported and "camhealth.iopc.curves" in imported
    leaked = sorted(m for m in imported if m.split(".")[0] in FORBIDDEN)
    assert not leaked, leaked
