"""Pseudo ground truth (threshold) and COCO annotation files."""

import json
import re

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


@pytest.mark.parametrize("batch_size", [0, -1, 2.5, True])
def test_batch_size_below_one_is_refused_naming_the_value(batch_size):
    """batch_size 0 gave 0 ground-truth entries for 3 frames (the detector called on empty batches), -1 gave 2."""
    calls = []

    def det(images):
        calls.append(images.shape[0])
        return [{"boxes": torch.tensor([[0.0, 0, 4, 4]]), "scores": torch.tensor([0.9]), "labels": torch.tensor([1])}
                for _ in range(images.shape[0])]

    with pytest.raises(ValueError, match=rf"batch_size = {batch_size!r} is out of the allowed range: an integer >= 1"):
        pseudo_ground_truth(det, torch.rand(3, 1, 8, 8), batch_size=batch_size)
    assert calls == []


def _coco(tmp_path, images, annotations):
    p = tmp_path / "ann.json"
    p.write_text(json.dumps({"images": images, "annotations": annotations}))
    return p


def test_a_base_name_or_stem_that_fits_several_annotated_files_is_refused(tmp_path):
    """/data/seq/cam1/0001.png and /data/seq/cam2/0001.png both got cam2's boxes (the base-name table kept the last
    of the two 0001.png)."""
    p = _coco(tmp_path, [{"id": 1, "file_name": "cam1/0001.png"}, {"id": 2, "file_name": "cam2/0001.png"}],
              [{"id": 1, "image_id": 1, "bbox": [10, 10, 20, 40]}, {"id": 2, "image_id": 2, "bbox": [200, 100, 30, 60]}])
    ann = load_coco_annotations(p)
    with pytest.raises(ValueError, match=r"image '/data/seq/cam1/0001.png': its base name '0001.png' fits 2 annotated "
                                         r"files \['cam1/0001.png', 'cam2/0001.png'\]"):
        ground_truth_for(["/data/seq/cam1/0001.png"], ann)
    with pytest.raises(ValueError, match=r"image '0001': its stem '0001' fits 2 annotated files"):
        ground_truth_for(["0001"], ann)
    # exact names are not ambiguous
    gts = ground_truth_for(["cam1/0001.png", "cam2/0001.png"], ann)
    assert [g["boxes"].tolist() for g in gts] == [[[10.0, 10.0, 30.0, 50.0]], [[200.0, 100.0, 230.0, 160.0]]]


@pytest.mark.parametrize("images, match", [
    ([{"id": 1, "file_name": "x.png"}, {"id": 2, "file_name": "x.png"}],
     r"file_name 'x.png' appears twice in 'images' \(ids 1 and 2\)"),
    ([{"id": 1, "file_name": "x.png"}, {"id": 1, "file_name": "y.png"}],
     r"image id 1 appears twice in 'images' \(file_name 'x.png' and 'y.png'\)"),
])
def test_a_repeated_file_name_or_image_id_is_refused(tmp_path, images, match):
    """Two images named x.png: the annotated one's box was lost ({'x.png': []})."""
    p = _coco(tmp_path, images, [{"id": 1, "image_id": 1, "bbox": [10, 10, 20, 40]}])
    with pytest.raises(ValueError, match=rf"{re.escape(str(p))}: {match}"):
        load_coco_annotations(p)
