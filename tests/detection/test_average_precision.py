"""COCO AP@0.5 with score >= 0.5 (App. A.1) through pycocotools; perfect = 1, empty = 0 via the adapter."""

import math

import pytest
import torch

from camhealth.detection import (
    TorchDetector,
    average_precision,
    coco_ground_truth,
    coco_results,
    evaluate_detections,
)

GT = [
    {"boxes": torch.tensor([[10.0, 10, 50, 90], [60, 20, 100, 100]]), "labels": torch.tensor([1, 1])},
    {"boxes": torch.tensor([[5.0, 5, 40, 60]]), "labels": torch.tensor([1])},
]
SIZE = (120, 160)


class GroundTruthNet(torch.nn.Module):
    """A 'detector' network that returns the ground truth (perfect) or nothing (empty), with a parameter
    so freezing is observable."""

    def __init__(self, gt, empty=False):
        super().__init__()
        self.gt, self.empty = gt, empty
        self.scale = torch.nn.Parameter(torch.ones(()))

    def forward(self, x):
        out = []
        for i in range(x.shape[0]):
            g = self.gt[i]
            n = 0 if self.empty else len(g["boxes"])
            out.append({"boxes": g["boxes"][:n] * self.scale, "scores": torch.full((n,), 0.9),
                        "labels": g["labels"][:n]})
        return out


@pytest.mark.parametrize("empty, expected", [(False, 1.0), (True, 0.0)])
def test_perfect_and_empty_detector_through_the_adapter(empty, expected):
    det = TorchDetector(GroundTruthNet(GT, empty))
    images = torch.rand(2, 1, *SIZE)
    assert average_precision(det(images), GT, SIZE) == pytest.approx(expected)


def test_known_ap_value_and_score_filter():
    # image 0: a false positive outranks the true positive of the first box; the second box is missed.
    dets = [
        {"boxes": torch.tensor([[200.0, 0, 210, 10], [10, 10, 50, 90]]), "scores": torch.tensor([0.9, 0.8]),
         "labels": torch.tensor([1, 1])},
        {"boxes": torch.tensor([[5.0, 5, 40, 60]]), "scores": torch.tensor([0.4]), "labels": torch.tensor([1])},
    ]
    res = evaluate_detections(dets, GT, (120, 220))
    # ranked: FP (p=1/1→0), TP (1/2, recall 1/3); the 0.4 TP is filtered out (score < 0.5).
    # 101-point interpolation: precision 0.5 at recall 0, 0.01, …, 0.33 (34 points) → 34·0.5/101
    assert res.ap == pytest.approx(34 * 0.5 / 101)
    assert res.n_gt == 3 and res.n_detections == 2
    # lowering the threshold admits the third detection: recall 2/3 at precision 2/3
    res2 = evaluate_detections(dets, GT, (120, 220), score_threshold=0.3)
    assert res2.ap > res.ap


def test_iou_threshold_boundary():
    gt = [{"boxes": torch.tensor([[0.0, 0, 10, 10]]), "labels": torch.tensor([1])}]
    half = [{"boxes": torch.tensor([[0.0, 0, 10, 20]]), "scores": torch.tensor([0.9]), "labels": torch.tensor([1])}]
    assert average_precision(half, gt, (30, 30)) == pytest.approx(1.0)  # IoU = 0.5 matches (COCO: >=)
    less = [{"boxes": torch.tensor([[0.0, 0, 10, 21]]), "scores": torch.tensor([0.9]), "labels": torch.tensor([1])}]
    assert average_precision(less, gt, (30, 30)) == 0.0


def test_no_ground_truth_is_nan_and_categories_are_averaged():
    empty_gt = [{"boxes": torch.zeros(0, 4), "labels": torch.zeros(0, dtype=torch.long)}]
    det = [{"boxes": torch.tensor([[0.0, 0, 5, 5]]), "scores": torch.tensor([0.9]), "labels": torch.tensor([1])}]
    assert math.isnan(average_precision(det, empty_gt, (10, 10)))
    gt = [{"boxes": torch.tensor([[0.0, 0, 5, 5], [10, 10, 20, 20]]), "labels": torch.tensor([1, 2])}]
    res = evaluate_detections(det, gt, (30, 30))
    assert res.per_category == {1: pytest.approx(1.0), 2: 0.0}
    assert res.ap == pytest.approx(0.5)


def test_coco_dicts():
    d = coco_ground_truth(GT, SIZE)
    assert [im["id"] for im in d["images"]] == [1, 2] and d["images"][0]["height"] == 120
    assert d["annotations"][0]["bbox"] == [10.0, 10.0, 40.0, 80.0] and d["annotations"][0]["id"] == 1
    res = coco_results([{"boxes": torch.tensor([[1.0, 2, 4, 8]]), "scores": torch.tensor([0.49]),
                         "labels": torch.tensor([1])}])
    assert res == []  # below the 0.5 threshold
    with pytest.raises(ValueError, match="one \\(H, W\\) or one per image"):
        coco_ground_truth(GT, [(1, 2), (3, 4), (5, 6)])


def test_mismatched_lengths_error():
    with pytest.raises(ValueError, match="2 detection entries for 1 ground-truth"):
        evaluate_detections([{"boxes": [], "scores": [], "labels": []}] * 2, GT[:1], SIZE)
