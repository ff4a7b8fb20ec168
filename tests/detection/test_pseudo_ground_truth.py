"""Pseudo ground truth (threshold) and COCO annotation files."""

import json

import pytest
import torch

from camhealth.detection import ground_truth_for, load_coco_annotations, pseudo_ground_truth


def test_threshold_and_batching():
    calls = []

    def det(images):
        calls.append(images.shape[0])
        return [{"boxes": torch.tensor([[0.0, 0, 4, 4], [1, 1, 6, 6]]), "scores": torch.tensor([0.65, 0.55]),
                 "labels": torch.tensor([1, 1])} for _ in range(images.shape[0])]

    gt = pseudo_ground_truth(det, torch.rand(5, 1, 8, 8), score_threshold=0.6, batch_size=2)
    assert calls == [2, 2, 1]
    assert [g["boxes"].tolist() for g in gt] == [[[0.0, 0, 4, 4]]] * 5
    with pytest.raises(ValueError, match="score_threshold"):
        pseudo_ground_truth(det, torch.rand(1, 1, 8, 8), 1.5)


def test_load_coco_and_match(tmp_path):
    data = {
        "images": [{"id": 7, "file_name": "dir/a.png"}, {"id": 8, "file_name": "b.png"}],
        "annotations": [
            {"id": 1, "image_id": 7, "category_id": 1, "bbox": [10, 20, 30, 40], "iscrowd": 0},
            {"id": 2, "image_id": 7, "category_id": 3, "bbox": [0, 0, 5, 5]},
        ],
        "categories": [{"id": 1, "name": "person"}, {"id": 3, "name": "car"}],
    }
    p = tmp_path / "ann.json"
    p.write_text(json.dumps(data))
    ann = load_coco_annotations(p, category_ids=[1])
    assert ann["dir/a.png"]["boxes"].tolist() == [[10.0, 20.0, 40.0, 60.0]]
    assert ann["b.png"]["boxes"].shape == (0, 4)
    gts = ground_truth_for(["/data/x/a.png", "b"], ann)
    assert len(gts) == 2 and gts[0]["labels"].tolist() == [1]
    with pytest.raises(KeyError, match="no annotations for 1"):
        ground_truth_for(["c.png"], ann)


@pytest.mark.parametrize(
    "content, match",
    [
        ("{", "not valid JSON"),
        ('{"images": []}', "not a COCO annotation file"),
        ('{"images": [{"id": 1, "file_name": "a"}], "annotations": [{"image_id": 2, "bbox": [0,0,1,1]}]}', "unknown image_id"),
        ('{"images": [{"id": 1, "file_name": "a"}], "annotations": [{"image_id": 1, "bbox": [0,0,-1,1]}]}', "negative width"),
    ],
)
def test_bad_annotation_files(tmp_path, content, match):
    p = tmp_path / "bad.json"
    p.write_text(content)
    with pytest.raises(ValueError, match=match):
        load_coco_annotations(p)
    with pytest.raises(FileNotFoundError):
        load_coco_annotations(tmp_path / "missing.json")
