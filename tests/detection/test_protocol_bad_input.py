"""validate_detections on labels that only look like integer class ids."""

import pytest
import torch

from camhealth.detection import coco_results, validate_detections


@pytest.mark.parametrize("label, shown", [(1e20, r"1\.0000000200408773e\+20"), (-1e17, r"-9\.999999843067494e\+16"),
                                          (2.0**53, r"9007199254740992\.0")])
def test_float_labels_too_large_to_be_whole_numbers_are_refused_naming_the_value(label, shown):
    """labels=[1e20] passed the whole-number check and became category -9223372036854775808 (int64 overflow)."""
    det = [{"boxes": torch.tensor([[1.0, 1, 5, 5]]), "scores": torch.tensor([0.9]), "labels": torch.tensor([label])}]
    with pytest.raises(ValueError, match=rf"\['labels'\] must be integer class ids \(whole numbers of magnitude "
                                         rf"< 2\^53\), got {shown}"):
        validate_detections(det, 1, (10, 10))
    with pytest.raises(ValueError, match=r"integer class ids"):
        coco_results(det)
    exact = dict(det[0], labels=torch.tensor([2.0**53 - 1, -7.0, 90.0], dtype=torch.float64),
                 boxes=torch.tensor([[1.0, 1, 5, 5]] * 3), scores=torch.full((3,), 0.9))
    assert validate_detections([exact], 1, (10, 10))[0]["labels"].tolist() == [2**53 - 1, -7, 90]  # still exact
