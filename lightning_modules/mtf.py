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
three-layer fully connected regressor with a sigmoid output. ≈ 0.6 GFLOP per 192-px patch (both directions).

**Both directions at once** (``joint_directions``): the H and V passes share the convolutional body, and by
default the regressor of each direction reads only its own pooled features, so the H and V estimates are made
independently — a disk (H = V exactly) comes out with |H − V| ≈ 1.4 % at the median, and the coupling of the two
directions of a motion line (both are |sinc(L·f·cos θ)|, |sinc(L·f·sin θ)| of one length) is not used. With
``joint_directions=True`` the regressor reads [own, other] features: H = head([f_H, f_V]), V = head([f_V, f_H]);
the head's first layer doubles its inputs (36 864 parameters, ≈ 0.15 MFLOP per patch), nothing else changes.
:meth:`MTFNet.state_from` carries a one-direction network over with zero weights on the other direction's
features, so ``--init_from`` starts exactly at its outputs.

Loss: L1 on the 16 MTF values; metric: AMAE (Eq. 5.1) in % per blur family.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from lightning_modules.base import EstimatorModule, freeze_all_but
from lightning_modules.blocks import ConvAct, FullyConnectedBlock, GlobalStatsPool, ResidualBlock
from lightning_modules.metrics import AMAEPerFamily

__all__ = ["MTFPreprocess", "MTFNet", "MTFEstimator", "FAMILIES", "sobel"]

FAMILIES: tuple[str, ...] = ("defocus", "linear", "nonlinear")


class MTFPreprocess(nn.Module):
    """B×T×P×P patches in [0, 1] → (2·B·T, 3·s², P/s, P/s): H-direction inputs of all patches, then those of
    the patches rotated by 90° (whose H direction is the original V direction)."""

    def __init__(self, downsample: int = 4, contrast_floor: float = 0.02) -> None:
        super().__init__()
        self.downsample = int(downsample)
        self.contrast_floor = float(contrast_floor)
        self.unshuffle = nn.PixelUnshuffle(self.downsample)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        b, t, h, w = image.shape
        x = image.reshape(b * t, 1, h, w).float()
        mean = x.mean((2, 3), keepdim=True)
        std = (x - mean).pow(2).mean((2, 3), keepdim=True).sqrt()
        x = (x - mean) / (std + self.contrast_floor)
        both = torch.cat([x, torch.rot90(x, 1, dims=(2, 3))], dim=0)
        gx, gy = sobel(both)
        channels = torch.cat([both, gx * 4.0, gy * 4.0], dim=1)
        return self.unshuffle(channels)


def sobel(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised Sobel derivatives (∂x, ∂y) of B×C×H×W with replicate borders — the values of Kornia's
    ``spatial_gradient(x, "sobel", normalized=True)`` (kernel [−1 0 1]ᵀ·[1 2 1]/8), computed separably
    with shifted differences: ~10× faster on CPU than the 3×3 convolution of a one-channel input, and
    exact in float32 also under bf16 autocast."""
    xp = F.pad(x, (1, 1, 1, 1), mode="replicate")
    dx = xp[..., :, 2:] - xp[..., :, :-2]  # (H+2, W)
    gx = (dx[..., :-2, :] + 2.0 * dx[..., 1:-1, :] + dx[..., 2:, :]) / 8.0
    dy = xp[..., 2:, :] - xp[..., :-2, :]  # (H, W+2)
    gy = (dy[..., :, :-2] + 2.0 * dy[..., :, 1:-1] + dy[..., :, 2:]) / 8.0
    return gx, gy


class MTFNet(nn.Module):
    """``forward(image) -> (B, 16)`` MTF (H then V) for B×T×P×P stacks in [0, 1] (T = 1: one patch)."""

    def __init__(
        self, widths: tuple[int, int, int] = (32, 64, 96), hidden: tuple[int, ...] = (128, 64), downsample: int = 4,
        joint_directions: bool = False,
    ) -> None:
        super().__init__()
        w1, w2, w3 = widths
        self.joint_directions = bool(joint_directions)
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
        self.head = FullyConnectedBlock((6 if self.joint_directions else 3) * w3, hidden, 8)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        b, t = image.shape[:2]
        x = self.pre(image)
        if x.is_contiguous(memory_format=torch.channels_last) is False and image.is_contiguous(memory_format=torch.channels_last):
            x = x.contiguous(memory_format=torch.channels_last)
        feats = self.pool(self.body(self.stem(x))).float()  # (2·B·T, F)
        feats = feats.view(2, b, t, -1).mean(2)  # average the T patches of a stack
        if self.joint_directions:  # each direction's regressor reads [own, other] features
            feats = torch.cat([feats, feats.flip(0)], dim=-1)
        mtf = torch.sigmoid(self.head(feats).float())  # (2, B, 8)
        return torch.cat([mtf[0], mtf[1]], dim=1)

    def state_from(self, source: "MTFNet") -> dict[str, torch.Tensor]:
        """``source``'s weights laid out for this network, so that it starts as ``source`` exactly: a
        one-direction ``source`` carried into a ``joint_directions`` network gets zero weights on the other
        direction's features. Raises ``ValueError`` for the reverse (the other direction's weights would be lost)."""
        state = dict(source.state_dict())
        if self.joint_directions == source.joint_directions:
            return state
        if source.joint_directions:
            raise ValueError("the source regressor reads both directions (joint_directions) and this network does not")
        w_old = state["head.0.weight"]
        state["head.0.weight"] = torch.cat([w_old, torch.zeros_like(w_old)], dim=1)
        return state


class MTFEstimator(EstimatorModule):
    """LightningModule of the MTF estimator.

    Args:
        patch_size: side [px] of the training patches (thesis: 192); the estimator's input size.
        widths: channels of the three resolution stages.
        hidden: hidden layers of the fully connected regressor.
        downsample: space-to-depth factor of the pre-processing.
        joint_directions: the regressor of each direction also reads the other direction's features (see the
            module docstring; default False, the layout of weights files before it existed).
        train_only: optimise only the parts of the network whose parameter names start with these prefixes
            (e.g. ``[head]``), the rest frozen (:func:`lightning_modules.base.freeze_all_but`); default: all.
        lr, weight_decay, channels_last, log_figures, max_figure_samples: see :class:`EstimatorModule`.
    """

    kind = "mtf"

    def __init__(
        self,
        patch_size: int = 192,
        widths: tuple[int, int, int] = (32, 64, 96),
        hidden: tuple[int, ...] = (128, 64),
        downsample: int = 4,
        joint_directions: bool = False,
        train_only: Sequence[str] | None = None,
        lr: float = 2e-3,
        weight_decay: float = 1e-4,
        channels_last: bool = True,
        log_figures: bool = True,
        max_figure_samples: int = 512,
    ) -> None:
        super().__init__(lr, weight_decay, channels_last, log_figures, max_figure_samples)
        self.save_hyperparameters()
        self._set_patch_size(patch_size)
        self.net = MTFNet(tuple(widths), tuple(hidden), downsample, joint_directions)
        freeze_all_but(self.net, train_only)
        self.val_amae = AMAEPerFamily(FAMILIES)
        self.test_amae = AMAEPerFamily(FAMILIES)

    def forward(self, image: torch.Tensor, meta_raw: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """MTF (B, 16), H at the 8 frequencies then V, for B×1×P×P patches (or B×T×P×P stacks)."""
        return {"mtf": self.net(self._prepare(image))}

    def export_inputs(self, batch_size: int = 2) -> tuple[torch.Tensor, ...]:
        g = torch.Generator().manual_seed(0)
        return (torch.rand(batch_size, 1, self.patch_size, self.patch_size, generator=g),)

    def training_step(self, batch: Mapping[str, Any], batch_idx: int) -> torch.Tensor:
        est = self(batch["image"])["mtf"]
        loss = F.l1_loss(est, batch["mtf"].to(est))
        self.log("train/loss", loss, prog_bar=True, batch_size=est.shape[0])
        return loss

    def validation_step(self, batch: Mapping[str, Any], batch_idx: int) -> None:
        est = self(batch["image"])["mtf"]
        truth = batch["mtf"].to(est)
        self.log("val/loss", F.l1_loss(est, truth), prog_bar=True, batch_size=est.shape[0], sync_dist=True)
        self.val_amae.update(est, truth, batch["family"])
        self._cache_for_figures(est=est, truth=truth, family=batch["family"].float(), size=batch["size"].float())

    def on_validation_epoch_end(self) -> None:
        stats = self.val_amae.compute()
        self.log_dict({f"val/{k}": v for k, v in stats.items() if k != "amae"}, sync_dist=True)
        self.log("val/amae", stats["amae"], prog_bar=True, sync_dist=True)
        self.val_amae.reset()
        cache = self._take_figure_cache()
        tb = self._tensorboard()
        if tb is not None and "est" in cache:
            from lightning_modules.figures import mtf_curves_figure

            captions = [f"{FAMILIES[int(f)]} {s:.1f} px" for f, s in zip(cache["family"].tolist(), cache["size"].tolist())]
            tb.add_figure("val/mtf_curves", mtf_curves_figure(cache["est"], cache["truth"], captions), self.global_step)

    def test_step(self, batch: Mapping[str, Any], batch_idx: int) -> None:
        est = self(batch["image"])["mtf"]
        self.test_amae.update(est, batch["mtf"].to(est), batch["family"])

    def on_test_epoch_end(self) -> None:
        self.log_dict({f"test/{k}": v for k, v in self.test_amae.compute().items()}, sync_dist=True)
        self.test_amae.reset()

    def predict_step(self, batch: Mapping[str, Any], batch_idx: int) -> dict[str, torch.Tensor]:
        return self(batch["image"])
