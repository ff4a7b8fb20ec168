"""No silent wrong numbers and messages that name the field: 12-bit data in 16-bit files, colour and ambiguous
array layouts, contradictory or mistyped metadata, out-of-range indices, negative PSFs, empty batches, and the
command lines' one-line errors (traceback only with --debug)."""

from __future__ import annotations

import ast
import struct
import warnings
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from camhealth import load_estimator
from camhealth._cli import run_cli
from camhealth.data.io import read_image, read_image_scaled
from camhealth.export import export_weights
from camhealth.physics.metadata import CameraMetadata
from camhealth.physics.mtf import mtf_hv
from lightning_modules import MTFEstimator, NoiseLevelEstimator, NoiseSourceEstimator

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------ 12-bit data in a 16-bit file
def _png16(path: Path, values: np.ndarray, sbit: int | None = None) -> Path:
    Image.fromarray(values.astype(np.uint16)).save(path)
    if sbit is not None:  # add a significant-bits chunk after IHDR
        data = path.read_bytes()
        at = 8 + 8 + 13 + 4
        chunk = b"sBIT" + bytes([sbit])
        path.write_bytes(data[:at] + struct.pack(">I", 1) + chunk + struct.pack(">I", zlib.crc32(chunk)) + data[at:])
    return path


def _twelve_bit_noise(sigma_12bit: float = 80.0, seed: int = 0) -> np.ndarray:
    g = np.random.default_rng(seed)
    return np.clip(np.round(2000 + g.normal(0, sigma_12bit, (64, 64))), 0, 4095)


@pytest.mark.parametrize("sbit", [None, 12])
def test_twelve_bit_data_in_a_16_bit_png_is_read_at_its_level(tmp_path, sbit):
    """80 DN of noise of a 12-bit camera is 80/4095·255 ≈ 5 DN of 8 bits; scaling by 65535 made it 0.3 DN."""
    values = _twelve_bit_noise()
    path = _png16(tmp_path / "d12.png", values, sbit)
    image, scaling = read_image_scaled(path)
    assert (scaling.file_bits, scaling.bits) == (16, 12)
    assert scaling.source == ("sBIT" if sbit else "largest value")
    assert "12-bit data (÷4095" in scaling.describe()
    expected = values.std() / 4095 * 255
    assert float(image.std()) * 255 == pytest.approx(expected, rel=1e-3) and expected > 4.5
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read_image(path)
    assert [str(w.message) for w in caught if "12-bit" in str(w.message)] == ([] if sbit else [
        f"{path}: 16-bit file read as 12-bit data (÷4095, guessed from the largest value {values.max():g}); "
        "pass bit_depth=16 to scale by 65535"])
    forced = read_image(path, bit_depth=16)
    assert float(forced.std()) * 255 == pytest.approx(values.std() / 65535 * 255, rel=1e-3)


def test_bit_depth_is_checked_against_the_data(tmp_path):
    path = _png16(tmp_path / "d12.png", _twelve_bit_noise())
    with pytest.raises(ValueError, match=r"holds values up to \d+ \(more than 1023\)"):
        read_image(path, bit_depth=10)
    with pytest.raises(ValueError, match="bit_depth = 20 must be 'auto' or an integer"):
        read_image(path, bit_depth=20)
    full = _png16(tmp_path / "full.png", np.array([[0, 65535]]))
    assert read_image_scaled(full)[1].describe() == "16-bit file read as 16-bit data (÷65535)"
    eight = tmp_path / "g8.png"
    Image.fromarray(np.array([[0, 255]], np.uint8)).save(eight)
    with pytest.raises(ValueError, match="stores 8-bit values"):
        read_image(eight, bit_depth=12)


# ------------------------------------------------------------------ layouts the estimators take
@pytest.fixture(scope="module")
def noise_est(tmp_path_factory):
    torch.manual_seed(0)
    return load_estimator(export_weights(NoiseSourceEstimator(patch_size=32), tmp_path_factory.mktemp("w") / "ns.pt"))


@pytest.mark.parametrize(
    "shape,match",
    [
        ((3, 32, 32), r"3×32×32 are ambiguous: 3 gray patches \(B×H×W\) or one colour image \(C×H×W"),
        ((4, 32, 32), r"ambiguous"),
        ((32, 32, 3), r"32×32×3 look like an H×W×C colour image \(channels last\)"),
        ((480, 640, 3), r"480×640×3 look like an H×W×C colour image"),
        ((2, 32, 32, 3), r"look like a B×H×W×C colour image"),
        ((2, 3, 32, 32), r"look like a B×C×H×W colour batch"),
        ((2, 2, 32, 32), r"must be B×1×H×W, B×H×W or H×W gray patches, got shape 2×2×32×32"),
    ],
)
@pytest.mark.parametrize("array", ["numpy", "torch"])
def test_colour_and_ambiguous_layouts_are_refused_naming_the_layouts(noise_est, shape, match, array):
    x = np.random.default_rng(0).random(shape, dtype=np.float32)
    with pytest.raises(ValueError, match=match):
        noise_est.predict(x if array == "numpy" else torch.from_numpy(x), "ICX285")


@pytest.mark.parametrize("batch", [1, 2, 5])
def test_gray_layouts_still_agree(noise_est, batch):
    x = torch.rand(batch, 1, 32, 32, generator=torch.Generator().manual_seed(batch)) * 0.6 + 0.2
    ref = noise_est.predict(x, "ICX285")["sigma"]
    assert torch.allclose(noise_est.predict(x[:, 0], "ICX285")["sigma"], ref, atol=1e-6)


@pytest.mark.parametrize("kind", ["noise_source", "drne", "mtf"])
@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_an_empty_batch_returns_empty_outputs(tmp_path, kind, dtype):
    model = {"noise_source": NoiseSourceEstimator, "drne": NoiseLevelEstimator, "mtf": MTFEstimator}[kind](patch_size=32)
    est = load_estimator(export_weights(model, tmp_path / "m.pt"))
    out = est.predict(np.zeros((0, 1, 32, 32), dtype), "ICX285" if kind == "noise_source" else None)
    assert out["assessable"].shape == (0,) and out["reason"] == []
    for key, value in out.items():
        if isinstance(value, torch.Tensor):
            assert value.shape[0] == 0, key
    assert {"noise_source": "sigma", "drne": "sigma_map", "mtf": "mtf"}[kind] in out


# ------------------------------------------------------------------ metadata
@pytest.mark.parametrize(
    "fields,exc,match",
    [
        ({"gain_db": "12"}, TypeError, r"gain_db must be a number in dB .*, got str '12'"),
        ({"gain_db": None}, TypeError, r"gain_db must be a number in dB .*, got NoneType None"),
        ({"exposure_s": [0.01, "x"]}, TypeError, r"exposure_s must be a number in s"),
        ({"sensor_type": "CMOS", "is_cmos": 0}, ValueError, r"sensor_type = 'CMOS' contradicts is_cmos = 0"),
        ({"sensor_type": "CCD", "is_cmos": True}, ValueError, r"sensor_type = 'CCD' contradicts is_cmos = True"),
        ({"sensor_type": 1}, TypeError, r"sensor_type must be 'CCD' or 'CMOS', got int 1"),
    ],
)
def test_metadata_values_name_the_field(fields, exc, match, noise_est):
    with pytest.raises(exc, match=match):
        CameraMetadata.from_dict(fields, base="ICX285")
    with pytest.raises(exc, match=match):  # the same through predict
        noise_est.predict(torch.rand(1, 1, 32, 32), fields, base_preset="ICX285")


def test_agreeing_sensor_type_and_is_cmos_are_accepted():
    assert CameraMetadata.from_dict({"sensor_type": "CMOS", "is_cmos": 1}, base="ICX285").is_cmos.item() == 1.0
    assert CameraMetadata.from_dict({"sensor_type": "ccd", "is_cmos": 0.0}, base="EV76C661").is_cmos.item() == 0.0


@pytest.mark.parametrize("batch", [1, 3])
def test_metadata_index_out_of_range_raises_index_error(batch):
    meta = CameraMetadata.preset("ICX285", batch_size=batch, gain_db=torch.linspace(0, 12, batch))
    for i in (batch, 5, -batch - 1):
        with pytest.raises(IndexError, match=f"metadata index {i} is out of range for batch size {batch}"):
            meta[i]
    assert meta[-1].gain_db.item() == meta.gain_db[-1].item() and meta[0].batch_size == 1


# ------------------------------------------------------------------ PSFs
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_mtf_hv_refuses_negative_psfs(dtype):
    psf = torch.zeros(2, 5, 5, dtype=dtype)
    psf[:, 2, 2] = 1.0
    assert mtf_hv(psf).shape == (2, 16)
    psf[1, 1, 3] = -0.2
    with pytest.raises(ValueError, match="psf must be non-negative .* kernel 1 has -0.2 at row 1, column 3"):
        mtf_hv(psf)
    tiny = torch.zeros(1, 3, 3, dtype=dtype)
    tiny[0, 1, 1] = 1.0
    tiny[0, 0, 0] = -1e-9  # rounding, not a negative lobe
    assert bool((mtf_hv(tiny) <= 1 + 1e-6).all())


# ------------------------------------------------------------------ command lines
CLIS = {
    "camhealth.fit": ["--config", "configs/noise_source.yaml", "--ckpt_path", "/nonexistent/last.ckpt"],
    "camhealth.export": ["/nonexistent/model.ckpt"],
    "camhealth.evaluate": ["--quick", "--source", "/nonexistent/folder", "--methods", "pca", "--no-progress",
                           "--out", "/tmp/never-written"],
    "camhealth.monitor": ["/nonexistent/clip.mp4"],
    "camhealth.corrupt": ["/nonexistent/folder", "--out", "/tmp/never-written"],
    "camhealth.demo": ["closed-loop", "--iopc", "/nonexistent/iopc.json"],
    "camhealth.iopc": ["--source", "/nonexistent/folder", "--out_dir", "/tmp/never-written"],
    "camhealth.model_card": ["/nonexistent/model.pt", "--command", "python -m camhealth.fit"],
    "camhealth.calibrate": ["/nonexistent/dark_200ms_0dB_25C", "--out", "/tmp/never-written/camera.yaml"],
}

#: CLIs whose main lives in the package's ``__main__.py`` (the others: ``camhealth/<tool>.py``; iopc: ``cli.py``)
PACKAGES = ("camhealth.iopc", "camhealth.monitor", "camhealth.calibrate")


def _main_of(module: str):
    import importlib

    mod = importlib.import_module("camhealth.iopc.cli" if module == "camhealth.iopc" else
                                  f"{module}.__main__" if module in PACKAGES else module)
    return mod.main


@pytest.mark.parametrize("module", sorted(CLIS))
def test_cli_errors_are_one_line_and_debug_shows_the_traceback(module, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)
    argv = [a.replace("/tmp/never-written", str(tmp_path / "out")) for a in CLIS[module]]
    prog = f"python -m {module}"
    code = run_cli(_main_of(module), prog, argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "error:" in err[0] and "Traceback" not in err[0], err
    assert "nonexistent" in err[0]
    try:  # --debug: the exception itself, or its traceback printed
        run_cli(_main_of(module), prog, [*argv, "--debug"])
    except SystemExit as exc:
        assert exc.code not in (0, None)
        assert "Traceback (most recent call last)" in capsys.readouterr().err
    except Exception as exc:  # noqa: BLE001
        assert exc.__traceback__ is not None
    else:
        assert "Traceback (most recent call last)" in capsys.readouterr().err


@pytest.mark.parametrize("module", sorted(CLIS))
def test_every_cli_entry_point_goes_through_run_cli(module):
    path = ROOT / (module.replace(".", "/") + ("/__main__.py" if module in PACKAGES else ".py"))
    tree = ast.parse(path.read_text())
    guards = [n for n in tree.body if isinstance(n, ast.If) and "__main__" in ast.unparse(n.test)]
    text = ast.unparse(guards[0]) if guards else ""
    if module == "camhealth.monitor":  # main() itself runs through run_cli
        text += ast.unparse(next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "main"))
    assert "run_cli(" in text, f"{path}: the __main__ block does not use camhealth._cli.run_cli"


def test_a_cli_run_as_a_module_prints_one_line(tmp_path):
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-m", "camhealth.export", str(tmp_path / "missing.ckpt")], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 2 and run.stderr.strip().splitlines() == [f"error: no such file: {tmp_path / 'missing.ckpt'}"]
    debug = subprocess.run([sys.executable, "-m", "camhealth.export", str(tmp_path / "missing.ckpt"), "--debug"],
                           cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert debug.returncode != 0 and "Traceback (most recent call last)" in debug.stderr


def test_a_file_where_a_folder_belongs_and_files_that_are_no_torch_files_are_named():
    """A file where an output folder is to be made gave a bare "[Errno 17] File exists"; a folder as a checkpoint
    "no such file"; a text file renamed .ckpt "the tensors-only reader stopped: 101"."""
    from camhealth._cli import one_line

    exc = FileExistsError(17, "File exists", "/tmp/run/out")
    assert one_line(exc) == "/tmp/run/out is a file, where a folder was to be made or written into: name a folder, or move the file"
    assert one_line(NotADirectoryError(20, "Not a directory", "/tmp/x")).startswith("/tmp/x is a file, where a folder")


def test_a_folder_or_a_text_file_as_a_checkpoint_is_named(tmp_path):
    from camhealth.export import _safe_load

    with pytest.raises(ValueError, match=rf"{tmp_path} is a folder; name a checkpoint \(.ckpt\) or weights file \(.pt\) in it"):
        _safe_load(tmp_path)
    text = tmp_path / "notes.ckpt"
    text.write_text("hello\n")
    with pytest.raises(ValueError, match=r"it is no torch file: neither a zip archive nor a pickle, it begins with b'hello\\n'"):
        _safe_load(text)
