"""OpenCV HOG people detector on crops of the embedded street clip (320×240 px)."""

import math

import pytest
import torch

from camhealth.data import StreetSampleSource
from camhealth.detection import (
    HOGPeopleDetector,
    average_precision,
    margin_to_score,
    pseudo_ground_truth,
    score_to_margin,
)


@pytest.fixture(scope="module")
def crops():
    img, _ = StreetSampleSource(max_frames=1)[0]  # 1×576×768
    # two 240×320 crops around pedestrians of frame 100
    return torch.stack([img[:, 100:340, 250:570], img[:, 60:300, 440:760]])


@pytest.fixture(scope="module")
def hog():
    return HOGPeopleDetector()


def test_finds_people_with_valid_boxes_and_scores(crops, hog):
    out = hog(crops)
    assert len(out) == 2
    for d in out:
        assert len(d["boxes"]) >= 1
        assert d["labels"].tolist() == [1] * len(d["labels"])
        assert bool(((d["scores"] >= 0.5) & (d["scores"] <= 1)).all())  # hit_threshold 0 ⇔ score >= 0.5
        b = d["boxes"]
        assert bool((b[:, 2] > b[:, 0]).all() and (b[:, 3] - b[:, 1] >= 100).all())  # people, not specks
        assert bool((b[:, [0, 2]] <= 320).all() and (b[:, [1, 3]] <= 240).all())
        assert torch.equal(d["scores"], d["scores"].sort(descending=True).values)


def test_flat_image_has_no_people_and_small_image_is_handled(hog):
    assert hog(torch.full((1, 1, 240, 320), 0.5))[0]["boxes"].shape == (0, 4)
    assert hog(torch.rand(1, 1, 60, 40))[0]["boxes"].shape == (0, 4)  # smaller than the 64×128 window


def test_deterministic_and_pseudo_gt_scores_one(crops, hog):
    a, b = hog(crops), hog(crops)
    assert all(torch.equal(x["boxes"], y["boxes"]) for x, y in zip(a, b))
    gt = pseudo_ground_truth(hog, crops, 0.6)
    assert all(bool((d["scores"][: len(g["boxes"])] >= 0.6).all()) for d, g in zip(a, gt))
    assert average_precision(hog(crops), gt, crops.shape[-2:]) == pytest.approx(1.0)


def test_upscale_maps_boxes_back(crops, hog):
    small = torch.nn.functional.interpolate(crops[:1], scale_factor=0.5, mode="area")
    assert hog(small)[0]["boxes"].shape[0] == 0  # people are ~75 px tall now: below the window
    up = HOGPeopleDetector(upscale=2.0)(small)[0]
    assert up["boxes"].shape[0] >= 1 and float(up["boxes"].max()) <= 160


def test_score_mapping():
    assert margin_to_score(0.0) == 0.5
    assert score_to_margin(margin_to_score(0.41)) == pytest.approx(0.41)
    assert float(margin_to_score(torch.tensor(2.0))) == pytest.approx(1 / (1 + math.exp(-2)))
    with pytest.raises(ValueError, match="open interval"):
        score_to_margin(1.0)


def test_bad_input_and_settings(hog):
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        hog(torch.full((1, 1, 130, 70), 1.5))
    with pytest.raises(ValueError, match="C = 1"):
        hog(torch.rand(1, 3, 130, 70))
    with pytest.raises(ValueError, match="multiples of the 8 px"):
        HOGPeopleDetector(win_stride=(4, 4))
    with pytest.raises(ValueError, match="pyramid step"):
        HOGPeopleDetector(scale=1.0)
