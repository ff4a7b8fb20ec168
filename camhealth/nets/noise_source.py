"""Noise-source network (thesis Sec. 4.3.3, Fig. 4.5 right) for cameras without full metadata: σ of photon shot noise
(PN), dark-current shot noise (DCSN), readout noise (RN) and the residual ξ from one patch plus what metadata there are.

With all eleven metadata fields the noise model fixes every source in closed form, and camhealth answers with the
physics-first estimator (:mod:`camhealth.estimators.physics_noise`, shipped as ``noise_source_full``, no network).
This network is for the thesis's other two metadata sets, where the closed form is not available: ``minimal`` (gain,
exposure, temperature; Min-Meta, shipped as ``noise_source_min``) and ``none`` (w/o-Meta, ``noise_source_none``).

Architecture (:class:`NoiseSourceNet`), sized for a 2-core CPU:

- **Shared image trunk** (:class:`NoiseTrunk`): the patch in [0, 1] and a 3×3 high-pass residual
  (amplified ×32 so 1-DN noise is O(0.1)) are folded by space-to-depth 2×2 into 8 channels at half
  resolution (no pixel is dropped), then a stem and four residual blocks (two strided) at 1/2, 1/4, 1/8
  resolution; global max/mean/std pooling. With ``width = 32`` this is ≈ 0.56 GFLOP per 128-px patch,
  ≈ 30× fewer than the thesis's 16 full-resolution 64-channel layers (≈ 17 GFLOP).
- **Four fully connected branches** (PN, DCSN, RN, ξ; the thesis's FCBs) fed the pooled features, cheap
  image statistics (:func:`~camhealth.estimators.noise_features.image_statistics`, including a robust
  classical σ estimate) and the normalised metadata that physically drive their source (:data:`BRANCH_FIELDS`,
  intersected with the configured ``metadata_set``). σ̂_s = 5·softplus(·) DN, ξ̂ = 10·(·) DN; σ̂_total = √(Σ σ̂_s²)
  (Eq. 4.2).

A plain ``torch.nn.Module``: inference imports no training framework. The LightningModule that trains it (loss,
metrics, figures) is :class:`lightning_modules.noise_source.NoiseSourceEstimator`.
"""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from camhealth.estimators.noise_features import box_mean3, image_statistics
from camhealth.nets.blocks import (ConvAct, FullyConnectedBlock, GlobalStatsPool, ResidualBlock, autocast_on, check_input_shape,
                                  check_sizes, working_dtype)
from camhealth.physics.metadata import FULL_FIELDS, METADATA_SETS

__all__ = ["NoiseTrunk", "NoiseSourceNet", "BRANCH_FIELDS", "OUTPUTS", "NETWORK_METADATA_SETS"]

#: Outputs of the noise-source network, in order (all in DN).
OUTPUTS: tuple[str, ...] = ("pn", "dcsn", "rn", "xi")

#: The metadata sets a network is trained for; with ``full`` metadata the closed form answers
#: (:mod:`camhealth.estimators.physics_noise`).
NETWORK_METADATA_SETS: tuple[str, ...] = ("none", "minimal")

#: Metadata that physically drive each source (conventions.md): PN ∝ √(g/FW); DCSN from the dark-current
#: law (D_FM, pixel area, T, t_exp) × g/FW; RN from W, f_clock, A_SN, sensor type, reset factor, T (kTC)
#: × g/FW; ξ sees everything. A network reads those of them its metadata set has.
BRANCH_FIELDS: dict[str, tuple[str, ...]] = {
    "pn": ("gain_db", "full_well_e"),
    "dcsn": ("gain_db", "exposure_s", "temperature_c", "dark_fom_na_per_cm2", "full_well_e", "pixel_size_um"),
    "rn": (
        "gain_db", "temperature_c", "full_well_e", "pixel_clock_hz", "sense_node_gain_v_per_e", "reset_factor",
        "is_cmos", "white_noise_v_per_rthz",
    ),
    "xi": FULL_FIELDS,
}


class NoiseTrunk(nn.Module):
    """Shared image trunk: B×1×P×P in [0, 1] → (B, 12·width) pooled features (P divisible by 8)."""

    def __init__(self, width: int = 32, highpass_gain: float = 32.0) -> None:
        super().__init__()
        (width,) = check_sizes(width, "width", 1)
        self.highpass_gain = float(highpass_gain)
        self.unshuffle = nn.PixelUnshuffle(2)
        self.stem = ConvAct(8, width)
        self.stages = nn.Sequential(
            ResidualBlock(width, width),
            ResidualBlock(width, 2 * width, stride=2),
            ResidualBlock(2 * width, 2 * width),
            ResidualBlock(2 * width, 4 * width, stride=2),
        )
        self.pool = GlobalStatsPool()
        self.out_features = 12 * width

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        local_mean = box_mean3(image)
        x = torch.cat([image * 2.0 - 1.0, (image - local_mean) * self.highpass_gain], dim=1)
        return self.pool(self.stages(self.stem(self.unshuffle(x))))


class NoiseSourceNet(nn.Module):
    """Trunk + four branches. ``forward(image, meta) -> (B, 4)`` σ̂ of (PN, DCSN, RN) and ξ̂ in DN.

    Args of forward:
        image: B×1×P×P in [0, 1] (P even, at least 4 px).
        meta: (B, 11) metadata normalised to [0, 1] (``CameraMetadata.normalize("full")``; zeros for ``none``);
            only the columns of the configured ``metadata_set`` are read.

    Another shape of either is a ``ValueError`` naming it; an empty batch (B = 0) gives a (0, 4) output. ``hidden``: the
    neurons of each branch's hidden layers, a list of integers >= 1 (an empty list: no hidden layer).
    """

    def __init__(self, metadata_set: str = "minimal", width: int = 32, hidden: Sequence[int] = (64, 32, 16)) -> None:
        super().__init__()
        if metadata_set not in NETWORK_METADATA_SETS:
            hint = (" (with all metadata camhealth answers in closed form: load_estimator('noise_source_full'), "
                    "camhealth.estimators.physics_noise)") if metadata_set == "full" else ""
            raise ValueError(f"metadata_set = {metadata_set!r} must be one of {list(NETWORK_METADATA_SETS)}{hint}")
        if isinstance(hidden, (str, bytes)) or not isinstance(hidden, Sequence):
            raise ValueError(f"hidden = {hidden!r} must be a list of integers >= 1 (the neurons of each branch's hidden "
                             "layers)")
        hidden = tuple(hidden)
        self.metadata_set = metadata_set
        self.trunk = NoiseTrunk(width)
        available = set(METADATA_SETS[metadata_set])
        self.branch_columns: list[list[int]] = [
            [FULL_FIELDS.index(f) for f in BRANCH_FIELDS[name] if f in available] for name in OUTPUTS
        ]
        n_base = self.trunk.out_features + 7  # pooled features, 6 image statistics, log Haar-MAD σ
        self.branches = nn.ModuleList(FullyConnectedBlock(n_base + len(cols), hidden, 1) for cols in self.branch_columns)

    @torch.no_grad()
    def trunk_activity(self, patch_size: int = 64, batch: int = 16, seed: int = 0) -> float:
        """Fraction of the trunk's pooled features that vary over a probe batch (random ramps, flats and edges
        with 0–20 DN of noise). 0 means the trunk is dead: its pooled features are constants and the branches see
        the image only through the scalar statistics (the model card reports it)."""
        g = torch.Generator().manual_seed(seed)
        shape = (batch, 1, patch_size, patch_size)
        ramp = torch.linspace(0, 1, patch_size).view(1, 1, 1, -1)
        level, slope = torch.rand(batch, 1, 1, 1, generator=g), torch.rand(batch, 1, 1, 1, generator=g) - 0.5
        edge = (torch.rand(shape, generator=g) > 0.5).float() * (torch.rand(batch, 1, 1, 1, generator=g) > 0.5)
        noise = torch.randn(shape, generator=g) * torch.rand(batch, 1, 1, 1, generator=g) * (20 / 255)
        x = (level + slope * ramp + 0.3 * edge + noise).clamp(0, 1)
        weight = next(self.trunk.parameters())
        was = self.training
        self.eval()
        feats = self.trunk(x.to(device=weight.device, dtype=weight.dtype)).float()
        self.train(was)
        return float((feats.std(0) > 1e-6).float().mean())

    def forward(self, image: torch.Tensor, meta: torch.Tensor) -> torch.Tensor:
        check_input_shape(image, "NoiseSourceNet", 2, 4)
        b = image.shape[0]
        if not isinstance(meta, torch.Tensor) or meta.ndim != 2 or meta.shape[0] != b or meta.shape[1] != len(FULL_FIELDS):
            shape = tuple(meta.shape) if isinstance(meta, torch.Tensor) else type(meta).__name__
            raise ValueError(f"meta has shape {shape}; NoiseSourceNet takes (B, {len(FULL_FIELDS)}) = ({b}, {len(FULL_FIELDS)}) "
                             "normalised metadata, one row per patch of the B×1×P×P image")
        dt = working_dtype(image, next(self.branches.parameters()))  # features, image statistics and metadata join in it
        if b == 0:
            return image.new_zeros((0, len(OUTPUTS)), dtype=dt)
        # (under autocast the image goes in as it is, its ops cast it; else in the trunk's weights' dtype)
        feats = self.trunk(image if autocast_on(image) else image.to(next(self.trunk.parameters()).dtype)).to(dt)
        stats = image_statistics(image).to(dt)
        base = torch.cat([feats, stats[:, :4], stats[:, 4:6] / 10.0, torch.log(stats[:, 5:6] + 0.1)], dim=1)
        raw = []
        for branch, cols in zip(self.branches, self.branch_columns):
            parts = [base, meta[:, cols].to(dt)] if cols else [base]
            raw.append(branch(torch.cat(parts, dim=1)).to(dt))
        raw_t = torch.cat(raw, dim=1)
        return torch.cat([5.0 * F.softplus(raw_t[:, :3]), 10.0 * raw_t[:, 3:4]], dim=1)
