"""evaluate_detections / average_precision / coco_ground_truth on bad input: boxes outside their image (a wrong box
format or the wrong image size) and non-numeric or non-finite settings are refused, naming the value."""

import pytest
import torch

from camhealth.detection import average_precision, coco_ground_truth, evaluate_detections


def _det(boxes, score=0.9):
    b = torch.tensor(boxes, dtype=torch.float32).reshape(-1, 4)
    return {"boxes": b, "scores": torch.full((b.shape[0],), score), "labels": torch.ones(b.shape[0], dtype=torch.long)}


def _gt(boxes):
    b = torch.tensor(boxes, dtype=torch.float32).reshape(-1, 4)
    return {"boxes": b, "labels": torch.ones(b.shape[0], dtype=torch.long)}


IN = [[10.0, 10, 50, 50]]


@pytest.mark.parametrize("dets, gts, sizes, match", [
    # ground truth and detection both beyond a 100×100 image: scored AP 1
    ([_det([[200.0, 200, 260, 260]])], [_gt([[200.0, 200, 260, 260]])], (100, 100),
     r"detections\[0\]\['boxes'\]\[0\] = \[200.0, 200.0, 260.0, 260.0\] lies outside the 100×100 px image"),
    # a detection far outside: scored AP 0 without a word
    ([_det([[1000.0, 1000, 1100, 1100]])], [_gt(IN)], (100, 100),
     r"detections\[0\]\['boxes'\]\[0\] = \[1000.0, 1000.0, 1100.0, 1100.0\] lies outside the 100×100 px"),
    # ground truth outside (second image, one size per image): W×H of that image
    ([_det(IN), _det([[5.0, 5, 30, 30]])], [_gt(IN), _gt([[10.0, 10, 70, 50]])], [(100, 100), (60, 40)],
     r"ground_truth\[1\]\['boxes'\]\[0\] = \[10.0, 10.0, 70.0, 50.0\] lies outside the 40×60 px image"),
    # only y beyond the height (W×H is not square)
    ([_det([[0.0, 0, 10, 90]])], [_gt(IN)], (60, 200), r"detections\[0\]\['boxes'\]\[0\] = .* outside the 200×60 px"),
    # an iscrowd ground-truth box is checked too
    ([_det(IN)], [dict(_gt([[10.0, 10, 50, 50], [150.0, 0, 150, 10]]), iscrowd=torch.tensor([False, True]))],
     (100, 100), r"ground_truth\[0\]\['boxes'\]\[1\] = \[150.0, 0.0, 150.0, 10.0\] lies outside the 100×100"),
])
def test_boxes_outside_their_image_are_refused_naming_image_box_and_size(dets, gts, sizes, match):
    with pytest.raises(ValueError, match=match):
        evaluate_detections(dets, gts, sizes)
    with pytest.raises(ValueError, match=r"lies outside the"):
        average_precision(dets, gts, sizes)


@pytest.mark.parametrize("inside, outside", [
    ([-1.0, -1, 10, 10], [-1.5, 0, 10, 10]),
    ([0.0, 0, 101, 101], [0.0, 0, 101.5, 50]),
    ([90.0, 90, 100.9, 100.9], [90.0, 90, 100, 101.2]),
])
def test_the_one_pixel_tolerance_applies_to_ground_truth(inside, outside):
    """Boxes within 1 px of the image edge (rounding of detector boxes) are kept; beyond it they are refused."""
    assert evaluate_detections([_det([inside])], [_gt([inside])], (100, 100)).ap == pytest.approx(1.0)
    with pytest.raises(ValueError, match=rf"ground_truth\[0\]\['boxes'\]\[0\] = .* lies outside the 100×100 px"):
        evaluate_detections([_det([inside])], [_gt([outside])], (100, 100))


def test_coco_ground_truth_refuses_a_box_outside_its_image():
    with pytest.raises(ValueError, match=r"ground_truth\[0\]\['boxes'\]\[0\] = \[200.0, 200.0, 260.0, 260.0\] lies "
                                         r"outside the 100×100 px image"):
        coco_ground_truth([_gt([[200.0, 200, 260, 260]])], (100, 100))


@pytest.mark.parametrize("kw, match", [
    ({"max_detections": float("nan")}, r"max_detections = nan must be an integer >= 1"),
    ({"max_detections": float("inf")}, r"max_detections = inf must be an integer >= 1"),
    ({"max_detections": True}, r"max_detections = True must be an integer >= 1"),
    ({"score_threshold": "0.5"}, r"score_threshold = '0.5' must lie in \[0, 1\]"),
    ({"iou_threshold": "0.5"}, r"iou_threshold = '0.5' must lie in \(0, 1\)"),
    ({"iou_threshold": None}, r"iou_threshold = None must lie in \(0, 1\)"),
])
def test_non_numeric_or_non_finite_settings_are_refused_naming_the_value(kw, match):
    """max_detections=nan raised 'cannot convert float NaN to integer', inf an OverflowError, a string threshold
    "'<=' not supported"; an integer-valued float or a 0-d tensor of the same setting is still accepted."""
    with pytest.raises(ValueError, match=match):
        evaluate_detections([_det(IN)], [_gt(IN)], (100, 100), **kw)
    valid = {"max_detections": 2.0, "score_threshold": torch.tensor(0.5), "iou_threshold": torch.tensor(0.5)}
    key = next(iter(kw))
    assert evaluate_detections([_det(IN)], [_gt(IN)], (100, 100), **{key: valid[key]}).ap == pytest.approx(1.0)
