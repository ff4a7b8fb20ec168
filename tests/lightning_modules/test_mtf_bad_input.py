"""MTFEstimator on bad input: images and labels it refuses, each error naming what it refuses; an empty batch gives a
(0, 16) output."""

from __future__ import annotations

import pytest
import torch

from lightning_modules import MTFEstimator

P = 32


@pytest.fixture
def module():
    torch.manual_seed(0)
    return MTFEstimator(patch_size=P, widths=(4, 4, 4), hidden=(4,))


def _patches(b: int = 2, t: int = 1) -> torch.Tensor:
    return torch.rand(b, t, P, P, generator=torch.Generator().manual_seed(0))


def _with_inf(x: torch.Tensor) -> torch.Tensor:
    x = x.clone()
    x[1, 0, 5, 5] = float("inf")
    return x


@pytest.mark.parametrize("make, error, match", [
    (lambda x: (x * 255).to(torch.uint8), TypeError, r"image must be a floating tensor .*got dtype torch\.uint8"),
    (lambda x: x * 255, ValueError, r"image must lie in \[0, 1\] \(DN/255\), got values in"),
    (_with_inf, ValueError, r"image must be finite, but 1 of 2048 values are NaN/inf \(first: inf\)"),
    (lambda x: torch.nn.functional.pad(x, (0, 16, 0, 16)), ValueError,
     r"image has shape \(2, 1, 48, 48\); this MTFEstimator \(patch_size = 32\) takes B×T×32×32"),
    (lambda x: x[:, 0], ValueError, r"image has shape \(2, 32, 32\); this MTFEstimator \(patch_size = 32\)"),
])  # fmt: skip
def test_forward_refuses_integer_dn_non_finite_and_misshaped_images(module, make, error, match):
    """uint8 DN patches were taken silently (the MTF moved by up to 0.10), and so was any patch size."""
    x = make(_patches())
    module.eval()
    with torch.no_grad():
        with pytest.raises(error, match=match):
            module(x)
        with pytest.raises(error, match=match):
            module.predict_step({"image": x}, 0)


@pytest.mark.parametrize("stack", [1, 3])
def test_an_empty_batch_gives_an_empty_output(module, stack):
    with torch.no_grad():
        assert module.eval()(torch.zeros(0, stack, P, P))["mtf"].shape == (0, 16)


def _batch() -> dict[str, torch.Tensor]:
    return {"image": _patches(3), "mtf": torch.rand(3, 16, generator=torch.Generator().manual_seed(2)),
            "family": torch.tensor([0, 1, 2]), "size": torch.tensor([3.0, 7.0, 11.0])}


def _nan_at(t: torch.Tensor) -> torch.Tensor:
    t = t.clone()
    t[1, 4] = float("nan")
    return t


@pytest.mark.parametrize("make, match", [
    (_nan_at, r"label batch\['mtf'\] must be finite, but 1 of 48 values are NaN/inf \(first: nan\) \(batch 5\)"),
    (lambda t: t[:1], r"label batch\['mtf'\] has shape \(1, 16\); it must be a tensor of shape \(3, 16\)"),
    (lambda t: t[:, :8], r"label batch\['mtf'\] has shape \(3, 8\); it must be a tensor of shape \(3, 16\)"),
])  # fmt: skip
@pytest.mark.parametrize("step", ["training_step", "validation_step", "test_step"])
def test_steps_refuse_non_finite_and_misshaped_labels(module, make, match, step):
    """A NaN label gave a NaN training loss; a (1, 16) label was used for every patch of the batch."""
    batch = _batch()
    batch["mtf"] = make(batch["mtf"])
    with pytest.raises(ValueError, match=match):
        getattr(module, step)(batch, 5)
