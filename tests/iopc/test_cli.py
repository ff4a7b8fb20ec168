"""``python -m camhealth.iopc`` end to end on two 320×240 street crops with the HOG detector."""

import json

import pytest
from PIL import Image

from camhealth.data import StreetSampleSource
from camhealth.iopc import IOPC
from camhealth.iopc.cli import main


@pytest.fixture(scope="module")
def crop_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("crops")
    img, _ = StreetSampleSource(max_frames=1)[0]
    for name, (y, x) in {"a.png": (100, 250), "b.png": (60, 440)}.items():
        arr = (img[0, y : y + 240, x : x + 320] * 255).round().byte().numpy()
        Image.fromarray(arr).save(folder / name)
    return folder


def _config(tmp_path, folder, **extra):
    cfg = {
        "source": str(folder),
        "estimators": {"noise": "physics", "mtf": "physics"},
        "sweep": {"grid": {"lengths_px": [0], "angles_deg": [0], "noise_levels_dn": [0, 5]}},
        "trainer": {"accelerator": "cpu", "devices": 1, "enable_progress_bar": False},
        "out_dir": str(tmp_path / "out"),
        "cache_dir": str(tmp_path / "cache"),
        "tensorboard": True,
        **extra,
    }
    p = tmp_path / "iopc.yaml"
    p.write_text(json.dumps(cfg))  # JSON is YAML
    return p


def test_cli_pseudo_ground_truth_and_resume(tmp_path, crop_folder, capsys):
    cfg = _config(tmp_path, crop_folder)
    iopc = main(["--config", str(cfg)])
    out = tmp_path / "out"
    assert {p.name for p in out.iterdir()} >= {"iopc.json", "iopc.npz", "iopc.png", "tensorboard"}
    assert any((out / "tensorboard").iterdir())
    assert len(iopc.records) == 2 and "IOPC (AP@0.5 opencv-hog-people)" in capsys.readouterr().out
    clean = next(r for r in iopc.records if r["key"] == "L0_a0_s0")
    assert clean["ap"] == pytest.approx(1.0) and clean["mtf_tilde"] == 1.0
    assert iopc.provenance["ground_truth"].startswith("pseudo") and iopc.provenance["estimator_specs"]["mtf"] == "physics"
    assert IOPC.load(out / "iopc.npz").to_dict()["ap_2d"] == iopc.to_dict()["ap_2d"]
    again = main(["--config", str(cfg)])  # every cell cached
    assert [r["seconds"] for r in again.records] == [r["seconds"] for r in iopc.records]


def test_cli_coco_annotations_and_overrides(tmp_path, crop_folder):
    ann = {"images": [{"id": 1, "file_name": "a.png"}, {"id": 2, "file_name": "b.png"}],
           "annotations": [{"id": 1, "image_id": 1, "category_id": 1, "bbox": [79, 48, 76, 151]},
                           {"id": 2, "image_id": 2, "category_id": 1, "bbox": [128, 57, 71, 142]}]}
    ann_path = tmp_path / "ann.json"
    ann_path.write_text(json.dumps(ann))
    cfg = _config(tmp_path, crop_folder, ground_truth={"annotations": str(ann_path)})
    iopc = main(["--config", str(cfg), "--sweep.grid.noise_levels_dn", "[0]", "--tensorboard", "false"])
    assert len(iopc.records) == 1 and "COCO annotations" in iopc.provenance["ground_truth"]
    assert next(r for r in iopc.records if r["key"] == "L0_a0_s0")["n_gt"] == 2


def test_cli_errors(tmp_path, crop_folder):
    with pytest.raises(ValueError, match="must be 'hog' or 'torch'"):
        main(["--config", str(_config(tmp_path, crop_folder)), "--detector.kind", "yolo"])
    with pytest.raises(ValueError, match="class_path"):
        main(["--config", str(_config(tmp_path, crop_folder)), "--detector.kind", "torch"])
