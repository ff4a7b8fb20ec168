"""The arguments every estimator LightningModule takes (EstimatorModule): a value of the wrong type is named."""

from __future__ import annotations

import pytest

from lightning_modules import MTFEstimator, NoiseLevelEstimator, NoiseSourceEstimator


@pytest.mark.parametrize("cls", [NoiseSourceEstimator, NoiseLevelEstimator, MTFEstimator])
@pytest.mark.parametrize("kwargs, match", [
    ({"lr": "0.1"}, r"lr = '0\.1' must be a finite number"),
    ({"lr": None}, r"lr = None must be a finite number"),
    ({"weight_decay": "0"}, r"weight_decay = '0' must be a finite number"),
])  # fmt: skip
def test_a_learning_rate_or_weight_decay_that_is_no_number_is_named(cls, kwargs, match):
    """The base class compared lr > 0 before the values were checked: "'>' not supported between instances of 'str'
    and 'int'", which names no argument."""
    with pytest.raises(ValueError, match=match):
        cls(patch_size=32, **kwargs)
