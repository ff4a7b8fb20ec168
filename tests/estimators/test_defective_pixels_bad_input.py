"""Defective pixels: the type of noise_dn."""

import pytest
import torch

from camhealth.estimators.defective_pixels import defective_pixels


def _patches(dtype: torch.dtype) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    x = (0.5 + 3.0 / 255.0 * torch.randn(2, 1, 32, 32, generator=g, dtype=torch.float64)).clamp(0, 1)
    x[0, 0, 10, 10] = 0.9  # a hot pixel
    return x.to(dtype)


@pytest.mark.parametrize("noise_dn", ["2", True, {"a": 1.0}, object(), torch.tensor([True, False])])
def test_a_noise_level_that_is_not_a_real_number_is_a_type_error(noise_dn):
    """"2" failed with "new(): invalid data type 'str'"."""
    with pytest.raises(TypeError, match=r"defective_pixels: noise_dn must be a real tensor of σ \[DN\] per patch"):
        defective_pixels(_patches(torch.float32), noise_dn)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_real_noise_levels_are_accepted_as_tensors_or_sequences(dtype):
    x = _patches(dtype)
    ref = defective_pixels(x, torch.tensor([3.0, 3.0]))
    got = defective_pixels(x, [3.0, 3.0])
    assert torch.equal(got.mask, ref.mask) and got.hot.tolist() == [1, 0]
    with pytest.raises(ValueError, match="one finite σ ≥ 0"):
        defective_pixels(x, [3.0, -1.0])
