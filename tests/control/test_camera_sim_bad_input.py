"""SimulatedCamera on overexposed frames, extreme settings and arguments that are not numbers."""

import re

import numpy as np
import pytest
import torch

from camhealth.control import SimulatedCamera
from camhealth.control.camera_sim import MAX_ILLUMINATION_PER_S


def _bright_band_frame(size=128):
    """Dark texture with a bright 0.95 band (overexposed at 40/s from ≈ 26 ms) and a black stripe."""
    g = torch.Generator().manual_seed(0)
    fr = torch.rand(1, 1, size, size, generator=g) * 0.2 + 0.02
    fr[..., :, : size // 4] = 0.95
    fr[..., : size // 12, :] = 0.0
    return fr


def _off_grid(image):
    dn = image.double() * 255.0
    return int(((dn - dn.round()).abs() > 1e-3).sum())


@pytest.mark.parametrize("illumination, exposure_s, motion, quantize", [
    (40.0, 0.1, 800.0, True),   # 80 px of motion: the Fourier-domain blur of the light beyond full scale
    (40.0, 0.1, 800.0, False),
    (40.0, 0.2, 800.0, True),
    (40.0, 0.1, 100.0, True),   # 10 px: direct convolution
    (1e4, 0.2, 800.0, True),
    (MAX_ILLUMINATION_PER_S, 0.2, 800.0, False),
])
def test_overexposed_capture_stays_in_range_and_on_the_8_bit_grid(illumination, exposure_s, motion, quantize):
    """The light beyond full scale was added after the clipping at 0 and after the quantisation: values down to
    −3e-7 (−0.78 at E = 1e7/s) and thousands of pixels off the 8-bit grid although quantize=True."""
    cam = SimulatedCamera(_bright_band_frame(), illumination_per_s=illumination, motion_px_per_s=motion,
                          quantize=quantize)
    cap = cam.capture(0, exposure_s, 0.0)
    assert float(cap.clipped_fraction[0]) > 0  # overexposed somewhere
    for t in (cap.image, cap.blurred):
        assert float(t.min()) >= 0.0 and float(t.max()) <= 1.0
    if quantize:
        assert _off_grid(cap.image) == 0
    assert torch.isfinite(cap.sigma_dn).all() and 0 <= float(cap.mean_intensity[0]) <= 1


@pytest.mark.parametrize("dtype", [torch.float16])
@pytest.mark.parametrize("illumination", [1e5, MAX_ILLUMINATION_PER_S])
def test_half_precision_frames_render_a_bright_scene(dtype, illumination):
    """E·t·g = 3.2e5 overflowed fp16 (max 65504): 'clean must be finite' for a scene fp32 frames render."""
    fr = _bright_band_frame(64)
    cap = SimulatedCamera(fr.to(dtype), illumination_per_s=illumination).capture(0, 0.2, 24.0)
    ref = SimulatedCamera(fr, illumination_per_s=illumination).capture(0, 0.2, 24.0)
    assert cap.image.dtype == dtype and bool(torch.isfinite(cap.image).all())
    assert float(cap.mean_intensity[0]) == pytest.approx(float(ref.mean_intensity[0]), abs=0.01)


@pytest.mark.parametrize("illumination", [1e7, 1e30, 1e36, 1e39])
def test_illumination_beyond_the_bound_is_refused(illumination):
    """1e36/s rendered an image of NaN without an error; 1e39/s failed as 'clean must be finite'."""
    with pytest.raises(ValueError, match=re.escape(f"illumination_per_s = {illumination!r} is out of the allowed range "
                                                   "(0, 1e+06] /s")):
        SimulatedCamera(_bright_band_frame(32), illumination_per_s=illumination)


@pytest.mark.parametrize("angle", [1e300, -1e300, 1e39])
def test_any_finite_motion_angle_renders_as_its_direction(angle):
    """motion_angle_deg = 1e300 failed deep in torch: 'value cannot be converted to type float without overflow'."""
    fr = _bright_band_frame(64) * 0.5
    a = SimulatedCamera(fr, motion_px_per_s=500.0, motion_angle_deg=angle).capture(0, 0.02, 0.0)
    b = SimulatedCamera(fr, motion_px_per_s=500.0, motion_angle_deg=float(np.fmod(angle, 360.0))).capture(0, 0.02, 0.0)
    torch.testing.assert_close(a.mtf, b.mtf)


@pytest.mark.parametrize("kwargs, match", [
    ({"frame_index": 0, "exposure_s": ["0.01"], "gain_db": 0.0}, r"exposure_s = \['0.01'\] must be a number"),
    ({"frame_index": 0, "exposure_s": [0.01, True], "gain_db": 0.0}, r"exposure_s = \[0.01, True\] must be a number"),
    ({"frame_index": 0, "exposure_s": 0.01 + 0j, "gain_db": 0.0}, r"exposure_s = \(0.01\+0j\) must be a number"),
    ({"frame_index": 0, "exposure_s": 0.01, "gain_db": [None]}, r"gain_db = \[None\] must be a number"),
    ({"frame_index": "a", "exposure_s": 0.01, "gain_db": 0.0}, r"frame_index = 'a' must be whole frame numbers"),
    ({"frame_index": ["0"], "exposure_s": 0.01, "gain_db": 0.0}, r"frame_index = \['0'\] must be whole frame numbers"),
    ({"frame_index": np.array(["0"]), "exposure_s": 0.01, "gain_db": 0.0}, r"frame_index = .* must be whole frame"),
])
def test_arguments_that_are_not_numbers_are_named(kwargs, match):
    """capture(0, ['0.01'], 0) failed with "too many dimensions 'str'", capture('a', …) with "new(): invalid data
    type 'str'"."""
    cam = SimulatedCamera(_bright_band_frame(32) * 0.5, motion_px_per_s=0.0)
    with pytest.raises(ValueError, match=match):
        cam.capture(**kwargs)


@pytest.mark.parametrize("index", [np.int64(1), np.int32(-1), np.uint8(1)])
def test_a_capture_is_indexed_by_any_integer(index):
    """Capture[np.int64(1)] was refused while Capture[torch.tensor(1)] was accepted."""
    cam = SimulatedCamera(_bright_band_frame(32) * 0.5, motion_px_per_s=0.0)
    cap = cam.capture([0, 0], [0.01, 0.02], 0.0)
    assert cap[index].exposure_s.tolist() == pytest.approx([0.02])
