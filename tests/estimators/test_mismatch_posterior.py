"""The posterior over single-field metadata mismatches: which field is wrong, and the σ it implies."""

from __future__ import annotations

import pytest
import torch

from camhealth.physics import form_image
from camhealth.physics.metadata import CameraMetadata
from datamodules.noise import expected_sigma_dn
from camhealth.estimators.noise_features import physics_prior_dn
from camhealth.estimators.mismatch_posterior import MISMATCH_POSTERIOR, POSTERIOR_FIELDS, mismatch_posterior


def _leaves(b: int, seed: int) -> torch.Tensor:
    """Piecewise-constant scenes in [0.15, 0.85] with strong edges (a coarse random grid, upsampled)."""
    g = torch.Generator().manual_seed(seed)
    levels = 0.15 + 0.7 * torch.rand(b, 1, 8, 8, generator=g)
    return torch.nn.functional.interpolate(levels, size=(128, 128), mode="nearest")


def _camera(**fields: float) -> CameraMetadata:
    """ICX285 at 12 dB with a strong dark current (D_FM 0.5 nA/cm², 0.1 s): all three sources ≈ 1–3 DN."""
    base = {"gain_db": 12.0, "exposure_s": 0.1, "dark_fom_na_per_cm2": 0.5, "temperature_c": 30.0, **fields}
    return CameraMetadata.preset("ICX285").replace(**{k: torch.tensor([v]) for k, v in base.items()})


# (what the image was made with, the field that should win, the source whose σ changes)
CASES = {
    "match": ({}, "match", None),
    "gain": ({"gain_db": 20.0}, "gain_db", None),
    "temperature": ({"temperature_c": 60.0}, "temperature_c", 1),
}


@pytest.mark.parametrize("case", list(CASES))
def test_posterior_names_the_wrong_field_and_recovers_the_labels(case):
    """Metadata right: P(match) is the largest and σ are the metadata's. Gain 12 → 20 dB (all sources grow) or
    temperature 30 → 60 °C (dark current ×≈ 9): that field wins with P > 0.8, and the posterior σ of every
    source is within 10 % (+0.05 DN) of the realised labels — where the metadata are off by up to 3×."""
    change, winner, _ = CASES[case]
    told, made = _camera(), _camera(**change)
    clean = _leaves(4, 1)
    formed = form_image(clean, made.expand(4), generator=torch.Generator().manual_seed(3))
    post = mismatch_posterior(formed.image, told)
    assert post.shape == (4, len(MISMATCH_POSTERIOR)) and post.dtype == torch.float32
    probs = post[:, 5:9]
    assert (post[:, 9] > 1000).all()  # diagonal details used
    assert (post[:, 10].abs() < 0.1).all()  # the texture check: flat leaves and white noise
    assert torch.allclose(probs.sum(1), torch.ones(4), atol=1e-5)
    names = ["match", *POSTERIOR_FIELDS]
    assert (probs.argmax(1) == names.index(winner)).all()
    assert (probs[:, names.index(winner)] > (0.8 if case != "match" else 0.5)).all()
    labels = formed.sigma_dn.float()
    assert (post[:, :3] - labels).abs().le(0.1 * labels + 0.05).all(), (post[:, :3], labels)
    if case != "match":  # the metadata alone were far off
        told_sigma = expected_sigma_dn(clean, told.expand(4)).float()
        assert ((told_sigma - labels).abs() > 0.3 * labels).any(dim=1).all()
    # the unclipped posterior total is the image's analytic total (what ξ compares the metadata's with)
    made_total = expected_sigma_dn(clean, made.expand(4)).float().pow(2).sum(1).sqrt()
    assert torch.allclose(post[:, 4], made_total, rtol=0.08)


def test_posterior_respects_what_no_temperature_can_explain():
    """Readout noise 11× the metadata's (white noise 5 → 55 nV/√Hz) on a camera with a tiny dark current:
    no temperature in 0–80 °C makes that much signal-independent noise, so the white noise wins outright and
    σ_DCSN stays the metadata's — the physics' feasible ranges decide, not a learned guess."""
    told = CameraMetadata.preset("ICX285").replace(gain_db=torch.tensor([12.0]), white_noise_v_per_rthz=torch.tensor([5e-9]))
    made = told.replace(white_noise_v_per_rthz=torch.tensor([55e-9]))
    formed = form_image(_leaves(4, 1), made.expand(4), generator=torch.Generator().manual_seed(3))
    post = mismatch_posterior(formed.image, told)
    assert (post[:, 6 + POSTERIOR_FIELDS.index("white_noise_v_per_rthz")] > 0.95).all()
    labels = formed.sigma_dn.float()
    assert (post[:, 2] - labels[:, 2]).abs().le(0.1 * labels[:, 2]).all()
    assert (post[:, 1] - labels[:, 1]).abs().le(0.01).all()


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_posterior_without_evidence_keeps_the_metadata(dtype):
    """Black and saturated patches carry no usable detail: the σ are the metadata's after clipping
    (finite, ≥ 0; :func:`clipped_prior_dn`), P(match) = 1 and no details used: the posterior abstains. Any float
    dtype in, float32 out."""
    told = _camera()
    ends = torch.stack([torch.zeros(1, 32, 32), torch.ones(1, 32, 32)]).to(dtype)
    post = mismatch_posterior(ends, told)
    assert post.dtype == torch.float32 and torch.isfinite(post).all() and (post >= 0).all()
    assert torch.equal(post[:, 5:], torch.tensor([1.0, 0.0, 0.0, 0.0, 0.0, 0.0]).expand(2, -1))
    clipped = physics_prior_dn(ends.float(), told, clipping=True)[:, 4:8]  # the metadata's σ after clipping
    assert torch.allclose(post[:, :4], clipped, rtol=1e-4, atol=1e-4)


def test_posterior_batch_one_and_metadata_batch_b():
    clean = _leaves(3, 2)
    metas = CameraMetadata.sample(3, generator=torch.Generator().manual_seed(0))
    formed = form_image(clean, metas, generator=torch.Generator().manual_seed(1))
    together = mismatch_posterior(formed.image, metas)
    alone = torch.cat([mismatch_posterior(formed.image[i:i + 1], metas[i:i + 1]) for i in range(3)])
    assert torch.allclose(together, alone, rtol=1e-4, atol=1e-5)


def test_posterior_rejects_bad_input():
    told = _camera()
    image = torch.rand(2, 1, 32, 32)
    with pytest.raises(ValueError, match="B×1×H×W"):
        mismatch_posterior(image[:, 0], told)
    with pytest.raises(ValueError, match="fields"):
        mismatch_posterior(image, told, fields=("colour",))
    with pytest.raises(ValueError, match="mismatch_probability"):
        mismatch_posterior(image, told, mismatch_probability=1.0)
    with pytest.raises(ValueError, match="metadata batch 3"):
        mismatch_posterior(image, CameraMetadata.sample(3, generator=torch.Generator().manual_seed(0)))
    with pytest.raises(ValueError, match="at least 8×8"):
        mismatch_posterior(torch.rand(1, 1, 4, 16), told)
    with pytest.raises(ValueError, match="NaN"):
        mismatch_posterior(torch.full((1, 1, 16, 16), float("nan")), told)


def test_posterior_at_extreme_metadata_and_batch_256():
    """The corners of Table 4.1 (0 and 80 °C, 0 and 24 dB, full well 2 000 e⁻, exposure 0.2 s) on a batch of 256
    small patches, heavily clipped at high gain: finite, non-negative σ and probabilities that sum to 1."""
    g = torch.Generator().manual_seed(9)
    b = 256
    corners = {
        "temperature_c": torch.where(torch.arange(b) % 2 == 0, 0.0, 80.0),
        "gain_db": torch.where(torch.arange(b) % 4 < 2, 0.0, 24.0),
        "full_well_e": torch.full((b,), 2000.0),
        "exposure_s": torch.full((b,), 0.2),
    }
    meta = CameraMetadata.sample(b, generator=g).replace(**corners)
    clean = torch.nn.functional.interpolate(torch.rand(b, 1, 4, 4, generator=g), size=(32, 32), mode="nearest")
    formed = form_image(clean, meta, generator=g)
    post = mismatch_posterior(formed.image, meta)
    assert post.shape == (b, len(MISMATCH_POSTERIOR)) and torch.isfinite(post).all()
    assert (post[:, :5] >= 0).all()
    assert torch.allclose(post[:, 5:9].sum(1), torch.ones(b), atol=1e-5)
