"""Average precision at IoU 0.5 of detections with confidence >= 0.5, by the COCO evaluator (pycocotools).

Thesis App. A.1 (Eq. A.1–A.3): detections with score p(B_D) < 0.5 are dropped; a detection is a true
positive if it overlaps a not-yet-matched ground-truth box with IoU > 0.5 (greedy matching in order of
decreasing score); AP is the area under the precision–recall curve. camhealth does not hand-write this:
it builds COCO-format dicts from the tensors and runs ``pycocotools.cocoeval.COCOeval`` (``iouType =
"bbox"``) with

* ``iouThrs = [0.5]`` — COCO matches at IoU >= 0.5 (the thesis writes > 0.5; the two differ only for a
  box pair at exactly 0.5);
* one area range (all sizes), ``maxDets = [max_detections]``: as in COCO, the highest-scoring
  ``max_detections`` detections per image *and category* are evaluated (with 2 categories and
  ``max_detections = 1`` two detections of an image count);
* COCO's 101-point interpolated precision (precision made monotone, sampled at recall 0, 0.01, …, 1):
  the numerical integration of Eq. A.3. AP is the mean over categories that have ground truth.

Degenerate cases, explicit: no ground-truth box in any image → AP is NaN (undefined; ``n_gt = 0``);
ground truth but no detection with score >= 0.5 → AP 0. Boxes are xyxy pixels (COCO stores xywh; the
conversion is done here); a detection or ground-truth box outside its image's W×H by more than 1 px is refused,
naming the image and the box (xywh or normalised boxes, or the wrong image size, would otherwise score a plausible
but wrong AP). Image ids are 1…N in the order of the lists. A ground-truth box of zero width or height can never be
matched (its IoU with every box is 0), so it is refused (:func:`validate_ground_truth`) unless marked
``iscrowd`` (ignored). The score threshold is applied to the scores as given (float64 included), before their
conversion to float32.
"""

from __future__ import annotations

import contextlib
import io
import math
import numbers
from dataclasses import dataclass, field
from typing import Mapping, Sequence, TypedDict

import numpy as np
import torch

from camhealth.detection.protocol import Detection, check_boxes_in_image, validate_detections

__all__ = [
    "GroundTruth",
    "APResult",
    "IOU_THRESHOLD",
    "SCORE_THRESHOLD",
    "coco_ground_truth",
    "coco_results",
    "evaluate_detections",
    "average_precision",
    "validate_ground_truth",
]

#: IoU at which a detection matches a ground-truth box (thesis App. A.1).
IOU_THRESHOLD = 0.5
#: Minimum detection confidence that enters the evaluation (thesis App. A.1).
SCORE_THRESHOLD = 0.5


class GroundTruth(TypedDict, total=False):
    """Ground truth of one image: ``boxes`` (N, 4) xyxy px, ``labels`` (N,) int64 COCO category ids;
    optional ``iscrowd`` (N,) bool (boxes that may be matched without counting, COCO semantics)."""

    boxes: torch.Tensor
    labels: torch.Tensor
    iscrowd: torch.Tensor


@dataclass
class APResult:
    """Result of :func:`evaluate_detections`.

    Attributes:
        ap: AP at IoU 0.5 in [0, 1] (mean over categories with ground truth); NaN without ground truth.
        per_category: AP per category id with ground truth.
        precision: (101,) interpolated precision at recall 0, 0.01, …, 1 (mean over categories; −1 where
            undefined, as in COCO).
        n_gt: number of ground-truth boxes (non-crowd).
        n_detections: detections that were evaluated: those with score >= the threshold, at most
            ``max_detections`` per image and category (the highest-scoring ones).
        n_images: number of images.
    """

    ap: float
    per_category: dict[int, float] = field(default_factory=dict)
    precision: np.ndarray = field(default_factory=lambda: np.full(101, -1.0))
    n_gt: int = 0
    n_detections: int = 0
    n_images: int = 0


def validate_ground_truth(ground_truth: object, name: str = "ground_truth") -> list[GroundTruth]:
    """Check ground truth (list of {boxes, labels} per image) and return it canonically (CPU tensors).

    Besides the checks of :func:`~camhealth.detection.protocol.validate_detections`, a box of zero width or height
    (x2 = x1 or y2 = y1) that is not ``iscrowd`` is refused, naming the image and the box: its IoU with every
    detection is 0, so it could never be matched and even a perfect detector would score it as missed.
    """
    if isinstance(ground_truth, Mapping) or not isinstance(ground_truth, (list, tuple)):
        raise TypeError(f"{name} must be a list with one dict {{boxes, labels}} per image, got {type(ground_truth).__name__}")
    dets = []
    for i, gt in enumerate(ground_truth):
        if not isinstance(gt, Mapping):
            raise TypeError(f"{name}[{i}] must be a dict with keys ['boxes', 'labels'], got {type(gt).__name__}")
        missing = [k for k in ("boxes", "labels") if k not in gt]
        if missing:
            raise ValueError(f"{name}[{i}] is missing key(s) {missing}; it has {sorted(map(str, gt))}")
        boxes = gt["boxes"]
        n = len(boxes) if not isinstance(boxes, torch.Tensor) else (boxes.shape[0] if boxes.ndim else 0)
        dets.append({"boxes": boxes, "labels": gt["labels"], "scores": torch.ones(n)})
    checked = validate_detections(dets, name=name)
    out: list[GroundTruth] = []
    for i, (d, gt) in enumerate(zip(checked, ground_truth)):
        g = GroundTruth(boxes=d["boxes"], labels=d["labels"])
        crowd = torch.zeros(d["boxes"].shape[0], dtype=torch.bool)
        if "iscrowd" in gt:
            crowd = torch.as_tensor(gt["iscrowd"]).reshape(-1).to(torch.bool)
            if crowd.shape[0] != d["boxes"].shape[0]:
                raise ValueError(f"{name}[{i}]['iscrowd'] has {crowd.shape[0]} values for {d['boxes'].shape[0]} boxes")
            g["iscrowd"] = crowd
        b = d["boxes"]
        flat = ((b[:, 2] <= b[:, 0]) | (b[:, 3] <= b[:, 1])) & ~crowd
        if bool(flat.any()):
            j = int(torch.nonzero(flat)[0, 0])
            raise ValueError(
                f"{name}[{i}]['boxes'][{j}] = {b[j].tolist()} has zero width or height: a ground-truth box of no area "
                "can never be matched (IoU 0 with every detection); drop it, or mark it iscrowd to ignore it"
            )
        out.append(g)
    return out


def _xywh(boxes: torch.Tensor) -> list[list[float]]:
    b = boxes.double()
    return torch.stack([b[:, 0], b[:, 1], b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]], dim=1).tolist()


def _is_number(v: object) -> bool:
    if isinstance(v, torch.Tensor):
        return v.ndim == 0
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _pixels(v: object, where: str) -> int:
    """A size in px: a whole number >= 1 (int, integer-valued float, numpy scalar or 0-d tensor)."""
    x = v.item() if isinstance(v, (torch.Tensor, np.generic)) else v
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) or x != int(x) or x < 1:
        raise ValueError(f"{where} = {x!r} must be a whole number of pixels >= 1")
    return int(x)


def _image_sizes(image_sizes: object, n: int) -> list[tuple[int, int]]:
    """One (H, W) per image from one (H, W) for all or one per image; sizes may be ints, integer-valued floats, numpy
    scalars or tensors ((2,) for one size, (N, 2) for one per image)."""
    if isinstance(image_sizes, torch.Tensor) and image_sizes.ndim in (1, 2):
        image_sizes = image_sizes.tolist()
    if isinstance(image_sizes, (str, bytes, Mapping)) or not isinstance(image_sizes, (Sequence, np.ndarray)):
        raise TypeError(f"image_sizes must be (H, W) or a list of (H, W), one per image, got {type(image_sizes).__name__}")
    sizes = list(image_sizes)
    if len(sizes) == 2 and all(_is_number(s) for s in sizes):
        return [(_pixels(sizes[0], "image_sizes H"), _pixels(sizes[1], "image_sizes W"))] * n
    if len(sizes) != n:
        raise ValueError(f"image_sizes has {len(sizes)} entries for {n} images; give one (H, W) or one per image")
    out = []
    for i, s in enumerate(sizes):
        s = s.tolist() if isinstance(s, (torch.Tensor, np.ndarray)) else s
        if isinstance(s, (str, bytes)) or not isinstance(s, Sequence) or len(s) != 2:
            raise ValueError(f"image_sizes[{i}] = {s!r} must be one (H, W)")
        out.append((_pixels(s[0], f"image_sizes[{i}] H"), _pixels(s[1], f"image_sizes[{i}] W")))
    return out


def _real(v: object) -> float | None:
    """``v`` (a real number, NumPy scalar or 0-d tensor; not a bool) as a float, else ``None``."""
    if isinstance(v, (torch.Tensor, np.ndarray)) and v.ndim == 0:
        v = v.item()
    elif isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        return None
    return float(v)


def _check_in_images(entries: Sequence[Mapping], sizes: Sequence[tuple[int, int]], name: str) -> None:
    """Every box of ``entries[i]`` within the W×H of ``sizes[i] = (H, W)`` up to 1 px, else ``ValueError`` naming the
    image, the box and the W×H (:func:`~camhealth.detection.protocol.check_boxes_in_image`)."""
    for i, (e, size) in enumerate(zip(entries, sizes)):
        check_boxes_in_image(e["boxes"], size, f"{name}[{i}]['boxes']")


def coco_ground_truth(
    ground_truth: Sequence[GroundTruth],
    image_sizes: Sequence[int] | Sequence[Sequence[int]],
    categories: Sequence[int] | None = None,
) -> dict:
    """COCO dataset dict (``images``, ``annotations``, ``categories``) of per-image ground truth.

    Args:
        ground_truth: one {boxes (N, 4) xyxy px, labels (N,)} per image; image ids are 1…N.
        image_sizes: ``(H, W)`` for all images or one per image [px]; every box must lie within its image up to
            1 px (``ValueError`` naming the image, the box and the W×H).
        categories: category ids to declare (default: the labels that occur, or [1] if none).
    """
    gts = validate_ground_truth(ground_truth)
    sizes = _image_sizes(image_sizes, len(gts))
    _check_in_images(gts, sizes, "ground_truth")
    cats = sorted({int(c) for g in gts for c in g["labels"].tolist()}) if categories is None else sorted(set(categories))
    cats = cats or [1]
    images, anns = [], []
    for i, (g, (h, w)) in enumerate(zip(gts, sizes), start=1):
        images.append({"id": i, "height": h, "width": w, "file_name": f"{i}"})
        crowd = g.get("iscrowd", torch.zeros(g["boxes"].shape[0], dtype=torch.bool)).tolist()
        for box, lab, c in zip(_xywh(g["boxes"]), g["labels"].tolist(), crowd):
            anns.append(
                {"id": len(anns) + 1, "image_id": i, "category_id": int(lab), "bbox": box,
                 "area": float(box[2] * box[3]), "iscrowd": int(c)}
            )
    return {"images": images, "annotations": anns, "categories": [{"id": c, "name": str(c)} for c in cats]}


def coco_results(detections: Sequence[Detection], score_threshold: float = SCORE_THRESHOLD) -> list[dict]:
    """COCO result list (``image_id``, ``category_id``, ``bbox`` xywh, ``score``) of the detections with
    score >= ``score_threshold`` (compared on the scores as given, float64 included); image ids are 1…N in list
    order."""
    dets = validate_detections(list(detections), min_score=score_threshold)
    out = []
    for i, d in enumerate(dets, start=1):
        for box, s, lab in zip(_xywh(d["boxes"]), d["scores"].tolist(), d["labels"].tolist()):
            out.append({"image_id": i, "category_id": int(lab), "bbox": box, "score": float(s)})
    return out


def evaluate_detections(
    detections: Sequence[Detection],
    ground_truth: Sequence[GroundTruth],
    image_sizes: Sequence[int] | Sequence[Sequence[int]],
    iou_threshold: float = IOU_THRESHOLD,
    score_threshold: float = SCORE_THRESHOLD,
    max_detections: int = 100,
) -> APResult:
    """COCO AP at one IoU threshold of detections with score >= ``score_threshold`` against ground truth.

    Args:
        detections: one :class:`~camhealth.detection.protocol.Detection` per image (validated here).
        ground_truth: one {boxes, labels} per image, same order.
        image_sizes: ``(H, W)`` of all images or one per image [px]. Every detection and ground-truth box must lie
            within its image's ``[0, W] × [0, H]`` up to 1 px, else ``ValueError`` naming the image, the box and the
            W×H (a box outside means xywh or normalised boxes, or the wrong image size, which would give a plausible
            but wrong AP).
        iou_threshold: IoU a match needs (>=), default 0.5.
        score_threshold: minimum confidence, default 0.5 (compared on the scores as given, before their
            conversion to float32).
        max_detections: highest-scoring detections per image *and category* that are evaluated (COCO's
            ``maxDets``; see the module docstring).
    """
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    iou = _real(iou_threshold)
    if iou is None or not 0.0 < iou < 1.0:
        raise ValueError(f"iou_threshold = {iou_threshold!r} must lie in (0, 1)")
    score = _real(score_threshold)
    if score is None or not 0.0 <= score <= 1.0:
        raise ValueError(f"score_threshold = {score_threshold!r} must lie in [0, 1]")
    iou_threshold, score_threshold = iou, score
    max_det = _real(max_detections)
    if max_det is None or not math.isfinite(max_det) or max_det != int(max_det) or max_det < 1:
        raise ValueError(f"max_detections = {max_detections!r} must be an integer >= 1")
    max_detections = int(max_det)
    detections = list(detections)
    dets = validate_detections(detections, name="detections")
    gts = validate_ground_truth(list(ground_truth))
    if len(dets) != len(gts):
        raise ValueError(f"{len(dets)} detection entries for {len(gts)} ground-truth entries; give one per image")
    if not gts:
        raise ValueError("evaluate_detections needs at least one image")
    sizes = _image_sizes(image_sizes, len(gts))
    _check_in_images(dets, sizes, "detections")  # a box outside its image: xywh or normalised boxes, or wrong sizes
    _check_in_images(gts, sizes, "ground_truth")
    labels = {int(c) for g in gts for c in g["labels"].tolist()} | {int(c) for d in dets for c in d["labels"].tolist()}
    gt_dict = coco_ground_truth(gts, sizes, categories=sorted(labels) or [1])
    results = coco_results(detections, score_threshold)  # thresholded on the scores as given, not on dets' float32
    n_gt = sum(1 for a in gt_dict["annotations"] if not a["iscrowd"])
    per_cell: dict[tuple[int, int], int] = {}
    for r in results:
        key = (r["image_id"], r["category_id"])
        per_cell[key] = per_cell.get(key, 0) + 1
    n_eval = sum(min(c, int(max_detections)) for c in per_cell.values())  # COCO's maxDets cut per image and category
    out = APResult(ap=float("nan"), n_gt=n_gt, n_detections=n_eval, n_images=len(gts))
    if n_gt == 0:
        return out
    quiet = io.StringIO()
    with contextlib.redirect_stdout(quiet):
        coco_gt = COCO()
        coco_gt.dataset = gt_dict
        coco_gt.createIndex()
        if results:
            coco_dt = coco_gt.loadRes(results)
        else:  # loadRes cannot take an empty list: an empty result set with the same images
            coco_dt = COCO()
            coco_dt.dataset = {"images": gt_dict["images"], "categories": gt_dict["categories"], "annotations": []}
            coco_dt.createIndex()
        ev = COCOeval(coco_gt, coco_dt, iouType="bbox")
        ev.params.imgIds = [im["id"] for im in gt_dict["images"]]
        ev.params.catIds = [c["id"] for c in gt_dict["categories"]]
        ev.params.iouThrs = np.array([float(iou_threshold)])
        ev.params.maxDets = [int(max_detections)]
        ev.params.areaRng = [[0.0, 1e10]]
        ev.params.areaRngLbl = ["all"]
        ev.evaluate()
        ev.accumulate()
    prec = ev.eval["precision"][0, :, :, 0, 0]  # (R=101, K)
    per_cat = {}
    for k, cat in enumerate(ev.params.catIds):
        p = prec[:, k]
        if bool((p > -1).any()):
            per_cat[int(cat)] = float(p[p > -1].mean())
    out.per_category = per_cat
    valid = prec > -1
    out.precision = np.where(valid.any(1), np.where(valid, prec, 0).sum(1) / np.maximum(valid.sum(1), 1), -1.0)
    out.ap = float(np.mean(list(per_cat.values()))) if per_cat else float("nan")
    if not math.isnan(out.ap):
        out.ap = min(max(out.ap, 0.0), 1.0)
    return out


def average_precision(
    detections: Sequence[Detection],
    ground_truth: Sequence[GroundTruth],
    image_sizes: Sequence[int] | Sequence[Sequence[int]],
    iou_threshold: float = IOU_THRESHOLD,
    score_threshold: float = SCORE_THRESHOLD,
) -> float:
    """AP in [0, 1] (NaN without ground truth); see :func:`evaluate_detections`."""
    return evaluate_detections(detections, ground_truth, image_sizes, iou_threshold, score_threshold).ap
