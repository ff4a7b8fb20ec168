"""Natural photographs bundled with scikit-image (``skimage.data``), available offline.

Only images that ship inside the scikit-image wheel are used (no ``pooch`` download), and only camera
photographs of real scenes: microscopy, astronomy, synthetic/graphic images, already-degraded images and
images too small for a 192×192 MTF patch are left out. The selection and the reasons are in
``docs/data.md``. Colour photographs are converted to gray with BT.601 luma (:func:`camhealth.data.to_gray`).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from camhealth.data._common import check_index
from camhealth.data.io import to_gray

__all__ = ["SKIMAGE_PHOTOS", "load_skimage_photo", "SkimagePhotosSource"]

#: name → (``skimage.data`` function, how to pick the image from its return value)
_LOADERS = {
    "astronaut": ("astronaut", None),
    "camera": ("camera", None),
    "chelsea": ("chelsea", None),
    "coffee": ("coffee", None),
    "coins": ("coins", None),
    "rocket": ("rocket", None),
    "motorcycle_left": ("stereo_motorcycle", 0),
    "brick": ("brick", None),
    "grass": ("grass", None),
    "gravel": ("gravel", None),
}

#: The photographs used, in this order (see ``docs/data.md`` for sources, licences and exclusions).
SKIMAGE_PHOTOS: tuple[str, ...] = tuple(_LOADERS)


def load_skimage_photo(name: str) -> torch.Tensor:
    """Load one photograph of :data:`SKIMAGE_PHOTOS` as a gray float32 tensor ``1×H×W`` in [0, 1]."""
    if name not in _LOADERS:
        raise ValueError(f"unknown scikit-image photo {name!r}; available: {list(SKIMAGE_PHOTOS)}")
    import skimage.data

    func, pick = _LOADERS[name]
    out = getattr(skimage.data, func)()
    if pick is not None:
        out = out[pick]
    arr = np.asarray(out)
    if arr.dtype != np.uint8:
        raise ValueError(f"skimage.data.{func}() returned dtype {arr.dtype}, expected uint8")
    gray = to_gray(arr.astype(np.float64) / 255.0)
    return torch.from_numpy(np.ascontiguousarray(gray, dtype=np.float32)).clamp_(0.0, 1.0).unsqueeze(0)


class SkimagePhotosSource(torch.utils.data.Dataset):
    """The offline scikit-image photographs as an image source.

    Args:
        names: subset of :data:`SKIMAGE_PHOTOS` to use (default: all, in that order).

    ``source[i] -> (image 1×H×W float32, id)`` with ids ``"skimage:<name>"``; each photo is its own
    split group.
    """

    def __init__(self, names: Sequence[str] | None = None) -> None:
        if isinstance(names, str):
            raise TypeError(f"names must be a list of photo names, not a string ({names!r}); use [{names!r}]")
        names = list(SKIMAGE_PHOTOS if names is None else names)
        if not names:
            raise ValueError(f"names must be a non-empty list of photo names from {list(SKIMAGE_PHOTOS)}")
        unknown = [n for n in names if n not in _LOADERS]
        if unknown:
            raise ValueError(f"unknown scikit-image photo(s) {unknown}; available: {list(SKIMAGE_PHOTOS)}")
        if len(set(names)) != len(names):
            raise ValueError(f"names must not repeat, got {names}")
        self.names = names
        self.ids = [f"skimage:{n}" for n in names]

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, str]:
        i = check_index(index, len(self), "SkimagePhotosSource")
        return load_skimage_photo(self.names[i]), self.ids[i]

    def __repr__(self) -> str:
        return f"{type(self).__name__}(names={self.names})"
