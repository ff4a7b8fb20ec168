"""The frozen-detector protocol: ``detector(images) -> list of {boxes, scores, labels}``.

A detector in camhealth is any callable that takes a batch of gray images ``B×1×H×W`` (float in [0, 1],
DN/255, the Kornia layout of ``conventions.md``) and returns one :class:`Detection` dict per image:

=========  ==========  =====================================================================
key        shape       meaning
=========  ==========  =====================================================================
``boxes``  (N, 4)      ``[x1, y1, x2, y2]`` in pixels of the input image (x = column, y = row),
                       x1 <= x2, y1 <= y2, float
``scores`` (N,)        confidence in [0, 1] (thesis App. A.1 filters at >= 0.5)
``labels`` (N,)        integer class ids (COCO category ids, e.g. 1 = person), int64
=========  ==========  =====================================================================

The detector is *frozen*: it is evaluated (eval mode, no gradient) and never trained by camhealth; it is
the downstream application whose accuracy the IOPCs of thesis Sec. 4.4.1 measure. Adapters:
:class:`~camhealth.detection.hog.HOGPeopleDetector` (OpenCV's built-in HOG people detector) and
:class:`~camhealth.detection.torch_adapter.TorchDetector` (any ``nn.Module``).

:func:`validate_detections` turns whatever a detector returned into this form (CPU tensors, fixed
dtypes) or raises a ``TypeError``/``ValueError`` naming the image, the key, the shape or the bad value —
a malformed detector output never reaches the COCO evaluator as a silent NaN.
"""

from __future__ import annotations

from typing import Any, Mapping, Protocol, Sequence, TypedDict, runtime_checkable

import numpy as np
import torch

__all__ = [
    "Detection", "Detector", "DETECTION_KEYS", "validate_detections", "check_boxes_in_image", "empty_detection",
    "filter_by_score",
]

#: Keys every detection dict must carry.
DETECTION_KEYS: tuple[str, ...] = ("boxes", "scores", "labels")


class Detection(TypedDict):
    """Detections of one image: ``boxes`` (N, 4) xyxy px float32, ``scores`` (N,) in [0, 1] float32,
    ``labels`` (N,) int64."""

    boxes: torch.Tensor
    scores: torch.Tensor
    labels: torch.Tensor


@runtime_checkable
class Detector(Protocol):
    """A frozen detector: ``detector(images B×1×H×W in [0, 1]) -> list of B`` :class:`Detection`."""

    def __call__(self, images: torch.Tensor) -> list[Detection]: ...


def empty_detection() -> Detection:
    """Detections of an image without objects (N = 0)."""
    return Detection(
        boxes=torch.zeros(0, 4, dtype=torch.float32),
        scores=torch.zeros(0, dtype=torch.float32),
        labels=torch.zeros(0, dtype=torch.int64),
    )


def _as_tensor(value: Any, where: str) -> torch.Tensor:
    if isinstance(value, torch.Tensor):
        return value.detach().cpu()
    if isinstance(value, (np.ndarray, list, tuple)):
        try:
            return torch.as_tensor(np.asarray(value, dtype=np.float64) if not isinstance(value, np.ndarray) else value)
        except (TypeError, ValueError) as err:
            raise TypeError(f"{where} must hold numbers, got {value!r}") from err
    raise TypeError(f"{where} must be a torch.Tensor, numpy array or list, got {type(value).__name__}")


#: Float labels must be smaller in magnitude than this (2^53): the largest range in which float64 holds every whole
#: number exactly (a larger one would not convert to the int64 category id it seems to name).
_MAX_FLOAT_LABEL = 2.0**53


def check_boxes_in_image(boxes: torch.Tensor, image_size: tuple[int, int], where: str) -> None:
    """Raise ``ValueError`` unless every xyxy box of (N, 4) ``boxes`` lies within ``[0, W] × [0, H]`` of an image of
    ``image_size = (H, W)`` px, up to 1 px; the message names ``where`` (e.g. ``"detections[2]['boxes']"``), the
    first box outside and the W×H. A box far outside the image means a wrong box format (xywh, normalised
    coordinates) or the wrong image size."""
    if boxes.numel() == 0:
        return
    h, w = image_size
    b = boxes.reshape(-1, 4)
    lo = b.min(dim=1).values
    beyond = (lo < -1) | (b[:, 0] > w + 1) | (b[:, 2] > w + 1) | (b[:, 1] > h + 1) | (b[:, 3] > h + 1)
    if bool(beyond.any()):
        j = int(torch.nonzero(beyond)[0, 0])
        raise ValueError(
            f"{where}[{j}] = {b[j].tolist()} lies outside the {w}×{h} px image (W×H; allowed: x in [0, {w}], "
            f"y in [0, {h}] up to 1 px); boxes must be [x1, y1, x2, y2] in pixels of the input image"
        )


def validate_detections(
    detections: object,
    batch_size: int | None = None,
    image_size: tuple[int, int] | None = None,
    name: str = "detector output",
    check_scores: bool = True,
    check_box_order: bool = True,
    min_score: float | None = None,
) -> list[Detection]:
    """Check a detector's output and return it in canonical form (CPU float32 boxes/scores, int64 labels).

    Args:
        detections: what the detector returned: a list/tuple with one mapping per image holding
            ``boxes`` (N, 4) xyxy px, ``scores`` (N,) and ``labels`` (N,) (tensors, arrays or lists).
        batch_size: number of images the detector was given (the list must be that long).
        image_size: ``(H, W)`` of the images; boxes must lie within ``[0, W] × [0, H]`` up to 1 px (a
            box far outside the image means a wrong box format, e.g. xywh or normalised coordinates).
        name: what to call the output in error messages.
        check_scores: require scores in [0, 1] (confidences, as the AP filter at 0.5 assumes).
        check_box_order: require x1 <= x2 and y1 <= y2 (off for a structural check of boxes that are
            still in another format, e.g. xywh).
        min_score: keep only the detections with score >= ``min_score``, compared in float64 on the scores as
            given, *before* their conversion to float32 (a float64 score of 0.49999999 rounds to 0.5 in float32
            and would pass :func:`filter_by_score` at 0.5); ``None`` keeps all.

    Raises:
        TypeError: not a list of mappings, or non-numeric content.
        ValueError: wrong length, missing keys, wrong shapes, non-finite values, x2 < x1 or y2 < y1, scores
            outside [0, 1], non-integer labels, boxes outside the image.
    """
    if isinstance(detections, Mapping) or not isinstance(detections, (list, tuple)):
        raise TypeError(
            f"{name} must be a list with one dict {{boxes, scores, labels}} per image, got {type(detections).__name__}"
        )
    if batch_size is not None and len(detections) != batch_size:
        raise ValueError(f"{name} has {len(detections)} entries but the detector was given {batch_size} image(s)")
    out: list[Detection] = []
    for i, det in enumerate(detections):
        where = f"{name}[{i}]"
        if not isinstance(det, Mapping):
            raise TypeError(f"{where} must be a dict with keys {list(DETECTION_KEYS)}, got {type(det).__name__}")
        missing = [k for k in DETECTION_KEYS if k not in det]
        if missing:
            raise ValueError(f"{where} is missing key(s) {missing}; it has {sorted(map(str, det))}")
        boxes = _as_tensor(det["boxes"], f"{where}['boxes']")
        scores = _as_tensor(det["scores"], f"{where}['scores']")
        labels = _as_tensor(det["labels"], f"{where}['labels']")
        if boxes.numel() == 0 and boxes.ndim <= 2:
            boxes = boxes.reshape(0, 4)
        if boxes.ndim != 2 or boxes.shape[1] != 4:
            raise ValueError(f"{where}['boxes'] must have shape (N, 4) [x1, y1, x2, y2], got {tuple(boxes.shape)}")
        n = boxes.shape[0]
        scores = scores.reshape(-1) if scores.ndim == 0 or (scores.ndim == 2 and scores.shape[1] == 1) else scores
        labels = labels.reshape(-1) if labels.ndim == 0 or (labels.ndim == 2 and labels.shape[1] == 1) else labels
        for key, t in (("scores", scores), ("labels", labels)):
            if t.ndim != 1 or t.shape[0] != n:
                raise ValueError(f"{where}['{key}'] must have shape ({n},) to match {n} box(es), got {tuple(t.shape)}")
        if boxes.dtype == torch.bool or boxes.dtype.is_complex:
            raise TypeError(f"{where}['boxes'] must be real numbers, got dtype {boxes.dtype}")
        boxes = boxes.to(torch.float32)
        scores64 = scores.to(torch.float64)  # the threshold is applied to these, not to the rounded float32 ones
        scores = scores.to(torch.float32)
        for key, t in (("boxes", boxes), ("scores", scores)):
            if not bool(torch.isfinite(t).all()):
                bad = t[~torch.isfinite(t)].flatten()[0].item()
                raise ValueError(f"{where}['{key}'] must be finite, got {bad}")
        if n:
            if check_box_order and bool((boxes[:, 2] < boxes[:, 0]).any() | (boxes[:, 3] < boxes[:, 1]).any()):
                j = int(torch.nonzero((boxes[:, 2] < boxes[:, 0]) | (boxes[:, 3] < boxes[:, 1]))[0, 0])
                raise ValueError(
                    f"{where}['boxes'][{j}] = {boxes[j].tolist()} has x2 < x1 or y2 < y1; boxes must be "
                    "[x1, y1, x2, y2] in pixels (convert xywh with x2 = x + w, y2 = y + h)"
                )
            if image_size is not None:
                check_boxes_in_image(boxes, image_size, f"{where}['boxes']")
            if check_scores and bool(((scores < 0) | (scores > 1)).any()):
                bad = scores[(scores < 0) | (scores > 1)][0].item()
                raise ValueError(
                    f"{where}['scores'] must be confidences in [0, 1], got {bad:g} (map raw margins/logits to "
                    "[0, 1], e.g. with a sigmoid)"
                )
        if labels.dtype.is_floating_point:
            bad = ~torch.isfinite(labels) | (labels != labels.round()) | (labels.abs() >= _MAX_FLOAT_LABEL)
            if bool(bad.any()):  # (a float of magnitude >= 2^53 is not a whole number it can hold exactly)
                raise ValueError(
                    f"{where}['labels'] must be integer class ids (whole numbers of magnitude < 2^53), got "
                    f"{labels[bad][0].item()!r} in {labels[:5].tolist()}"
                )
        elif labels.dtype == torch.bool or labels.dtype.is_complex:
            raise TypeError(f"{where}['labels'] must be integer class ids, got dtype {labels.dtype}")
        labels = labels.to(torch.int64)
        if min_score is not None:
            keep = scores64 >= float(min_score)
            boxes, scores, labels = boxes[keep], scores[keep], labels[keep]
        out.append(Detection(boxes=boxes.contiguous(), scores=scores.contiguous(), labels=labels))
    return out


def filter_by_score(detections: Sequence[Detection], threshold: float) -> list[Detection]:
    """Keep the detections with ``score >= threshold`` (thesis App. A.1: 0.5), compared on their canonical float32
    scores; to threshold scores given in float64 at their own precision use ``validate_detections(..., min_score=)``."""
    out = []
    for d in detections:
        keep = d["scores"] >= threshold
        out.append(Detection(boxes=d["boxes"][keep], scores=d["scores"][keep], labels=d["labels"][keep]))
    return out
