"""spectral_native_mtf / rendered_native_mtf on input they cannot measure: images without texture above the noise
floor, and arguments of the wrong type, shape or range."""

from __future__ import annotations

import pytest
import torch

from camhealth.data.dead_leaves import dead_leaves
from camhealth.data.native_mtf import rendered_native_mtf, spectral_native_mtf

_NO_TEXTURE = r"no measurable texture above the noise floor in fit_band = \(0\.05, 0\.2\)"


def _noise(sigma: float, dtype: torch.dtype, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (0.5 + sigma * torch.randn(1, 256, 256, generator=g, dtype=torch.float64)).clamp(0, 1).to(dtype)


def _faint_leaves(scale: float) -> torch.Tensor:
    """Dead leaves at ``scale`` × their contrast under 2.55 DN of white noise."""
    x = 0.5 + scale * (dead_leaves(256, seed=1, supersample=2).double() - 0.5)
    g = torch.Generator().manual_seed(1)
    return (x + 0.01 * torch.randn(x.shape, generator=g, dtype=torch.float64)).clamp(0, 1)


@pytest.mark.parametrize("images", [
    pytest.param(torch.full((1, 256, 256), 0.5), id="flat"),
    pytest.param(torch.zeros(2, 1, 128, 128), id="flat batch"),
    pytest.param(_noise(0.1, torch.float64), id="white noise float64"),
    pytest.param(_noise(0.02, torch.float32), id="white noise float32"),
    pytest.param(_noise(0.1, torch.float16), id="white noise float16"),
    pytest.param(_faint_leaves(0.001), id="dead leaves ×0.001 in noise"),
    pytest.param(_faint_leaves(0.01), id="dead leaves ×0.01 in noise"),
    pytest.param([_noise(0.1, torch.float64, 1), _noise(0.1, torch.float64, 2)], id="list of noise images"),
])
def test_an_image_without_texture_above_the_noise_floor_is_refused(images):
    """Such images gave MTFs of 0, 1e8 or 4e22 without a word (the power-law fit of power at or below the floor)."""
    with pytest.raises(ValueError, match=_NO_TEXTURE):
        spectral_native_mtf(images)


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(tile=100.5), TypeError, r"tile = 100\.5 must be an integer in \[32, 512\]"),
    (dict(tile="64"), TypeError, r"tile = '64' must be an integer in \[32, 512\]"),
    (dict(tile=True), TypeError, r"tile = True must be an integer in \[32, 512\]"),
    (dict(frequencies=(float("nan"),)), ValueError, r"frequencies must lie in \(0, 1\] \(× Nyquist\), got \[nan\]"),
    (dict(frequencies=(0.3, float("nan"))), ValueError, r"frequencies must lie in \(0, 1\].*got \[0\.3, nan\]"),
    (dict(frequencies=()), ValueError, r"frequencies must lie in \(0, 1\].*got \[\]"),
    (dict(fit_band=(0.1, 0.11)), ValueError, r"fit_band = \(0\.1, 0\.11\) holds 1 ring\(s\) of a 128-px tile.*at least 3"),
    (dict(fit_band=0.2), ValueError, r"fit_band = 0\.2 must be a pair \(low, high\)"),
])
def test_bad_arguments_are_named_with_their_value_and_range(kwargs, error, match):
    with pytest.raises(error, match=match):
        spectral_native_mtf(_faint_leaves(1.0), **kwargs)


@pytest.mark.parametrize("images, match", [
    (torch.rand(256, 256), r"images must be a 1×H×W or B×1×H×W tensor \(or a list of them\), got shape \(256, 256\)"),
    (torch.rand(1, 1, 1, 128, 128), r"images must be a 1×H×W or B×1×H×W tensor .*got shape \(1, 1, 1, 128, 128\)"),
    ([torch.rand(128, 128)], r"images\[0\] must be a 1×H×W or B×1×H×W tensor, got \(128, 128\)"),
    (2.0 * _faint_leaves(1.0), r"images must lie in \[0, 1\] \(DN/255\), got values in \[.*, 2\]"),
    (_faint_leaves(1.0) - 0.5, r"images must lie in \[0, 1\] \(DN/255\), got values in \[-0\.5, "),
])
def test_images_of_the_wrong_shape_or_range_are_named(images, match):
    """A 2-D H×W tensor was split into rows (the error named a shape of (256,)); values outside [0, 1] were measured."""
    with pytest.raises(ValueError, match=match):
        spectral_native_mtf(images)


@pytest.mark.parametrize("supersample, error, match", [
    (1.5, TypeError, r"supersample = 1\.5 must be an integer in \[1, 8\]"),
    (2.0, TypeError, r"supersample = 2\.0 must be an integer in \[1, 8\]"),
    ("4", TypeError, r"supersample = '4' must be an integer in \[1, 8\]"),
    (True, TypeError, r"supersample = True must be an integer in \[1, 8\]"),
])
def test_rendered_native_mtf_refuses_a_supersample_that_is_not_an_integer(supersample, error, match):
    """``rendered_native_mtf(1.5)`` measured supersample 1 without a word."""
    with pytest.raises(error, match=match):
        rendered_native_mtf(supersample, (0.6,), size=128)
