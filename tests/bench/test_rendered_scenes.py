"""The benchmark's rendered scenes (camhealth.bench.rendered_scenes): seeded, in range, and rendered with an exact
pixel aperture (a straight edge drawn by the same rule has native MTF 1)."""

from __future__ import annotations

import pytest
import torch

from camhealth.bench.rendered_scenes import CLASSES, render_scenes, render_slanted_edge


@pytest.mark.parametrize("cls", CLASSES)
def test_each_class_is_seeded_in_range_and_of_the_right_shape(cls):
    a = render_scenes(cls, 2, 64, seed=3)
    assert a.shape == (2, 1, 64, 64) and a.dtype == torch.float32
    assert float(a.min()) >= 0.0 and float(a.max()) <= 1.0
    assert torch.equal(a, render_scenes(cls, 2, 64, seed=3))  # same seed: identical
    assert torch.equal(a[:1], render_scenes(cls, 1, 64, seed=3))  # scene i does not depend on n
    assert not torch.equal(a, render_scenes(cls, 2, 64, seed=4))  # another seed: another scene
    assert not torch.equal(a[0], a[1])
    assert float(a.std((1, 2, 3)).min()) > 0.01  # not blank


def test_a_straight_edge_rendered_by_the_same_rule_has_native_mtf_1():
    """The mean of 8×8 point samples is the pixel-area integral within the closed form's 0.2 % at f_n 0.6; the
    slanted edge (pixel aperture divided out) must read 1 there, and the same edge point-sampled (s = 1) must not."""
    from camhealth.data.native_mtf import edge_native_mtf

    fn = (0.05, 0.3, 0.6)
    roi = (slice(None), slice(None), slice(24, 104), slice(34, 94))  # centre column, ±30 px across the edge
    sharp = edge_native_mtf(render_slanted_edge(128).double()[roi], fn, aperture=True)[0]
    assert torch.allclose(sharp, torch.ones(3, dtype=sharp.dtype), atol=0.02), sharp
    point = edge_native_mtf(render_slanted_edge(128, supersample=1).double()[roi], fn, aperture=True)[0]
    assert float(point[2]) > 1.1  # no aperture: 1/sinc(0.3) = 1.17, sharper than any camera


@pytest.mark.parametrize("kwargs,match", [
    ({"cls": "leaves"}, r"cls = 'leaves' is not one of"),
    ({"n": 0}, r"n = 0 is out of the allowed range \[1, 256\]"),
    ({"size": 8}, r"size = 8 px is out of the allowed range \[16, 1024\]"),
    ({"supersample": 17}, r"supersample = 17 is out of the allowed range \[1, 16\]"),
    ({"size": 1024, "supersample": 8}, r"size · supersample = 8192 px is out of the allowed range \[16, 4096\]"),
])
def test_bad_arguments_name_the_value_and_the_range(kwargs, match):
    args = {"cls": "strokes", "n": 1, "size": 32, "supersample": 2, **kwargs}
    with pytest.raises(ValueError, match=match):
        render_scenes(**args)


def test_slanted_edge_rejects_a_bad_angle():
    with pytest.raises(ValueError, match=r"angle_deg = 30 is out of the allowed range 1°…20°"):
        render_slanted_edge(64, angle_deg=30.0)


def test_the_background_ramp_is_documented_as_it_is_rendered():
    """The background of strokes/shapes is a ramp of total change b − a from level a at the top-left sample: it can
    leave [min(a, b), max(a, b)] and [0, 1] (render_scenes clamps), as the docstrings now say (they claimed a gradient
    between two levels in [0.15, 0.85]). The ramp itself is kept: the published tables were made with it."""
    import numpy as np

    from camhealth.bench import rendered_scenes as rs

    u = rs._fine_coords(64, 1)
    beyond_levels = beyond_unit = 0
    for i in range(300):
        a, b = np.random.default_rng([0, 0, i]).uniform(0.15, 0.85, 2)
        img = rs._gradient_background(np.random.default_rng([0, 0, i]), u)
        lo, hi = float(img.min()), float(img.max())
        assert img[0, 0] == pytest.approx(a, abs=1e-6)  # level a at the top-left sample
        assert hi - lo == pytest.approx(abs(b - a), abs=1e-5)  # total change |b − a| across the image
        assert a - abs(b - a) - 1e-6 <= lo and hi <= a + abs(b - a) + 1e-6  # the documented bounds
        beyond_levels += lo < min(a, b) - 1e-6 or hi > max(a, b) + 1e-6
        beyond_unit += lo < 0 or hi > 1
    assert beyond_levels > 0 and beyond_unit > 0  # it does leave both, as documented
    doc = " ".join((rs.__doc__ + rs._gradient_background.__doc__ + rs.render_scenes.__doc__).split())
    assert "two levels in [0.15, 0.85] across the image" not in doc
    assert "a − |b − a| … a + |b − a|" in doc and "clamps" in doc and "MTF truth" in doc
    scenes = rs.render_scenes("shapes", 1, 32, seed=0)
    assert 0.0 <= float(scenes.min()) and float(scenes.max()) <= 1.0
