"""OpenCV's built-in HOG people detector (Dalal & Triggs 2005) as a frozen camhealth detector.

The detector is the linear SVM that ships inside ``opencv-python-headless`` (``cv2.HOGDescriptor_get
DefaultPeopleDetector()``, 64×128 px window, trained on INRIA pedestrians): nothing is downloaded and
nothing is trained. It is the default downstream application of the IOPC sweep on the embedded street
clip, whose pedestrians are 130–150 px tall at the clip's native 768×576 px.

Pipeline per image: ``B×1×H×W`` float in [0, 1] → 8-bit DN ``round(255·x)`` → optional resize by
``upscale`` (for objects smaller than the 128 px window) → ``HOGDescriptor.detectMultiScale`` (sliding
window over an image pyramid, overlapping hits merged by ``groupRectangles`` with ``group_threshold``) →
boxes scaled back to input pixels.

Score mapping. ``detectMultiScale`` returns, per box, the SVM decision value (margin) ``w``: 0 on the
decision boundary, larger = more confident, unbounded. camhealth needs confidences in [0, 1] for the
App. A.1 filter (score >= 0.5), so the score is the logistic function of the margin,

    score = 1 / (1 + exp(−w)),

monotone in ``w`` (the AP ranking is unchanged) with score 0.5 ⇔ w = 0 — the SVM's own boundary, which is
also OpenCV's default ``hitThreshold``. So the evaluation threshold 0.5 keeps exactly the windows the SVM
classifies as people. Examples: w = 0.41 → 0.60 (the pseudo-ground-truth threshold, see
:mod:`~camhealth.detection.pseudo_ground_truth`), w = 1 → 0.73, w = 2 → 0.88. Boxes with w below
``hit_threshold`` (default 0, i.e. score < 0.5) are never returned.

OpenCV runs one image at a time (there is no batched HOG), so :meth:`HOGPeopleDetector.__call__` loops
over the batch; ≈ 0.1 s per 768×576 frame on one CPU core.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import numpy as np
import torch

from camhealth._validation import check_image
from camhealth.detection.protocol import Detection, validate_detections

__all__ = ["HOGPeopleDetector", "margin_to_score", "score_to_margin", "PERSON_LABEL"]

#: COCO category id of "person": the label of every HOG detection.
PERSON_LABEL = 1


def margin_to_score(margin: np.ndarray | torch.Tensor | float) -> np.ndarray | torch.Tensor | float:
    """Logistic map of the SVM margin w to a confidence in (0, 1): ``1 / (1 + exp(−w))``."""
    if isinstance(margin, torch.Tensor):
        return torch.sigmoid(margin)
    if isinstance(margin, np.ndarray):
        return 1.0 / (1.0 + np.exp(-margin))
    w = float(margin)
    try:
        return 1.0 / (1.0 + math.exp(-w))
    except OverflowError:  # w < −709: exp(−w) is beyond float64, and the score is exp(w) / (1 + exp(w)) = exp(w)
        return math.exp(w)


def score_to_margin(score: float) -> float:
    """Inverse of :func:`margin_to_score`: the margin ``log(s / (1 − s))`` of a score s in (0, 1)."""
    if not 0.0 < score < 1.0:
        raise ValueError(f"score = {score!r} must lie in the open interval (0, 1)")
    return math.log(score / (1.0 - score))


def _real(v: object) -> bool:
    """A real number (Python, NumPy or a 0-d tensor), not a bool."""
    if isinstance(v, torch.Tensor):
        return v.ndim == 0 and not v.dtype.is_complex and v.dtype != torch.bool
    return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_))


def _whole(v: object) -> bool:
    """A finite whole number (``int``, or an integer-valued float, NumPy scalar or 0-d tensor), not a bool."""
    return _real(v) and math.isfinite(float(v)) and float(v) == int(v)


class HOGPeopleDetector:
    """Frozen HOG + linear-SVM people detector of OpenCV, on camhealth image batches.

    Args:
        win_stride: sliding-window step (x, y) [px]; a multiple of the 8 px HOG cell.
        padding: border added around the image before the window slides (x, y) [px].
        scale: image-pyramid step (> 1).
        hit_threshold: minimum SVM margin of a window (0 = the SVM boundary = score 0.5).
        group_threshold: ``groupRectangles`` minimum cluster size − 1 (0: no grouping, raw windows).
        upscale: resize factor applied before detection (> 1 for people smaller than the 128 px window);
            boxes are returned in the input's pixels.
        num_threads: OpenCV threads (``cv2.setNumThreads``); ``None`` leaves OpenCV's setting.

    Call: ``detector(images)`` with images ``B×1×H×W`` float in [0, 1] → list of B
    :class:`~camhealth.detection.protocol.Detection` (label 1 = person).
    """

    frozen = True
    name = "opencv-hog-people"

    def __init__(
        self,
        win_stride: tuple[int, int] = (8, 8),
        padding: tuple[int, int] = (8, 8),
        scale: float = 1.05,
        hit_threshold: float = 0.0,
        group_threshold: int = 2,
        upscale: float = 1.0,
        num_threads: int | None = None,
    ) -> None:
        import cv2

        for nm, v in (("win_stride", win_stride), ("padding", padding)):
            pair = tuple(v) if isinstance(v, (tuple, list, np.ndarray, torch.Tensor)) else ()
            if len(pair) != 2 or not all(_whole(c) and c >= 0 for c in pair):
                raise ValueError(f"{nm} = {v!r} must be two non-negative integers (x, y) in px")
        if any(int(c) % 8 for c in win_stride) or 0 in tuple(int(c) for c in win_stride):
            raise ValueError(f"win_stride = {tuple(win_stride)!r} must be positive multiples of the 8 px HOG cell")
        if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 1.0):
            raise ValueError(f"scale = {scale!r} must be a pyramid step > 1")
        if not (_real(hit_threshold) and math.isfinite(hit_threshold)):
            raise ValueError(f"hit_threshold = {hit_threshold!r} must be finite (an SVM margin)")
        if not _whole(group_threshold) or group_threshold < 0:
            raise ValueError(f"group_threshold = {group_threshold!r} must be an integer >= 0")
        if not (isinstance(upscale, (int, float)) and math.isfinite(upscale) and 0.1 <= upscale <= 8.0):
            raise ValueError(f"upscale = {upscale!r} must be a resize factor in [0.1, 8]")
        self.win_stride = tuple(int(c) for c in win_stride)
        self.padding = tuple(int(c) for c in padding)
        self.scale = float(scale)
        self.hit_threshold = float(hit_threshold)
        self.group_threshold = int(group_threshold)
        self.upscale = float(upscale)
        if num_threads is not None:
            cv2.setNumThreads(int(num_threads))
        self._cv2 = cv2
        self._hog = cv2.HOGDescriptor()
        self._hog.setSVMDetector(cv2.HOGDescriptor_getDefaultPeopleDetector())

    def config(self) -> dict[str, Any]:
        """Settings, for provenance records."""
        return {
            "name": self.name,
            "opencv": self._cv2.__version__,
            "win_stride": list(self.win_stride),
            "padding": list(self.padding),
            "scale": self.scale,
            "hit_threshold": self.hit_threshold,
            "group_threshold": self.group_threshold,
            "upscale": self.upscale,
            "score": "1/(1+exp(-svm_margin))",
        }

    def detect_uint8(self, image: np.ndarray) -> Detection:
        """Detections on one H×W uint8 gray image (boxes in its pixels)."""
        if image.dtype != np.uint8 or image.ndim != 2:
            raise ValueError(f"expected an H×W uint8 image, got {image.dtype} with shape {image.shape}")
        src = image
        if self.upscale != 1.0:
            h, w = image.shape
            size = (max(1, round(w * self.upscale)), max(1, round(h * self.upscale)))
            interp = self._cv2.INTER_LINEAR if self.upscale > 1 else self._cv2.INTER_AREA
            src = self._cv2.resize(image, size, interpolation=interp)
        if src.shape[0] < 128 or src.shape[1] < 64:  # smaller than the detection window: nothing to find
            rects, weights = np.zeros((0, 4)), np.zeros((0,))
        else:
            rects, weights = self._hog.detectMultiScale(
                src,
                hitThreshold=self.hit_threshold,
                winStride=self.win_stride,
                padding=self.padding,
                scale=self.scale,
                groupThreshold=self.group_threshold,
            )
        rects = np.asarray(rects, dtype=np.float64).reshape(-1, 4) / self.upscale
        margins = np.asarray(weights, dtype=np.float64).reshape(-1)
        boxes = np.concatenate([rects[:, :2], rects[:, :2] + rects[:, 2:]], axis=1)  # xywh → xyxy
        h, w = image.shape
        boxes[:, [0, 2]] = boxes[:, [0, 2]].clip(0, w)
        boxes[:, [1, 3]] = boxes[:, [1, 3]].clip(0, h)
        order = np.argsort(-margins, kind="stable")
        return Detection(
            boxes=torch.as_tensor(boxes[order], dtype=torch.float32),
            scores=torch.as_tensor(margin_to_score(margins[order]), dtype=torch.float32),
            labels=torch.full((len(order),), PERSON_LABEL, dtype=torch.int64),
        )

    def __call__(self, images: torch.Tensor) -> list[Detection]:
        """Detect people in ``images`` (B×1×H×W float in [0, 1]); one dict per image."""
        check_image(images, "images")
        lo, hi = torch.aminmax(images.detach())
        if lo < 0 or hi > 1:
            raise ValueError(f"images must lie in [0, 1] (DN/255), got values in [{lo.item():g}, {hi.item():g}]")
        dn = (images.detach().float().cpu()[:, 0] * 255.0).round_().to(torch.uint8).numpy()
        dets = [self.detect_uint8(np.ascontiguousarray(a)) for a in dn]
        return validate_detections(dets, len(dets), tuple(images.shape[-2:]), name=self.name)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(win_stride={self.win_stride}, padding={self.padding}, scale={self.scale}, "
            f"hit_threshold={self.hit_threshold}, group_threshold={self.group_threshold}, upscale={self.upscale})"
        )
