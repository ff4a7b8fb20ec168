"""Patch grids, patch statistics, informative-patch selection, static-region reuse, coarse → refine."""

import math

import pytest
import torch

from camhealth.monitor.tiling import (
    BLACK,
    ESTIMATED,
    FEATURELESS,
    NO_EDGES,
    SATURATED,
    STATUS_NAMES,
    PatchGrid,
    SelectionConfig,
    StaticRegions,
    coarse_lattice,
    grid_statistics,
    lattice_mask,
    lattice_neighbours,
    patch_statistics,
    refine_plan,
    select_patches,
    status_counts,
)
from tests.monitor.conftest import noisy


@pytest.mark.parametrize("h,w,p,rows,cols,y0,x0", [
    (1024, 1280, 128, 8, 10, 0, 0),
    (1024, 1280, 192, 5, 6, 32, 64),
    (576, 768, 128, 4, 6, 32, 0),
    (100, 300, 128, 0, 2, 50, 22),
])
def test_grid_fit(h, w, p, rows, cols, y0, x0):
    g = PatchGrid.fit(h, w, p)
    assert (g.rows, g.cols, g.y0, g.x0) == (rows, cols, y0, x0)
    assert g.n == rows * cols and g.empty == (rows * cols == 0)
    boxes = g.boxes()
    assert boxes.shape == (g.n, 4)
    if g.n:
        assert int(boxes[:, 2].max()) <= w and int(boxes[:, 3].max()) <= h and int(boxes[:, :2].min()) >= 0


def test_grid_extract_is_the_boxes():
    frame = torch.rand(1, 1, 300, 450)
    g = PatchGrid.fit(300, 450, 128)
    patches = g.extract(frame)
    assert patches.shape == (g.n, 1, 128, 128)
    for i, (x0, y0, x1, y1) in enumerate(g.boxes().tolist()):
        assert torch.equal(patches[i, 0], frame[0, 0, y0:y1, x0:x1])
    with pytest.raises(ValueError, match="grid was made for"):
        g.extract(torch.rand(1, 1, 301, 450))


@pytest.mark.parametrize("bad,err", [(0, ValueError), (-5, ValueError), (12.5, TypeError), (True, TypeError)])
def test_grid_fit_rejects_bad_sizes(bad, err):
    with pytest.raises(err, match="patch"):
        PatchGrid.fit(100, 100, bad)


@pytest.mark.parametrize("sigma_dn", [2.0, 8.0])
def test_statistics_of_a_flat_noisy_patch(sigma_dn):
    x = noisy(torch.full((4, 1, 128, 128), 0.5), sigma_dn, seed=1)
    s = patch_statistics(x)
    assert torch.allclose(s.noise_dn, torch.full((4,), sigma_dn), rtol=0.08)
    assert torch.allclose(s.mean_dn, torch.full((4,), 127.5), atol=0.3)
    assert float(s.structure_dn.max()) < 1.0  # noise is removed from the structure contrast
    assert float(s.detail_dn.max()) < 0.25 * sigma_dn
    assert s.blocks_dn.shape == (4, 16, 16)
    assert float(s.clipped_low.max()) == 0 and float(s.clipped_high.max()) == 0


def test_statistics_of_texture_and_clipping():
    g = torch.Generator().manual_seed(2)
    coarse = torch.rand(2, 1, 12, 12, generator=g)
    texture = torch.nn.functional.interpolate(coarse, size=192, mode="bilinear", align_corners=False)
    s = patch_statistics(texture)
    assert float(s.structure_dn.min()) > 10 and float(s.detail_dn.min()) > 0.3
    half = torch.cat([torch.zeros(1, 1, 64, 128), torch.ones(1, 1, 64, 128)], dim=2)
    s = patch_statistics(half)
    assert float(s.clipped_low[0]) == pytest.approx(0.5) and float(s.clipped_high[0]) == pytest.approx(0.5)


@pytest.mark.parametrize("patch", [128, 192])
def test_grid_statistics_equal_patch_statistics(patch):
    frame = noisy(torch.rand(1, 1, 400, 520) * 0.6 + 0.2, 3.0, seed=3)
    frame[..., :130, :200] = 0.0
    g = PatchGrid.fit(400, 520, patch)
    a, b = patch_statistics(g.extract(frame)), grid_statistics(frame, g)
    for f in ("mean_dn", "clipped_low", "clipped_high", "noise_dn", "structure_dn", "detail_dn", "blocks_dn"):
        assert torch.allclose(getattr(a, f), getattr(b, f), atol=1e-3, rtol=1e-4), f


def test_statistics_reject_bad_patches():
    with pytest.raises(ValueError, match="multiple of 8"):
        patch_statistics(torch.rand(2, 1, 100, 100))
    with pytest.raises(TypeError, match="floating"):
        patch_statistics(torch.zeros(2, 1, 128, 128, dtype=torch.uint8))
    assert len(patch_statistics(torch.zeros(0, 1, 128, 128))) == 0


def _stats_for(patches):
    return patch_statistics(patches)


def test_select_reasons():
    g = torch.Generator().manual_seed(4)
    coarse = torch.rand(1, 1, 8, 8, generator=g)
    blocks = torch.nn.functional.interpolate(coarse, size=192, mode="nearest")  # steps between 24-px blocks: edges
    smooth = torch.nn.functional.interpolate(coarse, size=192, mode="bilinear", align_corners=False)  # no edge
    flat_noisy = noisy(torch.full((1, 1, 192, 192), 0.4), 6.0, seed=5)
    black = torch.zeros(1, 1, 192, 192)
    white = torch.ones(1, 1, 192, 192)
    x = torch.cat([blocks * 0.8 + 0.1, flat_noisy, black, white, smooth * 0.8 + 0.1])
    s = patch_statistics(x)
    mask, code = select_patches(s, "mtf")
    assert code.tolist() == [ESTIMATED, FEATURELESS, BLACK, SATURATED, NO_EDGES]
    assert mask.tolist() == [True, False, False, False, False]
    mask, code = select_patches(s, "noise")  # noise is still measurable on a flat patch
    assert code.tolist() == [ESTIMATED, ESTIMATED, BLACK, SATURATED, ESTIMATED]
    mask, code = select_patches(s, "mtf", SelectionConfig(min_structure_dn=0.0, max_clipped_fraction=1.0, min_edge_kurtosis=-3.0))
    assert mask.all()
    with pytest.raises(ValueError, match="task"):
        select_patches(s, "blur")


@pytest.mark.parametrize("kwargs,match", [
    ({"max_clipped_fraction": 1.5}, "max_clipped_fraction"),
    ({"min_structure_dn": -1.0}, "min_structure_dn"),
    ({"max_age": 0}, "max_age"),
    ({"noise_tol": (0.1,)}, "noise_tol"),
    ({"block_sigmas": float("nan")}, "block_sigmas"),
    ({"min_edge_kurtosis": -5.0}, "min_edge_kurtosis"),
    ({"min_edge_kurtosis": float("nan")}, "min_edge_kurtosis"),
])
def test_selection_config_validates(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SelectionConfig(**kwargs)


def test_static_regions_detect_motion_not_noise():
    base = torch.rand(1, 1, 8, 8, generator=torch.Generator().manual_seed(6))
    scene = torch.nn.functional.interpolate(base, size=(256, 384), mode="bilinear", align_corners=False) * 0.6 + 0.2
    grid = PatchGrid.fit(256, 384, 128)
    st = StaticRegions(grid.n, SelectionConfig(max_age=1000))
    s0 = grid_statistics(noisy(scene, 4.0, seed=7), grid)
    assert st.changed(s0).all()  # no reference yet
    st.update(torch.arange(grid.n), s0, frame=0)
    s1 = grid_statistics(noisy(scene, 4.0, seed=8), grid)  # same scene, new noise
    assert not st.changed(s1).any()
    moved = scene.clone()
    moved[..., 10:60, 20:70] = 0.95  # an object enters patch (0, 0)
    s2 = grid_statistics(noisy(moved, 4.0, seed=9), grid)
    assert st.changed(s2).tolist() == [True] + [False] * (grid.n - 1)
    s3 = grid_statistics(noisy(scene, 9.0, seed=10), grid)  # noise level changed (gain / temperature)
    assert st.changed(s3).all()
    st.reset()
    assert st.changed(s1).all()


@pytest.mark.parametrize("max_age", [1, 3, 8])
def test_refresh_is_staggered(max_age):
    stats = patch_statistics(torch.rand(24, 1, 16, 16))
    st = StaticRegions(24, SelectionConfig(max_age=max_age))
    st.update(torch.arange(24), stats, frame=0)  # everything estimated at once (a cold frame)
    counts = []
    for f in range(1, 3 * max_age + 1):  # a static scene: only the due patches are re-estimated
        due = st.due(f)
        counts.append(int(due.sum()))
        st.update(due.nonzero()[:, 0], stats, frame=f)
        assert int((f - st.last_frame).max()) < max_age  # no estimate older than max_age frames
    assert max(counts) - min(counts) <= 1  # the refresh work is spread evenly over the frames
    assert sum(counts[:max_age]) == 24  # each patch once per max_age frames


def test_lattice_and_coarse_pass():
    g = PatchGrid.fit(5 * 128, 6 * 128, 128)  # 5 × 6
    lat = lattice_mask(g).reshape(5, 6)
    assert lat[0::2, 0::2].all() and not lat[1::2].any() and not lat[:, 1::2].any()
    everything = torch.ones(g.n, dtype=torch.bool)
    first = coarse_lattice(g, everything, everything).reshape(5, 6)
    # off-lattice patches of the last column (col 5) have < 2 lattice neighbours only in corner cases:
    assert first[0::2, 0::2].all()
    assert not first[1, 1] and not first[0, 1]
    # a patch whose lattice neighbours are not informative must be estimated directly
    informative = everything.clone()
    informative[0] = informative[2] = False  # lattice (0, 0) and (0, 2)
    first = coarse_lattice(g, everything, informative)
    assert bool(first[1])  # (0, 1): its two lattice neighbours are uninformative


def test_lattice_neighbours_values():
    g = PatchGrid.fit(3 * 128, 3 * 128, 128)
    values = torch.arange(9, dtype=torch.float32)[:, None]
    nb = lattice_neighbours(g, values, torch.ones(9, dtype=torch.bool))
    got = sorted(v for v in nb[4, :, 0].tolist() if not math.isnan(v))  # centre: 4 diagonal lattice patches
    assert got == [0.0, 2.0, 6.0, 8.0]
    got = sorted(v for v in nb[1, :, 0].tolist() if not math.isnan(v))  # (0, 1): left and right
    assert got == [0.0, 2.0]


def test_refine_plan_interpolates_only_where_nothing_changes():
    g = PatchGrid.fit(3 * 128, 5 * 128, 128)  # 3 × 5
    n = g.n
    values = torch.full((n, 2), float("nan"))
    lat = lattice_mask(g)
    values[lat] = torch.tensor([2.0, 5.0])
    remaining = ~lat
    cue = torch.zeros(n)
    ok, out = refine_plan(g, remaining, values, lat, 0.1, [(cue, 0.5, 0.0)])
    assert ok.equal(remaining)
    assert torch.allclose(out[ok], torch.tensor([2.0, 5.0]).expand(int(ok.sum()), 2))
    # one lattice patch disagrees → its off-lattice neighbours are refined
    values2 = values.clone()
    values2[0] = torch.tensor([3.0, 5.0])  # patch (0, 0)
    ok2, _ = refine_plan(g, remaining, values2, lat, 0.1, [(cue, 0.5, 0.0)])
    assert not ok2[1] and not ok2[5] and not ok2[6] and bool(ok2[3])
    # a patch that does not look like its neighbours (cue) is refined
    cue2 = cue.clone()
    cue2[7] = 10.0
    ok3, _ = refine_plan(g, remaining, values, lat, 0.1, [(cue2, 0.5, 0.0)])
    assert not ok3[7] and bool(ok3[1])
    # components that are NaN everywhere (no per-source σ) are ignored
    values3 = values.clone()
    values3[:, 0] = float("nan")
    ok4, out4 = refine_plan(g, remaining, values3, lat, 0.1, [])
    assert ok4.equal(remaining) and torch.isnan(out4[ok4, 0]).all()


def test_status_counts():
    code = torch.tensor([0, 0, 2, 3, 6], dtype=torch.int8)
    c = status_counts(code)
    assert list(c) == list(STATUS_NAMES) and c["estimated"] == 2 and c["reused"] == 1 and c["black"] == 1
    assert c["not_assessable"] == 1 and sum(c.values()) == 5


def test_edge_kurtosis_matches_the_estimator_rule():
    """The monitor's frame-wide edge kurtosis is the estimator's (camhealth._inputs.edge_kurtosis) on the same
    patches with the same noise level, so a skipped "no_edges" patch is one the estimator calls not assessable."""
    from camhealth._inputs import edge_kurtosis

    g = torch.Generator().manual_seed(9)
    blocks = torch.nn.functional.interpolate(0.2 + 0.6 * torch.rand(3, 1, 12, 12, generator=g), size=192, mode="nearest")
    smooth = torch.nn.functional.interpolate(0.2 + 0.6 * torch.rand(3, 1, 12, 12, generator=g), size=192, mode="bilinear",
                                             align_corners=False)
    x = noisy(torch.cat([blocks, smooth]), 4.0, seed=10)
    s = patch_statistics(x)
    gamma, se = edge_kurtosis(x, s.noise_dn)
    assert torch.allclose(s.edge_kurtosis, gamma, rtol=1e-3, atol=1e-3) and torch.allclose(s.edge_kurtosis_se, se, rtol=1e-3)
    assert select_patches(s, "mtf")[1].tolist() == [ESTIMATED] * 3 + [NO_EDGES] * 3


@pytest.mark.parametrize("clipped_patches", [1, 3, 12])
def test_clipped_fractions_counted_on_the_patches_that_reach_the_bounds_equal_a_full_count(clipped_patches):
    """The clipped pixels are counted only on the patches whose extreme reaches 0 or 255 DN (all of them where more
    than half do): the same fractions as a count over every pixel, in the grid's row-major order."""
    g = torch.Generator().manual_seed(4)
    frame = torch.rand(1, 1, 512, 512, generator=g) * 0.6 + 0.2
    grid = PatchGrid.fit(512, 512, 128)
    boxes = grid.boxes()
    for k in range(clipped_patches):
        x0, y0 = int(boxes[k * 5 % 16, 0]), int(boxes[k * 5 % 16, 1])
        frame[..., y0:y0 + 40 + k, x0:x0 + 50] = 1.0
        frame[..., y0 + 60:y0 + 70, x0:x0 + 30 + k] = 0.0
    s = grid_statistics(frame, grid)
    patches = grid.extract(frame)
    tol = 0.5 / 255.0
    assert torch.equal(s.clipped_high, (patches >= 1 - tol).flatten(1).float().mean(1))
    assert torch.equal(s.clipped_low, (patches <= tol).flatten(1).float().mean(1))
    assert int((s.clipped_high > 0).sum()) == len(set(k * 5 % 16 for k in range(clipped_patches)))


@pytest.mark.parametrize("h,w,split", [
    (400, 2400, (1, 6)),   # a 2×12 MTF grid: six sectors of 2×2 patches, not 2×3 of 1×4
    (384, 3840, (1, 6)),   # 2×20: 1×6 (|2 − 20/6| = 1.33) beats 2×3 (|1 − 20/3| = 5.67)
    (1024, 1280, (2, 3)),  # 5×6: the documented 2×3 sectors
    (576, 768, (2, 3)),    # 3×4
])
def test_sector_split_is_the_one_closest_to_the_grids_aspect(h, w, split):
    """The MTF samples' sectors (:func:`_sector_ids`): the rows × cols split with rows·cols ≥ k whose sectors come
    closest to square; the 1 × k split is a candidate like any other and is kept where it fits best."""
    from camhealth.monitor.tiling import _sector_ids

    grid = PatchGrid.fit(h, w, 192)
    ids = _sector_ids(grid, 6).reshape(grid.rows, grid.cols)
    rows, cols = len(set(ids[:, 0].tolist())), len(set(ids[0].tolist()))
    assert (rows, cols) == split, ids.tolist()
    assert sorted(set(ids.reshape(-1).tolist())) == list(range(6))  # every sector has patches
