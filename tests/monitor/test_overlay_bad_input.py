"""render_overlay on bad and extreme input: a uint16 frame of a 10/12/14-bit camera is drawn at the bit depth it was
monitored at (``bit_depth``, as ``Monitor.process`` takes it), and a σ scale whose top lies beyond float32 draws the
colours it means, without numpy's overflow and division warnings."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from camhealth.monitor import Monitor
from camhealth.monitor.overlay import render_overlay
from tests.monitor.conftest import FakeMTF, FakeNoise

LEGEND_PX = 24  # the legend strip under each panel (at scale 1), which prints the scale's top


@pytest.fixture(scope="module")
def frame8():
    g = np.random.default_rng(0).normal(120, 6, (256, 384))
    g[:, 192:] += 60  # an edge: blur is assessable on the right
    return np.clip(g, 0, 255).round().astype(np.uint8)


@pytest.fixture(scope="module")
def report(frame8):
    return Monitor(FakeNoise(), FakeMTF(), sensor="ICX285", mode="map", warmup=False).process(frame8)


def test_a_12_bit_frame_is_drawn_at_its_bit_depth(frame8):
    """render_overlay had no bit_depth: a 12-bit frame in uint16 was drawn 16× too dark, with as_frame's warning
    telling the caller to pass a bit_depth the function did not take."""
    twelve = frame8.astype(np.uint16) * 16  # the same scene, 12-bit codes
    mon = Monitor(FakeNoise(), FakeMTF(), sensor="ICX285", mode="map", warmup=False)
    report12 = mon.process(twelve, bit_depth=12)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        drawn = render_overlay(twelve, report12, bit_depth=12)
    assert np.array_equal(drawn, render_overlay(twelve.astype(np.float32) / 4095, report12))
    assert abs(float(drawn.mean()) - float(render_overlay(frame8, report12).mean())) < 1.0
    with pytest.raises(ValueError, match=r"bit_depth = 12 is for uint16 frames; this frame is uint8"):
        render_overlay(frame8, report12, bit_depth=12)


@pytest.mark.parametrize("top, same_as", [(1e308, 1e30), (1e-320, 1e-30)])
def test_a_sigma_scale_beyond_float32_draws_without_warnings(frame8, report, top, same_as):
    """sigma_max_dn=1e308 ("overflow encountered in cast") and 1e-320 ("divide by zero encountered in divide", 0/0 for a
    σ of 0) printed numpy warnings and depended on NaN casts; the colours are those of any scale as far out."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        drawn = render_overlay(frame8, report, sigma_max_dn=top)
    ref = render_overlay(frame8, report, sigma_max_dn=same_as)
    noise_panel = slice(0, ref.shape[1] // 2)
    assert np.array_equal(drawn[:-LEGEND_PX, noise_panel], ref[:-LEGEND_PX, noise_panel])
    assert np.array_equal(drawn[:, ref.shape[1] // 2:], ref[:, ref.shape[1] // 2:])  # the blur panel: its own scale
