"""margin_to_score for margins whose exponential overflows, and HOGPeopleDetector settings that are not numbers."""

import math

import numpy as np
import pytest
import torch

from camhealth.detection import HOGPeopleDetector, margin_to_score


@pytest.mark.parametrize("margin", [-1000.0, -710.0, -1e300])
def test_very_negative_python_margins_give_a_score_near_zero_like_the_array_paths(margin):
    """margin_to_score(-1000.0) raised OverflowError: math range error; numpy and torch return 0."""
    s = margin_to_score(margin)
    assert 0.0 <= s < 1e-300
    assert s == pytest.approx(float(torch.sigmoid(torch.tensor(margin, dtype=torch.float64))), abs=1e-300)
    for w in (-700.0, -5.0, 0.0, 0.41, 2.0, 1000.0):  # ordinary margins: the same value as before
        assert margin_to_score(w) == 1.0 / (1.0 + math.exp(-w))


@pytest.mark.parametrize("kw, match", [
    ({"win_stride": (math.nan, 8)}, r"win_stride = \(nan, 8\) must be two non-negative integers \(x, y\) in px"),
    ({"win_stride": (8, math.inf)}, r"win_stride = \(8, inf\) must be two non-negative integers"),
    ({"padding": "ab"}, r"padding = 'ab' must be two non-negative integers \(x, y\) in px"),
    ({"padding": 8}, r"padding = 8 must be two non-negative integers"),
    ({"group_threshold": math.nan}, r"group_threshold = nan must be an integer >= 0"),
    ({"hit_threshold": "0"}, r"hit_threshold = '0' must be finite \(an SVM margin\)"),
])
def test_settings_that_are_not_numbers_are_refused_naming_the_parameter(kw, match):
    """win_stride=(nan, 8) and group_threshold=nan raised 'cannot convert float NaN to integer', padding='ab'
    "invalid literal for int()"; integer-valued settings of other types are still accepted."""
    with pytest.raises(ValueError, match=match):
        HOGPeopleDetector(**kw)
    hog = HOGPeopleDetector(win_stride=(np.int64(16), 8.0), padding=[0, torch.tensor(8)], group_threshold=1.0)
    assert hog.win_stride == (16, 8) and hog.padding == (0, 8) and hog.group_threshold == 1
