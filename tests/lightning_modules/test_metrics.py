from __future__ import annotations

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
    assert out["amae_linear"].item() == 0.0
    assert out["amae"].item() == pytest.approx(3.5)
