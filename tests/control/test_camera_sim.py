"""SimulatedCamera: radiometry ∝ t·g, motion length v·t, labels, validation, determinism."""

import pytest
import torch

from camhealth.control import SimulatedCamera, motion_kernel_for
from camhealth.physics.mtf import line_mtf
from tests.iopc.fakes import smooth_frames


@pytest.fixture
def frames():
    return smooth_frames(2, 64, 96)


def test_noise_free_intensity_scales_with_exposure_times_gain(frames):
    cam = SimulatedCamera(frames, illumination_per_s=20.0, motion_px_per_s=0.0, sources=(), quantize=False)
    cap = cam.capture([0, 0, 0], [0.01, 0.02, 0.01], [0.0, 0.0, 20 * torch.log10(torch.tensor(2.0)).item()])
    expected = frames[0] * 20.0 * 0.01
    torch.testing.assert_close(cap.image[0], expected, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(cap.image[1], 2 * expected, rtol=1e-5, atol=1e-6)  # twice the exposure
    torch.testing.assert_close(cap.image[2], cap.image[1], rtol=1e-5, atol=1e-6)  # = twice the gain
    assert cap.sigma_total_dn.abs().max() == 0 and cap.blur_length_px.tolist() == [0.0] * 3


@pytest.mark.parametrize("batch", [1, 3])
def test_motion_length_and_mtf_label(frames, batch):
    cam = SimulatedCamera(frames, motion_px_per_s=1000.0, motion_angle_deg=0.0, sources=())
    t = torch.tensor([0.004, 0.008, 0.012])[:batch]
    cap = cam.capture([1] * batch, t, 0.0)
    assert cap.blur_length_px.tolist() == pytest.approx((1000 * t).tolist())
    assert cap.image.shape == (batch, 1, 64, 96) and cap.mtf.shape == (batch, 16)
    # horizontal motion: V MTF is 1; H MTF at f_n = 0.1 follows |sinc(L·0.05)| (× pixel aperture, aliasing)
    assert torch.allclose(cap.mtf[:, 8:], torch.ones(batch, 8), atol=1e-6)
    cont = line_mtf(cap.blur_length_px.double(), torch.tensor(0.05, dtype=torch.float64)).float()
    assert torch.allclose(cap.mtf[:, 1], cont, atol=0.03)


def test_noise_grows_with_gain_and_is_seeded(frames):
    cam = SimulatedCamera(frames, sensor="EV76C661", illumination_per_s=50.0, motion_px_per_s=0.0, temperature_c=60.0)
    # 2 ms: even at 18 dB (×7.9) the frame stays below full scale, where saturation would cut the noise
    lo, hi = cam.capture([0, 0], [0.002, 0.002], [0.0, 18.0]).sigma_total_dn.tolist()
    assert hi > 3 * lo > 0
    a = cam.capture(0, 0.01, 6.0)
    b = cam.capture(0, 0.01, 6.0)
    assert torch.equal(a.image, b.image)  # same request → same frame
    c = cam.capture([1, 0, 0], [0.02, 0.01, 0.005], [0.0, 6.0, 12.0])
    assert torch.equal(c.image[1:2], a.image)  # … whatever else is in the batch
    assert torch.equal(a.image * 255, (a.image * 255).round())  # 8-bit output
    assert a[0].meta.gain_db.tolist() == pytest.approx([6.0])


def test_validation(frames):
    cam = SimulatedCamera(frames)
    with pytest.raises(ValueError, match="exposure_s"):
        cam.capture(0, 0.5, 0.0)  # beyond Table 4.1's 0.2 s
    with pytest.raises(ValueError, match="gain_db"):
        cam.capture(0, 0.01, 30.0)
    with pytest.raises(IndexError, match="out of range"):
        cam.capture(5, 0.01, 0.0)
    with pytest.raises(ValueError, match="batch of 3"):
        cam.capture([0, 1, 0], [0.01, 0.02], 0.0)
    for bad in (0.7, float("nan"), True):  # 0.7 rendered frame 0
        with pytest.raises(ValueError, match="must be whole frame numbers"):
            cam.capture(bad, 0.01, 0.0)
    assert cam.capture(1.0, 0.01, 0.0).image.shape[0] == 1
    with pytest.raises(ValueError, match="illumination_per_s"):
        SimulatedCamera(frames, illumination_per_s=0.0)
    with pytest.raises(ValueError, match="noise source"):
        SimulatedCamera(frames, sources=("shot",))
    assert motion_kernel_for(0.0) == 3 and motion_kernel_for(6.4) == 9 and motion_kernel_for(7.0) == 9


@pytest.mark.parametrize("gain_db", [0.0, 24.0])
def test_overexposed_pixels_read_full_scale_not_full_scale_less_noise(gain_db):
    # a 0.5 scene at E = 40/s, 0.2 s is 4× (0 dB) to 63× (24 dB) over full scale: the ADC clips signal plus noise
    cam = SimulatedCamera(torch.full((1, 1, 64, 64), 0.5), illumination_per_s=40.0, motion_px_per_s=0.0)
    cap = cam.capture(0, 0.2, gain_db)
    assert cap.image.min().item() == 1.0 and cap.clipped_fraction.item() == 1.0
    assert cap.blurred.min().item() == 1.0 and cap.sigma_total_dn.item() == 0.0
    assert cap.sigma_dn.abs().max().item() == 0.0 and cap.mean_intensity.item() == 1.0


def test_overexposure_is_blurred_and_leaves_the_rest_of_the_frame_alone():
    # left half dark (0.1), right half bright (0.9): at 0.05 s and 6 dB the right half is 3.6× over full scale
    x = torch.full((1, 1, 64, 64), 0.1)
    x[..., 32:] = 0.9
    cam = SimulatedCamera(x, illumination_per_s=40.0, motion_px_per_s=100.0)  # 5-px horizontal motion
    cap = cam.capture(0, 0.05, 6.0)
    free = SimulatedCamera(x * 0.25, illumination_per_s=40.0, motion_px_per_s=100.0).capture(0, 0.05, 6.0)
    assert bool((cap.image[..., 40:] == 1.0).all())  # the bright half is saturated everywhere
    assert bool((cap.image[..., :24] < 1.0).all())  # the dark half keeps its noise, far from the blurred edge
    # the light beyond full scale spreads across the edge like the rest of the light (5 px of motion)
    assert bool((cap.image[..., 30] > free.image[..., 30] + 0.2).all())
    assert 0.5 < cap.clipped_fraction.item() < 0.6 and cap.sigma_total_dn.item() > 0


def test_capture_index_from_the_end_and_out_of_range(frames):
    cam = SimulatedCamera(frames, motion_px_per_s=100.0)
    cap = cam.capture([0, 1], [0.01, 0.02], 0.0)
    assert cap[-1].exposure_s.tolist() == pytest.approx([0.02]) and cap[-1].image.shape[0] == 1
    assert torch.equal(cap[-2].image, cap[0].image) and cap[-1].meta.batch_size == 1
    for bad in (2, -3):
        with pytest.raises(IndexError, match=rf"capture index {bad} is out of the allowed range \[-2, 1\] for a batch of 2"):
            cap[bad]
    with pytest.raises(TypeError, match="indexed by an int, got float"):
        cap[0.5]


def test_motion_beyond_the_largest_kernel_names_speed_and_exposure(frames):
    cam = SimulatedCamera(frames, motion_px_per_s=2000.0)
    with pytest.raises(ValueError, match=r"motion_px_per_s · exposure_s = 2000 px/s · 0.2 s = 400 px of motion blur is "
                                         r"out of the allowed range \[0, 253\] px"):
        cam.capture(0, 0.2, 0.0)
    assert cam.capture(0, 0.1265, 0.0).blur_length_px.item() == pytest.approx(253.0)


def test_numbers_of_any_real_type_are_taken_and_booleans_and_text_refused(frames):
    """np.float32(40) and a 0-d tensor are numbers; True, 1.7 as a seed and "no" as quantize were taken as 1 / 1 / True."""
    import numpy as np

    for v in (np.float32(40.0), torch.tensor(40.0), 40):
        assert SimulatedCamera(frames, illumination_per_s=v).illumination == 40.0
    for kwargs, match in [
        ({"illumination_per_s": True}, r"illumination_per_s = True must be a finite number >= 0"),
        ({"motion_px_per_s": "5"}, r"motion_px_per_s = '5' must be a finite number"),
        ({"motion_angle_deg": float("nan")}, r"motion_angle_deg = nan must be a finite number"),
        ({"seed": 1.7}, r"seed = 1.7 must be an integer"),
        ({"seed": True}, r"seed = True must be an integer"),
        ({"quantize": "no"}, r"quantize = 'no' must be True or False"),
    ]:
        with pytest.raises(ValueError, match=match):
            SimulatedCamera(frames, **kwargs)
    cam = SimulatedCamera(frames, sources=())
    for t, g in (("0.01", 0.0), (0.01, True), (None, 0.0)):
        with pytest.raises(ValueError, match="must be a number or a sequence/tensor of numbers"):
            cam.capture(0, t, g)
