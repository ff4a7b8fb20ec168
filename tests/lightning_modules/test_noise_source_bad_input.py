"""NoiseSourceEstimator on bad input: labels and arguments it refuses, each error naming them; patches of another
size; an empty batch gives empty outputs."""

from __future__ import annotations

import pytest
import torch

from lightning_modules import NoiseSourceEstimator

P = 32


@pytest.fixture
def module():
    torch.manual_seed(0)
    return NoiseSourceEstimator(patch_size=P, width=4, hidden=(4,))


def _batch(meta_raw: torch.Tensor) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    return {"image": torch.rand(3, 1, P, P, generator=g) * 0.5 + 0.25, "meta_raw": meta_raw,
            "sigma": torch.rand(3, 3, generator=g) * 5, "sigma_total": torch.rand(3, generator=g) * 5, "xi": torch.zeros(3)}


def _nan_first(t: torch.Tensor) -> torch.Tensor:
    t = t.clone()
    t.view(-1)[0] = float("nan")
    return t


@pytest.mark.parametrize("key, make, match", [
    ("sigma", _nan_first, r"label batch\['sigma'\] must be finite, but 1 of 9 values are NaN/inf \(first: nan\) \(batch 2\)"),
    ("sigma_total", lambda t: torch.full_like(t, float("inf")), r"label batch\['sigma_total'\] must be finite, but 3 of 3 values"),
    ("xi", lambda t: torch.full_like(t, -float("inf")), r"label batch\['xi'\] must be finite, but 3 of 3 values .*\(first: -inf\)"),
    ("sigma", lambda t: t[:1], r"label batch\['sigma'\] has shape \(1, 3\); it must be a tensor of shape \(3, 3\)"),
    ("sigma", lambda t: torch.cat([t, t[:, :1]], 1), r"label batch\['sigma'\] has shape \(3, 4\); it must be a tensor of shape \(3, 3\)"),
    ("xi", lambda t: t[:, None], r"label batch\['xi'\] has shape \(3, 1\); it must be a tensor of shape \(3,\)"),
    ("sigma_total", lambda t: t[:1], r"label batch\['sigma_total'\] has shape \(1,\); it must be a tensor of shape \(3,\)"),
])  # fmt: skip
@pytest.mark.parametrize("step", ["training_step", "validation_step", "test_step"])
def test_steps_refuse_non_finite_and_misshaped_labels(module, meta_raw, key, make, match, step):
    """A NaN label gave a NaN loss in training and val/rms_pn = nan in validation, without an error."""
    batch = _batch(meta_raw)
    batch[key] = make(batch[key])
    with pytest.raises(ValueError, match=match):
        getattr(module, step)(batch, 2)


@pytest.mark.parametrize("size", [16, 48])
def test_forward_refuses_patches_of_another_size(module, meta_raw, size):
    with pytest.raises(ValueError, match=rf"image has shape \(3, 1, {size}, {size}\); this NoiseSourceEstimator "
                                         rf"\(patch_size = 32\) takes B×1×32×32 patches"):
        module(torch.rand(3, 1, size, size), meta_raw)


@pytest.mark.parametrize("metadata_set", ["none", "minimal"])
def test_an_empty_batch_gives_empty_outputs(meta_raw, metadata_set):
    module = NoiseSourceEstimator(patch_size=P, metadata_set=metadata_set, width=4, hidden=(4,)).eval()
    with torch.no_grad():
        out = module(torch.zeros(0, 1, P, P), meta_raw[:0])
    assert out["sigma"].shape == (0, 3) and out["sigma_total"].shape == (0,) and out["xi"].shape == (0,)


@pytest.mark.parametrize("kwargs, match", [
    ({"hidden": None}, r"hidden = None must be a list of integers >= 1"),
    ({"hidden": 16}, r"hidden = 16 must be a list of integers >= 1"),
    ({"lr": "0.1"}, r"lr = '0\.1' must be a finite number"),
    ({"weight_decay": "1e-4"}, r"weight_decay = '1e-4' must be a finite number"),
])  # fmt: skip
def test_arguments_of_the_wrong_type_are_named(kwargs, match):
    """lr = '0.1' failed as "'>' not supported between 'str' and 'int'", hidden = None as "'NoneType' object is not
    iterable"."""
    with pytest.raises(ValueError, match=match):
        NoiseSourceEstimator(patch_size=P, **kwargs)
