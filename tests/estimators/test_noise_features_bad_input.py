"""The closed-form priors of camhealth.estimators.noise_features on arguments they used to read silently or crash
on: DN-scaled or malformed images, per-patch metadata of the wrong length, negative or non-finite, flags given as
strings, a cache that is no dict, metadata that is no CameraMetadata, and fixed sensor constants lost on the way to the
noise model."""

import re

import pytest
import torch

from camhealth.estimators.noise_features import clipped_prior_dn, metadata_from_matrix, physics_prior_dn
from camhealth.physics.metadata import FULL_FIELDS, CameraMetadata, SensorConstants

_IMAGE = torch.full((2, 1, 32, 32), 0.4)
_ONE = torch.tensor([1.0])


@pytest.mark.parametrize("image, error, message", [
    (_IMAGE * 255, ValueError, r"image must lie in \[0, 1\].*102"),
    ((_IMAGE * 255).round().to(torch.uint8), TypeError, r"image must be a floating tensor.*uint8"),
    (torch.full((2, 1, 32, 32), float("nan")), ValueError, r"image must be finite"),
    (_IMAGE[:, 0], ValueError, r"image must have shape B×C×H×W.*\(2, 32, 32\)"),
    (_IMAGE.tolist(), TypeError, r"image must be a torch.Tensor, got list"),
], ids=["float DN", "uint8 DN", "NaN", "B×H×W", "list"])
def test_clipped_prior_refuses_images_it_cannot_read(image, error, message):
    """A DN-scaled image returned plausible numbers (treated as saturated); now it is refused like physics_prior_dn's."""
    with pytest.raises(error, match=message):
        clipped_prior_dn(image, _ONE, _ONE, _ONE)


@pytest.mark.parametrize("name", ["pn_slope", "dcsn_dn", "rn_dn"])
@pytest.mark.parametrize("values", [torch.ones(3), torch.ones(0), torch.ones(2, 2)], ids=["3 for 2", "none", "2×2"])
def test_clipped_prior_refuses_per_patch_values_of_another_length(name, values):
    """Each of pn_slope, dcsn_dn and rn_dn holds 1 or B values; 3 for 2 patches raised torch's "expanded size". One
    value and one per patch still give the same σ, far from the bounds the unclipped model's."""
    args = {"pn_slope": _ONE, "dcsn_dn": _ONE, "rn_dn": _ONE, name: values}
    with pytest.raises(ValueError, match=rf"{name} must hold 1 or 2 values \(one per patch\), got shape {re.escape(str(tuple(values.shape)))}"):
        clipped_prior_dn(_IMAGE, **args)
    one = clipped_prior_dn(_IMAGE, torch.tensor([0.5]), torch.tensor([1.0]), torch.tensor([2.0]))
    per = clipped_prior_dn(_IMAGE, torch.full((2,), 0.5), torch.ones(2), torch.full((2,), 2.0))
    assert torch.equal(one, per)
    assert torch.allclose(one[0], torch.tensor([(0.5 * 102.0) ** 0.5, 1.0, 2.0, (0.5 * 102.0 + 5.0) ** 0.5], dtype=torch.float64))


@pytest.mark.parametrize("name", ["pn_slope", "dcsn_dn", "rn_dn"])
def test_clipped_prior_refuses_per_patch_values_that_are_not_tensors(name):
    args = {"pn_slope": _ONE, "dcsn_dn": _ONE, "rn_dn": _ONE, name: [1.0, 1.0]}
    with pytest.raises(TypeError, match=rf"{name} must be a torch.Tensor .*got list"):
        clipped_prior_dn(_IMAGE, **args)


@pytest.mark.parametrize("clipping", ["no", "False", 0, 1, None])
def test_physics_prior_clipping_flag_must_be_a_bool(clipping):
    """clipping="no" returned the 8 columns of clipping=True."""
    with pytest.raises(TypeError, match=rf"clipping = {clipping!r} must be True or False"):
        physics_prior_dn(_IMAGE, CameraMetadata.preset("ICX285"), clipping=clipping)


@pytest.mark.parametrize("cache", [[], (), "cache", 0])
def test_physics_prior_cache_must_be_a_dict(cache):
    """cache=[] raised "'list' object has no attribute 'get'"."""
    with pytest.raises(TypeError, match=rf"cache = {re.escape(repr(cache))} must be a dict or None"):
        physics_prior_dn(_IMAGE, CameraMetadata.preset("ICX285"), cache=cache)


@pytest.mark.parametrize("constants", [SensorConstants(source_follower_gain=0.8),
                                       SensorConstants(flicker_corner_hz=1e8, cds_sample_time_s=1e-5)])
def test_metadata_from_matrix_keeps_the_constants_it_is_given(constants):
    """The raw rows carry the 11 fields only: the fixed constants are passed beside them, and the σ of the rebuilt
    metadata are those of the original."""
    meta = CameraMetadata.preset("EV76C661", gain_db=12.0)
    meta = CameraMetadata(**{n: getattr(meta, n) for n in FULL_FIELDS}, constants=constants)
    rows = torch.stack([getattr(meta, n).double() for n in FULL_FIELDS], 1)
    rebuilt = metadata_from_matrix(rows, constants)
    assert rebuilt.constants == constants
    assert torch.allclose(physics_prior_dn(_IMAGE, rebuilt), physics_prior_dn(_IMAGE, meta))
    assert metadata_from_matrix(rows).constants == SensorConstants()


@pytest.mark.parametrize("constants", [{"source_follower_gain": 0.8}, "default", 1.0])
def test_metadata_from_matrix_refuses_constants_that_are_not_sensor_constants(constants):
    rows = torch.stack([getattr(CameraMetadata.preset("ICX285"), n).double() for n in FULL_FIELDS], 1)
    with pytest.raises(TypeError, match=r"constants must be SensorConstants or None, got"):
        metadata_from_matrix(rows, constants)


@pytest.mark.parametrize("meta", ["ICX285", {"gain_db": 3.0}, None], ids=["preset name", "dict", "None"])
def test_physics_prior_refuses_metadata_that_is_not_camera_metadata(meta):
    """A preset name or a dict raised "'str' object has no attribute 'batch_size'"."""
    with pytest.raises(TypeError, match=r"meta must be CameraMetadata .*got " + type(meta).__name__):
        physics_prior_dn(_IMAGE, meta)


@pytest.mark.parametrize("name", ["pn_slope", "dcsn_dn", "rn_dn"])
@pytest.mark.parametrize("value, message", [(-1.0, r"= -1 .*out of the allowed range \[0, inf\]"),
                                            (float("inf"), r"must be finite"), (float("nan"), r"must be finite")],
                         ids=["negative", "inf", "NaN"])
def test_clipped_prior_names_the_argument_that_is_not_a_finite_sigma(name, value, message):
    """A negative σ was read as its absolute value, and NaN or ∞ was named "slope" or "offset" by the clipping model."""
    args = {"pn_slope": _ONE, "dcsn_dn": _ONE, "rn_dn": _ONE, name: torch.tensor([value])}
    with pytest.raises(ValueError, match=rf"{name} {message}"):
        clipped_prior_dn(_IMAGE, **args)


@pytest.mark.parametrize("u", [[1.0], 2.0, "1"])
def test_truncated_second_moment_takes_tensors_only(u):
    """A list or number raised "'list' object has no attribute 'double'"."""
    from camhealth.estimators.noise_features import truncated_second_moment

    with pytest.raises(TypeError, match=rf"u must be a torch.Tensor of real numbers, got {type(u).__name__}"):
        truncated_second_moment(u)


_PATCH = torch.full((2, 1, 16, 16), 0.4)


@pytest.mark.parametrize("image, error, message", [
    (torch.full((2, 1, 16, 16), float("nan")), ValueError, r"image must be finite, but 512 of 512 values are NaN/inf"),
    ((_PATCH * 255).round().to(torch.uint8), TypeError, r"image must be a floating tensor .*got dtype torch.uint8; "
                                                        r"convert integer DN images with x.float\(\) / 255"),
    (_PATCH[:, 0], ValueError, r"image must have shape B×C×H×W \(4 dims\), got \(2, 16, 16\)"),
    (_PATCH.expand(2, 3, 16, 16), ValueError, r"image must have C = 1 channel\(s\), got C = 3"),
    (_PATCH * 255, ValueError, r"image must hold intensities in \[0, 1\] \(DN/255; a static pair's unclamped fold within "
                               r"\[-1, 2\]\), got values in \[102, 102\]"),
    (_PATCH.tolist(), TypeError, r"image must be a torch.Tensor, got list"),
], ids=["NaN", "uint8 DN", "B×H×W", "3 channels", "float DN", "list"])
def test_block_details_refuses_images_it_cannot_read(image, error, message):
    """NaN passed through into the details, a uint8 image was read as DN × 255 (every block "clipped") and a B×H×W
    batch as one image of B rows of blocks."""
    from camhealth.estimators.noise_features import block_details

    with pytest.raises(error, match=message):
        block_details(image)


def test_block_details_reads_images_and_static_pair_folds_as_before():
    """An image in [0, 1] and a static pair's unclamped fold (within [−1, 2]) are read as the formulas say."""
    from camhealth.estimators.noise_features import block_details

    g = torch.Generator().manual_seed(0)
    for x in (torch.rand(2, 1, 16, 18, generator=g), torch.rand(1, 1, 8, 8, generator=g) * 2.0 - 0.5):
        m, d2, usable, _ = block_details(x)
        q = x * 255.0  # (even sides: every pixel in a 2×2 block)
        p00, p01, p10, p11 = q[..., 0::2, 0::2], q[..., 0::2, 1::2], q[..., 1::2, 0::2], q[..., 1::2, 1::2]
        assert torch.equal(m, (p00 + p01 + p10 + p11) / 4.0)
        assert torch.equal(d2[0], ((p00 - p01 - p10 + p11) / 2.0).square())


@pytest.mark.parametrize("x, error, message", [
    (torch.rand(16, 16), ValueError, r"x must have shape B×C×H×W \(4 dims\), got \(16, 16\)"),
    (torch.rand(1, 16, 16), ValueError, r"x must have shape B×C×H×W \(4 dims\), got \(1, 16, 16\)"),
    (torch.zeros(1, 1, 8, 8, dtype=torch.uint8), TypeError, r"x must be a floating tensor .*got dtype torch.uint8; "
                                                           r"convert integer DN images"),
    ([[0.5]], TypeError, r"x must be a torch.Tensor \(B×C×H×W\), got list"),
], ids=["2-D", "3-D", "uint8", "list"])
def test_box_mean3_refuses_what_is_no_image_batch(x, error, message):
    """A 2-D image failed in torch's replicate padding with a NotImplementedError about its dimensions."""
    from camhealth.estimators.noise_features import box_mean3

    with pytest.raises(error, match=message):
        box_mean3(x)


def test_box_mean3_of_an_image_batch_is_the_padded_3x3_mean():
    import torch.nn.functional as F

    from camhealth.estimators.noise_features import box_mean3

    x = torch.rand(2, 3, 9, 7, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    torch.testing.assert_close(box_mean3(x), F.avg_pool2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), 3, stride=1),
                               rtol=0, atol=1e-15)
