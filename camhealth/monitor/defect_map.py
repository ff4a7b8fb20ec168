"""A camera's known defective pixels, for the monitor to tell them from new ones.

A defect map is a boolean H×W array over the sensor's frame: ``True`` at a pixel known to be defective. It is what
``python -m camhealth.calibrate`` writes as ``hot_pixels`` and ``dead_pixels`` in ``camera.maps.npz`` (a dark master
more than 6 robust σ above its median; a flat-field signal more than 6 robust σ below its median), what a monitor run
found (``--defects-out``), or a vendor's or a user's own mask. The monitor (:class:`camhealth.monitor.Monitor`,
``defect_map=``) counts how many of the pixels it flags on a frame are on the map (``known``) and names only the
others in its alarm: a defect the calibration already lists is expected, one that appeared since is news (hot pixels
grow with age and radiation).

Accepted forms (:func:`load_defect_map`):

- ``.npz`` — ``hot_pixels`` and ``dead_pixels`` (calibration's maps; their union), ``defective_pixels`` (a monitor
  run's, written by :func:`save_defect_map`: ``python -m camhealth.monitor --defects-out``), or the archive's only
  array; read with
  ``allow_pickle=False``, so loading never runs code from the file, and only after its header declares at most
  :data:`MAX_MAP_PIXELS` elements;
- ``.npy`` — one array, the same way;
- ``.png``, ``.pgm``, ``.pbm``, ``.tif``, ``.tiff``, ``.bmp`` — a one-channel image, non-zero at the defects; its
  size is read from the header first (Pillow, which refuses more than twice ``PIL.Image.MAX_IMAGE_PIXELS``), and
  an image of more than :data:`MAX_MAP_PIXELS` pixels is refused before it is decoded;
- an array (NumPy or torch) of H×W.

Values must be boolean or whole numbers 0/1 (an image: zero and non-zero; a float image must also be finite, NaN/inf
refused); the map may mark no pixel (a calibration that found no hot pixels: every defect the monitor flags is then
new) but fewer than half of them (a map of mostly defects is an inverted mask or the wrong file).
"""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = [
    "IMAGE_SUFFIXES", "MAX_DEFECT_SHARE", "MAX_MAP_PIXELS", "NPZ_KEYS", "defect_map_path", "load_defect_map",
    "save_defect_map",
]

#: Image files read as masks (non-zero = defective).
IMAGE_SUFFIXES = (".png", ".pgm", ".pbm", ".tif", ".tiff", ".bmp")
#: The largest share of a frame's pixels a defect map may mark (above: an inverted mask or another file).
MAX_DEFECT_SHARE = 0.5
#: The arrays a ``.npz`` defect map is read from: calibration's ``camera.maps.npz`` hot and dead pixels (both, where
#: both are there: their union), else the defects a monitor run found (``python -m camhealth.monitor --defects-out``,
#: :func:`save_defect_map`).
NPZ_KEYS = ("hot_pixels", "dead_pixels", "defective_pixels")
#: The most pixels a defect map may have (a 400-megapixel sensor): a file that declares more is refused before its
#: data are read (a compressed archive can declare far more than it takes on disk).
MAX_MAP_PIXELS = 400_000_000


class _Refused(ValueError):
    """A file refused by its header: the message is final (not wrapped by the loader's other errors)."""


def _declared_size(fp: Any, name: str) -> None:
    """Reads the ``.npy`` header at ``fp`` and refuses an array of more than :data:`MAX_MAP_PIXELS` elements, or of
    a dtype other than bool, integer or float (kinds ``b``, ``i``, ``u``, ``f``), before its data are read."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(fp)
        if version == (1, 0):
            shape, _, dtype = fmt.read_array_header_1_0(fp)
        elif version in ((2, 0), (3, 0)):  # 3.0 differs from 2.0 only in the header's text encoding (UTF-8)
            shape, _, dtype = fmt.read_array_header_2_0(fp)
        else:
            raise ValueError(f"header version {version[0]}.{version[1]}; readable: 1.0, 2.0, 3.0")
    except ValueError as err:
        raise _Refused(f"{name} is not a plain NumPy array ({err})") from None
    n = int(np.prod(shape, dtype=np.float64)) if len(shape) else 1
    if n > MAX_MAP_PIXELS:
        raise _Refused(f"{name} declares an array of shape {tuple(shape)} ({n} elements, at most {MAX_MAP_PIXELS} "
                         "allowed): not read")
    if dtype.hasobject:
        raise _Refused(f"{name} declares an array of Python objects (dtype {dtype}): pickled arrays are refused")
    if dtype.kind not in "biuf" or n * dtype.itemsize > 8 * MAX_MAP_PIXELS:
        raise _Refused(f"{name} declares an array of dtype {dtype} ({dtype.itemsize} bytes per element): a defect map "
                       "must be bool or whole numbers 0/1 (bool, integer or float dtype): not read")


def _from_file(path: Path) -> tuple[np.ndarray, str]:
    if not path.is_file():
        raise FileNotFoundError(f"defect map {str(path)!r} does not exist (expected camera.maps.npz from "
                                "python -m camhealth.calibrate, a .npy array or a mask image)")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                names = list(z.files)
                keys = [k for k in NPZ_KEYS[:2] if k in names] or [k for k in NPZ_KEYS[2:] if k in names]
                keys = keys or (names[:1] if len(names) == 1 else [])
                if keys:
                    members = set(z.zip.namelist())
                    for key in keys:  # (np.load lists a member without the .npy suffix under its full name)
                        with z.zip.open(key + ".npy" if key + ".npy" in members else key) as fp:
                            _declared_size(fp, f"defect map {str(path)!r}[{key}]")
                    arrays = [np.asarray(z[key]) for key in keys]
                    if len(arrays) == 2:  # calibration's hot and dead pixels: their union, each checked as a map
                        hot, dead = (f"{path.name}[{key}]" for key in keys)
                        if arrays[0].shape != arrays[1].shape:
                            raise _Refused(f"defect map {str(path)!r}: {keys[0]} has shape {tuple(arrays[0].shape)} but "
                                           f"{keys[1]} has shape {tuple(arrays[1].shape)}: both must cover the same frame, "
                                           "pixel for pixel")
                        try:
                            union = _mask(arrays[0], hot) | _mask(arrays[1], dead)
                        except ValueError as err:  # (final: not the archive's own read errors below)
                            raise _Refused(str(err)) from None
                        return union, f"{path.name}[{' | '.join(keys)}]"
                    return arrays[0], f"{path.name}[{keys[0]}]"
        except _Refused:
            raise
        except ValueError as err:  # an object (pickled) array, or not an archive
            raise ValueError(f"defect map {str(path)!r} cannot be read as a plain NumPy archive ({err}); pickled "
                             "arrays are refused") from None
        except (OSError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as err:  # (a truncated or corrupt zip)
            raise ValueError(f"defect map {str(path)!r} is not a readable .npz archive ({err})") from None
        raise ValueError(f"defect map {str(path)!r} holds the arrays {names}: expected one of {list(NPZ_KEYS)} "
                         "(camera.maps.npz of python -m camhealth.calibrate, or a monitor's --defects-out) or a single array")
    if suffix == ".npy":
        try:
            with path.open("rb") as fp:
                _declared_size(fp, f"defect map {str(path)!r}")
            return np.load(path, allow_pickle=False), path.name
        except _Refused:
            raise
        except (ValueError, OSError, EOFError) as err:
            raise ValueError(f"defect map {str(path)!r} cannot be read as a plain .npy array ({err}); pickled arrays "
                             "are refused") from None
    if suffix in IMAGE_SUFFIXES:
        import warnings

        import cv2
        from PIL import Image

        try:  # the size from the header, before OpenCV decodes the image
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", Image.DecompressionBombWarning)
                with Image.open(path) as im:
                    width, height = im.size
        except Image.DecompressionBombError as err:
            raise _Refused(f"defect map {str(path)!r} is an image larger than Pillow allows ({err}): not read") from None
        except (OSError, SyntaxError, ValueError) as err:  # PIL.UnidentifiedImageError is an OSError
            raise ValueError(f"defect map {str(path)!r} is not a readable image ({err})") from None
        if width * height > MAX_MAP_PIXELS:
            raise _Refused(f"defect map {str(path)!r} is a {width}×{height} image ({width * height} pixels, at most "
                           f"{MAX_MAP_PIXELS} allowed): not read")
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"defect map {str(path)!r} is not a readable image")
        if img.ndim == 3:
            raise ValueError(f"defect map {str(path)!r} has {img.shape[2]} channels: a mask image must have one "
                             "(non-zero at the defects)")
        if img.dtype.kind == "f":  # a float image: NaN/inf is no answer about a pixel, not "non-zero"
            bad = int(np.count_nonzero(~np.isfinite(img)))
            if bad:
                raise ValueError(f"defect map {str(path)!r} holds {bad} non-finite value(s) (NaN/inf) of {img.size}: a "
                                 "mask image must be finite, zero or non-zero at the defects")
        return img != 0, path.name
    raise ValueError(f"defect map {str(path)!r}: suffix {suffix or '(none)'!r} is not one of "
                     f"{['.npz', '.npy', *IMAGE_SUFFIXES]}")


def _mask(arr: np.ndarray, name: str) -> np.ndarray:
    """``arr`` as a bool H×W map: 2-D, not empty, bool or whole numbers 0/1 (ValueError naming ``name`` otherwise)."""
    if arr.ndim != 2:
        raise ValueError(f"{name} has shape {tuple(arr.shape)}: a defect map must be 2-D (H×W)")
    if arr.size == 0:
        raise ValueError(f"{name} is empty (shape {tuple(arr.shape)})")
    if arr.dtype == np.bool_:
        return arr
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"{name} has dtype {arr.dtype}: expected bool or whole numbers 0/1")
    values = np.unique(arr)
    if not np.isin(values, (0, 1)).all():
        shown = ", ".join(f"{v:g}" for v in values[:6].astype(float))
        raise ValueError(f"{name} holds the values {shown}{' …' if values.size > 6 else ''}: a defect map must be "
                         "bool or 0/1")
    return arr != 0


def load_defect_map(source: Any, shape: tuple[int, int] | None = None) -> torch.Tensor:
    """The known defective pixels as a bool tensor (H, W) (module docstring for the forms accepted).

    Args:
        source: a path (str or Path) or an array of H×W.
        shape: (H, W) [px] the map must have, e.g. the frames' size (two whole numbers >= 1); ``None``: any.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: ``shape`` is not two whole numbers >= 1; the file cannot be read safely, or the map is not 2-D,
            holds values other than 0/1 (NaN included; a mask image: NaN/inf), marks at least
            :data:`MAX_DEFECT_SHARE` of the pixels, or does not have ``shape`` — each naming the value found and what
            is allowed.
    """
    if shape is not None:
        dims = shape.tolist() if isinstance(shape, (np.ndarray, torch.Tensor)) else shape
        dims = list(dims) if isinstance(dims, (tuple, list)) else None
        if dims is None or len(dims) != 2 or not all(
                isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
                and np.isfinite(v) and v == int(v) and v >= 1 for v in dims):
            raise ValueError(f"shape = {shape!r} must be (H, W): two whole numbers of pixels >= 1, or None")
        shape = (int(dims[0]), int(dims[1]))
    if isinstance(source, (str, Path)):
        arr, name = _from_file(Path(source))
    elif isinstance(source, torch.Tensor):
        t = source.detach().cpu()
        if t.dtype == torch.bfloat16:  # (NumPy has no bfloat16; float32 holds every bfloat16 value exactly)
            t = t.float()
        arr, name = t.numpy(), "defect map"
    elif isinstance(source, np.ndarray):
        arr, name = source, "defect map"
    else:
        raise TypeError(f"defect map must be a path or an H×W array, got {type(source).__name__}")
    arr = _mask(arr, name)
    if shape is not None and tuple(arr.shape) != tuple(shape):
        raise ValueError(f"{name} is {arr.shape[1]}×{arr.shape[0]} px (W×H) but the frames are {shape[1]}×{shape[0]} "
                         "px: the map must cover the whole frame, pixel for pixel")
    marked = int(arr.sum())
    if marked >= MAX_DEFECT_SHARE * arr.size:
        raise ValueError(f"{name} marks {marked} of {arr.size} pixels ({100.0 * marked / arr.size:.1f} %; a map must "
                         f"mark fewer than {100 * MAX_DEFECT_SHARE:g} %): an inverted mask or another file?")
    return torch.from_numpy(np.ascontiguousarray(arr))


def defect_map_path(path: str | Path) -> Path:
    """The file :func:`save_defect_map` writes for ``path``: ``.npz`` appended where missing; ValueError when it names
    a folder (which would otherwise become ``<folder>.npz`` beside it) or lies under a file."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path} is a folder; give the defect map's file name, e.g. {path / 'defects.npz'}")
    if path.suffix.lower() != ".npz":
        path = path.with_name(path.name + ".npz")
    if path.is_dir():
        raise ValueError(f"{path} is a folder; give another file name for the defect map")
    blocking = [d for d in path.parents if d.exists() and not d.is_dir()]
    if blocking:
        raise ValueError(f"cannot write {path}: {blocking[0]} is a file, not a folder")
    return path


def save_defect_map(path: str | Path, defective: torch.Tensor, frames: torch.Tensor | None = None) -> Path:
    """Writes a defect map that :func:`load_defect_map` reads: ``defective_pixels`` (bool H×W) and, where given,
    ``flagged_frames`` (int32 H×W, the frames each pixel was flagged in: whole numbers in [0, 2^31 − 1], else
    ``ValueError`` naming the first bad value), compressed, no pickled objects. Returns the path written (``.npz``
    appended where missing; a folder is refused, see :func:`defect_map_path`); the file's folder must exist."""
    arr = torch.as_tensor(defective).detach().cpu().numpy()
    if arr.ndim != 2 or arr.dtype != np.bool_:
        raise ValueError(f"defective must be a bool H×W array, got {arr.dtype} of shape {tuple(arr.shape)}")
    out = {"defective_pixels": arr}
    if frames is not None:
        raw = torch.as_tensor(frames).detach().cpu()
        if raw.dtype == torch.bfloat16:
            raw = raw.float()
        raw = raw.numpy()
        if raw.shape != arr.shape:
            raise ValueError(f"frames has shape {tuple(raw.shape)}, the map {tuple(arr.shape)}")
        if raw.dtype.kind not in "biuf":
            raise ValueError(f"frames has dtype {raw.dtype}: it must hold counts, whole numbers in [0, {2**31 - 1}]")
        if raw.size and raw.dtype.kind != "b":
            wide = raw.astype(np.float64)
            bad = ~np.isfinite(wide) | (wide < 0) | (wide > 2**31 - 1) | (wide != np.round(wide))
            if bad.any():
                first = wide[bad][0]
                raise ValueError(f"frames holds {int(bad.sum())} value(s) that are not counts (first: {first:g}): each "
                                 f"must be a whole number in [0, {2**31 - 1}] (the frames the pixel was flagged in)")
        out["flagged_frames"] = raw.astype(np.int32)
    path = defect_map_path(path)
    np.savez_compressed(path, **out)
    return path
