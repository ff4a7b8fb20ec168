"""camhealth._inputs on input its checks used to let through: NumPy half-precision patches, a patch size below one
pixel, an unknown estimator kind, and patches of another layout, scale or dtype given to the validated-range check."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from camhealth._inputs import _to_patches, assess_patches, beyond_validated_range


def _eight_bit(seed: int) -> np.ndarray:
    """Two 128-px patches of whole DN (k/255) around 128 DN."""
    rng = np.random.default_rng(seed)
    return (np.clip(np.round(128 + 6 * rng.standard_normal((2, 1, 128, 128))), 0, 255) / 255).astype(np.float32)


def _continuous(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(0.5 + 0.02 * rng.standard_normal((2, 1, 128, 128)), 0, 1).astype(np.float32)


@pytest.mark.parametrize("make", [_eight_bit, _continuous], ids=["8-bit values", "continuous values"])
@pytest.mark.parametrize("layout", ["B×1×H×W", "H×W"])
def test_numpy_float16_patches_read_as_the_same_torch_float16_patches(make, layout):
    """A NumPy float16 array is read as the torch float16 tensor of the same values is (8-bit data restored to k/255,
    continuous data kept), instead of a TypeError from torch for the NumPy dtype."""
    half = make(0).astype(np.float16)
    if layout == "H×W":
        half = half[0, 0]
    from_numpy = _to_patches(half, 128, "auto")
    from_torch = _to_patches(torch.from_numpy(half.copy()), 128, "auto")
    assert from_numpy.dtype == torch.float32 and torch.equal(from_numpy, from_torch)


@pytest.mark.parametrize("where", ["images", "reference", "other_exposures"])
def test_numpy_float16_frames_reach_the_physics_noise_estimator(where):
    """predict takes NumPy float16 images, references and other exposures like float32 ones of the same values."""
    from camhealth.estimators.physics_noise import PhysicsNoiseEstimator
    from camhealth.physics import CameraMetadata

    meta = CameraMetadata.preset("ICX285", gain_db=12.0)
    a, b = _eight_bit(1), _eight_bit(2)
    kwargs16 = {"images": a, "reference": None, "pool": where == "other_exposures"}
    kwargs32 = dict(kwargs16)
    if where == "images":
        kwargs16["images"] = a.astype(np.float16)
    elif where == "reference":
        kwargs16["reference"], kwargs32["reference"] = b.astype(np.float16), b
    else:
        other = CameraMetadata.preset("ICX285", gain_db=12.0, exposure_s=0.05)
        kwargs16["other_exposures"], kwargs32["other_exposures"] = [(b.astype(np.float16), other)], [(b, other)]
    est = PhysicsNoiseEstimator()
    got, want = est.predict(metadata=meta, **kwargs16), est.predict(metadata=meta, **kwargs32)
    for key in ("sigma_total", "xi", "xi_std", "p_match"):
        assert torch.equal(got[key], want[key]), key


@pytest.mark.parametrize("patch_size", [0, -1, 2.5, True, "128"])
def test_a_patch_size_below_one_pixel_or_not_an_integer_is_refused(patch_size):
    """The patch size is checked before it shapes anything: not an empty-dimension RuntimeError from torch, nor
    "patches must be -1×-1 px"."""
    with pytest.raises((TypeError, ValueError), match=rf"patch_size = {patch_size!r}.*(integer|≥ 1)"):
        _to_patches(np.zeros((1, 1, 0, 0), np.float32), patch_size, "auto")


@pytest.mark.parametrize("kind", ["foo", "noise", "MTF", ""])
def test_an_unknown_estimator_kind_is_refused(kind):
    """An unknown kind named with the known ones, instead of being read as a noise kind."""
    with pytest.raises(ValueError, match=rf"kind = {kind!r} must be one of 'mtf', 'drne', 'noise_source'"):
        assess_patches(torch.full((1, 1, 64, 64), 0.5), kind)


_FLAT = torch.full((1, 1, 64, 64), 0.4)


@pytest.mark.parametrize("patches, error, message", [
    ((_FLAT * 255).round().to(torch.uint8), TypeError, r"patches must be a floating tensor.*uint8"),
    (_FLAT * 255, ValueError, r"patches must lie in \[0, 1\].*102"),
    (torch.full((1, 1, 64, 64), float("nan")), ValueError, r"patches must be finite.*4096 of 4096"),
    (_FLAT[:, 0], ValueError, r"patches must have shape B×C×H×W.*\(1, 64, 64\)"),
    (_FLAT[..., :1, :], ValueError, r"patches must be at least 2×2 px, got 1×64"),
    (_FLAT.tolist(), TypeError, r"patches must be a torch.Tensor, got list"),
], ids=["uint8 DN", "float DN", "NaN", "B×H×W", "one row", "list"])
def test_the_validated_range_check_refuses_patches_it_cannot_read(patches, error, message):
    """beyond_validated_range checks its patches as every estimator function does (floating, finite, [0, 1],
    B×1×H×W, at least 2×2): a uint8 or DN-scaled patch of a 3 DN camera no longer reads "beyond the validated range",
    an all-NaN patch no longer "within it". An empty batch and valid patches are read as before."""
    with pytest.raises(error, match=message):
        beyond_validated_range(patches)
    assert beyond_validated_range(torch.zeros(0, 1, 64, 64)).shape == (0,)
    loud = (0.5 + 100.0 / 255.0 * torch.randn(1, 1, 64, 64, generator=torch.Generator().manual_seed(0))).clamp(0, 1)
    assert beyond_validated_range(torch.cat([_FLAT, loud])).tolist() == [False, True]
