"""LightningModule that trains the MTF estimator (thesis Sec. 4.3.1, after Bauer et al. 2018): 8 MTF values per
direction (H and V) from one 192-px patch or a temporal stack of patches. The network and its batched pre-processing
are :class:`camhealth.nets.mtf.MTFNet` and :class:`~camhealth.nets.mtf.MTFPreprocess` (plain ``torch.nn.Module``s,
architecture described there); their names stay importable from here.

Loss: L1 on the 16 MTF values; metric: AMAE (Eq. 5.1) in % per blur family.
"""

from __future__ import annotations

from typing import Any, Mapping

import torch
import torch.nn.functional as F

from camhealth.nets.mtf import MTFNet, MTFPreprocess, sobel
from lightning_modules.base import EstimatorModule
from lightning_modules.metrics import AMAEPerFamily

__all__ = ["MTFPreprocess", "MTFNet", "MTFEstimator", "FAMILIES", "sobel"]

FAMILIES: tuple[str, ...] = ("defocus", "linear", "nonlinear")


class MTFEstimator(EstimatorModule):
    """LightningModule of the MTF estimator.

    Args:
        patch_size: side [px] of the training patches (thesis: 192); the estimator's input size.
        widths: channels of the three resolution stages.
        hidden: hidden layers of the fully connected regressor.
        downsample: space-to-depth factor of the pre-processing.
        lr, weight_decay, channels_last, log_figures, max_figure_samples: see :class:`EstimatorModule`.
    """

    kind = "mtf"

    def __init__(
        self,
        patch_size: int = 192,
        widths: tuple[int, int, int] = (32, 64, 96),
        hidden: tuple[int, ...] = (128, 64),
        downsample: int = 4,
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
        self.net = MTFNet(tuple(widths), tuple(hidden), downsample)
        if self.patch_size % self.net.pre.downsample:  # the space-to-depth stem takes whole s×s cells
            raise ValueError(f"patch_size = {self.patch_size} px must be a multiple of downsample = "
                             f"{self.net.pre.downsample} (the network's space-to-depth factor)")
        self.val_amae = AMAEPerFamily(FAMILIES)
        self.test_amae = AMAEPerFamily(FAMILIES)

    def forward(self, image: torch.Tensor, meta_raw: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """MTF (B, 16), H at the 8 frequencies then V, for B×1×P×P patches (or B×T×P×P stacks) in [0, 1]
        (P = ``patch_size``). Another shape, an integer dtype, NaN/inf or a value outside [0, 1] is an error naming it
        (as :class:`~lightning_modules.NoiseSourceEstimator` refuses them); B = 0 gives a (0, 16) output."""
        self._check_image(image, stack=True)
        return {"mtf": self.net(self._prepare(image))}

    def export_inputs(self, batch_size: int = 2) -> tuple[torch.Tensor, ...]:
        g = torch.Generator().manual_seed(0)
        return (torch.rand(batch_size, 1, self.patch_size, self.patch_size, generator=g),)

    def _estimate_and_truth(self, batch: Mapping[str, Any], batch_idx: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(estimate, label) (B, 16). The label ``batch["mtf"]`` must be (B, 16) (a (1, 16) one would be broadcast to
        every patch) and finite: a ``ValueError`` naming it and the batch otherwise."""
        est = self(batch["image"])["mtf"]
        truth = self._label(batch, "mtf", tuple(est.shape))
        if not bool(torch.isfinite(truth).all()):
            self._refuse_non_finite({"batch['mtf']": truth}, batch_idx)
        return est, truth.to(est)

    def training_step(self, batch: Mapping[str, Any], batch_idx: int) -> torch.Tensor:
        est, truth = self._estimate_and_truth(batch, batch_idx)
        loss = F.l1_loss(est, truth)
        self.log("train/loss", loss, prog_bar=True, batch_size=est.shape[0])
        return loss

    def validation_step(self, batch: Mapping[str, Any], batch_idx: int) -> None:
        est, truth = self._estimate_and_truth(batch, batch_idx)
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
        est, truth = self._estimate_and_truth(batch, batch_idx)
        self.test_amae.update(est, truth, batch["family"])

    def on_test_epoch_end(self) -> None:
        self.log_dict({f"test/{k}": v for k, v in self.test_amae.compute().items()}, sync_dist=True)
        self.test_amae.reset()

    def predict_step(self, batch: Mapping[str, Any], batch_idx: int) -> dict[str, torch.Tensor]:
        return self(batch["image"])
