"""The MTF error table: fitted RMS against known errors, interpolation, the uncertainty formula, refusals."""

import math

import pytest
import torch

from camhealth.estimators.mtf_error import (DEFAULT_KNOTS, MTFErrorTable, fit_error_table, frame_uncertainty, mtf_uncertainty,
                                           shared_error_fraction)


def _table(rms=(0.02, 0.2, 0.04)) -> MTFErrorTable:
    return MTFErrorTable((0.0, 0.5, 1.0), rms, 100, "test")


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
@pytest.mark.parametrize("batch", [1, 256])
def test_table_interpolates_between_knots_and_holds_beyond(dtype, batch):
    t = _table()
    m = torch.tensor([-0.1, 0.0, 0.25, 0.5, 0.75, 1.0, 1.2], dtype=dtype).repeat(batch, 1)
    want = torch.tensor([0.02, 0.02, 0.11, 0.2, 0.12, 0.04, 0.04]).repeat(batch, 1)
    got = t(m)
    assert got.dtype == torch.float32 and got.shape == m.shape
    torch.testing.assert_close(got, want, atol=2e-3 if dtype in (torch.float16, torch.bfloat16) else 1e-6, rtol=0)


def test_uncertainty_adds_the_spread_in_quadrature_and_falls_back_without_a_table():
    t = _table()
    m, s = torch.full((4, 16), 0.5), torch.full((4, 16), 0.15)
    torch.testing.assert_close(mtf_uncertainty(m, t), torch.full((4, 16), 0.2))
    torch.testing.assert_close(mtf_uncertainty(m, t, s), torch.full((4, 16), 0.25))
    torch.testing.assert_close(mtf_uncertainty(m, None, s), s)
    assert torch.isnan(mtf_uncertainty(m, None)).all()
    assert mtf_uncertainty(torch.zeros(0, 16), t).shape == (0, 16)


def test_fit_recovers_a_known_error_profile():
    """Errors drawn with a known σ(H): the fitted RMS at each knot matches σ there (sampling error ~ σ/√(2n))."""
    g = torch.Generator().manual_seed(0)
    sigma = lambda h: 0.02 + 0.3 * h * (1 - h)  # noqa: E731
    # the table is a function of the estimate: draw the errors given the estimate
    est = torch.rand(4000, 16, generator=g, dtype=torch.float64)
    truth = est - sigma(est) * torch.randn(est.shape, generator=g, dtype=torch.float64)
    t = fit_error_table(est, truth, data="synthetic")
    assert t.knots == tuple(DEFAULT_KNOTS) and t.values == est.numel() and t.data == "synthetic"
    for k, r in zip(t.knots[1:-1], t.rms[1:-1]):  # inner knots: their nearest values lie around them
        assert abs(r - sigma(k)) < 0.1 * sigma(k) + 0.005, (k, r, sigma(k))
    # about 95 % of the values within 2u on data like the calibration set
    u = mtf_uncertainty(est, t)
    assert 0.93 < float(((est - truth).abs() <= 2 * u).float().mean()) < 0.97


def test_fit_uses_only_valid_patches_and_fills_sparse_knots():
    est = torch.full((10, 16), 0.5, dtype=torch.float64)
    truth = est + 0.1
    valid = torch.zeros(10, dtype=torch.bool)
    valid[:4] = True
    truth[~valid] = 0.5 + 0.9  # wrong patches that must not count
    t = fit_error_table(est, truth, valid, min_values=8)
    assert t.values == 64 and all(math.isclose(r, 0.1, abs_tol=1e-9) for r in t.rms)  # one measured knot: constant


@pytest.mark.parametrize("kwargs,match", [
    (dict(estimate=torch.rand(3, 16), truth=torch.rand(2, 16)), "same non-empty shape"),
    (dict(estimate=torch.zeros(0, 16), truth=torch.zeros(0, 16)), "same non-empty shape"),
    (dict(estimate=torch.full((3, 16), float("nan")), truth=torch.rand(3, 16)), "finite"),
    (dict(estimate=torch.rand(3, 16), truth=torch.rand(3, 16), valid=torch.ones(2, dtype=torch.bool)), r"valid \(2,\) must be \(3,\)"),
    (dict(estimate=torch.rand(3, 16), truth=torch.rand(3, 16), min_values=1000), "no knot has min_values = 1000"),
    (dict(estimate=torch.rand(3, 16), truth=torch.rand(3, 16), knots=(0.0, 0.7, 0.5, 1.0)), "increase strictly"),
])
def test_fit_refuses_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        fit_error_table(**kwargs)


@pytest.mark.parametrize("d,match", [
    ([0.1], "must be a JSON object"),
    ({"knots": [0, 1], "rms": [0.1, 0.1], "values": 5, "code": "x"}, r"unknown fields \['code'\]"),
    ({"knots": "01", "rms": [0.1, 0.1], "values": 5}, "knots = '01' must be a list of numbers"),
    ({"knots": [0, 1], "rms": [0.1, True], "values": 5}, "rms .* must be a list of numbers"),
    ({"knots": [0, 1], "rms": [0.1], "values": 5}, r"knots \(2\) and rms \(1\) must have the same length"),
    ({"knots": [0.1, 1], "rms": [0.1, 0.1], "values": 5}, "increase strictly from 0 to 1"),
    ({"knots": [0, 1], "rms": [0.1, 1.5], "values": 5}, r"allowed range \[0, 1\]"),
    ({"knots": [0, 1], "rms": [0.1, float("nan")], "values": 5}, "must be finite"),
    ({"knots": [0, 1], "rms": [0.1, 0.1], "values": 0}, "values = 0 must be a positive integer"),
    ({"knots": [0, 1], "rms": [0.1, 0.1], "values": 5, "data": 3}, "data must be a string"),
    ({"knots": [0, 1], "rms": [0.1, 0.1], "values": 5, "shared": 1.5}, r"shared = 1.5 must be a number in the allowed range \[0, 1\]"),
    ({"knots": [0, 1], "rms": [0.1, 0.1], "values": 5, "shared": "0.5"}, "shared = '0.5' must be a number"),
])
def test_from_dict_names_the_bad_field(d, match):
    with pytest.raises(ValueError, match=f"w.pt: .*{match}"):
        MTFErrorTable.from_dict(d, "w.pt")


def test_round_trip():
    t = _table()
    assert MTFErrorTable.from_dict(t.to_dict()) == t


def test_round_trip_keeps_the_shared_part_and_an_older_entry_reads_as_none_shared():
    t = MTFErrorTable((0.0, 0.5, 1.0), (0.02, 0.2, 0.04), 100, "test", 0.68)
    assert MTFErrorTable.from_dict(t.to_dict()) == t
    older = {k: v for k, v in t.to_dict().items() if k != "shared"}  # a file written before the field existed
    assert MTFErrorTable.from_dict(older).shared == 0.0


@pytest.mark.parametrize("rho", [0.0, 0.3, 0.7, 1.0])
def test_shared_fraction_recovers_the_common_part_of_the_errors(rho):
    """Errors z = √ρ·s + √(1 − ρ)·e per patch, s common to a frame's patches: the fraction is ρ."""
    t = _table((0.1, 0.1, 0.1))
    g = torch.Generator().manual_seed(0)
    frames = []
    for _ in range(400):
        truth = torch.full((9, 16), 0.5)
        common = torch.randn(1, 16, generator=g)
        own = torch.randn(9, 16, generator=g)
        frames.append((truth + 0.1 * (math.sqrt(rho) * common + math.sqrt(1 - rho) * own), truth))
    assert shared_error_fraction(frames, t) == pytest.approx(rho, abs=0.03)
    assert shared_error_fraction([(e[:1], tr[:1]) for e, tr in frames], t) == 0.0  # one patch: nothing
    with pytest.raises(ValueError, match="must be the same"):
        shared_error_fraction([(torch.zeros(3, 16), torch.zeros(2, 16))], t)


def _median_sd_monte_carlo(n: int, rho: float, draws: int = 200_000, seed: int = 0) -> float:
    """Standard deviation of the median (torch.quantile at 0.5: the mean of the two middle values for even n, as the
    monitor's spatial median) of n values √ρ·z₀ + √(1 − ρ)·z_i."""
    g = torch.Generator().manual_seed(seed + n)
    z0 = torch.randn(draws, 1, generator=g, dtype=torch.float64)
    z = torch.randn(draws, n, generator=g, dtype=torch.float64)
    return float((math.sqrt(rho) * z0 + math.sqrt(1 - rho) * z).quantile(0.5, dim=1).std())


@pytest.mark.parametrize("n", [1, 2, 3, 6, 10, 64])
@pytest.mark.parametrize("rho", [0.0, 0.68])
def test_frame_uncertainty_never_understates_the_median_standard_error(n, rho):
    """The large-n form u·√(ρ + (π/2)(1 − ρ)/n) against 2·10⁵ simulated medians (relative sampling error ≈ 0.2 %): at
    least the true standard error for every n, and within 2 % of it from 64 patches on (one patch: 1.2533·u at ρ = 0)."""
    u = torch.full((16,), 0.2)
    got = frame_uncertainty(u, n, rho)
    assert got.dtype == torch.float32 and got.shape == (16,)
    true = 0.2 * _median_sd_monte_carlo(n, rho)
    assert float(got[0]) >= true * 0.995
    if n >= 64:
        assert float(got[0]) == pytest.approx(true, rel=0.02)


@pytest.mark.parametrize("n", [1, 9, 256])
def test_frame_uncertainty_keeps_the_shared_part(n):
    u = torch.full((16,), 0.2)
    torch.testing.assert_close(frame_uncertainty(u, n, 0.0), u * math.sqrt(math.pi / 2 / n))  # independent: 1.2533·u/√n
    torch.testing.assert_close(frame_uncertainty(u, n, 1.0), u)  # all shared: no patch count shrinks it
    assert bool((frame_uncertainty(u, n, 0.68) >= u * math.sqrt(0.68)).all())
    with pytest.raises(ValueError, match="allowed range"):
        frame_uncertainty(u, n, 1.2)
    with pytest.raises(ValueError, match="n = 0 must be"):
        frame_uncertainty(u, 0, 0.5)


@pytest.mark.parametrize("n", [2.5, True, float("nan"), -3])
def test_frame_uncertainty_refuses_a_count_that_is_not_one(n):
    with pytest.raises(ValueError, match=r"must be an integer ≥ 1"):
        frame_uncertainty(torch.full((16,), 0.2), n, 0.5)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_table_and_uncertainty_stay_on_the_estimates_device(dtype):
    """The knots and RMS used to be made on the CPU, so an estimate on another device failed inside torch (here the
    meta device, which needs no GPU: the same path as CUDA). The result is on the estimate's device, float32."""
    t = _table()
    m = torch.rand(256, 16, dtype=dtype).to("meta")
    r = t(m)
    assert r.device.type == "meta" and r.shape == m.shape and r.dtype == torch.float32
    u = mtf_uncertainty(m, t, torch.rand(256, 16).to("meta"))
    assert u.device.type == "meta" and u.shape == m.shape and u.dtype == torch.float32
