"""Temporal/spatial median aggregation (Eq. 5.4) and the uncertainty-vs-window table (Eq. 5.5)."""

import pytest
import torch

from camhealth.estimators.aggregation import MAD_TO_STD, WINDOW_SIZES, spatial_median, temporal_median, uncertainty_by_window
from camhealth.estimators.pca_noise import pca_noise_sigma


def test_sliding_window_median_by_hand():
    x = torch.tensor([[1.0], [5.0], [2.0], [8.0], [3.0]])  # 5 frames, 1 patch
    agg = temporal_median(x, window=3)
    assert agg.median[:, 0].tolist() == [2.0, 5.0, 3.0]
    assert agg.low[:, 0].tolist() == [1.0, 2.0, 2.0] and agg.high[:, 0].tolist() == [5.0, 8.0, 8.0]
    # window [1, 5, 2]: |dev| from 2 = [1, 3, 0] → MAD 1 → spread 1.4826
    assert float(agg.spread[0, 0]) == pytest.approx(MAD_TO_STD)
    assert agg.count[:, 0].tolist() == [3, 3, 3]


def test_even_window_averages_the_middle_pair_and_disjoint_stride():
    x = torch.tensor([1.0, 3.0, 10.0, 20.0])
    agg = temporal_median(x, window=2, stride=2)
    assert agg.median.tolist() == [2.0, 15.0]


def test_nan_is_skipped_and_all_nan_window_stays_nan():
    x = torch.tensor([[1.0, float("nan")], [3.0, float("nan")], [float("nan"), float("nan")]])
    agg = temporal_median(x, window=3)
    assert agg.median[0, 0] == 2.0 and agg.count[0].tolist() == [2, 0]
    assert torch.isnan(agg.median[0, 1]) and torch.isnan(agg.spread[0, 1])


@pytest.mark.parametrize("shape, dim", [((4, 0), 1), ((0, 5), 1), ((3, 0, 2), (1, 2))])
def test_nothing_to_reduce_gives_nan_and_count_0(shape, dim):
    agg = spatial_median(torch.zeros(shape), dim=dim)
    kept = [s for i, s in enumerate(shape) if i not in ([dim] if isinstance(dim, int) else dim)]
    for v in (agg.median, agg.spread, agg.low, agg.high):
        assert list(v.shape) == kept and bool(torch.isnan(v).all())
    assert agg.count.tolist() == torch.zeros(kept, dtype=torch.int64).tolist()


def test_spatial_median_over_patches():
    x = torch.tensor([[1.0, 2.0, 100.0], [4.0, 5.0, 6.0]])  # 2 frames × 3 patches; an outlier patch
    agg = spatial_median(x, dim=1)
    assert agg.median.tolist() == [2.0, 5.0]
    agg2 = spatial_median(x.reshape(2, 3, 1), dim=(1, 2))
    assert torch.equal(agg2.median, agg.median)


def test_aggregation_reduces_spread_on_a_stationary_sequence():
    """30 frames of a static scene with fresh noise of σ = 20 DN: the PCA estimates scatter over
    patches and frames; the median over n frames narrows P_σ̃n monotonically and keeps its median."""
    g = torch.Generator().manual_seed(0)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, 64), torch.linspace(0, 1, 64), indexing="ij")
    scene = (0.5 + 0.2 * torch.sin(9 * xx) * torch.cos(7 * yy))[None, None]
    frames = (scene + torch.randn(30, 4, 64, 64, generator=g) * 20 / 255).clamp(0, 1)  # 30 frames, 4 "patches"
    est = pca_noise_sigma(frames.reshape(120, 1, 64, 64)).reshape(30, 4)
    table = uncertainty_by_window(est, windows=(1, 2, 4, 10, 20))
    stds = [table[n]["std"] for n in (1, 2, 4, 10, 20)]
    assert all(b < a for a, b in zip(stds, stds[1:]))
    assert table[20]["delta"] == pytest.approx(stds[0] - stds[-1]) and table[20]["delta"] > 0.5 * stds[0]
    assert abs(table[20]["median"] - table[1]["median"]) < 0.5
    assert table[1]["n_values"] == 120 and table[20]["n_values"] == 11 * 4
    assert 40 not in table  # windows longer than the sequence are skipped


def test_window_sizes_of_the_thesis():
    assert WINDOW_SIZES == (1, 2, 4, 10, 20, 40, 100)


@pytest.mark.parametrize("window, err", [(0, ValueError), (7, ValueError), (2.0, TypeError)])
def test_bad_window(window, err):
    with pytest.raises(err, match="window"):
        temporal_median(torch.rand(6, 3), window=window)


def test_bad_estimates():
    with pytest.raises(ValueError, match="inf"):
        temporal_median(torch.tensor([1.0, float("inf")]), window=1)
    with pytest.raises(TypeError, match="floating"):
        temporal_median(torch.tensor([1, 2]), window=1)
    with pytest.raises(ValueError, match="stride"):
        uncertainty_by_window(torch.rand(5, 2), stride="overlap")


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_estimates_are_aggregated_in_float32_and_returned_in_their_dtype(dtype):
    """torch.nanquantile takes float32/float64 only: half-precision estimates (NaN included) give the float32 result
    of the same values, cast back to their dtype."""
    g = torch.Generator().manual_seed(0)
    x = torch.rand(10, 5, generator=g).to(dtype)
    x[2, 1] = float("nan")
    for half, full in ((temporal_median(x, 3), temporal_median(x.float(), 3)),
                       (spatial_median(x, dim=1), spatial_median(x.float(), dim=1))):
        for name in ("median", "spread", "low", "high"):
            got, want = getattr(half, name), getattr(full, name)
            assert got.dtype == dtype and torch.equal(got, want.to(dtype)), name
        assert torch.equal(half.count, full.count)
    empty = spatial_median(torch.zeros(3, 0, dtype=dtype), dim=1)
    assert empty.median.dtype == dtype and bool(torch.isnan(empty.median).all())


def test_integer_estimates_get_a_hint_that_keeps_their_unit():
    """Integer σ in DN: the image hint "x.float() / 255" would have turned DN into DN/255 silently."""
    with pytest.raises(TypeError, match=r"estimates must be a floating tensor .* got dtype torch\.int64; convert with "
                                        r"estimates\.float\(\) \(the values keep their unit\)") as err:
        temporal_median(torch.tensor([[3], [4], [5]]), window=2)
    assert "255" not in str(err.value)
    with pytest.raises(TypeError, match="keep their unit"):
        uncertainty_by_window(torch.tensor([[3], [4], [5]]))


def test_uncertainty_by_window_checks_like_temporal_median():
    """A scalar crashed with a ZeroDivisionError and a window of 2.9 frames silently became 2."""
    with pytest.raises(ValueError, match="estimates must have a frame axis, got a scalar"):
        uncertainty_by_window(torch.tensor(3.0))
    x = torch.rand(10, 4)
    with pytest.raises(TypeError, match=r"every window must be an int \(frames\), got 2\.9 \(float\)"):
        uncertainty_by_window(x, windows=[1, 2.9])
    with pytest.raises(TypeError, match="got True"):
        uncertainty_by_window(x, windows=[True])
    assert sorted(uncertainty_by_window(x, windows=[1, 2, 40])) == [1, 2]  # sizes beyond the frames are skipped
