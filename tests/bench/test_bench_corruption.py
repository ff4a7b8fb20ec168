"""``python -m camhealth.bench corruption``: CLI end to end, the NumPy/SciPy reference loop's physics, and
the exact Poisson sampler the benchmarked pipeline uses. No wall-clock assertions."""

import subprocess
import sys

import numpy as np
import pytest
import torch
from scipy import special, stats

from camhealth.bench import BENCHMARKS, BenchResult, Row, format_table, timing_stats
from camhealth.bench import reference_loop as rl
from camhealth.bench.__main__ import main
from camhealth.physics.defocus_psf import defocus_psf
from camhealth.physics.image_formation import _poisson_quantile_expansion, apply_psf, form_image, sample_poisson
from camhealth.physics.metadata import CameraMetadata
from camhealth.physics.motion_psf import linear_motion_psf
from camhealth.physics.readout_noise import source_follower_sigma_e

TINY = ["corruption", "--batch", "2", "--size", "48", "--repeats", "1", "--warmup", "0", "--loop-images", "1",
        "--loop-repeats", "1", "--sf-frequencies", "500"]  # fmt: skip
ROWS = [
    "camhealth RandomDefocusBlur",
    "camhealth RandomMotionBlur linear",
    "camhealth RandomMotionBlur non-linear",
    "camhealth RandomSensorNoise",
    "camhealth CameraCorruption",
    "camhealth RandomSensorNoise, rng='counter'",
    "camhealth CameraCorruption, rng='counter'",
    "kornia RandomMotionBlur",
    "kornia RandomGaussianNoise",
    "NumPy/SciPy per-image loop",
    "σ_SF vectorised",
    "σ_SF Python loop",
]


# ------------------------------------------------------------------------------------------------ CLI
def test_cli_prints_every_row_and_appends_markdown(capsys, tmp_path):
    out = tmp_path / "bench.md"
    assert main(TINY + ["--out", str(out)]) == 0
    text = capsys.readouterr().out
    for name in ROWS:
        assert name in text
    assert "× kornia RandomMotionBlur" in text and "machine:" in text
    assert "timed on 1 image(s)" in text  # the loop rows say they are scaled
    assert "target ≤ 2×" in text and "target ≥ 20×" in text
    md = out.read_text()
    assert md.count("| camhealth ") == 7 and "|---|---:|" in md
    assert "with rng='counter':" in text and "torch.compile of its kernels" in text
    main(TINY + ["--out", str(out), "--markdown"])  # appends, keeps the first table
    assert out.read_text().count("### Corruption benchmark") == 2


def test_cli_as_module_with_threads():
    cmd = [sys.executable, "-m", "camhealth.bench"] + TINY + ["--threads", "1", "--markdown"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "| kornia RandomMotionBlur |" in res.stdout and "(1 threads)" in res.stdout
    assert "freed memory kept for reuse" in res.stdout and "minor page faults per CameraCorruption call" in res.stdout
    res = subprocess.run(cmd + ["--default-malloc"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "allocator: glibc defaults" in res.stdout


def test_cli_rejects_unknown_benchmark_and_bad_options(capsys):
    with pytest.raises(SystemExit):
        main(["nonsense"])
    with pytest.raises(SystemExit):
        main(["corruption", "--batch", "0"])
    assert "corruption" in BENCHMARKS


def test_table_statistics_and_ratio():
    assert timing_stats([5.0, 1.0, 3.0, 2.0, 4.0]) == (3.0, 2.0, 4.0)
    res = BenchResult("t", [Row("a", [2.0, 2.0]), Row("base", [4.0])], baseline="base", summary=["s"])
    text = format_table(res)
    assert res.row("a").ratio == pytest.approx(0.5) and "0.50" in text
    md = format_table(res, markdown=True)
    assert "| row | ms/batch (median) |" in md and "|---|---:|" in md and "- s" in md


# ---------------------------------------------------------------------------------- reference physics
@pytest.mark.parametrize("d", [0.0, 0.8, 1.0, 2.5, 7.3, 21.0])
def test_reference_disk_psf_equals_camhealth(d):
    ref = rl.disk_psf_loop(d, 23)
    ours = defocus_psf(torch.tensor([d], dtype=torch.float64), 23)[0].numpy()
    np.testing.assert_allclose(ref, ours, atol=1e-12)


@pytest.mark.parametrize("length,angle", [(0.0, 0.0), (1.0, 30.0), (5.5, 0.0), (9.0, 45.0), (21.0, 137.0), (20.0, 90.0)])
def test_reference_line_psf_equals_camhealth(length, angle):
    ref = rl.linear_motion_psf_loop(length, angle, 25)
    ours = linear_motion_psf(torch.tensor([length], dtype=torch.float64), torch.tensor([angle], dtype=torch.float64), 25)
    np.testing.assert_allclose(ref, ours[0].numpy(), atol=1e-12)


def test_reference_convolution_equals_apply_psf():
    x = torch.rand(1, 1, 40, 40, dtype=torch.float64)
    for psf in (defocus_psf(torch.tensor([7.0], dtype=torch.float64), 9), linear_motion_psf(
            torch.tensor([11.0], dtype=torch.float64), torch.tensor([30.0], dtype=torch.float64), 45)):  # fmt: skip
        ours = apply_psf(x, psf)[0, 0].numpy()  # 45 px: the FFT path
        np.testing.assert_allclose(rl._convolve(x[0, 0].numpy(), psf[0].numpy()), ours, atol=1e-9)


def test_reference_source_follower_loop_agrees_within_2_percent():
    meta = CameraMetadata.cat([CameraMetadata.preset("ICX285"), CameraMetadata.preset("EV76C661"),
                               CameraMetadata.sample(6, torch.Generator().manual_seed(3))]).to(dtype=torch.float64)  # fmt: skip
    ours = source_follower_sigma_e(meta).numpy()
    loop = np.array([
        rl.source_follower_sigma_e_loop(meta.white_noise_v_per_rthz[i].item(), meta.pixel_clock_hz[i].item(),
                                        meta.sense_node_gain_v_per_e[i].item(), meta.is_cmos[i].item() > 0.5)
        for i in range(meta.batch_size)
    ])  # fmt: skip
    np.testing.assert_allclose(loop, ours, rtol=0.02)
    assert loop[0] == pytest.approx(12.5, rel=0.02) and loop[1] == pytest.approx(24.0, rel=0.02)  # measured read noise


def test_reference_noise_sigma_matches_torch_pipeline():
    """Same metadata, same PSF parameters, flat gray (no clipping): realised σ per source agrees with the
    torch chain within statistical tolerance (σ from 96² px has ~1 % relative spread)."""
    meta = CameraMetadata.preset("EV76C661", batch_size=3, gain_db=[6.0, 12.0, 18.0], temperature_c=[40.0, 60.0, 75.0],
                                 exposure_s=[0.05, 0.1, 0.19], reset_factor=0.5)  # fmt: skip
    x = torch.full((3, 1, 96, 96), 0.4, dtype=torch.float64)
    d, length, angle = [3.0, 7.0, 11.0], [5.0, 9.0, 15.0], [0.0, 45.0, 120.0]
    dpsf = defocus_psf(torch.tensor(d, dtype=torch.float64), 13)
    mpsf = linear_motion_psf(torch.tensor(length, dtype=torch.float64), torch.tensor(angle, dtype=torch.float64), 17)
    ours = form_image(x, meta.to(dtype=torch.float64), defocus_psf=dpsf, motion_psf=mpsf, generator=torch.Generator().manual_seed(1))
    assert torch.all(ours.clipped_fraction == 0)
    ref = rl.corrupt_batch(x.numpy(), {n: getattr(meta, n).double().numpy() for n in rl.FULL_FIELDS}, seed=2,
                           diameter_px=d, defocus_kernel=13, length_px=length, angle_deg=angle, motion_kernel=17)  # fmt: skip
    np.testing.assert_allclose(ref.sigma_dn, ours.sigma_dn.numpy(), rtol=0.06)
    np.testing.assert_allclose(ref.sigma_dn, ours.sigma_expected_dn.numpy(), rtol=0.06)
    np.testing.assert_allclose(ref.sigma_total_dn, ours.sigma_total_dn.numpy(), rtol=0.06)
    # patch means of two independent noise realisations: 4 standard errors of their difference, √2·σ/√N
    se = np.sqrt(2.0) * ours.sigma_total_dn.numpy() / 255.0 / 96.0
    assert np.all(np.abs(ref.image.mean(axis=(1, 2)) - ours.image.mean(dim=(1, 2, 3)).numpy()) < 4 * se + 1e-4)


def test_params_from_torch_redoes_a_camera_call():
    from camhealth.augment import CameraCorruption

    cam = CameraCorruption()
    x = torch.rand(2, 1, 32, 32)
    cam(x)
    kw = rl.params_from_torch(cam._params, cam._defocus_ks, cam._motion_ks)
    assert set(kw) == {"meta", "diameter_px", "defocus_kernel", "length_px", "angle_deg", "motion_kernel"}
    res = rl.corrupt_batch(x.numpy(), **kw)
    assert res.image.shape == (2, 32, 32) and np.isfinite(res.sigma_dn).all()
    assert 0.0 <= res.image.min() and res.image.max() <= 1.0


# ------------------------------------------------------------------- exact Poisson sampler of the chain
def _quantile_expansion_errors(lams):
    """Ratio |y − exact boundary| / envelope over all quantile boundaries with 1e-10 < F < 1 − 1e-10."""
    worst = 0.0
    for lam in lams:
        ks = np.arange(max(0, int(lam - 14 * np.sqrt(lam) - 30)), int(lam + 14 * np.sqrt(lam) + 30))
        cdf = stats.poisson.cdf(ks, lam)
        ok = (cdf > 1e-10) & (cdf < 1 - 1e-10)
        z = torch.from_numpy(stats.norm.ppf(cdf[ok]))
        y, margin = _poisson_quantile_expansion(torch.full_like(z, lam), z.clone())
        keep = (margin > 0).numpy()  # |z| > 5 is always settled exactly
        err = np.abs(y.numpy() - (ks[ok] + 1))[keep]
        worst = max(worst, float((err / (0.5 - margin.numpy()[keep])).max(initial=0.0)))
    return worst


def test_poisson_expansion_envelope_holds_on_a_dense_grid():
    assert _quantile_expansion_errors(np.geomspace(10.0, 1e4, 600)) < 0.5  # ≥ 2× safety margin


def test_poisson_sampler_is_exact_inversion():
    """For the same normal deviates z, sample_poisson returns exactly the Poisson quantile at Φ(z)."""
    lam = torch.cat([torch.full((20_000,), v) for v in (10.0, 12.7, 33.0, 150.0, 640.0, 999.0)])
    z = torch.randn(lam.shape, generator=torch.Generator().manual_seed(5))
    k = sample_poisson(lam, torch.Generator().manual_seed(5)).numpy()
    u = special.ndtr(z.double().numpy())
    np.testing.assert_array_equal(k, stats.poisson.ppf(u, lam.double().numpy()))


def test_poisson_sampler_counter_rng_is_exact_inversion():
    """With counter-based normals too, the draw is the Poisson quantile at Φ(z) of the field's own z."""
    from camhealth.physics.counter_rng import counter_keys, counter_normal_at

    lam = torch.cat([torch.full((20_000,), v) for v in (10.0, 12.7, 33.0, 150.0, 640.0, 999.0)])
    k = sample_poisson(lam, torch.Generator().manual_seed(5), rng="counter").numpy()
    z = counter_normal_at(torch.arange(lam.numel()), counter_keys(torch.Generator().manual_seed(5)))
    want = stats.poisson.ppf(special.ndtr(z.double().numpy()), lam.double().numpy())
    # z recomputed here may differ from the sampler's own by float rounding of log/cos: a draw can then sit on
    # the other side of a quantile boundary (probability ~1e-7 each), never further
    diff = np.abs(k - want)
    assert diff.max() <= 1 and (diff > 0).mean() < 1e-4


@pytest.mark.parametrize("rng", ["torch", "counter"])
@pytest.mark.parametrize("lam", [0.3, 4.0, 10.0, 27.5, 400.0])
def test_poisson_sampler_goodness_of_fit(lam, rng):
    x = sample_poisson(torch.full((200_000,), lam), torch.Generator().manual_seed(7), rng=rng).numpy().astype(int)
    lo, hi = int(stats.poisson.ppf(1e-4, lam)), int(stats.poisson.ppf(1 - 1e-4, lam))
    obs = np.array([(x <= lo).sum()] + [(x == k).sum() for k in range(lo + 1, hi)] + [(x >= hi).sum()])
    pr = np.array([stats.poisson.cdf(lo, lam)] + [stats.poisson.pmf(k, lam) for k in range(lo + 1, hi)] + [stats.poisson.sf(hi - 1, lam)])
    assert stats.chisquare(obs, pr * obs.sum()).pvalue > 1e-3


def test_poisson_sampler_regimes_and_dtypes():
    g = torch.Generator().manual_seed(0)
    rate = torch.tensor([0.0, 3.0, 12.0, 500.0, 5e4] * 4000).reshape(4000, 5)
    x = sample_poisson(rate, g)
    assert x.shape == rate.shape and torch.all(x[:, 0] == 0)
    assert torch.all(x[:, :4] == x[:, :4].round())  # exact draws are integers; 5e4 uses N(λ, λ)
    np.testing.assert_allclose(x.mean(0).numpy(), rate[0].numpy(), rtol=0.02, atol=0.05)
    np.testing.assert_allclose(x.var(0).numpy(), rate[0].numpy(), rtol=0.08, atol=0.05)
    assert sample_poisson(torch.full((8,), 20.0, dtype=torch.float16), g).dtype == torch.float16
    assert sample_poisson(torch.full((8,), 20.0, dtype=torch.float64), g).dtype == torch.float64
    assert sample_poisson(torch.zeros(0), g).numel() == 0
    a = sample_poisson(rate, torch.Generator().manual_seed(3))
    assert torch.equal(a, sample_poisson(rate, torch.Generator().manual_seed(3)))


def test_library_reuse_comparison_checks_agreement_and_names_rows(capsys):
    """python -m camhealth.bench.library_reuse: each case's own code and library call agree before timing."""
    from camhealth.bench.library_reuse import compare, main

    rows = compare(["filter2d", "bias_std_rms"], threads=1, min_run_time=0.001)
    assert len(rows) == 6 and all(r["own_ms"] > 0 and r["library_ms"] > 0 and r["max_diff"] <= 1e-6 for r in rows)
    with pytest.raises(ValueError, match="unknown rows"):
        compare(["nope"])
    main(["--rows", "bias_std_rms", "--min-run-time", "0.001"])
    assert "| bias_std_rms: 2000 (library = camhealth.metrics) |" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["--threads", "0"])


@pytest.mark.parametrize("option,value", [("--sf-frequencies", "0"), ("--sf-frequencies", "-1"), ("--loop-images", "0"),
                                          ("--loop-images", "-3"), ("--loop-repeats", "0")])
def test_counts_below_one_are_refused_when_parsed(option, value, capsys, monkeypatch):
    """Exit status 2 naming the option before anything runs (--sf-frequencies 0 divided by zero after the whole run,
    -1 gave σ_SF = 0 for the "same chain" loop, --loop-images 0 silently became 1)."""
    from camhealth.bench import corruption

    monkeypatch.setattr(corruption, "run", lambda args: pytest.fail("the benchmark ran"))
    argv = [a for a in TINY if a != option]
    if option in TINY:
        del argv[TINY.index(option)]  # (its value, now at the option's place)
    with pytest.raises(SystemExit) as info:
        main(argv + [option, value])
    err = capsys.readouterr().err
    assert info.value.code == 2 and f"argument {option}: must be >= 1, got {value}" in err


def test_run_called_directly_refuses_counts_below_one():
    from types import SimpleNamespace

    from camhealth.bench.corruption import run

    args = SimpleNamespace(batch=2, size=32, repeats=1, warmup=0, seed=0, loop_images=1, loop_repeats=1, sf_frequencies=-1)
    with pytest.raises(ValueError, match="--sf-frequencies = -1 must be an integer ≥ 1"):
        run(args)
