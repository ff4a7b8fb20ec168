"""Ground truth for the IOPC sweep: COCO-style annotation files, or pseudo ground truth from the detector.

Thesis Sec. 4.4.1 scores a detector on corrupted images against ground-truth boxes B_GT. Two sources:

1. **COCO annotation files** (when a dataset has them): :func:`load_coco_annotations` reads the standard
   ``{"images": [...], "annotations": [{"image_id", "category_id", "bbox": [x, y, w, h], "iscrowd"}]}``
   JSON and returns xyxy boxes per image file name; :func:`ground_truth_for` matches them to image ids
   or paths of a camhealth source by file name (exact, then base name, then stem). A repeated image ``id`` or
   ``file_name`` in the file, or a base name / stem that fits several annotated images, is refused
   (``ValueError``), never resolved by picking one.
2. **Pseudo ground truth** (what the embedded street clip uses — it has no annotations): the frozen
   detector itself on the *clean* frame, keeping detections with score >= ``PSEUDO_GT_SCORE`` = 0.6.
   For the HOG detector (score = sigmoid(SVM margin)) this is a margin >= 0.41, i.e. the confident
   half of its clean detections (median clean margin ≈ 0.5 on the street clip). The 0.1 gap to the
   evaluation threshold 0.5 keeps a marginal clean detection from flipping between "object" and
   "background" under a tiny corruption. With this ground truth the clean frames score AP = 1 (every
   pseudo-GT box is detected, and clean detections with 0.5 <= score < 0.6 rank below all of them, so
   they cannot lower the interpolated precision); the IOPCs then measure how much of the detector's own
   confident clean behaviour survives blur and noise — not its absolute accuracy, which needs real
   annotations. A clean detection of zero width or height is not made a ground-truth box: no detection could ever
   match it (IoU 0), so it would cap every AP below 1
   (:func:`~camhealth.detection.average_precision.validate_ground_truth` refuses such boxes; a COCO file's zero-area
   annotation that is not ``iscrowd`` is refused by :func:`load_coco_annotations`, naming it).
"""

from __future__ import annotations

import json
import math
import numbers
import os
from pathlib import Path
from typing import Iterable, Mapping, Sequence, Union

import torch

from camhealth.detection.average_precision import GroundTruth, validate_ground_truth
from camhealth.detection.protocol import Detector, validate_detections

__all__ = ["PSEUDO_GT_SCORE", "pseudo_ground_truth", "load_coco_annotations", "ground_truth_for"]

#: Score threshold of pseudo ground truth from the clean frame (see the module docstring).
PSEUDO_GT_SCORE = 0.6

PathLike = Union[str, "os.PathLike[str]"]


def pseudo_ground_truth(
    detector: Detector,
    clean_images: torch.Tensor,
    score_threshold: float = PSEUDO_GT_SCORE,
    batch_size: int = 8,
) -> list[GroundTruth]:
    """Detections of ``detector`` on clean images with score >= ``score_threshold`` (compared on the scores as the
    detector gave them) and a non-zero width and height, as ground truth.

    Args:
        detector: frozen detector (protocol of :mod:`~camhealth.detection.protocol`).
        clean_images: B×1×H×W float in [0, 1].
        score_threshold: confidence a clean detection needs to become a ground-truth box.
        batch_size: images per detector call, an integer >= 1.
    """
    if not 0.0 <= score_threshold <= 1.0:
        raise ValueError(f"score_threshold = {score_threshold!r} must lie in [0, 1]")
    if isinstance(batch_size, bool) or not isinstance(batch_size, numbers.Integral) or batch_size < 1:
        raise ValueError(f"batch_size = {batch_size!r} is out of the allowed range: an integer >= 1")
    batch_size = int(batch_size)  # (a NumPy integer included)
    if not callable(detector):
        raise TypeError(f"detector must be callable (images -> list of detections), got {type(detector).__name__}")
    if not isinstance(clean_images, torch.Tensor) or clean_images.ndim != 4:
        raise ValueError("clean_images must be a B×1×H×W tensor")
    out: list[GroundTruth] = []
    for start in range(0, clean_images.shape[0], batch_size):
        chunk = clean_images[start : start + batch_size]
        dets = validate_detections(detector(chunk), chunk.shape[0], tuple(chunk.shape[-2:]), name="detector output",
                                   min_score=score_threshold)
        for d in dets:
            b = d["boxes"]
            area = (b[:, 2] > b[:, 0]) & (b[:, 3] > b[:, 1])  # a box of no area cannot be matched: not ground truth
            out.append(GroundTruth(boxes=b[area], labels=d["labels"][area]))
    return out


def _real_number(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _image_id(v: object) -> bool:
    """An image id of a COCO file: an int or a str (not a bool, which JSON's true/false would give)."""
    return isinstance(v, (int, str)) and not isinstance(v, bool)


def load_coco_annotations(path: PathLike, category_ids: Iterable[int] | None = None) -> dict[str, GroundTruth]:
    """Read a COCO-style annotation JSON → ``{file_name: GroundTruth}`` (xyxy px boxes, category labels).

    Images without annotations get empty ground truth. ``category_ids`` keeps only those categories. An image
    ``id`` or ``file_name`` that appears twice in ``images`` is refused (``ValueError`` naming both entries): the
    boxes of one of them would otherwise be lost or attached to the other.

    The file must be JSON text (UTF-8, -16 or -32). ``images`` and ``annotations`` must be lists of objects; an image
    needs an ``id`` (int or str) and a ``file_name``, and where it gives ``width`` and ``height`` (whole numbers of
    pixels >= 1) every box of it must lie within them up to 1 px. An annotation needs an ``image_id`` of ``images``
    and a ``bbox`` ``[x, y, w, h]`` of 4 finite numbers with w, h >= 0; its ``category_id`` must be a whole number
    (``1`` where it is missing: COCO files of one class often leave it out), and ``iscrowd`` (``0`` where missing)
    0, 1, true or false. Anything else is a ``ValueError`` naming the file, the image or annotation index and the
    value.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"COCO annotation file not found: {path}")
    try:
        data = json.loads(path.read_bytes())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{path} is not valid JSON text: {err}") from err
    if not isinstance(data, Mapping) or "images" not in data or "annotations" not in data:
        raise ValueError(f"{path} is not a COCO annotation file (needs top-level 'images' and 'annotations')")
    for key in ("images", "annotations"):
        if not isinstance(data[key], list):
            raise ValueError(f"{path}: '{key}' must be a list of objects, got {type(data[key]).__name__}")
    keep = None if category_ids is None else {int(c) for c in category_ids}
    names: dict[object, str] = {}
    ids_of: dict[str, object] = {}
    sizes: dict[object, tuple[float, float]] = {}
    for j, im in enumerate(data["images"]):
        if not isinstance(im, Mapping):
            raise ValueError(f"{path}: image {j} must be an object with 'id' and 'file_name', got {im!r}")
        if "id" not in im or "file_name" not in im:
            raise ValueError(f"{path}: every image needs 'id' and 'file_name', got {im!r}")
        if not _image_id(im["id"]):
            raise ValueError(f"{path}: image {j} has id {im['id']!r}: an image id must be an int or a str")
        name = str(im["file_name"])
        if im["id"] in names:
            raise ValueError(f"{path}: image id {im['id']!r} appears twice in 'images' (file_name {names[im['id']]!r} "
                             f"and {name!r}); every image needs its own id")
        if name in ids_of:
            raise ValueError(f"{path}: file_name {name!r} appears twice in 'images' (ids {ids_of[name]!r} and "
                             f"{im['id']!r}); every image file needs one entry")
        if "width" in im or "height" in im:
            wh = (im.get("width"), im.get("height"))
            if not all(_real_number(v) and v == int(v) and v >= 1 for v in wh):
                raise ValueError(f"{path}: image {j} ({name!r}) has width, height = {wh[0]!r}, {wh[1]!r}: each must "
                                 "be a whole number of pixels >= 1")
            sizes[im["id"]] = (float(wh[1]), float(wh[0]))
        names[im["id"]] = name
        ids_of[name] = im["id"]
    boxes: dict[object, list[list[float]]] = {i: [] for i in names}
    labels: dict[object, list[int]] = {i: [] for i in names}
    crowd: dict[object, list[bool]] = {i: [] for i in names}
    for k, ann in enumerate(data["annotations"]):
        if not isinstance(ann, Mapping):
            raise ValueError(f"{path}: annotation {k} must be an object with 'image_id' and 'bbox', got {ann!r}")
        image_id = ann.get("image_id")
        if not _image_id(image_id) or image_id not in names:
            raise ValueError(f"{path}: annotation {k} refers to unknown image_id {image_id!r}")
        bbox = ann.get("bbox")
        if not isinstance(bbox, (list, tuple)) or len(bbox) != 4:
            raise ValueError(f"{path}: annotation {k} needs a 'bbox' [x, y, w, h], got {bbox!r}")
        if not all(_real_number(v) for v in bbox):
            raise ValueError(f"{path}: annotation {k} has bbox {bbox!r}: a bbox [x, y, w, h] must hold 4 finite "
                             "numbers")
        cat = ann.get("category_id", 1)
        if not (_real_number(cat) and cat == int(cat) and abs(cat) < 2**53):
            raise ValueError(f"{path}: annotation {k} has category_id {cat!r}: a category id must be a whole number "
                             "(of magnitude < 2^53)")
        cat = int(cat)
        is_crowd = ann.get("iscrowd", 0)
        if isinstance(is_crowd, str) or is_crowd not in (0, 1):
            raise ValueError(f"{path}: annotation {k} has iscrowd {is_crowd!r}: allowed are 0, 1, true and false")
        is_crowd = bool(is_crowd)
        if keep is not None and cat not in keep:
            continue
        x, y, w, h = (float(v) for v in bbox)
        if w < 0 or h < 0:
            raise ValueError(f"{path}: annotation {k} has a negative width/height in bbox {bbox}")
        if (w == 0 or h == 0) and not is_crowd:
            raise ValueError(f"{path}: annotation {k} has zero width or height in bbox {bbox}: a box of no area "
                             "can never be matched (IoU 0 with every detection); drop it or mark it iscrowd")
        if image_id in sizes:
            ih, iw = sizes[image_id]
            if min(x, y) < -1 or x + w > iw + 1 or y + h > ih + 1:
                raise ValueError(f"{path}: annotation {k} has bbox {bbox} (x, y, w, h) outside its image "
                                 f"{names[image_id]!r} of {iw:g}×{ih:g} px (W×H, up to 1 px allowed); bbox must be "
                                 "[x, y, w, h] in pixels")
        boxes[image_id].append([x, y, x + w, y + h])
        labels[image_id].append(cat)
        crowd[image_id].append(is_crowd)
    out: dict[str, GroundTruth] = {}
    for i, name in names.items():
        g = {
            "boxes": torch.tensor(boxes[i], dtype=torch.float32).reshape(-1, 4),
            "labels": torch.tensor(labels[i], dtype=torch.int64),
            "iscrowd": torch.tensor(crowd[i], dtype=torch.bool),
        }
        out[name] = validate_ground_truth([g], name=f"{path.name}:{name}")[0]
    return out


def ground_truth_for(ids: Sequence[str], annotations: Mapping[str, GroundTruth]) -> list[GroundTruth]:
    """Ground truth for each image id/path in ``ids`` from :func:`load_coco_annotations`'s mapping.

    An id matches an annotation file name exactly, by base name, or by stem (``"dir/a.png"`` ↔ ``"a.png"``
    ↔ ``"a"``), in that order. Raises ``KeyError`` naming the ids without annotations, and ``ValueError`` naming
    the id and the candidates when the base name or stem it falls back to fits more than one annotated file
    (``"cam1/0001.png"`` and ``"cam2/0001.png"`` for ``"/data/cam1/0001.png"``): give ids that match exactly.
    """
    if isinstance(ids, (str, bytes, os.PathLike)):
        raise TypeError(f"ids must be a list of image ids or paths, got the single {type(ids).__name__} {ids!r}; "
                        f"pass [{ids!r}] for one image")
    by_base: dict[str, list[str]] = {}
    by_stem: dict[str, list[str]] = {}
    for k in annotations:
        by_base.setdefault(Path(k).name, []).append(k)
        by_stem.setdefault(Path(k).stem, []).append(k)
    out, missing = [], []
    for i in ids:
        if i in annotations:
            out.append(annotations[i])
            continue
        for how, table, key in (("base name", by_base, Path(i).name), ("stem", by_stem, Path(i).stem)):
            found = table.get(key, [])
            if len(found) > 1:
                raise ValueError(f"image {i!r}: its {how} {key!r} fits {len(found)} annotated files {sorted(found)}; "
                                 "cannot tell which is its ground truth (use ids that match a file_name exactly)")
            if found:
                out.append(annotations[found[0]])
                break
        else:
            missing.append(i)
    if missing:
        raise KeyError(f"no annotations for {len(missing)} image(s), e.g. {missing[:3]}")
    return out
