"""TorchDetector on bad settings, a sub-module left in train mode, and (boxes, scores, labels) of mismatched shapes."""

import math

import pytest
import torch

from camhealth.detection import TorchDetector


class _Ret(torch.nn.Module):
    def __init__(self, out):
        super().__init__()
        self.out = out
        self.w = torch.nn.Parameter(torch.zeros(1))

    def forward(self, x):
        return self.out


class _BNDet(torch.nn.Module):
    """A detector whose score depends on BatchNorm statistics and Dropout: train mode changes both."""

    def __init__(self):
        super().__init__()
        self.body = torch.nn.Sequential(torch.nn.Conv2d(1, 4, 3, padding=1), torch.nn.BatchNorm2d(4),
                                        torch.nn.Dropout(0.5))

    def forward(self, x):
        s = torch.sigmoid(self.body(x).mean((1, 2, 3)))
        b = x.shape[0]
        return [{"boxes": torch.tensor([[1.0, 1, 5, 5]]), "scores": s[i:i + 1], "labels": torch.tensor([1])}
                for i in range(b)]


@pytest.mark.parametrize("switch", ["body", "bn", "all_children"])
def test_a_sub_module_switched_to_train_mode_is_evaluated_in_eval_mode(switch):
    """module.body.train() (user code or a library) used to make every call train the BatchNorm statistics and drop
    units: three calls gave three scores and changed the weights hash."""
    torch.manual_seed(0)
    module = _BNDet()
    det = TorchDetector(module)
    images = torch.rand(2, 1, 16, 16, generator=torch.Generator().manual_seed(1))
    ref = det(images)[0]["scores"].item()
    weights = det.config()["weights"]
    if switch == "body":
        module.body.train()
    elif switch == "bn":
        module.body[1].train()
    else:
        for m in module.children():
            m.train()
    scores = [det(images)[0]["scores"].item() for _ in range(3)]
    assert scores == [ref] * 3
    assert det.config()["weights"] == weights
    assert not any(m.training for m in module.modules())


@pytest.mark.parametrize("scores, labels, key, shape", [
    (torch.zeros(1, 1), torch.zeros(2, 1), "scores", r"\(1, 1\)"),
    (torch.zeros(2), torch.zeros(2, 1), "scores", r"\(2,\)"),
    (torch.zeros(2, 1), torch.zeros(2, 3), "labels", r"\(2, 3\)"),
    (torch.zeros(2, 1), torch.zeros(1), "labels", r"\(1,\)"),
])
def test_tuple_output_with_mismatched_scores_or_labels_is_refused_naming_the_shapes(scores, labels, key, shape):
    """scores (1, 1) for boxes (2, 1, 4) gave IndexError: index 1 is out of bounds for dimension 0 with size 1."""
    det = TorchDetector(_Ret((torch.zeros(2, 1, 4), scores, labels)), name="mydet")
    with pytest.raises(ValueError, match=rf"mydet returned \(boxes, scores, labels\) with {key} of shape {shape}; "
                                         r"expected \(B=2, N=1\) to match boxes of shape \(2, 1, 4\)"):
        det(torch.rand(2, 1, 8, 8))


@pytest.mark.parametrize("kw, match", [
    ({"input_scale": math.inf}, r"input_scale = inf must be a finite number > 0"),
    ({"input_scale": math.nan}, r"input_scale = nan must be a finite number > 0"),
    ({"input_scale": "255"}, r"input_scale = '255' must be a finite number > 0"),
    ({"input_scale": 0.0}, r"input_scale = 0.0 must be a finite number > 0"),
    ({"channels": True}, r"channels = True must be 1 \(gray\) or 3"),
    ({"channels": 3.0}, r"channels = 3.0 must be 1 \(gray\) or 3"),
])
def test_bad_settings_are_refused_naming_the_value(kw, match):
    with pytest.raises(ValueError, match=match):
        TorchDetector(_Ret([]), **kw)
    out = [{"boxes": torch.tensor([[1.0, 1, 5, 5]]), "scores": torch.tensor([0.9]), "labels": torch.tensor([1])}]
    det = TorchDetector(_Ret(out), channels=3, input_scale=255)  # valid settings still work
    assert det.channels == 3 and det.input_scale == 255.0
    assert det(torch.rand(1, 1, 8, 8))[0]["boxes"].tolist() == [[1.0, 1.0, 5.0, 5.0]]
