"""LightningModule that trains the noise-level network (thesis Sec. 4.3.2, DRNE after Tan et al. 2019): a pixel-wise
σ map of the total noise and its patch statistics. The network is :class:`camhealth.nets.drne.NoiseLevelNet` (a plain
``torch.nn.Module``, architecture described there; :class:`~camhealth.nets.drne.ThesisNoiseNet` is the thesis-size
reference); their names stay importable from here.

Targets (from :class:`datamodules.NoiseDataModule`, physics at training time): the analytic per-pixel σ
of the image's metadata M', σ(x)² = 255²·g·I(x)/FW + σ_DCSN² + σ_RN² [DN²] with I the clean patch (before
clipping) and only the sources the data module realises (``noise_sources``; a source it leaves out has
``sigma_expected`` 0 and no term), and the realised patch σ after clipping (``sigma_total``). The patch estimate is
the root-mean-square of the map, √(mean σ̂(x)²), which is the σ of all noise in the patch when the map is right.
"""

from __future__ import annotations

from typing import Any, Mapping

import torch
import torch.nn.functional as F

from camhealth.estimators.noise_features import metadata_from_matrix
from camhealth.nets.drne import NoiseLevelNet, ThesisNoiseNet, check_dilations
from camhealth.physics.dark_current import dark_current_shot_sigma_e
from camhealth.physics.readout_noise import readout_sigma_e
from lightning_modules.base import EstimatorModule
from lightning_modules.metrics import NoiseErrorStats

__all__ = ["NoiseLevelNet", "ThesisNoiseNet", "NoiseLevelEstimator", "sigma_map_target_dn"]


def sigma_map_target_dn(
    clean: torch.Tensor, meta_image_raw: torch.Tensor, sigma_expected: torch.Tensor | None = None
) -> torch.Tensor:
    """Analytic per-pixel σ [DN] of the noise model for clean patches under metadata M' (B, 11), before
    clipping: √(255²·g·I/FW + σ_DCSN² + σ_RN²).

    ``sigma_expected`` (B, 3): the batch's analytic σ of (PN, DCSN, RN) [DN] (:class:`datamodules.NoiseDataModule`),
    0 for a source the data module does not realise (``noise_sources``). Each source whose entry is 0 is left out
    of the map, so the map describes the noise that is in the image; without it all three sources are in. An entry
    that is NaN, ±inf or negative is a ``ValueError`` naming it (it would read as "not realised" and drop the source)."""
    meta = metadata_from_matrix(meta_image_raw.to(clean.device).double())
    dn = meta.dn_per_electron
    dcsn = (dark_current_shot_sigma_e(meta) * dn).pow(2)
    rn = (readout_sigma_e(meta) * dn).pow(2)
    slope = 255.0**2 * meta.gain_factor / meta.full_well_e
    if sigma_expected is not None:
        se = sigma_expected.to(clean.device)
        if se.ndim != 2 or se.shape[1] != 3 or se.shape[0] != clean.shape[0]:
            raise ValueError(f"sigma_expected has shape {tuple(se.shape)}; it must be (B, 3) = ({clean.shape[0]}, 3): "
                             "σ of PN, DCSN, RN per patch")
        ok = torch.isfinite(se) & (se >= 0)
        if not bool(ok.all()):
            raise ValueError(f"sigma_expected must hold finite σ >= 0 DN (0: a source not realised), but "
                             f"{int((~ok).sum())} of {se.numel()} values are not (first: {se[~ok][0].item()})")
        realised = se > 0
        slope = torch.where(realised[:, 0], slope, torch.zeros_like(slope))
        dcsn = torch.where(realised[:, 1], dcsn, torch.zeros_like(dcsn))
        rn = torch.where(realised[:, 2], rn, torch.zeros_like(rn))
    const = dcsn + rn
    var = slope.view(-1, 1, 1, 1) * clean.double().clamp(0, 1) + const.view(-1, 1, 1, 1)
    return var.sqrt().float()


class NoiseLevelEstimator(EstimatorModule):
    """LightningModule of the DRNE-style noise-level estimator (no metadata).

    Args:
        patch_size: side [px] of the training patches (thesis: 128); the estimator's input size.
        width: channels of the network.
        dilations: dilation of each residual block, each an integer in [1, patch_size // 2 − 1] (the blocks run at
            half resolution; a larger dilation would reach only the zero padding: ``ValueError``).
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
        self._check_training_args()
        self._set_patch_size(patch_size)
        self.net = NoiseLevelNet(width, check_dilations(dilations, self.patch_size))
        self.map_weight = float(map_weight)
        self.huber_beta_dn = float(huber_beta_dn)
        self.val_stats = NoiseErrorStats(self.metric_names)
        self.test_stats = NoiseErrorStats(self.metric_names)

    def forward(self, image: torch.Tensor, meta_raw: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """σ map [DN] (B×1×P×P) and its patch RMS (``sigma_total``), mean and median [DN] for B×1×P×P patches in
        [0, 1] (P = ``patch_size``). Another shape, an integer dtype, NaN/inf or a value outside [0, 1] is an error
        naming it (as :class:`~lightning_modules.NoiseSourceEstimator` refuses them); B = 0 gives empty outputs."""
        self._check_image(image)
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

    def _step(self, batch: Mapping[str, Any], batch_idx: int | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(loss, estimate (B, 1), truth (B, 1)). The labels are checked: ``sigma_total`` (B,) and ``clean`` (B×1×P×P,
        the image's shape) or a ``ValueError`` naming the key and the shape; a NaN/inf in ``sigma_total`` or in the map
        target (from ``clean`` and ``meta_image_raw``) is a ``ValueError`` naming the label and the batch (one check)."""
        out = self(batch["image"])
        b = out["sigma_total"].shape[0]
        sigma_total = self._label(batch, "sigma_total", (b,))
        clean = self._label(batch, "clean", tuple(batch["image"].shape))
        # the sources the data realise (noise_sources): their analytic σ is 0 in sigma_expected for the others
        target_map = sigma_map_target_dn(clean, batch["meta_image_raw"], batch.get("sigma_expected"))
        if not bool(torch.isfinite(sigma_total).all() & torch.isfinite(target_map).all()):
            self._refuse_non_finite({"batch['sigma_total']": sigma_total, "batch['clean']": clean,
                                     "batch['meta_image_raw']": batch["meta_image_raw"],
                                     "σ map target (from batch['clean'], batch['meta_image_raw'])": target_map}, batch_idx)
        truth = sigma_total.to(out["sigma_total"])
        beta = self.huber_beta_dn
        map_loss = F.smooth_l1_loss(out["sigma_map"], target_map, beta=beta)
        patch_loss = F.smooth_l1_loss(out["sigma_total"], truth, beta=beta)
        loss = self.map_weight * map_loss + (1.0 - self.map_weight) * patch_loss
        return loss, out["sigma_total"][:, None], truth[:, None]

    def training_step(self, batch: Mapping[str, Any], batch_idx: int) -> torch.Tensor:
        loss, _, _ = self._step(batch, batch_idx)
        self.log("train/loss", loss, prog_bar=True, batch_size=batch["image"].shape[0])
        return loss

    def validation_step(self, batch: Mapping[str, Any], batch_idx: int) -> None:
        loss, est, truth = self._step(batch, batch_idx)
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
        _, est, truth = self._step(batch, batch_idx)
        self.test_stats.update(est, truth)

    def on_test_epoch_end(self) -> None:
        self.log_dict({f"test/{k}": v for k, v in self.test_stats.compute().items()}, sync_dist=True)
        self.test_stats.reset()

    def predict_step(self, batch: Mapping[str, Any], batch_idx: int) -> dict[str, torch.Tensor]:
        return self(batch["image"])
