"""`python -m camhealth.bench estimators`: the held-out noise set and its ξ protocol (no timing asserted)."""

from __future__ import annotations

import argparse

import torch

from camhealth.bench.estimators import add_arguments, held_out_noise
from camhealth.physics.metadata import FULL_FIELDS


def test_xi_fields_choose_which_metadata_the_altered_samples_change():
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--deadleaves", "20", "--per-image", "8", "--xi-fields", "gain_db"])
    data = held_out_noise(args)
    changed = data["meta_raw"] != data["meta_image_raw"]
    assert bool(data["altered"].any()) and torch.equal(changed.any(1), data["altered"])
    assert set(changed.any(0).nonzero().flatten().tolist()) == {FULL_FIELDS.index("gain_db")}
    default = held_out_noise(parser.parse_args(["--deadleaves", "20", "--per-image", "8"]))
    fields = (default["meta_raw"] != default["meta_image_raw"]).any(0).nonzero().flatten().tolist()
    assert len(fields) > 1 and set(fields) <= {FULL_FIELDS.index(f) for f in ("gain_db", "temperature_c", "white_noise_v_per_rthz")}


def test_split_floor_is_exact_without_signal_independent_alterations_and_grows_with_the_noise_level_error():
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    from camhealth.bench.estimators import split_floor

    gain_only = held_out_noise(parser.parse_args(["--deadleaves", "20", "--per-image", "8", "--xi-fields", "gain_db"]))
    rows = split_floor(gain_only, ("gain_db",), rel_errors=(0.0, 0.02, 0.05))
    assert rows[0]["rms_dcsn"] < 1e-4 and rows[0]["rms_rn"] < 1e-4  # a gain change keeps the split: no ambiguity
    assert 0 < rows[1]["rms_dcsn"] < rows[2]["rms_dcsn"] and 0 < rows[1]["rms_rn"] < rows[2]["rms_rn"]
    three = held_out_noise(parser.parse_args(["--deadleaves", "20", "--per-image", "8"]))
    exact = split_floor(three, ("gain_db", "temperature_c", "white_noise_v_per_rthz"), rel_errors=(0.0,))[0]
    assert exact["rms_dcsn"] + exact["rms_rn"] > 1e-3  # temperature vs white noise: a real ambiguity remains


def test_an_unknown_xi_field_is_refused_with_the_allowed_names(capsys):
    import pytest

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    with pytest.raises(SystemExit):
        parser.parse_args(["--xi-fields", "gain"])
    err = capsys.readouterr().err
    assert "'gain'" in err and "gain_db" in err and "white_noise_v_per_rthz" in err


def test_the_physics_first_estimator_beats_the_metadata_on_gain_altered_samples():
    """On the gain-only held-out set, where a wrong gain moves every source, ``noise_source_full``'s σ per source are
    closer to the labels than the metadata's closed form after clipping, and equal to it on the consistent samples
    it does not flag."""
    from camhealth import load_estimator
    from camhealth.bench.estimators import _meta, noise_accuracy
    from camhealth.estimators.noise_features import physics_prior_dn
    from lightning_modules.metrics import bias_std_rms

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    data = held_out_noise(parser.parse_args(["--deadleaves", "20", "--per-image", "8", "--xi-fields", "gain_db"]))
    est = load_estimator("noise_source_full")
    acc = noise_accuracy(est, data)
    assert acc["n"] == data["image"].shape[0]
    prior = physics_prior_dn(data["image"], _meta(data, slice(None)), clipping=True)[:, 4:7].double()
    for j, name in enumerate(("pn", "dcsn", "rn")):
        metadata_rms = bias_std_rms(prior[:, j], data["sigma"][:, j].double())[2].item()
        assert acc[f"rms_{name}"] < metadata_rms, name


def test_mtf_views_rows_use_the_averaged_flipped_estimates(tmp_path):
    """`--mtf-views 1 2`: the MTF accuracy of the second row is that of Estimator.predict(views=2)."""
    from camhealth import load_estimator
    from camhealth.bench.estimators import mtf_accuracy
    from camhealth.export import export_weights
    from lightning_modules import MTFEstimator
    from lightning_modules.metrics import amae_percent

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert parser.parse_args(["--mtf-views", "1", "2"]).mtf_views == [1, 2]
    assert parser.parse_args([]).mtf_views == [1]
    torch.manual_seed(0)
    est = load_estimator(export_weights(MTFEstimator(patch_size=32), tmp_path / "mtf.pt"))
    g = torch.Generator().manual_seed(0)
    data = {"image": torch.rand(6, 1, 32, 32, generator=g), "mtf": torch.rand(6, 16, generator=g), "family": torch.tensor([0, 1, 2, 0, 1, 2])}
    for views in (1, 2):
        acc = mtf_accuracy(est, data, views)
        expected = amae_percent(est.predict(data["image"], views=views)["mtf"].double(), data["mtf"].double())
        assert abs(acc["amae"] - expected.mean().item()) < 1e-9
    assert mtf_accuracy(est, data, 1)["amae"] != mtf_accuracy(est, data, 2)["amae"]


def test_round_robin_timing_calls_every_row_once_per_round():
    from camhealth.bench.estimators import _time_round_robin

    order: list[str] = []
    times = _time_round_robin([lambda: order.append("a"), lambda: order.append("b")], repeats=3, warmup=1)
    assert order == ["a", "b"] * 4  # one warm-up round, then three timed rounds, interleaved
    assert [len(t) for t in times] == [3, 3] and all(v >= 0 for t in times for v in t)


def test_run_reports_accuracy_and_time_for_each_model_and_precision(tmp_path):
    """End to end on the physics-first noise estimator and two tiny exported networks (noise-source, MTF): a row per
    model and precision, in the order of the models, each with its own held-out accuracy (no timing asserted)."""
    from camhealth.bench.estimators import run
    from camhealth.export import export_weights
    from lightning_modules import MTFEstimator, NoiseSourceEstimator

    torch.manual_seed(0)
    noise = export_weights(NoiseSourceEstimator(), tmp_path / "noise.pt")
    mtf = export_weights(MTFEstimator(), tmp_path / "mtf.pt")
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--models", "noise_source_full", "--checkpoint", str(noise), "--checkpoint", str(mtf),
                              "--deadleaves", "2", "--per-image", "1", "--no-reference"])
    args.batch, args.repeats, args.warmup = 4, 2, 0  # the options every benchmark shares (camhealth.bench.__main__)
    res = run(args)
    names = [r.name for r in res.rows]
    assert names == ["noise_source_full (noise_source, fp32)", "noise_source_full (noise_source, bf16)",
                     "noise (noise_source, fp32)", "noise (noise_source, bf16)", "mtf (mtf, fp32)", "mtf (mtf, bf16)"]
    assert all(len(r.times_ms) == 2 for r in res.rows)
    assert "total RMS" in res.rows[0].note and "total RMS" in res.rows[2].note and "AMAE" in res.rows[4].note
    assert any("closed form first, no network" in line for line in res.summary)
    assert "device cpu" in res.header[0]  # --device (default cpu): where load_estimator put the networks
