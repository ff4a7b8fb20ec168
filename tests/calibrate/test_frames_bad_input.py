"""``camhealth.calibrate.frames`` on input that broke it: 8-bit data held in half precision, JPEG image files,
malformed in-memory frames, absurd exposures, values outside [0, 1] and files that cannot be read."""

import re

import numpy as np
import pytest
import torch
from PIL import Image

from camhealth.calibrate import FrameSet, Protocol, calibrate, parse_set_name, read_manifest, sets_from_paths, synthetic_sets
from camhealth.calibrate import frames as frames_module
from camhealth.calibrate.frames import load_frames, load_frames_with_depth
from camhealth.calibrate.statistics import quantisation_step
from camhealth.physics import CameraMetadata

SMALL = Protocol(dark_temperatures_c=(40.0, 75.0), dark_exposures_s=(0.1, 0.2), flat_levels=(0.1, 0.3, 0.6), flat_gains_db=(0.0, 12.0))
DATASHEET = ("pixel_size_um", "pixel_clock_hz", "sense_node_gain_v_per_e", "is_cmos")


def _codes(seed=0, shape=(5, 16, 16), level=60.0, sigma=6.0):
    rng = np.random.default_rng(seed)
    return np.clip(np.rint(level + sigma * rng.standard_normal(shape)), 0, 255)


# --------------------------------------------------------------------------------------- half precision
HALF = {
    "torch float16": lambda a: torch.from_numpy(a).half(),
    "torch bfloat16": lambda a: torch.from_numpy(a).bfloat16(),
    "numpy float16": lambda a: a.astype(np.float16),
    "list of torch float16 frames": lambda a: [torch.from_numpy(f).half() for f in a],
    "list of torch bfloat16 1×H×W frames": lambda a: [torch.from_numpy(f[None]).bfloat16() for f in a],
}


@pytest.mark.parametrize("level", [20.0, 200.0])
@pytest.mark.parametrize("held", list(HALF))
def test_8_bit_frames_held_in_half_precision_are_read_as_whole_dn(held, level):
    """k/255 in float16 moves by up to 0.12 DN, in bfloat16 by up to 0.25 DN: the values left the 8-bit grid, the
    step came out 0 ("continuous") and the clipped darks were fitted as continuous values (dark current +86 %)."""
    codes = _codes(level=level)
    x, depth = load_frames_with_depth(FrameSet("dark", 0.1, frames=HALF[held]((codes / 255).astype(np.float32))))
    assert np.array_equal(x, (codes / 255).astype(np.float32))
    assert depth.depth is not None and depth.depth.bits == 8
    assert quantisation_step(x) == pytest.approx(1.0)


def test_a_float16_tiff_of_8_bit_data_is_read_as_whole_dn(tmp_path):
    import tifffile

    codes = _codes(1)
    for i, c in enumerate(codes):
        tifffile.imwrite(tmp_path / f"{i:03d}.tif", (c / 255).astype(np.float16))
    x, depth = load_frames_with_depth(FrameSet("dark", 0.1, paths=[tmp_path]))
    assert np.array_equal(x, (codes / 255).astype(np.float32))
    assert depth.depth.bits == 8 and depth.depth.source == "float16"


@pytest.mark.parametrize("data", ["continuous", "16-bit"])
def test_bfloat16_frames_that_are_not_8_bit_data_are_refused_naming_the_type(data):
    """bfloat16 holds 8 significant bits: its rounding (±0.5 DN above 128 DN) is noise the calibration would measure."""
    rng = np.random.default_rng(2)
    x = np.clip(0.5 + 0.02 * rng.standard_normal((5, 16, 16)), 0, 1)
    if data == "16-bit":
        x = np.rint(x * 65535) / 65535
    fs = FrameSet("flat", 0.01, frames=torch.from_numpy(x).bfloat16(), name="bf")
    with pytest.raises(ValueError, match=r"^flat set 'bf' .*: its frames are bfloat16, which holds 8 significant bits.*give the "
                                         r"frames as float32"):
        load_frames(fs)


@pytest.mark.parametrize("held", ["torch float16", "torch bfloat16"])
def test_8_bit_sets_in_half_precision_calibrate_as_in_float32(held):
    true = CameraMetadata.preset("ICX285")
    base = synthetic_sets(true, SMALL, frames=4, size=24, seed=3)
    sheet = {f: float(getattr(true, f)) for f in DATASHEET}
    f32 = [FrameSet(s.kind, s.exposure_s, s.gain_db, s.temperature_c, frames=(np.rint(s.frames * 255) / 255).astype(np.float32),
                    name=s.name) for s in base]
    half = [FrameSet(s.kind, s.exposure_s, s.gain_db, s.temperature_c, frames=HALF[held](s.frames), name=s.name) for s in f32]
    a, b = calibrate(f32, camera=sheet), calibrate(half, camera=sheet)
    for f in ("full_well_e", "white_noise_v_per_rthz", "dark_fom_na_per_cm2"):
        assert b.fields[f].value == a.fields[f].value, f
    assert all(r.step_dn == pytest.approx(1.0) for r in b.sets)


# --------------------------------------------------------------------------------------------------- JPEG
def _jpeg_set(folder, how):
    folder.mkdir()
    for i, c in enumerate(_codes(3)):
        im = Image.fromarray(c.astype(np.uint8))
        if how == "jpg":
            im.save(folder / f"{i:03d}.jpg", quality=100)
        elif how == "jpeg":
            im.save(folder / f"{i:03d}.jpeg", quality=95)
        elif how == "JPEG named .png":
            im.save(folder / f"{i:03d}.png", format="JPEG", quality=100)
        else:  # a TIFF with JPEG compression
            im.save(folder / f"{i:03d}.tif", compression="jpeg")
    return folder


@pytest.mark.parametrize("how, fmt", [("jpg", "JPEG"), ("jpeg", "JPEG"), ("JPEG named .png", r"JPEG \(under the extension '\.png'\)"),
                                      ("tiff", "TIFF with JPEG compression")])
def test_jpeg_frames_are_refused_like_lossy_video_naming_the_set_and_the_file(how, fmt, tmp_path):
    """JPEG at quality 95 gave a read noise 56 % low and a dark current 72 % low, without a word about JPEG."""
    folder = _jpeg_set(tmp_path / "dark_100ms_12dB_40C", how)
    with pytest.raises(ValueError, match=rf"^dark set '.*dark_100ms_12dB_40C' .*: image .*000\.\w+ is {fmt}, which is lossy: lossy "
                                         r"compression removes part of the temporal noise .*record the set losslessly"):
        load_frames(FrameSet("dark", 0.1, 12.0, 40.0, paths=[folder]))


@pytest.mark.parametrize("suffix", [".jpg", ".jpeg"])
def test_a_jpeg_file_given_by_name_is_refused_before_any_frame_is_read(suffix, tmp_path):
    p = tmp_path / f"dark_100ms_12dB_40C_0001{suffix}"
    Image.fromarray(_codes(4)[0].astype(np.uint8)).save(p, format="JPEG")
    with pytest.raises(ValueError, match=rf"image .*0001{re.escape(suffix)} is JPEG, which is lossy"):
        sets_from_paths([p])


# ------------------------------------------------------------------------------------- in-memory frames
@pytest.mark.parametrize("frames, message", [
    ([np.zeros((8, 8))] * 2 + [np.zeros((2, 8, 8))] + [np.zeros((8, 8))] * 2, r"frame 2 of its list has shape 2×8×8"),
    ("abc", r"its frames are a str \('abc'\)"),
    ({"a": 1}, r"its frames are a dict \(\{'a': 1\}\)"),
    (np.full((4, 8, 8), 0.5 + 0.5j, np.complex64), r"its frames are complex \(complex64\)"),
    (torch.full((4, 8, 8), 0.5 + 0.5j), r"its frames are complex \(complex64\)"),
    (np.full((4, 8, 8), "x"), r"its frames are not numbers \(dtype <U1"),
    ([np.zeros((8, 8)), "abc", np.zeros((8, 8))], r"frame 1 of its list is a str \('abc'\)"),
])
def test_malformed_in_memory_frames_are_refused_naming_the_set_and_what_they_are(frames, message):
    """A list mixing shapes, a string or a dict raised numpy's or Python's own errors naming no set; complex frames lost
    their imaginary part with only a ComplexWarning."""
    with pytest.raises(ValueError, match=rf"^dark set 'd' \(0\.1 s, 0 dB, 25 °C\): {message}"):
        load_frames(FrameSet("dark", 0.1, frames=frames, name="d"))


def test_a_list_mixing_hxw_and_1xhxw_frames_is_read_as_nxhxw():
    f = (_codes(5) / 255).astype(np.float32)
    x = load_frames(FrameSet("dark", 0.1, frames=[f[0], f[1][None], f[2], f[3][None], f[4]]))
    assert np.array_equal(x, f)


@pytest.mark.parametrize("change, message", [
    (lambda x: np.where(np.arange(x.size).reshape(x.shape) == 7, np.nan, x), r"got 1 NaN or infinite value\(s\) of 1280 and values from 0\.\d+ to 0\.\d+$"),
    (lambda x: np.where(np.arange(x.size).reshape(x.shape) == 7, 1.5, x), r"got values from 0\.\d+ to 1\.5$"),
    (lambda x: -x, r"got values from -0\.\d+ to -0\.\d+$"),
    (lambda x: np.rint(x * 255).astype(np.uint8), r"got values from \d+ to \d+; uint8 frames are integers, i\.e\. DN: divide them by "
                                                    r"2\^bits − 1 \(x / 255"),
    (lambda x: torch.from_numpy(np.rint(x * 4095).astype(np.int16)), r"int16 frames are integers, i\.e\. DN: divide"),
])
def test_in_memory_values_outside_0_1_are_refused_naming_the_values(change, message):
    """Every such set got one message, "frame values must be finite and in [0, 1] (DN/255)", naming neither the values
    nor how many, nor that integers are DN."""
    x = (_codes(6, level=60.0) / 255).astype(np.float32)
    with pytest.raises(ValueError, match=rf"^flat set 'f' .*: in-memory frame values must be finite and in \[0, 1\] .*{message}"):
        load_frames(FrameSet("flat", 0.01, frames=change(x), name="f"))


# ------------------------------------------------------------------------------------------ exposures
@pytest.mark.parametrize("exposure_s", [3600.5, 1e6, 1e150, 1e300])
def test_an_exposure_beyond_an_hour_is_refused_naming_the_value_and_the_range(exposure_s):
    """1e150 s was calibrated (exit 0) and 1e160 s crashed with a bare OverflowError."""
    with pytest.raises(ValueError, match=rf"^set f: exposure_s = {re.escape(f'{exposure_s:g}')} s is outside \(0, 3600\] s"):
        FrameSet("flat", exposure_s, frames=np.zeros((4, 8, 8), np.float32), name="f")


@pytest.mark.parametrize("token, shown", [("4000s", "4000"), ("1e9s", "1e+09"), ("5000000ms", "5000")])
def test_an_exposure_token_beyond_an_hour_is_refused_naming_it(token, shown):
    with pytest.raises(ValueError, match=rf"token '{token}' gives an exposure of {re.escape(shown)} s, outside \(0, 3600\] s"):
        parse_set_name(f"dark_{token}_12dB_40C")


# ------------------------------------------------------------------------------------------ reading files
@pytest.mark.parametrize("error", [PermissionError(13, "Permission denied"), OSError(5, "Input/output error")])
def test_a_frame_file_that_cannot_be_read_is_named_with_its_set_and_manifest(error, tmp_path, monkeypatch):
    """A PermissionError from the reader reached the user as it was, naming neither the set nor the manifest."""
    folder = tmp_path / "darks"
    folder.mkdir()
    for i, c in enumerate(_codes(7)):
        Image.fromarray(c.astype(np.uint8)).save(folder / f"{i:03d}.png")
    (tmp_path / "m.yaml").write_text("sets:\n  - {kind: dark, path: darks, exposure_s: 0.1, gain_db: 0, temperature_c: 25}\n")
    fs = read_manifest(tmp_path / "m.yaml").sets[0]

    def refuse(p, bit_depth):
        raise error

    monkeypatch.setattr(frames_module, "_read_frame", refuse)
    with pytest.raises(ValueError, match=rf"^dark set 'darks' .* \(manifest .*m\.yaml, set 1\): cannot read .*000\.png: "
                                         rf"{error.strerror}$"):
        load_frames(fs)
