"""Row and column noise (banding) from one patch: its estimate, its detection, and the details taken out of it."""

import math

import pytest
import torch

from camhealth.estimators.noise_features import block_details
from camhealth.estimators.row_column_noise import (
    MIN_BANDING_DN, MIN_DIFFERENCES, SERIAL_LIMIT, T_LIMIT, _midmean_constants, debanded_details, row_column_noise,
)


def _white(b: int, sigma_dn: float = 4.0, level: float = 0.5, seed: int = 0, size: int = 128) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return level + sigma_dn / 255.0 * torch.randn(b, 1, size, size, generator=g, dtype=torch.float64)


def _band(x: torch.Tensor, sigma_dn: float, kind: str, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    b, _, h, w = x.shape
    shape = (b, 1, h, 1) if kind == "rows" else (b, 1, 1, w)
    return x + sigma_dn / 255.0 * torch.randn(shape, generator=g, dtype=x.dtype)


def _eight_bit(x: torch.Tensor) -> torch.Tensor:
    return (x.clamp(0, 1) * 255.0).round() / 255.0


def test_midmean_constants_match_their_asymptotic_values():
    """The middle half of a Gaussian keeps 0.143 of its variance and its mean has 1.195 σ²/W (closed forms:
    (1 − 2α − 2cφ(c))/(1 − 2α) and [1 − 2α − 2cφ(c) + 2αc²]/(1 − 2α)², α = ¼, c = Φ⁻¹(¾))."""
    c = 0.6744897501960817
    phi = math.exp(-0.5 * c * c) / math.sqrt(2 * math.pi)
    k_inf = (0.5 - 2 * c * phi) / 0.5
    c_inf = (0.5 - 2 * c * phi + 0.5 * c * c) / 0.25
    k, cw = _midmean_constants(1024)
    assert k == pytest.approx(k_inf, rel=0.02) and cw == pytest.approx(c_inf, rel=0.03)
    k64, c64 = _midmean_constants(64)
    assert k_inf < k64 < 0.16 and cw == pytest.approx(c64, rel=0.05)


@pytest.mark.parametrize("quantise", [False, True])
def test_pixel_noise_alone_is_never_banding(quantise):
    """256 flat patches of white noise (float and 8-bit): T ≈ 1, nothing detected, σ̂ near 0."""
    x = _white(256)
    x = _eight_bit(x) if quantise else x
    r = row_column_noise(x)
    assert not r.detected.any()
    assert r.significance.median() == pytest.approx(1.0, abs=0.15)
    assert float(r.significance.max()) < T_LIMIT
    assert float(r.sigma_dn.median()) < 0.3
    assert not row_column_noise(x, pool=True).detected.any()


@pytest.mark.parametrize("kind, col", [("rows", 0), ("columns", 1)])
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_banding_is_detected_and_measured(kind, col, dtype):
    """2 DN of offsets per row (column) over 4 DN of pixel noise: detected on nearly every patch in its direction only,
    σ̂ within its sampling error per patch and within 5 % pooled over 64 patches (10 % from bfloat16, whose 8-bit
    mantissa rounds values near mid-grey to about 1 DN), whatever the input dtype."""
    x = _eight_bit(_band(_white(64), 2.0, kind)).to(dtype)
    r = row_column_noise(x)
    assert r.detected[:, col].float().mean() >= 0.95 and not r.detected[:, 1 - col].any()
    assert r.sigma_dn[:, col].median() == pytest.approx(2.0, rel=0.1)
    pooled = row_column_noise(x, pool=True)
    assert pooled.detected[:, col].all()
    assert pooled.sigma_dn[0, col] == pytest.approx(2.0, rel=0.1 if dtype == torch.bfloat16 else 0.05)
    se = pooled.var_se_dn2[0, col]
    assert 0 < se < 0.2 * 4.0  # the standard error of σ̂² [DN²]


@pytest.mark.parametrize("size", [8, 12, 16])
def test_small_patches_of_white_noise_are_not_banding(size):
    """A patch of fewer than 34 px gives fewer than MIN_DIFFERENCES differences, too few for T_LIMIT (white noise
    exceeds it on 3–11 % of 8–16 px patches): it reports no banding alone."""
    x = _eight_bit(_white(400, 5.0, seed=size, size=size))
    assert size // 2 - 1 < MIN_DIFFERENCES
    assert float(row_column_noise(x).detected.double().mean()) <= 0.01
    assert not row_column_noise(x, pool=True).detected.any()


def test_banding_on_a_large_patch_is_still_detected():
    """3 DN of row offsets over 5 DN of pixel noise on 128-px patches (63 differences): detected on every patch."""
    r = row_column_noise(_eight_bit(_band(_white(32, 5.0, seed=3), 3.0, "rows")))
    assert r.detected[:, 0].all() and not r.detected[:, 1].any()


@pytest.mark.parametrize("batch", [1, 256])
def test_scene_structure_along_rows_is_not_banding(batch):
    """What is constant along whole rows but not independent from row to row is the scene's: a vertical ramp and
    a smooth shading (the differences and the straight line take them out), stripes with a period of 10 px and a
    sinusoidal grating in both directions (the serial correlation refuses them)."""
    y = torch.arange(128, dtype=torch.float64).view(1, 1, 128, 1)
    xx = torch.arange(128, dtype=torch.float64).view(1, 1, 1, 128)
    noise = _white(batch, 2.0, 0.0)
    scenes = {
        "ramp": 0.2 + 0.6 * y / 127 + 0 * xx,
        "shading": 0.5 + 0.3 * torch.cos(y / 40.0) + 0 * xx,
        "stripes": 0.5 + 0.15 * torch.sin(2 * math.pi * y / 10.0) + 0 * xx,
        "grating": 0.5 + 0.15 * torch.sin(2 * math.pi * y / 6.0) + 0.15 * torch.sin(2 * math.pi * xx / 9.0),
    }
    for name, scene in scenes.items():
        x = _eight_bit(scene + noise)
        for pool in (False, True):
            r = row_column_noise(x, pool=pool)
            assert not r.detected.any(), (name, pool, r.significance[0], r.serial[0])
    # the stripes are significant and strong: only their correlation from row to row tells them from banding
    r = row_column_noise(_eight_bit(scenes["stripes"] + noise))
    assert (r.significance[:, 0] > T_LIMIT).all() and (r.sigma_dn[:, 0] > MIN_BANDING_DN).all()
    assert (r.serial[:, 0] > SERIAL_LIMIT).all()


def test_diagonal_detail_never_sees_banding_and_debanding_restores_white_noise():
    """Offsets per row and per column cancel in the diagonal detail exactly; taken out of the horizontal and vertical
    details and of the block-mean gradients, those read what pixel noise alone gives (E[h²] = E[v²] = E[d²])."""
    clean = _eight_bit(_white(16, 3.0))
    x = _eight_bit(_band(_band(clean, 5.0, "rows", 2), 5.0, "columns", 3))
    m, d2, usable, g2 = block_details(x)
    _, d2_clean, _, g2_clean = block_details(clean)
    r = row_column_noise(x)
    assert r.detected.all()
    band_only = _band(_band(torch.zeros_like(clean), 5.0, "rows", 2), 5.0, "columns", 3)
    assert block_details(band_only + 0.5)[1][0].abs().max() < 1e-6
    d2b, g2b = debanded_details(x, m, d2, g2, r.detected)
    assert torch.equal(d2b[0], d2[0])
    ratio_before = (d2[1].mean() + d2[2].mean()) / 2 / d2[0].mean()
    ratio_after = (d2b[1].mean() + d2b[2].mean()) / 2 / d2b[0].mean()
    assert ratio_before > 3.0 and ratio_after == pytest.approx(1.0, abs=0.06)
    assert float(g2b.median()) == pytest.approx(float(g2_clean.median()), rel=0.15)
    assert float(g2.median()) > 3 * float(g2_clean.median())
    # nothing detected: the very same tensors
    none = torch.zeros_like(r.detected)
    d2n, g2n = debanded_details(x, m, d2, g2, none)
    assert d2n is d2 and g2n is g2


@pytest.mark.parametrize("bad", [torch.zeros(4, 128, 128), torch.zeros(2, 3, 64, 64), torch.zeros(2, 1, 4, 64)])
def test_bad_shapes_are_refused_naming_the_shape(bad):
    with pytest.raises(ValueError, match=r"B×1×H×W patches with H, W ≥ 8, got"):
        row_column_noise(bad)


def test_constant_black_saturated_and_non_square_patches():
    """No texture, no noise (black, saturated, constant grey): nothing detected, every number finite. A non-square
    patch (128×96) takes each direction on its own and finds its row noise."""
    flat = torch.stack([torch.zeros(1, 128, 128), torch.ones(1, 128, 128), torch.full((1, 128, 128), 0.5)])
    for pool in (False, True):
        r = row_column_noise(flat, pool=pool)
        assert not r.detected.any()
        for t in (r.sigma_dn, r.var_se_dn2, r.significance, r.serial):
            assert torch.isfinite(t).all()
    wide = _eight_bit(_band(_white(16, 3.0, size=128)[..., :96], 3.0, "rows"))
    r = row_column_noise(wide)
    assert r.sigma_dn.shape == (16, 2)
    assert r.detected[:, 0].float().mean() > 0.9 and not r.detected[:, 1].any()
    assert r.sigma_dn[:, 0].median() == pytest.approx(3.0, rel=0.15)


@pytest.mark.parametrize("bad, error, match", [
    ("uint8", TypeError, r"patches must be a floating tensor .* got dtype torch\.uint8"),
    ("dn", ValueError, r"patches must lie in \[0, 1\] \(DN/255; .*\), got values in \["),
    ("nan", ValueError, r"patches must be finite, but 1 of \d+ values are NaN/inf"),
    ("numpy", TypeError, "patches must be a torch.Tensor, got ndarray"),
])
def test_bad_patches_are_refused(bad, error, match):
    """8-bit or DN-scale input read σ_row 255× too large (1666 DN for 5 DN), a NaN pixel was ignored, a numpy array
    failed with an AttributeError: each is refused, naming the dtype or the values."""
    x = _band(_white(2, seed=3), 5.0, "rows")
    if bad == "uint8":
        x = (x.clamp(0, 1) * 255).round().to(torch.uint8)
    elif bad == "dn":
        x = x * 255.0
    elif bad == "nan":
        x[0, 0, 3, 3] = float("nan")
    else:
        x = x.numpy()
    with pytest.raises(error, match=match):
        row_column_noise(x)


@pytest.mark.parametrize("pool", [False, True])
def test_an_empty_batch_gives_empty_fields(pool):
    """``pool=True`` on an empty batch raised an IndexError from ``median``."""
    out = row_column_noise(torch.zeros(0, 1, 64, 64), pool=pool)
    for field in (out.sigma_dn, out.var_se_dn2, out.significance, out.serial, out.detected):
        assert field.shape == (0, 2)


def test_a_static_pairs_unclamped_fold_is_accepted():
    """The fold of a static pair (``static_pair_image(clamp=False)``) swings up to 1/√2 beyond [0, 1]: accepted."""
    from camhealth.estimators.static_pair import static_pair_image

    g = torch.Generator().manual_seed(2)
    a = (0.97 + 60 / 255 * torch.randn(2, 1, 64, 64, generator=g)).clamp(0, 1)
    b = (0.97 + 60 / 255 * torch.randn(2, 1, 64, 64, generator=g)).clamp(0, 1)
    fold = static_pair_image(a, b, clamp=False)
    assert float(fold.max()) > 1.0
    assert row_column_noise(fold).sigma_dn.shape == (2, 2)
