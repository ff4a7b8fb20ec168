"""Bad input to camhealth.physics fails early with a message naming the argument, its value and what is allowed:
never a NaN image, a silently shifted or truncated kernel, or a crash deep inside torch."""

import dataclasses
import math
import re

import numpy as np
import pytest
import torch

from camhealth.physics import (
    CameraMetadata,
    SensorConstants,
    apply_psf,
    defocus_psf,
    form_image,
    gaussian_mtf,
    gaussian_psf,
    linear_motion_psf,
    photon_shot_sigma_dn,
    polygon_psf,
    sample_random_walk,
    sample_tiny_psf,
    spherical_psf,
    trajectory_psf,
)
from camhealth.physics.image_formation import poisson_z_table, sample_poisson, sample_poisson_per_sample
from camhealth.physics.metadata import SENSOR_CONSTANT_RANGES
from camhealth.physics.photon_shot_noise import photo_electrons, photon_shot_sigma_patch_dn
from camhealth.physics.readout_noise import readout_sigma_dn, source_follower_sigma_e

X = torch.full((2, 1, 16, 16), 0.5)


def _with_constants(meta: CameraMetadata, constants: SensorConstants) -> CameraMetadata:
    return CameraMetadata(**{n: getattr(meta, n) for n in meta.to_dict()}, constants=constants)


# ---------------------------------------------------------------------------------------------- SensorConstants
@pytest.mark.parametrize("field, value", [
    ("flicker_corner_hz", -1e9),  # was: NaN image and labels
    ("source_follower_gain", 0.0),  # was: salt and pepper, σ inf/NaN
    ("source_follower_gain", 1e-30),
    ("rtn_current_a", 1e3),  # was: σ_RN of 10⁶ DN
    ("cds_sample_time_s", 0.0),  # was: ZeroDivisionError
    ("cds_time_factor", 0.0),
    ("cds_time_factor", -0.5),
    ("rtn_time_factor", 0.0),
    ("offset_dn", -1.0),
    ("cds_gain", 0.0),
    ("reference_voltage_v", 0.0),
    ("cds_sample_time_s", math.nan),
    ("flicker_corner_hz", math.inf),
    ("rtn_current_a", 10**400),
])
def test_sensor_constants_out_of_range_are_refused_naming_the_field(field, value):
    low, high, unit = SENSOR_CONSTANT_RANGES[field]
    allowed = re.escape(f"is out of the allowed range [{low:g}, {high:g}]")
    with pytest.raises(ValueError, match=rf"^SensorConstants\.{field} = .* {allowed}"):
        SensorConstants(**{field: value})


@pytest.mark.parametrize("value", [True, "1e-6", None, torch.tensor([1e-6, 2e-6]), 1j])
def test_sensor_constants_must_be_real_numbers(value):
    with pytest.raises(TypeError, match=r"^SensorConstants\.cds_sample_time_s must be a real number in s, got"):
        SensorConstants(cds_sample_time_s=value)


def test_sensor_constants_defaults_and_numbers_of_other_types_are_kept():
    d = SensorConstants()
    assert dataclasses.astuple(d) == (0.0, 1.0, 1e-6, 0.5, 1e6, 1e-8, 0.1, 1.0, 5.0)
    c = SensorConstants(cds_sample_time_s=np.float64(5e-7), flicker_corner_hz=10_000, rtn_current_a=torch.tensor(2e-8, dtype=torch.float64))
    assert c == SensorConstants(cds_sample_time_s=5e-7, flicker_corner_hz=1e4, rtn_current_a=2e-8)
    assert all(type(v) is float for v in dataclasses.astuple(c))
    assert hash(c) == hash(SensorConstants(cds_sample_time_s=5e-7, flicker_corner_hz=1e4, rtn_current_a=2e-8))
    for name, (low, high, unit) in SENSOR_CONSTANT_RANGES.items():  # the ranges are documented with their units
        assert low <= getattr(d, name) <= high
        line = re.search(rf"{name}: (.*)", SensorConstants.__doc__).group(1)
        lo, hi = re.search(r"([-0-9.e]+)…([-0-9.e]*[0-9])", line).groups()
        assert (float(lo), float(hi)) == (low, high) and (f"[{unit}]" in line if unit else "[–]" in line), name


@pytest.mark.parametrize("field", sorted(SENSOR_CONSTANT_RANGES))
@pytest.mark.parametrize("end", [0, 1])
def test_every_allowed_sensor_constant_gives_a_finite_read_noise(field, end):
    """The ends of the ranges keep the readout model finite and positive (and the tabulated integral accurate)."""
    c = SensorConstants(**{field: SENSOR_CONSTANT_RANGES[field][end]})
    m = _with_constants(CameraMetadata.preset("EV76C661", batch_size=2, pixel_clock_hz=[8e6, 150e6], gain_db=24.0), c)
    s = readout_sigma_dn(m)
    assert bool(torch.isfinite(s).all()) and bool((s > 0).all())
    torch.testing.assert_close(source_follower_sigma_e(m), source_follower_sigma_e(m, tabulated=False), rtol=1e-3, atol=0)


def test_replaced_constants_go_through_the_same_checks():
    meta = CameraMetadata.preset("EV76C661")
    with pytest.raises(ValueError, match=r"SensorConstants\.flicker_corner_hz = -1e\+09 Hz"):
        dataclasses.replace(meta, constants=dataclasses.replace(meta.constants, flicker_corner_hz=-1e9))


# ---------------------------------------------------------------------------------------------- source_follower_e
@pytest.mark.parametrize("sf, exc, match", [
    (torch.tensor([math.nan]), ValueError, r"source_follower_e must be finite"),
    (torch.tensor([-1.0]), ValueError, r"source_follower_e = -1 e⁻ is out of the allowed range \[0, inf\)"),
    (torch.ones(3), ValueError, r"source_follower_e must have shape \(1,\) or \(B,\) = \(2,\).*got shape \(3,\)"),
    (torch.ones(2, 1), ValueError, r"source_follower_e must have shape \(1,\) or \(B,\)"),
    ([12.5], TypeError, r"source_follower_e must be a torch.Tensor"),
    (torch.ones(1, dtype=torch.int64), TypeError, r"source_follower_e must be a floating tensor"),
])
def test_form_image_checks_source_follower_e(sf, exc, match):
    with pytest.raises(exc, match=match):
        form_image(X, CameraMetadata.preset("ICX285"), source_follower_e=sf)


def test_form_image_accepts_a_valid_source_follower_e_unchanged():
    meta = CameraMetadata.preset("ICX285", batch_size=2)
    sf = source_follower_sigma_e(meta)
    a = form_image(X, meta, generator=torch.Generator().manual_seed(1), source_follower_e=sf).image
    b = form_image(X, meta, generator=torch.Generator().manual_seed(1)).image
    assert torch.equal(a, b)


# ---------------------------------------------------------------------------------------------- apply_psf image dtype
@pytest.mark.parametrize("dtype", [torch.int64, torch.uint8, torch.bool, torch.int32])
def test_apply_psf_refuses_non_floating_images(dtype):
    """An integer image was convolved with the kernel cast to its dtype (every tap 0): all zeros came back."""
    d = defocus_psf(torch.tensor([5.0, 3.0]), 7)
    with pytest.raises(TypeError, match=r"^image must be a floating tensor .*convert integer DN images with x.float\(\) / 255"):
        apply_psf(torch.ones(2, 1, 8, 8, dtype=dtype), d)


def test_apply_psf_refuses_images_that_are_not_4d():
    with pytest.raises(ValueError, match=r"image must have shape B×C×H×W \(4 dims\), got \(1, 8, 8\)"):
        apply_psf(torch.ones(1, 8, 8), defocus_psf(torch.tensor([3.0]), 5))
    with pytest.raises(TypeError, match=r"image must be a torch.Tensor"):
        apply_psf(np.ones((1, 1, 8, 8)), defocus_psf(torch.tensor([3.0]), 5))


# ---------------------------------------------------------------------------------------------- even kernels
@pytest.mark.parametrize("k", [2, 4, 40])
@pytest.mark.parametrize("arg", ["defocus_psf", "motion_psf", "apply_psf"])
def test_even_kernels_are_refused(k, arg):
    """An even kernel has no centre pixel: the image came back shifted by half a pixel."""
    img = torch.zeros(1, 1, 9, 9)
    img[0, 0, 4, 4] = 1
    psf = torch.full((1, k, k), 1.0 / k**2)
    name = "psf" if arg == "apply_psf" else arg
    with pytest.raises(ValueError, match=rf"^{name} must have an odd size k \(shape \(B, k, k\)\), got k = {k}"):
        if arg == "apply_psf":
            apply_psf(img, psf)
        else:
            form_image(img, None, sources=(), **{arg: psf})


def test_odd_kernels_still_keep_an_impulse_in_place():
    img = torch.zeros(1, 1, 9, 9, dtype=torch.float64)
    img[0, 0, 4, 4] = 1
    r = form_image(img, None, defocus_psf=torch.full((1, 3, 3), 1 / 9, dtype=torch.float64), sources=()).image[0, 0]
    ys, xs = torch.meshgrid(torch.arange(9.0, dtype=torch.float64), torch.arange(9.0, dtype=torch.float64), indexing="ij")
    assert float((r * ys).sum()) == pytest.approx(4.0) and float((r * xs).sum()) == pytest.approx(4.0)


# ---------------------------------------------------------------------------------------------- gaussian
@pytest.mark.parametrize("sigma, k, need", [(64.0, 3, "a σ of at most 63.5 px"), (2.0, 7, "kernel_size ≥ 9"),
                                            (2.01, 9, "kernel_size ≥ 11"), (7.6, 31, "kernel_size ≥ 33"),
                                            (1.0, 3, "kernel_size ≥ 5")])
def test_gaussian_psf_refuses_a_sigma_its_kernel_cannot_hold(sigma, k, need):
    """σ = 64 px in 3 px came back as a 3×3 box (MTF 0.97 where the Gaussian's is 1e-88)."""
    with pytest.raises(ValueError, match=rf"sigma_px = {sigma:g} px does not fit kernel_size = {k}: .*use {need}"):
        gaussian_psf(torch.tensor([sigma]), k)


@pytest.mark.parametrize("sigma, k", [(2.0, 9), (0.5, 3), (7.25, 31), (63.5, 255), (0.0, 1), (2.7, 15), (1.5, 9)])
def test_gaussian_psf_accepts_sigma_up_to_a_quarter_of_the_kernel(sigma, k):
    p = gaussian_psf(torch.tensor([sigma], dtype=torch.float64), k, torch.tensor([0.5, -0.5], dtype=torch.float64))
    assert p.shape == (1, k, k) and float(p.sum()) == pytest.approx(1.0)


@pytest.mark.parametrize("sigma", [-1.0, math.nan, torch.tensor([0.5, -0.1])])
def test_gaussian_mtf_refuses_negative_sigma(sigma):
    with pytest.raises(ValueError, match="sigma_px"):
        gaussian_mtf(sigma, 0.1)


def test_gaussian_mtf_of_valid_sigma_unchanged():
    assert gaussian_mtf(1.0, 0.1) == pytest.approx(math.exp(-2 * math.pi**2 * 0.01))
    assert gaussian_mtf(0.0, 0.3) == 1.0


# ---------------------------------------------------------------------------------------------- quantize flag
@pytest.mark.parametrize("flag", ["no", 1, 0, None, torch.tensor(True)])
def test_form_image_quantize_must_be_a_bool(flag):
    with pytest.raises(TypeError, match=r"^quantize = .* must be True or False"):
        form_image(X, CameraMetadata.preset("ICX285"), quantize=flag)


def test_form_image_quantize_accepts_numpy_bools():
    meta = CameraMetadata.preset("ICX285")
    a = form_image(X, meta, generator=torch.Generator().manual_seed(0), quantize=np.bool_(True)).image
    b = form_image(X, meta, generator=torch.Generator().manual_seed(0), quantize=True).image
    assert torch.equal(a, b)


# ---------------------------------------------------------------------------------------------- poisson_exact_below
@pytest.mark.parametrize("value, exc", [(-1.0, ValueError), (math.nan, ValueError), (0.0, ValueError), (9.99, ValueError),
                                        ("1e3", TypeError), (True, TypeError), (None, TypeError)])
def test_poisson_exact_below_is_checked(value, exc):
    """−1 switched every draw to N(λ, λ): non-integer and negative electron counts at 8 e⁻."""
    with pytest.raises(exc, match="poisson_exact_below"):
        form_image(X, CameraMetadata.preset("ICX285"), poisson_exact_below=value)
    rate = torch.full((4,), 5.0)
    with pytest.raises(exc, match="exact_below"):
        sample_poisson(rate, exact_below=value)
    with pytest.raises(exc, match="exact_below"):
        sample_poisson_per_sample(rate, (4, 8), exact_below=value)
    with pytest.raises(exc, match="exact_below"):
        poisson_z_table(rate.double(), exact_below=value)


@pytest.mark.parametrize("value", [10.0, 1e3, 1000, math.inf])
def test_poisson_exact_below_accepts_ten_electrons_and_more(value):
    dark = torch.full((1, 1, 32, 32), 1 / 255.0)
    m = CameraMetadata.preset("ICX285", full_well_e=2000.0)
    r = form_image(dark, m, sources=("photon",), generator=torch.Generator().manual_seed(0), poisson_exact_below=value)
    e = r.image.double() * 2000.0  # 7.8 e⁻ per pixel: drawn exactly, whole electrons
    assert bool(((e - e.round()).abs() < 1e-2).all())


# ---------------------------------------------------------------------------------------------- metadata
@pytest.mark.parametrize("field", ["gain_db", "exposure_s", "temperature_c"])
def test_bool_tensors_are_no_metadata_numbers(field):
    with pytest.raises(TypeError, match=rf"camera metadata {field} must hold numbers .*got a bool tensor"):
        CameraMetadata.preset("ICX285", **{field: torch.tensor([True])})


def test_is_cmos_takes_a_bool_tensor():
    assert CameraMetadata.preset("ICX285", is_cmos=torch.tensor([True])).is_cmos.tolist() == [1.0]


@pytest.mark.parametrize("call, exc, match", [
    (lambda: CameraMetadata.preset("ICX285", batch_size=-1), ValueError, r"batch_size = -1 must be an integer ≥ 0"),
    (lambda: CameraMetadata.preset("ICX285", batch_size=2.5), TypeError, r"batch_size must be an integer ≥ 0, got float"),
    (lambda: CameraMetadata.preset("ICX285", batch_size=True), TypeError, r"batch_size must be an integer ≥ 0, got bool"),
    (lambda: CameraMetadata.sample(2.5), TypeError, r"batch_size must be an integer ≥ 1, got float 2.5"),
    (lambda: CameraMetadata.sample(True), TypeError, r"batch_size must be an integer ≥ 1, got bool True"),
    (lambda: CameraMetadata.sample(0), ValueError, r"batch_size = 0 must be an integer ≥ 1"),
    (lambda: CameraMetadata.preset("ICX285").expand(-3), ValueError, r"batch_size = -3 must be an integer ≥ 0"),
    (lambda: CameraMetadata.preset("ICX285").expand(2.0), TypeError, r"batch_size must be an integer ≥ 0, got float"),
    (lambda: CameraMetadata.preset("ICX285", temperature_c=10**400), ValueError,
     r"camera metadata temperature_c = 1000.*… is out of the allowed range \[0, 80\] °C"),
])
def test_metadata_batch_sizes_and_huge_ints(call, exc, match):
    with pytest.raises(exc, match=match):
        call()


def test_metadata_batch_sizes_of_integer_types_work():
    assert CameraMetadata.preset("ICX285", batch_size=np.int64(3)).batch_size == 3
    assert CameraMetadata.sample(torch.tensor(2)).batch_size == 2
    assert CameraMetadata.preset("ICX285").expand(0).batch_size == 0


# ---------------------------------------------------------------------------------------------- sampling ranges
@pytest.mark.parametrize("ranges, exc, match", [
    ({"gain_db": ("a", "b")}, TypeError, r"range for gain_db must be a \(low, high\) pair of numbers"),
    ({"gain_db": (True, True)}, TypeError, r"range for gain_db must be a \(low, high\) pair of numbers.*bool"),
    ({"gain_db": (1, 2, 3)}, ValueError, r"range for gain_db must be a \(low, high\) pair, got 3 values"),
    ({"gain_db": None}, TypeError, r"range for gain_db must be a \(low, high\) pair of numbers, got NoneType"),
    ({"gain_db": (math.nan, 3.0)}, ValueError, r"range for gain_db .* must hold finite numbers"),
    ({"gain_db": (0.0, 24.000001)}, ValueError, r"range for gain_db = \(0.0, 24.000001\) must satisfy"),
    ("gain_db", TypeError, r"ranges must be a mapping of field: \(low, high\)"),
])
def test_sample_checks_each_range(ranges, exc, match):
    with pytest.raises(exc, match=match):
        CameraMetadata.sample(2, ranges=ranges)


def test_sample_takes_ranges_of_numbers_arrays_and_a_single_value():
    g = torch.Generator().manual_seed(0)
    m = CameraMetadata.sample(3, g, ranges={"gain_db": 6, "exposure_s": np.array([0.01, 0.02]),
                                            "temperature_c": torch.tensor([10.0, 20.0])})
    assert m.gain_db.tolist() == [6.0] * 3 and bool(((m.temperature_c >= 10) & (m.temperature_c <= 20)).all())


# ---------------------------------------------------------------------------------------------- photon shot noise
@pytest.mark.parametrize("fn", [photon_shot_sigma_dn, photo_electrons, photon_shot_sigma_patch_dn])
def test_photon_shot_noise_names_both_batch_sizes(fn):
    with pytest.raises(ValueError, match=r"metadata batch 2 does not match the intensity batch"):
        fn(torch.full((3, 1, 2, 2), 0.5), CameraMetadata.preset("ICX285", batch_size=2))
    assert fn(torch.full((3, 1, 2, 2), 0.5), CameraMetadata.preset("ICX285")).shape[0] == 3  # batch 1 broadcasts


# ---------------------------------------------------------------------------------------------- PSF helpers
@pytest.mark.parametrize("shift", [torch.zeros(3), torch.zeros(1), torch.zeros(2, 3)])
def test_gaussian_shift_of_a_wrong_shape_is_named(shift):
    with pytest.raises(ValueError, match=r"shift_px must have shape \(B, 2\) or \(2,\)"):
        gaussian_psf(torch.tensor([1.0]), 9, shift)


@pytest.mark.parametrize("call", [
    lambda g: sample_tiny_psf(2, 3, 3, generator=g),
    lambda g: form_image(X, CameraMetadata.preset("ICX285"), generator=g),
    lambda g: sample_random_walk(2, 8, generator=g),
    lambda g: sample_poisson(torch.full((4,), 5.0), g),
])
@pytest.mark.parametrize("generator", ["x", 3, np.random.default_rng(0)])
def test_generators_must_be_torch_generators(call, generator):
    with pytest.raises(TypeError, match=r"generator must be a torch.Generator or None, got"):
        call(generator)


# ---------------------------------------------------------------------------------------------- messages
@pytest.mark.parametrize("call, shown", [
    (lambda: defocus_psf(torch.tensor([5.000001]), 5), "diameter_px = 5.000001 px"),
    (lambda: defocus_psf(torch.tensor([5.000001], dtype=torch.float64), 5), "diameter_px = 5.000001 px"),
    (lambda: linear_motion_psf(torch.tensor([7.000001]), torch.tensor([0.0]), 7), "= 7.000001 px"),
    (lambda: CameraMetadata.preset("ICX285", is_cmos=0.9999999), "is_cmos[0] = 0.9999999 is"),
    (lambda: CameraMetadata.preset("ICX285", exposure_s=0.2000003), "exposure_s[0] = 0.2000003 s"),
    (lambda: CameraMetadata.preset("ICX285", exposure_s=0.3), "exposure_s[0] = 0.3 s"),  # short where it is clear
    (lambda: SensorConstants(cds_sample_time_s=1.0000001e-4), "cds_sample_time_s = 0.00010000001 s"),
])
def test_out_of_range_values_are_not_printed_as_the_bound(call, shown):
    with pytest.raises(ValueError) as info:
        call()
    assert shown in str(info.value)


# ---------------------------------------------------------------------------------------------- counts and tiny paths
def test_numpy_integers_count_as_ints():
    d = torch.tensor([5.0])
    assert torch.equal(polygon_psf(d, np.int64(6), 7, supersample=np.int32(8)), polygon_psf(d, 6, 7))
    assert torch.equal(spherical_psf(d, torch.tensor([0.2]), 7, n_rings=np.int64(16)),
                       spherical_psf(d, torch.tensor([0.2]), 7, n_rings=16))
    g = torch.Generator().manual_seed(1)
    t = sample_tiny_psf(np.int64(2), np.int64(3), 5, generator=g)
    assert torch.equal(t, sample_tiny_psf(2, 3, 5, generator=torch.Generator().manual_seed(1)))
    assert sample_random_walk(np.int64(2), np.int64(8)).shape == (2, 9, 2)
    with pytest.raises(TypeError, match="n_blades must be an int, got bool"):
        polygon_psf(d, True, 7)
    with pytest.raises(TypeError, match="n_rings must be an int, got float"):
        spherical_psf(d, torch.tensor([0.2]), 7, n_rings=16.0)


@pytest.mark.parametrize("scale", [1e-20, 1e-13, 1.0, 1e12])
def test_a_trajectory_in_any_unit_gives_the_same_kernel(scale):
    path = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [1.0, 2.0]]], dtype=torch.float64)
    ref = trajectory_psf(path, torch.tensor([4.0], dtype=torch.float64), 7)
    torch.testing.assert_close(trajectory_psf(path * scale, torch.tensor([4.0], dtype=torch.float64), 7), ref)


@pytest.mark.parametrize("path", [torch.zeros(1, 3, 2), torch.full((1, 3, 2), 1e6), torch.full((1, 3, 2), 1e-30)])
def test_a_trajectory_whose_vertices_coincide_is_refused(path):
    with pytest.raises(ValueError, match="non-zero arc length"):
        trajectory_psf(path, torch.tensor([2.0]), 9)
