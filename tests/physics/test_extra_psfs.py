"""Tests of the further PSF families: Gaussian, polygon, ring, spherical aberration, random-walk shake, tiny."""

from __future__ import annotations

import math

import pytest
import torch

from camhealth.physics import (
    NORMALIZED_FREQUENCIES,
    defocus_psf,
    gaussian_mtf,
    gaussian_psf,
    mtf_hv,
    polygon_psf,
    ring_mtf,
    ring_psf,
    sample_random_walk,
    sample_tiny_psf,
    spherical_psf,
    trajectory_psf,
)
from camhealth.physics.defocus_psf import _disk_coverage
from camhealth.physics.mtf import disk_mtf
from camhealth.physics.polygon_psf import polygon_area_px2

F = torch.tensor(NORMALIZED_FREQUENCIES, dtype=torch.float64) / 2  # cycles/px


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _kernels(batch: int, dtype: torch.dtype, k: int = 21) -> dict[str, torch.Tensor]:
    g = _gen(batch)
    u = torch.rand(batch, generator=g, dtype=dtype)
    shift = torch.rand(batch, 2, generator=g, dtype=dtype) - 0.5
    return {
        "gaussian": gaussian_psf(0.2 + 3.0 * u, k, shift),
        "polygon": polygon_psf(1.0 + 18.0 * u, 5, k, rotation_deg=90.0 * u, shift_px=shift),
        "ring": ring_psf(2.0 + 18.0 * u, 0.3 + 0.5 * u, k),
        "spherical": spherical_psf(2.0 + 16.0 * u, 2.0 * u - 1.0, k, n_rings=16),
        "random_walk": trajectory_psf(sample_random_walk(batch, 32, generator=g, dtype=dtype), 1.0 + 19.0 * u, k),
        "tiny": sample_tiny_psf(batch, 3, k, generator=g, dtype=dtype),
    }


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("batch", [1, 64])
def test_every_generator_sums_to_one_is_non_negative_and_batched(dtype, batch):
    for name, k in _kernels(batch, dtype).items():
        assert k.shape == (batch, 21, 21) and k.dtype == dtype, name
        tol = 1e-5 if dtype == torch.float32 else 1e-12
        torch.testing.assert_close(k.sum((-2, -1)), torch.ones(batch, dtype=dtype), atol=tol, rtol=0, msg=name)
        assert bool((k >= 0).all()) and bool(torch.isfinite(k).all()), name


def test_batched_equals_one_by_one_and_seeded():
    a = _kernels(8, torch.float64)
    b = _kernels(8, torch.float64)
    for name in a:
        torch.testing.assert_close(a[name], b[name], msg=name)  # same seed, same kernels
    c = _kernels(9, torch.float64)
    assert not torch.equal(c["tiny"][:8], a["tiny"])  # another seed, other kernels
    s = torch.tensor([0.5, 1.3, 2.7], dtype=torch.float64)
    sh = torch.tensor([[0.1, -0.2], [0.0, 0.4], [-0.5, 0.5]], dtype=torch.float64)
    one = torch.cat([gaussian_psf(s[i:i + 1], 15, sh[i]) for i in range(3)])
    torch.testing.assert_close(gaussian_psf(s, 15, sh), one)
    d = torch.tensor([3.0, 7.0, 12.0], dtype=torch.float64)
    one = torch.cat([spherical_psf(d[i:i + 1], torch.tensor([0.4]), 15, n_rings=16) for i in range(3)])
    torch.testing.assert_close(spherical_psf(d, torch.tensor([0.4]), 15, n_rings=16), one)


def test_gaussian_matches_its_closed_form():
    """Pixel masses are erf differences (checked against a 1-D brute-force integral), the kernel's MTF is
    exp(−2π²σ²f²)·|sinc f| up to aliasing, and a shift moves the centroid by exactly (dx, dy)."""
    sigma = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    k = gaussian_psf(sigma, 31)
    want = gaussian_mtf(sigma[:, None], F) * torch.sinc(F)
    got = mtf_hv(k)
    torch.testing.assert_close(got[:, :8], want, atol=2e-3, rtol=0)
    torch.testing.assert_close(got[:, 8:], want, atol=2e-3, rtol=0)
    x = torch.linspace(-0.5, 0.5, 20001, dtype=torch.float64)
    brute = torch.exp(-(x + 1.0) ** 2 / 2.0).mean() / math.sqrt(2 * math.pi)  # pixel centred 1 px from the centre
    row = gaussian_psf(torch.tensor([1.0], dtype=torch.float64), 31)[0].sum(0)
    assert abs(float(row[16]) - float(brute)) < 1e-7
    sh = torch.tensor([[0.3, -0.2]], dtype=torch.float64)
    ks = gaussian_psf(torch.tensor([2.0], dtype=torch.float64), 31, sh)[0]
    pos = torch.arange(31, dtype=torch.float64) - 15
    assert abs(float((ks.sum(0) * pos).sum()) - 0.3) < 1e-6 and abs(float((ks.sum(1) * pos).sum()) + 0.2) < 1e-6
    torch.testing.assert_close(mtf_hv(ks[None]), mtf_hv(k[1:2]), atol=1e-6, rtol=0)  # a shift keeps the MTF


def test_polygon_area_and_disk_limit():
    d = torch.tensor([5.0, 11.0], dtype=torch.float64)
    cov = polygon_psf(d, 6, 15, supersample=32)
    hexagon = polygon_area_px2(d, 6)
    disk = math.pi * (d / 2) ** 2
    # the centre pixel is fully covered: its normalised value is 1 / (covered area); supersampling at s = 32 keeps
    # the area within half a sub-pixel row along the perimeter (6·d/2 px) of the closed form
    bound = 0.5 * 3 * d / 32 / hexagon
    assert bool(((1.0 / cov[:, 7, 7] / hexagon - 1).abs() <= bound).all())
    assert bool((hexagon < disk).all())
    many = polygon_psf(d, 16, 15, supersample=32)
    torch.testing.assert_close(many, defocus_psf(d, 15), atol=4e-3, rtol=0)
    torch.testing.assert_close(mtf_hv(many)[:, :8], disk_mtf(d[:, None], F) * torch.sinc(F), atol=0.03, rtol=0)


def test_ring_matches_its_closed_form_and_disk():
    d = torch.tensor([6.0, 12.0, 20.0], dtype=torch.float64)
    eps = torch.tensor([0.5, 0.3, 0.7], dtype=torch.float64)
    k = ring_psf(d, eps, 23)
    want = ring_mtf(d[:, None], eps[:, None], F) * torch.sinc(F)
    torch.testing.assert_close(mtf_hv(k)[:, :8], want, atol=0.03, rtol=0)
    area = _disk_coverage(d, 23).sum((1, 2)) - _disk_coverage(d * eps, 23).sum((1, 2))
    torch.testing.assert_close(area, math.pi / 4 * d**2 * (1 - eps**2), atol=1e-10, rtol=0)
    torch.testing.assert_close(ring_psf(d, torch.zeros(1, dtype=torch.float64), 23), defocus_psf(d, 23))
    assert float(k[1, 11, 11]) == 0.0  # the centre pixel lies inside the 3.6-px hole


def test_ring_mtf_of_a_point_is_one_and_bad_obstruction_is_refused():
    # d → 0 is a point (MTF 1), not the 0/0 of the area-weighted form; ε = 0 is the disk
    assert float(ring_mtf(0.0, 0.5, 0.1)) == pytest.approx(1.0)
    assert float(ring_mtf(1e-16, 0.5, 0.1)) == pytest.approx(1.0)
    assert float(ring_mtf(7.0, 0.0, 0.1)) == pytest.approx(float(disk_mtf(7.0, 0.1)), abs=1e-12)
    with pytest.raises(ValueError, match=r"obstruction = 2 is out of the allowed range \[0, 0.95\]"):
        ring_mtf(5.0, 2.0, 0.1)
    with pytest.raises(ValueError, match=r"obstruction = -0.1 is out"):
        ring_mtf(5.0, -0.1, 0.1)
    with pytest.raises(ValueError, match=r"diameter_px = -1 px is out"):
        ring_mtf(-1.0, 0.5, 0.1)


def test_spherical_zero_is_the_disk_and_sign_moves_mass():
    d = torch.tensor([6.0, 14.0], dtype=torch.float64)
    k0 = spherical_psf(d, torch.zeros(1), 17)
    torch.testing.assert_close(k0, defocus_psf(d, 17), atol=3e-3, rtol=0)
    torch.testing.assert_close(mtf_hv(k0), mtf_hv(defocus_psf(d, 17)), atol=5e-3, rtol=0)
    core = spherical_psf(d, torch.tensor([0.8]), 17)
    rim = spherical_psf(d, torch.tensor([-0.9]), 17)
    assert bool((core[:, 8, 8] > k0[:, 8, 8]).all()) and bool((rim[:, 8, 8] < k0[:, 8, 8]).all())


def test_random_walk_length_and_straight_path():
    line = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]], dtype=torch.float64)
    from camhealth.physics import linear_motion_psf

    torch.testing.assert_close(trajectory_psf(line, torch.tensor([9.0], dtype=torch.float64), 11),
                               linear_motion_psf(torch.tensor([9.0], dtype=torch.float64), 0.0, 11))
    tr = sample_random_walk(16, 64, generator=_gen(3))
    steps = (tr[:, 1:] - tr[:, :-1]).norm(dim=-1)
    torch.testing.assert_close(steps, torch.ones_like(steps))
    with pytest.raises(ValueError, match="length_px"):
        trajectory_psf(tr, torch.tensor([30.0]), 21)


def test_tiny_support():
    k = sample_tiny_psf(32, 4, 9, generator=_gen(1), dtype=torch.float64)
    assert bool((k[:, :2].sum((1, 2)) == 0).all()) and bool((k[:, 6:].sum((1, 2)) == 0).all())
    assert bool((k[:, 2:6, 2:6] > 0).all())
    torch.testing.assert_close(sample_tiny_psf(2, 1, 5), defocus_psf(torch.zeros(2), 5))


@pytest.mark.parametrize("call,match", [
    (lambda: gaussian_psf(torch.tensor([-1.0]), 9), "sigma_px"),
    (lambda: gaussian_psf(torch.tensor([float("nan")]), 9), "sigma_px"),
    (lambda: gaussian_psf(torch.tensor([1.0]), 8), "kernel_size"),
    (lambda: gaussian_psf(torch.tensor([1.0]), 9, torch.tensor([0.7, 0.0])), "shift_px"),
    (lambda: gaussian_psf(torch.tensor([1.0]), 9, torch.zeros(1, 3)), "shift_px"),
    (lambda: polygon_psf(torch.tensor([3.0]), 2, 9), "n_blades"),
    (lambda: polygon_psf(torch.tensor([9.0]), 6, 9), "diameter_px"),
    (lambda: ring_psf(torch.tensor([3.0]), torch.tensor([1.0]), 9), "obstruction"),
    (lambda: spherical_psf(torch.tensor([3.0]), torch.tensor([1.5]), 9), "spherical"),
    (lambda: spherical_psf(torch.tensor([9.0]), torch.tensor([0.0]), 9), "diameter_px"),
    (lambda: sample_random_walk(0), "batch_size"),
    (lambda: sample_random_walk(2, anxiety=-1.0), "anxiety"),
    (lambda: trajectory_psf(torch.zeros(1, 3, 2), torch.tensor([2.0]), 9), "non-zero arc length"),
    (lambda: sample_tiny_psf(2, 6, 9), "support_px"),
    (lambda: gaussian_psf(torch.ones(2), 9, torch.zeros(3, 2)), "incompatible batch sizes"),
])
def test_bad_input_names_the_value(call, match):
    with pytest.raises((ValueError, TypeError), match=match):
        call()


def test_half_precision_inputs_give_float32():
    k = gaussian_psf(torch.tensor([1.5], dtype=torch.float16), 9)
    assert k.dtype == torch.float32 and abs(float(k.sum()) - 1) < 1e-6
    k = ring_psf(torch.tensor([5.0], dtype=torch.bfloat16), torch.tensor([0.5], dtype=torch.bfloat16), 9)
    assert k.dtype == torch.float32 and abs(float(k.sum()) - 1) < 1e-6


@pytest.mark.parametrize("support", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("kernel", [5, 7, 9])
def test_tiny_psf_support_placement_is_the_documented_one(support, kernel):
    """Rows and columns c − s//2 … c − s//2 + s − 1 about the centre c = k//2: for even s, s/2 pixels left of /
    above the centre and s/2 − 1 right of / below it (s = 4 in k = 7: columns 1…4)."""
    import camhealth.physics.tiny_psf as tiny_psf

    if support > kernel:
        pytest.skip("support larger than the kernel")
    psf = tiny_psf.sample_tiny_psf(3, support, kernel, generator=torch.Generator().manual_seed(0))
    nz = (psf != 0).any(0)
    rows, cols = nz.any(1).nonzero().flatten().tolist(), nz.any(0).nonzero().flatten().tolist()
    c = kernel // 2
    first = c - support // 2
    assert rows == cols == list(range(first, first + support))
    if support % 2 == 0:
        assert c - rows[0] == support // 2 and rows[-1] - c == support // 2 - 1
    assert "s/2 − 1 right of / below it" in " ".join(tiny_psf.__doc__.split())
