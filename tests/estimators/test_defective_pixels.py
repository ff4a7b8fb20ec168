"""Defective pixels: a pixel that stands above or below all its neighbours by far more than the local noise."""

import math

import pytest
import torch
import torch.nn.functional as F

from camhealth.bench.sensor_variants import simulate_variant
from camhealth.estimators.defective_pixels import DEFECT_SIGMAS, MIN_DEFECT_DN, defective_pixels, repair_defective_pixels
from camhealth.physics import CameraMetadata


def _white(b: int, sigma: float, level: float = 128.0, seed: int = 0, size: int = 128) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return ((level + sigma * torch.randn(b, 1, size, size, generator=g)).round().clamp(0, 255)) / 255.0


def _camera_ramp(b: int = 8, seed: int = 1) -> torch.Tensor:
    """A ramp 60–200 DN with an ICX285's shot, dark-current and readout noise, rounded to 8 bit."""
    meta = CameraMetadata.preset("ICX285")
    ramp = torch.linspace(60.0, 200.0, 128).view(1, 1, 1, 128).expand(b, 1, 128, 128) / 255.0
    noisy, _ = simulate_variant(ramp.contiguous(), meta, ("round8",), torch.Generator().manual_seed(seed))
    return noisy


def _inject(x: torch.Tensor, n: int, amp: tuple[float, float], seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` isolated defects per patch (at least 3 px apart and from the border), half bright, half dark."""
    g = torch.Generator().manual_seed(seed)
    b, _, h, w = x.shape
    truth = torch.zeros(b, 1, h, w, dtype=torch.int8)
    grid = torch.stack(torch.meshgrid(torch.arange(4, h - 4, 4), torch.arange(4, w - 4, 4), indexing="ij"), -1).reshape(-1, 2)
    out = x.clone() * 255.0
    for i in range(b):
        pick = grid[torch.randperm(grid.shape[0], generator=g)[:n]]
        sign = torch.where(torch.arange(n) % 2 == 0, 1, -1)
        a = amp[0] + (amp[1] - amp[0]) * torch.rand(n, generator=g)
        out[i, 0, pick[:, 0], pick[:, 1]] += sign * a
        truth[i, 0, pick[:, 0], pick[:, 1]] = sign.to(torch.int8)
    return out.clamp(0, 255).round() / 255.0, truth


@pytest.mark.parametrize("sigma", [0.5, 1.0, 5.0, 30.0])
def test_white_noise_is_never_a_defect(sigma):
    """For Gaussian noise the chance that a pixel exceeds the largest of 8 neighbours by 6 σ is 2.5·10⁻¹¹: no pixel of
    256 patches (4.1 M pixels) is flagged, 8-bit rounded, at any level."""
    d = defective_pixels(_white(256, sigma))
    assert int(d.hot.sum() + d.dark.sum()) == 0
    assert d.checked.tolist() == [126 * 126] * 256 and d.mask.shape == (256, 1, 128, 128)


def test_null_chance_of_a_6_sigma_step_is_tiny():
    """P(Z₀ − max(Z₁…Z₈) > k) = ∫ φ(z) Φ(z − k)⁸ dz (closed form, numerical quadrature) — the design's false-alarm rate."""
    z = torch.linspace(-10.0, 20.0, 300001, dtype=torch.float64)
    phi = torch.exp(-0.5 * z * z) / math.sqrt(2 * math.pi)
    cdf = 0.5 * (1 + torch.erf((z - DEFECT_SIGMAS) / math.sqrt(2)))
    p = float(torch.trapezoid(phi * cdf**8, z))
    assert 1e-12 < p < 1e-10


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_isolated_hot_and_dark_pixels_are_found_on_a_noisy_ramp(dtype):
    """Defects of 40–200 DN on a ramp with the camera's own noise: every one found with its sign, nothing else."""
    x, truth = _inject(_camera_ramp(), 20, (40.0, 200.0), seed=2)
    d = defective_pixels(x.to(dtype))
    assert torch.equal(d.mask, truth)
    assert d.hot.tolist() == [10] * 8 and d.dark.tolist() == [10] * 8
    assert torch.allclose(d.fraction, torch.full((8,), 20 / 126**2, dtype=torch.float64))


def test_small_offsets_below_the_floor_are_not_reported():
    x, _ = _inject(_white(4, 0.3), 10, (MIN_DEFECT_DN - 3.0, MIN_DEFECT_DN - 2.0), seed=3)
    d = defective_pixels(x)
    assert int(d.hot.sum() + d.dark.sum()) == 0


def test_hot_pixels_on_a_dark_frame_and_dense_defects():
    """A dark frame (readout noise 0.7 DN at 2 DN) — where hot pixels are measured — shows every hot pixel of 15 DN and
    more; at 1 % of the pixels, defects a few pixels apart do not hide each other (candidates are left out of the
    windows' fits): ≥ 90 % found (the rest have another defect among their 8 neighbours), none wrong."""
    dark = _white(4, 0.7, level=2.0, seed=4)
    x, truth = _inject(dark, 30, (15.0, 60.0), seed=5)
    truth = truth.clamp_min(0)  # the dark ones are clipped at 0 DN: nothing to see
    x = torch.where(truth.bool(), x, dark)
    d = defective_pixels(x)
    assert torch.equal(d.mask.clamp_min(0), truth) and int(d.dark.sum()) == 0
    g = torch.Generator().manual_seed(6)
    base = _camera_ramp(4, seed=7)
    hit = torch.rand(base.shape, generator=g) < 0.01
    hit[..., :1, :] = hit[..., -1:, :] = False
    hit[..., :, :1] = hit[..., :, -1:] = False
    sign = torch.where(torch.rand(base.shape, generator=g) < 0.5, 1.0, -1.0)
    x = (base * 255 + hit * sign * (60 + 100 * torch.rand(base.shape, generator=g))).clamp(0, 255).round() / 255
    d = defective_pixels(x)
    found = d.mask != 0
    assert int((found & ~hit).sum()) == 0
    assert int((found & hit).sum()) >= 0.9 * int(hit.sum())


def test_scene_structure_is_not_a_defect():
    """Edges, 1-px lines in every direction, a 1-px checkerboard, shading and points seen through a lens (a Gaussian
    PSF of σ ≥ 1 px) with noise: nothing flagged."""
    g = torch.Generator().manual_seed(8)
    yy, xx = torch.meshgrid(torch.arange(128.0), torch.arange(128.0), indexing="ij")
    scenes = [
        torch.where(xx < 64, 40.0, 200.0),  # a step edge
        torch.where((yy == 64) | (xx == 30) | (yy == xx) | (yy == 127 - xx), 220.0, 60.0),  # 1-px lines
        torch.where((yy + xx) % 2 == 0, 180.0, 70.0),  # checkerboard
        60.0 + 1.0 * xx + 0.5 * yy,  # shading
    ]
    points = torch.zeros(128, 128)
    points[20::24, 20::24] = 1.0
    for s in (1.0, 1.5):
        k = torch.exp(-0.5 * (torch.arange(-6.0, 7.0) / s) ** 2)
        k = k / k.sum()
        blurred = F.conv2d(F.conv2d(points.view(1, 1, 128, 128), k.view(1, 1, 1, 13), padding=(0, 6)), k.view(1, 1, 13, 1), padding=(6, 0))
        scenes.append(50.0 + 180.0 * blurred[0, 0] / blurred.max())
    x = torch.stack(scenes).unsqueeze(1)
    x = ((x + 2.0 * torch.randn(x.shape, generator=g)).clamp(0, 255).round()) / 255.0
    d = defective_pixels(x)
    assert (d.hot + d.dark).tolist() == [0] * len(scenes)


@pytest.mark.parametrize("level", [0.0, 1.0])
def test_black_and_saturated_frames(level):
    """Nothing stands out of a black or saturated frame; a hot pixel in a black frame does, a dead one in a saturated
    frame too."""
    x = torch.full((1, 1, 64, 64), level)
    assert int(defective_pixels(x).hot + defective_pixels(x).dark) == 0
    y = x.clone()
    y[0, 0, 30, 30] = 0.5
    d = defective_pixels(y)
    assert (int(d.hot), int(d.dark)) == ((1, 0) if level == 0.0 else (0, 1))
    assert int(d.mask[0, 0, 30, 30]) == (1 if level == 0.0 else -1)


def test_batch_of_one_small_and_non_square_patches():
    x, truth = _inject(_camera_ramp(1), 4, (80.0, 120.0), seed=9)
    d = defective_pixels(x[..., :40, :])
    assert torch.equal(d.mask, truth[..., :40, :]) and d.checked.tolist() == [38 * 126]
    assert int(defective_pixels(torch.rand(1, 1, 3, 3)).checked) == 1
    empty = defective_pixels(torch.zeros(0, 1, 16, 16))
    assert empty.hot.shape == (0,) and empty.mask.shape == (0, 1, 16, 16)


@pytest.mark.parametrize("bad, match", [
    (torch.zeros(1, 3, 16, 16), "B×1×H×W"),
    (torch.zeros(16, 16), "B×1×H×W"),
    (torch.zeros(1, 1, 2, 16), "H, W ≥ 3"),
    (torch.full((1, 1, 16, 16), float("nan")), "NaN"),
    (torch.full((1, 1, 16, 16), 100.0), r"\[0, 1\] \(DN/255\), got values in \[100, 100\]"),
    (torch.full((1, 1, 16, 16), -0.5), r"\[0, 1\] \(DN/255\), got values in \[-0.5, -0.5\]"),
])
def test_bad_input_is_refused(bad, match):
    with pytest.raises(ValueError, match=match):
        defective_pixels(bad)


@pytest.mark.parametrize("bad, match", [
    (torch.zeros(1, 1, 16, 16, dtype=torch.uint8), "floating"),
    (torch.zeros(0, 1, 16, 16, dtype=torch.int64), "floating"),
    (torch.zeros(1, 1, 16, 16).numpy(), "torch.Tensor, got ndarray"),
])
def test_wrong_types_are_refused(bad, match):
    with pytest.raises(TypeError, match=match):
        defective_pixels(bad)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_dn_scaled_patches_are_refused_not_read_with_a_tiny_floor(dtype):
    """A 3 DN bump is below MIN_DEFECT_DN; the same patch given in DN (× 255) used to be accepted and the bump reported
    as a hot pixel (the 8 DN floor became 8/255 DN). Now the range is checked, in every float dtype."""
    x = torch.full((1, 1, 64, 64), 100 / 255)
    x[0, 0, 30, 30] = 103 / 255
    assert int(defective_pixels(x.to(dtype)).hot) == 0
    with pytest.raises(ValueError, match=r"patches must lie in \[0, 1\] \(DN/255\)"):
        defective_pixels((x * 255).to(dtype))
    with pytest.raises(ValueError, match=r"patches must lie in \[0, 1\]"):
        defective_pixels((x - 1).to(dtype))


@pytest.mark.parametrize("level, sigma", [(0.0, 3.0), (-3.0, 5.0), (-6.0, 8.0), (255.0, 20.0), (258.0, 5.0), (262.0, 20.0)])
def test_noise_clipped_at_black_or_saturation_is_not_a_defect(level, sigma):
    """White noise around a level at or beyond 0 or 255 DN, 8-bit: the clipped pixels hide the noise's spread from σ_n
    (at mean 0 DN, σ 3 DN it reads 1.5 DN), and noise peaks amid them used to be reported — 20 to 5800 per million
    pixels. The censored-noise level of the window (σ_c) restores the 6 σ test: nothing flagged in 32 patches."""
    g = torch.Generator().manual_seed(int(level * 10 + sigma))
    x = ((level + sigma * torch.randn(32, 1, 128, 128, generator=g)).round().clamp(0, 255)) / 255.0
    d = defective_pixels(x)
    assert int(d.hot.sum() + d.dark.sum()) == 0 and d.checked.tolist() == [126 * 126] * 32


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
@pytest.mark.parametrize("batch", [1, 256])
def test_clear_defects_on_clipped_noise_are_still_found(dtype, batch):
    """On a black frame with σ = 3 DN (half the pixels at 0 DN) hot pixels of 60 DN (20 σ) are found and the noise is
    not; on a frame at 255 DN with σ = 5 DN dead pixels 80 DN (16 σ) below it are found; batch 1 and 256, every float
    dtype."""
    g = torch.Generator().manual_seed(batch)
    black = (3.0 * torch.randn(batch, 1, 48, 48, generator=g)).round().clamp(0, 255)
    white = (255.0 + 5.0 * torch.randn(batch, 1, 48, 48, generator=g)).round().clamp(0, 255)
    truth = torch.zeros(batch, 1, 48, 48, dtype=torch.bool)
    truth[..., 8:-8:8, 8:-8:8] = True
    x = torch.cat([torch.where(truth, black + 60.0, black), torch.where(truth, white - 80.0, white)]) / 255.0
    d = defective_pixels(x.to(dtype))
    assert torch.equal(d.mask[:batch] == 1, truth) and torch.equal(d.mask[batch:] == -1, truth)
    assert int(d.dark[:batch].sum() + d.hot[batch:].sum()) == 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.bfloat16])
def test_repair_replaces_each_defect_by_its_good_neighbours_mean(dtype):
    """A defect's value becomes the mean of its 8 neighbours that are not defects themselves; every other pixel is
    untouched; without defects the input comes back as it is (the same tensor)."""
    x, truth = _inject(_camera_ramp(2), 12, (60.0, 150.0), seed=10)
    x[0, 0, 40, 40], x[0, 0, 40, 41] = 1.0, 0.0  # a bright and a dark pixel side by side: a cluster, not found
    x[0, 0, 60, 60], x[0, 0, 61, 62] = 1.0, 1.0  # two defects one pixel apart diagonally: both found
    x = x.to(dtype)
    fixed, found = repair_defective_pixels(x)
    assert fixed.dtype == dtype and found.mask[0, 0, 60, 60] == 1 and found.mask[0, 0, 61, 62] == 1
    bad = found.mask != 0
    assert torch.equal(fixed[~bad], x[~bad])
    xf = x.double()
    for b, _, y, xx in bad.nonzero().tolist():
        ring = [(y + dy, xx + dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)]
        good = [float(xf[b, 0, p, q]) for p, q in ring if not bad[b, 0, p, q]]
        assert float(fixed[b, 0, y, xx]) == pytest.approx(sum(good) / len(good), abs=2e-3 if dtype == torch.bfloat16 else 1e-6)
    clean = _camera_ramp(2)
    same, none = repair_defective_pixels(clean)
    assert same is clean and int(none.hot.sum() + none.dark.sum()) == 0


@pytest.mark.parametrize("noise_dn", [torch.ones(3), torch.tensor([1.0, float("nan")]), torch.tensor([1.0, -2.0])])
def test_a_given_noise_level_must_be_one_finite_sigma_per_patch(noise_dn):
    with pytest.raises(ValueError, match="noise_dn must hold one finite σ ≥ 0"):
        defective_pixels(_white(2, 1.0, size=32), noise_dn=noise_dn)


def test_a_given_noise_level_gives_the_same_answer_as_the_computed_one():
    from camhealth._inputs import haar_noise_dn

    x, _ = _inject(_camera_ramp(2), 10, (60.0, 150.0), seed=11)
    assert torch.equal(defective_pixels(x, noise_dn=haar_noise_dn(x)).mask, defective_pixels(x).mask)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_gathered_and_the_dense_neighbour_test_agree(dtype, monkeypatch):
    """The candidates' 8 neighbours are gathered where the left and upper steps pass (few pixels), or read for every
    pixel at once where more than _DENSE_SHARE do: the same defects either way — a camera ramp with defects, 1-px
    columns and a 1-px grid of 10 DN steps (steps the noise estimate does not see; the grid's pass the prefilter at
    every pixel) with defects, and white noise with defects at the border of the tested area."""
    import camhealth.estimators.defective_pixels as dp

    ramp, _ = _inject(_camera_ramp(4), 20, (20.0, 150.0), seed=3)
    cols = (torch.arange(128) % 2).float().view(1, 1, 1, 128).expand(2, 1, 128, 128) * 0.04 + 0.3
    i = torch.arange(128) % 2  # steps to the left and upper neighbour at every pixel, no diagonal Haar detail
    grid = (i.view(-1, 1) + i.view(1, -1)).float().expand(2, 1, 128, 128) * 0.04 + 0.3
    patterned, _ = _inject(torch.cat([cols, grid]).contiguous(), 10, (60.0, 120.0), seed=4)
    edge = _white(2, 2.0, seed=5)
    edge[:, 0, 1, 1], edge[:, 0, -2, -2], edge[:, 0, 1, -2] = 1.0, 0.0, 1.0
    patterned = patterned[:2]  # the columns (the grid is a pattern, not tested: below)
    for x in (ramp, patterned, edge):
        x = x.to(dtype)
        monkeypatch.setattr(dp, "_DENSE_SHARE", 1.0)  # always gathered
        gathered = defective_pixels(x)
        monkeypatch.setattr(dp, "_DENSE_SHARE", -1.0)  # always dense
        dense = defective_pixels(x)
        assert torch.equal(gathered.mask, dense.mask) and int((dense.mask != 0).sum()) > 0
    assert (dense.mask[:, 0, 1, 1] == 1).all() and (dense.mask[:, 0, -2, -2] == -1).all()


def test_a_regular_grid_of_local_extremes_is_a_pattern_not_defects():
    """A 1-px grid of 10 DN steps with no diagonal Haar detail (as a raw Bayer mosaic read as gray makes): every other
    pixel is a local maximum or minimum beyond the noise estimate, half of them candidates — a pattern, not isolated
    defects: no defect reported and the patch not counted as tested; beside it a patch with 1 % of real defects is
    read as before."""
    from camhealth.estimators.defective_pixels import MAX_CANDIDATE_SHARE

    i = torch.arange(128) % 2
    grid = ((i.view(-1, 1) + i.view(1, -1)).float() * 0.04 + 0.3).expand(1, 1, 128, 128)
    real, truth = _inject(_camera_ramp(1), 160, (60.0, 120.0), seed=8)  # 1 % of the pixels
    d = defective_pixels(torch.cat([grid, real]))
    assert int(d.hot[0] + d.dark[0]) == 0 and int(d.checked[0]) == 0 and not bool(d.mask[0].any())
    assert int(d.checked[1]) == 126 * 126 and int(d.hot[1] + d.dark[1]) >= 0.9 * int((truth != 0).sum())
    assert 160 / (126 * 126) < MAX_CANDIDATE_SHARE
    fixed, _ = repair_defective_pixels(grid.contiguous())
    assert torch.equal(fixed, grid)

