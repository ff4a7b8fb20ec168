"""estimate_regions and resolve_estimator refuse input and estimator outputs that would give wrong numbers."""

import pytest
import torch

from camhealth.iopc import PHYSICS, ImmerkaerNoiseEstimator, estimate_regions, resolve_estimator
from camhealth.physics import CameraMetadata


def _images(batch=2, size=256, sigma_dn=5.0):
    g = torch.Generator().manual_seed(0)
    return (0.5 + sigma_dn / 255 * torch.randn(batch, 1, size, size, generator=g)).clamp(0, 1)


BOXES = [torch.tensor([[10.0, 10.0, 200.0, 200.0]]), torch.tensor([[0.0, 0.0, 50.0, 50.0]])]


class _Noise:
    """A noise-source estimator whose output is ``out(number of patches)``."""

    kind, metadata_set, patch_size = "noise_source", "none", 128

    def __init__(self, out):
        self.out = out

    def predict(self, patches, metadata=None):
        return self.out(patches.shape[0])


class _MTF:
    kind, metadata_set, patch_size = "mtf", "none", 64

    def __init__(self, out):
        self.out = out

    def predict(self, patches, metadata=None):
        return self.out(patches.shape[0])


@pytest.mark.parametrize("scale", [255.0, 2.0])
@pytest.mark.parametrize("noise", [PHYSICS, "immerkaer"])
def test_images_outside_0_1_are_refused(scale, noise):
    """Images in DN (0..255) with the physics labels gave σ̃ = 1275 DN for 5 DN of noise, without an error."""
    img = _images()
    est = resolve_estimator(noise, "noise")
    with pytest.raises(ValueError, match=r"images must lie in \[0, 1\] \(DN/255\), got values in \[.*\]"):
        estimate_regions(img * scale, BOXES, est, None, physics={"blurred": torch.full_like(img, 0.5) * scale})


@pytest.mark.parametrize("batch", [3, 4])
def test_metadata_of_another_batch_is_refused(batch):
    """Metadata of batch 3 for 2 images was accepted, and tiles took the rows by image index."""
    meta = CameraMetadata.preset("ICX285", batch_size=batch)
    est = _Noise(lambda n: {"sigma_total": torch.ones(n)})
    with pytest.raises(ValueError, match=rf"metadata has batch {batch} for 2 images; allowed: 1 or 2"):
        estimate_regions(_images(), BOXES, est, None, metadata=meta)


@pytest.mark.parametrize("out, match", [
    (lambda n: {"sigma_total": torch.ones(n), "assessable": torch.ones(1, dtype=torch.bool)},
     r"noise estimator returned assessable of shape \(1,\) for 5 patches; expected \(5,\)"),
    (lambda n: {"sigma_total": torch.tensor(3.0)}, r"returned sigma_total of shape \(\) for 5 patches; expected \(5,\)"),
    (lambda n: {"sigma_total": torch.ones(n + 1)}, r"returned sigma_total of shape \(6,\) for 5 patches; expected \(5,\)"),
    (lambda n: {"sigma_total": torch.ones(n), "sigma": torch.ones(n, 2)},
     r"returned sigma of shape \(5, 2\) for 5 patches; expected \(5, 3\)"),
    (lambda n: {"sigma_total": -torch.ones(n)}, r"returned sigma_total = -1 DN, out of the allowed range: >= 0 DN"),
    (lambda n: {"sigma_total": torch.ones(n), "sigma": -torch.ones(n, 3)},
     r"returned sigma = -1 DN, out of the allowed range: >= 0 DN"),
])
def test_noise_estimator_outputs_of_the_wrong_shape_or_sign_are_refused(out, match):
    """A 1-element ``assessable`` was broadcast to all 5 tiles; σ = −1 came back as σ̃ = −1 DN."""
    with pytest.raises(ValueError, match=match):
        estimate_regions(_images(), BOXES, _Noise(out), None)


@pytest.mark.parametrize("out, match", [
    (lambda n: {"mtf": torch.ones(n, 8)}, r"MTF estimator returned mtf of shape \(17, 8\) for 17 patches; expected \(17, 16\)"),
    (lambda n: {"mtf": torch.ones(n, 17)}, r"returned mtf of shape \(17, 17\) for 17 patches; expected \(17, 16\)"),
    (lambda n: {"mtf": torch.ones(2 * n, 16)}, r"returned mtf of shape \(34, 16\) for 17 patches; expected \(17, 16\)"),
    (lambda n: {"mtf": torch.ones(n, 16), "assessable": torch.ones(1, dtype=torch.bool)},
     r"returned assessable of shape \(1,\) for 17 patches; expected \(17,\)"),
])
def test_mtf_estimator_outputs_of_the_wrong_shape_are_refused(out, match):
    with pytest.raises(ValueError, match=match):
        estimate_regions(_images(), BOXES, None, _MTF(out))


@pytest.mark.parametrize("regions, error, match", [
    ([torch.tensor([[1.0, 2.0, 3.0]]), torch.zeros(0, 4)], ValueError, r"regions\[0\] has shape \(1, 3\); allowed: \(N, 4\)"),
    ([torch.tensor([1.0, 2.0, 300.0, 300.0]), torch.zeros(0, 4)], ValueError, r"regions\[0\] has shape \(4,\); allowed"),
    ([[[1.0, 2.0, 100.0, 100.0]], []], TypeError, r"regions\[0\] must be a tensor of shape \(N, 4\) .* got list"),
    ([torch.zeros(0, 4), torch.tensor([[float("nan"), 0.0, 30.0, 30.0]])], ValueError,
     r"regions\[1\] holds a non-finite box \[nan, 0.0, 30.0, 30.0\]"),
    ([torch.tensor([[200.0, 200.0, 10.0, 10.0]]), torch.zeros(0, 4)], ValueError,
     r"regions\[0\] holds the box \[200.0, 200.0, 10.0, 10.0\] with x2 < x1"),
])
def test_regions_that_are_not_xyxy_box_tensors_are_refused(regions, error, match):
    """(N, 3) boxes failed with "index 3 is out of bounds", a nested list with "'list' object has no attribute
    'detach'"; a NaN or reversed box silently overlapped no tile."""
    with pytest.raises(error, match=match):
        estimate_regions(_images(), regions, ImmerkaerNoiseEstimator(), None)


@pytest.mark.parametrize("physics, noise, mtf, match", [
    ({"blurred": torch.zeros(2, 1, 128, 128)}, PHYSICS, None,
     r"physics\['blurred'\] has shape \(2, 1, 128, 128\); allowed: the images' shape \(2, 1, 256, 256\)"),
    ({"mtf": torch.ones(1, 16)}, None, PHYSICS, r"physics\['mtf'\] has shape \(1, 16\) for 2 images; allowed: \(2, 16\)"),
    ({"mtf": torch.full((2, 16), 5.0)}, None, PHYSICS, r"physics\['mtf'\] = 5 is out of the allowed range \[0, 1\]"),
    ({"mtf": torch.full((2, 16), -1.0)}, None, PHYSICS, r"physics\['mtf'\] = -1 is out of the allowed range \[0, 1\]"),
    ({"blurred": None, "sigma_dn": torch.ones(1, 3)}, PHYSICS, None,
     r"physics\['sigma_dn'\] has shape \(1, 3\) for 2 images; allowed: \(2, 3\)"),
    ({"blurred": None, "sigma_dn": -torch.ones(2, 3)}, PHYSICS, None,
     r"physics\['sigma_dn'\] = -1 DN is out of the allowed range \[0, inf\] DN"),
])
def test_physics_labels_of_another_shape_or_range_are_refused(physics, noise, mtf, match):
    """physics['mtf'] of (1, 16) for 2 images failed with "index 1 is out of bounds"; an MTF of 5.0 or −1.0 came back
    as MTF̃ = 5.0 / −1.0."""
    img = _images()
    physics = {k: (img.clone() if v is None else v) for k, v in physics.items()}
    with pytest.raises(ValueError, match=match):
        estimate_regions(img, BOXES, noise, mtf, physics=physics)


class _Spec:
    kind, metadata_set = "mtf", "none"

    def __init__(self, patch_size, predict=True):
        self.patch_size = patch_size
        if not predict:
            self.predict = None

    def predict(self, patches, metadata=None):
        return {"mtf": torch.ones(patches.shape[0], 16)}


@pytest.mark.parametrize("patch_size", ["abc", 64.7, 64.0, True, 4])
def test_resolve_estimator_needs_an_integer_patch_size(patch_size):
    """patch_size="abc" failed with "invalid literal for int()"; 64.7 was accepted and truncated to 64-px tiles."""
    with pytest.raises(ValueError, match=rf"estimator patch_size = {patch_size!r} is out of the allowed range: an "
                                         r"integer >= 8 px"):
        resolve_estimator(_Spec(patch_size), "mtf")


def test_resolve_estimator_needs_a_callable_predict():
    with pytest.raises(TypeError, match=r"the mtf estimator's predict = None is not callable"):
        resolve_estimator(_Spec(64, predict=False), "mtf")


@pytest.mark.parametrize("patch_size", [3, 5, 7, 7.5, "8"])
def test_immerkaer_patch_size_must_be_one_predict_reads(patch_size):
    """ImmerkaerNoiseEstimator(patch_size=5) was accepted, but predict refuses every patch under 8 px."""
    with pytest.raises(ValueError, match=rf"patch_size = {patch_size!r} is out of the allowed range: an integer >= 8 px"):
        ImmerkaerNoiseEstimator(patch_size)
