import pytest
import torch

from camhealth.augment import CameraCorruption, RandomDefocusBlur, RandomMotionBlur, RandomSensorNoise
from camhealth.physics.defocus_psf import defocus_psf
from camhealth.physics.metadata import CameraMetadata
from camhealth.physics.mtf import mtf_hv


def _modules():
    return {
        "defocus": lambda **kw: RandomDefocusBlur(diameter=(1.0, 11.0), **kw),
        "linear": lambda **kw: RandomMotionBlur(length=(1.0, 11.0), **kw),
        "nonlinear": lambda **kw: RandomMotionBlur(length=(1.0, 11.0), intensity=(0.2, 1.0), **kw),
        "noise": lambda **kw: RandomSensorNoise(**kw),
        "camera": lambda **kw: CameraCorruption(
            RandomDefocusBlur((1.0, 7.0)), RandomMotionBlur((1.0, 7.0), intensity=(0.0, 1.0)), RandomSensorNoise(), **kw
        ),
        "noise_counter": lambda **kw: RandomSensorNoise(rng="counter", **kw),
        "camera_counter": lambda **kw: CameraCorruption(
            RandomDefocusBlur((1.0, 7.0)), RandomMotionBlur((1.0, 7.0), intensity=(0.0, 1.0)),
            RandomSensorNoise(rng="counter"), **kw
        ),
    }


MODULES = list(_modules())


@pytest.mark.parametrize("name", MODULES)
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_shape_dtype_range(name, dtype, device):
    aug = _modules()[name]()
    x = torch.rand(3, 1, 32, 32, device=device).to(dtype)
    y = aug(x)
    assert y.shape == x.shape and y.dtype == dtype and y.device == x.device
    assert torch.isfinite(y.float()).all() and y.min() >= 0 and y.max() <= 1


@pytest.mark.parametrize("name", MODULES)
def test_params_replay_is_exact(name):
    aug = _modules()[name]()
    x = torch.rand(4, 1, 32, 32)
    y = aug(x)
    assert torch.equal(aug(x, params=aug._params), y)
    assert not torch.equal(aug(x), y)  # fresh parameters differ


@pytest.mark.parametrize("name", MODULES)
def test_seeded_reproducibility(name):
    x = torch.rand(4, 1, 32, 32)
    torch.manual_seed(11)
    a = _modules()[name]()(x)
    torch.manual_seed(11)
    b = _modules()[name]()(x)
    assert torch.equal(a, b)


@pytest.mark.parametrize("name", ["defocus", "linear", "nonlinear"])
def test_same_on_batch_blur(name):
    aug = _modules()[name](same_on_batch=True)
    x = torch.rand(1, 1, 32, 32).expand(5, -1, -1, -1).contiguous()
    y = aug(x)
    assert torch.allclose(y, y[:1].expand_as(y))
    mtf = aug.labels()["mtf"]
    assert torch.allclose(mtf, mtf[:1].expand_as(mtf))


def test_same_on_batch_noise_shares_metadata_not_field():
    aug = RandomSensorNoise(same_on_batch=True)
    y = aug(torch.full((4, 1, 32, 32), 0.5))
    meta = aug.labels()["metadata"]
    assert torch.all(meta.gain_db == meta.gain_db[0])
    assert not torch.equal(y[0], y[1])


@pytest.mark.parametrize("batch", [1, 256])
def test_batch_sizes(batch):
    aug = _modules()["camera"]()
    y = aug(torch.rand(batch, 1, 16, 16))
    lab = aug.labels()
    assert y.shape[0] == batch and lab["mtf"].shape == (batch, 16) and lab["sigma_dn"].shape == (batch, 3)


def test_keepdim():
    x = torch.rand(1, 24, 24)
    assert RandomDefocusBlur((1.0, 3.0), keepdim=True)(x).shape == x.shape
    assert RandomSensorNoise(keepdim=False)(x).shape == (1, 1, 24, 24)


def test_p_gates_samples_and_labels():
    aug = RandomDefocusBlur(diameter=(5.0, 9.0), p=0.5)
    x = torch.rand(32, 1, 24, 24)
    y = aug(x)
    applied = aug._params["batch_prob"] > 0.5
    assert 0 < applied.sum() < 32
    assert torch.equal(y[~applied], x[~applied])
    mtf = aug.labels()["mtf"]
    assert torch.all(mtf[~applied] == 1) and torch.all(mtf[applied, 7] < 1)


def test_mtf_label_is_mtf_of_applied_psf():
    aug = RandomDefocusBlur(diameter=(2.0, 9.0))
    aug(torch.rand(6, 1, 32, 32))
    d = aug._params["diameter"]
    assert torch.allclose(aug.labels()["mtf"], mtf_hv(defocus_psf(d, aug._defocus_ks)), atol=1e-6)


def test_camera_labels_combine_components_and_gates():
    cam = CameraCorruption(RandomDefocusBlur((3.0, 5.0), p=0.5), RandomMotionBlur((3.0, 9.0), p=0.5), RandomSensorNoise(p=0.5))
    x = torch.full((64, 1, 32, 32), 0.5)
    y = cam(x)
    lab = cam.labels()
    p = cam._params
    none = (p["defocus_gate"] < 0.5) & (p["motion_gate"] < 0.5)
    assert torch.all(lab["mtf"][none] == 1)
    quiet = p["noise_gate"] < 0.5
    assert torch.all(lab["sigma_dn"][quiet] == 0)
    clean_samples = none & quiet
    if clean_samples.any():
        assert torch.allclose(y[clean_samples], x[clean_samples])



def test_camera_blur_gradient_reaches_samples_whose_noise_is_gated_off():
    cam = CameraCorruption(RandomDefocusBlur((2.0, 4.0)), None, RandomSensorNoise(metadata="ICX285", sources=("dark", "readout"), p=0.5))
    x = torch.rand(16, 1, 10, 10, dtype=torch.float64) * 0.6 + 0.2
    torch.manual_seed(2)
    cam(x)
    params = cam._params
    quiet = params["noise_gate"] < 0.5
    assert 0 < int(quiet.sum()) < 16
    xg = x.clone().requires_grad_(True)
    cam(xg, params=params).sum().backward()
    assert torch.all(xg.grad.flatten(1).abs().sum(1) > 0)  # every sample: the blur's gradient, noise or not
    # the samples without noise are their blurred image, differentiably (the noisy ones add a constant here)
    assert torch.autograd.gradcheck(lambda t: cam(t, params=params)[quiet], (x[:].clone().requires_grad_(True),))


def test_clipped_fraction_label_is_of_the_output_each_sample_got():
    meta = CameraMetadata.preset("EV76C661", gain_db=24.0, exposure_s=0.2, temperature_c=80.0)
    aug = RandomSensorNoise(metadata=meta, p=0.5)
    for x in (torch.full((16, 1, 24, 24), 0.98), torch.ones(16, 1, 24, 24)):
        y = aug(x)
        lab = aug.labels()["clipped_fraction"]
        off = aug._params["batch_prob"] < 0.5
        assert 0 < int(off.sum()) < 16
        got = ((y <= 0) | (y >= 1)).flatten(1).float().mean(1)
        assert torch.allclose(lab[off].float(), got[off])  # untouched: 0 for the 0.98 frame, 1 for the white one
        assert torch.all(lab[~off] > 0.3)  # noisy samples near full scale clip about half their pixels

def test_noise_labels_match_physics_for_given_metadata():
    meta = CameraMetadata.preset("EV76C661", batch_size=2, gain_db=[6.0, 24.0], temperature_c=[30.0, 70.0], exposure_s=0.1)
    aug = RandomSensorNoise()
    x = torch.full((2, 1, 128, 128), 0.4)
    aug(x, params=RandomSensorNoise.params_from_metadata(meta, seed=3))
    lab = aug.labels()
    assert torch.allclose(lab["sigma_dn"], lab["sigma_expected_dn"], rtol=0.05)
    assert torch.allclose(lab["metadata"].gain_db, meta.gain_db)


def test_fixed_preset_and_ranges():
    aug = RandomSensorNoise(metadata="ICX285", ranges={"gain_db": (12.0, 24.0)}, sources=("photon", "readout"))
    aug(torch.rand(8, 1, 16, 16))
    lab = aug.labels()
    assert torch.all(lab["metadata"].full_well_e == 14000)
    assert lab["metadata"].gain_db.min() >= 12
    assert torch.all(lab["sigma_dn"][:, 1] == 0)


def test_blur_gradcheck():
    aug = RandomDefocusBlur((2.0, 4.0))
    x = torch.rand(2, 1, 8, 8, dtype=torch.float64, requires_grad=True)
    aug(x.detach())
    params = aug._params
    assert torch.autograd.gradcheck(lambda t: aug(t, params=params), (x,))
    mb = RandomMotionBlur((2.0, 4.0), intensity=(0.0, 1.0))
    mb(x.detach())
    mp = mb._params
    assert torch.autograd.gradcheck(lambda t: mb(t, params=mp), (x,))


@pytest.mark.parametrize("rng", ["torch", "counter"])
def test_noise_gradient_is_identity_on_unclipped_pixels(rng):
    aug = RandomSensorNoise(metadata="ICX285", rng=rng)
    x = torch.full((1, 1, 16, 16), 0.5, requires_grad=True)
    aug(x).sum().backward()
    assert torch.allclose(x.grad, torch.ones_like(x))


@pytest.mark.parametrize(
    "ctor,match",
    [
        (lambda: RandomDefocusBlur(diameter=(5.0, 2.0)), "low ≤ high"),
        (lambda: RandomDefocusBlur(diameter=(1.0, 9.0), kernel_size=7), "does not fit"),
        (lambda: RandomDefocusBlur(kernel_size=8), "odd"),
        (lambda: RandomMotionBlur(intensity=(0.0, 2.0)), "intensity"),
        (lambda: RandomSensorNoise(sources=("cosmic",)), "unknown noise source"),
        (lambda: RandomSensorNoise(metadata="nope"), "unknown sensor preset"),
        (lambda: RandomSensorNoise(rng="philox"), "rng must be one of"),
        (lambda: RandomSensorNoise(ranges={"gain_db": (0.0, 40.0)}), "gain_db"),
        (lambda: CameraCorruption(defocus=RandomSensorNoise()), "RandomDefocusBlur"),
    ],
)
def test_bad_construction(ctor, match):
    with pytest.raises((ValueError, TypeError), match=match):
        ctor()


@pytest.mark.parametrize(
    "bad,exc",
    [
        (torch.full((1, 1, 8, 8), float("nan")), ValueError),
        (torch.zeros(1, 1, 8, 8, dtype=torch.int64), TypeError),
        (torch.full((1, 1, 8, 8), -0.5), ValueError),
        (torch.zeros(2, 2, 1, 8, 8), ValueError),
    ],
)
def test_bad_input(bad, exc):
    with pytest.raises(exc):
        _modules()["camera"]()(bad)


def test_labels_before_call_raise():
    with pytest.raises(RuntimeError, match="call the module"):
        RandomSensorNoise().labels()


def test_a_kornia_style_positional_call_fails_loudly():
    """Kornia's ``RandomMotionBlur(kernel_size, angle, direction)`` must not be read as camhealth's (length, angle,
    intensity): only the first argument is positional, the rest are keyword-only."""
    with pytest.raises(TypeError):
        RandomMotionBlur(3, 35.0, 0.5)
    with pytest.raises(TypeError):
        RandomDefocusBlur((1.0, 5.0), 7)
    with pytest.raises(TypeError):
        RandomSensorNoise(("photon",), "ICX285")
    blur = RandomMotionBlur((3.0, 5.0), angle=35.0, intensity=0.5)  # the same settings by name work
    assert blur(torch.rand(2, 1, 32, 32)).shape == (2, 1, 32, 32)


def test_camera_without_components_is_refused():
    with pytest.raises(ValueError, match=r"needs at least one component \(defocus, motion or noise\)"):
        CameraCorruption(None, None, None)
    assert CameraCorruption(None, None, RandomSensorNoise()).noise is not None


@pytest.mark.parametrize("value", [5, 5.0, "np.int64", "np.float32", "tensor0d"])
def test_numpy_and_tensor_scalars_are_ranges(value):
    import numpy as np

    v = {"np.int64": np.int64(5), "np.float32": np.float32(5.0), "tensor0d": torch.tensor(5.0)}.get(value, value)
    assert RandomDefocusBlur(v)._param_generator.ranges["diameter"] == (5.0, 5.0)


@pytest.mark.parametrize("bad,err,shown", [("ab", TypeError, "str 'ab'"), ([1, 2, 3], ValueError, r"\[1, 2, 3\]"),
                                           (True, TypeError, "bool True"), (None, ValueError, "None")])
def test_bad_ranges_name_the_argument(bad, err, shown):
    with pytest.raises(err, match=rf"diameter must be a number or a \(low, high\) pair, got {shown}"):
        RandomDefocusBlur(bad)


def test_labels_of_params_without_the_batch_size_is_a_clear_error():
    with pytest.raises(ValueError, match=r"hold neither 'forward_input_shape' nor 'batch_prob'"):
        RandomDefocusBlur().labels({"diameter": torch.tensor([3.0, 5.0])})


def test_params_from_metadata_is_the_noise_modules_alone():
    # the camera's parameters hold blur entries too: metadata alone cannot make them
    assert not hasattr(CameraCorruption, "params_from_metadata") and not hasattr(RandomDefocusBlur, "params_from_metadata")
    meta = CameraMetadata.preset("ICX285", batch_size=2)
    assert RandomSensorNoise.params_from_metadata(meta, seed=1)["noise_seed"].tolist() == [1, 1]


@pytest.mark.parametrize("name", ["defocus", "linear", "nonlinear"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_blur_kernels_are_built_in_the_physics_dtype(name, dtype):
    """float64 images are blurred with float64 kernels (float32 kernels left errors of ~2e-8), float32 images with
    float32 ones: the output is apply_psf with the kernel of the parameters built in that dtype."""
    from camhealth.physics.image_formation import apply_psf
    from camhealth.physics.motion_psf import linear_motion_psf, nonlinear_motion_psf

    aug = _modules()[name]()
    x = torch.rand(6, 1, 40, 40, dtype=dtype)
    y = aug(x)
    p = {k: v.to(dtype) for k, v in aug._params.items() if v.is_floating_point()}
    if name == "defocus":
        psf = defocus_psf(p["diameter"], aug._defocus_ks)
    elif name == "linear":
        psf = linear_motion_psf(p["length"], p["angle"], aug._motion_ks)
    else:
        psf = nonlinear_motion_psf(p["length"], p["angle"], p["intensity"], p["shake_noise"], aug._motion_ks)
    assert psf.dtype == dtype
    assert torch.allclose(y, apply_psf(x, psf).clamp(0, 1), rtol=0, atol=4 * torch.finfo(dtype).eps)


def test_camera_corruption_takes_only_its_components_positionally():
    """``CameraCorruption(None, blur, None, 0.5, True, True)`` was read as p = 0.5, same_on_batch and keepdim."""
    with pytest.raises(TypeError, match="positional"):
        CameraCorruption(None, RandomMotionBlur(), None, 0.5)
    cam = CameraCorruption(None, RandomMotionBlur(), None, p=0.5, same_on_batch=True, keepdim=True)
    assert cam.p == 0.5 and cam.same_on_batch and cam.keepdim
