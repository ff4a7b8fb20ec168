"""Frozen object detectors and their accuracy: the downstream application of thesis Sec. 4.4.

- :mod:`~camhealth.detection.protocol` — ``detector(images B×1×H×W) -> list of {boxes, scores, labels}``
  and :func:`validate_detections` (clear errors for malformed output).
- :mod:`~camhealth.detection.hog` — OpenCV's built-in HOG people detector (no download).
- :mod:`~camhealth.detection.torch_adapter` — any ``nn.Module`` detector, frozen.
- :mod:`~camhealth.detection.average_precision` — COCO AP at IoU 0.5 over detections with score >= 0.5
  (pycocotools, App. A.1).
- :mod:`~camhealth.detection.pseudo_ground_truth` — COCO annotation files, or pseudo ground truth from
  the detector on the clean frame (score >= 0.6).

>>> from camhealth.detection import HOGPeopleDetector, pseudo_ground_truth, average_precision
>>> det = HOGPeopleDetector()
>>> gt = pseudo_ground_truth(det, clean)                       # clean: B×1×H×W in [0, 1]
>>> ap = average_precision(det(corrupted), gt, clean.shape[-2:])
"""

from camhealth.detection.average_precision import (
    IOU_THRESHOLD,
    SCORE_THRESHOLD,
    APResult,
    GroundTruth,
    average_precision,
    coco_ground_truth,
    coco_results,
    evaluate_detections,
    validate_ground_truth,
)
from camhealth.detection.hog import PERSON_LABEL, HOGPeopleDetector, margin_to_score, score_to_margin
from camhealth.detection.protocol import (
    DETECTION_KEYS,
    Detection,
    Detector,
    empty_detection,
    filter_by_score,
    validate_detections,
)
from camhealth.detection.pseudo_ground_truth import (
    PSEUDO_GT_SCORE,
    ground_truth_for,
    load_coco_annotations,
    pseudo_ground_truth,
)
from camhealth.detection.torch_adapter import TorchDetector, freeze

__all__ = [
    "Detection", "Detector", "DETECTION_KEYS", "validate_detections", "empty_detection", "filter_by_score",
    "HOGPeopleDetector", "PERSON_LABEL", "margin_to_score", "score_to_margin",
    "TorchDetector", "freeze",
    "GroundTruth", "APResult", "IOU_THRESHOLD", "SCORE_THRESHOLD", "coco_ground_truth", "coco_results",
    "evaluate_detections", "average_precision", "validate_ground_truth",
    "PSEUDO_GT_SCORE", "pseudo_ground_truth", "load_coco_annotations", "ground_truth_for",
]
