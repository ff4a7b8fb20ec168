"""Noise-level network (thesis Sec. 4.3.2, DRNE after Tan et al. 2019): a pixel-wise σ map [DN] of the total
noise, for signal-dependent (Poisson–Gaussian) sensor noise.

:class:`NoiseLevelNet` keeps the DRNE idea — no pooling on the way to a per-pixel output, dilated
convolutions for context, residual blocks — at CPU cost: the patch and its ×32 high-pass residual are
folded 2×2 into 8 channels (space-to-depth), processed at half resolution by a stem, three dilated
residual blocks (dilation 1, 2, 4) and a head, and unfolded back to full resolution with a pixel shuffle
(depth-to-space), so the map is still per pixel. ≈ 0.56 GFLOP per 128-px patch at ``width = 32``.
:class:`ThesisNoiseNet` is the thesis-size reference (16 full-resolution 64-channel 3×3 layers,
≈ 17 GFLOP per 128-px patch) used by the benchmarks.

Plain ``torch.nn.Module``s: inference imports no training framework. The LightningModule that trains
:class:`NoiseLevelNet` (targets, loss, metrics, figures) is :class:`lightning_modules.drne.NoiseLevelEstimator`.
"""

from __future__ import annotations

import numbers

import torch
import torch.nn.functional as F
from torch import nn

from camhealth.nets.blocks import ConvAct, ResidualBlock, autocast_on, check_input_shape, check_sizes, working_dtype

__all__ = ["NoiseLevelNet", "ThesisNoiseNet", "check_dilations"]


def check_dilations(dilations, patch_size: int | None = None) -> tuple[int, ...]:
    """The dilations of :class:`NoiseLevelNet`'s residual blocks as a tuple: each an integer >= 1 and, for patches of
    ``patch_size`` px, at most ``patch_size // 2 − 1``. The blocks run at half resolution (``patch_size / 2`` px): a 3×3
    convolution dilated by that much or more reaches only the zero padding with its eight outer taps, for every pixel,
    so only its centre tap would ever see the image. ``TypeError`` for a value that is not a list of integers,
    ``ValueError`` naming the value and the allowed range otherwise."""
    if isinstance(dilations, (str, bytes)) or not isinstance(dilations, (list, tuple)):
        raise TypeError(f"dilations = {dilations!r} must be a list of integers, one per residual block")
    bad = [d for d in dilations if isinstance(d, bool) or not isinstance(d, numbers.Integral) or d < 1]
    if bad:
        raise ValueError(f"dilations = {tuple(dilations)!r}: each must be an integer >= 1, got {bad[0]!r}")
    if patch_size is not None:
        half = int(patch_size) // 2
        large = [d for d in dilations if d >= half]
        if large:
            raise ValueError(
                f"dilations = {tuple(int(d) for d in dilations)!r}: {int(large[0])} is too large for patch_size = "
                f"{int(patch_size)}: the residual blocks run at half resolution ({half}×{half} px), where a dilation of "
                f"{half} or more reaches only the zero padding; each dilation must be an integer in [1, {half - 1}]"
            )
    return tuple(int(d) for d in dilations)


class NoiseLevelNet(nn.Module):
    """B×1×H×W in [0, 1] (H, W even) → B×1×H×W σ map [DN] (≥ 0). Another shape is a ``ValueError`` naming it; an empty
    batch (B = 0) gives an empty map."""

    def __init__(self, width: int = 32, dilations: tuple[int, ...] = (1, 2, 4), highpass_gain: float = 32.0) -> None:
        super().__init__()
        dilations = check_dilations(dilations)
        (width,) = check_sizes(width, "width", 1)
        self.highpass_gain = float(highpass_gain)
        self.unshuffle = nn.PixelUnshuffle(2)
        self.stem = ConvAct(8, width)
        self.body = nn.Sequential(*[ResidualBlock(width, width, dilation=d) for d in dilations])
        self.head = nn.Sequential(ConvAct(width, width), nn.Conv2d(width, 4, 3, padding=1))
        self.shuffle = nn.PixelShuffle(2)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        check_input_shape(image, "NoiseLevelNet", 2, 2)
        if image.shape[0] == 0:
            return image.new_zeros(image.shape, dtype=working_dtype(image, self.stem[0].weight))
        if not autocast_on(image):  # the input in the weights' dtype (autocast casts it itself)
            image = image.to(self.stem[0].weight.dtype)
        local_mean = F.avg_pool2d(F.pad(image, (1, 1, 1, 1), mode="replicate"), 3, stride=1)
        x = torch.cat([image * 2.0 - 1.0, (image - local_mean) * self.highpass_gain], dim=1)
        y = self.shuffle(self.head(self.body(self.stem(self.unshuffle(x)))))
        return 5.0 * F.softplus(y.to(working_dtype(image, self.stem[0].weight)))


class ThesisNoiseNet(nn.Module):
    """Thesis-size reference: 16 full-resolution 3×3 convolution layers, 64 channels (≈ 17 GFLOP per
    128-px patch), output a σ map [DN] of B×1×H×W patches (another shape: ``ValueError`` naming it). Used to time the
    thesis's design on the same patches."""

    def __init__(self, width: int = 64, layers: int = 16) -> None:
        super().__init__()
        (width,), (layers,) = check_sizes(width, "width", 1), check_sizes(layers, "layers", 1, low=2)
        mods: list[nn.Module] = [ConvAct(1, width)]
        mods += [ConvAct(width, width) for _ in range(layers - 2)]
        mods.append(nn.Conv2d(width, 1, 3, padding=1))
        self.body = nn.Sequential(*mods)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        check_input_shape(image, "ThesisNoiseNet", 1, 1)
        weight = self.body[0][0].weight
        if not autocast_on(image):  # the input in the weights' dtype (autocast casts it itself)
            image = image.to(weight.dtype)
        return 5.0 * F.softplus(self.body(image).to(working_dtype(image, weight)))
