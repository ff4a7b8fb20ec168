"""LightningModule that trains the noise-source network (thesis Sec. 4.3.3) for cameras without full metadata.

The network — σ of photon shot (PN), dark-current shot (DCSN) and readout noise (RN) and the residual ξ from one patch
plus what metadata there are — is :class:`camhealth.nets.noise_source.NoiseSourceNet` (a plain ``torch.nn.Module``,
architecture described there); its names stay importable from here.

Training targets (from :class:`datamodules.NoiseDataModule`): realised σ per source after gain and
clipping (``sigma``), the realised total (``sigma_total``) and ξ (``xi``), all in DN, with a smooth-L1
loss. Metrics: Bias/Std/RMS (Eq. 6.2) per source, total and ξ.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import torch
import torch.nn.functional as F

from camhealth.estimators.noise_features import metadata_from_matrix
from camhealth.nets.noise_source import BRANCH_FIELDS, NETWORK_METADATA_SETS, OUTPUTS, NoiseSourceNet, NoiseTrunk
from camhealth.physics.metadata import FULL_FIELDS
from lightning_modules.base import EstimatorModule
from lightning_modules.metrics import NoiseErrorStats

__all__ = ["NoiseTrunk", "NoiseSourceNet", "NoiseSourceEstimator", "BRANCH_FIELDS", "OUTPUTS", "NETWORK_METADATA_SETS"]


class NoiseSourceEstimator(EstimatorModule):
    """LightningModule of the noise-source network (w/o- or Min-Meta).

    Args:
        patch_size: side [px] of the training patches (thesis: 128); the estimator's input size.
        metadata_set: metadata the network reads: ``minimal`` (gain, exposure, temperature; Min-Meta) or ``none``
            (w/o-Meta). With all metadata camhealth answers in closed form (``noise_source_full``).
        width: channels of the first trunk stage (the others use 2× and 4×).
        hidden: neurons of the hidden layers of each branch (thesis: 32, 16, 8).
        loss_weights: weights (≥ 0, at least one > 0; 1 for a term not given) of the smooth-L1 terms ``pn``,
            ``dcsn``, ``rn``, ``total``, ``xi``; the loss is their weighted mean.
        huber_beta_dn: smooth-L1 transition [DN].
        lr, weight_decay, channels_last, log_figures, max_figure_samples: see :class:`EstimatorModule`.
    """

    kind = "noise_source"
    metric_names: tuple[str, ...] = ("pn", "dcsn", "rn", "total", "xi")

    def __init__(
        self,
        patch_size: int = 128,
        metadata_set: str = "minimal",
        width: int = 32,
        hidden: Sequence[int] = (64, 32, 16),
        loss_weights: Mapping[str, float] | None = None,
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
        self.metadata_set = metadata_set
        self.net = NoiseSourceNet(metadata_set, width, hidden)  # (which names a hidden that is not a list of sizes)
        weights = {"pn": 1.0, "dcsn": 1.0, "rn": 1.0, "total": 1.0, "xi": 1.0, **(loss_weights or {})}
        unknown = set(weights) - set(self.metric_names)
        if unknown:
            raise ValueError(f"loss_weights has unknown key(s) {sorted(unknown)}; allowed {list(self.metric_names)}")
        weights = {k: float(v) for k, v in weights.items()}
        if not sum(weights.values()) > 0:  # the loss is their weighted mean: 0/0 otherwise
            raise ValueError(f"loss_weights = {dict(loss_weights or {})!r}: at least one loss term needs a weight > 0 "
                             f"(terms not given weigh 1; weights are ≥ 0, got {weights})")
        self.loss_weights = weights
        self.huber_beta_dn = float(huber_beta_dn)
        self.val_stats = NoiseErrorStats(self.metric_names)
        self.test_stats = NoiseErrorStats(self.metric_names)

    # ------------------------------------------------------------------ inference
    def network_inputs(self, image: torch.Tensor, meta_raw: torch.Tensor | None) -> tuple[torch.Tensor, ...]:
        """(image, normalised metadata (B, 11)) for :class:`NoiseSourceNet` (zeros for ``none``)."""
        b = image.shape[0]
        if self.metadata_set == "none":
            return image, image.new_zeros(b, len(FULL_FIELDS))
        if meta_raw is None:
            raise ValueError(f"this estimator reads {self.metadata_set!r} metadata; pass metadata")
        meta = metadata_from_matrix(meta_raw.to(image.device))
        return image, meta.normalize("full").to(image.dtype)

    def forward(self, image: torch.Tensor, meta_raw: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """σ̂ per source, total and ξ̂ in DN for B×1×P×P patches in [0, 1] (P = ``patch_size``; another shape is a
        ``ValueError`` naming it, and the network's image statistics refuse an integer dtype, NaN/inf and values
        outside [0, 1]) and (B, 11) raw metadata."""
        self._check_image(image, values=False)  # (the values: image_statistics checks them, once)
        img, norm = self.network_inputs(image, meta_raw)
        out = self.net(self._prepare(img), norm)
        sigma = out[:, :3]
        return {"sigma": sigma, "sigma_total": sigma.pow(2).sum(1).add(1e-12).sqrt(), "xi": out[:, 3]}

    def export_inputs(self, batch_size: int = 2) -> tuple[torch.Tensor, ...]:
        g = torch.Generator().manual_seed(0)
        image = torch.rand(batch_size, 1, self.patch_size, self.patch_size, generator=g)
        return image, torch.rand(batch_size, len(FULL_FIELDS), generator=g)

    @property
    def example_input_array(self) -> tuple[torch.Tensor, ...]:
        """One patch in [0, 1] and the raw metadata (1, 11) of an ICX285 at its default operating point."""
        from camhealth.physics.metadata import CameraMetadata

        meta = CameraMetadata.lookup("ICX285").expand(1)
        return (*super().example_input_array, torch.stack([getattr(meta, n).float() for n in FULL_FIELDS], 1))

    # ------------------------------------------------------------------ training
    def _estimates_and_truth(self, batch: Mapping[str, Any],
                             batch_idx: int | None = None) -> tuple[torch.Tensor, torch.Tensor, dict]:
        """(estimates, labels) (B, 5) in the order of :attr:`metric_names` and the outputs. The labels ``sigma`` (B, 3),
        ``sigma_total`` (B,) and ``xi`` (B,) are checked: another shape, or a NaN/inf (one check of all of them), is a
        ``ValueError`` naming the label (and the batch)."""
        out = self(batch["image"], batch.get("meta_raw"))
        b = out["sigma"].shape[0]
        labels = {"sigma": self._label(batch, "sigma", (b, 3)), "sigma_total": self._label(batch, "sigma_total", (b,)),
                  "xi": self._label(batch, "xi", (b,))}
        est = torch.cat([out["sigma"], out["sigma_total"][:, None], out["xi"][:, None]], dim=1)
        truth = torch.cat([labels["sigma"], labels["sigma_total"][:, None], labels["xi"][:, None]], dim=1).to(est)
        if not bool(torch.isfinite(truth).all()):
            self._refuse_non_finite({f"batch[{k!r}]": v for k, v in labels.items()}, batch_idx)
        return est, truth, out

    def _loss(self, est: torch.Tensor, truth: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        per = F.smooth_l1_loss(est, truth, beta=self.huber_beta_dn, reduction="none").mean(0)
        terms = {n: per[i] for i, n in enumerate(self.metric_names)}
        loss = sum(self.loss_weights[n] * terms[n] for n in self.metric_names) / sum(self.loss_weights.values())
        return loss, terms

    def training_step(self, batch: Mapping[str, Any], batch_idx: int) -> torch.Tensor:
        est, truth, _ = self._estimates_and_truth(batch, batch_idx)
        loss, terms = self._loss(est, truth)
        self.log("train/loss", loss, prog_bar=True, batch_size=est.shape[0])
        self.log_dict({f"train/loss_{k}": v for k, v in terms.items()}, batch_size=est.shape[0])
        return loss

    def validation_step(self, batch: Mapping[str, Any], batch_idx: int) -> None:
        est, truth, _ = self._estimates_and_truth(batch, batch_idx)
        loss, _ = self._loss(est, truth)
        self.log("val/loss", loss, prog_bar=True, batch_size=est.shape[0], sync_dist=True)
        self.val_stats.update(est, truth)
        if batch_idx == 0:
            self._cache_for_figures(images=batch["image"][:8], est_first=est[:8], truth_first=truth[:8])
        self._cache_for_figures(est=est, truth=truth)

    def on_validation_epoch_end(self) -> None:
        stats = self.val_stats.compute()
        self.log_dict({f"val/{k}": v for k, v in stats.items() if k != "rms_total"}, sync_dist=True)
        self.log("val/rms_total", stats["rms_total"], prog_bar=True, sync_dist=True)
        self.val_stats.reset()
        self._log_figures("val")

    def test_step(self, batch: Mapping[str, Any], batch_idx: int) -> None:
        est, truth, _ = self._estimates_and_truth(batch, batch_idx)
        self.test_stats.update(est, truth)

    def on_test_epoch_end(self) -> None:
        self.log_dict({f"test/{k}": v for k, v in self.test_stats.compute().items()}, sync_dist=True)
        self.test_stats.reset()

    def predict_step(self, batch: Mapping[str, Any], batch_idx: int) -> dict[str, torch.Tensor]:
        return self(batch["image"], batch.get("meta_raw"))

    def _log_figures(self, stage: str) -> None:
        cache = self._take_figure_cache()
        tb = self._tensorboard()
        if tb is None or "est" not in cache:
            return
        from lightning_modules.figures import patch_grid_figure, sigma_scatter_figure

        names = ["PN", "DCSN", "RN", "total", "ξ"]
        tb.add_figure(f"{stage}/sigma_scatter", sigma_scatter_figure(cache["est"], cache["truth"], names), self.global_step)
        e, t = cache["est_first"], cache["truth_first"]
        captions = [
            f"σ̂ {e[j, 3]:.1f} / σ {t[j, 3]:.1f}\nPN {e[j, 0]:.1f}/{t[j, 0]:.1f} ξ {e[j, 4]:.1f}/{t[j, 4]:.1f}"
            for j in range(e.shape[0])
        ]
        tb.add_figure(f"{stage}/patches", patch_grid_figure(cache["images"], captions), self.global_step)
