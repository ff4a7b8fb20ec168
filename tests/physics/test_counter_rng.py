"""Counter-based random fields: statistics, independence, reproducibility, eager = compiled, errors."""

import warnings

import numpy as np
import pytest
import torch
from scipy import stats

from camhealth.physics import counter_rng
from camhealth.physics.counter_rng import (
    LazyCompiled, counter_keys, counter_normal, counter_normal_at, counter_uniform, counter_uniform_at,
)

N = 1 << 20


def _keys(seed=0):
    return counter_keys(torch.Generator().manual_seed(seed))


def test_keys_are_reproducible_int32_from_the_generator():
    a, b, c = _keys(1), _keys(1), _keys(2)
    assert a.dtype == torch.int32 and a.shape == (3,)
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_uniform_grid_range_and_chi_square():
    u = counter_uniform((N,), _keys())
    assert u.dtype == torch.float32 and float(u.min()) >= 0.0 and float(u.max()) < 1.0
    scaled = u.double() * 2**24
    assert torch.equal(scaled, scaled.round())  # multiples of 2⁻²⁴, the grid of torch.rand
    counts = np.histogram(u.numpy(), bins=256, range=(0, 1))[0]
    assert stats.chisquare(counts).pvalue > 1e-4


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_normal_moments_and_kolmogorov_smirnov(dtype):
    z = counter_normal((N,), _keys(3), dtype).double().numpy()
    assert abs(z.mean()) < 5 / N**0.5 and abs(z.var() - 1) < 5 * (2 / N) ** 0.5
    assert abs(stats.skew(z)) < 5 * (6 / N) ** 0.5 and abs(stats.kurtosis(z)) < 5 * (24 / N) ** 0.5
    assert stats.kstest(z, "norm").pvalue > 1e-4
    assert np.abs(z).max() < 5.95  # u₁ ≥ 2⁻²⁵ caps |z| at √(50 ln 2) ≈ 5.89


def test_neighbours_draws_and_fields_are_uncorrelated():
    shape = (16, 1, 256, 256)
    z = counter_normal(shape, _keys(4)).double()
    w = counter_normal(shape, _keys(5)).double()
    bound = 5 / z.numel() ** 0.5

    def corr(a, b):
        a, b = a - a.mean(), b - b.mean()
        return float((a * b).mean() / (a.std() * b.std()))

    assert abs(corr(z[..., 1:], z[..., :-1])) < bound  # horizontal neighbours
    assert abs(corr(z[..., 1:, :], z[..., :-1, :])) < bound  # vertical neighbours
    assert abs(corr(z[1:], z[:-1])) < bound  # neighbouring samples
    assert abs(corr(z, w)) < bound  # fields of different keys
    assert abs(corr(z ** 2, w ** 2)) < bound
    u = counter_uniform(shape, _keys(4)).double()  # the uniform behind z's first word vs z itself: dependent by
    assert abs(corr(u, z ** 2)) > 0.5  # construction (sanity check that corr() can fail)


def test_subset_and_scaled_fields_match_the_field():
    keys = _keys(6)
    z = counter_normal((4, 1000), keys)
    idx = torch.tensor([0, 5, 999, 1000, 3999])
    assert torch.allclose(counter_normal_at(idx, keys), z.view(-1)[idx], atol=1e-6)
    scale = torch.tensor([0.0, 1.0, 2.5, 10.0])
    assert torch.allclose(counter_normal((4, 1000), keys, scale=scale), z * scale[:, None], atol=1e-5)
    u = counter_uniform((4, 1000), keys)
    assert torch.equal(counter_uniform_at(idx, keys), u.view(-1)[idx])


def test_eager_and_compiled_give_the_same_numbers(monkeypatch):
    keys = _keys(7)
    u_c, z_c = counter_uniform((3, 5000), keys), counter_normal((3, 5000), keys, torch.float64)
    monkeypatch.setenv("CAMHEALTH_COMPILE", "0")
    assert not counter_rng.compiled()
    u_e, z_e = counter_uniform((3, 5000), keys), counter_normal((3, 5000), keys, torch.float64)
    assert torch.equal(u_c, u_e)  # integer arithmetic: identical
    assert torch.allclose(z_c, z_e, rtol=1e-12, atol=1e-12)


def test_failed_compilation_falls_back_to_eager_with_one_warning(monkeypatch):
    def boom(*args, **kwargs):
        raise RuntimeError("no C++ compiler")

    monkeypatch.setattr(torch, "compile", lambda fn, **kw: boom)
    lazy = LazyCompiled(lambda x: x * 2)
    with pytest.warns(RuntimeWarning, match="no C\\+\\+ compiler"):
        assert torch.equal(lazy(torch.ones(3)), torch.full((3,), 2.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # only once
        assert torch.equal(lazy(torch.ones(2)), torch.full((2,), 2.0))


def test_size_and_scale_errors():
    keys = _keys()
    with pytest.raises(ValueError, match="at most 2147483647 elements"):
        counter_uniform((2**16, 2**16), keys)
    with pytest.raises(ValueError, match="one value per sample"):
        counter_normal((3, 10), keys, scale=torch.ones(2))


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_draws_are_the_float32_draws_rounded(dtype):
    """A 24-bit integer overflows float16 and the 2⁻²⁴ grid rounds up to 1.0 in both half formats: the draws are
    computed in float32 and rounded at the end, uniforms kept below 1, normals finite."""
    keys = _keys(4)
    n = 1 << 16
    u, u32 = counter_uniform((n,), keys, dtype), counter_uniform((n,), keys)
    assert u.dtype == dtype and float(u.min()) >= 0.0 and float(u.max()) < 1.0
    below_one = torch.nextafter(torch.ones((), dtype=dtype), torch.zeros((), dtype=dtype))
    assert torch.equal(u, u32.to(dtype).clamp(max=below_one))
    z, z32 = counter_normal((n,), keys, dtype), counter_normal((n,), keys)
    assert z.dtype == dtype and bool(torch.isfinite(z).all()) and torch.equal(z, z32.to(dtype))
    assert abs(float(z.float().mean())) < 0.02 and abs(float(z.float().std()) - 1.0) < 0.02
    scale = torch.tensor([1.0, 3.0])
    assert torch.equal(counter_normal((2, n // 2), keys, dtype, scale), counter_normal((2, n // 2), keys, scale=scale).to(dtype))
    idx = torch.arange(0, n, 13)
    assert torch.equal(counter_uniform_at(idx, keys, dtype), u[idx])
    assert torch.equal(counter_normal_at(idx, keys, dtype), counter_normal_at(idx, keys).to(dtype))


def test_a_dtype_that_is_not_floating_is_a_type_error():
    with pytest.raises(TypeError, match="dtype must be a floating torch.dtype"):
        counter_uniform((4,), _keys(), torch.int32)
