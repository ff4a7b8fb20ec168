"""Noise-level estimator (thesis Sec. 4.3.2, DRNE after Tan et al. 2019): a pixel-wise σ map of the total
noise and its patch statistics, for signal-dependent (Poisson–Gaussian) sensor noise.

:class:`NoiseLevelNet` keeps the DRNE idea — no pooling on the way to a per-pixel output, dilated
convolutions for context, residual blocks — at CPU cost: the patch and its ×32 high-pass residual are
folded 2×2 into 8 channels (space-to-depth), processed at half resolution by a stem, three dilated
residual blocks (dilation 1, 2, 4) and a head, and unfolded back to full resolution with a pixel shuffle
(depth-to-space), so the map is still per pixel. ≈ 0.5 GFLOP per 128-px patch at ``width = 32``.
:class:`ThesisNoiseNet` is the thesis-size reference (16 full-resolution 64-channel 3×3 layers,
≈ 17 GFLOP per 128-px patch) used by the benchmark.

Targets (from :class:`datamodules.NoiseDataModule`, physics at training time): the analytic per-pixel σ
of the image's metadata M', σ(x)² = 255²·g·I(x)/FW + σ_DCSN² + σ_RN² [DN²] with I the clean patch (before
clipping), and the realised patch σ after clipping (``sigma_total``). The patch estimate is the
root-mean-square of the map, √(mean σ̂(x)²), which is the σ of all noise in the patch when the map is right.
"""

from __future__ import annotations

from typing import Any, Mapping

import torch
import torch.nn.functional as F
from torch import nn

from camhealth.physics.dark_current import dark_current_shot_sigma_e
from camhealth.physics.readout_noise import readout_sigma_e
from lightning_modules.base import EstimatorModule
from lightning_modules.blocks import ConvAct, ResidualBlock
from lightning_modules.metrics import NoiseErrorStats
from camhealth.estimators.noise_features import metadata_from_matrix

__all__ = ["NoiseLevelNet", "ThesisNoiseNet", "NoiseLevelEstimator", "sigma_map_target_dn"]


class NoiseLevelNet(nn.Module):
    """B×1×H×W in [0, 1] (H, W even) → B×1×H×W σ map [DN] (≥ 0)."""

    def __init__(self, width: int = 32, dilations: tuple[int, ...] = (1, 2, 4), highpass_gain: float = 32.0) -> None:
        super().__init__()
        self.highpass_gain = float(highpass_gain)
        self.unshuffle = nn.PixelUnshuffle(2)
        self.stem = ConvAct(8, width)
        self.body = nn.Sequential(*[ResidualBlock(width, width, dilation=d) for d in dilations])
        self.head = nn.Sequential(ConvAct(width, width), nn.Conv2d(width, 4, 3, padding=1))
        self.shuffle = nn.PixelShuffle(2)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        local_mean = F.avg_pool2d(F.pad(image, (1, 1, 1, 1), mode="replicate"), 3, stride=1)
        x = torch.cat([image * 2.0 - 1.0, (image - local_mean) * self.highpass_gain], dim=1)
        y = self.shuffle(self.head(self.body(self.stem(self.unshuffle(x)))))
        return 5.0 * F.softplus(y.float())


class ThesisNoiseNet(nn.Module):
    """Thesis-size reference: 16 full-resolution 3×3 convolution layers, 64 channels (≈ 17 GFLOP per
    128-px patch), output a σ map [DN]. Used to time the thesis's design on the same patches."""

    def __init__(self, width: int = 64, layers: int = 16) -> None:
        super().__init__()
        mods: list[nn.Module] = [ConvAct(1, width)]
        mods += [ConvAct(width, width) for _ in range(layers - 2)]
        mods.append(nn.Conv2d(width, 1, 3, padding=1))
        self.body = nn.Sequential(*mods)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return 5.0 * F.softplus(self.body(image).float())


def sigma_map_target_dn(clean: torch.Tensor, meta_image_raw: torch.Tensor) -> torch.Tensor:
    """Analytic per-pixel σ [DN] of the noise model for clean patches under metadata M' (B, 11), before
    clipping: √(255²·g·I/FW + σ_DCSN² + σ_RN²)."""
    meta = metadata_from_matrix(meta_image_raw.to(clean.device).double())
    dn = meta.dn_per_electron
    const = (dark_current_shot_sigma_e(meta) * dn).pow(2) + (readout_sigma_e(meta) * dn).pow(2)
    slope = 255.0**2 * meta.gain_factor / meta.full_well_e
    var = slope.view(-1, 1, 1, 1) * clean.double().clamp(0, 1) + const.view(-1, 1, 1, 1)
    return var.sqrt().float()


class NoiseLevelEstimator(EstimatorModule):
    """LightningModule of the DRNE-style noise-level estimator (no metadata).

    Args:
        patch_size: side [px] of the training patches (thesis: 128); the estimator's input size.
        width: channels of the network.
        dilations: dilation of each residual block.
        map_weight: weight of the per-pixel map loss against the patch-σ loss.
        huber_beta_dn: smooth-L1 transition [DN].
        lr, weight_decay, channels_last, log_figures, max_figure_samples: see :class:`EstimatorModule`.
    """

    kind = "drne"
    metric_names: tuple[str, ...] = ("total",)

    def __init__(
        self,
        patch_size: int = 128,
        width: int = 32,
        dilations: tuple[int, ...] = (1, 2, 4),
        map_weight: float = 0.5,
        huber_beta_dn: float = 0.5,
        lr: float = 2e-3,
        weight_decay: float = 1e-4,
        channels_last: bool = True,
        log_figures: bool = True,
        max_figure_samples: int = 512,
    ) -> None:
        super().__init__(lr, weight_decay, channels_last, log_figures, max_figure_samples)
        self.save_hyperparameters()
        self._set_patch_size(patch_size)
        self.net = NoiseLevelNet(width, tuple(dilations))
        self.map_weight = float(map_weight)
        self.huber_beta_dn = float(huber_beta_dn)
        self.val_stats = NoiseErrorStats(self.metric_names)
        self.test_stats = NoiseErrorStats(self.metric_names)

    def forward(self, image: torch.Tensor, meta_raw: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """σ map [DN] (B×1×H×W) and its patch RMS (``sigma_total``), mean and median [DN]."""
        sigma_map = self.net(self._prepare(image))
        flat = sigma_map.flatten(1)
        return {
            "sigma_map": sigma_map,
            "sigma_total": flat.pow(2).mean(1).sqrt(),
            "sigma_mean": flat.mean(1),
            "sigma_median": flat.median(1).values,
        }

    def export_inputs(self, batch_size: int = 2) -> tuple[torch.Tensor, ...]:
        g = torch.Generator().manual_seed(0)
        return (torch.rand(batch_size, 1, self.patch_size, self.patch_size, generator=g),)

    def _step(self, batch: Mapping[str, Any]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        out = self(batch["image"])
        target_map = sigma_map_target_dn(batch["clean"], batch["meta_image_raw"])
        beta = self.huber_beta_dn
        map_loss = F.smooth_l1_loss(out["sigma_map"], target_map, beta=beta)
        patch_loss = F.smooth_l1_loss(out["sigma_total"], batch["sigma_total"].to(out["sigma_total"]), beta=beta)
        loss = self.map_weight * map_loss + (1.0 - self.map_weight) * patch_loss
        return loss, out["sigma_total"][:, None], batch["sigma_total"][:, None].to(out["sigma_total"])

    def training_step(self, batch: Mapping[str, Any], batch_idx: int) -> torch.Tensor:
        loss, _, _ = self._step(batch)
        self.log("train/loss", loss, prog_bar=True, batch_size=batch["image"].shape[0])
        return loss

    def validation_step(self, batch: Mapping[str, Any], batch_idx: int) -> None:
        loss, est, truth = self._step(batch)
        self.log("val/loss", loss, prog_bar=True, batch_size=est.shape[0], sync_dist=True)
        self.val_stats.update(est, truth)
        self._cache_for_figures(est=est, truth=truth)

    def on_validation_epoch_end(self) -> None:
        stats = self.val_stats.compute()
        self.log_dict({f"val/{k}": v for k, v in stats.items() if k != "rms_total"}, sync_dist=True)
        self.log("val/rms_total", stats["rms_total"], prog_bar=True, sync_dist=True)
        self.val_stats.reset()
        cache = self._take_figure_cache()
        tb = self._tensorboard()
        if tb is not None and "est" in cache:
            from lightning_modules.figures import sigma_scatter_figure

            tb.add_figure("val/sigma_scatter", sigma_scatter_figure(cache["est"], cache["truth"], ["total"]), self.global_step)

    def test_step(self, batch: Mapping[str, Any], batch_idx: int) -> None:
        _, est, truth = self._step(batch)
        self.test_stats.update(est, truth)

    def on_test_epoch_end(self) -> None:
        self.log_dict({f"test/{k}": v for k, v in self.test_stats.compute().items()}, sync_dist=True)
        self.test_stats.reset()

    def predict_step(self, batch: Mapping[str, Any], batch_idx: int) -> dict[str, torch.Tensor]:
        return self(batch["image"])
