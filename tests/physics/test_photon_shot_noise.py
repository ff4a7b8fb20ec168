import pytest
import torch

from camhealth.physics.image_formation import form_image, sample_poisson
from camhealth.physics.metadata import CameraMetadata
from camhealth.physics.photon_shot_noise import photo_electrons, photon_shot_sigma_dn, photon_shot_sigma_patch_dn


def test_closed_form_sigma():
    m = CameraMetadata.preset("ICX285", batch_size=2, gain_db=[0.0, 20.0])
    i = torch.full((2, 1, 4, 4), 0.5)
    s = photon_shot_sigma_dn(i, m)
    assert s[0, 0, 0, 0].item() == pytest.approx(255 * (0.5 / 14000) ** 0.5, rel=1e-5)
    assert s[1, 0, 0, 0].item() == pytest.approx(255 * (10 * 0.5 / 14000) ** 0.5, rel=1e-5)
    assert torch.allclose(photon_shot_sigma_patch_dn(i, m), s[:, 0, 0, 0])
    assert photo_electrons(i, m)[0, 0, 0, 0].item() == pytest.approx(7000.0)


def test_gain_doubles_variance():
    m = CameraMetadata.preset("ICX285", batch_size=2, gain_db=[0.0, 20 * torch.log10(torch.tensor(2.0)).item()])
    s = photon_shot_sigma_patch_dn(torch.full((2, 1, 2, 2), 0.3), m)
    assert (s[1] / s[0]).item() ** 2 == pytest.approx(2.0, rel=1e-4)


@pytest.mark.parametrize("rate", [0.5, 3.0, 40.0, 5000.0])
def test_poisson_variance_equals_mean(rate):
    g = torch.Generator().manual_seed(5)
    x = sample_poisson(torch.full((200_000,), rate), g)
    n = x.numel()
    assert x.mean().item() == pytest.approx(rate, abs=5 * (rate / n) ** 0.5)
    # var of the sample variance of a Poisson ≈ (μ + 2μ²)/n
    assert x.var().item() == pytest.approx(rate, abs=5 * ((rate + 2 * rate**2) / n) ** 0.5)
    if rate < 1e3:  # exact Poisson: integer counts
        assert torch.equal(x, x.round())


def test_realised_photon_noise_matches_analytic():
    m = CameraMetadata.preset("EV76C661", batch_size=3, gain_db=[0.0, 12.0, 24.0])
    x = torch.full((3, 1, 128, 128), 0.4)
    r = form_image(x, m, sources=("photon",), generator=torch.Generator().manual_seed(0))
    # std of a 16384-pixel sample: relative standard error ≈ 1/√(2n) ≈ 0.6 %
    assert torch.allclose(r.sigma_dn[:, 0], r.sigma_expected_dn[:, 0], rtol=0.03)
    assert torch.all(r.sigma_dn[:, 1:] == 0)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), 2.0, -0.1])
def test_bad_intensity_is_refused_naming_it(bad):
    m = CameraMetadata.preset("ICX285")
    for fn in (photon_shot_sigma_dn, photo_electrons):
        with pytest.raises(ValueError, match="intensity"):
            fn(torch.tensor([[0.5, bad]]), m)
    if bad != bad or abs(bad) == float("inf"):
        with pytest.raises(ValueError, match="mean intensity"):
            photon_shot_sigma_patch_dn(torch.full((1, 1, 2, 2), bad), m)


@pytest.mark.parametrize("value,shown", [(200.0, "200"), (-0.5, "-0.5")])
def test_patch_sigma_refuses_a_dn_image_or_negative_mean(value, shown):
    # a DN image (0…255) where [0, 1] is meant would read σ_PN ≈ 121 DN; a negative one 0
    meta = CameraMetadata.preset("ICX285")
    with pytest.raises(ValueError, match=rf"mean intensity\[0\] = {shown} is out of the allowed range \[0, 1\] \(DN/255\)"):
        photon_shot_sigma_patch_dn(torch.full((1, 1, 4, 4), value), meta)


def test_patch_sigma_counts_slight_ringing_below_zero_as_zero():
    x = torch.full((1, 1, 4, 4), 0.5)
    x[0, 0, 0, 0] = -1e-3  # ringing of one pixel after a blur; the mean stays in [0, 1]
    meta = CameraMetadata.preset("ICX285")
    want = photon_shot_sigma_patch_dn(x.clamp_min(0), meta)
    torch.testing.assert_close(photon_shot_sigma_patch_dn(x, meta), want)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_intensities_get_float32_accuracy(dtype):
    """FW/g = 1e5 e⁻ overflows float16 and g/FW = 1e-5 is subnormal there: the arithmetic runs in float32, so the
    only error left is the rounding of the input intensity and of the result."""
    m = CameraMetadata.preset("ICX285", full_well_e=100_000.0)  # 0 dB: FW/g = 1e5
    i = torch.tensor([[0.01, 0.02, 0.05, 0.5]]).to(dtype)
    i64 = i.double()  # the intensities the function sees, exactly
    tol = torch.finfo(dtype).eps  # one rounding of the result (the σ ≤ 255 DN fit the format)
    electrons = photo_electrons(i, m)
    assert electrons.dtype == torch.float32  # counts up to 1e5 do not fit float16
    assert torch.allclose(electrons.double(), i64 * 1e5, rtol=1e-6)
    sigma = photon_shot_sigma_dn(i, m)
    assert sigma.dtype == dtype
    assert torch.allclose(sigma.double(), 255.0 * (i64 / 1e5).sqrt(), rtol=tol)
    patch = photon_shot_sigma_patch_dn(i.view(4, 1, 1, 1), m.expand(4))
    assert patch.dtype == dtype
    assert torch.allclose(patch.double(), 255.0 * (i64[0] / 1e5).sqrt(), rtol=tol)
