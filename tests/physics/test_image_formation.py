import pytest
import torch

from camhealth.physics.defocus_psf import defocus_psf
from camhealth.physics import image_formation
from camhealth.physics.image_formation import apply_psf, form_image, kernel_support_radii, plan_support_groups
from camhealth.physics.metadata import CameraMetadata
from camhealth.physics.motion_psf import linear_motion_psf


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


@pytest.fixture(params=["torch", "counter"])
def rng(request):
    """Both random-number sources of the noise fields (torch's generator, counter-based draws)."""
    return request.param


@pytest.mark.parametrize("source,idx", [("photon", 0), ("dark", 1), ("readout", 2)])
def test_each_source_realised_sigma_matches_analytic(source, idx, rng):
    m = CameraMetadata.preset("EV76C661", batch_size=3, gain_db=[0.0, 12.0, 18.0], temperature_c=[20.0, 50.0, 70.0],
                              exposure_s=[0.01, 0.1, 0.2])
    x = torch.full((3, 1, 128, 128), 0.45)
    r = form_image(x, m, sources=(source,), generator=_gen(), rng=rng)
    assert torch.allclose(r.sigma_dn[:, idx], r.sigma_expected_dn[:, idx], rtol=0.04)
    others = [j for j in range(3) if j != idx]
    assert torch.all(r.sigma_dn[:, others] == 0)
    assert torch.allclose(r.sigma_total_dn, r.sigma_dn[:, idx], rtol=1e-4)


def test_sources_add_in_quadrature(rng):
    m = CameraMetadata.preset("EV76C661", batch_size=2, gain_db=12.0, temperature_c=60.0, exposure_s=0.1)
    r = form_image(torch.full((2, 1, 128, 128), 0.5), m, generator=_gen(), rng=rng)
    assert torch.allclose(r.sigma_total_dn, r.sigma_dn.pow(2).sum(1).sqrt(), rtol=0.03)
    assert torch.allclose(r.sigma_total_expected_dn, r.sigma_expected_dn.pow(2).sum(1).sqrt())


def test_clipping_makes_the_realised_total_smaller_than_the_quadrature_of_the_attributed_sources(rng):
    """At a clipped pixel every source's noise is scaled by the same factor (the attribution rule), so the
    attributed sources are correlated and √(Σ σ_s²) overstates the realised total (why the noise-source
    network has a total head); without clipping they agree (test above)."""
    # a small full well at high gain and temperature (a camera of the held-out split): σ ≈ 170 DN before clipping
    m = CameraMetadata.preset(
        "EV76C661", batch_size=2, gain_db=22.0, exposure_s=0.17, temperature_c=65.0, dark_fom_na_per_cm2=0.8,
        full_well_e=2500.0, pixel_clock_hz=4.1e7, sense_node_gain_v_per_e=1.13e-6, reset_factor=0.38,
        pixel_size_um=8.8, white_noise_v_per_rthz=3.6e-8,
    )
    r = form_image(torch.full((2, 1, 128, 128), 0.45), m, generator=_gen(), rng=rng)
    quad = r.sigma_dn.pow(2).sum(1).sqrt()
    assert (r.clipped_fraction > 0.3).all()
    assert (r.sigma_total_dn < 0.95 * quad).all() and (r.sigma_total_dn > 0.5 * quad).all()


def test_zero_noise_is_identity_and_black_frame_is_finite(rng):
    # full well 100 000 e⁻, 0 dB, no dark current, short exposure: photon σ of a black frame is 0
    m = CameraMetadata.preset("ICX285", full_well_e=100_000.0, dark_fom_na_per_cm2=0.0, exposure_s=0.001)
    black = torch.zeros(1, 1, 32, 32)
    r = form_image(black, m, sources=("photon", "dark"), generator=_gen(), rng=rng)
    assert torch.equal(r.image, black)
    assert torch.all(r.sigma_dn == 0) and torch.all(r.sigma_expected_dn == 0)
    r = form_image(black, m, generator=_gen(), rng=rng)  # readout noise on black: half clipped at 0
    assert torch.isfinite(r.image).all() and r.image.min() >= 0
    assert 0.3 < r.clipped_fraction.item() < 0.7
    assert r.sigma_dn[0, 2] < r.sigma_expected_dn[0, 2]


def test_saturated_frame_clips_and_labels_shrink(rng):
    m = CameraMetadata.preset("EV76C661", gain_db=24.0, full_well_e=2000.0, temperature_c=80.0, exposure_s=0.2)
    white = torch.ones(1, 1, 64, 64)
    r = form_image(white, m, generator=_gen(), rng=rng)
    assert r.image.max() <= 1 and torch.isfinite(r.sigma_dn).all()
    assert r.clipped_fraction.item() > 0.4
    assert torch.all(r.sigma_dn <= r.sigma_expected_dn * 1.05)


def test_large_sigma_above_30_dn(rng):
    m = CameraMetadata.preset("EV76C661", gain_db=24.0, full_well_e=2000.0, temperature_c=80.0, exposure_s=0.2)
    r = form_image(torch.full((2, 1, 128, 128), 0.5), m, generator=_gen(), rng=rng)
    assert (r.sigma_total_expected_dn > 30).all()
    assert torch.isfinite(r.image).all()


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_dtypes_preserved_and_statistics_agree(dtype, rng):
    m = CameraMetadata.preset("ICX285", gain_db=18.0)
    x = torch.full((2, 1, 64, 64), 0.5, dtype=dtype)
    r = form_image(x, m, defocus_psf=defocus_psf(torch.tensor([3.0, 5.0]), 7), generator=_gen(), rng=rng)
    assert r.image.dtype == dtype and torch.isfinite(r.image.float()).all()
    assert torch.allclose(r.sigma_dn[:, 0].float(), r.sigma_expected_dn[:, 0].float(), rtol=0.05)


@pytest.mark.parametrize("batch", [1, 256])
def test_batch_sizes(batch, rng):
    m = CameraMetadata.sample(batch, _gen(1))
    r = form_image(torch.rand(batch, 1, 16, 16, generator=_gen(2)), m, generator=_gen(3), rng=rng)
    assert r.image.shape == (batch, 1, 16, 16) and r.sigma_dn.shape == (batch, 3)
    assert torch.isfinite(r.sigma_dn).all()


def test_seeded_reproducibility(rng):
    m = CameraMetadata.sample(4, _gen(1))
    x = torch.rand(4, 1, 32, 32, generator=_gen(2))
    a = form_image(x, m, generator=_gen(7), rng=rng).image
    b = form_image(x, m, generator=_gen(7), rng=rng).image
    c = form_image(x, m, generator=_gen(8), rng=rng).image
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_photon_noise_is_motion_blurred_and_directional(rng):
    """PN before a horizontal motion blur becomes horizontally correlated (Sec. 5.4)."""
    m = CameraMetadata.preset("EV76C661", gain_db=24.0)
    psf = linear_motion_psf(torch.tensor([9.0]), torch.tensor([0.0]), 11)
    r = form_image(torch.full((1, 1, 128, 128), 0.5), m, motion_psf=psf, sources=("photon",), generator=_gen(), rng=rng)
    n = r.image[0, 0] - 0.5
    corr_h = (n[:, 1:] * n[:, :-1]).mean() / n.var()
    corr_v = (n[1:, :] * n[:-1, :]).mean() / n.var()
    assert corr_h > 0.7 and abs(corr_v) < 0.1
    # the analytic PN label accounts for the averaging: √Σh² of the kernel
    assert r.sigma_dn[0, 0].item() == pytest.approx(r.sigma_expected_dn[0, 0].item(), rel=0.1)


def test_quantize_gives_whole_dn():
    m = CameraMetadata.preset("ICX285", gain_db=12.0)
    r = form_image(torch.full((1, 1, 16, 16), 0.3), m, generator=_gen(), quantize=True)
    dn = r.image * 255
    assert torch.allclose(dn, dn.round(), atol=1e-4)


def test_gradient_flows_through_blur_and_noise(rng):
    m = CameraMetadata.preset("ICX285", gain_db=6.0)
    x = torch.full((1, 1, 16, 16), 0.5, dtype=torch.float64, requires_grad=True)
    psf = defocus_psf(torch.tensor([3.0], dtype=torch.float64), 5)
    y = form_image(x, m, defocus_psf=psf, generator=_gen(), rng=rng).image
    y.sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_apply_psf_gradcheck_and_delta():
    x = torch.rand(2, 1, 9, 9, dtype=torch.float64, requires_grad=True)
    psf = defocus_psf(torch.tensor([2.5, 4.0], dtype=torch.float64), 5)
    assert torch.autograd.gradcheck(lambda t: apply_psf(t, psf), (x,))
    delta = torch.ones(2, 1, 1, dtype=torch.float64)
    assert torch.equal(apply_psf(x, delta), x)


@pytest.mark.parametrize("channels", [1, 2])
@pytest.mark.parametrize("batch", [1, 5, 40])
def test_apply_psf_support_groups_equal_the_full_kernel(batch, channels):
    """Cropping every kernel to its support and convolving in groups gives the full k×k convolution."""
    g = torch.Generator().manual_seed(11)
    x = torch.rand(batch, channels, 40, 36, generator=g, dtype=torch.float64)
    size = torch.rand(batch, generator=g, dtype=torch.float64) * 20 + 0.5
    angle = torch.rand(batch, generator=g, dtype=torch.float64) * 180
    for psf in (defocus_psf(size, 23), linear_motion_psf(size, angle, 23)):
        grouped, full = apply_psf(x, psf), apply_psf(x, psf, group_by_support=False)
        assert torch.allclose(grouped, full, rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype,tol", [(torch.float16, 2e-3), (torch.bfloat16, 1.6e-2), (torch.float64, 1e-6)])
def test_apply_psf_grouped_in_every_dtype_and_batch_256(dtype, tol):
    g = torch.Generator().manual_seed(5)
    x = torch.rand(256, 1, 24, 24, generator=g)
    psf = defocus_psf(torch.rand(256, generator=g) * 9 + 1, 11)
    ref = apply_psf(x, psf)
    y = apply_psf(x.to(dtype), psf)
    assert y.dtype == dtype and y.shape == x.shape and bool(torch.isfinite(y).all())
    assert (y.float() - ref).abs().max() < tol


def test_support_radii_and_group_plan():
    psf = linear_motion_psf(torch.tensor([9.0, 9.0, 1.0, 15.0]), torch.tensor([0.0, 90.0, 0.0, 45.0]), 17)
    r = kernel_support_radii(psf)
    assert r[0, 0] <= 1 and r[0, 1] >= 4 and r[1, 1] <= 1 and r[1, 0] >= 4 and r[2].tolist() == [0, 0]
    assert r[3, 0] == r[3, 1] >= 5
    radii = kernel_support_radii(defocus_psf(torch.linspace(1, 21, 64), 23))
    groups = plan_support_groups(radii, channels=1, pixels=192 * 192)
    idx = torch.cat([i for i, _, _ in groups])
    assert sorted(idx.tolist()) == list(range(64))  # every sample exactly once
    for i, ry, rx in groups:
        assert len(i) >= 16 and int(radii[i, 0].max()) == ry and int(radii[i, 1].max()) == rx
    assert len(groups) > 1  # 1–21 px disks are worth splitting at this size
    with pytest.raises(ValueError, match=r"radii must have shape \(B, 2\)"):
        plan_support_groups(radii[:, :1])
    with pytest.raises(ValueError, match="channels = 0"):
        plan_support_groups(radii, channels=0)


def test_apply_psf_grouped_gradcheck(monkeypatch):
    monkeypatch.setattr(image_formation, "_CALL_OVERHEAD_MACS", 0.0)  # split even tiny images into groups
    g = torch.Generator().manual_seed(3)
    x = torch.rand(32, 1, 6, 6, dtype=torch.float64, generator=g).requires_grad_()
    psf = defocus_psf(torch.cat([torch.full((16,), 1.5), torch.full((16,), 4.5)]).double(), 5)
    assert len(plan_support_groups(kernel_support_radii(psf), 1, 36)) == 2
    assert torch.autograd.gradcheck(lambda t: apply_psf(t, psf), (x,))


def test_large_kernel_on_small_image_uses_replicate_padding():
    psf = defocus_psf(torch.tensor([39.0]), 41)
    y = apply_psf(torch.full((1, 1, 16, 16), 0.7), psf)
    assert torch.allclose(y, torch.full_like(y, 0.7), atol=1e-5)


@pytest.mark.parametrize(
    "bad,exc,match",
    [
        (torch.full((1, 1, 8, 8), float("nan")), ValueError, "finite"),
        (torch.zeros(8, 8), ValueError, "B×C×H×W"),
        (torch.zeros(1, 1, 8, 8, dtype=torch.uint8), TypeError, "floating"),
        (torch.full((1, 1, 8, 8), 2.0), ValueError, r"\[0, 1\]"),
        ([[0.5]], TypeError, "torch.Tensor"),
    ],
)
def test_bad_input_errors(bad, exc, match):
    with pytest.raises(exc, match=match):
        form_image(bad, CameraMetadata.preset("ICX285"))


def test_bad_sources_and_missing_metadata():
    x = torch.zeros(1, 1, 8, 8)
    with pytest.raises(ValueError, match="unknown noise source"):
        form_image(x, CameraMetadata.preset("ICX285"), sources=("thermal",))
    with pytest.raises(ValueError, match="metadata"):
        form_image(x, None)
    with pytest.raises(ValueError, match="batch"):
        form_image(torch.zeros(3, 1, 8, 8), CameraMetadata.sample(2))


@pytest.mark.parametrize("lam", [0.0, 0.4, 5.0, 37.0, 640.0, 5000.0])
def test_poisson_per_sample_rate_mean_variance_and_fit(lam, rng):
    import numpy as np
    from scipy import stats

    from camhealth.physics.image_formation import sample_poisson_per_sample

    x = sample_poisson_per_sample(torch.tensor([lam, 1.0]), (2, 1, 200, 200), _gen(11), rng=rng)
    assert x.shape == (2, 1, 200, 200) and x.dtype == torch.float32
    v = x[0].flatten().double()
    tol = 5 * (lam / v.numel()) ** 0.5 + 1e-9
    assert abs(float(v.mean()) - lam) < tol and abs(float(v.var()) - lam) < 0.05 * lam + 1e-9
    if 0 < lam < 1000:
        assert torch.equal(v, v.round())
        ks = np.arange(0, int(lam + 8 * lam**0.5 + 10))
        obs = np.array([(v.numpy() == k).sum() for k in ks])
        exp = stats.poisson.pmf(ks, lam) * v.numel()
        keep = exp > 5
        chi2 = ((obs[keep] - exp[keep]) ** 2 / exp[keep]).sum()
        assert stats.chi2.sf(chi2, keep.sum() - 1) > 1e-3


def test_poisson_per_sample_rate_rejects_bad_rates():
    from camhealth.physics.image_formation import sample_poisson_per_sample

    with pytest.raises(ValueError, match="rate"):
        sample_poisson_per_sample(torch.tensor([1.0]), (2, 4))
    with pytest.raises(ValueError, match=">= 0"):
        sample_poisson_per_sample(torch.tensor([-1.0, float("nan")]), (2, 4))


def test_counter_photon_and_dark_noise_are_the_centred_draws_of_the_samplers():
    """The fused noise passes of rng='counter' equal (draw − λ)·unit of the public samplers with the same keys."""
    from camhealth.physics.image_formation import (
        _dark_noise_counter, _photon_noise_counter, sample_poisson, sample_poisson_per_sample,
    )

    x = torch.rand(3, 1, 40, 40, generator=_gen(1)) * torch.tensor([1.0, 0.01, 0.3]).view(3, 1, 1, 1)
    to_int = torch.tensor([1e-3, 2e-4, 5e-2]).view(3, 1, 1, 1)  # rates up to 1000, 50 and 6 e⁻ (all regimes)
    noise = _photon_noise_counter(x, to_int, _gen(5), 1e3)
    electrons = x / to_int
    ref = (sample_poisson(electrons, _gen(5), rng="counter") - electrons) * to_int
    assert torch.allclose(noise, ref, atol=1e-6)
    dark = torch.tensor([0.7, 40.0, 2500.0], dtype=torch.float64)
    dn = _dark_noise_counter(dark, to_int, (3, 1, 40, 40), _gen(6), 1e3, torch.float32)
    assert dn.shape == (3, 1, 40, 40)
    rows = dn.flatten(1) / to_int.view(3, 1) + dark.float()[:, None]  # back to electron counts
    assert torch.allclose(rows[:2], rows[:2].round(), atol=1e-3)  # exact (integer) draws below exact_below
    big = _dark_noise_counter(dark[1:], to_int[1:], (2, 1, 40, 40), _gen(6), 1e3, torch.float32)
    ref = sample_poisson_per_sample(dark[1:], (2, 1, 40, 40), _gen(6), rng="counter") - dark[1:].float().view(2, 1, 1, 1)
    assert torch.allclose(big, ref * to_int[1:], atol=1e-4)


@pytest.mark.parametrize(
    "fields",
    [
        dict(temperature_c=0.0, gain_db=0.0, exposure_s=0.001),  # cold, no gain: tiny dark current
        dict(temperature_c=80.0, gain_db=24.0, full_well_e=2000.0, exposure_s=0.2),  # hot, high gain, small well
        dict(temperature_c=80.0, gain_db=0.0, exposure_s=0.2),  # dark current near exact_below
    ],
)
def test_extreme_metadata_labels_match_physics_for_both_rngs(fields, rng):
    m = CameraMetadata.preset("EV76C661", batch_size=2, **fields)
    x = torch.full((2, 1, 96, 96), 0.3)
    r = form_image(x, m, generator=_gen(4), rng=rng)
    assert torch.isfinite(r.image).all() and torch.isfinite(r.sigma_dn).all()
    unclipped = r.clipped_fraction < 0.01
    if bool(unclipped.any()):  # without clipping each realised σ is its analytic expectation (± sampling)
        got, want = r.sigma_dn[unclipped], r.sigma_expected_dn[unclipped]
        assert torch.allclose(got, want, rtol=0.05, atol=0.02)
    else:  # clipping only shrinks the realised noise
        assert torch.all(r.sigma_dn <= r.sigma_expected_dn * 1.05 + 0.02)


@pytest.mark.parametrize("lam", [0.0, 0.07, 3.0, 9.99, 37.0, 640.0, 999.0])
def test_counter_per_sample_draws_are_the_exact_inverse_cdf_at_their_normal(lam):
    """rng='counter': a per-sample-rate draw is min{k : F(k) ≥ Φ(z)} for the field's own normal z (SciPy's ppf),
    via the z-space table of poisson_z_table; above exact_below it is λ + √λ·z."""
    import numpy as np
    from scipy import special, stats

    from camhealth.physics.counter_rng import counter_keys, counter_normal
    from camhealth.physics.image_formation import sample_poisson_per_sample

    shape = (2, 150 * 150)
    x = sample_poisson_per_sample(torch.tensor([lam, 2500.0]), shape, _gen(21), rng="counter")
    z = counter_normal(shape, counter_keys(_gen(21)), torch.float32).double().numpy()
    ref = stats.poisson.ppf(special.ndtr(z[0]), lam) if lam > 0 else np.zeros_like(z[0])
    off = np.abs(x[0].double().numpy() - ref)
    assert off.max() <= 1.0 and (off > 0).mean() <= 1e-4  # z recomputed outside the kernel: float rounding only
    assert np.allclose(x[1].double().numpy(), 2500.0 + 50.0 * z[1], atol=2e-3)  # normal approximation


def test_poisson_z_table_cells_and_bounds():
    """Every cell holds at most one quantile boundary (cells doubled for large rates); bases are monotone and
    start at the count whose boundary lies below z = −6; λ = 0 gives a table of zeros."""
    import numpy as np
    from scipy import special, stats

    from camhealth.physics.image_formation import poisson_z_table

    t = poisson_z_table(torch.tensor([0.0, 0.5, 40.0, 999.0], dtype=torch.float64))
    assert t.shape == (4, 1024) and t.dtype == torch.float64
    assert torch.equal(t[0], torch.full_like(t[0], 0.75))  # base 0, no boundary (s = 1.5)
    base = t.floor()
    assert bool((base[:, 1:] >= base[:, :-1]).all())
    assert int(base[3, 0]) == int(stats.poisson.ppf(special.ndtr(-6.0), 999.0))  # the quantile at z = −6
    big = poisson_z_table(torch.tensor([20_000.0], dtype=torch.float64), exact_below=1e5)
    assert big.shape[1] >= 2048  # boundaries ≈ 1/√λ = 0.007 apart: finer cells
    s = (big - big.floor()) * 2
    assert bool(((s < 1) | (s == 1.5)).all())
    # the table's draw at a few z equals the exact quantile
    z = np.array([-5.5, -1.0, 0.0, 0.3, 2.0, 5.5])
    cells = big.shape[1]
    pos = (z + 6.0) * cells / 12.0
    cell = np.floor(pos).astype(int)
    v = big[0, cell].numpy()
    draw = np.floor(v) + ((pos - cell) > (v - np.floor(v)) * 2)
    assert np.array_equal(draw, stats.poisson.ppf(special.ndtr(z), 20_000.0))


def test_counter_noise_drawn_in_the_clipping_pass_equals_the_separate_fields():
    """rng='counter' without gradient draws dark and readout noise inside the clipping pass; with gradient the fields
    are realised separately: same keys, same image and labels (to float rounding)."""
    from camhealth.physics.motion_psf import linear_motion_psf

    x = torch.rand(4, 1, 48, 48, generator=_gen(2)) * 0.98 + 0.01
    x[1] = 1.0  # saturated: clipping attribution
    meta = CameraMetadata.sample(4, generator=_gen(3))
    dpsf = defocus_psf(torch.tensor([1.0, 3.0, 5.0, 0.0]), 7)
    mpsf = linear_motion_psf(torch.tensor([3.0, 1.0, 7.0, 2.0]), torch.tensor([0.0, 30.0, 90.0, 45.0]), 9)
    fused = form_image(x, meta, dpsf, mpsf, generator=_gen(7), rng="counter")
    xg = x.clone().requires_grad_(True)
    separate = form_image(xg, meta, dpsf, mpsf, generator=_gen(7), rng="counter")
    assert torch.allclose(fused.image, separate.image.detach(), atol=1e-6)
    assert torch.allclose(fused.sigma_dn, separate.sigma_dn, rtol=1e-4, atol=1e-5)
    assert torch.allclose(fused.sigma_total_dn, separate.sigma_total_dn, rtol=1e-4, atol=1e-5)
    assert torch.equal(fused.clipped_fraction, separate.clipped_fraction)
    assert bool((fused.sigma_dn > 0).all())


def test_poisson_z_table_rejects_rates_beyond_its_resolution():
    from camhealth.physics.image_formation import poisson_z_table

    with pytest.raises(ValueError, match="exact_below"):
        poisson_z_table(torch.tensor([1e9], dtype=torch.float64), exact_below=1e10)


@pytest.mark.parametrize("bad", [[-1.0], [float("nan")], [float("inf")]])
def test_poisson_z_table_rejects_bad_rates(bad):
    from camhealth.physics.image_formation import poisson_z_table

    with pytest.raises(ValueError, match=">= 0"):
        poisson_z_table(torch.tensor(bad, dtype=torch.float64))


@pytest.mark.parametrize("k", [5, 41])  # the direct path (filter2d, behaviour="conv") and the FFT path
def test_apply_psf_is_true_convolution_with_asymmetric_kernels(k):
    """An asymmetric kernel is convolved, not correlated: the reference flips it for conv2d (a correlation);
    the FFT path also equals Kornia's fft_conv(behaviour="conv")."""
    import kornia

    g = torch.Generator().manual_seed(7)
    x = torch.rand(3, 1, 50, 46, generator=g, dtype=torch.float64)
    psf = torch.rand(3, k, k, generator=g, dtype=torch.float64)
    psf[:, : k // 2] = 0.0  # support only below and on the centre row: a correlation would shift the other way
    psf = psf / psf.sum((-1, -2), keepdim=True)
    y = apply_psf(x, psf, group_by_support=False)
    p = k // 2
    padded = torch.nn.functional.pad(x, (p, p, p, p), mode="reflect")
    ref = torch.cat([torch.nn.functional.conv2d(padded[i : i + 1], psf[i].flip(-1, -2)[None, None]) for i in range(3)])
    assert torch.allclose(y, ref, rtol=0, atol=1e-10)
    if k >= image_formation.FFT_MIN_KERNEL:
        lib = kornia.filters.fft_conv(x, psf, border_type="reflect", behaviour="conv")
        assert torch.allclose(image_formation._fft_convolve(x, psf, "reflect"), lib, rtol=0, atol=1e-10)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_poisson_per_sample_refuses_half_precision_counts(dtype, rng):
    """float16 holds no count above 65 504 (a 7e4 e⁻ rate was all inf) and bfloat16 rounds counts above 256."""
    with pytest.raises(TypeError, match="float32 or torch.float64 .*got torch.(float16|bfloat16)"):
        image_formation.sample_poisson_per_sample(torch.tensor([7e4]), (1, 100), _gen(), dtype=dtype, rng=rng)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sources_given_as_one_name_are_that_source(dtype, rng):
    m = CameraMetadata.preset("ICX285", batch_size=2, gain_db=12.0)
    x = torch.full((2, 1, 16, 16), 0.4, dtype=dtype)
    for name in ("photon", "dark", "readout"):
        one = form_image(x, m, sources=name, generator=_gen(3), rng=rng)
        ref = form_image(x, m, sources=(name,), generator=_gen(3), rng=rng)
        assert torch.equal(one.image, ref.image) and torch.equal(one.sigma_dn, ref.sigma_dn)


@pytest.mark.parametrize("bad,shown", [(float("nan"), "nan"), (float("inf"), "inf"), (-3.0, "-3")])
@pytest.mark.parametrize("others", [[50.0, 5000.0], [20.0, 30.0], [0.5, 2.0]])  # mid, expansion-only and small regimes
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sample_poisson_refuses_nan_infinite_and_negative_rates(bad, shown, others, dtype, rng):
    rate = torch.tensor([[others[0], bad, others[1]]], dtype=dtype)
    with pytest.raises(ValueError, match=rf"Poisson rate\[0, 1\] = {shown} is out of the allowed range \[0, inf\)"):
        image_formation.sample_poisson(rate, _gen(), rng=rng)


def _psf_cases():
    ok = defocus_psf(torch.tensor([3.0, 5.0]), 7)
    unnormalised = ok.clone()
    unnormalised[1] *= 9.0
    negative = ok.clone()
    negative[1, 0, 0] = -0.1
    nan = ok.clone()
    nan[1, 3, 3] = float("nan")
    return [
        (unnormalised, ValueError, r"kernel 1 sums to 9; a blur kernel must sum to 1"),
        (negative, ValueError, r"must be non-negative .* kernel 1 has -0.1 at row 0, column 0"),
        (nan, ValueError, r"must be finite"),
        (torch.ones(2, 3, 3, dtype=torch.int64), TypeError, r"must be a floating tensor .* got dtype torch.int64$"),
        (ok[:, :, :6], ValueError, r"must have shape \(B, k, k\)"),
    ]


@pytest.mark.parametrize("case", range(5))
@pytest.mark.parametrize("arg", ["defocus_psf", "motion_psf"])
def test_form_image_refuses_kernels_that_are_not_normalised_blurs(case, arg):
    """A kernel summing to 9 brightened the scene ×9 (and clipping hid it), a negative one darkened it, an integer
    one failed later with a misleading message about the image: each is refused, naming the argument."""
    psf, exc, match = _psf_cases()[case]
    x = torch.full((2, 1, 16, 16), 0.5)
    with pytest.raises(exc, match=f"^{arg}.*{match}" if exc is ValueError else f"^{arg} {match}"):
        form_image(x, None, sources=(), **{arg: psf})


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_form_image_accepts_normalised_kernels_in_every_dtype(dtype):
    x = torch.full((3, 1, 16, 16), 0.5)
    d = defocus_psf(torch.tensor([1.0, 4.5, 11.0]), 13).to(dtype)
    mo = linear_motion_psf(torch.tensor([2.0, 7.5, 11.0]), torch.tensor([0.0, 30.0, 135.0]), 13).to(dtype)
    out = form_image(x, None, defocus_psf=d, motion_psf=mo, sources=())
    assert torch.allclose(out.image.mean((1, 2, 3)), torch.full((3,), 0.5), atol=5e-3)


def test_apply_psf_refuses_a_kernel_with_nan():
    psf = torch.full((1, 3, 3), 1 / 9)
    psf[0, 1, 1] = float("nan")
    with pytest.raises(ValueError, match="psf must be finite"):
        apply_psf(torch.rand(1, 1, 8, 8), psf)


@pytest.mark.parametrize("k, size", [(1, 8), (5, 8), (7, (6, 9)), (17, 8), (15, (5, 12))])
def test_psf_noise_gain_is_the_mean_squared_row_of_the_blur_operator(k, size):
    """apply_psf is linear: A (N×N) maps a white-noise field to the blurred one, whose variance at pixel p is
    σ²·Σ_i A[p, i]². The padding lets several taps read one pixel near the borders (reflect, or replicate where the
    kernel outgrows the image), so the mean over p exceeds Σ h². psf_noise_gain_sq against A built from impulses."""
    from camhealth.physics.image_formation import psf_noise_gain_sq

    h, w = (size, size) if isinstance(size, int) else size
    g = torch.Generator().manual_seed(k)
    psf = torch.rand(3, k, k, generator=g, dtype=torch.float64)
    psf = psf / psf.sum((-1, -2), keepdim=True)
    impulses = torch.eye(h * w, dtype=torch.float64).view(h * w, 1, h, w)
    for i in range(3):
        a = apply_psf(impulses, psf[i : i + 1]).view(h * w, h * w)  # column j: the response to impulse j
        want = a.square().sum(1).mean()  # Σ_j over impulses = Σ over A's columns; mean over output pixels
        assert psf_noise_gain_sq(psf[i : i + 1], h, w).item() == pytest.approx(want.item(), rel=1e-12)
    if k > 1:
        assert (psf_noise_gain_sq(psf, h, w) > psf.square().sum((-1, -2))).all()  # the folded taps add


def test_expected_photon_sigma_after_a_motion_blur_as_long_as_the_patch():
    """A 41-px motion blur of a 32-px flat patch: the padding reads the photon noise several times near the borders,
    and the analytic σ_PN label (Σ h² alone: 1.22 DN against the image's 1.56) now counts it (within 2 %)."""
    from camhealth.physics.motion_psf import linear_motion_psf

    meta = CameraMetadata.preset("EV76C661", gain_db=24.0)
    b, k = 256, 41
    psf = linear_motion_psf(torch.full((1,), 41.0), torch.zeros(1), k).expand(b, k, k)
    f = form_image(torch.full((b, 1, 32, 32), 0.5), meta, motion_psf=psf, sources=("photon",),
                   generator=torch.Generator().manual_seed(1))
    rms = ((f.image - f.blurred) * 255).square().mean().sqrt()  # the noise as drawn, about its zero mean
    assert float(f.sigma_expected_dn[0, 0]) == pytest.approx(float(rms), rel=0.02)
    from camhealth.physics.photon_shot_noise import photon_shot_sigma_patch_dn

    independent_taps = photon_shot_sigma_patch_dn(torch.full((1, 1, 32, 32), 0.5), meta) * psf[0].square().sum().sqrt()
    assert float(f.sigma_expected_dn[0, 0]) > 1.2 * float(independent_taps)  # what the label read before
