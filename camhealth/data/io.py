"""Reading images from disk as camhealth tensors, and the one colour → gray rule of the package.

Convention (``docs/data.md``): an image is a float32 tensor ``1×H×W`` (add the batch dimension
yourself) with values in [0, 1] = DN / (2^bits − 1): DN/255 for 8-bit files; a 16-bit file holds data of
``bits`` ≤ 16 significant bits — a 12-bit camera's frames in a 16-bit PNG are DN/4095, not DN/65535 (which
would read 5 DN of noise as 0.3 DN). :func:`read_image` takes ``bit_depth`` (8…16) or detects it
(``"auto"``): from a PNG's significant-bits chunk (``sBIT``) where there is one, else from the largest
value (the fewest of 8, 10, 12, 14, 16 bits that hold it), and warns when it had to guess;
:func:`read_image_scaled` also returns which scaling it used (:class:`ImageScaling`). A PNG with ``sBIT`` = b < 16
is read as the PNG specification writes it (ISO/IEC 15948 §12.5): the b-bit samples scaled up to the full 16-bit
range (shifted left by 16 − b bits, with or without bit replication) are read as (value >> (16 − b)) / (2^b − 1);
a file whose samples do not have that layout but fit in b bits (the low b bits, as some cameras write it) is read
as value / (2^b − 1).
Colour is converted to gray with the ITU-R BT.601 luma weights

    Y = 0.299 R + 0.587 G + 0.114 B

applied to the stored (gamma-encoded) values, exactly as Pillow's ``convert("L")``, OpenCV's
``COLOR_RGB2GRAY`` and ``kornia.color.rgb_to_grayscale`` do, but in floating point (no rounding to 8
bits). An alpha channel is dropped (not composited); a palette image is expanded to its colours first.
"""

from __future__ import annotations

import dataclasses
import errno
import os
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Union

import numpy as np
import torch

__all__ = ["BT601_WEIGHTS", "IMAGE_EXTENSIONS", "ImageScaling", "to_gray", "read_image", "read_image_scaled", "read_samples"]

PathLike = Union[str, "os.PathLike[str]"]

#: ITU-R BT.601 luma weights for (R, G, B); they sum to 1.
BT601_WEIGHTS = (0.299, 0.587, 0.114)

#: File extensions :func:`read_image` accepts (lower case; matching is case-insensitive).
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


def to_gray(image):
    """Convert an image to a single gray channel with the BT.601 luma weights.

    Works on numpy arrays (channels **last**, as images come from files) and on torch tensors
    (channels **first**, Kornia layout). Values are not rescaled: the weights sum to 1, so an input in
    [0, 1] stays in [0, 1] (and 0..255 stays 0..255).

    Channel rules: 1 channel → unchanged; 2 channels → gray + alpha, alpha dropped; 3 channels → RGB;
    4 channels → RGBA, alpha dropped.

    Tensors go through :func:`kornia.color.rgb_to_grayscale` (the same weights). Arrays are weighted in float64
    with NumPy: converting to a tensor and back costs more than the weighting (through Kornia, uint8 frames take
    1.2–1.3× as long, 1280×1024 RGB and 640×480 RGBA, 1 thread: ``python -m camhealth.bench.library_reuse --rows gray``).

    Args:
        image: numpy ``H×W`` or ``H×W×C``; or torch ``C×H×W`` or ``B×C×H×W``; ``C`` in {1, 2, 3, 4}.

    Returns:
        numpy: ``H×W`` floating array (float32 for integer/float32 input, float64 for float64 input).
        torch: same rank as the input with ``C = 1`` (``1×H×W`` or ``B×1×H×W``), floating dtype.
    """
    if isinstance(image, torch.Tensor):
        if image.ndim not in (3, 4):
            raise ValueError(
                f"to_gray expects a torch tensor C×H×W or B×C×H×W (channels first), got shape {tuple(image.shape)}"
            )
        c = image.shape[-3]
        if c not in (1, 2, 3, 4):
            raise ValueError(f"to_gray expects 1, 2, 3 or 4 channels, got C = {c} (shape {tuple(image.shape)})")
        x = image if image.is_floating_point() else image.to(torch.float32)
        if c in (1, 2):
            return x[..., :1, :, :].clone()
        from kornia.color import rgb_to_grayscale

        return rgb_to_grayscale(x[..., :3, :, :])  # BT.601 weights (= BT601_WEIGHTS)

    arr = np.asarray(image)
    if arr.ndim == 2:
        out_dtype = np.float64 if arr.dtype == np.float64 else np.float32
        return arr.astype(out_dtype, copy=True)
    if arr.ndim != 3:
        raise ValueError(f"to_gray expects a numpy array H×W or H×W×C (channels last), got shape {arr.shape}")
    c = arr.shape[-1]
    if c not in (1, 2, 3, 4):
        hint = ""
        if arr.shape[0] in (1, 3, 4):  # C×H×W (gray, RGB, RGBA), as a tensor holds it
            hint = (f"; this looks channels-first (C×H×W, C = {arr.shape[0]}): a NumPy image is H×W×C, channels last — "
                    "transpose it with np.moveaxis(a, 0, -1)")
        raise ValueError(f"to_gray expects 1, 2, 3 or 4 channels (last axis), got C = {c} (shape {arr.shape}){hint}")
    out_dtype = np.float64 if arr.dtype == np.float64 else np.float32
    if c in (1, 2):
        return arr[..., 0].astype(out_dtype, copy=True)
    rgb = arr[..., :3].astype(np.float64)
    gray = rgb[..., 0] * BT601_WEIGHTS[0] + rgb[..., 1] * BT601_WEIGHTS[1] + rgb[..., 2] * BT601_WEIGHTS[2]
    return gray.astype(out_dtype)


@dataclass(frozen=True)
class ImageScaling:
    """How :func:`read_image_scaled` mapped a file's integer values to [0, 1].

    Attributes:
        file_bits: bits per sample of the file (8 or 16); ``None`` for floating-point or 1-bit data.
        bits: significant bits the values were scaled by (value / (2^bits − 1)); ``None`` when not scaled.
        source: where ``bits`` came from: ``"file"`` (8-bit data, or 16-bit data using the full range),
            ``"sBIT"`` (the PNG's significant-bits chunk: the samples are either scaled up to 16 bits as the PNG
            specification says, ``shift`` > 0, or held in the low ``bits`` bits, ``shift`` = 0),
            ``"largest value"`` (a guess from the data),
            ``"sequence"`` (a frame of a sequence read at the larger depth its first frame's guess gave,
            :func:`read_sequence_frame`) or
            ``"given"`` (the caller's ``bit_depth``).
        max_value: the largest value in the file (DN of the file).
        shift: bits the file's samples were shifted right before the division (16 − ``bits`` for a PNG whose
            ``sBIT`` samples are scaled up to 16 bits as the PNG specification says, else 0): the value read is
            (sample >> shift) / (2^bits − 1), an integer code over 2^bits − 1 either way.
        channels: samples per pixel in the file (1 gray, 2 gray + alpha, 3 colour, 4 colour + alpha); the image
            read is gray either way (:func:`to_gray`).
    """

    file_bits: int | None
    bits: int | None
    source: str
    max_value: float
    shift: int = 0
    channels: int = 1

    @property
    def divisor(self) -> float | None:
        return None if self.bits is None else float(2**self.bits - 1)

    def describe(self) -> str:
        if self.bits is None:
            return "floating-point data in [0, 1], not rescaled"
        why = {"given": ", as given", "sBIT": ", from the PNG's sBIT chunk",
               "largest value": f", guessed from the largest value {self.max_value:g}",
               "sequence": ", the sequence's first frame's guess (its own largest value "
                           f"{self.max_value:g} fits)"}.get(self.source, "")
        shifted = f"samples >> {self.shift}, " if self.shift else ""
        return f"{self.file_bits}-bit file read as {self.bits}-bit data ({shifted}÷{2**self.bits - 1}{why})"


_BIT_DEPTHS = (8, 10, 12, 14, 16)


def _is_tiff(path: Path) -> bool:
    return path.suffix.lower() in (".tif", ".tiff")


def _colour_samples(arr: np.ndarray) -> np.ndarray:
    """``arr`` without its alpha channel (gray + alpha, RGBA): the samples the gray image is made of."""
    return arr[..., :-1] if arr.ndim == 3 and arr.shape[-1] in (2, 4) else arr


def _check_bit_depth(bit_depth: int | str) -> int | str:
    if isinstance(bit_depth, str) and bit_depth == "auto":
        return bit_depth
    if isinstance(bit_depth, bool) or not isinstance(bit_depth, (int, np.integer)) or not 1 <= int(bit_depth) <= 16:
        raise ValueError(f"bit_depth = {bit_depth!r} must be 'auto' or an integer number of bits in [1, 16]")
    return int(bit_depth)


def _png_sbit(path: Path) -> int | None:
    """Largest significant-bits value of a PNG's ``sBIT`` chunk (before the image data), or ``None``."""
    try:
        with open(path, "rb") as f:
            if f.read(8) != b"\x89PNG\r\n\x1a\n":
                return None
            while True:
                head = f.read(8)
                if len(head) < 8:
                    return None
                length, kind = struct.unpack(">I4s", head)
                if kind in (b"IDAT", b"IEND"):
                    return None
                data = f.read(length)
                f.seek(4, os.SEEK_CUR)  # CRC
                if kind == b"sBIT" and 1 <= len(data) <= 4:
                    return max(data)
    except OSError:
        return None


def _spec_scaled(arr: np.ndarray, bits: int) -> bool:
    """Whether every 16-bit sample is a ``bits``-bit code scaled up to 16 bits as the PNG specification writes it
    (ISO/IEC 15948 §12.5): shifted left by 16 − ``bits`` (low bits zero), or with bit replication (the low bits
    repeat the code's top bits), one rule for the whole image."""
    if not 1 <= bits < 16 or arr.size == 0:
        return False
    shift = 16 - bits
    v = arr.astype(np.uint32, copy=False)
    code = v >> shift
    if not np.any(v & ((1 << shift) - 1)):  # left shift, low bits zero
        return True
    replicated = code << shift
    pos = shift
    while pos > 0:  # fill the low bits with the code's top bits, again and again (b < 8 repeats it more than once)
        pos -= bits
        replicated |= (code << pos) if pos >= 0 else (code >> -pos)
    return bool(np.array_equal(replicated, v))


def _sbit_scaling(arr: np.ndarray, bits: int, top: int, source: str) -> ImageScaling | None:
    """The scaling of a 16-bit PNG whose ``sBIT`` chunk says ``bits`` (< 16): samples scaled up to 16 bits as the PNG
    specification says → shifted back; samples held in the low ``bits`` bits → as they are; else ``None``."""
    if _spec_scaled(arr, bits):
        return ImageScaling(16, bits, source, float(top), shift=16 - bits)
    if top <= 2**bits - 1:
        return ImageScaling(16, bits, source, float(top))
    return None


def _scaling(arr: np.ndarray, path: Path, bit_depth: int | str) -> ImageScaling:
    """The scaling of integer samples ``arr``: the gray or colour samples only (alpha is dropped, so it sets neither
    the largest value nor the check against ``bit_depth``; the caller passes them without the alpha channel)."""
    file_bits = 8 if arr.dtype == np.uint8 else 16
    top = int(arr.max()) if arr.size else 0
    if bit_depth != "auto" and file_bits == 16 and bit_depth < 16 and not _is_tiff(path):
        # the depth the PNG's sBIT chunk declares, given as the bit depth: its spec-scaled samples are read as codes
        if _png_sbit(path) == bit_depth and _spec_scaled(arr, int(bit_depth)):
            return ImageScaling(16, int(bit_depth), "given", float(top), shift=16 - int(bit_depth))
    if bit_depth != "auto":
        if bit_depth > file_bits:
            raise ValueError(f"cannot read image {path} as {bit_depth}-bit data: the file stores {file_bits}-bit values")
        if top > 2**bit_depth - 1:
            raise ValueError(
                f"cannot read image {path} as {bit_depth}-bit data: it holds values up to {top} "
                f"(more than {2**bit_depth - 1}); give a larger bit_depth or 'auto'"
            )
        return ImageScaling(file_bits, int(bit_depth), "given", float(top))
    if file_bits == 8:
        return ImageScaling(8, 8, "file", float(top))
    sbit = None if _is_tiff(path) else _png_sbit(path)  # (any name: the PNG signature decides)
    if sbit == 16:
        return ImageScaling(16, 16, "file", float(top))
    if sbit is not None and 1 <= sbit < 16:
        scaling = _sbit_scaling(arr, sbit, top, "sBIT")
        if scaling is not None:
            return scaling
    bits = next(b for b in _BIT_DEPTHS if top <= 2**b - 1)
    return ImageScaling(16, bits, "file" if bits == 16 else "largest value", float(top))


def _check_float_range(arr: np.ndarray, path: Path) -> None:
    """Floating-point samples must be finite and in [0, 1]; ``ValueError`` naming the file and the values otherwise."""
    bad = int(np.count_nonzero(~np.isfinite(arr)))
    if bad:
        raise ValueError(f"cannot read image {path}: floating-point pixel data must be finite and in [0, 1], got "
                         f"{bad} NaN or infinite value(s) of {arr.size}")
    if arr.size and (arr.min() < 0.0 or arr.max() > 1.0):
        raise ValueError(
            f"cannot read image {path}: floating-point pixel data must be finite and in [0, 1], got range "
            f"[{arr.min():g}, {arr.max():g}]"
        )


def _normalise(arr: np.ndarray, path: Path, scaling: ImageScaling | None = None) -> np.ndarray:
    """Integer DN → [0, 1] by ``scaling`` (default: the dtype's maximum); float data must already be in [0, 1].

    Integer and boolean data become float32 (exact for 16-bit values; the quotient is the float32 the tensor
    holds), float16/float32 data float32, float64 data stay float64."""
    if arr.dtype == np.bool_:
        return arr.astype(np.float32)
    if arr.dtype in (np.uint8, np.uint16):
        divisor = scaling.divisor if scaling is not None else float(np.iinfo(arr.dtype).max)
        if scaling is not None and scaling.shift:
            arr = arr >> np.uint16(scaling.shift)  # PNG sBIT samples scaled up to 16 bits: back to their codes
        return arr.astype(np.float32) / np.float32(divisor)
    if np.issubdtype(arr.dtype, np.floating):
        arr = arr.astype(np.promote_types(arr.dtype, np.float32), copy=False)
        _check_float_range(arr, path)
        return arr
    raise ValueError(
        f"cannot read image {path}: unsupported pixel type {arr.dtype} (supported: 8-bit and 16-bit unsigned "
        "integers, floats in [0, 1])"
    )


def _png_header(path: Path) -> tuple[int, int, int, int] | None:
    """(bit depth, colour type, width, height) from a PNG's IHDR chunk, or None if the file is not a PNG."""
    with open(path, "rb") as f:
        head = f.read(26)
    if len(head) < 26 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    width, height = struct.unpack(">II", head[16:24])
    return head[24], head[25], width, height


def _check_pixels(path: Path, width: int, height: int) -> None:
    """Refuse an image of more than ``PIL.Image.MAX_IMAGE_PIXELS`` pixels (read now; ``None`` = no limit) before
    it is decoded: the decoders that are not Pillow (OpenCV, tifffile) apply no limit of their own."""
    from PIL import Image

    limit = Image.MAX_IMAGE_PIXELS
    if limit is not None and int(width) * int(height) > limit:
        raise ValueError(
            f"cannot read image {path}: {width}×{height} = {int(width) * int(height)} pixels is more than the limit "
            f"of {limit} pixels (PIL.Image.MAX_IMAGE_PIXELS)"
        )


def _read_16bit_colour_png(path: Path, width: int, height: int) -> np.ndarray:
    """Pillow truncates 16-bit colour / gray+alpha PNGs to 8 bits; OpenCV reads them losslessly."""
    _check_pixels(path, width, height)
    try:
        import cv2
    except ImportError:  # pragma: no cover - cv2 is a dependency; fall back to 8-bit precision
        return _read_pillow(path)
    data = np.fromfile(str(path), dtype=np.uint8)
    arr = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise ValueError(f"cannot read image {path}: OpenCV could not decode the 16-bit colour PNG")
    if arr.ndim == 3 and arr.shape[-1] >= 3:  # OpenCV gives BGR(A)
        arr = np.concatenate([arr[..., 2::-1], arr[..., 3:]], axis=-1)
    return arr


def _read_pillow(path: Path) -> np.ndarray:
    from PIL import Image, ImageOps

    try:
        with warnings.catch_warnings():  # Pillow only warns between 1× and 2× its limit: refused below instead
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            opened = Image.open(path)
    except Image.DecompressionBombError as e:  # more than 2× the limit: Pillow refuses to open it
        raise ValueError(f"cannot read image {path}: more than twice the limit of {Image.MAX_IMAGE_PIXELS} pixels "
                         f"(PIL.Image.MAX_IMAGE_PIXELS; Pillow: {e})") from None
    with opened as im:
        _check_pixels(path, *im.size)  # the limit itself, before decoding, as for the other decoders
        fmt = im.format
        im.load()
        im = ImageOps.exif_transpose(im)  # camera JPEGs: show the image upright, as a viewer would
        mode = im.mode
        if mode == "1":
            im = im.convert("L")
        elif mode in ("P", "PA"):
            im = im.convert("RGBA")
        elif mode in ("CMYK", "YCbCr", "LAB", "HSV"):
            im = im.convert("RGB")
        elif mode == "I":
            # 32-bit integer mode: only 16-bit PNG data land here (older Pillow); anything else is ambiguous.
            if fmt != "PNG":
                raise ValueError(f"cannot read image {path}: unsupported 32-bit integer pixel data")
            arr = np.asarray(im, dtype=np.int64)
            return np.clip(arr, 0, 65535).astype(np.uint16)
        arr = np.array(im)
    if arr.dtype.byteorder == ">":  # I;16B
        arr = arr.astype(arr.dtype.newbyteorder("="))
    return arr


#: TIFF photometric interpretations read by :func:`_read_tiff`, and the names of some others (for messages).
_TIFF_PHOTOMETRIC = {0: "MINISWHITE", 1: "MINISBLACK", 2: "RGB", 3: "PALETTE"}
_TIFF_PHOTOMETRIC_OTHER = {4: "MASK", 5: "SEPARATED (CMYK)", 6: "YCBCR", 8: "CIELAB", 9: "ICCLAB", 10: "ITULAB",
                           32803: "CFA", 32844: "LOGL", 32845: "LOGLUV", 34892: "LINEAR_RAW"}


def _read_tiff(path: Path) -> tuple[np.ndarray, bool]:
    """The first page's samples, and whether they are palette colours (16-bit full scale by the TIFF standard).

    A colour map whose entries are all multiples of 256 holds 8-bit colours × 256 (as Pillow writes it; tifffile
    and libtiff read such maps as 8-bit): its colours are returned as 8-bit samples (``False``: read like any 8-bit
    data, as the same palette PNG). A MINISWHITE page is inverted: integers ``max − v``, 1-bit ``not v``, floats
    (checked to lie in [0, 1] first) ``1 − v``."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        _check_pixels(path, page.imagewidth, page.imagelength * max(1, int(page.imagedepth)))
        if page.samplesperpixel > 4:
            raise ValueError(
                f"cannot read image {path}: {page.samplesperpixel} samples per pixel (supported: 1 to 4)"
            )
        arr = page.asarray()
        photometric = int(page.photometric)
        planar = int(page.planarconfig)
        colormap = page.colormap
    if planar == 2 and arr.ndim == 3:  # separate planes → channels last
        arr = np.moveaxis(arr, 0, -1)
    if photometric == 3 and colormap is not None:  # palette
        cmap = np.asarray(colormap)  # 3×N, 16-bit
        if not np.any(cmap.astype(np.uint32) & 0xFF):  # 8-bit colours × 256
            return np.moveaxis((cmap.astype(np.uint32) >> 8).astype(np.uint8)[:, arr], 0, -1), False
        return np.moveaxis(cmap[:, arr], 0, -1).astype(np.uint16), True
    if photometric == 0 and arr.dtype in (np.uint8, np.uint16):  # MINISWHITE
        arr = np.iinfo(arr.dtype).max - arr
    elif photometric == 0 and arr.dtype == np.bool_:  # 1-bit MINISWHITE: a set sample is black
        arr = ~arr
    elif photometric == 0 and np.issubdtype(arr.dtype, np.floating):  # float MINISWHITE: 0 is white
        _check_float_range(arr, path)
        arr = 1.0 - arr
    elif photometric not in _TIFF_PHOTOMETRIC:
        name = _TIFF_PHOTOMETRIC_OTHER.get(photometric, "unknown")
        supported = ", ".join(f"{k} ({v})" for k, v in _TIFF_PHOTOMETRIC.items())
        raise ValueError(f"cannot read image {path}: unsupported TIFF photometric interpretation {photometric} ({name}); "
                         f"supported: {supported}; convert the file to gray or RGB")
    return arr, False


def read_image(path: PathLike, bit_depth: int | str = "auto") -> torch.Tensor:
    """Read an image file as a gray float32 tensor ``1×H×W`` in [0, 1].

    Formats: PNG, JPEG, TIFF (first page), BMP; 8-bit (÷255) or 16-bit samples, gray, gray+alpha, palette, RGB
    or RGBA. Colour → gray by BT.601 luma (:func:`to_gray`); alpha is dropped. JPEG EXIF orientation is applied.

    ``bit_depth``: significant bits of 16-bit data, 1…16 (values are divided by 2^bit_depth − 1; a value above
    that raises — except in a PNG whose ``sBIT`` chunk declares this depth and whose samples are scaled up to 16
    bits as the PNG specification says, read as (value >> (16 − bit_depth)) / (2^bit_depth − 1)), or ``"auto"``
    (default): the PNG's ``sBIT`` chunk where there is one (samples scaled up to 16 bits as the PNG specification
    says, or held in the low bits: module docstring), else the fewest of 8, 10,
    12, 14 or 16 bits that hold the largest value — a guess, announced with a ``UserWarning`` that names the
    scaling when it is not 16 bits (pass ``bit_depth=16`` for DN/65535). Only the gray or colour samples count
    toward the largest value and the check against ``bit_depth``: the alpha channel is dropped, so an image reads the
    same with or without it. A palette TIFF's colours are 16-bit full scale (÷65535 under ``"auto"``); a colour map
    whose entries are all multiples of 256 holds 8-bit colours × 256 (Pillow writes palette TIFFs so; tifffile and
    libtiff read them as 8-bit) and is read as 8-bit colours (÷255) — either way it reads like the same palette PNG.
    A floating-point MINISWHITE TIFF reads 1 − v. The file's type is taken from its name, except that a PNG is
    recognised by its signature whatever its extension (a 16-bit PNG named ``.jpg`` is read at 16 bits, its
    ``sBIT`` chunk included). :func:`read_image_scaled` returns the scaling with the image.

    Raises:
        FileNotFoundError: ``path`` does not exist or is a broken symbolic link (the message names it and, for a
            link, where it leads or that it loops).
        ValueError: unsupported extension (the message lists :data:`IMAGE_EXTENSIONS`), ``path`` is not a
            regular file (a directory, FIFO, ...), the file is corrupt/unreadable or has an unsupported pixel
            type or TIFF photometric interpretation (CMYK; the message lists the supported ones), holds values beyond
            ``bit_depth``, or has more pixels than ``PIL.Image.MAX_IMAGE_PIXELS``
            (read when the file is opened; checked from the header, before decoding, for every format — Pillow
            alone would only warn up to twice that limit) (the message names the file).
    """
    image, scaling = read_image_scaled(path, bit_depth)
    if scaling.source == "largest value":
        warnings.warn(f"{path}: {scaling.describe()}; pass bit_depth=16 to scale by 65535", UserWarning, stacklevel=2)
    return image


def read_samples(path: PathLike) -> np.ndarray:
    """An image file's samples as decoded, before any gray conversion or scaling: ``H×W`` or ``H×W×C`` (RGB(A)
    order; C = 2 for gray + alpha), uint8 or uint16, by the decoder :func:`read_image_scaled` uses for the file. For
    callers that must tell a colour image from a gray one saved as RGB (equal samples), e.g. the calibration.
    Errors as :func:`read_image`."""
    p = Path(path)
    if _is_tiff(p):
        return _read_tiff(p)[0]
    header = _png_header(p)  # (any name: the PNG signature decides)
    if header is not None and header[0] == 16 and header[1] in (2, 4, 6):
        return _read_16bit_colour_png(p, header[2], header[3])
    return _read_pillow(p)


def read_sequence_frame(path: PathLike, bit_depth: int | str, first_bits: int | None) -> tuple[torch.Tensor, ImageScaling]:
    """A frame of a sequence (a folder of frames) as :func:`read_image_scaled` reads it, with one scale for the
    sequence where ``bit_depth`` is ``"auto"`` and the depth is guessed from the largest value: at least
    ``first_bits`` (the guess from the sequence's first frame; a darker frame is not read brighter), more where the
    frame itself holds larger values (a brighter frame is not refused). A frame's scale depends only on itself and
    the first frame, whatever order the frames are read in."""
    frame, scaling = read_image_scaled(path, bit_depth)
    if (bit_depth == "auto" and first_bits is not None and scaling.source == "largest value" and scaling.bits is not None
            and scaling.bits < first_bits):
        frame = frame * ((2.0**scaling.bits - 1.0) / (2.0**first_bits - 1.0))
        scaling = ImageScaling(scaling.file_bits, int(first_bits), "sequence", scaling.max_value, channels=scaling.channels)
    return frame, scaling


def first_frame_bits(path: PathLike, bit_depth: int | str) -> int | None:
    """The depth ``"auto"`` guesses from a sequence's first frame's largest value (:func:`read_sequence_frame`), or
    ``None`` (another ``bit_depth``, a declared or full-range depth, 8-bit or floating-point data, an unreadable file)."""
    if bit_depth != "auto":
        return None
    try:
        _, scaling = read_image_scaled(path, "auto")
    except (OSError, ValueError):
        return None
    return scaling.bits if scaling.source == "largest value" else None


def _broken_link(p: Path) -> str:
    """Why the symbolic link ``p`` leads to nothing: its target that does not exist, or a loop of links."""
    try:
        os.stat(p)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "it leads back to itself through a loop of links"
    return f"it leads to {os.path.realpath(p)}, which does not exist"


def read_image_scaled(path: PathLike, bit_depth: int | str = "auto") -> tuple[torch.Tensor, ImageScaling]:
    """:func:`read_image` without the warning, plus the :class:`ImageScaling` it used."""
    bit_depth = _check_bit_depth(bit_depth)
    p = Path(path)
    if not p.exists():
        if p.is_symlink():  # (a link whose target is gone, or a loop of links: listed by list_images, not skipped)
            raise FileNotFoundError(f"cannot read image {p}: broken symbolic link ({_broken_link(p)})")
        raise FileNotFoundError(f"image file not found: {p}")
    if p.is_dir():
        raise ValueError(f"cannot read image {p}: it is a directory, not an image file")
    if not p.is_file():
        raise ValueError(f"cannot read image {p}: not a regular file (a FIFO, socket or device); give an image file")
    ext = p.suffix.lower()
    if ext not in IMAGE_EXTENSIONS:
        raise ValueError(
            f"cannot read image {p}: unsupported extension {p.suffix!r}; allowed: {', '.join(IMAGE_EXTENSIONS)}"
        )
    palette = False
    try:
        if ext in (".tif", ".tiff"):
            arr, palette = _read_tiff(p)
        else:
            header = _png_header(p)  # a PNG by its signature, whatever its name says
            if header is not None and header[0] == 16 and header[1] in (2, 4, 6):
                arr = _read_16bit_colour_png(p, header[2], header[3])
            else:
                arr = _read_pillow(p)
    except ValueError as e:
        if str(p) in str(e):
            raise
        raise ValueError(f"cannot read image {p}: {e}") from e
    except (FileNotFoundError, PermissionError):
        raise
    except Exception as e:  # PIL.UnidentifiedImageError, truncated data, tifffile errors, ...
        raise ValueError(f"cannot read image {p} (corrupt or not a valid {ext[1:].upper()} file): {e}") from e

    if arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[-1] not in (2, 3, 4)):
        raise ValueError(f"cannot read image {p}: unsupported array shape {arr.shape}")
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"cannot read image {p}: the image is empty (shape {arr.shape})")
    if palette and bit_depth == "auto":  # 16-bit palette colours are full scale, as a palette PNG's 8-bit ones
        scaling = ImageScaling(16, 16, "file", float(arr.max()))
    elif arr.dtype in (np.uint8, np.uint16):
        scaling = _scaling(_colour_samples(arr), p, bit_depth)  # alpha (dropped) sets no depth
    else:
        scaling = ImageScaling(None, None, "file", float(np.nanmax(arr)) if arr.size else 0.0)
    gray = to_gray(_normalise(arr, p, scaling))
    out = torch.from_numpy(np.ascontiguousarray(gray, dtype=np.float32)).clamp_(0.0, 1.0)
    return out.unsqueeze(0), dataclasses.replace(scaling, channels=int(arr.shape[-1]) if arr.ndim == 3 else 1)
