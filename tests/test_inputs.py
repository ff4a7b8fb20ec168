"""The shared input checks of camhealth._inputs: the edge test of the MTF estimators (noise-corrected gradient kurtosis)."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from camhealth._inputs import (
    MIN_EDGE_KURTOSIS, assess_patches, edge_kurtosis, edge_kurtosis_from_moments, has_edges, structure_contrast_dn,
)


def _random_phase_texture(n: int, size: int, beta: float, seed: int) -> torch.Tensor:
    """Gaussian random field with power spectrum f^-β, std 30 DN around 128 DN ([0, 1] units)."""
    g = torch.Generator().manual_seed(seed)
    w = torch.fft.rfft2(torch.randn(n, 1, size, size, generator=g, dtype=torch.float64))
    f = torch.sqrt(torch.fft.fftfreq(size, dtype=torch.float64)[:, None] ** 2 + torch.fft.rfftfreq(size, dtype=torch.float64)[None, :] ** 2)
    x = torch.fft.irfft2(w * torch.where(f > 0, f.clamp_min(1e-9) ** (-beta / 2), torch.zeros(())), s=(size, size))
    x = (x - x.mean((2, 3), keepdim=True)) / x.std(dim=(2, 3), keepdim=True)
    return (128.0 + 30.0 * x).clamp(0, 255) / 255.0


def _blocks(n: int, size: int, block: int, seed: int) -> torch.Tensor:
    """Random gray blocks (edges between them), 40–215 DN."""
    g = torch.Generator().manual_seed(seed)
    return F.interpolate((40.0 + 175.0 * torch.rand(n, 1, size // block, size // block, generator=g, dtype=torch.float64)) / 255.0,
                         size=size, mode="nearest")


def _noisy(x: torch.Tensor, sigma_dn: float, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (x + sigma_dn / 255.0 * torch.randn(x.shape, generator=g, dtype=x.dtype)).clamp(0, 1)


def test_moments_closed_form_with_noise():
    """Sparse gradients ±a with probability p (excess kurtosis 1/p − 3) plus N(0, σ²/2) noise: the exact moments give
    γ = 1/p − 3 whatever σ — κ₄ is additive and Gaussian noise has none."""
    p, a = torch.tensor([0.02, 0.1, 0.3], dtype=torch.float64), 12.0
    for sigma in (0.0, 3.0, 20.0):
        vn = sigma**2 / 2
        m2 = p * a**2 + vn
        m4 = p * a**4 + 6 * p * a**2 * vn + 3 * vn**2
        gamma, se = edge_kurtosis_from_moments(m2, m4, torch.full_like(p, sigma), 10_000)
        assert torch.allclose(gamma.double(), 1 / p - 3, rtol=1e-5)
        assert torch.allclose(se.double(), math.sqrt(24 / 10_000) * (m2 / (p * a**2)) ** 2, rtol=1e-5)
    # noise explaining all of m2: no scene evidence
    gamma, se = edge_kurtosis_from_moments(torch.tensor([8.0]), torch.tensor([192.0]), torch.tensor([4.0]), 100)
    assert gamma.item() == 0.0 and math.isinf(se.item())


@pytest.mark.parametrize("sigma_dn", [0.0, 5.0, 10.0])
def test_gaussian_texture_has_no_edges(sigma_dn):
    x = _noisy(_random_phase_texture(6, 192, 2.0, seed=1), sigma_dn, seed=2).float()
    gamma, se = edge_kurtosis(x, structure_contrast_dn(x)[1])
    assert gamma.abs().max() < 0.5, gamma
    assert not has_edges(gamma, se).any()
    ok, reason = assess_patches(x, "mtf")
    assert not ok.any() and set(reason) == {"no edges"}


@pytest.mark.parametrize("sigma_dn", [0.0, 5.0, 10.0])
def test_edges_survive_blur_and_noise(sigma_dn):
    """Blocks blurred by a 5×5 box and then noisy: large γ, the noise correction keeps it near the clean value."""
    clean = F.avg_pool2d(F.pad(_blocks(6, 192, 16, seed=3), (2, 2, 2, 2), mode="replicate"), 5, stride=1)
    ref = edge_kurtosis(clean.float(), torch.zeros(6))[0]
    x = _noisy(clean, sigma_dn, seed=4).float()
    gamma, se = edge_kurtosis(x, structure_contrast_dn(x)[1])
    assert (ref > 5 * MIN_EDGE_KURTOSIS).all() and has_edges(gamma, se).all()
    assert torch.allclose(gamma, ref, rtol=0.25), (gamma, ref)
    ok, reason = assess_patches(x, "mtf")
    assert ok.all() and set(reason) == {""}


def test_weak_structure_under_strong_noise_is_not_shown():
    """±2 DN blocks under 20 DN of noise: γ is far too uncertain to show edges (standard error ≫ γ)."""
    x = _noisy(0.5 + 4.0 / 255.0 * (_blocks(4, 192, 16, seed=5) - 0.5), 20.0, seed=6).float()
    gamma, se = edge_kurtosis(x, structure_contrast_dn(x)[1])
    assert (se > 1.0).all() and not has_edges(gamma, se).any()


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16, torch.float32, torch.float64])
@pytest.mark.parametrize("batch", [1, 256])
def test_batched_and_dtypes(dtype, batch):
    parts = [_blocks(batch // 2 + batch % 2, 32, 4, seed=7)] + ([_random_phase_texture(batch // 2, 32, 2.0, seed=8)] if batch > 1 else [])
    x = torch.cat(parts).to(dtype)
    noise = structure_contrast_dn(x)[1]
    gamma, se = edge_kurtosis(x, noise)
    assert gamma.shape == se.shape == (batch,) and gamma.dtype == torch.float32 and torch.isfinite(gamma).all()
    one, one_se = edge_kurtosis(x[:1], noise[:1])
    assert torch.allclose(one, gamma[:1]) and torch.allclose(one_se, se[:1])
    assert has_edges(gamma[:1], se[:1]).all()  # the blocks come first
    ok, reason = assess_patches(x, "mtf")  # the estimator's rule at every precision
    assert ok[: batch // 2 + batch % 2].all() and not ok[batch // 2 + batch % 2:].any()


def test_tiny_patches_show_no_edges():
    gamma, se = edge_kurtosis(torch.rand(3, 1, 3, 3), torch.zeros(3))
    assert (gamma == 0).all() and torch.isinf(se).all() and not has_edges(gamma, se).any()


@pytest.mark.parametrize("kind", ["rows", "columns", "both"])
def test_row_and_column_noise_is_no_structure_to_read_blur_on(kind, monkeypatch):
    """A flat 192-px patch with 3 DN of pixel noise and 10 DN of offsets per row (column, both) has ≈ 3.5 DN of
    8×8-block contrast from the banding alone: the MTF would read it as a scene, its blur across the banding as strong,
    with a confident error bar. Taken out (with two standard errors), the patch is featureless. A straight edge along
    the banding keeps its contrast and stays assessable."""
    import camhealth._inputs as inputs

    g = torch.Generator().manual_seed(7)
    x = 0.5 + 3.0 / 255.0 * torch.randn(64, 1, 192, 192, generator=g)
    if kind in ("rows", "both"):
        x = x + 10.0 / 255.0 * torch.randn(64, 1, 192, 1, generator=g)
    if kind in ("columns", "both"):
        x = x + 10.0 / 255.0 * torch.randn(64, 1, 1, 192, generator=g)
    x = (x.clamp(0, 1) * 255).round() / 255
    ok, reason = assess_patches(x, "mtf")
    assert int(ok.sum()) <= 1 and reason.count("featureless") >= 63
    edge = 0.4 + 0.15 * (torch.arange(192.0) > 96).float().view(1, 1, 192, 1).expand(16, 1, 192, 192)
    banded_edge = edge + 3.0 / 255.0 * torch.randn(16, 1, 192, 192, generator=g) + 10.0 / 255.0 * torch.randn(16, 1, 192, 1, generator=g)
    assert assess_patches((banded_edge.clamp(0, 1) * 255).round() / 255, "mtf")[0].all()
    # without the banding taken out, banding in one direction is read as a scene (in both, the edge test refuses
    # most of it: its gradients are as Gaussian across the rows as along them)
    monkeypatch.setattr(inputs, "_without_banding", lambda p, s, n, m: s)
    assert int(assess_patches(x, "mtf")[0].sum()) >= (32 if kind != "both" else 0)


def test_flat_banded_patches_over_a_sweep_are_nearly_never_assessable():
    """Flat 192-px patches, 1–20 DN of pixel noise × 3–30 DN of row, column or both kinds of banding, 64 each
    (2 304 in all): at most 2 % pass the featureless and edge tests (35 do, mostly at 30 DN of banding)."""
    g = torch.Generator().manual_seed(1)
    passed = 0
    for sw in (1.0, 3.0, 8.0, 20.0):
        for sr in (3.0, 10.0, 30.0):
            for kind in ("rows", "cols", "both"):
                x = 0.5 + sw / 255.0 * torch.randn(64, 1, 192, 192, generator=g)
                if kind in ("rows", "both"):
                    x = x + sr / 255.0 * torch.randn(64, 1, 192, 1, generator=g)
                if kind in ("cols", "both"):
                    x = x + sr / 255.0 * torch.randn(64, 1, 1, 192, generator=g)
                passed += int(assess_patches((x.clamp(0, 1) * 255).round() / 255, "mtf")[0].sum())
    assert passed <= 0.02 * 2304, passed


@pytest.mark.parametrize("size", [2, 9, 128, 192])
def test_haar_noise_dn_is_structure_contrasts_noise_level(size):
    """The shared robust σ̂ [DN]: the one ``structure_contrast_dn`` reports, within 5 % of white noise's σ."""
    from camhealth._inputs import haar_noise_dn

    g = torch.Generator().manual_seed(size)
    x = (0.5 + 6.0 / 255.0 * torch.randn(4, 1, size, size, generator=g))
    sigma = haar_noise_dn(x)
    assert sigma.shape == (4,) and sigma.dtype == torch.float32
    assert torch.allclose(sigma, structure_contrast_dn(x)[1])
    if size >= 128:
        assert torch.allclose(sigma, torch.full((4,), 6.0), rtol=0.05)


def test_assess_patches_with_the_callers_noise_level_answers_as_without():
    """A caller that has σ̂ (haar_noise_dn in float64, as Estimator.predict does for the MTF) gets the same verdicts
    as assess_patches computing it itself: edges, textures, flat and noisy patches alike."""
    from camhealth._inputs import assess_patches, haar_noise_dn

    g = torch.Generator().manual_seed(3)
    flat = torch.full((4, 1, 64, 64), 0.5)
    edge = flat.clone()
    edge[..., 32:] = 0.8
    texture = torch.rand(4, 1, 64, 64, generator=g)
    x = torch.cat([flat, edge, texture]) + torch.linspace(0, 20, 12).view(12, 1, 1, 1) / 255 * torch.randn(12, 1, 64, 64, generator=g)
    x = x.clamp(0, 1)
    own = assess_patches(x, "mtf")
    given = assess_patches(x, "mtf", haar_noise_dn(x, torch.float64))
    assert torch.equal(own[0], given[0]) and own[1] == given[1]
    assert len(set(own[1])) > 1  # the patches are not all judged alike


def test_statistics_of_tiny_patches_stay_on_the_patches_device(device):
    """Patches too small for the block statistics still get their answers on their own device."""
    from camhealth._inputs import _structure_stats, edge_kurtosis

    x = torch.rand(2, 1, 3, 3, generator=torch.Generator().manual_seed(0)).to(device)
    gamma, se = edge_kurtosis(x, torch.ones(2, device=device))
    assert gamma.device.type == se.device.type == device.type and bool(torch.isinf(se).all())
    one = torch.rand(2, 1, 1, 5, generator=torch.Generator().manual_seed(1)).to(device)
    s, noise, means = _structure_stats(one)
    assert s.device.type == noise.device.type == device.type and means is None


@pytest.mark.parametrize("mean_dn", [20.0, 40.0, 235.0])
def test_flat_patches_under_heavily_clipped_noise_are_not_assessable_for_mtf(mean_dn):
    """64 DN of noise on a flat 20 or 235 DN patch clips a third of it: the structure contrast² of pure noise scatters by
    σ²/64·√(2/576) ≈ 3.8 DN², so a fixed 2 DN (4 DN²) let one flat patch in seven through as a scene; the limit raised by
    three of those standard deviations (3.9 DN there) lets at most one in a hundred."""
    from camhealth._inputs import contrast_limit_dn

    g = torch.Generator().manual_seed(0)
    x = (mean_dn + 64.0 * torch.randn(200, 1, 192, 192, generator=g)).clamp(0, 255).round() / 255.0
    ok, reason = assess_patches(x, "mtf")
    assert ok.float().mean() <= 0.01 and reason.count("featureless") >= 190
    # the closed form: √(2² + 3·σ²/64·√(2/576)); the fixed 2 DN where there is no noise
    limit = contrast_limit_dn(torch.tensor([0.0, 10.0, 64.0], dtype=torch.float64), 576, 64)
    want = [(4.0 + 3.0 * s * s / 64.0 * math.sqrt(2.0 / 576)) ** 0.5 for s in (0.0, 10.0, 64.0)]
    assert limit.tolist() == pytest.approx(want, rel=1e-6) and limit[0].item() == pytest.approx(2.0)


@pytest.mark.parametrize("dtype", [">f4", ">f8", ">u2", ">i4", "longdouble"])
def test_big_endian_and_long_double_arrays_are_read_as_their_values(dtype):
    """A big-endian array (FITS, some TIFF readers) raised torch's "byte order different from the native byte order",
    and a long double one torch's "can't convert np.ndarray of type numpy.longdouble"; both are the same DN or
    [0, 1] values as the native array."""
    import numpy as np

    from camhealth._inputs import _to_patches

    dn = np.round(np.random.default_rng(0).random((2, 32, 32)) * 255.0)
    native = dn / 255.0 if dtype[-2] == "f" or dtype == "longdouble" else dn.astype(np.uint8)
    want = _to_patches(native, 32, "auto")
    arr = native.astype(np.longdouble if dtype == "longdouble" else np.dtype(dtype))
    got = _to_patches(arr, 32, "dn" if dtype[-2] in "ui" else "auto")  # wider integers: 8-bit DN only when said so
    assert got.dtype == torch.float32 and torch.equal(got, want)


@pytest.mark.parametrize("dtype", ["uint16", "int16", "int32", "int64", "torch.int64", "torch.uint16"])
def test_integers_wider_than_8_bits_are_dn_only_when_said_so(dtype):
    """A dark frame of a 12-bit camera in uint16 holds values ≤ 255 too: read as 8-bit DN its noise would be 16×
    too large. Integers wider than 8 bits are refused with the default ``input_range='auto'`` (naming the dtype, the
    values and the ways out) and read as DN with ``input_range='dn'``; uint8 stays DN by itself."""
    import numpy as np

    from camhealth._inputs import _to_patches

    dn = np.round(np.random.default_rng(0).random((2, 32, 32)) * 200.0)
    arr = torch.from_numpy(dn).to(getattr(torch, dtype[6:])) if dtype.startswith("torch.") else dn.astype(dtype)
    name = dtype[6:] if dtype.startswith("torch.") else dtype
    with pytest.raises(ValueError, match=rf"dtype {name} may hold more than 8 bits .*min 0, max 200.*input_range='dn'"):
        _to_patches(arr, 32, "auto")
    want = _to_patches(dn.astype(np.uint8), 32, "auto")
    assert torch.equal(_to_patches(arr, 32, "dn"), want)
    assert torch.allclose(want[:, 0] * 255, torch.from_numpy(dn).float(), atol=1e-4)


def test_long_double_values_beyond_float64_are_named():
    import numpy as np

    from camhealth._inputs import _to_patches

    arr = np.full((1, 32, 32), np.longdouble("1e400"))
    if not np.isfinite(arr).all():
        pytest.skip("this platform's long double is float64")
    with pytest.raises(ValueError, match=r"beyond float64's range \(min 1e\+400, max 1e\+400\); allowed: DN 0…255 or \[0, 1\]"):
        _to_patches(arr, 32, "auto")


@pytest.mark.parametrize("shape, layout", [((32, 32, 1), "an H×W×1"), ((3, 32, 32, 1), "a B×H×W×1")])
def test_a_gray_image_with_its_channel_last_is_named_as_such(shape, layout):
    """H×W×1 gray input said "patches must be 32×32 px, got 32×1"; it names the channels-last layout and the fix."""
    from camhealth._inputs import _to_patches

    with pytest.raises(ValueError, match=rf"look like {layout} gray image \(channels last\).*drop the channel axis"):
        _to_patches(torch.full(shape, 0.5), 32, "auto")


def _clipped_patches(black: float, saturated: float, noise_dn: float = 10.0, size: int = 128, n: int = 2, seed: int = 1):
    """Patches whose first ``black`` share of columns lies far below 0 DN and next ``saturated`` share far above 255 DN
    (crushed and blown out), the rest at 128 DN, with ``noise_dn`` of white noise everywhere ([0, 1])."""
    g = torch.Generator().manual_seed(seed)
    mean = torch.full((n, 1, size, size), 127.5)
    wb, ws = int(size * black), int(size * saturated)
    mean[..., :wb] = -60.0
    mean[..., wb:wb + ws] = 320.0
    return ((mean + noise_dn * torch.randn(n, 1, size, size, generator=g)) / 255.0).clamp(0, 1)


@pytest.mark.parametrize("kind", ["noise_source", "drne", "mtf"])
def test_a_patch_mostly_clipped_at_both_ends_is_not_assessable(kind):
    """45 % crushed black and 45 % blown out (each share under half): the noise networks read 10 DN of noise as 0.8 DN
    and the MTF an 84 %-clipped blur as sharp, all "assessable". Both shares together over half: "clipped". A patch
    mostly one of them keeps its own reason, and one under half clipped in all stays assessable (noise)."""
    from camhealth.estimators.physics_noise import BEYOND_VALIDATED

    size = 192 if kind == "mtf" else 128
    ok, reason = assess_patches(_clipped_patches(0.45, 0.45, size=size), kind)
    assert not ok.any() and reason == ["clipped", "clipped"]
    assert assess_patches(_clipped_patches(0.6, 0.3, size=size), kind)[1] == ["black", "black"]
    assert assess_patches(_clipped_patches(0.3, 0.6, size=size), kind)[1] == ["saturated", "saturated"]
    if kind != "mtf":
        assert assess_patches(_clipped_patches(0.3, 0.15, size=size), kind)[1] == ["", ""]
        # noise so strong that it clips half the patch at both ends (200 DN at 128 DN): what is known is the noise
        loud = _clipped_patches(0.0, 0.0, noise_dn=200.0, size=size)
        assert assess_patches(loud, kind)[1] == [BEYOND_VALIDATED] * 2
    else:
        loud = _clipped_patches(0.0, 0.0, noise_dn=200.0, size=size)
        assert assess_patches(loud, kind)[1] == ["clipped"] * 2


def test_the_clipped_share_is_exact_at_one_half():
    """Exactly half the pixels at 0 or 255 DN (a quarter each) is not more than half: the flag starts one pixel later."""
    x = torch.full((2, 1, 192, 192), 0.5)
    flat = x.view(2, -1)
    half = flat.shape[1] // 2
    flat[:, : half // 2] = 0.0
    flat[:, half // 2: half] = 1.0
    assert assess_patches(x, "noise_source")[1] == ["", ""]
    flat[1, half] = 1.0
    assert assess_patches(x, "noise_source")[1] == ["", "clipped"]


@pytest.mark.parametrize("dtype", ["uint8", "uint16", "int64", "torch.uint8", "torch.int32"])
def test_integers_with_input_range_unit_are_refused(dtype):
    """``input_range='unit'`` says the values lie in [0, 1]; integers are DN. A 12-bit frame in uint16 was read as 8-bit
    DN (16× the noise) and a 0/1 int64 mask as 1 DN rather than white, without a word. Refused, naming the dtype and
    what to pass; empty batches alike. Floats with 'unit' and integers with 'dn' are read as before."""
    import numpy as np

    from camhealth._inputs import _to_patches

    ones = np.ones((2, 32, 32))
    arr = torch.from_numpy(ones).to(getattr(torch, dtype[6:])) if dtype.startswith("torch.") else ones.astype(dtype)
    name = dtype[6:] if dtype.startswith("torch.") else dtype
    for x in (arr, arr[:0]):
        with pytest.raises(ValueError, match=rf"dtype {name} are integers, i\.e\. DN, but input_range='unit'.*"
                                             rf"input_range='dn'"):
            _to_patches(x, 32, "unit")
    assert torch.equal(_to_patches(arr, 32, "dn"), torch.full((2, 1, 32, 32), 1 / 255))
    assert torch.equal(_to_patches(ones / 2, 32, "unit"), torch.full((2, 1, 32, 32), 0.5))


def test_a_scalar_and_a_meta_tensor_are_named_as_such():
    """A 0-d tensor said "got shape " (empty text) and a meta-device tensor raised torch's "Cannot copy out of meta
    tensor"."""
    from camhealth._inputs import _to_patches

    with pytest.raises(ValueError, match=r"got shape \(\) \(a 0-d scalar\)"):
        _to_patches(torch.tensor(0.5), 32, "auto")
    with pytest.raises(ValueError, match=r"meta device \(shape 1×1×32×32, no values\)"):
        _to_patches(torch.empty(1, 1, 32, 32, device="meta"), 32, "auto")
