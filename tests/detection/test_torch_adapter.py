"""TorchDetector: frozen module, output formats, clear errors."""

import pytest
import torch

from camhealth.detection import TorchDetector


class TensorOut(torch.nn.Module):
    """Returns (B, N, 6) rows [x, y, w, h, score, label] with one padding row (score −1)."""

    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(1, 1, 3)
        self.dropout = torch.nn.Dropout(0.5)

    def forward(self, x):
        b = x.shape[0]
        rows = torch.tensor([[2.0, 3.0, 10.0, 20.0, 0.8, 1.0], [0.0, 0.0, 0.0, 0.0, -1.0, 0.0]])
        return rows.expand(b, 2, 6).clone()


def test_module_is_frozen_and_stays_frozen():
    m = TensorOut()
    det = TorchDetector(m, box_format="xywh")
    assert not m.training and all(not p.requires_grad for p in m.parameters())
    m.train()  # someone flips it back
    det(torch.rand(1, 1, 32, 32))
    assert not m.training
    assert det.config()["parameters"] == sum(p.numel() for p in m.parameters())


@pytest.mark.parametrize("batch", [1, 3])
def test_tensor_output_padding_and_xywh(batch):
    det = TorchDetector(TensorOut(), box_format="xywh")
    out = det(torch.rand(batch, 1, 32, 32))
    assert len(out) == batch
    assert out[0]["boxes"].tolist() == [[2.0, 3.0, 12.0, 23.0]]
    out[0]["boxes"] += 1  # caller may modify (not an inference tensor)


def test_tuple_output_normalised_cxcywh_and_rgb():
    class M(torch.nn.Module):
        def forward(self, x):
            assert x.shape[1] == 3 and float(x.max()) > 1.5  # RGB and DN
            b = x.shape[0]
            return (torch.tensor([[[0.5, 0.5, 0.5, 0.25]]]).expand(b, 1, 4), torch.full((b, 1), 0.9),
                    torch.ones(b, 1, dtype=torch.long))

    det = TorchDetector(M(), channels=3, input_scale=255.0, box_format="cxcywh", normalized_boxes=True)
    (out,) = det(torch.rand(1, 1, 40, 80) * 0.5 + 0.25)
    assert out["boxes"].tolist() == [[20.0, 15.0, 60.0, 25.0]]


def test_postprocess_hook():
    class M(torch.nn.Module):
        def forward(self, x):
            return {"b": torch.tensor([[0.0, 0, 4, 4]])}

    det = TorchDetector(M(), postprocess=lambda raw, imgs: [{"boxes": raw["b"], "scores": [0.7], "labels": [2]}])
    assert det(torch.rand(1, 1, 8, 8))[0]["labels"].tolist() == [2]


@pytest.mark.parametrize(
    "output, match",
    [
        ({"boxes": torch.zeros(1, 4)}, "expected a list of dicts"),
        (torch.zeros(1, 2, 5), r"\(B=1, N, 6\)"),
        ([{"boxes": torch.zeros(1, 4), "scores": torch.ones(1)}], "missing key"),
        ([{"boxes": torch.tensor([[0.0, 0, 999, 5]]), "scores": torch.ones(1), "labels": torch.ones(1)}], "outside the 16×16"),
    ],
)
def test_malformed_module_output(output, match):
    class M(torch.nn.Module):
        def forward(self, x):
            return output

    with pytest.raises((TypeError, ValueError), match=match):
        TorchDetector(M(), name="bad")(torch.rand(1, 1, 16, 16))


def test_bad_input_and_args():
    det = TorchDetector(TensorOut())
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        det(torch.full((1, 1, 8, 8), 2.0))
    with pytest.raises(ValueError, match="C = 1"):
        det(torch.rand(1, 3, 8, 8))
    with pytest.raises(ValueError, match="box_format"):
        TorchDetector(TensorOut(), box_format="yxyx")
    with pytest.raises(TypeError, match="nn.Module"):
        TorchDetector(lambda x: x)


def test_a_nan_score_in_tensor_rows_is_refused_not_dropped_as_padding():
    """Only negative scores are padding: a NaN score reached no check and the detection vanished silently."""

    class NanRow(torch.nn.Module):
        def forward(self, x):
            return torch.tensor([[[1.0, 1.0, 5.0, 5.0, float("nan"), 1.0]]]).expand(x.shape[0], 1, 6)

    with pytest.raises(ValueError, match="finite"):
        TorchDetector(NanRow())(torch.rand(1, 1, 16, 16))


def test_config_names_the_weights():
    a, b = TensorOut(), TensorOut()
    with torch.no_grad():
        b.conv.weight.add_(1.0)
    assert TorchDetector(a).config()["weights"] != TorchDetector(b).config()["weights"]
    assert TorchDetector(a).config()["weights"] == TorchDetector(a).config()["weights"]


class ConvBoxes(torch.nn.Module):
    """Runs a real convolution (its weights fix the dtype the input must have) and returns one box per image whose
    score is the mean of the convolved image, so what the module saw is checked through the output."""

    def __init__(self, channels: int = 1):
        super().__init__()
        self.conv = torch.nn.Conv2d(channels, 1, 3, bias=True)
        with torch.no_grad():
            self.conv.weight.fill_(1.0 / (9 * channels))
            self.conv.bias.zero_()

    def forward(self, x):
        y = self.conv(x)
        return [{"boxes": torch.tensor([[1.0, 1.0, 5.0, 5.0]]), "scores": y[i].mean().reshape(1).float(),
                 "labels": torch.ones(1)} for i in range(x.shape[0])]


@pytest.mark.parametrize("image_dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
@pytest.mark.parametrize("module_dtype", [torch.float32, torch.bfloat16, torch.float64])
@pytest.mark.parametrize("batch", [1, 256])
def test_any_float_image_runs_in_the_modules_dtype(image_dtype, module_dtype, batch):
    """check_image accepts fp16/bf16/fp32/fp64 images, but the adapter used to hand them to the module unconverted
    ("Input type (c10::Half) and bias type (float) should be the same"). They are now cast to the dtype of the
    module's weights (fp32, or a module cast to bf16/fp64) and give the same detections."""
    g = torch.Generator().manual_seed(batch)
    images = torch.rand(batch, 1, 16, 16, generator=g)
    det = TorchDetector(ConvBoxes().to(module_dtype))
    assert det.dtype == module_dtype
    out = det(images.to(image_dtype))
    want = images.mean(dim=(1, 2, 3))  # the 3×3 box filter's mean over the valid area ≈ the image mean
    got = torch.stack([d["scores"][0] for d in out])
    assert len(out) == batch and got.dtype == torch.float32
    assert torch.allclose(got, want, atol=0.03)


class InPlaceNormalise(torch.nn.Module):
    """A module whose forward normalises its input in place (as some exported detectors do)."""

    def forward(self, x):
        x.sub_(0.5).div_(0.25)
        return [{"boxes": torch.zeros(0, 4), "scores": torch.zeros(0), "labels": torch.zeros(0)} for _ in range(x.shape[0])]


@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_a_module_that_works_in_place_does_not_change_the_callers_images(channels, dtype):
    """With channels 1 and a float32 image the module used to get the caller's own tensor (a pixel went 0.75 → 1.0);
    with channels 3 a stride-0 expand view, on which an in-place op raised. The module now gets its own copy."""
    images = torch.full((2, 1, 8, 8), 0.75, dtype=dtype)
    before = images.clone()
    TorchDetector(InPlaceNormalise(), channels=channels)(images)
    assert torch.equal(images, before)
