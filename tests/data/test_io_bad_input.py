"""read_image on files whose layout is legal but unusual: alpha beside 16-bit samples, palette TIFFs with 8-bit colours
× 256, floating-point MINISWHITE, a PNG under another extension, CMYK TIFF."""

from __future__ import annotations

import struct
import warnings
import zlib

import numpy as np
import pytest
import tifffile
import torch
from PIL import Image

from camhealth.data.io import read_image, read_image_scaled

#: 12-bit data (largest value 3780) in a 16-bit container
_DATA12 = (np.arange(64, dtype=np.uint16).reshape(8, 8) * 60)


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def _png16(path, arr: np.ndarray, colour_type: int) -> None:
    """A 16-bit PNG written byte by byte (gray 0, RGB 2, gray + alpha 4, RGBA 6)."""
    h, w = arr.shape[:2]
    raw = b"".join(b"\x00" + arr[i].astype(">u2").tobytes() for i in range(h))
    ihdr = struct.pack(">IIBBBBB", w, h, 16, colour_type, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(raw)) + _chunk(b"IEND", b""))


def _opaque(arr: np.ndarray) -> np.ndarray:
    return np.full(arr.shape[:2] + (1,), 65535, np.uint16)


@pytest.mark.parametrize("kind", ["gray+alpha png", "rgba png", "rgba tiff"])
def test_alpha_does_not_set_the_bit_depth_of_16_bit_data(tmp_path, kind):
    """The same 12-bit data read with and without an opaque alpha channel (65535, dropped): the same image, scaled by
    the colour samples' largest value; ``bit_depth=12`` accepts the file."""
    gray = tmp_path / "gray.png"
    _png16(gray, _DATA12, 0)
    rgb = np.stack([_DATA12] * 3, -1)
    p = tmp_path / ("a.tif" if "tiff" in kind else "a.png")
    if kind == "gray+alpha png":
        _png16(p, np.concatenate([_DATA12[..., None], _opaque(_DATA12)], -1), 4)
    elif kind == "rgba png":
        _png16(p, np.concatenate([rgb, _opaque(rgb)], -1), 6)
    else:
        tifffile.imwrite(p, np.concatenate([rgb, _opaque(rgb)], -1), photometric="rgb", extrasamples=["unassalpha"])
    want, want_scaling = read_image_scaled(gray)
    got, scaling = read_image_scaled(p)
    assert (scaling.bits, scaling.source, scaling.max_value) == (12, "largest value", 3780.0), scaling
    assert want_scaling.bits == 12 and torch.allclose(got, want, atol=1e-6)
    given, _ = read_image_scaled(p, bit_depth=12)
    assert torch.allclose(given, want, atol=1e-6)
    with pytest.raises(ValueError, match=r"as 11-bit data: it holds values up to 3780 \(more than 2047\)"):
        read_image_scaled(p, bit_depth=11)  # the colour samples still set the check


@pytest.mark.parametrize("white_index, grey", [(1, 48), (7, 200)])
def test_pillow_palette_tiff_with_8_bit_colours_times_256_reads_like_the_palette_png(tmp_path, white_index, grey):
    """Pillow writes a palette TIFF's colour map as 8-bit colours × 256 (white = 65280): read as 8-bit colours, white is
    1.0 as in the same palette PNG, not 65280/65535."""
    idx = np.array([[0, white_index, 2]], np.uint8)
    palette = [0] * 768
    palette[3 * white_index: 3 * white_index + 3] = [255, 255, 255]
    palette[6:9] = [grey] * 3
    im = Image.fromarray(idx, "P")
    im.putpalette(palette)
    im.save(tmp_path / "p.png")
    im.save(tmp_path / "p.tif")
    with tifffile.TiffFile(tmp_path / "p.tif") as tif:
        assert int(tif.pages[0].colormap.max()) == 65280  # (the layout this test is about)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        x_tif, scaling = read_image_scaled(tmp_path / "p.tif")
    assert x_tif[0, 0, 1].item() == 1.0 and scaling.bits == 8
    assert x_tif[0, 0, 2].item() == pytest.approx(grey / 255, abs=1e-7)
    assert torch.equal(x_tif, read_image(tmp_path / "p.png"))


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.float16])
@pytest.mark.parametrize("value", [0.0, 0.25, 1.0])
def test_float_miniswhite_tiff_is_inverted(tmp_path, dtype, value):
    """MINISWHITE: 0 is white. A float sample v reads 1 − v, as the integer ones read max − v."""
    p = tmp_path / "mw.tif"
    tifffile.imwrite(p, np.full((4, 4), value, dtype), photometric="miniswhite")
    x = read_image(p)
    assert torch.allclose(x, torch.full((1, 4, 4), 1.0 - value), atol=1e-6), (x[0, 0, 0].item(), 1.0 - value)


@pytest.mark.parametrize("ext", [".jpg", ".jpeg", ".bmp"])
@pytest.mark.parametrize("colour_type", [2, 6])
def test_a_16_bit_colour_png_under_another_extension_keeps_its_16_bits(tmp_path, ext, colour_type):
    """A PNG is recognised by its signature: named .jpg it reads as named .png (16-bit samples, not 8)."""
    rgb = np.stack([_DATA12] * 3, -1)
    arr = rgb if colour_type == 2 else np.concatenate([rgb, _opaque(rgb)], -1)
    _png16(tmp_path / "c.png", arr, colour_type)
    (tmp_path / f"c{ext}").write_bytes((tmp_path / "c.png").read_bytes())
    want, _ = read_image_scaled(tmp_path / "c.png")
    got, scaling = read_image_scaled(tmp_path / f"c{ext}")
    assert scaling.file_bits == 16 and scaling.bits == 12, scaling
    assert torch.equal(got, want) and got.max().item() == pytest.approx(3780 / 4095, abs=1e-6)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_cmyk_tiff_is_refused_naming_cmyk_and_the_supported_interpretations(tmp_path, dtype):
    p = tmp_path / "cmyk.tif"
    tifffile.imwrite(p, np.zeros((4, 4, 4), dtype), photometric="separated")
    with pytest.raises(ValueError, match=r"cmyk\.tif: unsupported TIFF photometric interpretation 5 \(SEPARATED \(CMYK\)\); "
                                         r"supported: 0 \(MINISWHITE\), 1 \(MINISBLACK\), 2 \(RGB\), 3 \(PALETTE\)"):
        read_image(p)


# ------------------------------------------------------------------ a channels-first array
@pytest.mark.parametrize("shape", [(3, 300, 400), (4, 30, 40), (1, 30, 40)])
def test_a_channels_first_array_is_named_as_such_with_the_transpose(shape):
    """A 3×H×W array (a tensor's layout) said only "got C = 400 (shape (3, 300, 400))"."""
    from camhealth.data.io import to_gray
    from camhealth.monitor.api import as_frame

    a = np.random.default_rng(0).random(shape, dtype=np.float32)
    hint = (rf"this looks channels-first \(C×H×W, C = {shape[0]}\): a NumPy image is H×W×C, channels last — "
            r"transpose it with np\.moveaxis\(a, 0, -1\)")
    with pytest.raises(ValueError, match=rf"got C = {shape[-1]} \(shape \({shape[0]}, .*\)\); {hint}"):
        to_gray(a)
    transposed = to_gray(np.moveaxis(a, 0, -1))  # the hint works: as the tensor reads
    np.testing.assert_allclose(transposed, to_gray(torch.from_numpy(a)).numpy()[0], atol=1e-6)
    if shape[0] != 1:  # (as_frame takes a 1×H×W array as H×W)
        with pytest.raises(ValueError, match=hint):
            as_frame(a)


@pytest.mark.parametrize("shape", [(5, 30, 40), (2, 30, 40), (30, 40, 7)])
def test_no_channels_first_hint_where_the_first_axis_is_no_channel_count(shape):
    from camhealth.data.io import to_gray

    with pytest.raises(ValueError, match=r"got C = \d+ \(shape \(\d+, \d+, \d+\)\)$"):
        to_gray(np.zeros(shape, np.float32))
