"""Image-formation physics: camera metadata, sensor noise, optics, PSFs and MTF (one model per file).

- :mod:`~camhealth.physics.metadata` — batched camera metadata (Table 4.1), presets, normalisation.
- :mod:`~camhealth.physics.photon_shot_noise`, :mod:`~camhealth.physics.dark_current`,
  :mod:`~camhealth.physics.readout_noise` — the three noise sources of Konnik & Welsh (2014).
- :mod:`~camhealth.physics.image_formation` — the Fig. 3.7 chain with per-source labels.
- :mod:`~camhealth.physics.clipping` — each source's σ after clipping to [0, 255] DN, in closed form.
- :mod:`~camhealth.physics.thin_lens` — circle of confusion, hyperfocal distance, blur-size conversion.
- :mod:`~camhealth.physics.defocus_psf`, :mod:`~camhealth.physics.motion_psf` — PSFs (disk, line, camera shake);
  :mod:`~camhealth.physics.gaussian_psf`, :mod:`~camhealth.physics.polygon_psf`, :mod:`~camhealth.physics.ring_psf`,
  :mod:`~camhealth.physics.spherical_psf`, :mod:`~camhealth.physics.random_walk_psf`, :mod:`~camhealth.physics.tiny_psf`
  — further PSF families (Gaussian and polygonal-aperture defocus, donut bokeh, defocus with spherical aberration,
  random-walk shake, tiny random kernels) for held-out evaluation.
- :mod:`~camhealth.physics.mtf` — MTF at the 8 normalised frequencies, H/V and any angle.
"""

from camhealth.physics.clipping import clipped_sigma_dn, estimate_clean_dn
from camhealth.physics.dark_current import dark_current_e_per_s, dark_current_shot_sigma_dn, dark_signal_e
from camhealth.physics.defocus_psf import default_kernel_size, defocus_psf
from camhealth.physics.image_formation import NOISE_SOURCES, ImageFormation, apply_psf, form_image
from camhealth.physics.metadata import (
    FULL_FIELDS,
    METADATA_RANGES,
    MINIMAL_FIELDS,
    PRESETS,
    SENSOR_CONSTANT_RANGES,
    CameraMetadata,
    SensorConstants,
    celsius_to_kelvin,
    db_to_factor,
    factor_to_db,
    kelvin_to_celsius,
)
from camhealth.physics.gaussian_psf import gaussian_mtf, gaussian_psf
from camhealth.physics.polygon_psf import polygon_psf
from camhealth.physics.random_walk_psf import sample_random_walk, trajectory_psf
from camhealth.physics.ring_psf import ring_mtf, ring_psf
from camhealth.physics.spherical_psf import spherical_psf
from camhealth.physics.tiny_psf import sample_tiny_psf
from camhealth.physics.motion_psf import linear_motion_psf, nonlinear_motion_psf, sample_shake_noise
from camhealth.physics.mtf import NORMALIZED_FREQUENCIES, mtf_from_psf, mtf_hv
from camhealth.physics.photon_shot_noise import photon_shot_sigma_dn
from camhealth.physics.readout_noise import readout_sigma_dn, readout_sigma_e, source_follower_sigma_e
from camhealth.physics.thin_lens import (
    circle_of_confusion_mm,
    circle_of_confusion_px,
    convert_blur_size_px,
    hyperfocal_distance_mm,
    motion_length_px,
)

__all__ = [
    "clipped_sigma_dn", "estimate_clean_dn",
    "NOISE_SOURCES", "NORMALIZED_FREQUENCIES", "FULL_FIELDS", "MINIMAL_FIELDS", "METADATA_RANGES", "PRESETS",
    "SENSOR_CONSTANT_RANGES", "CameraMetadata", "SensorConstants", "ImageFormation", "form_image", "apply_psf",
    "defocus_psf", "default_kernel_size", "linear_motion_psf", "nonlinear_motion_psf", "sample_shake_noise",
    "gaussian_psf", "gaussian_mtf", "polygon_psf", "ring_psf", "ring_mtf", "spherical_psf", "sample_random_walk",
    "trajectory_psf", "sample_tiny_psf",
    "mtf_from_psf", "mtf_hv", "photon_shot_sigma_dn", "dark_current_e_per_s", "dark_signal_e",
    "dark_current_shot_sigma_dn", "source_follower_sigma_e", "readout_sigma_e", "readout_sigma_dn",
    "circle_of_confusion_mm", "circle_of_confusion_px", "hyperfocal_distance_mm", "convert_blur_size_px",
    "motion_length_px", "db_to_factor", "factor_to_db", "celsius_to_kelvin", "kelvin_to_celsius",
]
