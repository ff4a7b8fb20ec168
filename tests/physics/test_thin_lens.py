"""Tests for camhealth.physics.thin_lens (Eq. 3.7, 3.9, 5.2, L = v·t)."""

import math

import pytest
import torch

from camhealth.physics.thin_lens import (
    circle_of_confusion_mm,
    circle_of_confusion_px,
    convert_blur_size_px,
    hyperfocal_distance_mm,
    motion_length_px,
)


def test_coc_matches_equation_and_is_zero_in_focus():
    d_a, f, d_o, d_b = 6.0, 20.0, 2000.0, 5000.0
    expected = d_a * f / (d_o - f) * abs(d_b - d_o) / d_b
    assert circle_of_confusion_mm(d_a, f, d_o, d_b) == pytest.approx(expected, rel=1e-12)
    assert circle_of_confusion_mm(d_a, f, d_o, d_o) == 0.0
    assert isinstance(circle_of_confusion_mm(d_a, f, d_o, d_b), float)


def test_coc_px_reproduces_defcars_design():
    # Thesis Sec. 5.1.2 (DEFCARS): d_p = 2.4 µm, D_A = 6.03 mm, d_B = 6 m, f = 21.11 mm; the focus
    # distances d_O were chosen to give the kernel sizes d ∈ {3, 7, 11, 15, 21} px.
    d_o = torch.tensor([4500.0, 3400.0, 2700.0, 2200.0, 1800.0], dtype=torch.float64)
    d = circle_of_confusion_px(6.03, 21.11, d_o, 6000.0, 2.4)
    assert d.dtype == torch.float64
    torch.testing.assert_close(d, torch.tensor([3.0, 7.0, 11.0, 15.0, 21.0], dtype=torch.float64), atol=0.6, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tensor_broadcast_and_dtype(dtype):
    d_b = torch.linspace(1000.0, 10000.0, 256, dtype=dtype)
    out = circle_of_confusion_px(5.0, 16.0, 3000.0, d_b, 5.3)
    assert out.shape == (256,) and out.dtype == dtype
    ref = 5.0 * 16.0 / (3000.0 - 16.0) * (d_b.double() - 3000.0).abs() / d_b.double() * 1000.0 / 5.3
    torch.testing.assert_close(out.double(), ref, rtol=1e-6, atol=1e-9)


def test_hyperfocal():
    # H = D_A·f/d_p + f; f = 8 mm, D_A = 4 mm, 6.45 µm pixels
    assert hyperfocal_distance_mm(4.0, 8.0, 0.00645) == pytest.approx(4.0 * 8.0 / 0.00645 + 8.0)
    # An object at H/2 with focus at H is blurred by about one pixel (the DoF definition).
    h = hyperfocal_distance_mm(4.0, 8.0, 0.00645)
    assert circle_of_confusion_px(4.0, 8.0, h, h / 2, 6.45) == pytest.approx(1.0, rel=0.01)


def test_convert_blur_size_eq_5_2():
    # Thesis example: 21 px on KITTI (4.65 µm) ≈ 41 px on the DEFCARS camera (2.4 µm).
    assert convert_blur_size_px(21.0, 4.65, 2.4) == pytest.approx(21.0 * 4.65 / 2.4)
    assert round(convert_blur_size_px(21.0, 4.65, 2.4)) == 41
    # round trip
    assert convert_blur_size_px(convert_blur_size_px(7.0, 6.45, 5.3), 5.3, 6.45) == pytest.approx(7.0)


def test_motion_length():
    assert motion_length_px(300.0, 0.01) == pytest.approx(3.0)
    out = motion_length_px(torch.tensor([100.0, 200.0]), 0.05)
    torch.testing.assert_close(out, torch.tensor([5.0, 10.0]))


def test_bad_values():
    with pytest.raises(ValueError, match="focus_distance_mm = 10"):
        circle_of_confusion_mm(5.0, 20.0, 10.0, 1000.0)
    with pytest.raises(ValueError, match="aperture_diameter_mm = -1"):
        circle_of_confusion_mm(-1.0, 20.0, 1000.0, 1000.0)
    with pytest.raises(ValueError, match="pixel_pitch_um = 0"):
        circle_of_confusion_px(5.0, 20.0, 1000.0, 2000.0, 0.0)
    with pytest.raises(ValueError, match="nan"):
        hyperfocal_distance_mm(math.nan, 8.0, 0.005)
    with pytest.raises(ValueError, match="velocity_px_per_s = -5"):
        motion_length_px(-5.0, 0.01)
    with pytest.raises(ValueError, match="size_px = -2"):
        convert_blur_size_px(-2.0, 4.65, 2.4)


def test_bad_types():
    with pytest.raises(TypeError, match="aperture_diameter_mm"):
        circle_of_confusion_mm("5", 20.0, 1000.0, 2000.0)
    with pytest.raises(TypeError, match="exposure_s"):
        motion_length_px(100.0, None)
    with pytest.raises(TypeError):
        hyperfocal_distance_mm(True, 8.0, 0.005)
