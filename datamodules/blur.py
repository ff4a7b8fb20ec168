"""``BlurDataModule``: clean patches blurred on the fly (defocus / linear / non-linear motion) with MTF labels.

Batches after :meth:`BlurDataModule.on_after_batch_transfer` (on the batch's device, B patches):

=================  ==========  ======================================================================
key                shape       meaning
=================  ==========  ======================================================================
``image``          B×1×P×P     blurred (and, with ``noise: true``, noisy) patch in [0, 1]
``clean``          B×1×P×P     the clean patch (after flips/rot90/brightness)
``mtf``            (B, 16)     MTF of the applied PSF: H at the 8 normalised frequencies, then V
``family``         (B,) long   0 defocus, 1 linear motion, 2 non-linear motion (camera shake)
``size``           (B,)        blur size [px]: disk diameter d, or motion path (arc) length L
``angle``          (B,)        motion direction Φ [deg] (0 for defocus)
``intensity``      (B,)        shake intensity (0 for defocus and linear motion)
``psf``            (B, k, k)   the applied kernels (k = ``kernel_size``), only with ``return_psf: true``
with ``noise: true`` also ``noisy`` (B,) bool, ``sigma`` (B, 3), ``sigma_total`` (B,),
``sigma_expected`` (B, 3) [DN] and ``meta_raw`` (B, 11) (metadata of the noise; see NoiseDataModule)
=================  ==========  ======================================================================

Each sample gets ONE blur: its family is drawn with the weights ``families`` and its size uniformly from
``size_range`` (up to 31 px by default); the PSFs come from :mod:`camhealth.physics` (``defocus_psf``,
``linear_motion_psf``, ``nonlinear_motion_psf``) and the labels from ``mtf_hv`` on the same kernels.
The image is formed by :func:`camhealth.physics.form_image` (FFT convolution for large kernels, reflect
padding).

Optional noise after blur (combined corruption, thesis Sec. 5.4): with ``noise: true`` a fraction
``noise_probability`` of the samples also gets sensor noise with metadata sampled as in
:class:`~datamodules.NoiseDataModule`. ``noise_order: physical`` follows Fig. 3.7 — defocus before the
photon noise, motion blur after it (so photon noise becomes structured, directional noise);
``noise_order: after_blur`` adds all noise after the blur. The MTF label is the blur's in both cases.
"""

from __future__ import annotations

import numbers
from typing import Any, Mapping, Sequence

import torch

from camhealth._validation import check_odd_kernel_size
from camhealth.augment._base import check_sources
from camhealth.augment.blur import motion_kernel_size
from camhealth.physics.defocus_psf import default_kernel_size, defocus_psf
from camhealth.physics.image_formation import NOISE_SOURCES, form_image
from camhealth.physics.metadata import METADATA_RANGES, MINIMAL_FIELDS, CameraMetadata
from camhealth.physics.motion_psf import linear_motion_psf, nonlinear_motion_psf, sample_shake_noise
from camhealth.physics.mtf import mtf_hv

from datamodules.noise import check_metadata_ranges, metadata_matrix
from datamodules.patches import PatchDataModule, _check_number, check_flag

__all__ = ["BlurDataModule", "FAMILIES", "blur_psf", "min_patch_size"]

#: Blur families in label order (``family`` label = index).
FAMILIES: tuple[str, ...] = ("defocus", "linear", "nonlinear")

#: Steps of the camera-shake path (as in :class:`camhealth.augment.RandomMotionBlur`).
SHAKE_STEPS = 64


def min_patch_size(kernel_size: int) -> int:
    """The smallest patch side [px] :class:`BlurDataModule` accepts for ``kernel_size``: 2·kernel_size − 1.

    A pixel closer than ``kernel_size // 2`` to the patch edge is blurred partly from the reflect-padded border (a
    mirror image of the patch's own edge) instead of the scene beyond the patch. The image stays the kernel applied
    to a scene, so the label is still the optics' MTF, but that scene has a mirror seam no camera sees, and on a patch
    hardly larger than the kernel the seam is most of what the patch shows; only the central (P − 2·(k // 2))² pixels
    are the true scene blurred. This rule keeps that centre at least one kernel wide (an edge there shows its whole
    spread function). How much the seam moves what a patch shows, measured (x gratings
    at the 8 label frequencies, modulation fitted over the whole patch, mean over 16 phases, worst frequency,
    against the same scene blurred without padding; defocus / linear / non-linear blur filling the kernel, k = 15
    and 35): the fitted modulation differs by 0.15–0.39 at P = k, 0.07–0.20 at 1.5·k, 0.06–0.11 at 2·k − 1, and then only
    slowly less with the border's share of the patch (0.03–0.07 at 3–4·k); below 2·k − 1 it grows steeply.
    """
    return 2 * int(kernel_size) - 1


def blur_psf(
    family: torch.Tensor,
    size: torch.Tensor,
    angle: torch.Tensor,
    intensity: torch.Tensor,
    shake_noise: torch.Tensor,
    kernel_size: int,
) -> torch.Tensor:
    """(B, k, k) PSFs of mixed families: defocus disks of diameter ``size``, straight lines of length
    ``size`` at ``angle``, or camera-shake paths of arc length ``size`` with ``intensity`` and
    ``shake_noise`` (B, N, 2). Deterministic."""
    b = family.shape[0]
    dev = size.device
    psf = torch.zeros(b, kernel_size, kernel_size, device=dev, dtype=torch.float32)
    for fam_id, make in (
        (0, lambda m: defocus_psf(size[m], kernel_size)),
        (1, lambda m: linear_motion_psf(size[m], angle[m], kernel_size)),
        (2, lambda m: nonlinear_motion_psf(size[m], angle[m], intensity[m], shake_noise[m], kernel_size)),
    ):
        m = family == fam_id
        if bool(m.any()):
            psf[m] = make(m).to(psf.dtype)
    return psf


class BlurDataModule(PatchDataModule):
    """Blurred patches with their 16 MTF labels, blur family and size, corrupted on the device.

    Data options: as :class:`~datamodules.NoiseDataModule` (source, split, patches, augmentation,
    rejection, loaders); the default ``patch_size`` is 192 (thesis 4.3.1).

    Blur options:
        families: relative weights of ``defocus``, ``linear`` and ``nonlinear`` motion blur (a family with
            weight 0 never occurs).
        size_range: ``[low, high]`` blur size [px] (disk diameter or path length), uniform; high ≤ 63.
        angle_range: ``[low, high]`` motion direction [deg], uniform (0° horizontal, 90° vertical).
        shake_intensity: ``[low, high]`` camera-shake intensity of non-linear motion, in [0, 1].
        kernel_size: odd PSF size; default: the smallest holding ``size_range[1]`` for every family.
            ``patch_size`` must be at least 2·kernel_size − 1 (:func:`min_patch_size`; 69 px for the default
            35-px kernel of 31-px blur): in smaller patches most of what is blurred is the reflect-padded border's
            mirror seam, not the scene.
        return_psf: also return the applied kernels as ``psf``.

    Noise options (combined corruption): ``noise`` (switch), ``noise_probability`` (fraction of samples),
    ``noise_order`` (``"physical"`` Fig. 3.7 order or ``"after_blur"``), ``noise_sources``, ``sensor``,
    ``metadata_ranges``, ``gain_uniform_in``, ``train_rng`` (as in NoiseDataModule).
    """

    default_patch_size = 192

    def __init__(
        self,
        source: str = "default",
        source_kwargs: dict[str, Any] | None = None,
        patch_size: int = 192,
        batch_size: int = 32,
        num_workers: int = 0,
        patches_per_image: int = 32,
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
        families: dict[str, float] | None = None,
        size_range: tuple[float, float] = (1.0, 31.0),
        angle_range: tuple[float, float] = (0.0, 180.0),
        shake_intensity: tuple[float, float] = (0.5, 1.0),
        kernel_size: int | None = None,
        return_psf: bool = False,
        noise: bool = False,
        noise_probability: float = 1.0,
        noise_order: str = "physical",
        noise_sources: Sequence[str] = NOISE_SOURCES,
        sensor: str | None = None,
        metadata_ranges: dict[str, tuple[float, float]] | None = None,
        gain_uniform_in: str = "factor",
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
        if families is not None and not isinstance(families, Mapping):
            raise TypeError(f"families = {families!r} must be a mapping of blur family to weight, e.g. "
                            "{defocus: 2.0, linear: 1.0, nonlinear: 1.0} (families: " + ", ".join(FAMILIES) + ")")
        weights = {"defocus": 1.0, "linear": 1.0, "nonlinear": 1.0} if families is None else dict(families)
        unknown = set(weights) - set(FAMILIES)
        if unknown:
            raise ValueError(f"unknown blur famil(ies) {sorted(map(str, unknown))}; choose from {list(FAMILIES)}")
        for f, v in weights.items():
            if isinstance(v, bool) or not isinstance(v, numbers.Real):
                raise TypeError(f"families[{f!r}] = {v!r} must be a number (the family's weight, >= 0)")
        w = torch.tensor([float(weights.get(f, 0.0)) for f in FAMILIES], dtype=torch.float64)
        if bool((w < 0).any()) or not bool(torch.isfinite(w).all()) or float(w.sum()) <= 0:
            raise ValueError(f"families weights {weights} must be finite, >= 0 and not all 0")
        self.family_weights = w / w.sum()
        self.size_range = _pair(size_range, "size_range", 0.0, 63.0)
        self.angle_range = _pair(angle_range, "angle_range", -360.0, 360.0)
        self.shake_intensity = _pair(shake_intensity, "shake_intensity", 0.0, 1.0)
        need = max(default_kernel_size(self.size_range[1]), motion_kernel_size(self.size_range[1], True))
        if kernel_size is None:
            kernel_size = need
        elif check_odd_kernel_size(kernel_size) < self.size_range[1]:
            raise ValueError(f"kernel_size = {kernel_size} must be odd and >= size_range[1] = {self.size_range[1]:g}")
        self.kernel_size = int(kernel_size)
        smallest = min_patch_size(self.kernel_size)
        if self.patch_size < smallest:
            raise ValueError(
                f"patch_size = {self.patch_size} is too small for kernel_size = {self.kernel_size} (size_range[1] = "
                f"{self.size_range[1]:g} px): patch_size must be >= 2·kernel_size − 1 = {smallest}, so that the "
                f"pixels blurred without the padded border (at least kernel_size // 2 = {self.kernel_size // 2} px from "
                "every edge) span at least one kernel; in smaller patches most of what is blurred is the reflect-padded "
                "border's mirror seam, not the scene. Use a larger patch_size or a smaller size_range[1] / kernel_size"
            )
        self.return_psf = check_flag(return_psf, "return_psf")
        self.noise = check_flag(noise, "noise")
        self.noise_probability = _check_number(noise_probability, "noise_probability", 0.0, 1.0)
        if noise_order not in ("physical", "after_blur"):
            raise ValueError(f"noise_order = {noise_order!r} must be 'physical' or 'after_blur'")
        self.noise_order = noise_order
        self.noise_sources = check_sources(noise_sources)
        if self.noise and not self.noise_sources:
            raise ValueError(f"noise_sources = {list(noise_sources)!r} must name at least one of {list(NOISE_SOURCES)} "
                             "with noise: true (noisy samples are labelled as carrying noise)")
        self.sensor = sensor
        # a preset name or a metadata file (camera.yaml of camhealth.calibrate), read once
        self._sensor_meta = CameraMetadata.lookup(sensor) if sensor is not None else None
        ranges = check_metadata_ranges(metadata_ranges)
        if sensor is not None:
            ranges = {**{n: METADATA_RANGES[n] for n in MINIMAL_FIELDS}, **ranges}
        self.metadata_ranges = ranges
        if gain_uniform_in not in ("factor", "db"):  # (checked here too: noise off samples no metadata)
            raise ValueError(f"gain_uniform_in = {gain_uniform_in!r} is not one of ['factor', 'db']")
        self.gain_uniform_in = gain_uniform_in
        if self.noise or ranges:  # a bad range or preset is refused also where noise is off
            CameraMetadata.sample(1, ranges=self.metadata_ranges, fixed=self._sensor_meta, gain_uniform_in=gain_uniform_in)

    # ------------------------------------------------------------------ parameters
    def sample_params(self, batch_size: int, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        """Random blur parameters (CPU): ``family``, ``size``, ``angle``, ``intensity``, ``shake_noise``."""
        b = batch_size
        family = torch.multinomial(self.family_weights, b, replacement=True, generator=generator)
        u = torch.rand(b, 3, generator=generator, dtype=torch.float64)
        lo, hi = self.size_range
        size = lo + u[:, 0] * (hi - lo)
        alo, ahi = self.angle_range
        angle = alo + u[:, 1] * (ahi - alo)
        ilo, ihi = self.shake_intensity
        intensity = ilo + u[:, 2] * (ihi - ilo)
        angle = torch.where(family == 0, torch.zeros_like(angle), angle)
        intensity = torch.where(family == 2, intensity, torch.zeros_like(intensity))
        shake = sample_shake_noise(b, SHAKE_STEPS, generator=generator)
        return {
            "family": family,
            "size": size.float(),
            "angle": angle.float(),
            "intensity": intensity.float(),
            "shake_noise": shake,
        }

    # ------------------------------------------------------------------ corruption
    def corrupt_with(
        self,
        clean: torch.Tensor,
        params: Mapping[str, torch.Tensor],
        meta: CameraMetadata | None = None,
        noisy: torch.Tensor | None = None,
        noise_seed: int = 0,
        rng: str = "torch",
    ) -> dict[str, torch.Tensor]:
        """Blur ``clean`` with the PSFs of ``params`` (and add noise under ``meta`` where ``noisy``)."""
        dev = clean.device
        p = {k: v.to(dev) for k, v in params.items()}
        psf = blur_psf(p["family"], p["size"], p["angle"], p["intensity"], p["shake_noise"], self.kernel_size)
        out: dict[str, torch.Tensor] = {
            "mtf": mtf_hv(psf).float(),
            "family": p["family"].long(),
            "size": p["size"].float(),
            "angle": p["angle"].float(),
            "intensity": p["intensity"].float(),
        }
        if meta is None:
            formed = form_image(clean, None, defocus_psf=psf, sources=())
            out["image"] = formed.image
        else:
            b = clean.shape[0]
            meta = meta.expand(b).to(device=dev)
            if self.noise_order == "physical":
                delta = torch.zeros_like(psf)
                delta[:, self.kernel_size // 2, self.kernel_size // 2] = 1.0
                is_def = (p["family"] == 0).view(-1, 1, 1)
                dpsf, mpsf = torch.where(is_def, psf, delta), torch.where(is_def, delta, psf)
            else:
                dpsf, mpsf = psf, None
            g = torch.Generator(device=dev).manual_seed(int(noise_seed))
            formed = form_image(
                clean, meta, defocus_psf=dpsf, motion_psf=mpsf, sources=self.noise_sources, generator=g, rng=rng
            )
            noisy = torch.ones(b, dtype=torch.bool, device=dev) if noisy is None else noisy.to(dev)
            m = noisy.view(-1, 1, 1, 1)
            out["image"] = torch.where(m, formed.image, formed.blurred.clamp(0, 1).to(formed.image.dtype))
            z = noisy[:, None]
            out["noisy"] = noisy
            out["sigma"] = torch.where(z, formed.sigma_dn, 0).float()
            out["sigma_total"] = torch.where(noisy, formed.sigma_total_dn, 0).float()
            out["sigma_expected"] = torch.where(z, formed.sigma_expected_dn, 0).float()
            out["meta_raw"] = metadata_matrix(meta).float()
        if self.return_psf:
            out["psf"] = psf
        return out

    def corrupt(self, clean: torch.Tensor, generator: torch.Generator | None, rng: str = "torch") -> dict[str, torch.Tensor]:
        b = clean.shape[0]
        params = self.sample_params(b, generator)
        if not self.noise:
            return self.corrupt_with(clean, params)
        meta = CameraMetadata.sample(
            b, generator=generator, ranges=self.metadata_ranges, fixed=self._sensor_meta, gain_uniform_in=self.gain_uniform_in
        )
        noisy = torch.rand(b, generator=generator) < self.noise_probability
        seed = int(torch.randint(0, 2**62, (1,), generator=generator))
        return self.corrupt_with(clean, params, meta, noisy, seed, rng)


def _pair(v: Any, name: str, low: float, high: float) -> tuple[float, float]:
    if isinstance(v, numbers.Real) and not isinstance(v, bool):
        v = (v, v)
    pair = list(v) if isinstance(v, (list, tuple)) else None
    if pair is None or len(pair) != 2 or any(isinstance(x, bool) or not isinstance(x, numbers.Real) for x in pair):
        raise ValueError(f"{name} must be a number or a [low, high] pair of numbers, got {v!r}")
    lo, hi = float(pair[0]), float(pair[1])
    if not (low <= lo <= hi <= high):
        raise ValueError(f"{name} = [{lo:g}, {hi:g}] must satisfy {low:g} <= low <= high <= {high:g}")
    return lo, hi
