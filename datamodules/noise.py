"""``NoiseDataModule``: clean patches corrupted on the fly with the physical sensor-noise model.

Batches after :meth:`NoiseDataModule.on_after_batch_transfer` (all on the batch's device, B patches):

========================  ==========  ===================================================================
key                       shape       meaning
========================  ==========  ===================================================================
``image``                 B×1×P×P     noisy patch in [0, 1] (corrupted with the *image* metadata M')
``clean``                 B×1×P×P     the clean patch (after flips/rot90/brightness)
``meta_raw``              (B, 11)     metadata M given to the network, physical units, ``FULL_FIELDS`` order
``meta``                  (B, k)      M normalised to [0, 1] for ``metadata_set`` (k = 0, 3 or 11)
``meta_image_raw``        (B, 11)     metadata M' the image was actually corrupted with (= M unless altered)
``sigma``                 (B, 3)      realised σ of (PN, DCSN, RN) in the image [DN], after gain + clipping
                                      (before the rounding of ``quantize: true``, see below)
``sigma_total``           (B,)        realised σ of all noise in ``image`` [DN]: std(image − noise-free image),
                                      after clipping and, with ``quantize: true``, rounding to whole DN
``sigma_expected``        (B, 3)      analytic σ of (PN, DCSN, RN) under M' [DN] (before clipping)
``xi``                    (B,)        residual noise ξ = σ_Model(M) − σ_Image(M') [DN]
``xi_norm``               (B,)        ξ / 255 ∈ [−1, 1]
``altered``               (B,) bool   True where M' ≠ M (one of ``xi_fields`` resampled)
``index``, ``image_id``, ``stage``    patch index in its dataset, source image id, split
========================  ==========  ===================================================================

**Which metadata the labels refer to.** ``sigma``, ``sigma_total`` and ``sigma_expected`` describe the noise
that is really in the image, i.e. they refer to the image metadata M'. ``meta``/``meta_raw`` is what the
network is told (M). Where ``altered`` is False, M' = M.

**Rounding (``quantize: true``).** The image is rounded to whole DN after clipping. ``sigma_total`` is then
measured on the rounded image, std(``image`` − noise-free image), so it is the σ of the noise really in
``image``. The per-source ``sigma`` are measured before rounding: rounding adds an error of its own, which no
source owns. For noise of a few DN or more this error is about uniform, 1/12 DN² of variance; for noise well
below 1 DN on a clean patch already on the 8-bit grid, rounding mostly snaps a pixel back to its clean value and
*removes* noise. So with ``quantize: true`` the per-source ``sigma`` do not add up to ``sigma_total``. With
``quantize: false`` (the default, and what every shipped noise model was trained on) ``sigma`` and ``sigma_total``
describe the same noise, and ``sigma_total`` is std(``image`` − noise-free image) as well. ``sigma_expected`` and
ξ are analytic and never include the rounding.

**ξ (conventions.md Eq. 4.3, thesis Eq. 4.3).** With probability ``xi_probability`` a sample is corrupted
with altered metadata M' = M with ONE field of ``xi_fields`` (default gain, temperature, white noise)
redrawn uniformly from its sampling range, while the network is given M. Then

    ξ = σ_Model(M) − σ_Image(M'),   σ(M) = √(σ_PN(M)² + σ_DCSN(M)² + σ_RN(M)²)

where both totals are the *analytic* noise model for this clean patch (σ_PN from the patch's mean
intensity; the same expressions as ``form_image``'s ``sigma_expected_dn``, evaluated in one call for M and
M'), exactly as the thesis writes Eq. 4.3. ξ is therefore exactly 0 when M = M', and ξ < 0 when the image
is noisier than the metadata say (e.g. the real gain is higher than reported). Realised σ (``sigma``) would
differ from the analytic one by sampling noise and clipping even for M = M', which is why ξ uses the
analytic model on both sides. The default ``xi_probability`` 0.5 is our choice (the thesis does not state
its fraction): half the samples teach the residual, half the consistent model.

Metadata sampling: every field of thesis Table 4.1 uniformly (gain uniform in the linear factor), or a
sensor preset (``sensor: ICX285`` / ``EV76C661``) with the operating point (gain, exposure, temperature)
sampled; ``metadata_ranges`` narrows/overrides any field's range (fields named there are always sampled).
"""

from __future__ import annotations

import numbers
from typing import Any, Mapping, Sequence

import torch

from camhealth.augment._base import check_sources
from camhealth.physics.dark_current import dark_current_shot_sigma_e
from camhealth.physics.image_formation import NOISE_SOURCES, form_image
from camhealth.physics.metadata import FULL_FIELDS, METADATA_RANGES, METADATA_SETS, MINIMAL_FIELDS, CameraMetadata
from camhealth.physics.photon_shot_noise import photon_shot_sigma_patch_dn
from camhealth.physics.readout_noise import readout_sigma_e, source_follower_sigma_e

from datamodules.patches import PatchDataModule, _check_number, check_flag

__all__ = ["NoiseDataModule", "check_metadata_ranges", "expected_sigma_dn", "metadata_matrix", "realised_sigma_dn",
           "XI_FIELDS"]

#: Fields that may be altered for ξ (any metadata field is allowed; these are the defaults).
XI_FIELDS: tuple[str, ...] = ("gain_db", "temperature_c", "white_noise_v_per_rthz")


def check_metadata_ranges(metadata_ranges: Any) -> dict[str, tuple[float, float]]:
    """``metadata_ranges`` (``None`` or field → ``[low, high]``) as ``{field: (low, high)}`` floats; an entry that is
    not a pair of numbers is a ``ValueError`` naming its field (which fields exist and which ranges they allow is
    :meth:`CameraMetadata.sample`'s check)."""
    if metadata_ranges is None:
        return {}
    if not isinstance(metadata_ranges, Mapping):
        raise ValueError(f"metadata_ranges = {metadata_ranges!r} must be a mapping of field to [low, high], "
                         "e.g. {gain_db: [0, 12]}")
    out = {}
    for k, v in metadata_ranges.items():
        pair = list(v) if isinstance(v, (list, tuple)) else None
        if pair is None or len(pair) != 2 or any(isinstance(x, bool) or not isinstance(x, numbers.Real) for x in pair):
            raise ValueError(f"metadata_ranges[{k!r}] = {v!r} must be a [low, high] pair of numbers")
        out[k] = (float(pair[0]), float(pair[1]))
    return out


def realised_sigma_dn(image: torch.Tensor, noise_free: torch.Tensor) -> torch.Tensor:
    """Realised σ [DN] of the noise in ``image``: the per-sample (unbiased) standard deviation of
    ``image − noise_free`` over all pixels, in float64, shape (B,)."""
    d = image.detach().double() - noise_free.detach().double()
    return d.flatten(1).std(1) * 255.0


def metadata_matrix(meta: CameraMetadata) -> torch.Tensor:
    """(B, 11) raw metadata in ``FULL_FIELDS`` order and physical units (``is_cmos`` as 0/1)."""
    return torch.stack([getattr(meta, n) for n in FULL_FIELDS], dim=1)


def expected_sigma_dn(
    clean: torch.Tensor,
    meta: CameraMetadata,
    sources: Sequence[str] = NOISE_SOURCES,
    source_follower_e: torch.Tensor | None = None,
) -> torch.Tensor:
    """Analytic σ (PN, DCSN, RN) [DN] before clipping of clean patches under ``meta``, shape (B, 3).

    The same expressions as ``form_image``'s ``sigma_expected_dn`` for a noise-only corruption (no blur):
    PN from the patch mean intensity, DCSN = √(DC·t_exp), RN from Eq. 3.17; sources not in ``sources`` are 0.
    ``source_follower_e`` optionally passes a precomputed ``source_follower_sigma_e(meta)``.
    """
    b = clean.shape[0]
    wd = torch.float64 if clean.dtype == torch.float64 else torch.float32
    x = clean.to(wd)
    meta = meta.expand(b).to(device=clean.device)
    zeros = torch.zeros(b, device=clean.device, dtype=wd)
    dn = meta.dn_per_electron.to(wd)
    pn = photon_shot_sigma_patch_dn(x, meta).to(wd) if "photon" in sources else zeros
    dc = dark_current_shot_sigma_e(meta).to(wd) * dn if "dark" in sources else zeros
    rn = readout_sigma_e(meta, source_follower_e).to(wd) * dn if "readout" in sources else zeros
    return torch.stack([pn, dc, rn], dim=1)


class NoiseDataModule(PatchDataModule):
    """Noisy patches with metadata, per-source σ labels and the residual ξ, corrupted on the device.

    Data options (shared with :class:`~datamodules.BlurDataModule`):
        source: image source spec for :func:`camhealth.data.build_source`: ``"default"`` (embedded photos +
            street frames, offline), ``"street"``, ``"skimage"``, ``"deadleaves"``, a folder or a video.
        source_kwargs: extra arguments of the source (e.g. ``{deadleaves: 100}`` for ``default``).
        patch_size: patch side [px] (default 128, thesis 4.3.3).
        batch_size: patches per batch.
        num_workers: DataLoader workers (default 0: on a 2-core machine the main process is fastest,
            the corruption runs in the main process anyway).
        patches_per_image: training patches per image and epoch (epoch length = train images × this).
        val_patches_per_image: fixed validation/test crops per image.
        val_fraction, test_fraction, seed: leak-free split by source image/clip
            (:func:`camhealth.data.split_ids`); ``seed`` also fixes the val/test crops and corruption.
        group_by: split groups: ``"id"`` (frames ``clip#000123`` of one clip together, else per image) or
            ``"folder"`` (all images of one sub-folder together).
        flips, rot90, brightness_dn: training augmentation (random flips, rot90, ±brightness_dn DN).
        min_std_dn, max_clipped_fraction, keep_hard_patches, max_tries: rejection of near-uniform
            (std < min_std_dn DN) and clipped (> max_clipped_fraction of pixels at 0/255 DN) patches;
            ``keep_hard_patches: true`` keeps them (robustness tests).
        pin_memory: pin host memory of the clean batches (for GPU training).
        train_rng: random numbers of the training batches' noise fields, ``"torch"`` (default) or ``"counter"``
            (compiled counter-based draws: same physics, faster on CPU; val/test batches always use torch's).

    Noise options:
        metadata_set: which normalised metadata the network gets in ``meta``: ``"none"``, ``"minimal"``
            (gain, exposure, temperature) or ``"full"`` (all 11).
        sensor: ``None`` (sample every Table 4.1 field), a preset (``"ICX285"``, ``"EV76C661"``) or a metadata
            file (``camera.yaml`` from ``python -m camhealth.calibrate``) whose sensor fields stay fixed while gain,
            exposure and temperature are sampled.
        metadata_ranges: per-field ``[low, high]`` sampling ranges (inside Table 4.1), e.g.
            ``{gain_db: [0, 12]}``; each entry must be a pair of numbers.
        gain_uniform_in: sample the gain uniformly in the linear ``"factor"`` (thesis) or in ``"db"``.
        noise_sources: which sources to realise, subset of ``["photon", "dark", "readout"]``.
        quantize: round the noisy image to whole DN (a bool). ``sigma_total`` is then the σ of the noise in the
            rounded image; the per-source ``sigma`` stay the σ before rounding (rounding's own error, ≈ 1/12 DN²
            for noise of a few DN, belongs to no source; see the module docstring).
        xi_probability: probability that a sample's image is corrupted with altered metadata M'.
        xi_fields: fields of which one (chosen uniformly) is redrawn for M'.

    See the module docstring for the batch keys and the exact ξ definition.
    """

    default_patch_size = 128

    def __init__(
        self,
        source: str = "default",
        source_kwargs: dict[str, Any] | None = None,
        patch_size: int = 128,
        batch_size: int = 32,
        num_workers: int = 0,
        patches_per_image: int = 64,
        val_patches_per_image: int = 8,
        val_fraction: float = 0.15,
        test_fraction: float = 0.15,
        seed: int = 0,
        group_by: str = "id",
        flips: bool = True,
        rot90: bool = True,
        brightness_dn: float = 20.0,
        min_std_dn: float = 2.0,
        max_clipped_fraction: float = 0.05,
        keep_hard_patches: bool = False,
        max_tries: int = 20,
        pin_memory: bool = False,
        train_rng: str = "torch",
        metadata_set: str = "full",
        sensor: str | None = None,
        metadata_ranges: dict[str, tuple[float, float]] | None = None,
        gain_uniform_in: str = "factor",
        noise_sources: Sequence[str] = NOISE_SOURCES,
        quantize: bool = False,
        xi_probability: float = 0.5,
        xi_fields: Sequence[str] = XI_FIELDS,
    ) -> None:
        super().__init__(
            source=source,
            source_kwargs=source_kwargs,
            patch_size=patch_size,
            batch_size=batch_size,
            num_workers=num_workers,
            patches_per_image=patches_per_image,
            val_patches_per_image=val_patches_per_image,
            val_fraction=val_fraction,
            test_fraction=test_fraction,
            seed=seed,
            group_by=group_by,
            flips=flips,
            rot90=rot90,
            brightness_dn=brightness_dn,
            min_std_dn=min_std_dn,
            max_clipped_fraction=max_clipped_fraction,
            keep_hard_patches=keep_hard_patches,
            max_tries=max_tries,
            pin_memory=pin_memory,
            train_rng=train_rng,
        )
        self.save_hyperparameters()
        if metadata_set not in METADATA_SETS:
            raise ValueError(f"metadata_set = {metadata_set!r} must be one of {list(METADATA_SETS)}")
        self.metadata_set = metadata_set
        self.sensor = sensor
        # a preset name or a metadata file (camera.yaml of camhealth.calibrate), read once
        self._sensor_meta = CameraMetadata.lookup(sensor) if sensor is not None else None
        ranges = check_metadata_ranges(metadata_ranges)
        if sensor is not None:  # a preset fixes the sensor; the operating point is still sampled
            ranges = {**{n: METADATA_RANGES[n] for n in MINIMAL_FIELDS}, **ranges}
        self.metadata_ranges = ranges
        self.gain_uniform_in = gain_uniform_in
        self.xi_probability = _check_number(xi_probability, "xi_probability", 0.0, 1.0)
        xi_fields = tuple(xi_fields)
        bad = [f for f in xi_fields if f not in FULL_FIELDS]
        if bad or (not xi_fields and self.xi_probability > 0):
            raise ValueError(f"xi_fields {list(xi_fields)} must be a non-empty list of fields from {list(FULL_FIELDS)}")
        self.xi_fields = xi_fields
        self.noise_sources = check_sources(noise_sources)
        if not self.noise_sources:
            raise ValueError(f"noise_sources = {list(noise_sources)!r} must name at least one of {list(NOISE_SOURCES)} "
                             "(every sample is labelled as carrying noise)")
        self.quantize = check_flag(quantize, "quantize")
        # Validate the sampling configuration now (a bad preset/range fails at construction).
        CameraMetadata.sample(1, ranges=self.metadata_ranges, fixed=self._sensor_meta, gain_uniform_in=gain_uniform_in)

    # ------------------------------------------------------------------ metadata
    def sample_metadata(
        self, batch_size: int, generator: torch.Generator | None = None
    ) -> tuple[CameraMetadata, CameraMetadata, torch.Tensor]:
        """Draw (M, M', altered): the metadata given to the network, the metadata the image is corrupted
        with, and which samples differ (one ``xi_fields`` entry redrawn from its sampling range)."""
        meta = CameraMetadata.sample(
            batch_size, generator=generator, ranges=self.metadata_ranges, fixed=self._sensor_meta,
            gain_uniform_in=self.gain_uniform_in,
        )
        altered = torch.rand(batch_size, generator=generator) < self.xi_probability
        if not self.xi_fields or not bool(altered.any()):
            return meta, meta, torch.zeros(batch_size, dtype=torch.bool)
        alt_ranges = {f: self.metadata_ranges.get(f, METADATA_RANGES[f]) for f in self.xi_fields}
        other = CameraMetadata.sample(batch_size, generator=generator, ranges=alt_ranges, gain_uniform_in=self.gain_uniform_in)
        choice = torch.randint(len(self.xi_fields), (batch_size,), generator=generator)
        changes = {}
        for j, f in enumerate(self.xi_fields):
            sel = altered & (choice == j)
            if bool(sel.any()):
                changes[f] = torch.where(sel, getattr(other, f), getattr(meta, f))
        return meta, meta.replace(**changes), altered

    # ------------------------------------------------------------------ corruption
    def corrupt_with(
        self, clean: torch.Tensor, meta: CameraMetadata, meta_image: CameraMetadata, noise_seed: int, rng: str = "torch"
    ) -> dict[str, torch.Tensor]:
        """Corrupt ``clean`` with ``meta_image`` (noise field from ``noise_seed``), label it, and compute ξ
        against the metadata ``meta`` the network is given. Deterministic: the image equals
        ``form_image(clean, meta_image, generator=torch.Generator(device).manual_seed(noise_seed))``, the
        same call :class:`camhealth.augment.RandomSensorNoise` makes for these parameters."""
        dev = clean.device
        b = clean.shape[0]
        meta, meta_image = meta.expand(b).to(device=dev), meta_image.expand(b).to(device=dev)
        both_meta = CameraMetadata.cat([meta, meta_image])
        # σ_SF depends on (W, f_clock, A_SN, sensor type) only: integrate it once for M and M' together.
        sf = source_follower_sigma_e(both_meta) if "readout" in self.noise_sources else None
        generator = torch.Generator(device=dev).manual_seed(int(noise_seed))
        formed = form_image(
            clean, meta_image, sources=self.noise_sources, generator=generator, quantize=self.quantize,
            source_follower_e=None if sf is None else sf[b:], rng=rng,
        )
        # σ_Model(M) and σ_Image(M') from the analytic model, in one call (same numerical footing).
        both = expected_sigma_dn(torch.cat([clean, clean]), both_meta, self.noise_sources, source_follower_e=sf)
        total = both.pow(2).sum(1).sqrt()
        xi = (total[:b] - total[b:]).float()
        same = torch.ones(b, dtype=torch.bool, device=dev)
        for n in FULL_FIELDS:
            same = same & (getattr(meta, n) == getattr(meta_image, n))
        # form_image measures σ before it rounds: with quantize, the total is measured on the image it returns
        sigma_total = realised_sigma_dn(formed.image, formed.blurred) if self.quantize else formed.sigma_total_dn
        return {
            "image": formed.image,
            "meta_raw": metadata_matrix(meta).float(),
            "meta": meta.normalize(self.metadata_set).float(),
            "meta_image_raw": metadata_matrix(meta_image).float(),
            "sigma": formed.sigma_dn.float(),
            "sigma_total": sigma_total.float(),
            "sigma_expected": formed.sigma_expected_dn.float(),
            "xi": xi,
            "xi_norm": xi / 255.0,
            "altered": ~same,
        }

    def corrupt(self, clean: torch.Tensor, generator: torch.Generator | None, rng: str = "torch") -> dict[str, torch.Tensor]:
        meta, meta_image, _ = self.sample_metadata(clean.shape[0], generator)
        seed = int(torch.randint(0, 2**62, (1,), generator=generator))
        return self.corrupt_with(clean, meta, meta_image, seed, rng)
