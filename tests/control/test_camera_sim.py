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
    lo, hi = cam.capture([0, 0], [0.01, 0.01], [0.0, 18.0]).sigma_total_dn.tolist()
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
