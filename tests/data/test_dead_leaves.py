"""Procedural dead-leaves images."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from camhealth.data import DeadLeavesSource, dead_leaves, dead_leaves_radius_pdf
from camhealth.data.dead_leaves import _paint_by_boxes, _paint_direct, _sample_leaves


def test_same_seed_identical_different_seed_different():
    a = dead_leaves((64, 80), seed=7)
    b = dead_leaves((64, 80), seed=7)
    c = dead_leaves((64, 80), seed=8)
    assert a.shape == (1, 64, 80) and a.dtype == torch.float32
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


def test_values_in_range_and_frame_fully_covered():
    x = dead_leaves((96, 96), r_min=1.0, contrast=1.0, seed=1)
    assert 0.0 <= x.min().item() and x.max().item() <= 1.0
    # with contrast 0.5 every leaf is in [0.25, 0.75]; an uncovered pixel would stay 0
    y = dead_leaves((96, 96), r_min=1.0, contrast=0.5, seed=1)
    assert y.min().item() >= 0.25 and y.max().item() <= 0.75
    assert len(torch.unique(x)) > 50  # many leaves visible
    z = dead_leaves((32, 32), contrast=0.0, seed=0, supersample=2)
    assert torch.all(z == 0.5)


def test_edge_density_grows_as_r_min_shrinks():
    def edges(img):
        return (img[:, 1:, :] != img[:, :-1, :]).float().mean().item()

    fine = np.mean([edges(dead_leaves((128, 128), r_min=1.0, seed=s)) for s in range(3)])
    coarse = np.mean([edges(dead_leaves((128, 128), r_min=8.0, seed=s)) for s in range(3)])
    assert fine > 2 * coarse


def test_radius_distribution_is_power_law_minus_3():
    rng = np.random.default_rng(0)
    h = w = 64
    r, cx, cy, _ = _sample_leaves(rng, 400_000, h, w, 1.0, 64.0, 0.0, 1.0)
    # leaves centred inside the frame are an unbiased sample of p(r) ∝ r^-3
    inside = (cx >= 0) & (cx <= w - 1) & (cy >= 0) & (cy <= h - 1)
    r_in = r[inside]
    edges = np.geomspace(1.0, 16.0, 9)
    counts, _ = np.histogram(r_in, bins=edges)
    density = counts / np.diff(edges)
    centres = np.sqrt(edges[:-1] * edges[1:])
    slope = np.polyfit(np.log(centres), np.log(density), 1)[0]
    assert slope == pytest.approx(-3.0, abs=0.1)
    # and the radii of all leaves touching the frame stay within [r_min, r_max]
    assert r.min() >= 1.0 and r.max() <= 64.0
    grid = np.linspace(1, 64, 20001)
    pdf = dead_leaves_radius_pdf(grid, 1.0, 64.0)
    assert float(np.sum((pdf[1:] + pdf[:-1]) / 2 * np.diff(grid))) == pytest.approx(1.0, abs=1e-3)


def _naive_front_to_back(h, w, r, cx, cy, val):
    img = np.zeros(h * w, np.float32)
    unc = np.ones(h * w, bool)
    yy, xx = np.mgrid[0:h, 0:w]
    for k in range(len(r)):
        hit = (((xx - cx[k]) ** 2 + (yy - cy[k]) ** 2) <= r[k] ** 2).ravel() & unc
        img[hit] = val[k]
        unc[hit] = False
    return img, unc


def test_vectorised_painting_matches_naive_reference():
    h, w = 23, 31
    rng = np.random.default_rng(3)
    r, cx, cy, val = _sample_leaves(rng, 300, h, w, 0.8, 12.0, 0.0, 1.0)
    ref, ref_unc = _naive_front_to_back(h, w, r, cx, cy, val)

    x0 = np.maximum(np.ceil(cx - r), 0).astype(np.int64)
    x1 = np.minimum(np.floor(cx + r), w - 1).astype(np.int64)
    y0 = np.maximum(np.ceil(cy - r), 0).astype(np.int64)
    y1 = np.minimum(np.floor(cy + r), h - 1).astype(np.int64)
    bw, bh = np.maximum(x1 - x0 + 1, 0), np.maximum(y1 - y0 + 1, 0)
    img, unc = np.zeros(h * w, np.float32), np.ones(h * w, bool)
    _paint_by_boxes(img, unc, w, r, cx, cy, val, x0, y0, bw, bh)
    assert np.array_equal(unc, ref_unc) and np.array_equal(img, ref)

    img2, unc2 = np.zeros(h * w, np.float32), np.ones(h * w, bool)
    _paint_direct(img2, unc2, w, r, cx, cy, val)
    assert np.array_equal(unc2, ref_unc) and np.array_equal(img2, ref)


def test_source_ranges_draw_each_images_edge_density_and_contrast_reproducibly():
    from camhealth.data.dead_leaves import DeadLeavesSource

    fixed, ranged = DeadLeavesSource(4, size=64), DeadLeavesSource(4, size=64, r_min=[1.0, 6.0], contrast=[0.3, 1.0])
    assert torch.equal(DeadLeavesSource(4, size=64, r_min=[2.0, 2.0])[2][0], fixed[2][0])  # a degenerate range = the value
    params = [ranged.image_params(i) for i in range(4)]
    assert params == [DeadLeavesSource(4, size=64, r_min=[1.0, 6.0], contrast=[0.3, 1.0]).image_params(i) for i in range(4)]
    assert len(set(params)) == 4 and all(1.0 <= r <= 6.0 and 0.3 <= c <= 1.0 for r, c in params)
    for i, (_, c) in enumerate(params):
        img = ranged[i][0]
        assert float(img.min()) >= 0.5 - c / 2 - 1e-6 and float(img.max()) <= 0.5 + c / 2 + 1e-6
    with pytest.raises(ValueError, match=r"r_min = \[6, 1\]"):
        DeadLeavesSource(2, r_min=[6.0, 1.0])
    with pytest.raises(ValueError, match=r"r_min = 0.2 px must be >= 0.5"):
        DeadLeavesSource(2, r_min=[0.2, 1.0])
    with pytest.raises(ValueError, match=r"contrast = 1.5 must be in \[0, 1\]"):
        DeadLeavesSource(2, contrast=[0.5, 1.5])
    with pytest.raises(ValueError, match="r_min must be a number or a \\[low, high\\] pair"):
        DeadLeavesSource(2, r_min="big")
