"""Noise-source estimator (thesis Sec. 4.3.3, Fig. 4.5 right): σ of photon shot noise (PN), dark-current
shot noise (DCSN), readout noise (RN) and the residual ξ from one patch plus camera metadata.

Architecture (:class:`NoiseSourceNet`), sized for a 2-core CPU:

- **Shared image trunk** (:class:`NoiseTrunk`): the patch in [0, 1] and a 3×3 high-pass residual
  (amplified ×32 so 1-DN noise is O(0.1)) are folded by space-to-depth 2×2 into 8 channels at half
  resolution (no pixel is dropped), then a stem and four residual blocks (two strided) at 1/2, 1/4, 1/8
  resolution; global max/mean/std pooling. With ``width = 32`` this is ≈ 0.55 GFLOP per 128-px patch,
  ≈ 30× fewer than the thesis's 16 full-resolution 64-channel layers (≈ 17 GFLOP).
- **Four fully connected branches** (PN, DCSN, RN, ξ; the thesis's FCBs) fed the pooled features, cheap
  image statistics (:func:`~camhealth.estimators.noise_features.image_statistics`, including a robust
  classical σ estimate and, for the hybrid, its log-ratio to the closed-form total) and the normalised
  metadata that physically drive their source (:data:`BRANCH_FIELDS`, intersected with the configured
  ``metadata_set``: ``none`` = w/o-Meta, ``minimal`` = Min-Meta, ``full`` = Full-Meta).
- **Physics at inference** (``physics_prior: true``, Full-Meta only): the closed-form σ of each source
  under the given metadata (:func:`~camhealth.estimators.noise_features.physics_prior_dn`) enters each
  branch (as log σ) and the branch outputs a bounded log-correction: σ̂_s = σ_s(M) · exp(δ_s),
  δ_s = r + 5·tanh(Δ_s/5) (clamped to ±8), where r = log((σ̂_MAD + 0.1)/(σ_Model(M) + 0.1)) is the log-ratio of a robust
  classical estimate of the noise in the image (Haar-MAD) to the noise the metadata predict, and Δ_s is
  learned. ξ̂ = σ_Model(M) − σ_Model(M)·exp(δ_ξ). With zero-initialised output layers the untrained
  hybrid is the closed-form noise model, split over the sources as the physics says and scaled to the
  noise level the image shows; training learns what neither can give: texture bias of the classical
  estimate, clipping and saturation, and which source a mismatch ξ belongs to. The pure network (``physics_prior: false``) predicts σ̂_s = 5·softplus(·) DN and ξ̂ directly.

- **Total head** (``total_branch: true``, the default): the realised total after clipping is *not* the quadrature
  sum of the per-source σ once pixels clip — clipping scales every source's noise at a clipped pixel by the
  same factor (the attribution rule of :func:`~camhealth.physics.image_formation.form_image`), which
  correlates the attributed sources, so √(Σ σ_s²) overstates the realised total (by ≈ 1 % at a few clipped
  pixels, by a fifth or more on half-clipped patches; even the true per-source σ give 0.8–0.9 DN total RMS on
  the 592-patch held-out set). A fifth branch (all metadata, the pooled features, the clipped fractions, log √(Σ σ̂_s²))
  learns a bounded log-correction: σ̂_total = √(Σ σ̂_s²) · exp(5·tanh(Δ_T/5)), zero-initialised, so without
  training it is Eq. 4.2's quadrature sum. Weights files written before it existed load with
  ``total_branch: false`` (total = √(Σ σ̂_s²)).

- **Wider branch inputs** (options, off by default and in the shipped files written before them):
  ``branch_inputs: all`` feeds every source branch all metadata fields and the closed-form σ of every source
  and the total (the split of an excess between DCSN and RN depends on what a temperature change and what a
  white-noise change could explain, i.e. on both sources' metadata); ``nlf_statistics: true`` adds the Haar-MAD σ
  and mean intensity of three intensity terciles of the patch
  (:func:`~camhealth.estimators.noise_features.nlf_statistics`: photon noise grows with intensity, dark-current and
  readout noise do not). :meth:`NoiseSourceNet.state_from` carries the weights of a network that reads less
  into one that reads more with zero weights on the new inputs, so ``--init_from`` starts exactly there.

- **Clipping and the image's noise level from physics** (options, off by default; on in the shipped
  ``noise_source_full_meta`` since session 8): ``prior_clipping: true`` starts the source branches from σ_s(M)
  *after clipping* to [0, 255] DN and the total head from the clipped total
  (:func:`~camhealth.estimators.noise_features.clipped_prior_dn`: the clean scene recovered near the bounds, the
  per-pixel variances carried through the clipping in closed form), so the network no longer learns what saturation
  does to each source; ``noise_fit_statistics: true`` feeds every branch two metadata-conditioned fits of the
  patch's noise-level function on its flat, unclipped blocks — the signal-independent variance with the photon
  slope fixed, the gain ratio with the metadata's split fixed — their likelihood ratio and what σ_DCSN and σ_RN
  would be if one of them alone took up the change (:func:`~camhealth.estimators.noise_features.noise_fit_statistics`).
  Both are computed with the prior, outside the exported graph; the prior input is then (B, 8), (B, 10) or (B, 14).

- **Which field is wrong, from physics** (option ``mismatch_posterior``, session 9; needs ``prior_clipping``): the
  Bayesian posterior over single-field mismatches of the metadata (:mod:`camhealth.estimators.mismatch_posterior`) —
  every candidate's σ from the physics, weighed by the likelihood of the patch's flat-block details — appended to
  the prior (eleven columns), and a trust head that blends each output with it,
  log σ̂ = log σ̂_own + λ·(log σ_post − log σ̂_own), λ = sigmoid(·) ∈ (0, 1) learned per patch and output, 0 where the
  posterior abstains. The branches are unchanged, so ``--init_from`` a file without it starts at λ = 0.05.

Training targets (from :class:`datamodules.NoiseDataModule`): realised σ per source after gain and
clipping (``sigma``), the realised total (``sigma_total``) and ξ (``xi``), all in DN, with a smooth-L1
loss. Metrics: Bias/Std/RMS (Eq. 6.2) per source, total and ξ.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from camhealth.physics.metadata import FULL_FIELDS, METADATA_SETS
from lightning_modules.base import EstimatorModule, freeze_all_but
from lightning_modules.blocks import ConvAct, FullyConnectedBlock, GlobalStatsPool, ResidualBlock
from lightning_modules.metrics import NoiseErrorStats
from camhealth.estimators.noise_features import (
    _MIN_FIT_BLOCKS, IMAGE_STATISTICS, NLF_STATISTICS, NOISE_FIT_STATISTICS, box_mean3, image_statistics, metadata_from_matrix,
    nlf_statistics, physics_prior_dn,
)
from camhealth.estimators.mismatch_posterior import MISMATCH_POSTERIOR

__all__ = [
    "NoiseTrunk", "NoiseSourceNet", "NoiseSourceEstimator", "BRANCH_FIELDS", "BRANCH_INPUTS", "OUTPUTS", "PRIOR_ANCHORS",
    "TRUNK_ACTIVATIONS",
]

#: Outputs of the noise-source network, in order (all in DN).
OUTPUTS: tuple[str, ...] = ("pn", "dcsn", "rn", "xi")

#: Metadata that physically drive each source (conventions.md): PN ∝ √(g/FW); DCSN from the dark-current
#: law (D_FM, pixel area, T, t_exp) × g/FW; RN from W, f_clock, A_SN, sensor type, reset factor, T (kTC)
#: × g/FW; ξ sees everything.
BRANCH_FIELDS: dict[str, tuple[str, ...]] = {
    "pn": ("gain_db", "full_well_e"),
    "dcsn": ("gain_db", "exposure_s", "temperature_c", "dark_fom_na_per_cm2", "full_well_e", "pixel_size_um"),
    "rn": (
        "gain_db", "temperature_c", "full_well_e", "pixel_clock_hz", "sense_node_gain_v_per_e", "reset_factor",
        "is_cmos", "white_noise_v_per_rthz",
    ),
    "xi": FULL_FIELDS,
}

_MAX_LOG_CORRECTION = 5.0
# Initial output bias of the trust head: λ = sigmoid(−3) ≈ 0.05 (a small, non-zero gradient toward the posterior).
_TRUST_START = -3.0
#: What the trust head reads besides the branches' inputs: the posterior's σ as log ratios to the metadata's
#: (clipped PN, DCSN, RN, total; unclipped total), its four probabilities, log(1 + details used)/10 and its texture check.
_TRUST_INPUTS: tuple[str, ...] = (
    *(f"log_ratio:{n}" for n in MISMATCH_POSTERIOR[:5]), *MISMATCH_POSTERIOR[5:9], "log1p_posterior_details",
    "posterior_texture",
)
# Offset [DN] of the trust head's log ratio: full trust (λ = 1) gives the posterior's σ (relative error ≤ 1e-6 DN / σ_clipped(M)).
_TRUST_EPS_DN = 1e-6

#: Starting points of the hybrid's log-correction: ``"image"`` — the closed-form σ per source rescaled by the
#: ratio r of a robust classical noise estimate of the patch to the closed-form total (the default);
#: ``"metadata"`` — the closed-form σ itself (r is still an input of every branch).
PRIOR_ANCHORS: tuple[str, ...] = ("image", "metadata")

#: What the source branches read besides the shared features: ``"own"`` — the metadata that drive their source
#: (:data:`BRANCH_FIELDS`) and their own closed-form σ (the default, as the thesis's FCBs); ``"all"`` — every
#: available metadata field and the closed-form σ of all sources and the total, so the DCSN branch can weigh
#: an excess of signal-independent noise against what a readout-noise change would explain, and vice versa.
BRANCH_INPUTS: tuple[str, ...] = ("own", "all")


#: Activations of the trunk: ``"relu"`` (the shipped files written before the option) or ``"leaky_relu"``
#: (slope 0.05 below zero: a unit that is off for every input still gets a gradient, so the trunk cannot die).
TRUNK_ACTIVATIONS: tuple[str, ...] = ("relu", "leaky_relu")


class NoiseTrunk(nn.Module):
    """Shared image trunk: B×1×P×P in [0, 1] → (B, 12·width) pooled features (P divisible by 8)."""

    def __init__(self, width: int = 32, highpass_gain: float = 32.0, activation: str = "relu") -> None:
        super().__init__()
        if activation not in TRUNK_ACTIVATIONS:
            raise ValueError(f"trunk_activation = {activation!r} must be one of {list(TRUNK_ACTIVATIONS)}")
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
        if activation == "leaky_relu":  # same parameters, so weights files stay interchangeable
            for module in list(self.modules()):
                for name, child in module.named_children():
                    if isinstance(child, nn.ReLU):
                        setattr(module, name, nn.LeakyReLU(0.05, inplace=True))

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        local_mean = box_mean3(image)
        x = torch.cat([image * 2.0 - 1.0, (image - local_mean) * self.highpass_gain], dim=1)
        return self.pool(self.stages(self.stem(self.unshuffle(x))))


class NoiseSourceNet(nn.Module):
    """Trunk + four branches (+ the total head). ``forward(image, meta, prior) -> (B, 4)`` σ̂ of (PN, DCSN, RN)
    and ξ̂ in DN, or ``(B, 5)`` with σ̂_total last when ``total_branch``.

    Args of forward:
        image: B×1×P×P in [0, 1].
        meta: (B, 11) metadata normalised to [0, 1] (``CameraMetadata.normalize("full")``); only the
            columns of the configured ``metadata_set`` are read.
        prior: (B, 4) closed-form σ (PN, DCSN, RN, total) in DN; read only with ``physics_prior``.
    """

    def __init__(
        self, metadata_set: str = "full", physics_prior: bool = True, width: int = 32, hidden: Sequence[int] = (64, 32, 16),
        prior_anchor: str = "image", total_branch: bool = True, branch_inputs: str = "own", nlf_statistics: bool = False,
        trunk_activation: str = "relu", prior_clipping: bool = False, noise_fit_statistics: bool = False,
        mismatch_posterior: bool = False,
    ) -> None:
        super().__init__()
        if mismatch_posterior and not prior_clipping:
            raise ValueError("mismatch_posterior needs prior_clipping: true (the posterior's clipped σ is read against the clipped prior)")
        self.mismatch_posterior = bool(mismatch_posterior)
        if prior_clipping and not physics_prior:
            raise ValueError("prior_clipping needs physics_prior: true (it is the clipped closed-form σ the hybrid starts from)")
        if noise_fit_statistics and not physics_prior:
            raise ValueError("noise_fit_statistics needs physics_prior: true (the fits are conditioned on the metadata's noise model)")
        self.prior_clipping = bool(prior_clipping)
        self.noise_fit_statistics = bool(noise_fit_statistics)
        if branch_inputs not in BRANCH_INPUTS:
            raise ValueError(f"branch_inputs = {branch_inputs!r} must be one of {list(BRANCH_INPUTS)}")
        self.branch_inputs = branch_inputs
        self.nlf_statistics = bool(nlf_statistics)
        if prior_anchor not in PRIOR_ANCHORS:
            raise ValueError(f"prior_anchor = {prior_anchor!r} must be one of {list(PRIOR_ANCHORS)}")
        self.prior_anchor = prior_anchor
        if metadata_set not in METADATA_SETS:
            raise ValueError(f"metadata_set = {metadata_set!r} must be one of {list(METADATA_SETS)}")
        if physics_prior and metadata_set != "full":
            raise ValueError(
                f"physics_prior needs metadata_set 'full' (the closed-form σ_DCSN and σ_RN need all 11 fields), "
                f"got {metadata_set!r}"
            )
        self.metadata_set = metadata_set
        self.physics_prior = bool(physics_prior)
        self.trunk = NoiseTrunk(width, activation=trunk_activation)
        available = set(METADATA_SETS[metadata_set])
        fields = FULL_FIELDS if branch_inputs == "all" else None
        self.branch_columns: list[list[int]] = [
            [FULL_FIELDS.index(f) for f in (fields or BRANCH_FIELDS[name]) if f in available] for name in OUTPUTS
        ]
        #: closed-form σ (columns of ``prior``: PN, DCSN, RN, total) each branch reads, as log σ
        self.prior_columns: list[list[int]] = [
            ([0, 1, 2, 3] if branch_inputs == "all" else [i]) if self.physics_prior else [] for i in range(len(OUTPUTS))
        ]
        n_base = len(self._base_names())
        self.branches = nn.ModuleList(
            FullyConnectedBlock(n_base + len(cols) + len(pcols), tuple(hidden), 1)
            for cols, pcols in zip(self.branch_columns, self.prior_columns)
        )
        if self.physics_prior:  # start from the noise model exactly: δ = 0
            for branch in self.branches:
                nn.init.zeros_(branch[-1].weight)
                nn.init.zeros_(branch[-1].bias)
        self.total_branch = bool(total_branch)
        if self.total_branch:  # reads every available metadata field and log √(Σ σ̂_s²); starts at Eq. 4.2 exactly
            self.total_columns = [FULL_FIELDS.index(f) for f in FULL_FIELDS if f in available]
            self.total_head = FullyConnectedBlock(n_base + len(self.total_columns) + 1, tuple(hidden), 1)
            nn.init.zeros_(self.total_head[-1].weight)
            nn.init.zeros_(self.total_head[-1].bias)
        if self.mismatch_posterior:  # how far each output follows the posterior: λ = sigmoid(·), starts at 0.05
            self.trust_head = FullyConnectedBlock(n_base + len(_TRUST_INPUTS), tuple(hidden), len(OUTPUTS))
            nn.init.zeros_(self.trust_head[-1].weight)
            nn.init.constant_(self.trust_head[-1].bias, _TRUST_START)

    def _base_names(self) -> list[str]:
        names = [f"trunk{i}" for i in range(self.trunk.out_features)]
        names += [*IMAGE_STATISTICS, "log_haar_mad"] + (["log_ratio_to_model"] if self.physics_prior else [])
        names += list(NLF_STATISTICS) if self.nlf_statistics else []
        return names + (list(NOISE_FIT_STATISTICS) if self.noise_fit_statistics else [])

    @property
    def prior_width(self) -> int:
        """Columns of the ``prior`` input: the closed-form σ (4), after clipping (4 with ``prior_clipping``), the
        noise fits (6 with ``noise_fit_statistics``, :data:`~camhealth.estimators.noise_features.NOISE_FIT_STATISTICS`),
        the mismatch posterior (11 with ``mismatch_posterior``, :data:`~camhealth.estimators.mismatch_posterior.MISMATCH_POSTERIOR`)."""
        return (4 + 4 * self.prior_clipping + len(NOISE_FIT_STATISTICS) * self.noise_fit_statistics
                + len(MISMATCH_POSTERIOR) * self.mismatch_posterior)

    def input_names(self) -> dict[str, list[str]]:
        """Names of the input columns of the first layer of every branch (and of the total head), by the
        prefix of its weight in the state dict. Used to carry weights between input layouts."""
        base = self._base_names()
        out = {
            f"branches.{i}.0": base + [f"meta:{FULL_FIELDS[c]}" for c in cols] + [f"log_prior:{k}" for k in pcols]
            for i, (cols, pcols) in enumerate(zip(self.branch_columns, self.prior_columns))
        }
        if self.total_branch:
            out["total_head.0"] = base + [f"meta:{FULL_FIELDS[c]}" for c in self.total_columns] + ["log_quadrature_sum"]
        if self.mismatch_posterior:
            out["trust_head.0"] = base + list(_TRUST_INPUTS)
        return out

    def state_from(self, source: "NoiseSourceNet") -> dict[str, torch.Tensor]:
        """``source``'s weights laid out for this network, so that it starts as ``source`` exactly.

        The networks may differ in what their branches read (``branch_inputs``, ``nlf_statistics``) and in the
        total head: an input this network has and ``source`` lacks gets a zero weight column (it does not move
        the output until training moves it); a total head ``source`` lacks keeps its zero-initialised output
        (σ̂_total = √(Σ σ̂_s²), which is what ``source`` returns). Raises ``ValueError`` if ``source`` reads an
        input this network does not, or if anything else differs (trunk width, hidden sizes, prior, metadata)."""
        state = dict(source.state_dict())
        mine = self.state_dict()
        if self.total_branch and not source.total_branch:
            state.update({k: v for k, v in mine.items() if k.startswith("total_head.")})
        if self.mismatch_posterior and not getattr(source, "mismatch_posterior", False):  # λ starts at 0.05
            state.update({k: v for k, v in mine.items() if k.startswith("trust_head.")})
        old_names, new_names = source.input_names(), self.input_names()
        for prefix, names in new_names.items():
            key = f"{prefix}.weight"
            if prefix not in old_names or key not in state:
                continue
            old = old_names[prefix]
            if old == names:
                continue
            dropped = sorted(set(old) - set(names))
            if dropped:
                raise ValueError(f"{prefix} of the source reads inputs this network does not: {dropped[:4]}")
            w_old = state[key]
            w_new = torch.zeros(w_old.shape[0], len(names), dtype=w_old.dtype)
            where = {n: j for j, n in enumerate(old)}
            for j, n in enumerate(names):
                if n in where:
                    w_new[:, j] = w_old[:, where[n]]
            state[key] = w_new
        return state

    @torch.no_grad()
    def trunk_activity(self, patch_size: int = 64, batch: int = 16, seed: int = 0) -> float:
        """Fraction of the trunk's pooled features that vary over a probe batch (random ramps, flats and edges
        with 0–20 DN of noise). 0 means the trunk is dead: every ReLU of its last stage is off for every input,
        the pooled features are constants and the branches see the image only through the scalar statistics."""
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

    @torch.no_grad()
    def revive_trunk(self, seed: int = 0) -> None:
        """Re-initialise a dead trunk (:meth:`trunk_activity` 0) without changing the network's function.

        A trunk without normalisation can die in long training (dying ReLUs): its pooled features become
        constants. Their contribution to every branch (and the total head) is folded into the first layer's bias,
        the weights on the trunk's columns are set to zero, and the trunk gets a fresh initialisation (seeded):
        the outputs are unchanged, and fine-tuning can learn to use the image again. Raises ``ValueError`` when
        the trunk is alive (re-initialising it would change the function)."""
        activity = self.trunk_activity()
        if activity > 0:
            raise ValueError(f"the trunk is alive ({activity:.0%} of its pooled features vary); nothing to revive")
        weight = next(self.trunk.parameters())
        probe = torch.full((1, 1, 64, 64), 0.5, device=weight.device, dtype=weight.dtype)
        const = self.trunk(probe).float()[0]  # the same for every input
        n = self.trunk.out_features
        heads = list(self.branches) + ([self.total_head] if self.total_branch else [])
        for head in heads:
            first = head[0]
            first.bias += first.weight[:, :n] @ const.to(first.weight.dtype)
            first.weight[:, :n] = 0.0
        state = torch.random.get_rng_state()
        torch.manual_seed(seed)
        for mod in self.trunk.modules():
            if isinstance(mod, nn.Conv2d):
                mod.reset_parameters()
        torch.random.set_rng_state(state)

    def forward(self, image: torch.Tensor, meta: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
        feats = self.trunk(image).float()
        stats = image_statistics(image)
        log_mad = torch.log(stats[:, 5:6] + 0.1)
        scalars = [stats[:, :4], stats[:, 4:6] / 10.0, log_mad]
        ratio = log_mad - torch.log(prior[:, 3:4].float() + 0.1)
        if self.physics_prior:  # how much noisier the image looks than the metadata say (robust estimate)
            scalars.append(ratio)
        if self.nlf_statistics:  # the noise level in three intensity terciles
            scalars.append(nlf_statistics(image))
        if self.noise_fit_statistics:  # the metadata-conditioned noise fits, computed with the prior
            lo = 8 if self.prior_clipping else 4
            scalars.append(prior[:, lo:lo + len(NOISE_FIT_STATISTICS)].float())
        base = torch.cat([feats, *scalars], dim=1)
        raw = []
        for branch, cols, pcols in zip(self.branches, self.branch_columns, self.prior_columns):
            parts = [base]
            if cols:
                parts.append(meta[:, cols].float())
            if pcols:  # "own": PN, DCSN, RN see their own closed-form σ and ξ the total; "all": every one
                parts.append(torch.log(prior[:, pcols].float() + 0.01))
            raw.append(branch(torch.cat(parts, dim=1)).float())
        raw_t = torch.cat(raw, dim=1)
        if self.physics_prior:
            # Start from the noise model — rescaled to the robust image estimate (anchor "image") or as the
            # metadata give it (anchor "metadata") — and learn the rest.
            start = ratio if self.prior_anchor == "image" else torch.zeros_like(ratio)
            delta = start + _MAX_LOG_CORRECTION * torch.tanh(raw_t / _MAX_LOG_CORRECTION)
            if self.mismatch_posterior:  # blend with the posterior by the learned trust λ ∈ (0, 1), 0 where it abstains
                post = prior[:, -len(MISMATCH_POSTERIOR):].float()
                anchor = torch.cat([prior[:, 4:8], prior[:, 3:4]], dim=1).float()
                log_post = torch.log((post[:, :5] + 0.1) / (anchor + 0.1))  # inputs of the trust head
                evidence = (post[:, 9:10] >= _MIN_FIT_BLOCKS).float()  # the posterior's own no-evidence threshold
                trust_in = torch.cat([base, log_post, post[:, 5:9], torch.log1p(post[:, 9:10]) / 10.0, post[:, 10:11]], dim=1)
                trust = torch.sigmoid(self.trust_head(trust_in).float()) * evidence
                target = torch.log((torch.cat([post[:, :3], post[:, 4:5]], dim=1) + _TRUST_EPS_DN)
                                   / (torch.cat([anchor[:, :3], anchor[:, 4:5]], dim=1) + _TRUST_EPS_DN))
                delta = delta + trust * (target - delta)
            delta = delta.clamp(-8.0, 8.0)
            # with prior_clipping the sources start from their σ after clipping (columns 4–6); ξ keeps the
            # unclipped model total, as its label does (Eq. 4.3)
            sigma = (prior[:, 4:7] if self.prior_clipping else prior[:, :3]).float() * torch.exp(delta[:, :3])
            total = prior[:, 3:4].float()
            xi = total - total * torch.exp(delta[:, 3:4])
        else:
            sigma = 5.0 * F.softplus(raw_t[:, :3])
            xi = 10.0 * raw_t[:, 3:4]
        if not self.total_branch:
            return torch.cat([sigma, xi], dim=1)
        quad = sigma.pow(2).sum(1, keepdim=True).add(1e-12).sqrt()
        parts = [base, torch.log(quad + 0.1)]
        if self.total_columns:
            parts.insert(1, meta[:, self.total_columns].float())
        delta_t = _MAX_LOG_CORRECTION * torch.tanh(self.total_head(torch.cat(parts, dim=1)).float() / _MAX_LOG_CORRECTION)
        if self.prior_clipping:  # start from the clipped model total, moved as the sources are: the clipped
            # sources' noise is correlated, so their quadrature sum overstates the total (module docstring)
            clipped = prior[:, 4:8].float()
            quad = quad * (clipped[:, 3:4] + 1e-6) / (clipped[:, :3].pow(2).sum(1, keepdim=True).add(1e-12).sqrt() + 1e-6)
        return torch.cat([sigma, xi, quad * torch.exp(delta_t)], dim=1)


class NoiseSourceEstimator(EstimatorModule):
    """LightningModule of the noise-source estimator (w/o-, Min- or Full-Meta, hybrid or pure).

    Args:
        patch_size: side [px] of the training patches (thesis: 128); the estimator's input size.
        metadata_set: metadata the network reads: ``none`` (w/o-Meta), ``minimal`` (gain, exposure,
            temperature) or ``full`` (all 11 fields of thesis Table 4.1).
        physics_prior: hybrid network that starts from the closed-form σ per source (Full-Meta only).
        width: channels of the first trunk stage (the others use 2× and 4×).
        hidden: neurons of the hidden layers of each branch (thesis: 32, 16, 8).
        loss_weights: weights of the smooth-L1 terms ``pn``, ``dcsn``, ``rn``, ``total``, ``xi``.
        huber_beta_dn: smooth-L1 transition [DN].
        lr, weight_decay, channels_last, log_figures, max_figure_samples: see :class:`EstimatorModule`.
        prior_anchor: starting point of the hybrid's correction (:data:`PRIOR_ANCHORS`): ``"image"`` (default,
            the shipped ``noise_source_full``) starts from the closed-form σ rescaled to the patch's robust noise estimate;
            ``"metadata"`` starts from the closed-form σ itself, so texture that the robust estimate mistakes
            for noise does not move the start (the shipped ``noise_source_full_meta``; docs/estimators.md).
        total_branch: learn the realised total after clipping with a fifth, zero-initialised branch instead of
            taking √(Σ σ̂_s²) (module docstring; default ``True``; weights files without the key load as ``False``).
        branch_inputs: what the source branches read (:data:`BRANCH_INPUTS`): ``"own"`` (default) their
            source's metadata and closed-form σ, ``"all"`` every metadata field and every closed-form σ.
        nlf_statistics: also feed every branch the three-point noise-level function of the patch
            (:func:`~camhealth.estimators.noise_features.nlf_statistics`; default ``False``).
        trunk_activation: ``"relu"`` (default) or ``"leaky_relu"`` (:data:`TRUNK_ACTIVATIONS`; a trunk without
            normalisation can die with ReLU — :meth:`NoiseSourceNet.trunk_activity`).
        prior_clipping: start the source branches (and the total head) from the closed-form σ *after clipping*
            to [0, 255] DN (:func:`~camhealth.estimators.noise_features.clipped_prior_dn`) instead of before it, so the
            network no longer has to learn what saturation does to each source (default ``False``; needs
            ``physics_prior``). The prior input is then (B, 8).
        noise_fit_statistics: also feed every branch how far the image's noise is from the metadata's, by two
            one-parameter fits of its noise-level function on flat, unclipped blocks, their likelihood ratio and the
            σ_DCSN or σ_RN that would take up the change alone
            (:func:`~camhealth.estimators.noise_features.noise_fit_statistics`; default ``False``; needs
            ``physics_prior``; six more prior columns).
        mismatch_posterior: also compute, outside the network, the Bayesian posterior over single-field metadata
            mismatches (:func:`~camhealth.estimators.mismatch_posterior.mismatch_posterior`: gain, temperature or
            white noise redrawn, each candidate's σ from the physics, weighed by the likelihood of the patch's
            flat-block Haar details), and let a trust head (reading the branches' inputs and the posterior's σ,
            probabilities and evidence) blend each output with it: log σ̂ = log σ̂_own + λ·(log σ_post − log σ̂_own),
            λ = sigmoid(·) per patch and output, 0.05 at the start, 0 where the posterior abstains; λ = 1 is the
            posterior's σ. Default ``False``; needs ``prior_clipping``; eleven more prior columns.
        train_only: optimise only the parts of the network whose parameter names start with these prefixes (e.g.
            ``[trust_head]`` to fit the trust head of a network carried in by ``--init_from`` while its branches keep
            their function); default ``None``, everything.
    """

    kind = "noise_source"
    metric_names: tuple[str, ...] = ("pn", "dcsn", "rn", "total", "xi")

    def __init__(
        self,
        patch_size: int = 128,
        metadata_set: str = "full",
        physics_prior: bool = True,
        width: int = 32,
        hidden: Sequence[int] = (64, 32, 16),
        loss_weights: Mapping[str, float] | None = None,
        huber_beta_dn: float = 0.5,
        lr: float = 2e-3,
        weight_decay: float = 1e-4,
        channels_last: bool = True,
        log_figures: bool = True,
        max_figure_samples: int = 512,
        prior_anchor: str = "image",
        total_branch: bool = True,
        branch_inputs: str = "own",
        nlf_statistics: bool = False,
        trunk_activation: str = "relu",
        prior_clipping: bool = False,
        noise_fit_statistics: bool = False,
        mismatch_posterior: bool = False,
        train_only: Sequence[str] | None = None,
    ) -> None:
        super().__init__(lr, weight_decay, channels_last, log_figures, max_figure_samples)
        self.save_hyperparameters()
        self._set_patch_size(patch_size)
        self.metadata_set = metadata_set
        self.physics_prior = bool(physics_prior)
        self.net = NoiseSourceNet(
            metadata_set, physics_prior, width, tuple(hidden), prior_anchor, total_branch, branch_inputs, nlf_statistics,
            trunk_activation, prior_clipping, noise_fit_statistics, mismatch_posterior,
        )
        self.prior_clipping = self.net.prior_clipping
        self.noise_fit_statistics = self.net.noise_fit_statistics
        self.mismatch_posterior = self.net.mismatch_posterior
        freeze_all_but(self.net, train_only)  # optimise only these parts of the network; freeze the rest
        weights = {"pn": 1.0, "dcsn": 1.0, "rn": 1.0, "total": 1.0, "xi": 1.0, **(loss_weights or {})}
        unknown = set(weights) - set(self.metric_names)
        if unknown:
            raise ValueError(f"loss_weights has unknown key(s) {sorted(unknown)}; allowed {list(self.metric_names)}")
        self.loss_weights = weights
        self.huber_beta_dn = float(huber_beta_dn)
        self.val_stats = NoiseErrorStats(self.metric_names)
        self.test_stats = NoiseErrorStats(self.metric_names)

    # ------------------------------------------------------------------ inference
    def network_inputs(self, image: torch.Tensor, meta_raw: torch.Tensor | None) -> tuple[torch.Tensor, ...]:
        """(image, normalised metadata (B, 11), closed-form prior (B, 4)) for :class:`NoiseSourceNet`."""
        b = image.shape[0]
        if self.metadata_set == "none":
            return image, image.new_zeros(b, len(FULL_FIELDS)), image.new_zeros(b, 4)
        if meta_raw is None:
            raise ValueError(f"this estimator reads {self.metadata_set!r} metadata; pass metadata")
        meta = metadata_from_matrix(meta_raw.to(image.device))
        norm = meta.normalize("full").to(image.dtype)
        prior = (
            physics_prior_dn(image, meta, clipping=self.prior_clipping, noise_fit=self.noise_fit_statistics,
                             posterior=self.mismatch_posterior)
            if self.physics_prior else image.new_zeros(b, 4)
        )
        return image, norm, prior

    def forward(self, image: torch.Tensor, meta_raw: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """σ̂ per source, total and ξ̂ in DN for B×1×P×P patches in [0, 1] and (B, 11) raw metadata."""
        img, norm, prior = self.network_inputs(image, meta_raw)
        out = self.net(self._prepare(img), norm, prior)
        sigma = out[:, :3]
        return {
            "sigma": sigma,
            "sigma_total": out[:, 4] if out.shape[1] > 4 else sigma.pow(2).sum(1).add(1e-12).sqrt(),
            "xi": out[:, 3],
            "prior": prior,
        }

    def export_inputs(self, batch_size: int = 2) -> tuple[torch.Tensor, ...]:
        g = torch.Generator().manual_seed(0)
        image = torch.rand(batch_size, 1, self.patch_size, self.patch_size, generator=g)
        width = self.net.prior_width
        return image, torch.rand(batch_size, len(FULL_FIELDS), generator=g), torch.rand(batch_size, width, generator=g) * 5

    # ------------------------------------------------------------------ training
    def _estimates_and_truth(self, batch: Mapping[str, Any]) -> tuple[torch.Tensor, torch.Tensor, dict]:
        out = self(batch["image"], batch.get("meta_raw"))
        est = torch.cat([out["sigma"], out["sigma_total"][:, None], out["xi"][:, None]], dim=1)
        truth = torch.cat([batch["sigma"], batch["sigma_total"][:, None], batch["xi"][:, None]], dim=1).to(est)
        return est, truth, out

    def _loss(self, est: torch.Tensor, truth: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        per = F.smooth_l1_loss(est, truth, beta=self.huber_beta_dn, reduction="none").mean(0)
        terms = {n: per[i] for i, n in enumerate(self.metric_names)}
        loss = sum(self.loss_weights[n] * terms[n] for n in self.metric_names) / sum(self.loss_weights.values())
        return loss, terms

    def training_step(self, batch: Mapping[str, Any], batch_idx: int) -> torch.Tensor:
        est, truth, _ = self._estimates_and_truth(batch)
        loss, terms = self._loss(est, truth)
        self.log("train/loss", loss, prog_bar=True, batch_size=est.shape[0])
        self.log_dict({f"train/loss_{k}": v for k, v in terms.items()}, batch_size=est.shape[0])
        return loss

    def validation_step(self, batch: Mapping[str, Any], batch_idx: int) -> None:
        est, truth, _ = self._estimates_and_truth(batch)
        loss, _ = self._loss(est, truth)
        self.log("val/loss", loss, prog_bar=True, batch_size=est.shape[0])
        self.val_stats.update(est, truth)
        if batch_idx == 0:
            self._cache_for_figures(images=batch["image"][:8], est_first=est[:8], truth_first=truth[:8])
        self._cache_for_figures(est=est, truth=truth)

    def on_validation_epoch_end(self) -> None:
        stats = self.val_stats.compute()
        self.log_dict({f"val/{k}": v for k, v in stats.items() if k != "rms_total"})
        self.log("val/rms_total", stats["rms_total"], prog_bar=True)
        self.val_stats.reset()
        self._log_figures("val")

    def test_step(self, batch: Mapping[str, Any], batch_idx: int) -> None:
        est, truth, _ = self._estimates_and_truth(batch)
        self.test_stats.update(est, truth)

    def on_test_epoch_end(self) -> None:
        self.log_dict({f"test/{k}": v for k, v in self.test_stats.compute().items()})
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
