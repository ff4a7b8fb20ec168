"""Overlay PNGs and heat maps."""

import numpy as np
import pytest
import torch

from camhealth.monitor import Monitor
from camhealth.monitor.overlay import heat_map, render_overlay, save_overlay
from tests.monitor.conftest import FakeMTF, FakeNoise, noisy


@pytest.fixture
def report_and_frame(street_frames):
    mon = Monitor(FakeNoise(), FakeMTF(), sensor="ICX285")
    frame = noisy(street_frames[0], 3.0, seed=0).clone()
    frame[..., :200, :200] = 1.0  # a saturated corner: skipped patches are hatched
    return mon.process(frame), frame


def test_heat_map_matches_patch_values(report_and_frame):
    report, _ = report_and_frame
    hm = heat_map(report.noise)
    g = report.noise.grid_obj
    assert hm.shape == (576, 768) and hm.dtype == np.float32
    assert np.isnan(hm[:32]).all()  # outside the grid (576 = 32 + 4·128 + 32)
    for i, (x0, y0, x1, y1) in enumerate(g.boxes().tolist()):
        v = float(report.noise.values[i, 4])
        block = hm[y0:y1, x0:x1]
        assert (np.isnan(block).all() if np.isnan(v) else np.allclose(block, v))
    assert np.isnan(hm[32:160, 0:128]).all()  # the saturated patch has no value
    hm_mtf = heat_map(report.mtf)
    assert np.nanmax(hm_mtf) <= 1 and np.nanmin(hm_mtf) >= 0
    with pytest.raises(ValueError, match="quantity"):
        heat_map(report.noise, "indicator")


def test_render_and_save(report_and_frame, tmp_path):
    import cv2

    report, frame = report_and_frame
    img = render_overlay(frame, report)
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    assert img.shape[1] == 2 * 768 and img.shape[0] > 576  # two panels + title/colour bar
    path = save_overlay(tmp_path / "o" / "f.png", frame, report, sigma_max_dn=10.0)
    back = cv2.imread(str(path))
    assert back.shape == img.shape
    small = render_overlay(frame, report, max_panel_width=384)
    assert small.shape[1] == 2 * 384
    with pytest.raises(ValueError, match="PNG"):
        save_overlay(tmp_path / "f.jpg", frame, report)
    with pytest.raises(ValueError, match="report is for"):
        render_overlay(torch.rand(100, 100), report)
    for bad in (0.0, "20", float("nan"), True):
        with pytest.raises(ValueError, match=r"sigma_max_dn = .* must be a finite number > 0"):
            render_overlay(frame, report, sigma_max_dn=bad)
    for bad in (0, -5, 10.5):  # a 0-px panel was drawn as a 59×2 px image
        with pytest.raises(ValueError, match=r"max_panel_width = .* must be an integer ≥ 64"):
            render_overlay(frame, report, max_panel_width=bad)


def test_heat_map_of_a_frame_smaller_than_one_patch_is_all_nan():
    """A frame smaller than one patch is a documented skip: its heat map is the H×W map, NaN everywhere (no grid)."""
    r = Monitor(FakeNoise(), FakeMTF(), sensor="ICX285", warmup=False).process(np.full((100, 90), 128, np.uint8))
    for task in (r.noise, r.mtf):
        assert not task.assessable and "smaller than one" in task.note
        hm = heat_map(task)
        assert hm.shape == (100, 90) and hm.dtype == np.float32 and np.isnan(hm).all()
