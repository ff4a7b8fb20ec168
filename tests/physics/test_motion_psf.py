"""Tests for camhealth.physics.motion_psf (linear Eq. 3.10 and non-linear camera shake)."""

import numpy as np
import pytest
import scipy.ndimage as ndi
import torch

from camhealth.physics.motion_psf import (
    _rasterise_polyline,
    linear_motion_psf,
    nonlinear_motion_psf,
    sample_shake_noise,
)

DTYPES = [torch.float32, torch.float64]


def _noise(batch, seed=0, dtype=torch.float32, n_steps=64):
    return sample_shake_noise(batch, n_steps, generator=torch.Generator().manual_seed(seed), dtype=dtype)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("batch", [1, 256])
def test_linear_sums_to_one(dtype, batch):
    g = torch.Generator().manual_seed(1)
    length = (torch.rand(batch, generator=g) * 21.0).to(dtype)
    angle = (torch.rand(batch, generator=g) * 360.0).to(dtype)
    k = linear_motion_psf(length, angle, 21)
    assert k.shape == (batch, 21, 21) and k.dtype == dtype
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(k.sum(dim=(-2, -1)), torch.ones(batch, dtype=dtype), atol=tol, rtol=0)
    assert bool((k >= 0).all())
    torch.testing.assert_close(k, k.flip(-1).flip(-2))  # segment centred on the kernel centre


def test_linear_exact_values_and_delta():
    k = linear_motion_psf(torch.tensor([2.5, 0.0, 1.0], dtype=torch.float64), torch.tensor([0.0, 33.0, 0.0]), 5)
    row = torch.tensor([0.0, 0.3, 0.4, 0.3, 0.0], dtype=torch.float64)  # 0.75 + 1 + 0.75 px of 2.5 px
    torch.testing.assert_close(k[0, 2], row)
    assert k[0].sum(dim=1)[[0, 1, 3, 4]].abs().max() == 0
    delta = torch.zeros(5, 5, dtype=torch.float64)
    delta[2, 2] = 1.0
    torch.testing.assert_close(k[1], delta)  # L = 0
    torch.testing.assert_close(k[2], delta)  # 1 px horizontal motion stays in the centre pixel
    torch.testing.assert_close(linear_motion_psf(torch.tensor([1.0]), torch.tensor([45.0]), 1), torch.ones(1, 1, 1))


def test_linear_angle_convention():
    # 45° is counter-clockwise with y down: from bottom-left to top-right.
    k = linear_motion_psf(torch.tensor([5.6]), torch.tensor([45.0]), 7)[0]
    assert k[1, 5] > 0 and k[5, 1] > 0 and k[1, 1] == 0 and k[5, 5] == 0


@pytest.mark.parametrize("dtype", DTYPES)
def test_linear_rotation_and_transpose(dtype):
    g = torch.Generator().manual_seed(2)
    length = (torch.rand(32, generator=g) * 15.0).to(dtype)
    angle = (torch.rand(32, generator=g) * 180.0).to(dtype)
    k = linear_motion_psf(length, angle, 15)
    tol = dict(atol=1e-6, rtol=0)
    # counter-clockwise 90° rotation of the kernel == angle + 90°
    torch.testing.assert_close(torch.rot90(k, 1, (-2, -1)), linear_motion_psf(length, angle + 90.0, 15), **tol)
    # transposition (reflection across the diagonal) == 90° − angle; in particular 0° ↔ 90°
    torch.testing.assert_close(k.transpose(-1, -2), linear_motion_psf(length, 90.0 - angle, 15), **tol)
    h = linear_motion_psf(length, torch.zeros_like(length), 15)
    torch.testing.assert_close(h.transpose(-1, -2), linear_motion_psf(length, torch.full_like(length, 90.0), 15), **tol)


def test_linear_subpixel_smooth():
    a, b = linear_motion_psf(torch.tensor([5.3, 5.3001], dtype=torch.float64), torch.tensor([17.0, 17.0]), 9)
    assert (a - b).abs().max() < 1e-4
    assert (a - b).abs().max() > 0


def test_sample_shake_noise():
    n = _noise(8, seed=3)
    assert n.shape == (8, 64, 2) and n.dtype == torch.float32
    torch.testing.assert_close(n, _noise(8, seed=3))
    assert _noise(2, dtype=torch.float64, n_steps=16).shape == (2, 16, 2)
    with pytest.raises(ValueError, match="n_steps = 1"):
        sample_shake_noise(2, 1)
    with pytest.raises(TypeError, match="batch_size"):
        sample_shake_noise(2.0)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("batch", [1, 256])
def test_nonlinear_sums_to_one_and_intensity_zero_is_linear(dtype, batch):
    g = torch.Generator().manual_seed(4)
    length = (torch.rand(batch, generator=g) * 21.0).to(dtype)
    angle = (torch.rand(batch, generator=g) * 360.0).to(dtype)
    noise = _noise(batch, seed=5, dtype=dtype)
    k1 = nonlinear_motion_psf(length, angle, torch.ones(batch, dtype=dtype), noise, 21)
    assert k1.shape == (batch, 21, 21) and k1.dtype == dtype
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(k1.sum(dim=(-2, -1)), torch.ones(batch, dtype=dtype), atol=tol, rtol=0)
    k0 = nonlinear_motion_psf(length, angle, torch.zeros(batch, dtype=dtype), noise, 21)
    torch.testing.assert_close(k0, linear_motion_psf(length, angle, 21), atol=1e-6, rtol=0)


def test_nonlinear_reproducible_and_noise_dependent():
    args = (torch.tensor([15.0]), torch.tensor([30.0]), torch.tensor([0.8]))
    a = nonlinear_motion_psf(*args, _noise(1, seed=6), 17)
    b = nonlinear_motion_psf(*args, _noise(1, seed=6), 17)
    c = nonlinear_motion_psf(*args, _noise(1, seed=7), 17)
    torch.testing.assert_close(a, b, atol=0, rtol=0)
    assert (a - c).abs().max() > 1e-2


def test_nonlinear_path_coherent_curved_and_inhomogeneous():
    batch = 64
    noise = _noise(batch, seed=8, dtype=torch.float64)
    k = nonlinear_motion_psf(torch.tensor([15.0]), torch.tensor([0.0]), torch.tensor([1.0]), noise, 17).numpy()
    straight = linear_motion_psf(torch.tensor([15.0]), torch.tensor([0.0]), 17).numpy()[0]
    for kern in k:
        # one 8-connected component: a continuous path, no jumps
        assert ndi.label(kern > 0, structure=np.ones((3, 3)))[1] == 1
    # strongly curved: most paths leave the centre row; jerky speed gives very uneven intensities
    assert np.mean([np.abs(kern - straight).sum() > 0.5 for kern in k]) > 0.8
    assert np.median(k.max(axis=(1, 2)) / np.array([np.median(kern[kern > 0]) for kern in k])) > 2.0


def test_nonlinear_no_mass_lost_when_fitting():
    k = 15
    # A path touching the kernel border keeps all its mass ...
    verts = torch.tensor([[[-7.5, 0.0], [0.0, -7.5], [7.5, 7.5]]], dtype=torch.float64)
    raw = _rasterise_polyline(verts, torch.tensor([[0.5, 0.5]], dtype=torch.float64), k)
    assert raw.sum().item() == pytest.approx(1.0, abs=1e-12)
    # ... while one that leaves the kernel loses mass (it is dropped, not silently piled on the border).
    raw_out = _rasterise_polyline(verts * 1.2, torch.tensor([[0.5, 0.5]], dtype=torch.float64), k)
    assert raw_out.sum().item() < 0.99


def test_nonlinear_raw_mass_is_one_for_public_paths(monkeypatch):
    import camhealth.physics.motion_psf as mp

    seen = []
    orig = mp._rasterise_polyline

    def spy(vertices, weights, kernel_size):
        out = orig(vertices, weights, kernel_size)
        seen.append(out.sum(dim=(-2, -1)))
        return out

    monkeypatch.setattr(mp, "_rasterise_polyline", spy)
    batch = 128
    g = torch.Generator().manual_seed(11)
    angle, intensity = torch.rand(batch, generator=g) * 360, torch.rand(batch, generator=g)
    mp.nonlinear_motion_psf(torch.full((batch,), 13.0), angle, intensity, _noise(batch, seed=10), 13)
    torch.testing.assert_close(seen[0], torch.ones(batch, dtype=torch.float64), atol=1e-12, rtol=0)


def test_bad_inputs():
    noise = _noise(1)
    with pytest.raises(ValueError, match=r"length_px = -1 px .*\[0, 9\]"):
        linear_motion_psf(torch.tensor([-1.0]), torch.tensor([0.0]), 9)
    with pytest.raises(ValueError, match=r"length_px = 10 px .*\[0, 9\]"):
        nonlinear_motion_psf(torch.tensor([10.0]), torch.tensor([0.0]), torch.tensor([0.5]), noise, 9)
    with pytest.raises(ValueError, match="nan"):
        linear_motion_psf(torch.tensor([3.0]), torch.tensor([float("nan")]), 9)
    with pytest.raises(ValueError, match=r"intensity = 1.5 .*\[0, 1\]"):
        nonlinear_motion_psf(torch.tensor([3.0]), torch.tensor([0.0]), torch.tensor([1.5]), noise, 9)
    with pytest.raises(ValueError, match="kernel_size = 10"):
        linear_motion_psf(torch.tensor([3.0]), torch.tensor([0.0]), 10)
    with pytest.raises(ValueError, match="shake_noise"):
        nonlinear_motion_psf(torch.tensor([3.0]), torch.tensor([0.0]), torch.tensor([0.5]), noise[..., :1], 9)
    with pytest.raises(ValueError, match="batch"):
        linear_motion_psf(torch.ones(3), torch.zeros(2), 9)
    with pytest.raises(TypeError, match="length_px"):
        linear_motion_psf(None, torch.tensor([0.0]), 9)
    with pytest.raises(TypeError, match="shake_noise"):
        nonlinear_motion_psf(torch.tensor([3.0]), torch.tensor([0.0]), torch.tensor([0.5]), noise.long(), 9)
    big = noise.clone()
    big[0, 3, 1] = 1e4  # exp of the speed overflowed into NaN steps: "index -9223372036854775808 is out of bounds"
    with pytest.raises(ValueError, match=r"shake_noise must hold standard-normal draws, \|value\| ≤ 8; got 10000"):
        nonlinear_motion_psf(torch.tensor([3.0]), torch.tensor([0.0]), torch.tensor([0.5]), big, 9)
