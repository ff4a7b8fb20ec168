"""load_coco_annotations, pseudo_ground_truth and ground_truth_for on malformed input: every refusal names the file,
the image or annotation index and the value; nothing is silently coerced."""

import json
import re

import numpy as np
import pytest
import torch

from camhealth.detection import ground_truth_for, load_coco_annotations, pseudo_ground_truth

IMG = [{"id": 1, "file_name": "a.png", "width": 100, "height": 100}]


def _ann(**kw):
    return {"id": 1, "image_id": 1, "category_id": 1, "bbox": [5, 5, 20, 20], **kw}


@pytest.mark.parametrize("data, match", [
    # silently coerced before: int(1.7) = 1, bool("no") = True (a zero-width box then accepted as crowd)
    ({"images": IMG, "annotations": [_ann(category_id=1.7)]}, r"annotation 0 has category_id 1\.7: a category id must "
                                                              r"be a whole number"),
    ({"images": IMG, "annotations": [_ann(category_id=True)]}, r"annotation 0 has category_id True"),
    ({"images": IMG, "annotations": [_ann(), _ann(bbox=[5, 5, 0, 20], iscrowd="no")]},
     r"annotation 1 has iscrowd 'no': allowed are 0, 1, true and false"),
    ({"images": IMG, "annotations": [_ann(iscrowd=2)]}, r"annotation 0 has iscrowd 2"),
    # a box outside the image's own width × height
    ({"images": IMG, "annotations": [_ann(bbox=[500, 500, 20, 20])]},
     r"annotation 0 has bbox \[500, 500, 20, 20\] \(x, y, w, h\) outside its image 'a.png' of 100×100 px"),
    ({"images": [{"id": 1, "file_name": "a.png", "width": 200, "height": 50}],
      "annotations": [_ann(bbox=[5, 5, 20, 60])]},
     r"annotation 0 has bbox \[5, 5, 20, 60\] \(x, y, w, h\) outside its image 'a.png' of 200×50 px"),
    ({"images": [{"id": 1, "file_name": "a.png", "width": 0, "height": 50}], "annotations": []},
     r"image 0 \('a.png'\) has width, height = 0, 50: each must be a whole number of pixels >= 1"),
    # crashes with messages that named neither the file nor the annotation
    ({"images": {"id_file_name": 1}, "annotations": []}, r"'images' must be a list of objects, got dict"),
    ({"images": IMG, "annotations": {"0": _ann()}}, r"'annotations' must be a list of objects, got dict"),
    ({"images": [1], "annotations": []}, r"image 0 must be an object with 'id' and 'file_name', got 1"),
    ({"images": IMG, "annotations": [[1, 2]]},
     r"annotation 0 must be an object with 'image_id' and 'bbox', got \[1, 2\]"),
    ({"images": IMG, "annotations": [_ann(bbox=None)]}, r"annotation 0 needs a 'bbox' \[x, y, w, h\], got None"),
    ({"images": IMG, "annotations": [_ann(bbox=["a", 1, 2, 3])]}, r"annotation 0 has bbox \['a', 1, 2, 3\]: a bbox "
                                                                 r"\[x, y, w, h\] must hold 4 finite numbers"),
    ({"images": IMG, "annotations": [_ann(bbox=[True, 1, 2, 3])]}, r"annotation 0 has bbox \[True, 1, 2, 3\]"),
    ({"images": IMG, "annotations": [_ann(category_id="person")]}, r"annotation 0 has category_id 'person'"),
    ({"images": [{"id": [1], "file_name": "a"}], "annotations": []}, r"image 0 has id \[1\]: an image id must be an "
                                                                     r"int or a str"),
    ({"images": IMG, "annotations": [_ann(image_id=[1])]}, r"annotation 0 refers to unknown image_id \[1\]"),
])
def test_malformed_coco_files_are_refused_naming_file_entry_and_value(tmp_path, data, match):
    p = tmp_path / "ann.json"
    p.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=rf"{re.escape(str(p))}: {match}"):
        load_coco_annotations(p)


@pytest.mark.parametrize("raw", [b"\x89PNG\r\n\x1a\n\xff\xfe\x00", b'{"images": [], "annotations": [], "x": "\xff"}'])
def test_a_file_that_is_not_json_text_is_refused_naming_it(tmp_path, raw):
    p = tmp_path / "ann.json"
    p.write_bytes(raw)
    with pytest.raises(ValueError, match=rf"{re.escape(str(p))} is not valid JSON text"):
        load_coco_annotations(p)


def test_bbox_nan_is_refused_naming_the_annotation(tmp_path):
    p = tmp_path / "ann.json"
    p.write_text('{"images": [{"id": 1, "file_name": "a.png"}], '
                 '"annotations": [{"image_id": 1, "bbox": [NaN, 1, 2, 3]}]}')
    with pytest.raises(ValueError, match=r"annotation 0 has bbox \[nan, 1, 2, 3\]: a bbox \[x, y, w, h\] must hold 4 "
                                         r"finite numbers"):
        load_coco_annotations(p)


@pytest.mark.parametrize("bad, match", [
    ({"category_id": 1.7}, r"annotation 0 has category_id 1\.7"),
    ({"iscrowd": "yes"}, r"annotation 0 has iscrowd 'yes'"),
    ({"bbox": [80, 80, 22, 20]}, r"annotation 0 has bbox \[80, 80, 22, 20\] \(x, y, w, h\) outside its image"),
])
def test_valid_values_are_read_as_before_and_their_bad_neighbours_refused(tmp_path, bad, match):
    """Integer-valued float category ids, iscrowd true/1, a missing category_id (1) and a box within 1 px of the
    image edge are read; an image without width/height is not checked against a size."""
    data = {"images": IMG + [{"id": "b", "file_name": "b.png"}],
            "annotations": [_ann(category_id=3.0, bbox=[80, 80, 20.5, 20.5]), _ann(bbox=[1, 1, 0, 5], iscrowd=True),
                            {"image_id": "b", "bbox": [1000, 1000, 10, 10], "iscrowd": 0}]}
    p = tmp_path / "ann.json"
    p.write_text(json.dumps(data))
    ann = load_coco_annotations(p)
    assert ann["a.png"]["labels"].tolist() == [3, 1] and ann["a.png"]["iscrowd"].tolist() == [False, True]
    assert ann["b.png"]["labels"].tolist() == [1]
    data["annotations"][0].update(bad)
    p.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=rf"{re.escape(str(p))}: {match}"):
        load_coco_annotations(p)


@pytest.mark.parametrize("batch_size", [np.int64(2), np.int32(1)])
def test_numpy_integer_batch_size_is_accepted(batch_size):
    """np.int64(2) was refused as 'out of the allowed range: an integer >= 1'."""
    calls = []

    def det(images):
        calls.append(images.shape[0])
        return [{"boxes": torch.tensor([[0.0, 0, 4, 4]]), "scores": torch.tensor([0.9]), "labels": torch.tensor([1])}
                for _ in range(images.shape[0])]

    gt = pseudo_ground_truth(det, torch.rand(3, 1, 8, 8), batch_size=batch_size)
    assert len(gt) == 3 and max(calls) == int(batch_size)


@pytest.mark.parametrize("ids", ["a.png", b"a.png"])
def test_a_single_string_for_ids_is_refused_naming_it(tmp_path, ids):
    """ground_truth_for('a.png', ann) iterated the characters: 'no annotations for 4 image(s), e.g. ['.', 'p', 'n']'."""
    p = tmp_path / "ann.json"
    p.write_text(json.dumps({"images": IMG, "annotations": []}))
    ann = load_coco_annotations(p)
    with pytest.raises(TypeError, match=rf"ids must be a list of image ids or paths, got the single "
                                        rf"{type(ids).__name__} {re.escape(repr(ids))}"):
        ground_truth_for(ids, ann)
    assert len(ground_truth_for(["a.png"], ann)) == 1
