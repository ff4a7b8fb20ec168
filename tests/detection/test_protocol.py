"""validate_detections: canonical form and clear errors for malformed detector output."""

import numpy as np
import pytest
import torch

from camhealth.detection import empty_detection, filter_by_score, validate_detections


def _good():
    return [{"boxes": torch.tensor([[1.0, 2.0, 10.0, 20.0]]), "scores": torch.tensor([0.7]), "labels": torch.tensor([1])}]


@pytest.mark.parametrize("container", ["torch", "numpy", "list"])
def test_canonical_form(container):
    det = {"boxes": [[1, 2, 10, 20], [0, 0, 5, 5]], "scores": [0.9, 0.4], "labels": [1, 3]}
    if container == "torch":
        det = {k: torch.tensor(v) for k, v in det.items()}
    elif container == "numpy":
        det = {k: np.asarray(v) for k, v in det.items()}
    (out,) = validate_detections([det], 1, (40, 30))
    assert out["boxes"].dtype == torch.float32 and out["boxes"].shape == (2, 4)
    assert out["scores"].dtype == torch.float32 and out["labels"].dtype == torch.int64
    assert out["labels"].tolist() == [1, 3]
    (kept,) = filter_by_score([out], 0.5)
    assert kept["scores"].tolist() == pytest.approx([0.9])


def test_empty_detections_are_fine():
    (out,) = validate_detections([{"boxes": [], "scores": [], "labels": []}], 1)
    assert out["boxes"].shape == (0, 4)
    assert validate_detections([empty_detection()], 1)[0]["scores"].numel() == 0


@pytest.mark.parametrize(
    "bad, exc, match",
    [
        ({"boxes": torch.zeros(1, 4)}, TypeError, "list with one dict"),  # a dict, not a list
        ([], ValueError, "0 entries but the detector was given 1"),
        (["not a dict"], TypeError, "must be a dict"),
        ([{"boxes": torch.zeros(1, 4), "scores": torch.ones(1)}], ValueError, r"missing key\(s\) \['labels'\]"),
        ([{"boxes": torch.zeros(1, 3), "scores": torch.ones(1), "labels": torch.ones(1)}], ValueError, r"shape \(N, 4\)"),
        ([{"boxes": torch.zeros(2, 4), "scores": torch.ones(1), "labels": torch.ones(2)}], ValueError, r"'scores'\] must have shape \(2,\)"),
        ([{"boxes": torch.tensor([[0.0, 0, float("nan"), 1]]), "scores": torch.ones(1), "labels": torch.ones(1)}], ValueError, "finite"),
        ([{"boxes": torch.tensor([[5.0, 0, 1, 1]]), "scores": torch.ones(1), "labels": torch.ones(1)}], ValueError, "x2 < x1"),
        ([{"boxes": torch.tensor([[0.0, 0, 1, 1]]), "scores": torch.tensor([3.2]), "labels": torch.ones(1)}], ValueError, r"confidences in \[0, 1\]"),
        ([{"boxes": torch.tensor([[0.0, 0, 1, 1]]), "scores": torch.ones(1), "labels": torch.tensor([1.5])}], ValueError, "integer class ids"),
        ([{"boxes": torch.tensor([[0.0, 0, 500, 1]]), "scores": torch.ones(1), "labels": torch.ones(1)}], ValueError, "outside the 30×40 px"),
        ([{"boxes": "abc", "scores": torch.ones(1), "labels": torch.ones(1)}], TypeError, "must be a torch.Tensor"),
    ],
)
def test_malformed_output_gives_clear_error(bad, exc, match):
    with pytest.raises(exc, match=match):
        validate_detections(bad, 1, (40, 30))
