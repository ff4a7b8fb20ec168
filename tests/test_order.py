"""camhealth._order: NumPy-backed order statistics give torch's values bit for bit, and fall back to torch."""

from __future__ import annotations

import pytest
import torch

from camhealth._order import kth_smallest, lower_median, sorted_values


def _rows(dtype: torch.dtype, shape: tuple[int, ...], seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    if dtype.is_floating_point:
        x = torch.randn(*shape, generator=g, dtype=torch.float64).to(dtype)
        x.view(-1)[::7] = 0.0  # ties
        return x
    return torch.randint(-50, 50, shape, generator=g).to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.int64, torch.bfloat16, torch.float16])
@pytest.mark.parametrize("shape", [(1, 1), (3, 64), (2, 5, 2048), (256, 17)])
def test_kth_smallest_and_median_equal_torch(dtype, shape):
    x = _rows(dtype, shape)
    n = shape[-1]
    for k in sorted({1, (n + 1) // 2, n}):
        assert torch.equal(kth_smallest(x, k), x.kthvalue(k, dim=-1).values)
    assert torch.equal(lower_median(x), x.median(-1).values)
    assert lower_median(x).dtype == x.dtype


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.int32, torch.bfloat16])
def test_sorted_values_equal_torch_sort(dtype):
    x = _rows(dtype, (2, 8, 64, 64))
    assert torch.equal(sorted_values(x), x.sort(-1).values)
    t = x.transpose(-1, -2)  # not contiguous
    assert torch.equal(sorted_values(t), t.sort(-1).values)


def test_gradients_take_torch_path():
    x = torch.randn(4, 9, dtype=torch.float64, requires_grad=True)
    m = lower_median(x)
    m.sum().backward()
    assert x.grad is not None and float(x.grad.sum()) == 4.0
    assert sorted_values(x).requires_grad


def test_k_out_of_range_is_named():
    with pytest.raises(ValueError, match=r"k = 0 must be in \[1, 5\]"):
        kth_smallest(torch.zeros(2, 5), 0)
    with pytest.raises(ValueError, match=r"k = 6"):
        kth_smallest(torch.zeros(2, 5), 6)


def test_inference_tensors_and_results_own_their_memory():
    with torch.inference_mode():
        x = torch.rand(3, 11)
        m = lower_median(x)
    assert torch.equal(m, x.median(-1).values)
    y = torch.rand(3, 11)
    before = y.clone()
    m, s = lower_median(y), sorted_values(y)
    m += 1.0
    s.zero_()
    assert torch.equal(y, before)  # neither result is a view of the input


class _Median(torch.nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return lower_median(x) + sorted_values(x)[..., 0]


@pytest.mark.filterwarnings("ignore:`torch.jit.trace:DeprecationWarning")
def test_traced_and_exported_code_takes_torch_operators():
    """NumPy cannot be traced: under torch.export and TorchScript tracing the helpers use torch's operators and the
    exported program gives the eager values."""
    x = torch.rand(3, 17, generator=torch.Generator().manual_seed(1))
    want = x.median(-1).values + x.sort(-1).values[..., 0]
    ep = torch.export.export(_Median(), (x,))
    assert torch.equal(ep.module()(x), want)
    traced = torch.jit.trace(_Median(), (x,))
    assert torch.equal(traced(x), want)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.int64])
def test_each_device_gets_the_cpu_values_on_its_own_device(device, dtype):
    """On a GPU the helpers run torch's operators on the tensor's device and give the CPU path's values."""
    x = _rows(dtype, (5, 9, 129), seed=4)
    xd = x.to(device)
    for got, want in ((kth_smallest(xd, 3), kth_smallest(x, 3)), (lower_median(xd), lower_median(x)),
                      (sorted_values(xd), sorted_values(x))):
        assert got.device.type == device.type
        assert torch.equal(got.cpu(), want)
