"""``python -m camhealth.iopc`` end to end on two 320×240 street crops with the HOG detector."""

import json

import pytest
import torch
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


@pytest.mark.parametrize("stride", ["0", "-1"])
def test_frames_stride_below_one_is_refused_naming_the_key(tmp_path, crop_folder, stride):
    """--frames.stride 0 failed with Python's "slice step cannot be zero", which names no flag; -1 reversed the
    frames silently."""
    with pytest.raises(ValueError, match=rf"frames.stride = {stride} is out of the allowed range: an integer >= 1"):
        main(["--config", str(_config(tmp_path, crop_folder)), "--frames.stride", stride])


def test_bad_sweep_bins_are_refused_before_the_sweep(tmp_path, crop_folder):
    """Bins the curves cannot use failed only after every cell was computed."""
    with pytest.raises(ValueError, match=r"sigma_bins_dn = \[5.0\] needs at least 2 bin centres"):
        main(["--config", str(_config(tmp_path, crop_folder)), "--sweep.sigma_bins_dn", "[5]"])
    assert not (tmp_path / "cache").exists()


def _instantiated(argv):
    from camhealth.iopc.cli import build_parser

    parser = build_parser()
    cfg = parser.parse_args(argv)
    return (getattr(parser, "instantiate", None) or parser.instantiate_classes)(cfg)


def test_torch_detector_in_yaml_as_configs_iopc_documents(tmp_path):
    """A second --config with ``detector.torch.class_path`` + ``init_args`` only (the form configs/iopc.yaml shows) is the
    user's module, not a jsonargparse subclass spec; the first config's other detector.torch settings stay."""
    from pathlib import Path

    from camhealth.detection import TorchDetector
    from camhealth.iopc.cli import build_detector

    user = tmp_path / "user.yaml"
    user.write_text("detector:\n  kind: torch\n  torch:\n    class_path: torch.nn.Linear\n"
                    "    init_args: {in_features: 2, out_features: 3}\n")
    base = Path(__file__).resolve().parents[2] / "configs" / "iopc.yaml"
    init = _instantiated(["--config", str(base), "--detector.torch.channels", "3", "--config", str(user)])
    t = init.detector.torch
    assert (t.class_path, t.init_args, t.channels) == ("torch.nn.Linear", {"in_features": 2, "out_features": 3}, 3)
    detector = build_detector(init.detector)
    assert isinstance(detector, TorchDetector) and detector.module.out_features == 3


def test_torch_detector_class_path_must_be_a_module_class_and_is_not_called_otherwise(tmp_path):
    marker = tmp_path / "MARKER"
    cfg = tmp_path / "evil.yaml"
    cfg.write_text(json.dumps({"detector": {"kind": "torch", "torch": {
        "class_path": "subprocess.run", "init_args": {"args": ["touch", str(marker)]}}}}))
    from camhealth.iopc.cli import build_detector

    for argv in (["--config", str(cfg)],
                 ["--detector.kind", "torch", "--detector.torch.class_path", "subprocess.run",
                  "--detector.torch.init_args", json.dumps({"args": ["touch", str(marker)]})]):
        with pytest.raises(ValueError, match=r"class_path 'subprocess.run' is a function, not a torch.nn.Module class"):
            build_detector(_instantiated(argv).detector)
    assert not marker.exists()
    with pytest.raises(ValueError, match="'collections.OrderedDict' is a type, not a torch.nn.Module class"):
        build_detector(_instantiated(["--detector.kind", "torch", "--detector.torch.class_path", "collections.OrderedDict"]).detector)


def test_torch_detector_checkpoint_is_read_as_plain_tensors_naming_the_file(tmp_path):
    import torch

    from camhealth.iopc.cli import build_detector
    from tests._evil_files import Payload

    args = ["--detector.kind", "torch", "--detector.torch.class_path", "torch.nn.Linear",
            "--detector.torch.init_args", '{"in_features": 2, "out_features": 1}']
    good = tmp_path / "good.pt"
    torch.save({"state_dict": {"weight": torch.full((1, 2), 7.0), "bias": torch.zeros(1)}}, good)
    detector = build_detector(_instantiated([*args, "--detector.torch.checkpoint", str(good)]).detector)
    assert float(detector.module.weight[0, 0]) == 7.0
    evil, marker = tmp_path / "evil.pt", tmp_path / "MARKER"
    torch.save({"state_dict": Payload(marker)}, evil)
    with pytest.raises(ValueError, match=f"detector.torch.checkpoint {evil}: not a state dict of plain tensors") as info:
        build_detector(_instantiated([*args, "--detector.torch.checkpoint", str(evil)]).detector)
    assert not marker.exists() and "weights_only" not in str(info.value) and "camhealth never unpickles" in str(info.value)
    with pytest.raises(FileNotFoundError, match="detector.torch.checkpoint .*missing.pt: no such file"):
        build_detector(_instantiated([*args, "--detector.torch.checkpoint", str(tmp_path / "missing.pt")]).detector)


class TwoClassDetector(torch.nn.Module):
    """One 'person' (label 1) and one 'car' (label 3) box per image, score 0.9."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(1))

    def forward(self, x):
        boxes = torch.tensor([[20.0, 20.0, 80.0, 150.0], [120.0, 100.0, 220.0, 160.0]])
        return [{"boxes": boxes, "scores": torch.tensor([0.9, 0.9]), "labels": torch.tensor([1, 3])}
                for _ in range(x.shape[0])]


def test_category_ids_filter_pseudo_ground_truth_and_detections(tmp_path, crop_folder):
    """With pseudo ground truth (annotations null) category_ids was ignored: the cars (3) stayed in the ground truth,
    n_gt was 4 instead of 2 and the AP averaged over a category the user excluded."""
    detector = {"kind": "torch", "torch": {"class_path": f"{__name__}.TwoClassDetector"}}
    cfg = _config(tmp_path, crop_folder, detector=detector, ground_truth={"annotations": None, "category_ids": [1]},
                  tensorboard=False)
    iopc = main(["--config", str(cfg), "--sweep.grid.noise_levels_dn", "[0]"])
    assert iopc.records[0]["n_gt"] == 2 and iopc.provenance["ground_truth_boxes"] == 2
    assert iopc.records[0]["n_detections"] == 2 and iopc.records[0]["ap"] == pytest.approx(1.0)
    assert iopc.provenance["ground_truth"].endswith("categories [1]")
    assert iopc.provenance["detector"]["category_ids"] == [1]  # in the fingerprint: other categories, other cells
    with pytest.raises(ValueError, match=r"ground_truth.category_ids = \[\] is out of the allowed range"):
        main(["--config", str(cfg), "--ground_truth.category_ids", "[]"])
