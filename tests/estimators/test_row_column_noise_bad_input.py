"""Row and column noise: a ``pool`` that is not a bool is refused naming it (a string such as "no" read as true)."""

from __future__ import annotations

import pytest
import torch

from camhealth.estimators.row_column_noise import row_column_noise


@pytest.mark.parametrize("pool", ["no", "False", 0, 1, None, torch.tensor(True)])
def test_pool_must_be_a_bool(pool):
    patches = torch.full((2, 1, 16, 16), 0.5)
    with pytest.raises(TypeError, match=r"pool = .* must be a bool"):
        row_column_noise(patches, pool=pool)


@pytest.mark.parametrize("pool", [True, False])
def test_a_bool_pool_is_read(pool):
    torch.manual_seed(0)
    patches = (0.5 + 0.02 * torch.randn(2, 1, 16, 16)).clamp(0, 1)
    out = row_column_noise(patches, pool=pool)
    assert out.sigma_dn.shape == (2, 2)
