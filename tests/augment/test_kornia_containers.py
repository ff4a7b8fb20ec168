"""The corruption modules inside Kornia containers (masks, boxes, keypoints, classes, inverse), empty batches,
construction checks and labels of replayed params."""

from __future__ import annotations

import kornia.augmentation as K
import pytest
import torch
from kornia.geometry.boxes import Boxes

from camhealth.augment import CameraCorruption, RandomDefocusBlur, RandomMotionBlur, RandomSensorNoise

MODULES = {
    "defocus": lambda **kw: RandomDefocusBlur(diameter=(1.0, 5.0), **kw),
    "motion": lambda **kw: RandomMotionBlur(length=(1.0, 5.0), intensity=(0.0, 1.0), **kw),
    "noise": lambda **kw: RandomSensorNoise(**kw),
    "camera": lambda **kw: CameraCorruption(RandomDefocusBlur((1.0, 5.0)), RandomMotionBlur((1.0, 5.0)), RandomSensorNoise(), **kw),
}

B, H, W = 2, 24, 32


def _data(dtype=torch.float32):
    g = torch.Generator().manual_seed(0)
    img = torch.rand(B, 1, H, W, generator=g).to(dtype)
    return {
        "input": img,
        "mask": (torch.rand(B, 1, H, W, generator=g) > 0.5).to(dtype),
        "bbox": torch.tensor([[[2.0, 3.0], [12.0, 3.0], [12.0, 9.0], [2.0, 9.0]]], dtype=dtype).expand(B, 1, 4, 2).clone(),
        "bbox_xyxy": torch.tensor([[[2.0, 3.0, 12.0, 9.0]]], dtype=dtype).expand(B, 1, 4).clone(),
        "bbox_xywh": torch.tensor([[[2.0, 3.0, 10.0, 6.0]]], dtype=dtype).expand(B, 1, 4).clone(),
        "keypoints": torch.tensor([[[4.0, 5.0], [20.0, 10.0], [30.0, 20.0]]], dtype=dtype).expand(B, 3, 2).clone(),
    }


KEYS = ["mask", "bbox", "bbox_xyxy", "bbox_xywh", "keypoints"]


@pytest.mark.parametrize("name", MODULES)
@pytest.mark.parametrize("p", [1.0, 0.5])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_every_data_key_passes_through_and_replays(name, p, dtype):
    data = _data(dtype)
    torch.manual_seed(1)
    seq = K.AugmentationSequential(MODULES[name](p=p), data_keys=["input", *KEYS])
    out = seq(*data.values())
    assert out[0].shape == data["input"].shape and out[0].dtype == dtype
    for key, got in zip(KEYS, out[1:]):
        assert torch.equal(got, data[key]), key  # masks, boxes and keypoints are not moved by an intensity change
    if p == 1.0:
        assert not torch.equal(out[0], data["input"])
    replay = seq(*data.values(), params=seq._params)
    assert torch.equal(replay[0], out[0])


@pytest.mark.parametrize("name", MODULES)
def test_label_masks_of_any_value_and_layout(name):
    """Masks hold class labels (0…5 here), integers, or B×H×W: they are not images and pass through unchecked, in
    the layout Kornia's own intensity augmentations give (B×H×W comes back B×1×H×W unless ``keepdim``)."""
    img = _data()["input"]
    labels = torch.randint(0, 6, (B, 1, H, W), generator=torch.Generator().manual_seed(2))
    for keepdim in (False, True):
        for mask in (labels, labels.float(), labels[:, 0]):
            seq = K.AugmentationSequential(MODULES[name](keepdim=keepdim), data_keys=["input", "mask"])
            _, got = seq(img, mask)
            jitter = K.AugmentationSequential(K.ColorJitter(0.1, p=1.0, keepdim=keepdim), data_keys=["input", "mask"])
            _, want = jitter(img.expand(-1, 3, -1, -1), mask)
            assert got.shape == want.shape and got.dtype == mask.dtype
            assert torch.equal(got.reshape(mask.shape), mask)


@pytest.mark.parametrize("name", MODULES)
def test_class_key_and_boxes_object(name):
    data = _data()
    cls = torch.tensor([0, 3])
    seq = K.AugmentationSequential(MODULES[name](), data_keys=["input", "class"])
    out = seq(data["input"], cls)
    assert torch.equal(out[1], cls)
    boxes = Boxes.from_tensor(data["bbox_xyxy"], mode="xyxy")
    mod = MODULES[name]()
    mod(data["input"])
    assert torch.equal(mod.transform_boxes(boxes, mod._params, mod.flags).data, boxes.data)


@pytest.mark.parametrize("name", MODULES)
def test_with_a_geometric_step_and_inverse(name):
    """The issue's pipeline: RandomAffine then the corruption, with masks and keypoints. The coordinate keys follow
    the affine alone, and ``inverse`` undoes the affine and leaves the corruption applied, as for ColorJitter."""
    data = _data()
    keys = ["input", "mask", "bbox_xyxy", "keypoints"]
    args = [data[k] for k in keys]
    torch.manual_seed(3)
    seq = K.AugmentationSequential(K.RandomAffine(15.0, p=1.0), MODULES[name](), data_keys=keys)
    out = seq(*args)
    reference = K.AugmentationSequential(K.RandomAffine(15.0, p=1.0), K.ColorJitter(0.1, p=1.0), data_keys=keys)
    reference(*[a.expand(-1, 3, -1, -1) if i == 0 else a for i, a in enumerate(args)])  # draws its own params
    ref_params = [seq._params[0], reference._params[1]]
    ref_out = reference(*[a.expand(-1, 3, -1, -1) if i == 0 else a for i, a in enumerate(args)], params=ref_params)
    for got, want in zip(out[1:], ref_out[1:]):
        assert torch.allclose(got, want, atol=1e-5)
    back = seq.inverse(*out)
    ref_back = reference.inverse(*ref_out, params=ref_params)
    assert back[0].shape == data["input"].shape
    for got, want in zip(back[1:], ref_back[1:]):
        assert torch.allclose(got, want, atol=1e-4)
    assert torch.allclose(back[3], data["keypoints"], atol=1e-3)  # keypoints come back where they were


@pytest.mark.parametrize("name", MODULES)
@pytest.mark.parametrize("keepdim", [False, True])
def test_empty_batch_returns_empty(name, keepdim):
    mod = MODULES[name](keepdim=keepdim)
    y = mod(torch.rand(0, 1, 16, 16))
    assert y.shape == (0, 1, 16, 16)
    labels = mod.labels()
    for key, value in labels.items():
        assert len(value) == 0, key
    if "mtf" in labels:
        assert labels["mtf"].shape == (0, 16)
    if "sigma_dn" in labels:
        assert labels["sigma_dn"].shape == (0, 3)


@pytest.mark.parametrize(
    "ctor,match",
    [
        (lambda: RandomMotionBlur(p=1.5), r"p = 1.5 must be a probability in \[0, 1\]"),
        (lambda: RandomSensorNoise(p=-0.1), r"p = -0.1"),
        (lambda: CameraCorruption(p=True), r"p = True"),
        (lambda: RandomDefocusBlur(diameter=(250.0, 255.0)), r"diameter = \(250, 255\) must satisfy 0 ≤ low ≤ high ≤ 253"),
        (lambda: RandomMotionBlur(length=(250.0, 255.0)), r"length = \(250, 255\) must satisfy 0 ≤ low ≤ high ≤ 252"),
    ],
)
def test_refused_at_construction(ctor, match):
    with pytest.raises(ValueError, match=match):
        ctor()


def test_largest_blurs_fit():
    x = torch.rand(1, 1, 8, 8)
    assert RandomDefocusBlur(diameter=253.0)(x).shape == x.shape
    assert RandomMotionBlur(length=252.0)(x).shape == x.shape


@pytest.mark.parametrize("name", ["noise", "camera"])
def test_labels_of_earlier_params_are_refused_not_mixed(name):
    """labels(params=p1) after another call would give p1's MTF with the later call's σ: refused; after replaying p1
    the labels are p1's."""
    mod = MODULES[name]()
    x = torch.rand(3, 1, 32, 32, generator=torch.Generator().manual_seed(4))
    torch.manual_seed(5)
    mod(x)
    p1 = mod._params
    first = mod.labels()
    mod(x)
    with pytest.raises(ValueError, match="replay that call first"):
        mod.labels(params=p1)
    mod(x, params=p1)
    again = mod.labels(params=p1)
    assert torch.equal(again["sigma_dn"], first["sigma_dn"])
    if "mtf" in first:
        assert torch.equal(again["mtf"], first["mtf"])


def test_blur_labels_of_earlier_params_are_theirs():
    """Blur labels depend only on the params: labels(params=p1) is p1's MTF after any later call."""
    mod = MODULES["defocus"]()
    x = torch.rand(3, 1, 32, 32)
    mod(x)
    p1, first = mod._params, mod.labels()["mtf"]
    mod(x)
    assert torch.equal(mod.labels(params=p1)["mtf"], first)


@pytest.mark.parametrize("make", [RandomSensorNoise, RandomDefocusBlur, CameraCorruption])
def test_a_kornia_blurs_rounding_above_white_is_clamped_not_refused(make):
    """Kornia's blurs return 1.0000001 on white areas: a camhealth corruption after one in AugmentationSequential takes
    it (clamped into [0, 1]); a value clearly out of range is still refused, named in full."""
    x = torch.ones(8, 1, 32, 32)
    x[:, :, :8] = 0.0
    blur = K.RandomGaussianBlur((7, 7), (0.5, 3.0), p=1.0)
    torch.manual_seed(0)
    seq = K.AugmentationSequential(blur, make())
    for _ in range(6):
        y = seq(x)
        assert bool(torch.isfinite(y).all()) and float(y.min()) >= 0 and float(y.max()) <= 1
    over = torch.full((1, 1, 8, 8), 0.5)
    over[..., 0, 0] = 1.01
    with pytest.raises(ValueError, match=r"got values in \[0.5, 1.0099999904632568\]"):
        make()(over)


@pytest.mark.parametrize("make", [lambda: RandomDefocusBlur((3.0, 9.0)), RandomSensorNoise, CameraCorruption])
def test_params_replayed_at_p_1_agree_with_their_labels_whatever_batch_prob_says(make):
    """At p = 1 Kornia transforms every sample, whatever the replayed params' batch_prob (from a p < 1 module) says;
    the labels follow the image."""
    x = torch.rand(8, 1, 32, 32)
    mod = make()
    mod(x)
    params = dict(mod._params)
    params["batch_prob"] = torch.zeros(8)
    y = mod(x, params=params)
    labels = mod.labels()
    assert not torch.equal(y, x)
    if "mtf" in labels:
        assert bool((labels["mtf"][:, -1] < 1).all())
    if "sigma_total_dn" in labels:
        assert bool((labels["sigma_total_dn"] > 0).all())


def test_a_fractional_or_bool_noise_seed_is_refused():
    x = torch.full((2, 1, 16, 16), 0.5)
    noise = RandomSensorNoise(metadata="ICX285")
    noise(x)
    for seeds in (torch.tensor([1.2, 1.7]), torch.tensor([True, False])):
        params = dict(noise._params)
        params["noise_seed"] = seeds
        with pytest.raises(TypeError, match="noise_seed must hold integers"):
            noise(x, params=params)


def test_numpy_and_tensor_scalars_are_numbers_and_flags_are_bools():
    import numpy as np

    assert RandomDefocusBlur(p=np.float32(0.5)).p == 0.5 and RandomDefocusBlur(p=torch.tensor(0.25)).p == 0.25
    assert RandomMotionBlur(kernel_size=np.int64(7), length=(1.0, 5.0))(torch.rand(1, 1, 16, 16)).shape == (1, 1, 16, 16)
    with pytest.raises(ValueError, match=r"p = '0.5' must be a probability"):
        RandomDefocusBlur(p="0.5")
    with pytest.raises(TypeError, match="quantize = 'no' must be True or False"):
        RandomSensorNoise(quantize="no")


def test_the_repr_names_every_setting_and_component():
    noise = RandomSensorNoise(sources=("photon",), quantize=True, rng="counter")
    assert "sources=['photon'], quantize=True, rng='counter'" in repr(noise)
    cam = repr(CameraCorruption(RandomDefocusBlur((1.0, 3.0)), None, noise))
    assert cam.startswith("CameraCorruption(defocus=RandomDefocusBlur(diameter=(1.0, 3.0)") and "noise=RandomSensorNoise(" in cam
    assert "motion=" not in cam
