"""NoiseLevelEstimator (DRNE) on bad input: images and labels it refuses, each error naming what it refuses; an
empty batch gives empty outputs."""

from __future__ import annotations

import pytest
import torch

from camhealth.physics.metadata import CameraMetadata
from datamodules.noise import metadata_matrix
from lightning_modules import NoiseLevelEstimator
from lightning_modules.drne import sigma_map_target_dn

P = 32


@pytest.fixture
def module():
    torch.manual_seed(0)
    return NoiseLevelEstimator(patch_size=P, width=8)


def _patches(b: int = 2) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    return (0.5 + torch.randn(b, 1, P, P, generator=g) * 10 / 255).clamp(0, 1)


def _with_nan(x: torch.Tensor) -> torch.Tensor:
    x = x.clone()
    x[0, 0, 3, 3] = float("nan")
    return x


@pytest.mark.parametrize("make, error, match", [
    (lambda x: (x * 255).round().to(torch.uint8), TypeError,
     r"image must be a floating tensor .*got dtype torch\.uint8; convert integer DN images with x\.float\(\) / 255"),
    (lambda x: x * 255, ValueError, r"image must lie in \[0, 1\] \(DN/255\), got values in \[\d+(\.\d+)?, \d+(\.\d+)?\]"),
    (_with_nan, ValueError, r"image must be finite, but 1 of 2048 values are NaN/inf \(first: nan\)"),
    (lambda x: x[..., :16, :16], ValueError,
     r"image has shape \(2, 1, 16, 16\); this NoiseLevelEstimator \(patch_size = 32\) takes B×1×32×32 patches"),
    (lambda x: x[:, 0], ValueError, r"image has shape \(2, 32, 32\); this NoiseLevelEstimator \(patch_size = 32\)"),
    (lambda x: x.expand(2, 3, P, P), ValueError, r"image has shape \(2, 3, 32, 32\); this NoiseLevelEstimator"),
])  # fmt: skip
def test_forward_and_predict_step_refuse_integer_dn_non_finite_and_misshaped_images(module, make, error, match):
    """The shipped drne.pt read uint8 DN patches of 10 DN noise as 2679 DN, and took any patch size, like the
    noise-source module does not."""
    x = make(_patches())
    module.eval()
    with torch.no_grad():
        with pytest.raises(error, match=match):
            module(x)
        with pytest.raises(error, match=match):
            module.predict_step({"image": x}, 0)


@pytest.mark.parametrize("channels_last", [True, False])
def test_an_empty_batch_gives_empty_outputs(channels_last):
    module = NoiseLevelEstimator(patch_size=P, width=8, channels_last=channels_last).eval()
    with torch.no_grad():
        out = module(torch.zeros(0, 1, P, P))
    assert out["sigma_map"].shape == (0, 1, P, P)
    assert all(out[k].shape == (0,) for k in ("sigma_total", "sigma_mean", "sigma_median"))


def _batch() -> dict[str, torch.Tensor]:
    meta = CameraMetadata.preset("ICX285", batch_size=3, gain_db=torch.tensor([0.0, 6.0, 12.0]))
    clean = torch.rand(3, 1, P, P, generator=torch.Generator().manual_seed(1)) * 0.6 + 0.2
    return {"image": (clean + 0.02).clamp(0, 1), "clean": clean, "meta_image_raw": metadata_matrix(meta).float(),
            "sigma_total": torch.tensor([1.0, 2.0, 3.0]), "sigma_expected": torch.tensor([[1.0, 0.5, 0.5]]).repeat(3, 1)}


def _nan_at_0(t: torch.Tensor) -> torch.Tensor:
    t = t.clone()
    t.view(-1)[0] = float("nan")
    return t


@pytest.mark.parametrize("key, make, match", [
    ("sigma_total", _nan_at_0, r"label batch\['sigma_total'\] must be finite, but 1 of 3 values are NaN/inf \(first: nan\) \(batch 7\)"),
    ("sigma_total", lambda t: torch.full_like(t, float("inf")),
     r"label batch\['sigma_total'\] must be finite, but 3 of 3 values are NaN/inf \(first: inf\) \(batch 7\)"),
    ("clean", lambda t: torch.full_like(t, float("nan")), r"label batch\['clean'\] must be finite, but 3072 of 3072 values"),
    ("sigma_total", lambda t: t[:, None], r"label batch\['sigma_total'\] has shape \(3, 1\); it must be a tensor of shape \(3,\)"),
    ("sigma_total", lambda t: t[:1], r"label batch\['sigma_total'\] has shape \(1,\); it must be a tensor of shape \(3,\)"),
    ("clean", lambda t: t[..., :16, :16], r"label batch\['clean'\] has shape \(3, 1, 16, 16\); it must be a tensor of shape \(3, 1, 32, 32\)"),
])  # fmt: skip
@pytest.mark.parametrize("step", ["training_step", "validation_step", "test_step"])
def test_steps_refuse_non_finite_and_misshaped_labels(module, key, make, match, step):
    """A NaN/inf label gave a NaN/inf loss the optimiser went on with; a (B, 1) sigma_total was broadcast against the
    (B,) estimates (B×B pairs) with only torch's warning."""
    batch = _batch()
    batch[key] = make(batch[key])
    with pytest.raises(ValueError, match=match):
        getattr(module, step)(batch, 7)


@pytest.mark.parametrize("value, match", [
    (float("nan"), r"sigma_expected must hold finite σ >= 0 DN \(0: a source not realised\), but 1 of 9 values are not \(first: nan\)"),
    (-1.0, r"sigma_expected must hold finite σ >= 0 DN .*but 1 of 9 values are not \(first: -1\.0\)"),
    (float("inf"), r"sigma_expected must hold finite σ >= 0 DN .*\(first: inf\)"),
])  # fmt: skip
def test_the_map_target_refuses_sigma_expected_that_is_not_a_finite_sigma(value, match):
    """A NaN or negative entry read as "source not realised" and dropped that source from the target (1.463 → 1.441 DN)."""
    batch = _batch()
    se = batch["sigma_expected"].clone()
    se[1, 2] = value
    with pytest.raises(ValueError, match=match):
        sigma_map_target_dn(batch["clean"], batch["meta_image_raw"], se)
