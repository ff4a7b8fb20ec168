"""Procedural dead-leaves images."""

from __future__ import annotations

import math


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


# ---- shading and elliptical leaves ---------------------------------------------------------------------------------


def test_defaults_are_bit_identical_to_the_disk_renderer():
    import hashlib

    def sha(x):
        return hashlib.sha256(x.numpy().tobytes()).hexdigest()

    # checksums of the renderer before shading and thin leaves existed (numpy's PCG64; same numpy → same bytes)
    a = dead_leaves((48, 64), r_min=1.5, contrast=0.8, seed=11, supersample=2)
    assert sha(a) == "473f1eae946385d5a9f14bd14f5a29425b5db6bcf58ea8e7945d003bd36d96d5"
    src = DeadLeavesSource(3, size=40, seed=5, r_min=[1, 10], contrast=[0.15, 1], supersample=4)
    assert sha(src[2][0]) == "3ba0667cb5341a01b5affb072723dc255612aaef9f277b2f3fb05e79e41da1d5"
    # the options at their neutral values change nothing
    assert torch.equal(
        a, dead_leaves((48, 64), r_min=1.5, contrast=0.8, seed=11, supersample=2, shading=0.0, thin=0.0)
    )
    neutral = DeadLeavesSource(
        3, size=40, seed=5, r_min=[1, 10], contrast=[0.15, 1], supersample=4, shading=[0, 0], thin=[0, 0]
    )
    assert torch.equal(src[2][0], neutral[2][0])
    # the scenes the shipped MTF schedule trains on (configs/mtf_full.yaml's dead-leaves arguments) stay what they were
    trained = DeadLeavesSource(3, size=48, seed=0, r_min=[1, 10], contrast=[0.15, 1], supersample=4, shading=[0, 0.6], thin=[0, 0.6])
    assert sha(trained[2][0]) == "28f4a2aa7505b1d1705f6e92aaaf630cd5e166fbd2d51e9cdbce255e3ce39081"
    # a shading / thin range draws after r_min and contrast: their per-image values are unchanged
    ranged = DeadLeavesSource(3, size=40, seed=5, r_min=[1, 10], contrast=[0.15, 1], shading=[0, 1], thin=[0, 1])
    for i in range(3):
        assert ranged.scene_params(i)[:2] == src.image_params(i) == ranged.image_params(i)


def _plane_fit(img):
    """Least-squares plane v = v0 + gx·x + gy·y over all pixels: ((gx, gy), max |residual|)."""
    h, w = img.shape
    yy, xx = np.mgrid[0:h, 0:w]
    a = np.stack([np.ones(h * w), xx.ravel(), yy.ravel()], axis=1)
    coef, *_ = np.linalg.lstsq(a, img.ravel().astype(np.float64), rcond=None)
    return coef[1:], float(np.abs(a @ coef - img.ravel()).max())


def test_shading_is_a_linear_ramp_with_bounded_random_slope():
    r, shading, contrast = 2000.0, 0.8, 0.5
    bound = shading * contrast / r  # gray level per output px
    for s in (1, 2):  # the slope per output pixel does not depend on supersample
        slopes = []
        for seed in range(12):
            img = dead_leaves(48, r_min=r, r_max=r + 1, contrast=contrast, seed=seed, supersample=s, shading=shading)[0].numpy()
            g, resid = _plane_fit(img)
            if resid > 1e-6:  # the frame is not one leaf (a second leaf shows at a border): rare with r = 2000
                continue
            slopes.append(g)
        slopes = np.array(slopes)
        assert len(slopes) >= 8
        mag = np.hypot(slopes[:, 0], slopes[:, 1])
        assert mag.max() <= bound * (1 + 1e-3)
        assert mag.max() > 0.3 * bound  # a real ramp, not flat leaves
        ang = np.arctan2(slopes[:, 1], slopes[:, 0])
        assert np.ptp(np.cos(ang)) > 1.0 and np.ptp(np.sin(ang)) > 1.0  # directions spread over the circle
        # flat without shading
        g, resid = _plane_fit(dead_leaves(48, r_min=r, r_max=r + 1, contrast=contrast, seed=0, supersample=s)[0].numpy())
        assert resid < 1e-6 and np.hypot(*g) < 1e-9


def test_thin_and_shading_keep_the_frame_covered_and_in_range():
    for kw in (dict(thin=1.0), dict(thin=0.5, supersample=2), dict(shading=1.0, thin=0.8, supersample=2)):
        x = dead_leaves((80, 96), r_min=1.0, contrast=0.5, seed=4, **kw)
        assert torch.isfinite(x).all() and 0.0 <= float(x.min()) and float(x.max()) <= 1.0
        if "shading" not in kw:  # an uncovered pixel would stay 0
            assert float(x.min()) >= 0.25 and float(x.max()) <= 0.75
        assert len(torch.unique(x)) > 50


def _naive_shaped(h, w, r, cx, cy, val, ell, grad):
    img = np.zeros(h * w, np.float32)
    unc = np.ones(h * w, bool)
    yy, xx = np.mgrid[0:h, 0:w]
    c, s, a2, b2 = ell
    for k in range(len(r)):
        dx, dy = (xx - cx[k]).ravel(), (yy - cy[k]).ravel()
        u, v = dx * c[k] + dy * s[k], dy * c[k] - dx * s[k]
        hit = (u * u * b2[k] + v * v * a2[k] <= a2[k] * b2[k]) & unc
        img[hit] = val[k] + grad[0][k] * dx[hit] + grad[1][k] * dy[hit]
        unc[hit] = False
    return img, unc


def test_vectorised_painting_of_shaded_ellipses_matches_naive_reference():
    h, w = 27, 33
    rng = np.random.default_rng(5)
    r, cx, cy, val = _sample_leaves(rng, 300, h, w, 0.8, 10.0, 0.0, 1.0, math.sqrt(5.0))
    k = 5.0 ** rng.random(300)
    th = math.pi * rng.random(300)
    c, s = np.cos(th), np.sin(th)
    ell = (c, s, r * r * k, r * r / k)
    g, phi = 0.5 * rng.random(300) / r, 2 * math.pi * rng.random(300)
    grad = (g * np.cos(phi), g * np.sin(phi))
    ref, ref_unc = _naive_shaped(h, w, r, cx, cy, val, ell, grad)
    assert ref_unc.sum() < h * w  # something painted

    ex = np.sqrt(ell[2] * c * c + ell[3] * s * s) + 1e-9
    ey = np.sqrt(ell[2] * s * s + ell[3] * c * c) + 1e-9
    x0 = np.maximum(np.ceil(cx - ex), 0).astype(np.int64)
    x1 = np.minimum(np.floor(cx + ex), w - 1).astype(np.int64)
    y0 = np.maximum(np.ceil(cy - ey), 0).astype(np.int64)
    y1 = np.minimum(np.floor(cy + ey), h - 1).astype(np.int64)
    bw, bh = np.maximum(x1 - x0 + 1, 0), np.maximum(y1 - y0 + 1, 0)
    img, unc = np.zeros(h * w, np.float32), np.ones(h * w, bool)
    _paint_by_boxes(img, unc, w, r, cx, cy, val, x0, y0, bw, bh, ell, grad)
    assert np.array_equal(unc, ref_unc) and np.array_equal(img, ref)

    img2, unc2 = np.zeros(h * w, np.float32), np.ones(h * w, bool)
    _paint_direct(img2, unc2, w, r, cx, cy, val, ell, grad)
    assert np.array_equal(unc2, ref_unc) and np.array_equal(img2, ref)


def test_dilated_sampling_for_ellipses_keeps_the_radius_law():
    rng = np.random.default_rng(1)
    h = w = 64
    m = math.sqrt(8.0)
    r, cx, cy, _ = _sample_leaves(rng, 400_000, h, w, 1.0, 64.0, 0.0, 1.0, m)
    inside = (cx >= 0) & (cx <= w - 1) & (cy >= 0) & (cy <= h - 1)
    edges = np.geomspace(1.0, 16.0, 9)
    density = np.histogram(r[inside], bins=edges)[0] / np.diff(edges)
    slope = np.polyfit(np.log(np.sqrt(edges[:-1] * edges[1:])), np.log(density), 1)[0]
    assert slope == pytest.approx(-3.0, abs=0.1)
    assert (np.abs(cx - (w - 1) / 2) <= (w - 1) / 2 + m * r + 1e-9).all()  # centres within the frame dilated by m·r
    assert (cx < -r).any()  # and beyond the disk dilation


def test_shaded_elliptical_leaves_are_seeded_and_deterministic():
    kw = dict(size=(40, 56), r_min=1.5, shading=0.6, thin=0.4, supersample=2)
    a, b, c = dead_leaves(seed=3, **kw), dead_leaves(seed=3, **kw), dead_leaves(seed=4, **kw)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert not torch.equal(a, dead_leaves(seed=3, **{**kw, "shading": 0.0}))
    src = DeadLeavesSource(4, size=32, seed=2, shading=[0.2, 0.9], thin=[0.1, 0.6], supersample=2)
    again = DeadLeavesSource(4, size=32, seed=2, shading=[0.2, 0.9], thin=[0.1, 0.6], supersample=2)
    assert all(torch.equal(src[i][0], again[i][0]) for i in (3, 0, 2))
    assert not torch.equal(src[0][0], src[1][0])
    params = [src.scene_params(i) for i in range(4)]
    assert len(set(params)) == 4 and all(0.2 <= s <= 0.9 and 0.1 <= t <= 0.6 and c == 1.0 for _, _, s, t, c in params)
    assert "shading=[0.2, 0.9], thin=[0.1, 0.6], coverage=1)" in repr(src)
    fixed = DeadLeavesSource(2, size=32, seed=2, shading=0.5, thin=0.25)
    assert fixed.scene_params(1) == (2.0, 1.0, 0.5, 0.25, 1.0) and "shading=0.5, thin=0.25," in repr(fixed)


def test_default_source_forwards_shading():
    from camhealth.data.sources import DefaultSource

    src = DefaultSource(deadleaves=2, deadleaves_size=32, include_skimage=False, include_street=False, shading=0.4)
    (dl,) = src.sources
    assert isinstance(dl, DeadLeavesSource) and dl.scene_params(0)[2:] == (0.4, 0.0, 1.0)
    assert torch.equal(src[1][0], DeadLeavesSource(2, size=32, shading=0.4)[1][0])


@pytest.mark.parametrize(
    "kw, msg",
    [
        (dict(shading=-0.1), r"shading = -0.1 must be in \[0, 1\]"),
        (dict(shading=1.5), r"shading = 1.5 must be in \[0, 1\]"),
        (dict(shading=float("nan")), r"shading = nan must be in \[0, 1\]"),
        (dict(thin=-0.1), r"thin = -0.1 must be in \[0, 1\]"),
        (dict(thin=1.5), r"thin = 1.5 must be in \[0, 1\]"),
        (dict(thin=float("nan")), r"thin = nan must be in \[0, 1\]"),
        (dict(thin="a lot"), r"thin.*'a lot'"),
    ],
)
def test_bad_shading_and_thin_are_rejected(kw, msg):
    with pytest.raises(ValueError, match=msg):
        dead_leaves(16, **kw)
    with pytest.raises(ValueError, match=msg):
        DeadLeavesSource(2, size=16, **kw)


def test_bad_shading_and_thin_ranges_are_rejected():
    with pytest.raises(ValueError, match=r"thin = 1.5 must be in \[0, 1\]"):
        DeadLeavesSource(2, thin=[0.2, 1.5])
    with pytest.raises(ValueError, match=r"shading = \[0.8, 0.2\]"):
        DeadLeavesSource(2, shading=[0.8, 0.2])
    with pytest.raises(ValueError, match=r"thin = \[nan, 0.2\] must be finite"):
        DeadLeavesSource(2, thin=[float("nan"), 0.2])


def _regions_by_level(img):
    """Pixel coordinates of each gray level (a leaf's visible pieces: levels are continuous, one per leaf)."""
    vals, inv = np.unique(img.ravel(), return_inverse=True)
    yy, xx = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    order = np.argsort(inv, kind="stable")
    bounds = np.searchsorted(inv[order], np.arange(len(vals) + 1))
    for k in range(len(vals)):
        idx = order[bounds[k] : bounds[k + 1]]
        yield xx.ravel()[idx].astype(np.float64), yy.ravel()[idx].astype(np.float64)


def test_thin_leaves_are_narrow_and_long():
    from camhealth.data.dead_leaves import THIN_LENGTH, THIN_WIDTH_PX

    r = 8.0
    kw = dict(size=160, r_min=r, r_max=r + 0.01, contrast=1.0, supersample=1)
    # every pixel of a thin leaf lies within b ≤ THIN_WIDTH_PX[1]/2 of its major axis, so any set of its pixels has
    # variance ≤ b² across its least-spread direction; a disk of radius 8 has 4² along every direction
    minor, major = [], []
    for seed in range(3):
        for xx, yy in _regions_by_level(dead_leaves(seed=seed, thin=1.0, **kw)[0].numpy()):
            if xx.size >= 30:
                ev = np.linalg.eigvalsh(np.cov(np.stack([xx, yy])))
                minor.append(math.sqrt(max(ev[0], 0.0)))
                major.append(math.sqrt(ev[1]))
    assert len(minor) > 20
    assert max(minor) <= THIN_WIDTH_PX[1] / 2 + 1e-6
    assert max(major) > THIN_LENGTH * r / 4  # long: a whole leaf has std a/2 = THIN_LENGTH·r/2 along its axis
    disks = [
        math.sqrt(np.linalg.eigvalsh(np.cov(np.stack([xx, yy])))[0])
        for xx, yy in _regions_by_level(dead_leaves(seed=0, **kw)[0].numpy())
        if xx.size >= 30
    ]
    assert np.median(disks) > 2.0 * np.median(minor)


def test_thin_share_sets_the_edge_density_and_keeps_the_frame_covered():
    def edge_density(x):
        x = x[0]
        return float(((x[:, 1:] != x[:, :-1]).float().mean() + (x[1:] != x[:-1]).float().mean()) / 2)

    kw = dict(size=(96, 112), r_min=3.0, contrast=0.5, seed=2)
    dens = []
    for thin in (0.0, 0.3, 1.0):
        x = dead_leaves(thin=thin, **kw)
        assert torch.isfinite(x).all() and float(x.min()) >= 0.25 and float(x.max()) <= 0.75  # covered, in range
        dens.append(edge_density(x))
    assert dens[0] < dens[1] < dens[2] and dens[2] > 1.5 * dens[0]
    sup = dead_leaves(thin=0.5, supersample=2, shading=0.5, **kw)
    assert torch.isfinite(sup).all() and 0.0 <= float(sup.min()) and float(sup.max()) <= 1.0
    assert torch.equal(sup, dead_leaves(thin=0.5, supersample=2, shading=0.5, **kw))  # seeded


def test_default_source_forwards_thin():
    from camhealth.data.sources import DefaultSource

    src = DefaultSource(deadleaves=2, deadleaves_size=32, include_skimage=False, include_street=False, thin=[0.1, 0.6])
    (dl,) = src.sources
    assert isinstance(dl, DeadLeavesSource) and 0.1 <= dl.scene_params(1)[3] <= 0.6
    assert torch.equal(src[1][0], DeadLeavesSource(2, size=32, thin=[0.1, 0.6])[1][0])


@pytest.mark.parametrize("coverage", [0.05, 0.2, 0.5, 0.9])
def test_coverage_leaves_that_share_of_the_frame_to_a_ramp_background(coverage):
    """``coverage`` < 1: the leaves cover at least that share of the pixels (the whole batch of leaves that reaches it
    is painted, so the share overshoots: by how much depends on the leaf sizes and the frame, see ``_render``), the
    rest is the linear-ramp background drawn from the seed sequence (seed, 3)."""
    from camhealth.data.dead_leaves import _gradient_background, _render

    rng, rng2 = np.random.default_rng(5), np.random.default_rng(6)
    img, uncovered = _render(rng, 200, 240, 2.0, 100.0, 0.0, 1.0, 0.0, rng2, 0.0, (1.0, 1.0), coverage)
    share = 1.0 - uncovered.mean()
    assert coverage <= share < 1.0
    kw = dict(size=(200, 240), r_min=2.0, supersample=1, contrast=0.8)
    out = dead_leaves(seed=9, coverage=coverage, **kw)[0].numpy()
    bg = _gradient_background(np.random.Generator(np.random.PCG64(np.random.SeedSequence([9, 3]))), 200, 240, 0.1, 0.9)
    on_bg = np.isclose(out, bg, atol=1e-6)
    assert coverage - 0.05 <= 1.0 - on_bg.mean() < 1.0  # (a leaf may match the ramp at a few pixels)
    # the background is a plane: second differences vanish where three pixels in a row lie on it
    d2 = bg[:, 2:] - 2 * bg[:, 1:-1] + bg[:, :-2]
    assert np.abs(d2).max() < 1e-5 and 0.1 - 1e-6 <= bg.min() and bg.max() <= 0.9 + 1e-6
    assert torch.equal(dead_leaves(seed=9, coverage=1.0, **kw), dead_leaves(seed=9, **kw))  # 1: the full model


def test_coverage_range_is_drawn_per_image_and_leaves_fixed_images_unchanged():
    src = DeadLeavesSource(6, size=48, seed=4, coverage=[0.3, 1.0], supersample=2)
    cov = [src.scene_params(i)[4] for i in range(6)]
    assert len(set(cov)) == 6 and all(0.3 <= c <= 1.0 for c in cov)
    assert all(torch.equal(src[i][0], DeadLeavesSource(6, size=48, seed=4, coverage=[0.3, 1.0], supersample=2)[i][0]) for i in (5, 0))
    plain, full = DeadLeavesSource(3, size=48, seed=4, thin=[0.1, 0.5]), DeadLeavesSource(3, size=48, seed=4, thin=[0.1, 0.5], coverage=1.0)
    assert all(torch.equal(plain[i][0], full[i][0]) for i in range(3))
    # r_min, contrast, shading and thin draws do not depend on the coverage range
    both = DeadLeavesSource(3, size=48, seed=4, thin=[0.1, 0.5], coverage=[0.2, 0.9])
    assert [both.scene_params(i)[:4] for i in range(3)] == [plain.scene_params(i)[:4] for i in range(3)]


@pytest.mark.parametrize(
    "kw, msg",
    [
        (dict(coverage=0.0), r"coverage = 0 must be in \(0, 1\]"),
        (dict(coverage=1.5), r"coverage = 1.5 must be in \(0, 1\]"),
        (dict(coverage=float("nan")), r"coverage = nan must be in \(0, 1\]"),
        (dict(coverage="most"), r"coverage.*'most'"),
    ],
)
def test_bad_coverage_is_rejected(kw, msg):
    with pytest.raises(ValueError, match=msg):
        dead_leaves(16, **kw)
    with pytest.raises(ValueError, match=msg):
        DeadLeavesSource(2, size=16, **kw)
