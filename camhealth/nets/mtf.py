"""MTF estimator (thesis Sec. 4.3.1, after Bauer et al. 2018): 8 MTF values per direction (H and V) at
f_n ∈ {0.05, …, 0.6} of Nyquist from one 192-px patch, or from a temporal stack of patches of one location.

**Pre-processing runs inside the forward pass, batched** (:class:`MTFPreprocess`; the thesis lost 98 % of
its blur-estimator runtime to serial pre-processing): (i) per-patch mean/contrast normalisation,
(ii) H/V by rotation — the V estimate is the H estimate of the patch rotated by 90°, so both directions
share one network and run as one batch of 2B, (iii) Sobel derivative channels ∂x, ∂y, (iv) space-to-depth
4×4 downsampling (3 channels → 48 channels at 48×48 px) which enlarges the receptive field of the early
layers while keeping every pixel (the finest frequencies are still there).

:class:`MTFNet`: a stem and five residual blocks (two strided: 48 → 24 → 12 px), global max/mean/std pooling,
**feature averaging over the T patches of a stack** (the thesis's intermediate representation layer), and a
three-layer fully connected regressor with a sigmoid output. ≈ 0.78 GFLOP per 192-px patch (both directions).

**Both directions at once**: the H and V passes share the convolutional body, and the regressor of each direction
reads [own, other] pooled features: H = head([f_H, f_V]), V = head([f_V, f_H]). So it can see isotropy (a disk has
H = V exactly) and the coupling of a motion line's two directions (|sinc(L·f·cos θ)|, |sinc(L·f·sin θ)| of one
length L), which two independent regressors cannot.

Plain ``torch.nn.Module``s: inference imports no training framework. The LightningModule that trains
:class:`MTFNet` (loss: L1 on the 16 MTF values; metric: AMAE, Eq. 5.1, per blur family) is
:class:`lightning_modules.mtf.MTFEstimator`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from camhealth.nets.blocks import (ConvAct, FullyConnectedBlock, GlobalStatsPool, ResidualBlock, check_input_shape, check_sizes,
                                  working_dtype)

__all__ = ["MTFPreprocess", "MTFNet", "sobel"]


class MTFPreprocess(nn.Module):
    """B×T×P×P patches in [0, 1] → (2·B·T, 3·s², P/s, P/s): H-direction inputs of all patches, then those of
    the patches rotated by 90° (whose H direction is the original V direction). Differentiable with respect to the
    patches (no operation in place on a tensor autograd keeps)."""

    def __init__(self, downsample: int = 4, contrast_floor: float = 0.02) -> None:
        super().__init__()
        (self.downsample,) = check_sizes(downsample, "downsample", 1)
        self.contrast_floor = float(contrast_floor)
        self.unshuffle = nn.PixelUnshuffle(self.downsample)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        b, t, h, w = image.shape
        x = image.reshape(b * t, 1, h, w)
        x = x.double() if x.dtype == torch.float64 else x.float()  # the contrast statistics in float32 (or float64)
        mean = x.mean((2, 3), keepdim=True)
        centred = x - mean
        std = centred.pow(2).mean((2, 3), keepdim=True).sqrt()
        x = centred / (std + self.contrast_floor)  # (not in place: pow keeps centred for its gradient)
        both = torch.cat([x, torch.rot90(x, 1, dims=(2, 3))], dim=0)
        gx, gy = sobel(both)
        s = self.downsample
        if h % s or w % s:
            return self.unshuffle(torch.cat([both, gx * 4.0, gy * 4.0], dim=1))  # its error message names the sizes
        # the values of self.unshuffle(cat([both, 4·gx, 4·gy])) (channel c·s² + i·s + j holds pixel (i, j) of each
        # s×s cell of input channel c): each input's cells are a view (n, s, s, H/s, W/s), and one stack writes them
        # all, once (3× faster than the concatenation and pixel_unshuffle on the CPU; a stack straight into
        # channels-last memory is 3× slower than this one and a conversion afterwards)
        n, hs, ws = both.shape[0], h // s, w // s
        views = [v.reshape(n, hs, s, ws, s).permute(0, 2, 4, 1, 3) for v in (both, gx.mul_(4.0), gy.mul_(4.0))]
        return torch.stack(views, dim=1).reshape(n, 3 * s * s, hs, ws)


def sobel(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised Sobel derivatives (∂x, ∂y) of B×C×H×W with replicate borders — the values of Kornia's
    ``spatial_gradient(x, "sobel", normalized=True)`` (kernel [−1 0 1]ᵀ·[1 2 1]/8), computed separably
    with shifted differences: ~10× faster on CPU than the 3×3 convolution of a one-channel input, and
    exact in float32 also under bf16 autocast."""
    xp = F.pad(x, (1, 1, 1, 1), mode="replicate")
    dx = xp[..., :, 2:] - xp[..., :, :-2]  # (H+2, W)
    # (a + 2b + c)/8 in that order, accumulated in place on one new tensor per derivative (no temporaries)
    gx = torch.add(dx[..., :-2, :], dx[..., 1:-1, :], alpha=2.0).add_(dx[..., 2:, :]).div_(8.0)
    dy = xp[..., 2:, :] - xp[..., :-2, :]  # (H, W+2)
    gy = torch.add(dy[..., :, :-2], dy[..., :, 1:-1], alpha=2.0).add_(dy[..., :, 2:]).div_(8.0)
    return gx, gy


class MTFNet(nn.Module):
    """``forward(image) -> (B, 16)`` MTF (H then V) for B×T×P×P stacks in [0, 1] (T = 1: one patch; P a multiple of
    ``downsample``). Another shape is a ``ValueError`` naming it; an empty batch (B = 0) gives a (0, 16) output."""

    def __init__(
        self, widths: tuple[int, int, int] = (32, 64, 96), hidden: tuple[int, ...] = (128, 64), downsample: int = 4,
    ) -> None:
        super().__init__()
        w1, w2, w3 = check_sizes(widths, "widths", 3)
        check_sizes(hidden, "hidden")
        self.pre = MTFPreprocess(downsample)
        self.stem = ConvAct(3 * downsample * downsample, w1)
        self.body = nn.Sequential(
            ResidualBlock(w1, w1, rezero=True),
            ResidualBlock(w1, w2, stride=2, rezero=True),
            ResidualBlock(w2, w2, rezero=True),
            ResidualBlock(w2, w3, stride=2, rezero=True),
            ResidualBlock(w3, w3, rezero=True),
        )
        self.pool = GlobalStatsPool()
        self.head = FullyConnectedBlock(6 * w3, hidden, 8)  # [own, other] direction's max/mean/std

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        s = self.pre.downsample
        check_input_shape(image, "MTFNet", s, s, stack=True)
        b, t = image.shape[:2]
        dt = working_dtype(image, self.stem[0].weight)  # statistics, pooled features and outputs
        if b == 0:
            return image.new_zeros((0, 16), dtype=dt)
        x = self.pre(image).to(dt)
        if x.is_contiguous(memory_format=torch.channels_last) is False and image.is_contiguous(memory_format=torch.channels_last):
            x = x.contiguous(memory_format=torch.channels_last)
        feats = self.pool(self.body(self.stem(x))).to(dt)  # (2·B·T, F)
        feats = feats.view(2, b, t, -1).mean(2)  # average the T patches of a stack
        feats = torch.cat([feats, feats.flip(0)], dim=-1)  # each direction's regressor reads [own, other] features
        mtf = torch.sigmoid(self.head(feats).to(dt))  # (2, B, 8)
        return torch.cat([mtf[0], mtf[1]], dim=1)
