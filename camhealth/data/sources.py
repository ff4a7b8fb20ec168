"""Combining image sources, building one from a spec string, and the leak-free train/val/test split.

Split rule (``split_ids``): every id is mapped to a **group key** and every group to a split by a hash of
``(seed, group key)`` alone, so an image always lands in the same split whatever other images are in the
list and in whatever order. Frames of one clip share a group and therefore a split:

* ids of the form ``"<clip>#<digits>"`` (street frames ``"street:vtest#000123"``, video/frame-folder frames
  ``"video:run1.avi#000042"``) → group ``"<clip>"``;
* any other id (``"skimage:camera"``, ``"deadleaves-000042"``, ``"sub/img.png"``) is its own group.

Pass ``group_key=`` to group differently (e.g. by sub-folder for a folder of several clips' frames).
"""

from __future__ import annotations

import bisect
import hashlib
import inspect
import math
import re
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import torch

from camhealth.data._common import check_index, check_int, check_whole
from camhealth.data.dead_leaves import DeadLeavesSource
from camhealth.data.image_folder import ImageFolderSource
from camhealth.data.io import _check_bit_depth
from camhealth.data.skimage_photos import SkimagePhotosSource
from camhealth.data.street_sample import StreetSampleSource
from camhealth.data.video import VIDEO_EXTENSIONS, FrameSequence

__all__ = ["AreaDownsampledSource", "ConcatSource", "DefaultSource", "DEADLEAVES_OPTIONS", "build_source",
           "check_source_options", "group_key", "source_options", "split_ids", "SPLITS"]

#: Split names returned by :func:`split_ids`, in order.
SPLITS = ("train", "val", "test")

_FRAME_ID = re.compile(r"^(.+)#\d+$")


class ConcatSource(torch.utils.data.Dataset):
    """Several image sources one after another; ids must be unique across them."""

    def __init__(self, sources: Sequence[torch.utils.data.Dataset]) -> None:
        sources = list(sources)
        if not sources:
            raise ValueError("ConcatSource needs at least one source")
        for s in sources:
            if not hasattr(s, "ids") or not hasattr(s, "__getitem__"):
                raise TypeError(f"{type(s).__name__} is not an image source (needs .ids and __getitem__)")
        self.sources = sources
        self.ids: list[str] = [i for s in sources for i in s.ids]
        if len(set(self.ids)) != len(self.ids):
            seen: set[str] = set()
            dup = next(i for i in self.ids if i in seen or seen.add(i))  # type: ignore[func-returns-value]
            raise ValueError(f"duplicate image id {dup!r} across sources")
        self._ends = []
        total = 0
        for s in sources:
            total += len(s)
            self._ends.append(total)

    def __len__(self) -> int:
        return self._ends[-1]

    def __getitem__(self, index: int) -> tuple[torch.Tensor, str]:
        i = check_index(index, len(self), type(self).__name__)
        k = bisect.bisect_right(self._ends, i)
        offset = self._ends[k - 1] if k else 0
        return self.sources[k][i - offset]

    def __repr__(self) -> str:
        inner = ", ".join(repr(s) for s in self.sources)
        return f"{type(self).__name__}([{inner}])"


class AreaDownsampledSource(torch.utils.data.Dataset):
    """A source whose images are area-downsampled by an integer ``factor``: each output pixel is the mean of a
    ``factor × factor`` block (the last rows/columns that do not fill a block are dropped).

    Why: a camera pixel integrates light over its area, so the block mean is exactly what a camera with
    ``factor``× larger pixels and the same optics would record — the new pixel aperture is an exact box and the
    original optics' blur shrinks by ``factor`` in pixels. The native MTF of the result (relative to an ideal
    pixel-aperture camera) at a normalised frequency f_n is the original optics' MTF at f_n / ``factor``
    (``docs/data.md``, *Native MTF of the sources*): a soft photograph or video frame becomes a sharp one.
    Ids are those of ``source`` (so the train/val/test split is the same as at full resolution).
    """

    def __init__(self, source: torch.utils.data.Dataset, factor: int) -> None:
        if not hasattr(source, "ids") or not hasattr(source, "__getitem__"):
            raise TypeError(f"{type(source).__name__} is not an image source (needs .ids and __getitem__)")
        self.factor = check_int(factor, "area_downsample factor", 1)
        if self.factor > 8:
            raise ValueError(f"area_downsample factor = {self.factor} is out of the allowed range [1, 8]")
        self.source = source
        self.ids: list[str] = list(source.ids)

    def __len__(self) -> int:
        return len(self.source)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, str]:
        img, image_id = self.source[index]
        k = self.factor
        if k == 1:
            return img, image_id
        h, w = img.shape[-2] // k, img.shape[-1] // k
        if h == 0 or w == 0:
            raise ValueError(f"image {image_id!r} ({img.shape[-2]}×{img.shape[-1]} px) is smaller than one {k}×{k} block")
        x = img[..., : h * k, : w * k].double()  # exact block means (float64), back to float32 in [0, 1]
        out = x.reshape(*x.shape[:-2], h, k, w, k).mean((-3, -1))
        return out.to(img.dtype).contiguous(), image_id

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.source!r}, factor={self.factor})"



def _arguments(fn: Callable, skip: Sequence[str] = ()) -> tuple[str, ...]:
    """The named keyword arguments of ``fn`` (no ``self``, ``*args``, ``**kwargs`` or those in ``skip``)."""
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    return tuple(p.name for p in inspect.signature(fn).parameters.values()
                 if p.kind in kinds and p.name != "self" and p.name not in skip)


#: The options of :class:`DefaultSource` that shape its dead-leaves images, handed on to :class:`DeadLeavesSource`:
#: every argument of it but those :class:`DefaultSource` sets itself (``n_images`` = ``deadleaves``, ``size`` =
#: ``deadleaves_size``, ``seed``).
DEADLEAVES_OPTIONS: tuple[str, ...] = _arguments(DeadLeavesSource.__init__, ("n_images", "size", "seed"))


def _check_options(given: Mapping[str, Any], allowed: Sequence[str], name: str, what: str) -> None:
    """``ValueError`` naming the keys of ``given`` that are not in ``allowed``, and listing ``allowed``."""
    unknown = sorted(str(k) for k in given if k not in allowed)
    if unknown:
        raise ValueError(f"{name}: unknown option(s) {unknown} for {what}; allowed: {sorted(allowed)}")


def _check_default_options(options: Mapping[str, Any], name: str) -> None:
    """The options of :class:`DefaultSource` (``options``: all of them, as ``source_kwargs`` gives them): each one
    known, and the options that shape the dead-leaves images (``deadleaves_size``, ``seed`` and
    :data:`DEADLEAVES_OPTIONS`) only together with such images (``deadleaves`` > 0)."""
    _check_options(options, _DEFAULT_OPTIONS, name, "the built-in source 'default' (DefaultSource)")
    shaping = sorted(k for k in options if k in DEADLEAVES_OPTIONS or k in ("deadleaves_size", "seed"))
    deadleaves = options.get("deadleaves", 0)
    if shaping and isinstance(deadleaves, int) and not isinstance(deadleaves, bool) and deadleaves == 0:
        raise ValueError(f"{name}: dead-leaves option(s) {shaping} given with deadleaves = 0 (no dead-leaves images "
                         f"to shape): set deadleaves > 0 or leave them out")


class DefaultSource(ConcatSource):
    """The offline default training images: scikit-image photos + street frames (+ dead-leaves images).

    Args:
        deadleaves: number of procedural dead-leaves images to append (0: none).
        deadleaves_size: their ``(H, W)``.
        seed: seed of the dead-leaves images.
        street_stride: keep every n-th street frame (1: all 50).
        include_skimage, include_street: switch those parts off.
        deadleaves_antialiased: also append the first N dead-leaves images rendered with 2× supersampling
            (anti-aliased edges, as a lens and a pixel aperture would render them; the plain ones have hard
            one-pixel steps). Ids ``"deadleaves-000042#2"``: the same split group as the plain rendering, so
            a scene never sits in two splits.
        photo_repeat: list the scikit-image photos this many times (1: once). The copies have ids
            ``"skimage:grass#1"`` … — the same split group as the photo, so a photo never sits in two splits —
            and give the few natural photos (fine texture such as grass and gravel) more weight among the
            dead-leaves images without leaving any of those out. Each copy draws its own crops.
        area_downsample: area-downsample the scikit-image photos and street frames by this integer factor
            (:class:`AreaDownsampledSource`; 1: native resolution). Their own optics blur shrinks by the factor and the
            pixel aperture stays an exact box, so 2 or 3 make soft photographs sharp (native MTF at f_n = 0.6 in
            ``docs/data.md``); images that end up smaller than the patch size are skipped by the DataModule. Dead
            leaves are not downsampled: render them with ``supersample`` (4 or 8: a pixel is the mean of s×s point
            samples, within 1 % / 0.3 % of the exact pixel-area integral at f_n = 0.6).
        deadleaves_kwargs: further :class:`DeadLeavesSource` arguments (:data:`DEADLEAVES_OPTIONS`: ``r_min``,
            ``r_max``, ``contrast``, ``supersample``, ``shading``, ``thin``, ``coverage``).

    Raises:
        ValueError: an option that is none of the above (naming it and listing the allowed ones; a misspelt
            ``dead_leaves: 60`` would otherwise train without the dead-leaves images), or dead-leaves options
            (``deadleaves_size`` or :data:`DEADLEAVES_OPTIONS`) with ``deadleaves`` = 0; a value out of range.
    """

    def __init__(
        self,
        deadleaves: int = 0,
        deadleaves_size: int | Sequence[int] = (256, 256),
        seed: int = 0,
        street_stride: int = 1,
        include_skimage: bool = True,
        include_street: bool = True,
        deadleaves_antialiased: int = 0,
        photo_repeat: int = 1,
        area_downsample: int = 1,
        **deadleaves_kwargs,
    ) -> None:
        _check_options(deadleaves_kwargs, _DEFAULT_OPTIONS, "DefaultSource", "the built-in source 'default'")
        deadleaves = check_int(deadleaves, "deadleaves", 0)
        if deadleaves == 0 and deadleaves_kwargs:
            _check_default_options({**deadleaves_kwargs, "deadleaves": 0}, "DefaultSource")
        n_aa = check_int(deadleaves_antialiased, "deadleaves_antialiased", 0)
        repeat = check_int(photo_repeat, "photo_repeat", 1)
        k = check_whole(area_downsample, "area_downsample", 1, 8)
        if k > 1 and not (include_skimage or include_street):
            raise ValueError(f"area_downsample = {k} downsamples the photos and street frames; both are switched off")
        photo = (lambda src: AreaDownsampledSource(src, k)) if k > 1 else (lambda src: src)
        if repeat > 1 and not include_skimage:
            raise ValueError(f"photo_repeat = {repeat} repeats the scikit-image photos; they are switched off (include_skimage=False)")
        if n_aa > deadleaves:
            raise ValueError(f"deadleaves_antialiased = {n_aa} must be <= deadleaves = {deadleaves} (it re-renders those images)")
        if n_aa and check_whole(deadleaves_kwargs.get("supersample", 1), "supersample", 1, 8) != 1:
            raise ValueError("deadleaves_antialiased re-renders the plain (supersample 1) images; do not pass supersample too")
        parts: list[torch.utils.data.Dataset] = []
        if include_skimage:
            parts.append(photo(SkimagePhotosSource()))
            for r in range(1, repeat):
                copy = SkimagePhotosSource()
                copy.ids = [f"{i}#{r}" for i in copy.ids]
                parts.append(photo(copy))
        if include_street:
            parts.append(photo(StreetSampleSource(stride=street_stride)))
        if deadleaves:
            parts.append(DeadLeavesSource(deadleaves, size=deadleaves_size, seed=seed, **deadleaves_kwargs))
        if n_aa:
            aa = DeadLeavesSource(n_aa, size=deadleaves_size, seed=seed, **{**deadleaves_kwargs, "supersample": 2})
            aa.ids = [f"{i}#2" for i in aa.ids]
            parts.append(aa)
        if not parts:
            raise ValueError("DefaultSource is empty: enable skimage/street photos or ask for deadleaves > 0")
        super().__init__(parts)


#: Every option of :class:`DefaultSource` (its arguments and :data:`DEADLEAVES_OPTIONS`).
_DEFAULT_OPTIONS: tuple[str, ...] = (*_arguments(DefaultSource.__init__), *DEADLEAVES_OPTIONS)

#: The built-in sources by name.
_BUILT_IN = ("default", "deadleaves", "skimage", "street")


def _source_kind(spec: str | Path, must_exist: bool = True) -> tuple[str, Path | None]:
    """What ``spec`` names: ``("default" | "deadleaves" | "skimage" | "street", None)``, ``("frames", folder)``,
    ``("folder", path)`` or ``("video", path)``; ``("missing", path)`` for a path that does not exist when not
    ``must_exist``. The errors of :func:`build_source` for a spec that names nothing it can read."""
    if isinstance(spec, str):
        key = spec.strip().lower()
        if key in _BUILT_IN:
            return key, None
        if spec.startswith("frames:"):
            return "frames", Path(spec[len("frames:"):])
    elif not isinstance(spec, Path):
        raise TypeError(f"spec must be a str or a Path, got {type(spec).__name__}")
    path = Path(spec)
    if not path.exists():
        if not must_exist:
            return "missing", path
        raise FileNotFoundError(
            f"image source {str(spec)!r} is neither a built-in source ('default', 'deadleaves', 'skimage', "
            "'street') nor an existing folder or video file"
        )
    if path.is_dir():
        return "folder", path
    if path.suffix.lower() in VIDEO_EXTENSIONS:
        return "video", path
    raise ValueError(
        f"cannot use {path} as an image source: expected a folder of images or a video file "
        f"({', '.join(VIDEO_EXTENSIONS)}); for a single image use camhealth.data.read_image"
    )


#: For each kind of source: the class it builds (named in messages) and the options it takes besides
#: ``area_downsample`` and ``bit_depth``.
_KIND_OPTIONS: dict[str, tuple[str, tuple[str, ...]]] = {
    "deadleaves": ("DeadLeavesSource", _arguments(DeadLeavesSource.__init__)),
    "skimage": ("SkimagePhotosSource", _arguments(SkimagePhotosSource.__init__)),
    "street": ("StreetSampleSource", _arguments(StreetSampleSource.__init__)),
    "frames": ("FrameSequence", _arguments(FrameSequence.__init__, ("path", "bit_depth"))),
    "folder": ("ImageFolderSource", _arguments(ImageFolderSource.__init__, ("root", "bit_depth"))),
    # (a video file has no file extensions to choose)
    "video": ("FrameSequence", _arguments(FrameSequence.__init__, ("path", "bit_depth", "extensions"))),
}


def source_options(spec: str | Path) -> tuple[str, ...]:
    """The keyword arguments :func:`build_source` takes for ``spec`` (sorted): ``"default"``: :class:`DefaultSource`'s
    and :data:`DEADLEAVES_OPTIONS`; ``"deadleaves"``: :class:`DeadLeavesSource`'s; a folder: ``recursive``,
    ``extensions``; a video file or ``"frames:<folder>"``: the frame range (``stride``, ``max_frames``, ``start``;
    a frames folder also ``extensions``); ``"skimage"``: ``names``; ``"street"``: ``stride``, ``max_frames``. Each
    also takes ``bit_depth`` and all but ``"deadleaves"`` ``area_downsample``."""
    kind, _ = _source_kind(spec)
    if kind == "default":
        return tuple(sorted({*_DEFAULT_OPTIONS, "bit_depth"}))
    extra = ("bit_depth",) if kind == "deadleaves" else ("area_downsample", "bit_depth")
    return tuple(sorted({*_KIND_OPTIONS[kind][1], *extra}))


def _describe(spec: str | Path, kind: str) -> str:
    if kind in _BUILT_IN:
        return f"the built-in source {kind!r} ({'DefaultSource' if kind == 'default' else _KIND_OPTIONS[kind][0]})"
    noun = {"frames": "frame folder", "folder": "image folder", "video": "video file"}[kind]
    return f"the {noun} {str(spec)!r} ({_KIND_OPTIONS[kind][0]})"


def check_source_options(spec: str | Path, options: Mapping[str, Any], name: str = "source_kwargs") -> None:
    """Refuse an option :func:`build_source` would not use for ``spec``: a ``ValueError`` naming the unknown key(s),
    the kind of source and the allowed keys (:func:`source_options`), or, for ``"default"``, dead-leaves options
    with ``deadleaves`` = 0. Only the keys are checked (the values when the source is built); a path that does not
    exist (yet) is not checked here (:func:`build_source` names it). ``name`` starts the message."""
    if not isinstance(options, Mapping):
        raise TypeError(f"{name} = {options!r} must be a mapping of source options (e.g. {{deadleaves: 60}}) or null")
    kind, _ = _source_kind(spec, must_exist=False)
    if kind == "missing":
        return
    if kind == "default":
        _check_default_options({k: v for k, v in options.items() if k != "bit_depth"}, name)
        return
    _check_options(options, source_options(spec), name, _describe(spec, kind))


def build_source(spec: str | Path, **kwargs) -> torch.utils.data.Dataset:
    """Build an image source from a spec.

    * ``"default"`` → :class:`DefaultSource` (kwargs passed on);
    * ``"deadleaves"`` → :class:`DeadLeavesSource` (kwargs; ``n_images`` defaults to 1000);
    * ``"skimage"`` → :class:`SkimagePhotosSource`; ``"street"`` → :class:`StreetSampleSource`;
    * a folder → :class:`ImageFolderSource` (``recursive``, ``extensions``); ``"frames:<folder>"`` → the folder
      as one clip of frames (one split group);
    * a video file → its frames (``stride``, ``max_frames``, ``start``) as one clip;
    * ``area_downsample=k`` (any spec but ``"deadleaves"``): the images area-downsampled by k
      (:class:`AreaDownsampledSource`; for ``"default"`` the photos and street frames only);
    * ``bit_depth`` (``"auto"``, the default, or 1…16): the significant bits of the image files of a folder or
      ``"frames:<folder>"`` (:class:`ImageFolderSource`, :class:`FrameSequence`); any other depth than ``"auto"``
      for a built-in source or a video file is a ``ValueError`` (their scaling is fixed).

    A keyword the source does not take is a ``ValueError`` naming it and listing those it takes
    (:func:`source_options`; :func:`check_source_options`), never silently dropped.

    Every result has ``len()``, ``source[i] -> (image 1×H×W float32 in [0, 1], id)`` and ``.ids``.
    """
    kind, path = _source_kind(spec)
    if kind == "default":
        _check_default_options({k: v for k, v in kwargs.items() if k != "bit_depth"}, "build_source")
    elif not (kind == "deadleaves" and "area_downsample" in kwargs):  # (that one has its own message below)
        check_source_options(spec, kwargs, "build_source")
    bit_depth = _check_bit_depth(kwargs.pop("bit_depth", "auto"))

    def fixed_scaling(what: str) -> None:
        if bit_depth != "auto":
            raise ValueError(f"bit_depth = {bit_depth!r} applies to a folder of image files; {what} {str(spec)!r} has its own "
                             "scaling (leave bit_depth 'auto')")

    if kind == "default":
        fixed_scaling("the built-in source")
        return DefaultSource(**kwargs)
    k = check_whole(kwargs.pop("area_downsample", 1), "area_downsample", 1, 8)  # (a bool is no factor)
    if k != 1:
        if kind == "deadleaves":
            raise ValueError(f"area_downsample = {k!r}: dead leaves are rendered, not downsampled; pass supersample= instead")
        return AreaDownsampledSource(build_source(spec, bit_depth=bit_depth, **kwargs), k)
    if kind == "deadleaves":
        check_source_options(spec, kwargs, "build_source")
    if kind in ("deadleaves", "skimage", "street"):
        fixed_scaling("the built-in source")
    if kind == "deadleaves":
        kwargs.setdefault("n_images", 1000)
        return DeadLeavesSource(**kwargs)
    if kind == "skimage":
        return SkimagePhotosSource(**kwargs)
    if kind == "street":
        return StreetSampleSource(**kwargs)
    if kind == "frames":
        return FrameSequence(path, bit_depth=bit_depth, **kwargs).as_source()
    if kind == "folder":
        return ImageFolderSource(path, bit_depth=bit_depth, **kwargs)
    fixed_scaling("the video file")
    return FrameSequence(path, **kwargs).as_source()


def group_key(image_id: str) -> str:
    """Default split group of an id: ``"<clip>"`` for ``"<clip>#<digits>"`` frame ids, else the id itself."""
    m = _FRAME_ID.match(image_id)
    return m.group(1) if m else image_id


def _unit_hash(seed: int, key: str) -> float:
    # surrogateescape: an id from a file name that is not valid UTF-8 (its bytes kept as surrogates by os.listdir)
    # hashes its original bytes; a valid name gives the same digest as plain UTF-8
    text = f"{seed}\x1f{key}"
    try:
        data = text.encode("utf-8", "surrogateescape")
    except UnicodeEncodeError:  # another lone surrogate (an id made in memory): still one fixed byte string
        data = text.encode("utf-8", "surrogatepass")
    digest = hashlib.blake2b(data, digest_size=8).digest()
    return int.from_bytes(digest, "big") / 2.0**64


def split_ids(
    ids: Sequence[str],
    val_fraction: float = 0.1,
    test_fraction: float = 0.1,
    seed: int = 0,
    group_key: Callable[[str], str] = group_key,
) -> dict[str, list[int]]:
    """Deterministic, leak-free train/val/test split by source image (or clip).

    Each group key ``g`` gets ``u = blake2b(f"{seed}␟{g}") / 2⁶⁴ ∈ [0, 1)``; ``u < test_fraction`` → test,
    ``u < test_fraction + val_fraction`` → val, else train. The assignment of an id depends only on its
    group key and ``seed`` — adding, removing or reordering other ids never moves it — and all ids of a
    group share one split. The fractions are therefore expected values: with few groups (the default
    source has 11: 10 photos + 1 street clip) the realised split sizes vary, and a split may be empty.

    Returns:
        ``{"train": [...], "val": [...], "test": [...]}``: ascending indices into ``ids``.
    """
    if isinstance(ids, str):
        raise TypeError("ids must be a sequence of id strings, not a single string")
    for name, f in (("val_fraction", val_fraction), ("test_fraction", test_fraction)):
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not math.isfinite(f) or not 0.0 <= f <= 1.0:
            raise ValueError(f"{name} = {f!r} must be a number in [0, 1]")
    if val_fraction + test_fraction > 1.0:
        raise ValueError(
            f"val_fraction + test_fraction = {val_fraction + test_fraction:g} must be <= 1"
        )
    seed = check_int(seed, "seed", 0)
    out: dict[str, list[int]] = {s: [] for s in SPLITS}
    cache: dict[str, str] = {}
    for i, image_id in enumerate(ids):
        if not isinstance(image_id, str):
            raise TypeError(f"ids[{i}] must be a str, got {type(image_id).__name__}")
        g = group_key(image_id)
        split = cache.get(g)
        if split is None:
            u = _unit_hash(seed, g)
            split = "test" if u < test_fraction else "val" if u < test_fraction + val_fraction else "train"
            cache[g] = split
        out[split].append(i)
    return out
