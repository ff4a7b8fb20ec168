"""Row and column noise on partly clipped patches: fully clipped blocks are left out."""

import pytest
import torch

from camhealth.estimators.noise_features import block_details
from camhealth.estimators.row_column_noise import debanded_details, row_column_noise


def _banded(b: int, pixel_dn: float, row_dn: float, level: float = 0.5, seed: int = 0, size: int = 128,
            dtype: torch.dtype = torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = (level + pixel_dn / 255.0 * torch.randn(b, 1, size, size, generator=g, dtype=torch.float64)
         + row_dn / 255.0 * torch.randn(b, 1, size, 1, generator=g, dtype=torch.float64))
    return ((x.clamp(0, 1) * 255.0).round() / 255.0).to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("pool", [False, True])
@pytest.mark.parametrize("fill", [1.0, 0.0])
@pytest.mark.parametrize("frac", [0.2, 0.4, 0.6])
def test_saturated_or_black_columns_do_not_pull_row_noise_down(dtype, pool, fill, frac):
    """5 DN of row offsets over 2 DN of pixel noise with 20–60 % of the columns at 255 (0) DN: σ̂_row stays within
    10 % of the unclipped patch's (it read −13 % at 20 %, −50 % at 40 %) and is still detected."""
    x = _banded(16, 2.0, 5.0, dtype=dtype)
    ref = row_column_noise(x, pool=pool)
    x[..., : int(128 * frac)] = fill
    r = row_column_noise(x, pool=pool)
    assert r.detected[:, 0].all() and not r.detected[:, 1].any()
    assert float(r.sigma_dn[:, 0].mean()) == pytest.approx(float(ref.sigma_dn[:, 0].mean()), rel=0.1)


def test_saturated_rows_are_left_out_of_the_differences():
    """The bottom 40 % of the rows saturated: the rows above still give the row noise (those rows are not read)."""
    x = _banded(16, 2.0, 5.0, seed=4)
    ref = row_column_noise(x[..., :76, :])
    x[..., 76:, :] = 1.0
    r = row_column_noise(x)
    assert r.detected[:, 0].all()
    assert float(r.sigma_dn[:, 0].mean()) == pytest.approx(float(ref.sigma_dn[:, 0].mean()), rel=0.05)


@pytest.mark.parametrize("pool", [False, True])
def test_a_fully_clipped_patch_reads_nothing(pool):
    x = torch.cat([torch.ones(2, 1, 64, 64), torch.zeros(2, 1, 64, 64)])
    r = row_column_noise(x, pool=pool)
    assert not r.detected.any()
    for t in (r.sigma_dn, r.var_se_dn2, r.significance, r.serial):
        assert torch.isfinite(t).all() and not t.any()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_unclipped_patches_of_a_batch_keep_their_numbers(dtype):
    """Patches without a fully clipped block are read exactly as alone, whatever the other patches of the batch."""
    x = _banded(8, 3.0, 2.0, seed=7, dtype=dtype)
    x[0, ..., :40] = 1.0
    x[3, ..., 60:90, :] = 0.0
    keep = torch.tensor([1, 2, 4, 5, 6, 7])
    r, alone = row_column_noise(x), row_column_noise(x[keep])
    for f in ("sigma_dn", "var_se_dn2", "significance", "serial", "detected"):
        assert torch.equal(getattr(r, f)[keep], getattr(alone, f)), f


def test_noise_clipped_at_scattered_pixels_still_shows_its_banding():
    """A dark patch (mean 3 DN, 5 DN of noise: 31 % of the pixels at 0) with 2 DN of row noise: detected on nearly
    every patch as before (leaving out every block with a clipped pixel found it on 6 %)."""
    x = _banded(64, 5.0, 2.0, level=3.0 / 255.0, seed=5)
    assert float((x == 0).float().mean()) > 0.25
    r = row_column_noise(x)
    assert float(r.detected[:, 0].float().mean()) >= 0.9 and not r.detected[:, 1].any()


def test_debanding_a_clipped_patch_takes_the_offsets_of_its_unclipped_blocks():
    """With 40 % of the columns saturated, the offsets taken out are the unclipped blocks' midmeans: their horizontal
    details then read pixel noise alone (E[h²] = E[d²])."""
    x = _banded(16, 3.0, 5.0, seed=2)
    x[..., :52] = 1.0
    m, d2, usable, g2 = block_details(x)
    r = row_column_noise(x)
    assert r.detected[:, 0].all()
    d2b, _ = debanded_details(x, m, d2, g2, r.detected)
    free = d2b[1][..., 26:]
    ratio = free.mean() / d2b[0][..., 26:].mean()
    assert float(ratio) == pytest.approx(1.0, abs=0.08)
