"""Fixtures of the monitor tests: fast fake estimators with the inference contract, untrained exported
models of the real architectures (behaviour tests only), and a few street-clip frames."""

from __future__ import annotations

import pytest
import torch

from camhealth.inference import assess_patches


class FakeNoise:
    """Noise-source estimator stand-in: σ_total = robust σ of the patch (Haar-diagonal MAD, DN), split
    into PN/DCSN/RN by fixed shares; ξ = ``xi_dn`` (or a function of the call number). Counts patches."""

    kind = "noise_source"
    patch_size = 128
    metadata_set = "full"
    name = "fake_noise"

    def __init__(self, xi_dn: float = 0.0, values=None) -> None:
        self.xi_dn = xi_dn
        self.values = values  # optional list of σ_total per call (overrides the measurement)
        self.calls = 0
        self.patches = 0
        self.last_metadata = None

    def predict(self, patches, metadata=None, precision="fp32", batch_size=256):
        assert patches.ndim == 4 and patches.shape[1:] == (1, self.patch_size, self.patch_size)
        assert patches.dtype == torch.float32 and float(patches.min()) >= 0 and float(patches.max()) <= 1
        if self.metadata_set != "none":
            assert metadata is not None
        self.last_metadata = metadata
        b = patches.shape[0]
        x = patches * 255.0
        d = (x[..., 0::2, 0::2] - x[..., 0::2, 1::2] - x[..., 1::2, 0::2] + x[..., 1::2, 1::2]) / 2
        total = d.abs().flatten(1).median(1).values / 0.6745
        if self.values is not None:
            total = torch.full((b,), float(self.values[self.calls % len(self.values)]))
        share = torch.tensor([0.8, 0.1, 0.5])
        sigma = total[:, None] * share / share.pow(2).sum().sqrt()
        ok, reason = assess_patches(patches, "noise_source")
        self.calls += 1
        self.patches += b
        xi = torch.full((b,), float(self.xi_dn))
        return {"sigma": sigma, "sigma_total": total, "xi": xi, "assessable": ok, "reason": reason}


class FakeMTF:
    """MTF estimator stand-in: MTF falls with frequency at a rate set by the patch's mean gradient."""

    kind = "mtf"
    patch_size = 192
    metadata_set = "none"
    name = "fake_mtf"

    def __init__(self) -> None:
        self.calls = 0
        self.patches = 0

    def predict(self, patches, metadata=None, precision="fp32", batch_size=256):
        b = patches.shape[0]
        g = (patches[..., :, 1:] - patches[..., :, :-1]).abs().flatten(1).mean(1) * 255.0
        f = torch.tensor([0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6])
        h = torch.exp(-f[None] / (0.2 + g[:, None] / 20.0))
        ok, reason = assess_patches(patches, "mtf")
        self.calls += 1
        self.patches += b
        return {"mtf": torch.cat([h, h], 1), "assessable": ok, "reason": reason}


@pytest.fixture
def fake_noise():
    return FakeNoise()


@pytest.fixture
def fake_mtf():
    return FakeMTF()


@pytest.fixture(scope="session")
def model_files(tmp_path_factory):
    """(noise_source_full weights, mtf weights) of untrained networks, exported like the shipped ones."""
    from camhealth.export import export_weights
    from lightning_modules import MTFEstimator, NoiseSourceEstimator

    torch.manual_seed(0)
    d = tmp_path_factory.mktemp("models")
    return export_weights(NoiseSourceEstimator(), d / "ns.pt"), export_weights(MTFEstimator(), d / "mtf.pt")


@pytest.fixture(scope="session")
def street_frames():
    """The first 4 frames of the embedded street clip (1×576×768 each, [0, 1])."""
    from camhealth.data import street_sequence

    return [f for f, _ in street_sequence(max_frames=4)]


def noisy(frame: torch.Tensor, sigma_dn: float, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (frame + torch.randn(frame.shape, generator=g) * sigma_dn / 255.0).clamp(0, 1)


def run_monitor_cli(argv, capsys, *extra):
    """``python -m camhealth.monitor ARGV EXTRA`` in-process: (exit code, stdout, stderr); torch's thread count is
    restored afterwards (the CLI sets it)."""
    from camhealth.monitor.__main__ import main

    n = torch.get_num_threads()
    try:
        code = main([*argv, *extra])
    finally:
        torch.set_num_threads(n)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def models(model_files):
    """CLI options naming the untrained exported models, one thread, no progress bar."""
    ns, mtf = model_files
    return ["--noise-model", str(ns), "--mtf-model", str(mtf), "--no-progress", "--threads", "1"]

