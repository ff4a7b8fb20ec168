"""Tests for camhealth.physics.defocus_psf (anti-aliased disk, Eq. 3.6)."""

import math

import numpy as np
import pytest
import torch

from camhealth.physics.defocus_psf import _disk_coverage, default_kernel_size, defocus_psf

DTYPES = [torch.float32, torch.float64]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("batch", [1, 256])
def test_sums_to_one_shape_dtype(dtype, batch):
    g = torch.Generator().manual_seed(0)
    d = torch.rand(batch, generator=g, dtype=dtype) * 21.0
    k = defocus_psf(d, 23)
    assert k.shape == (batch, 23, 23) and k.dtype == dtype and k.device == d.device
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(k.sum(dim=(-2, -1)), torch.ones(batch, dtype=dtype), atol=tol, rtol=0)
    assert bool((k >= 0).all())
    # symmetric under flips and transposition (disk centred on the kernel centre)
    torch.testing.assert_close(k, k.flip(-1))
    torch.testing.assert_close(k, k.flip(-2))
    torch.testing.assert_close(k, k.transpose(-1, -2))


def test_coverage_is_exact_area():
    d = torch.tensor([0.3, 1.0, 2.7, 7.3, 21.0, 41.0], dtype=torch.float64)
    cov = _disk_coverage(d, 41)
    torch.testing.assert_close(cov.sum(dim=(-2, -1)), math.pi * d**2 / 4, rtol=1e-12, atol=1e-12)
    # against a brute-force 200×200 supersampling of each pixel
    s, kk, dd = 200, 7, 3.7
    grid = (np.arange(kk * s) + 0.5) / s - kk / 2
    xx, yy = np.meshgrid(grid, grid)
    brute = (xx**2 + yy**2 <= (dd / 2) ** 2).reshape(kk, s, kk, s).mean(axis=(1, 3))
    exact = _disk_coverage(torch.tensor([dd], dtype=torch.float64), kk)[0].numpy()
    assert np.abs(brute - exact).max() < 2e-4


@pytest.mark.parametrize("d", [0.0, 0.5, 1.0])
def test_small_diameter_is_delta(d):
    k = defocus_psf(torch.tensor([d]), 5)
    expected = torch.zeros(1, 5, 5)
    expected[0, 2, 2] = 1.0
    torch.testing.assert_close(k, expected)


def test_kernel_size_one():
    k = defocus_psf(torch.tensor([0.0, 0.8, 1.0]), 1)
    torch.testing.assert_close(k, torch.ones(3, 1, 1))


def test_large_kernel_d39():
    k = defocus_psf(torch.tensor([39.0], dtype=torch.float64), 41)
    assert k.shape == (1, 41, 41)
    assert k[0, 20, 20] == pytest.approx(4.0 / (math.pi * 39.0**2), rel=1e-12)  # interior pixel fully covered
    assert k[0, 0].abs().max() == 0 and k[0, 20, 0] == 0  # 1 px margin untouched
    assert k[0, 20, 1] > 0


def test_subpixel_diameters_spread_monotonically_and_smoothly():
    d = torch.linspace(0.0, 3.0, 61, dtype=torch.float64)
    k = defocus_psf(d, 5)
    centre = k[:, 2, 2]
    assert bool((centre[1:] <= centre[:-1] + 1e-15).all())
    assert bool((centre[d > 1.0][1:] < centre[d > 1.0][:-1]).all())  # strictly decreasing beyond 1 px
    k05, k15 = defocus_psf(torch.tensor([0.5, 1.5]), 5)
    assert k05[2, 2] == 1.0 and 0.4 < k15[2, 2] < 1.0 and k15[2, 1] > 0
    # continuity: a 1e-4 px change moves the kernel by far less than one "staircase" step
    a, b = defocus_psf(torch.tensor([2.3, 2.3001], dtype=torch.float64), 5)
    assert (a - b).abs().max() < 1e-4


def test_default_kernel_size():
    assert default_kernel_size(39.0) == 41
    assert default_kernel_size(21) == 23
    assert default_kernel_size(20.5) == 23
    assert default_kernel_size(0.0) == 3
    assert default_kernel_size(torch.tensor([3.0, 11.0, 15.0])) == 17
    with pytest.raises(ValueError, match="max_diameter_px = -1"):
        default_kernel_size(-1.0)


def test_bad_inputs():
    with pytest.raises(ValueError, match="nan"):
        defocus_psf(torch.tensor([1.0, float("nan")]), 5)
    with pytest.raises(ValueError, match=r"diameter_px = -0.5 px .*\[0, 5\]"):
        defocus_psf(torch.tensor([-0.5]), 5)
    with pytest.raises(ValueError, match=r"diameter_px = 7 px .*\[0, 5\]"):
        defocus_psf(torch.tensor([7.0]), 5)
    with pytest.raises(ValueError, match="kernel_size = 8"):
        defocus_psf(torch.tensor([3.0]), 8)
    with pytest.raises(TypeError, match="kernel_size"):
        defocus_psf(torch.tensor([3.0]), 5.0)
    with pytest.raises(TypeError, match="diameter_px"):
        defocus_psf("3", 5)
    with pytest.raises(TypeError, match="diameter_px"):
        defocus_psf(torch.tensor([True]), 5)
