"""NoiseErrorStats on bad input: no samples give NaN (no data, not a perfect 0); a NaN/inf truth is refused by name."""

from __future__ import annotations

import math

import pytest
import torch

from lightning_modules.metrics import NoiseErrorStats


@pytest.mark.parametrize("updates", [[], [(torch.zeros(0, 2), torch.zeros(0, 2))]])
def test_no_samples_give_nan_not_a_perfect_score(updates):
    """Bias = Std = RMS = 0 came out without data; AMAEPerFamily gives NaN there."""
    stats = NoiseErrorStats(["a", "b"])
    for est, truth in updates:
        stats.update(est, truth)
    out = stats.compute()
    assert set(out) == {f"{q}_{n}" for q in ("bias", "std", "rms") for n in ("a", "b")}
    assert all(math.isnan(float(v)) for v in out.values()), out


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_a_non_finite_truth_is_refused_naming_it(value):
    """An inf truth gave bias = inf, std = nan."""
    stats = NoiseErrorStats(["a", "b"])
    truth = torch.tensor([[1.0, 2.0], [3.0, value]])
    with pytest.raises(ValueError, match=rf"truth must be finite for Bias/Std/RMS, but 1 of 4 values are NaN/inf "
                                         rf"\(first: {value}, column 'b'\)"):
        stats.update(torch.ones(2, 2), truth)
    assert stats.count == 0  # nothing was accumulated


def test_samples_after_an_empty_batch_are_counted_and_reset_empties_again():
    stats = NoiseErrorStats(["a"])
    stats.update(torch.zeros(0, 1), torch.zeros(0, 1))
    assert math.isnan(float(stats.compute()["rms_a"]))
    stats.update(torch.tensor([[2.0], [4.0]]), torch.tensor([[1.0], [1.0]]))
    out = stats.compute()
    assert float(out["bias_a"]) == pytest.approx(2.0) and float(out["std_a"]) == pytest.approx(1.0)
    stats.reset()
    assert math.isnan(float(stats.compute()["bias_a"]))
