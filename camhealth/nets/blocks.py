"""Network building blocks shared by the estimators, sized for a 2-core CPU, and FLOP/parameter counting.

The estimators trade full-resolution layers for **space-to-depth** stems (``nn.PixelUnshuffle``): an
s×s block of pixels becomes s² channels, so every later 3×3 convolution runs on s² fewer positions while
no pixel (and no high frequency, which is where noise and blur live) is thrown away. FLOPs are counted
with :class:`torch.utils.flop_counter.FlopCounterMode` (one multiply-add = 2 FLOP).
"""

from __future__ import annotations

import numbers
from typing import Sequence

import torch
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

__all__ = ["ConvAct", "ResidualBlock", "FullyConnectedBlock", "count_flops", "count_parameters", "GlobalStatsPool", "autocast_on",
           "working_dtype", "check_sizes", "check_input_shape"]


def check_sizes(value: object, name: str, count: int | None = None, low: int = 1) -> tuple[int, ...]:
    """A network's layer sizes (an integer, or a sequence of them: channels, neurons, factors) as a tuple of ints, or
    ``ValueError`` naming ``name`` unless each is an integer ≥ ``low`` (not a bool) and, with ``count``, there are that
    many. A layer of 0 units would make an output that ignores its input."""
    items = (value,) if isinstance(value, numbers.Integral) or not isinstance(value, Sequence) else tuple(value)
    bad = [v for v in items if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < low]
    if bad or (count is not None and len(items) != count) or not items:
        what = f"{count} integers" if count is not None and count > 1 else ("an integer" if count == 1 else "integers")
        raise ValueError(f"{name} = {value!r} must be {what} >= {low}"
                         + (f", got {bad[0]!r}" if bad else f", got {len(items)} value(s)"))
    return tuple(int(v) for v in items)


def check_input_shape(image: object, net: str, multiple: int, min_side: int, stack: bool = False) -> torch.Tensor:
    """The input of a network's ``forward``: ``TypeError`` unless ``image`` is a tensor, ``ValueError`` naming its shape
    and the shape ``net`` takes unless it is B×1×H×W (with ``stack``: B×T×P×P, T ≥ 1 patches of one location, H = W = P)
    with H and W multiples of ``multiple`` px and at least ``min_side`` px. B = 0 passes (the networks answer an empty
    batch with empty outputs). Only the shape is read, never a value, so the check also holds while the network is
    traced or exported."""
    if not isinstance(image, torch.Tensor):
        raise TypeError(f"{net} takes the image as a torch.Tensor, got {type(image).__name__}")
    shape = tuple(image.shape)
    ok = len(shape) == 4 and (shape[1] >= 1 if stack else shape[1] == 1)
    if ok:
        h, w = shape[2], shape[3]
        ok = min(h, w) >= min_side and h % multiple == 0 and w % multiple == 0 and (h == w or not stack)
    if not ok:
        form = "B×T×P×P (T ≥ 1 patches of one location; a single patch: T = 1)" if stack else "B×1×H×W"
        sides = "P" if stack else "H and W"
        raise ValueError(f"image has shape {shape}; {net} takes {form} with {sides} a multiple of {multiple} px, at least "
                         f"{min_side} px")
    return image


class ConvAct(nn.Sequential):
    """3×3 convolution (+ optional stride/dilation) followed by ReLU."""

    def __init__(self, c_in: int, c_out: int, stride: int = 1, dilation: int = 1, kernel_size: int = 3) -> None:
        pad = dilation * (kernel_size // 2)
        super().__init__(
            nn.Conv2d(c_in, c_out, kernel_size, stride=stride, padding=pad, dilation=dilation, bias=True),
            nn.ReLU(inplace=True),
        )


class ResidualBlock(nn.Module):
    """Two 3×3 convolutions with an identity (or 1×1 strided projection) shortcut; no normalisation layer
    (batch statistics would mix the noise levels of different patches of a batch).

    ``rezero=True`` scales the residual branch by a learnable scalar initialised to 0 (Bachlechner et al.
    2020), which keeps deep stacks without normalisation stable at high learning rates."""

    def __init__(self, c_in: int, c_out: int, stride: int = 1, dilation: int = 1, rezero: bool = False) -> None:
        super().__init__()
        self.rezero = nn.Parameter(torch.zeros(1)) if rezero else None
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride=stride, padding=dilation, dilation=dilation)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, padding=dilation, dilation=dilation)
        self.act = nn.ReLU(inplace=True)
        self.shortcut = (
            nn.Identity() if stride == 1 and c_in == c_out else nn.Conv2d(c_in, c_out, 1, stride=stride)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.conv2(self.act(self.conv1(x)))
        if self.rezero is not None:
            y = y * self.rezero
        return self.act(y + self.shortcut(x))


class GlobalStatsPool(nn.Module):
    """Global max, mean and standard deviation over H×W: (B, C, H, W) → (B, 3C).

    Max pooling is the thesis's choice (DRNE_cust); mean and std add the robust statistics a noise level
    needs (a single max is dominated by the most textured position of the patch). For float16 features the std is
    computed in float32 and cast back: float16 rounds its 1e-8 floor to 0, and a constant channel's std (a dead
    ReLU's) would then have an infinite gradient."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        flat = x.flatten(2)
        mean = flat.mean(2)
        if flat.dtype == torch.float16:  # float16 cannot hold the 1e-8 (it rounds to 0): the std in float32
            wide = flat.float()
            std = (wide.pow(2).mean(2) - wide.mean(2).pow(2)).clamp_min(0).add(1e-8).sqrt().to(flat.dtype)
        else:
            std = (flat.pow(2).mean(2) - mean.pow(2)).clamp_min(0).add(1e-8).sqrt()
        return torch.cat([flat.amax(2), mean, std], dim=1)


class FullyConnectedBlock(nn.Sequential):
    """The thesis's FCB: fully connected layers with ReLU between them (e.g. 32, 16, 8 neurons) and a
    final linear layer to ``n_out`` outputs."""

    def __init__(self, n_in: int, hidden: Sequence[int] = (32, 16, 8), n_out: int = 1) -> None:
        if len(tuple(hidden)):
            check_sizes(hidden, "hidden")
        layers: list[nn.Module] = []
        for h in hidden:
            layers += [nn.Linear(n_in, h), nn.ReLU(inplace=True)]
            n_in = h
        layers.append(nn.Linear(n_in, n_out))
        super().__init__(*layers)


def working_dtype(x: torch.Tensor, weight: torch.Tensor) -> torch.dtype:
    """The dtype a network's statistics, pooled features and outputs are kept in: float32 under autocast (whose ops
    cast their inputs anyway; what ``predict(precision="bf16")`` and bf16-mixed training run), else the weights' dtype
    (float32 as shipped; a module cast as a whole to bfloat16 or float64, Lightning's "bf16-true" / "64-true")."""
    return torch.float32 if autocast_on(x) else weight.dtype


def autocast_on(x: torch.Tensor) -> bool:
    """Whether autocast is on for ``x``'s device type (False for one autocast does not know: meta, while counting
    FLOPs)."""
    try:
        return torch.is_autocast_enabled(x.device.type)
    except RuntimeError:
        return False


def count_parameters(module: nn.Module) -> int:
    """Number of parameters, frozen ones included (a network fine-tuned with ``train_only`` still has them all)."""
    return sum(p.numel() for p in module.parameters())


@torch.no_grad()
def count_flops(module: nn.Module, *inputs: torch.Tensor) -> int:
    """FLOPs of one forward pass on ``inputs`` (counted by torch's ``FlopCounterMode``; 2 per MAC). The inputs are
    moved to the module's device first (a LightningModule describes its network while it trains on a GPU)."""
    device = next((p.device for p in module.parameters()), None)
    if device is not None:
        inputs = tuple(t.to(device) for t in inputs)
    was_training = module.training
    module.eval()
    counter = FlopCounterMode(display=False)
    with counter:
        module(*inputs)
    module.train(was_training)
    return int(counter.get_total_flops())
