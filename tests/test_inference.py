"""`camhealth.load_estimator(...).predict`: input conventions, metadata handling, flags, precision."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from camhealth import load_estimator
from camhealth.export import export_weights
from camhealth.inference import assess_patches, shipped_models
from camhealth.physics.metadata import CameraMetadata
from lightning_modules import MTFEstimator, NoiseSourceEstimator


@pytest.fixture(scope="module")
def noise_est(tmp_path_factory):
    torch.manual_seed(0)
    m = NoiseSourceEstimator(patch_size=32)
    with torch.no_grad():
        for p in m.net.parameters():
            p.add_(0.01 * torch.randn_like(p))
    return load_estimator(export_weights(m, tmp_path_factory.mktemp("w") / "ns.pt"))


@pytest.fixture(scope="module")
def min_est(tmp_path_factory):
    m = NoiseSourceEstimator(patch_size=32, metadata_set="minimal", physics_prior=False)
    return load_estimator(export_weights(m, tmp_path_factory.mktemp("w") / "min.pt"))


def _patches(batch=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(batch, 1, 32, 32, generator=g) * 0.6 + 0.2


@pytest.mark.parametrize("batch", [1, 3])
def test_outputs_and_shapes(noise_est, batch):
    out = noise_est.predict(_patches(batch), "ICX285")
    assert out["sigma"].shape == (batch, 3) and out["xi"].shape == (batch,) and out["sigma_total"].shape == (batch,)
    assert out["assessable"].dtype == torch.bool and len(out["reason"]) == batch
    # the total head corrects √(Σ σ_s²) by a bounded factor exp(±5) (realised total after clipping)
    ratio = out["sigma_total"] / out["sigma"].pow(2).sum(1).sqrt()
    assert torch.isfinite(ratio).all() and (ratio > math.exp(-5.0)).all() and (ratio < math.exp(5.0)).all()


@pytest.mark.parametrize("total_branch", [False, True])
def test_total_is_quadrature_without_or_before_training_the_total_head(tmp_path, total_branch):
    torch.manual_seed(1)
    m = NoiseSourceEstimator(patch_size=32, total_branch=total_branch)
    keep = {id(p) for p in m.net.total_head[-1].parameters()} if total_branch else set()
    with torch.no_grad():  # perturb everything except the zero-initialised output layer of the total head
        for p in m.net.parameters():
            if id(p) not in keep:
                p.add_(0.01 * torch.randn_like(p))
    est = load_estimator(export_weights(m, tmp_path / "ns.pt"))
    out = est.predict(_patches(3), "ICX285")
    assert torch.allclose(out["sigma_total"], out["sigma"].pow(2).sum(1).sqrt(), rtol=1e-5)
    assert est._module.net.total_branch is total_branch


def test_dn_uint8_float_and_numpy_inputs_agree(noise_est):
    x = (_patches(2) * 255).round()
    ref = noise_est.predict(x / 255, "ICX285")["sigma"]
    u8 = noise_est.predict(x.to(torch.uint8).numpy(), "ICX285")["sigma"]
    dn = noise_est.predict(x, "ICX285", input_range="dn")["sigma"]
    assert torch.allclose(ref, u8, atol=1e-5) and torch.allclose(ref, dn, atol=1e-5)
    hw = noise_est.predict(x[0, 0].to(torch.uint8), "ICX285")["sigma"]  # H×W
    assert torch.allclose(hw, ref[:1], atol=1e-5)


def test_bad_inputs_get_clear_errors(noise_est):
    x = _patches(2)
    with pytest.raises(ValueError, match="looks like DN"):
        noise_est.predict(x * 255, "ICX285")
    nan = x.clone()
    nan[0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        noise_est.predict(nan, "ICX285")
    with pytest.raises(ValueError, match="32×32"):
        noise_est.predict(torch.rand(2, 1, 40, 40), "ICX285")
    with pytest.raises(ValueError, match="B×1×H×W"):
        noise_est.predict(torch.rand(2, 3, 32, 32), "ICX285")
    with pytest.raises(TypeError, match="numeric"):
        noise_est.predict(np.array([["a"]]), "ICX285")
    with pytest.raises(ValueError, match="pass metadata"):
        noise_est.predict(x)
    with pytest.raises(ValueError, match="in DN must lie in"):
        noise_est.predict(x * 400, "ICX285", input_range="dn")


@pytest.mark.parametrize("field,value", [("gain_db", 30.0), ("temperature_c", -5.0), ("full_well_e", 1000.0)])
def test_metadata_out_of_range_names_field(noise_est, field, value):
    with pytest.raises(ValueError, match=field):
        noise_est.predict(_patches(1), {field: value}, base_preset="ICX285")


def test_metadata_batch_and_dict(noise_est, min_est):
    x = _patches(3)
    meta = CameraMetadata.preset("EV76C661", batch_size=3, gain_db=torch.tensor([0.0, 12.0, 24.0]))
    full = noise_est.predict(x, meta)
    one = noise_est.predict(x[1:2], meta[1:2])
    assert torch.allclose(full["sigma"][1:2], one["sigma"], atol=1e-5)
    with pytest.raises(ValueError, match="batch size 2"):
        noise_est.predict(x, meta[:2])
    # Min-Meta: gain/exposure/temperature suffice
    out = min_est.predict(x, {"gain_db": 6.0, "exposure_s": 0.01, "temperature_c": 30.0})
    assert torch.isfinite(out["sigma"]).all()


@pytest.mark.parametrize("fill,reason", [(0.0, "black"), (1.0, "saturated")])
def test_black_and_saturated_are_finite_and_flagged(noise_est, fill, reason):
    out = noise_est.predict(torch.full((2, 1, 32, 32), fill), "ICX285")
    assert torch.isfinite(out["sigma"]).all() and torch.isfinite(out["xi"]).all()
    assert not out["assessable"].any() and out["reason"] == [reason, reason]


def test_featureless_only_for_mtf():
    flat = torch.full((1, 1, 16, 16), 0.5)
    assert assess_patches(flat, "mtf")[1] == ["featureless"]
    assert assess_patches(flat, "noise_source")[1] == [""]


def test_fp32_and_bf16_agree(noise_est, tmp_path):
    """bf16 autocast inference stays within 5 % + 0.1 DN of fp32 (noise) and 0.03 of MTF."""
    x = _patches(4, seed=3)
    a = noise_est.predict(x, "ICX285", precision="fp32")["sigma"]
    b = noise_est.predict(x, "ICX285", precision="bf16")["sigma"]
    assert torch.allclose(a, b, rtol=0.05, atol=0.1)
    mtf = load_estimator(export_weights(MTFEstimator(patch_size=32), tmp_path / "mtf.pt"))
    y = torch.rand(4, 1, 32, 32)
    assert torch.allclose(mtf.predict(y, precision="fp32")["mtf"], mtf.predict(y, precision="bf16")["mtf"], atol=0.03)
    with pytest.raises(ValueError, match="precision"):
        mtf.predict(y, precision="fp16")


@pytest.mark.parametrize("batch", [1, 256])
def test_large_and_single_batches(noise_est, batch):
    x = torch.rand(batch, 1, 32, 32)
    out = noise_est.predict(x, "ICX285", batch_size=100)
    assert out["sigma"].shape == (batch, 3) and torch.isfinite(out["sigma"]).all()


def test_shipped_models_load_by_name():
    shipped = shipped_models()
    for name in shipped:
        est = load_estimator(name)
        assert est.kind in ("mtf", "drne", "noise_source")
        assert "metrics" in est.description  # every shipped model carries its held-out metrics


def test_model_card_lists_metrics_and_command(tmp_path):
    from camhealth.model_card import card_text

    path = export_weights(NoiseSourceEstimator(patch_size=32), tmp_path / "m.pt", metrics={"test/rms_total": 0.42})
    text = card_text(path, "python -m camhealth.fit --config configs/noise_source.yaml", timing={"fp32": 1.0, "bf16": 0.5})
    assert "test/rms_total | 0.420" in text and "configs/noise_source.yaml" in text and "GFLOP" in text
    assert "Trunk activity" in text and "— dead" not in text  # a fresh trunk is alive
    assert "Inference default" not in text
    blended = export_weights(NoiseSourceEstimator(patch_size=32), tmp_path / "b.pt", inference={"posterior_blend": {"weight": 0.5}})
    text = card_text(blended, "cmd", timing={"fp32": 1.0, "bf16": 0.5})
    assert "Inference default" in text and '"weight": 0.5' in text and '"fields": ["gain_db"]' in text


def test_bucket_sizes():
    from camhealth.inference import bucket_size

    assert [bucket_size(n) for n in (1, 4, 5, 31, 32, 33, 80, 129)] == [4, 4, 8, 32, 32, 48, 80, 144]
    with pytest.raises(ValueError):
        bucket_size(0)


def test_padding_to_a_bucket_does_not_change_results(noise_est):
    """Batches are padded to bucket sizes: every patch's estimate is the one it gets alone (fp32)."""
    x = _patches(7, seed=3)
    meta = CameraMetadata.preset("ICX285", batch_size=7, gain_db=torch.linspace(0, 24, 7).tolist())
    together = noise_est.predict(x, meta)
    for i in (0, 6):
        alone = noise_est.predict(x[i : i + 1], meta[i])
        assert torch.allclose(alone["sigma"], together["sigma"][i : i + 1], atol=1e-5)
        assert torch.allclose(alone["xi"], together["xi"][i : i + 1], atol=1e-5)


@pytest.mark.parametrize("views", [2, 4])
def test_mtf_views_average_the_flipped_copies(tmp_path, views):
    torch.manual_seed(0)
    mtf = load_estimator(export_weights(MTFEstimator(patch_size=32, joint_directions=True), tmp_path / "mtf.pt"))
    y = torch.rand(3, 1, 32, 32)
    flips = [(-2, -1)] if views == 2 else [(-1,), (-2,), (-2, -1)]
    expected = torch.stack([mtf.predict(y)["mtf"]] + [mtf.predict(y.flip(d))["mtf"] for d in flips]).mean(0)
    out = mtf.predict(y, views=views)
    assert out["mtf"].shape == (3, 16) and torch.allclose(out["mtf"], expected, atol=1e-6)
    assert out["assessable"].shape == (3,) and len(out["reason"]) == 3
    assert not torch.allclose(out["mtf"], mtf.predict(y)["mtf"])  # the flipped copies do add estimates


def test_views_are_checked(noise_est, tmp_path):
    mtf = load_estimator(export_weights(MTFEstimator(patch_size=32), tmp_path / "mtf.pt"))
    with pytest.raises(ValueError, match="views = 3 must be 1, 2 or 4"):
        mtf.predict(torch.rand(1, 1, 32, 32), views=3)
    with pytest.raises(ValueError, match="views = 2 averages flipped copies of MTF patches"):
        noise_est.predict(_patches(1), "ICX285", views=2)


@pytest.mark.parametrize("fill,reason", [(0.0, "black"), (1.0, "saturated"), (0.5, "featureless")])
def test_mtf_views_keep_the_flags_of_hard_patches(tmp_path, fill, reason):
    mtf = load_estimator(export_weights(MTFEstimator(patch_size=32, joint_directions=True), tmp_path / "mtf.pt"))
    x = torch.cat([torch.full((1, 1, 32, 32), fill), torch.rand(1, 1, 32, 32, generator=torch.Generator().manual_seed(2))])
    out = mtf.predict(x, views=4, precision="bf16")
    assert torch.isfinite(out["mtf"]).all() and out["mtf"].shape == (2, 16)
    assert out["reason"] == [reason, ""] and out["assessable"].tolist() == [False, True]


def _split_case(seed=0):
    """Two 128-px ramps of the EV76C661 at 50 °C, 0.05 s, 12 dB, reporting its W = 59 nV/√Hz: the first made with
    W′ = 10 nV/√Hz (readout noise far below what the metadata say, dark current unchanged), the second with M′ = M.
    Realised DCSN / RN of the first: 2.66 / 0.49 DN; the shipped network alone reads 1.40 / 2.05."""
    from camhealth.physics import form_image

    kw = dict(batch_size=2, gain_db=12.0, exposure_s=0.05, temperature_c=50.0)
    told = CameraMetadata.preset("EV76C661", white_noise_v_per_rthz=59e-9, **kw)
    made = CameraMetadata.preset("EV76C661", white_noise_v_per_rthz=[10e-9, 59e-9], **kw)
    clean = torch.linspace(0.2, 0.8, 128).view(1, 1, 1, 128).expand(2, 1, 128, 128).contiguous()
    formed = form_image(clean, made, generator=torch.Generator().manual_seed(seed))
    return formed.image.float(), told, formed.sigma_dn


def test_posterior_split_resplits_only_where_the_posterior_is_sure():
    """posterior_split keeps the network's DCSN² + RN², PN, total and ξ, and moves the split toward the truth on the
    white-noise-altered ramp; the consistent ramp is left exactly as the network gives it."""
    est = load_estimator("noise_source_full_meta")
    x, meta, truth = _split_case()
    plain = est.predict(x, meta)
    split = est.predict(x, meta, posterior_split=0.9)
    assert split["resplit"].tolist() == [True, False] and "resplit" not in plain
    for k in ("sigma_total", "xi"):
        assert torch.equal(split[k], plain[k])
    assert torch.equal(split["sigma"][:, 0], plain["sigma"][:, 0]) and torch.equal(split["sigma"][1], plain["sigma"][1])
    level = lambda s: s[:, 1].double().square() + s[:, 2].double().square()  # noqa: E731
    assert torch.allclose(level(split["sigma"]), level(plain["sigma"]), rtol=1e-5)
    err = lambda s: (s[0, 1:] - truth[0, 1:]).abs().sum().item()  # noqa: E731
    assert err(split["sigma"]) < 0.5 * err(plain["sigma"])  # 0.40 vs 2.82 DN (DCSN + RN absolute error)
    assert torch.isfinite(split["sigma"]).all()
    # black and saturated patches carry no evidence: the posterior abstains, nothing is re-split, all finite
    hard = torch.stack([torch.zeros(1, 128, 128), torch.ones(1, 128, 128)])
    out = est.predict(hard, meta, posterior_split=0.9)
    assert out["resplit"].tolist() == [False, False] and torch.isfinite(out["sigma"]).all()
    assert torch.equal(out["sigma"], est.predict(hard, meta)["sigma"])
    # bf16 autocast: the posterior runs in float32/64 outside it; the same patch is re-split, and the result agrees
    # with fp32 within the stated bf16 tolerance (5 % + 0.1 DN)
    half = est.predict(x, meta, posterior_split=0.9, precision="bf16")
    assert half["resplit"].tolist() == [True, False]
    assert torch.allclose(half["sigma"], split["sigma"], rtol=0.05, atol=0.1)


def test_posterior_split_is_checked(noise_est, min_est, tmp_path):
    x, meta, _ = _split_case()
    est = load_estimator("noise_source_full_meta")
    for bad in (0.0, 1.0, 1.5, -0.1, True, "0.9"):
        with pytest.raises(ValueError, match="posterior_split = .* must be a probability in \\(0, 1\\)"):
            est.predict(x, meta, posterior_split=bad)
    with pytest.raises(ValueError, match="Full-Meta noise-source estimator with the physics prior"):
        min_est.predict(_patches(1), {"gain_db": 6.0, "exposure_s": 0.01, "temperature_c": 30.0}, base_preset="ICX285", posterior_split=0.9)
    mtf = load_estimator(export_weights(MTFEstimator(patch_size=32), tmp_path / "mtf.pt"))
    with pytest.raises(ValueError, match="Full-Meta noise-source estimator"):
        mtf.predict(torch.rand(1, 1, 32, 32), posterior_split=0.9)


# ---------------------------------------------------------------- posterior blend (session 14)
def test_posterior_blend_weight_is_the_documented_ramp():
    """w = weight · ramp(texture: 0.25 → 0.1) · ramp(details: 100 → 150), in closed form."""
    from camhealth.inference import PosteriorBlend

    b = PosteriorBlend()
    details = torch.tensor([0.0, 31.0, 100.0, 125.0, 150.0, 5000.0, 5000.0, 5000.0, 5000.0, 125.0])
    texture = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.175, 0.25, 3.0, 0.175])
    expect = torch.tensor([0.0, 0.0, 0.0, 0.35, 0.7, 0.7, 0.35, 0.0, 0.0, 0.175], dtype=torch.float64)
    assert torch.allclose(b.weights(details, texture), expect, atol=1e-12)
    assert PosteriorBlend(weight=1.0, texture_lo=0.0, texture_hi=1.0, details_lo=32, details_hi=64).weights(
        torch.tensor([48.0]), torch.tensor([0.5])).item() == pytest.approx(0.25)


def _gain_case(seed=0):
    """Two 128-px ramps of the ICX285 at 30 °C, 0.02 s, reporting 6 dB: the first made at 18 dB (the thesis's
    mismatch: another gain), the second with M′ = M."""
    from camhealth.physics import form_image

    kw = dict(batch_size=2, exposure_s=0.02, temperature_c=30.0)
    told = CameraMetadata.preset("ICX285", gain_db=6.0, **kw)
    made = CameraMetadata.preset("ICX285", gain_db=[18.0, 6.0], **kw)
    clean = torch.linspace(0.15, 0.85, 128).view(1, 1, 1, 128).expand(2, 1, 128, 128).contiguous()
    formed = form_image(clean, made, generator=torch.Generator().manual_seed(seed))
    return formed.image.float(), told, formed.sigma_dn.float(), formed.sigma_total_dn.float()


def test_posterior_blend_follows_the_closed_form_where_the_patch_is_flat():
    """On a white-noise ramp the blend is exactly log σ̂ + w·(log σ_post − log σ̂) with the posterior of
    camhealth.estimators.mismatch_posterior, and ξ̂ + w·(ξ_post − ξ̂); it is on by default for noise_source_full_gain,
    and ``posterior_blend=None`` gives the network alone."""
    from camhealth.inference import PosteriorBlend
    from camhealth.estimators.mismatch_posterior import mismatch_posterior
    from camhealth.estimators.noise_features import physics_prior_dn

    est = load_estimator("noise_source_full_gain")
    assert est.posterior_blend == PosteriorBlend()  # the shipped setting is the documented default
    x, meta, truth, total_true = _gain_case()
    alone = est.predict(x, meta, posterior_blend=None)
    auto = est.predict(x, meta)
    assert "posterior_weight" not in alone and auto["posterior_weight"].shape == (2,)
    post = mismatch_posterior(x, meta, fields=["gain_db"]).double()
    w = PosteriorBlend().weights(post[:, -2], post[:, -1])
    assert torch.allclose(auto["posterior_weight"].double(), w.float().double()) and (w > 0).all()  # white noise on ramps
    own = torch.cat([alone["sigma"], alone["sigma_total"][:, None]], 1).double()
    expect = (own.log() + w[:, None] * (post[:, :4].log() - own.log())).exp()
    got = torch.cat([auto["sigma"], auto["sigma_total"][:, None]], 1).double()
    assert torch.allclose(got, expect.float().double(), rtol=1e-5)
    xi_post = physics_prior_dn(x, meta)[:, 3].double() - post[:, 4]
    assert torch.allclose(auto["xi"].double(), alone["xi"].double() + w * (xi_post - alone["xi"].double()), atol=1e-4)
    # where the gain was altered the posterior is right and the blend moves toward the truth
    err = lambda o: (torch.cat([o["sigma"][0], o["sigma_total"][:1]]) - torch.cat([truth[0], total_true[:1]])).abs().sum().item()  # noqa: E731
    assert err(auto) <= err(alone) + 1e-6
    assert torch.equal(est.predict(x, meta, posterior_blend=True)["sigma"], auto["sigma"])


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
@pytest.mark.parametrize("batch", [1, 256])
def test_posterior_blend_on_hard_patches(precision, batch):
    """Black, saturated and textured patches: the posterior abstains or the texture check closes the gate (w = 0:
    the network's own outputs, exactly). A noiseless mid-grey patch has flat, perfectly "white" details of zero
    power, which no camera of the physics makes (the ICX285 has σ ≥ 1.5 DN at the smallest gain): the posterior's
    nearest explanation is the smallest noise the physics allows, and the blend lands between it and the network's
    (log-space), finite. All finite, fp32 and bf16, batch 1 and 256."""
    est = load_estimator("noise_source_full_gain")
    g = torch.Generator().manual_seed(3)
    kinds = [torch.zeros(1, 128, 128), torch.ones(1, 128, 128), torch.full((1, 128, 128), 0.5),
             (torch.rand(1, 128, 128, generator=g) > 0.5).float() * 0.6 + 0.2]  # binary texture, no noise
    x = torch.stack([kinds[i % 4] for i in range(batch)])
    meta = CameraMetadata.preset("ICX285", gain_db=24.0, temperature_c=80.0)
    out = est.predict(x, meta, precision=precision)
    alone = est.predict(x, meta, precision=precision, posterior_blend=None)
    grey = torch.tensor([i % 4 == 2 for i in range(batch)])
    assert (out["posterior_weight"][~grey] == 0).all() and (out["posterior_weight"][grey] > 0).all()
    for k in ("sigma", "sigma_total", "xi"):
        assert torch.isfinite(out[k]).all() and torch.equal(out[k][~grey], alone[k][~grey])
    if not bool(grey.any()):
        return
    from camhealth.estimators.mismatch_posterior import mismatch_posterior

    post = mismatch_posterior(x[grey][:1], meta, fields=["gain_db"])[0, :4]
    got = torch.cat([out["sigma"][grey], out["sigma_total"][grey, None]], 1)
    own = torch.cat([alone["sigma"][grey], alone["sigma_total"][grey, None]], 1)
    lo, hi = torch.minimum(own, post), torch.maximum(own, post)
    assert ((got >= lo * (1 - 1e-3)) & (got <= hi * (1 + 1e-3))).all()


def test_posterior_blend_fp32_and_bf16_agree():
    est = load_estimator("noise_source_full_gain")
    x, meta, _, _ = _gain_case(seed=4)
    a, b = est.predict(x, meta), est.predict(x, meta, precision="bf16")
    assert torch.equal(a["posterior_weight"], b["posterior_weight"])
    assert torch.allclose(a["sigma"], b["sigma"], rtol=0.05, atol=0.1)  # the stated bf16 tolerance
    assert torch.allclose(a["sigma_total"], b["sigma_total"], rtol=0.05, atol=0.1)


def test_posterior_blend_is_checked(min_est, tmp_path):
    from camhealth.inference import PosteriorBlend

    est = load_estimator("noise_source_full_gain")
    x, meta, _, _ = _gain_case()
    bad = [
        ({"weight": 0.0}, "weight = 0.0 must be in \\(0, 1\\]"), ({"weight": 1.5}, "weight = 1.5 must be in"),
        ({"weight": float("nan")}, "weight = nan must be a finite number"),
        ({"texture_lo": 0.3, "texture_hi": 0.2}, "texture_lo = 0.3 must be below texture_hi = 0.2"),
        ({"details_lo": 10}, "details_lo = 10.0 must be in \\[32, details_hi"),
        ({"details_lo": 200, "details_hi": 150}, "details_lo = 200.0 must be in \\[32, details_hi = 150.0\\)"),
        ({"fields": ["gain"]}, "fields = \\['gain'\\] must be distinct names from"),
        ({"fields": []}, "must be distinct names from"), ({"gain": 1}, "unknown key\\(s\\) \\['gain'\\]"),
        ("yes", "posterior_blend = 'yes' must be 'auto', None/False, True"), (0.5, "posterior_blend = 0.5 must be"),
    ]
    for value, msg in bad:
        with pytest.raises(ValueError, match=msg):
            est.predict(x, meta, posterior_blend=value)
    assert PosteriorBlend(fields="gain_db").fields == ("gain_db",)
    with pytest.raises(ValueError, match="Full-Meta noise-source estimator with the physics prior"):
        min_est.predict(_patches(1), {"gain_db": 6.0, "exposure_s": 0.01, "temperature_c": 30.0}, base_preset="ICX285", posterior_blend=True)
    mtf = load_estimator(export_weights(MTFEstimator(patch_size=32), tmp_path / "mtf.pt"))
    with pytest.raises(ValueError, match="Full-Meta noise-source estimator"):
        mtf.predict(torch.rand(1, 1, 32, 32), posterior_blend=True)
    assert "posterior_weight" not in mtf.predict(torch.rand(1, 1, 32, 32))  # "auto" with no setting: off
