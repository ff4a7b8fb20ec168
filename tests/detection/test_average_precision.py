"""COCO AP@0.5 with score >= 0.5 (App. A.1) through pycocotools; perfect = 1, empty = 0 via the adapter."""

import math

import numpy as np
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


# ----------------------------------------------------------------------------------- degenerate and edge inputs
def test_zero_area_ground_truth_is_refused_naming_the_box_unless_crowd():
    """A ground-truth box of zero width or height has IoU 0 with every box: a perfect detection of it scored AP 0.
    It is refused, naming image and box; marked iscrowd it is ignored (as COCO ignores crowd boxes)."""
    from camhealth.detection import validate_ground_truth

    flat = [{"boxes": torch.tensor([[0.0, 0, 10, 10], [10.0, 10, 10, 20]]), "labels": torch.tensor([1, 1])}]
    det = [{"boxes": flat[0]["boxes"].clone(), "scores": torch.tensor([0.9, 0.9]), "labels": torch.tensor([1, 1])}]
    with pytest.raises(ValueError, match=r"ground_truth\[0\]\['boxes'\]\[1\] = \[10.0, 10.0, 10.0, 20.0\] has zero width"):
        evaluate_detections(det, flat, (30, 30))
    with pytest.raises(ValueError, match=r"zero width or height"):
        validate_ground_truth([{"boxes": torch.tensor([[3.0, 5, 9, 5]]), "labels": torch.tensor([2])}])
    crowd = [dict(flat[0], iscrowd=torch.tensor([False, True]))]
    first = [{k: v[:1] for k, v in det[0].items()}]  # the detection of the box with an area
    res = evaluate_detections(first, crowd, (30, 30))
    assert res.ap == pytest.approx(1.0) and res.n_gt == 1


def test_pseudo_ground_truth_leaves_out_zero_area_detections():
    """A detector's zero-area box on the clean frame used to become a ground-truth box no detection can match, so the
    detector scored AP ≈ 0.5 against its own clean output; it is left out and the clean frames score AP 1."""
    from camhealth.detection import pseudo_ground_truth

    def det(images):
        return [{"boxes": torch.tensor([[0.0, 0, 4, 4], [2.0, 2, 2, 6]]), "scores": torch.tensor([0.9, 0.7]),
                 "labels": torch.tensor([1, 1])} for _ in range(images.shape[0])]

    gt = pseudo_ground_truth(det, torch.rand(3, 1, 8, 8))
    assert [g["boxes"].tolist() for g in gt] == [[[0.0, 0.0, 4.0, 4.0]]] * 3
    assert evaluate_detections(det(torch.rand(3, 1, 8, 8)), gt, (8, 8)).ap == pytest.approx(1.0)


def test_coco_file_with_a_zero_area_annotation_is_refused(tmp_path):
    import json

    from camhealth.detection import load_coco_annotations

    data = {"images": [{"id": 1, "file_name": "a.png"}],
            "annotations": [{"image_id": 1, "category_id": 1, "bbox": [5, 5, 0, 10]},
                            {"image_id": 1, "category_id": 1, "bbox": [5, 5, 10, 0], "iscrowd": 1}]}
    p = tmp_path / "ann.json"
    p.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"annotation 0 has zero width or height"):
        load_coco_annotations(p)
    data["annotations"] = data["annotations"][1:]  # the crowd one alone: ignored by the evaluation, kept
    p.write_text(json.dumps(data))
    assert load_coco_annotations(p)["a.png"]["iscrowd"].tolist() == [True]


@pytest.mark.parametrize("batch", [1, 256])
def test_max_detections_is_per_image_and_category_and_n_detections_counts_the_evaluated(batch):
    """COCO applies maxDets per image and category: with two categories and max_detections = 1 both detections of an
    image are evaluated (AP 1); with one category only the higher-scoring one (AP 51/101: recall 1/2 at precision 1).
    n_detections used to count every detection above the threshold (2 per image) in both cases."""
    boxes = torch.tensor([[0.0, 0, 10, 10], [20, 20, 30, 30]])
    two = [{"boxes": boxes, "labels": torch.tensor([1, 2])}] * batch
    det2 = [{"boxes": boxes, "scores": torch.tensor([0.9, 0.8]), "labels": torch.tensor([1, 2])}] * batch
    r = evaluate_detections(det2, two, (40, 40), max_detections=1)
    assert r.ap == pytest.approx(1.0) and r.n_detections == 2 * batch
    one = [{"boxes": boxes, "labels": torch.tensor([1, 1])}] * batch
    det1 = [{"boxes": boxes, "scores": torch.tensor([0.9, 0.8]), "labels": torch.tensor([1, 1])}] * batch
    r = evaluate_detections(det1, one, (40, 40), max_detections=1)
    assert r.ap == pytest.approx(51 / 101) and r.n_detections == batch and r.n_gt == 2 * batch
    assert evaluate_detections(det1, one, (40, 40), max_detections=2).n_detections == 2 * batch


def test_the_score_threshold_is_applied_before_the_float32_conversion():
    """A float64 score of 0.49999999 rounds to 0.5 in float32 and used to pass the >= 0.5 filter (AP 1, one detection
    evaluated); it is now compared as given (float32 scores as before). A score of exactly 0.5 passes in either dtype;
    pseudo ground truth at 0.6 is thresholded the same way."""
    from camhealth.detection import pseudo_ground_truth

    gt = [{"boxes": torch.tensor([[0.0, 0, 10, 10]]), "labels": torch.tensor([1])}]
    for dtype, below in ((torch.float64, 0.49999999), (torch.float32, 0.4999999)):
        for score, ap, n in ((below, 0.0, 0), (0.5, 1.0, 1)):
            det = [{"boxes": torch.tensor([[0.0, 0, 10, 10]]), "scores": torch.tensor([score], dtype=dtype),
                    "labels": torch.tensor([1])}]
            r = evaluate_detections(det, gt, (40, 40))
            assert (r.ap, r.n_detections) == (pytest.approx(ap), n), (dtype, score)
            assert len(coco_results(det)) == n
    clean = [{"boxes": torch.tensor([[0.0, 0, 10, 10]]), "scores": torch.tensor([0.59999999], dtype=torch.float64),
              "labels": torch.tensor([1])}]
    assert pseudo_ground_truth(lambda im: clean, torch.rand(1, 1, 40, 40))[0]["boxes"].shape == (0, 4)


def test_image_sizes_accept_integer_valued_numbers_and_tensors():
    """(40.0, 40.0) or a tensor [40, 40] for one image used to raise "image_sizes has 2 entries for 1 images"; every
    form of one (H, W) or one per image gives the same answer."""
    det = [{"boxes": torch.tensor([[0.0, 0, 10, 10]]), "scores": torch.tensor([0.9]), "labels": torch.tensor([1])}]
    gt = [{"boxes": torch.tensor([[0.0, 0, 10, 10]]), "labels": torch.tensor([1])}]
    for sizes in [(40.0, 40.0), torch.tensor([40, 40]), (torch.tensor(40), torch.tensor(40.0)), [(40, 40.0)],
                  torch.tensor([[40, 40]]), torch.Size([40, 40]), (np.int64(40), np.float32(40.0))]:
        assert average_precision(det, gt, sizes) == pytest.approx(1.0), sizes
        assert coco_ground_truth(gt, sizes)["images"][0]["height"] == 40, sizes


@pytest.mark.parametrize("sizes, match", [
    ((-5, 0), r"image_sizes H = -5 must be a whole number of pixels >= 1"),
    ((40, 0), r"image_sizes W = 0 must be"),
    ((40.5, 40), r"image_sizes H = 40.5 must be"),
    ((float("nan"), 40), r"image_sizes H = nan must be"),
    ([(40, 40), (30, -1)], r"image_sizes\[1\] W = -1 must be"),
    ([(40, 40), (30,)], r"image_sizes\[1\] = \(30,\) must be one \(H, W\)"),
])
def test_image_sizes_out_of_range_are_refused_naming_the_value(sizes, match):
    """Negative and zero sizes used to be accepted without a word."""
    gt = [{"boxes": torch.tensor([[0.0, 0, 5, 5]]), "labels": torch.tensor([1])}] * 2
    det = [{"boxes": torch.tensor([[0.0, 0, 5, 5]]), "scores": torch.tensor([0.9]), "labels": torch.tensor([1])}] * 2
    with pytest.raises(ValueError, match=match):
        evaluate_detections(det, gt, sizes)
