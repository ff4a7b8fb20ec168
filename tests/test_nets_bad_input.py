"""The networks of camhealth.nets on bad or unusual input: shapes they refuse by name, empty batches, the gradient
with respect to the image, and float16 features."""

from __future__ import annotations

import pytest
import torch

from camhealth.nets import GlobalStatsPool, MTFNet, MTFPreprocess, NoiseLevelNet, NoiseSourceNet, ThesisNoiseNet


def _networks():
    torch.manual_seed(0)
    return {"NoiseLevelNet": NoiseLevelNet(4, (1,)), "MTFNet": MTFNet((4, 4, 4), (4,), 4),
            "NoiseSourceNet": NoiseSourceNet("none", 4, (4,)), "ThesisNoiseNet": ThesisNoiseNet(4, 3)}


def _run(name: str, net: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
    return net(x, torch.zeros(x.shape[0] if x.ndim else 0, 11)) if name == "NoiseSourceNet" else net(x)


@pytest.mark.parametrize("name, shape", [("NoiseLevelNet", (1, 64, 64)), ("MTFNet", (1, 64, 64)),
                                         ("MTFNet", (3, 64, 64)), ("NoiseSourceNet", (1, 64, 64))])
def test_an_empty_batch_gives_empty_outputs(name, shape):
    """B = 0 failed inside torch ("expected input[0, 2, 64, 64] to have 8 channels", "cannot reshape tensor of 0
    elements")."""
    net = _networks()[name].eval()
    with torch.no_grad():
        out = _run(name, net, torch.zeros(0, *shape))
    want = {"NoiseLevelNet": (0, 1, 64, 64), "MTFNet": (0, 16), "NoiseSourceNet": (0, 4)}[name]
    assert out.shape == want and out.dtype == torch.float32


@pytest.mark.parametrize("name, shape, match", [
    ("NoiseLevelNet", (2, 64, 64), r"image has shape \(2, 64, 64\); NoiseLevelNet takes B×1×H×W with H and W a multiple of 2 px"),
    ("NoiseLevelNet", (2, 1, 63, 63), r"image has shape \(2, 1, 63, 63\); NoiseLevelNet takes B×1×H×W with H and W a multiple of 2 px"),
    ("NoiseLevelNet", (2, 2, 64, 64), r"image has shape \(2, 2, 64, 64\); NoiseLevelNet takes B×1×H×W"),
    ("NoiseSourceNet", (2, 1, 63, 63), r"image has shape \(2, 1, 63, 63\); NoiseSourceNet takes B×1×H×W with H and W a multiple of 2 px"),
    ("NoiseSourceNet", (2, 64, 64), r"image has shape \(2, 64, 64\); NoiseSourceNet takes B×1×H×W"),
    ("MTFNet", (2, 1, 62, 62), r"image has shape \(2, 1, 62, 62\); MTFNet takes B×T×P×P .* with P a multiple of 4 px"),
    ("MTFNet", (2, 1, 64, 32), r"image has shape \(2, 1, 64, 32\); MTFNet takes B×T×P×P"),
    ("MTFNet", (2, 64, 64), r"image has shape \(2, 64, 64\); MTFNet takes B×T×P×P"),
    ("ThesisNoiseNet", (2, 64, 64), r"image has shape \(2, 64, 64\); ThesisNoiseNet takes B×1×H×W"),
])  # fmt: skip
def test_a_misshaped_image_is_refused_naming_its_shape_and_the_one_taken(name, shape, match):
    """A 3-D tensor failed as "required rank 4 tensor to use channels_last format", a 63-px patch inside pixel_unshuffle."""
    net = _networks()[name].eval()
    with pytest.raises(ValueError, match=match), torch.no_grad():
        _run(name, net, torch.rand(*shape))


@pytest.mark.parametrize("rows", [1, 3])
def test_noise_source_metadata_of_another_batch_size_is_refused(rows):
    net = _networks()["NoiseSourceNet"].eval()
    with pytest.raises(ValueError, match=rf"meta has shape \({rows}, 11\); NoiseSourceNet takes \(B, 11\) = \(2, 11\)"):
        net(torch.rand(2, 1, 64, 64), torch.zeros(rows, 11))


@pytest.mark.parametrize("hidden", [None, 8])
def test_noise_source_hidden_that_is_no_list_is_named(hidden):
    with pytest.raises(ValueError, match=rf"hidden = {hidden} must be a list of integers >= 1"):
        NoiseSourceNet("none", 4, hidden)


@pytest.mark.parametrize("module", ["MTFPreprocess", "MTFNet"])
@pytest.mark.parametrize("stack", [1, 2])
def test_mtf_network_gradient_with_respect_to_the_image_passes_gradcheck(module, stack):
    """MTFPreprocess divided in place a tensor autograd keeps for pow's backward: backprop to the image raised "one of
    the variables needed for gradient computation has been modified by an inplace operation"."""
    torch.manual_seed(0)
    net = (MTFPreprocess(4) if module == "MTFPreprocess" else MTFNet((4, 4, 4), (4,), 4)).double()
    x = torch.rand(1, stack, 8, 8, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    assert torch.autograd.gradcheck(net, (x.requires_grad_(True),), eps=1e-6, atol=1e-5, fast_mode=True)


def test_mtf_preprocess_values_and_gradient_are_those_of_the_contrast_normalisation():
    """The division out of place gives the same values, bit for bit, and the gradient of the written-out computation."""
    from camhealth.nets.mtf import sobel

    x = torch.rand(2, 1, 16, 16, generator=torch.Generator().manual_seed(2), requires_grad=True)
    centred = x - x.mean((2, 3), keepdim=True)
    z = centred / (centred.pow(2).mean((2, 3), keepdim=True).sqrt() + 0.02)
    both = torch.cat([z, torch.rot90(z, 1, dims=(2, 3))])
    gx, gy = sobel(both)
    want = torch.nn.functional.pixel_unshuffle(torch.cat([both, gx * 4.0, gy * 4.0], 1), 4)
    out = MTFPreprocess(4)(x)
    assert torch.equal(out, want)
    weights = torch.rand(out.shape, generator=torch.Generator().manual_seed(3))
    (grad,) = torch.autograd.grad((out * weights).sum(), x)
    (want_grad,) = torch.autograd.grad((want * weights).sum(), x)
    assert torch.allclose(grad, want_grad, rtol=1e-5, atol=1e-6)


def test_blur_then_mtf_network_backpropagates_to_the_blur_input():
    from camhealth.augment import RandomDefocusBlur

    torch.manual_seed(0)
    x = torch.rand(2, 1, 64, 64, requires_grad=True)
    y = MTFNet((4, 4, 4), (4,), 4)(RandomDefocusBlur(diameter=5.0)(x))
    y.sum().backward()
    assert x.grad is not None and bool(torch.isfinite(x.grad).all()) and bool(x.grad.abs().sum() > 0)


@pytest.mark.parametrize("fill", [0.0, 0.5, 3.0])
@pytest.mark.parametrize("size", [4, 8])
def test_float16_global_stats_pool_of_a_constant_channel_has_a_finite_gradient(fill, size):
    """In float16 the 1e-8 floor under the variance rounded to 0: a constant (dead-ReLU) channel's std was 0 and its
    gradient not finite (float32, bfloat16 and float64 were fine)."""
    x = torch.full((2, 3, size, size), fill, dtype=torch.float16, requires_grad=True)
    y = GlobalStatsPool()(x)
    y.sum().backward()
    assert y.dtype == torch.float16 and bool(torch.isfinite(y).all())
    assert float(y[0, 6]) == pytest.approx(1e-4, rel=0.01)  # std of a constant channel: the floor's square root
    assert bool(torch.isfinite(x.grad).all())
