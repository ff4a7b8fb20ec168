from __future__ import annotations

import math

import pytest
import torch

from lightning_modules.metrics import AMAEPerFamily, NoiseErrorStats, amae_percent, bias_std_rms


def test_noise_error_stats_hand_computed():
    est = torch.tensor([[1.0], [2.0], [4.0]])
    truth = torch.tensor([[1.0], [1.0], [1.0]])  # errors 0, 1, 3: mean 4/3, mean sq 10/3
    m = NoiseErrorStats(["total"])
    m.update(est[:2], truth[:2])
    m.update(est[2:], truth[2:])
    out = m.compute()
    mean, msq = 4 / 3, 10 / 3
    assert out["bias_total"].item() == pytest.approx(mean)
    assert out["std_total"].item() == pytest.approx((msq - mean**2) ** 0.5)
    assert out["rms_total"].item() == pytest.approx(msq**0.5)
    b, s, r = bias_std_rms(est, truth)
    assert (b.item(), s.item(), r.item()) == pytest.approx((out["bias_total"].item(), out["std_total"].item(), out["rms_total"].item()), rel=1e-6)


def test_noise_error_stats_rejects_shapes():
    with pytest.raises(ValueError, match=r"\(B, 2\)"):
        NoiseErrorStats(["a", "b"]).update(torch.zeros(3, 1), torch.zeros(3, 1))


def test_amae_hand_computed_and_per_family():
    truth = torch.ones(2, 16)
    est = truth.clone()
    est[0, :8] -= 0.1  # H off by 0.1, V exact → AMAE (10 % + 0) / 2 = 5 %
    est[1] -= 0.02  # both off by 0.02 → 2 %
    assert amae_percent(est, truth).tolist() == pytest.approx([5.0, 2.0])
    m = AMAEPerFamily()
    m.update(est, truth, torch.tensor([0, 2]))
    out = m.compute()
    assert out["amae_defocus"].item() == pytest.approx(5.0)
    assert out["amae_nonlinear"].item() == pytest.approx(2.0)
    assert math.isnan(out["amae_linear"].item())  # no sample of the family: no data, not a perfect 0 %
    assert out["amae"].item() == pytest.approx(3.5)
    assert all(math.isnan(v.item()) for v in AMAEPerFamily().compute().values())  # no samples at all


@pytest.mark.parametrize("labels,bad", [([5, 0], "5"), ([0, -1], "-1"), ([0, 3], "3"), ([0.5, 1.0], "0.5"),
                                        ([float("nan"), 0.0], "nan")])
def test_amae_refuses_family_labels_outside_the_families(labels, bad):
    """A label outside 0..2 was clamped into the first or last family; now it is refused, naming the value."""
    m = AMAEPerFamily()
    with pytest.raises(ValueError, match=rf"family label {bad} is not a family index 0..2"):
        m.update(torch.rand(2, 16), torch.rand(2, 16), torch.tensor(labels))
    assert m.count.sum().item() == 0  # nothing was counted


@pytest.mark.parametrize("cast", ["bfloat16", "float16", "half", "double", "float64", "meta"])
def test_metric_states_stay_float64_when_the_module_is_cast(cast):
    """Lightning's bf16-true casts the module with .to(torch.bfloat16) (64-true with .double()): the accumulators keep
    float64 (a bf16 count stops growing at 256, index_add_ refuses float64 sources) and move with the device only."""
    from lightning_modules import MTFEstimator, NoiseSourceEstimator

    def apply(module):
        if cast in ("half", "double"):
            return getattr(module, cast)()
        return module.to(cast if cast == "meta" else getattr(torch, cast))

    device = "meta" if cast == "meta" else "cpu"
    for module in (NoiseSourceEstimator(patch_size=32), MTFEstimator(patch_size=32)):
        apply(module)
        for metric in module.modules():
            if isinstance(metric, (NoiseErrorStats, AMAEPerFamily)):
                for key in metric._defaults:
                    state = getattr(metric, key)
                    assert state.dtype == metric._defaults[key].dtype == torch.float64, (type(metric).__name__, key)
                    assert state.device.type == metric._defaults[key].device.type == device, (type(metric).__name__, key)
    if cast == "meta":
        return
    g = torch.Generator().manual_seed(0)
    est, truth = torch.rand(600, 16, generator=g), torch.rand(600, 16, generator=g)
    family = torch.randint(0, 3, (600,), generator=g)
    ref, low = AMAEPerFamily(), apply(AMAEPerFamily())
    noise_ref, noise_low = NoiseErrorStats(["total"]), apply(NoiseErrorStats(["total"]))
    for i in range(0, 600, 8):
        ref.update(est[i:i + 8], truth[i:i + 8], family[i:i + 8])
        low.update(est[i:i + 8], truth[i:i + 8], family[i:i + 8])
        noise_ref.update(est[i:i + 8, :1] * 10, truth[i:i + 8, :1] * 10)
        noise_low.update(est[i:i + 8, :1] * 10, truth[i:i + 8, :1] * 10)
    assert noise_low.count.item() == 600
    for a, b in ((ref.compute(), low.compute()), (noise_ref.compute(), noise_low.compute())):
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


# ------------------------------------------------------------------- camhealth.metrics: shapes and output dtype
@pytest.mark.parametrize("batch", [1, 4, 256])
def test_bias_std_rms_and_mae_hv_refuse_a_truth_that_enlarges_the_estimate(batch):
    """A (B,) estimate against a (B, 1) truth used to be broadcast both ways into B × B pairs (for 1, 2, 3, 4: Std 1.58
    and n 16 instead of Std 0 and n 4); (B, 16) MTFs against (B, 1, 16) into (B, B, 2). Both are refused, naming the
    shapes; one-way broadcasting (one truth for every row) still gives what the expanded truth gives."""
    from camhealth.metrics import bias_std_rms as full, mae_hv

    est = torch.arange(1.0, batch + 1.0)
    truth = est[:, None].clone()
    with pytest.raises(ValueError, match=rf"truth \({batch}, 1\) must broadcast to estimate \({batch},\)"):
        full(est, truth)
    with pytest.raises(ValueError, match=rf"truth \({batch}, 1\) must broadcast to estimate \({batch},\)"):
        bias_std_rms(est, truth)  # the tuple form of lightning_modules
    with pytest.raises(ValueError, match=rf"target \({batch}, 1, 16\) must broadcast to pred \({batch}, 16\)"):
        mae_hv(torch.rand(batch, 16), torch.rand(batch, 1, 16))
    r = full(est, truth.reshape(-1))
    assert (float(r["std"]), float(r["rms"]), int(r["n"])) == (0.0, 0.0, batch)
    g = torch.Generator().manual_seed(batch)
    est, truth = torch.rand(batch, 3, generator=g) * 10, torch.rand(3, generator=g) * 10
    a, b = full(est, truth, dim=0), full(est, truth.expand(batch, 3), dim=0)
    assert all(torch.equal(a[k], b[k]) for k in a) and int(a["n"]) == batch
    mtf, gt = torch.rand(batch, 16, generator=g), torch.rand(16, generator=g)
    assert torch.equal(mae_hv(mtf, gt), mae_hv(mtf, gt.expand(batch, 16)))


_FLOATS = (torch.float16, torch.bfloat16, torch.float32, torch.float64)


@pytest.mark.parametrize("a, b", [(a, b) for a in _FLOATS for b in _FLOATS if a != b])
def test_bias_std_rms_returns_the_promoted_dtype_in_either_order(a, b):
    """The output dtype used to be the estimate's: an fp16 estimate against an fp64 truth gave fp16, the reverse fp64.
    Now it is torch.promote_types of the two, whichever comes first, with the float64 values."""
    from camhealth.metrics import bias_std_rms as full

    est, truth = torch.tensor([11.0, 13.0, 19.0, 21.0]), torch.tensor([10.0, 10.0, 20.0, 20.0])
    want = torch.promote_types(a, b)
    for r in (full(est.to(a), truth.to(b)), full(truth.to(b), est.to(a))):
        assert {r[k].dtype for k in ("bias", "std", "rms")} == {want}
        assert float(r["bias"]) == pytest.approx(1.0) and float(r["rms"]) == pytest.approx(math.sqrt(3.0), rel=1e-2)


def test_bias_std_rms_refuses_a_result_that_overflows_float16():
    """fp16 estimates of 60000 against truths of −60000: the error 120000 is finite in float64 but was returned as
    inf in float16. Now it is refused, naming the value and the dtype; float32 inputs give it."""
    from camhealth.metrics import bias_std_rms as full

    est, truth = torch.full((4,), 60000.0, dtype=torch.float16), torch.full((4,), -60000.0, dtype=torch.float16)
    with pytest.raises(ValueError, match=r"up to 120000 do not fit the output dtype torch.float16"):
        full(est, truth)
    r = full(est.float(), truth.float())
    assert float(r["bias"]) == float(r["rms"]) == 120000.0 and r["rms"].dtype == torch.float32
    small = full(torch.full((4,), 30000.0, dtype=torch.float16), torch.full((4,), -30000.0, dtype=torch.float16))
    assert float(small["rms"]) == 60000.0 and small["rms"].dtype == torch.float16
