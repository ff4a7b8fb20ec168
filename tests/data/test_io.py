"""read_image / to_gray: bit depths, colour, errors."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import tifffile
import torch
from PIL import Image

from camhealth.data import BT601_WEIGHTS, IMAGE_EXTENSIONS, read_image, to_gray
from camhealth.data.io import read_image_scaled


def _bt601(rgb: np.ndarray) -> np.ndarray:
    return rgb[..., 0] * 0.299 + rgb[..., 1] * 0.587 + rgb[..., 2] * 0.114


def test_16bit_png_full_scale_reads_as_one(tmp_path):
    a = np.array([[65535, 32768], [0, 1]], dtype=np.uint16)
    p = tmp_path / "g16.png"
    Image.fromarray(a).save(p)
    x = read_image(p)
    assert x.shape == (1, 2, 2) and x.dtype == torch.float32
    assert x[0, 0, 0].item() == 1.0
    assert x[0, 0, 1].item() == pytest.approx(32768 / 65535, abs=1e-7)
    assert x[0, 1, 0].item() == 0.0


def test_8bit_gray_png_and_bmp(tmp_path):
    a = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    for ext in (".png", ".bmp"):
        p = tmp_path / f"g8{ext}"
        Image.fromarray(a).save(p)
        x = read_image(p)
        assert torch.equal(x[0], torch.from_numpy(a.astype(np.float32) / 255))


def test_16bit_tiff_gray_and_rgb(tmp_path):
    g = np.full((3, 5), 65535, dtype=np.uint16)
    tifffile.imwrite(tmp_path / "g.tif", g)
    assert read_image(tmp_path / "g.tif").max().item() == 1.0
    rgb = np.zeros((3, 5, 3), dtype=np.uint16)
    rgb[..., 1] = 65535
    tifffile.imwrite(tmp_path / "c.tiff", rgb, photometric="rgb")
    assert read_image(tmp_path / "c.tiff")[0, 0, 0].item() == pytest.approx(0.587, abs=1e-6)


def test_colour_png_uses_bt601_and_drops_alpha(tmp_path):
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (6, 7, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(tmp_path / "c.png")
    expected = _bt601(rgb.astype(np.float64) / 255)
    assert np.allclose(read_image(tmp_path / "c.png")[0].numpy(), expected, atol=1e-6)
    rgba = np.dstack([rgb, np.full((6, 7), 10, np.uint8)])  # nearly transparent: alpha must be ignored
    Image.fromarray(rgba).save(tmp_path / "ca.png")
    assert np.allclose(read_image(tmp_path / "ca.png")[0].numpy(), expected, atol=1e-6)


def test_16bit_colour_png_keeps_16bit_precision(tmp_path):
    cv2 = pytest.importorskip("cv2")
    rgb = np.array([[[1000, 30000, 65535], [65535, 65535, 65535]]], dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "c16.png"), rgb[..., ::-1])  # cv2 writes BGR
    x = read_image(tmp_path / "c16.png")
    assert np.allclose(x[0].numpy(), _bt601(rgb / 65535.0), atol=1e-6)
    assert x[0, 0, 1].item() == 1.0


def test_jpeg_colour_reads_close_to_bt601(tmp_path):
    Image.fromarray(np.full((8, 8, 3), (200, 100, 50), np.uint8)).save(tmp_path / "c.jpg", quality=100)
    x = read_image(tmp_path / "c.jpg")
    assert x.shape == (1, 8, 8)
    assert x.mean().item() == pytest.approx((0.299 * 200 + 0.587 * 100 + 0.114 * 50) / 255, abs=3 / 255)


def test_palette_png(tmp_path):
    Image.fromarray(np.full((4, 4), 77, np.uint8)).convert("P").save(tmp_path / "p.png")
    assert read_image(tmp_path / "p.png")[0, 0, 0].item() == pytest.approx(77 / 255, abs=1e-6)


def test_missing_file_names_path(tmp_path):
    p = tmp_path / "nope.png"
    with pytest.raises(FileNotFoundError, match="nope.png"):
        read_image(p)


@pytest.mark.parametrize("name", ["bad.png", "bad.jpg", "bad.tif", "bad.bmp"])
def test_corrupt_file_is_valueerror_naming_file(tmp_path, name):
    p = tmp_path / name
    p.write_bytes(b"this is not an image" * 5)
    with pytest.raises(ValueError, match=name.replace(".", r"\.")):
        read_image(p)


def test_truncated_png_is_valueerror(tmp_path):
    p = tmp_path / "t.png"
    Image.fromarray(np.random.default_rng(1).integers(0, 256, (64, 64), dtype=np.uint8)).save(p)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="t.png"):
        read_image(p)


def test_unsupported_extension_lists_allowed(tmp_path):
    p = tmp_path / "x.gif"
    p.write_bytes(b"GIF89a")
    with pytest.raises(ValueError) as e:
        read_image(p)
    for ext in IMAGE_EXTENSIONS:
        assert ext in str(e.value)


def test_to_gray_numpy_and_torch_agree_with_kornia():
    kornia = pytest.importorskip("kornia")
    rng = np.random.default_rng(2)
    rgb = rng.random((5, 6, 3))
    g = to_gray(rgb)
    assert g.shape == (5, 6) and np.allclose(g, _bt601(rgb))
    assert np.allclose(to_gray(np.dstack([rgb, np.zeros((5, 6))])), g)  # RGBA: alpha dropped
    t = torch.from_numpy(rgb).permute(2, 0, 1).unsqueeze(0).float()  # 1×3×H×W
    tg = to_gray(t)
    assert tg.shape == (1, 1, 5, 6)
    assert torch.allclose(tg, kornia.color.rgb_to_grayscale(t), atol=1e-6)
    assert sum(BT601_WEIGHTS) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="channels"):
        to_gray(torch.zeros(1, 5, 4, 4))


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64, torch.uint8])
def test_to_gray_tensor_weights_dtypes_and_layouts(dtype):
    """Tensors go through Kornia's rgb_to_grayscale: its weights are BT601_WEIGHTS, in every dtype and layout."""
    eye = torch.eye(3).view(3, 3, 1, 1).expand(3, 3, 2, 2)  # sample i: channel i = 1, others 0
    scale = 255 if dtype == torch.uint8 else 1
    g = to_gray((eye * scale).to(dtype))
    want_dtype = torch.float32 if dtype == torch.uint8 else dtype
    assert g.shape == (3, 1, 2, 2) and g.dtype == want_dtype
    tol = {torch.float16: 1e-3, torch.bfloat16: 4e-3}.get(dtype, 1e-6) * scale
    assert torch.allclose(g[:, 0, 0, 0].double(), torch.tensor(BT601_WEIGHTS, dtype=torch.float64) * scale, atol=tol)
    rgba = torch.cat([eye[:1], torch.ones(1, 1, 2, 2)], 1).to(torch.float64)  # alpha dropped, C×H×W too
    assert torch.allclose(to_gray(rgba[0]), torch.full((1, 2, 2), BT601_WEIGHTS[0], dtype=torch.float64))
    assert torch.equal(to_gray(rgba[:, :2]), rgba[:, :1])  # gray + alpha: gray kept


def _png_bytes(width: int, height: int, depth: int, colour_type: int, channels: int) -> bytes:
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    raw = (b"\x00" + b"\x00" * (width * channels * depth // 8)) * height
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


@pytest.mark.parametrize("kind", ["png16rgb", "tif"])
def test_pixel_limit_holds_for_decoders_other_than_pillow(tmp_path, monkeypatch, kind):
    """16-bit colour PNGs (OpenCV) and TIFFs (tifffile) are refused from the header above PIL.Image.MAX_IMAGE_PIXELS."""
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)
    if kind == "png16rgb":
        p = tmp_path / "big.png"
        p.write_bytes(_png_bytes(64, 32, 16, 2, 3))
    else:
        p = tmp_path / "big.tif"
        tifffile.imwrite(p, np.zeros((32, 64), np.uint8), compression="zlib")
    with pytest.raises(ValueError, match=r"big\.(png|tif).*64×32 = 2048 pixels.*1000"):
        read_image(p)
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 2048)
    assert read_image(p, bit_depth=16 if kind == "png16rgb" else "auto").shape == (1, 32, 64)


def test_palette_tiff_reads_like_the_same_palette_png(tmp_path):
    """Palette TIFF colours are 16-bit full scale: no bit-depth guess from the largest colour."""
    cmap = np.zeros((3, 256), np.uint16)
    cmap[:, 1] = 48 * 257
    idx = np.array([[0, 1]], np.uint8)
    tifffile.imwrite(tmp_path / "p.tif", idx, photometric="palette", colormap=cmap)
    im = Image.fromarray(idx, "P")
    im.putpalette([0, 0, 0, 48, 48, 48] + [0] * 750)
    im.save(tmp_path / "p.png")
    x_png = read_image(tmp_path / "p.png")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "guessed from the largest value" warning
        x_tif = read_image(tmp_path / "p.tif")
    assert x_tif[0, 0, 1].item() == pytest.approx(48 / 255, abs=1e-6)
    assert torch.allclose(x_tif, x_png, atol=1e-6)


def test_one_bit_miniswhite_tiff_is_inverted_like_8_bit(tmp_path):
    a = np.zeros((2, 2), bool)
    a[0, 0] = True  # a set sample is black in MINISWHITE
    tifffile.imwrite(tmp_path / "mw1.tif", a, photometric="miniswhite")
    tifffile.imwrite(tmp_path / "mw8.tif", a.astype(np.uint8) * 255, photometric="miniswhite")
    x1 = read_image(tmp_path / "mw1.tif")
    assert x1[0].tolist() == [[0.0, 1.0], [1.0, 1.0]]
    assert torch.equal(x1, read_image(tmp_path / "mw8.tif"))


def test_fifo_is_refused_without_opening_it(tmp_path):
    import os

    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs on this platform")
    import threading
    import time

    p = tmp_path / "pipe.png"
    os.mkfifo(p)  # opening it for reading blocks until a writer comes

    def unblock_readers():  # so that code that does open the FIFO fails the test instead of hanging it
        for _ in range(200):
            try:
                os.close(os.open(p, os.O_WRONLY | os.O_NONBLOCK))  # ENXIO while no reader waits
            except OSError:
                pass
            time.sleep(0.02)

    threading.Thread(target=unblock_readers, daemon=True).start()
    with pytest.raises(ValueError, match=r"pipe\.png.*not a regular file"):
        read_image(p)


# ------------------------------------------------------------------ PNG sBIT as the PNG specification writes it
def _png16_sbit(path, values: np.ndarray, sbit: int):
    """A 16-bit gray PNG of ``values`` (stored as they are) with an ``sBIT`` chunk before the image data."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    h, w = values.shape
    raw = b"".join(b"\x00" + values[i].astype(">u2").tobytes() for i in range(h))
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0))
    png += chunk(b"sBIT", bytes([sbit])) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")
    path.write_bytes(png)
    return path


def _spec_scale(codes: np.ndarray, bits: int, replicate: bool) -> np.ndarray:
    """ISO/IEC 15948 §12.5: a ``bits``-bit code scaled up to 16 bits by left shift, optionally with bit replication."""
    c = codes.astype(np.uint32)
    out = c << (16 - bits)
    pos = 16 - bits
    while replicate and pos > 0:
        pos -= bits
        out |= (c << pos) if pos >= 0 else (c >> -pos)
    return out.astype(np.uint16)


@pytest.mark.parametrize("bits", [5, 10, 12])
@pytest.mark.parametrize("replicate", [False, True])
@pytest.mark.parametrize("top_fraction", [0.06, 0.25, 1.0])
def test_png_sbit_samples_scaled_up_as_the_png_spec_says_read_as_their_codes(tmp_path, bits, replicate, top_fraction):
    """A dark, a mid and a bright frame of b-bit codes scaled up to 16 bits (sBIT = b): code/(2^b − 1), no warning.
    (A dark 12-bit frame read 16× too bright, a mid one 4× too bright before.)"""
    top = max(1, int(round((2**bits - 1) * top_fraction)))
    codes = np.random.default_rng(bits).integers(0, top + 1, (24, 24))
    codes[0, 0] = top
    p = _png16_sbit(tmp_path / "spec.png", _spec_scale(codes, bits, replicate), bits)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        image, scaling = read_image_scaled(p)
    want = torch.from_numpy((codes / (2**bits - 1)).astype(np.float32))
    assert torch.allclose(image[0], want, atol=1e-7)
    assert (scaling.file_bits, scaling.bits, scaling.source, scaling.shift) == (16, bits, "sBIT", 16 - bits)
    assert f"samples >> {16 - bits}, ÷{2**bits - 1}, from the PNG's sBIT chunk" in scaling.describe()
    given, given_scaling = read_image_scaled(p, bits)  # the declared depth given (as a calibration does): the same
    assert torch.equal(given, image) and given_scaling.bits == bits


def test_png_sbit_samples_in_the_low_bits_are_still_read_as_they_are(tmp_path):
    """A 12-bit camera's values written as they are (low bits) with sBIT 12: value/4095, as before."""
    values = np.random.default_rng(1).integers(0, 4096, (24, 24)).astype(np.uint16)
    p = _png16_sbit(tmp_path / "low.png", values, 12)
    image, scaling = read_image_scaled(p)
    assert torch.allclose(image[0], torch.from_numpy((values / 4095).astype(np.float32)), atol=1e-7)
    assert (scaling.bits, scaling.source, scaling.shift) == (12, "sBIT", 0)
    assert scaling.describe() == "16-bit file read as 12-bit data (÷4095, from the PNG's sBIT chunk)"
    assert torch.equal(read_image(p, bit_depth=12), image)


def test_png_sbit_that_fits_neither_layout_falls_back_to_the_largest_value(tmp_path):
    values = np.random.default_rng(2).integers(0, 60000, (16, 16)).astype(np.uint16)
    values[0, 0] = 60001  # not a multiple of 16, above 4095
    p = _png16_sbit(tmp_path / "odd.png", values, 12)
    _, scaling = read_image_scaled(p)
    assert (scaling.bits, scaling.source, scaling.shift) == (16, "file", 0)


@pytest.mark.parametrize("pixels", [1600, 2500])  # between 1× and 2× the limit (Pillow only warned), and above 2×
@pytest.mark.parametrize("ext", [".png", ".jpg", ".bmp"])
def test_pixel_limit_holds_for_pillow_formats(tmp_path, monkeypatch, pixels, ext):
    """8-bit PNG/JPEG/BMP files above PIL.Image.MAX_IMAGE_PIXELS are refused, as the docstring says."""
    side = int(round(pixels**0.5))
    p = tmp_path / f"big{ext}"
    Image.fromarray(np.zeros((side, side, 3), np.uint8)).save(p)
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no DecompressionBombWarning: a refusal
        with pytest.raises(ValueError, match=rf"cannot read image .*big\{ext}: .*limit of 1000 pixels") as caught:
            read_image(p)
    assert str(pixels) in str(caught.value)
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", pixels)
    assert read_image(p).shape == (1, side, side)


@pytest.mark.parametrize("bad, match", [
    (float("nan"), r"got 1 NaN or infinite value\(s\) of 64"),
    (float("inf"), r"got 1 NaN or infinite value\(s\) of 64"),
    (1.5, r"must be finite and in \[0, 1\], got range \[0.1, 1.5\]"),
])
def test_float_tiff_outside_0_1_names_what_is_wrong(tmp_path, bad, match):
    """A float TIFF with one NaN reported the range of its finite values, which looked valid."""
    arr = np.full((8, 8), 0.1, np.float32)
    arr[3, 4] = bad
    tifffile.imwrite(tmp_path / "f.tif", arr)
    with pytest.raises(ValueError, match=match):
        read_image(tmp_path / "f.tif")
