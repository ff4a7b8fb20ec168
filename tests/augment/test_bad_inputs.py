"""Bad input to the corruption modules fails early with a message naming the argument or params entry, its value
and what is allowed: never a silently switched-off component, a
coerced flag, or a bare KeyError / torch RuntimeError."""

import inspect
import re

import numpy as np
import pytest
import torch

from camhealth.augment import CameraCorruption, RandomDefocusBlur, RandomMotionBlur, RandomSensorNoise
from camhealth.physics import CameraMetadata

X = torch.rand(4, 1, 16, 16)
MODULES = {
    "defocus": lambda **kw: RandomDefocusBlur((3.0, 7.0), **kw),
    "motion": lambda **kw: RandomMotionBlur((3.0, 7.0), intensity=(0.0, 1.0), **kw),
    "noise": lambda **kw: RandomSensorNoise(metadata="ICX285", **kw),
    "camera": lambda **kw: CameraCorruption(**kw),
}


def _params(mod, x=X):
    mod(x)
    return {k: v.clone() for k, v in mod._params.items()}


# ---------------------------------------------------------------------------------------------- constants on replay
@pytest.mark.parametrize("field, value", [("flicker_corner_hz", -1e9), ("source_follower_gain", 0.0),
                                          ("cds_sample_time_s", 0.0), ("cds_time_factor", 0.0), ("rtn_current_a", 1e3)])
@pytest.mark.parametrize("name", ["noise", "camera"])
def test_replayed_sensor_constants_are_checked(name, field, value):
    """Every row of const_<field> changed: NaN images, salt and pepper or a ZeroDivisionError before."""
    mod = MODULES[name]()
    params = _params(mod)
    params[f"const_{field}"] = torch.full((4,), value, dtype=torch.float64)
    with pytest.raises(ValueError, match=rf"^params const_{field} = .* is out of the allowed range"):
        mod(X, params=params)


# ---------------------------------------------------------------------------------------------- flags
@pytest.mark.parametrize("flag", ["same_on_batch", "keepdim"])
@pytest.mark.parametrize("value", ["no", 1, 0, None])
@pytest.mark.parametrize("name", sorted(MODULES))
def test_flags_must_be_bools(name, flag, value):
    """``same_on_batch="no"`` shared the parameters, ``keepdim="no"`` kept the dims."""
    with pytest.raises(TypeError, match=rf"^{flag} = .* must be True or False \(a bool\)"):
        MODULES[name](**{flag: value})


def test_numpy_bool_flags_are_bools():
    aug = RandomDefocusBlur((1.0, 9.0), same_on_batch=np.bool_(True), keepdim=np.bool_(False))
    aug(torch.rand(4, 1, 16, 16))
    assert aug.same_on_batch is True and aug.keepdim is False and len(set(aug._params["diameter"].tolist())) == 1


# ---------------------------------------------------------------------------------------------- CameraCorruption
@pytest.mark.parametrize("component", ["defocus", "motion", "noise"])
def test_camera_components_are_fixed_at_construction(component):
    """A new component assigned later was silently ignored (the kernel size and generator were the old ones)."""
    cam = CameraCorruption(RandomDefocusBlur(3.0), RandomMotionBlur(3.0), RandomSensorNoise())
    new = {"defocus": RandomDefocusBlur(40.0), "motion": RandomMotionBlur(40.0), "noise": RandomSensorNoise()}[component]
    with pytest.raises(AttributeError, match=rf"CameraCorruption.{component} is fixed at construction.*build a new "
                                             rf"CameraCorruption\({component}=...\)"):
        setattr(cam, component, new)
    with pytest.raises(AttributeError, match=rf"CameraCorruption.{component} is fixed at construction"):
        setattr(cam, component, None)
    with pytest.raises(AttributeError, match=rf"CameraCorruption.{component} is fixed at construction"):
        delattr(cam, component)
    cam.p = 0.5  # other attributes stay assignable
    cam.defocus.p = 0.5  # and a component's own p is read at every call
    assert cam.p == 0.5 and isinstance(getattr(cam, component), type(new))


# ---------------------------------------------------------------------------------------------- gates
@pytest.mark.parametrize("gate", ["defocus_gate", "motion_gate", "noise_gate"])
@pytest.mark.parametrize("value", [float("nan"), 7.0, 0.5, -1.0])
def test_replayed_gates_must_be_0_or_1(gate, value):
    """A NaN gate switched the component off silently (as 0); 7 was taken as 1."""
    cam = CameraCorruption()
    params = _params(cam)
    params[gate] = torch.full((4,), value)
    with pytest.raises(ValueError, match=rf"^params {gate} must hold 0 \(\w+ off\) or 1 \(\w+ on\) per sample, got"):
        cam(X, params=params)


def test_bool_gates_equal_float_gates():
    cam = CameraCorruption(RandomDefocusBlur((3.0, 7.0), p=0.5), RandomMotionBlur((3.0, 7.0), p=0.5),
                           RandomSensorNoise(p=0.5))
    x = torch.rand(8, 1, 16, 16)
    params = _params(cam, x)
    y = cam(x, params=params)
    as_bool = {k: (v > 0.5 if k.endswith("_gate") else v) for k, v in params.items()}
    assert torch.equal(cam(x, params=as_bool), y)


# ---------------------------------------------------------------------------------------------- ranges
@pytest.mark.parametrize("make, match", [
    (lambda: RandomDefocusBlur(("1", "3")), r"diameter must be a number or a \(low, high\) pair.*str"),
    (lambda: RandomDefocusBlur((True, 3)), r"diameter must be a number or a \(low, high\) pair.*bool"),
    (lambda: RandomDefocusBlur("3"), r"diameter must be a number or a \(low, high\) pair, got str"),
    (lambda: RandomMotionBlur(angle=(0, "90")), r"angle must be a number or a \(low, high\) pair.*str"),
    (lambda: RandomMotionBlur(intensity=(np.bool_(False), 1.0)), r"intensity must be a number or a \(low, high\) pair"),
    (lambda: RandomSensorNoise(ranges={"gain_db": (True, True)}), r"range for gain_db must be a \(low, high\) pair of numbers"),
    (lambda: RandomSensorNoise(ranges={"gain_db": ("a", "b")}), r"range for gain_db must be a \(low, high\) pair of numbers"),
    (lambda: RandomSensorNoise(ranges="gain_db"), r"ranges must be a mapping of field: \(low, high\)"),
    (lambda: RandomSensorNoise(ranges=[("gain_db", (0, 6))]), r"ranges must be a mapping of field: \(low, high\)"),
])
def test_strings_and_bools_are_no_range_numbers(make, match):
    with pytest.raises(TypeError, match=match):
        make()


@pytest.mark.parametrize("make, match", [
    (lambda: RandomSensorNoise(ranges={"gain_db": (1, 2, 3)}), r"range for gain_db must be a \(low, high\) pair, got 3 values"),
    (lambda: RandomDefocusBlur((1.0, 253.00001)), r"diameter = \(1.0, 253.00001\) must satisfy 0 ≤ low ≤ high ≤ 253"),
    (lambda: RandomDefocusBlur((1.0, 254.0)), r"diameter = \(1, 254\) must satisfy 0 ≤ low ≤ high ≤ 253"),
])
def test_bad_range_values_are_named(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_ranges_of_numbers_still_work():
    assert RandomDefocusBlur((np.float32(1.0), torch.tensor(3))).__class__ is RandomDefocusBlur
    aug = RandomSensorNoise(ranges={"gain_db": 6})  # one number: that value
    aug(X)
    assert aug._params["meta_gain_db"].tolist() == [6.0] * 4


# ---------------------------------------------------------------------------------------------- missing keys
@pytest.mark.parametrize("name, key", [("defocus", "diameter"), ("motion", "length"), ("motion", "angle"),
                                       ("motion", "intensity"), ("motion", "shake_noise"), ("noise", "noise_seed"),
                                       ("camera", "diameter"), ("camera", "length"), ("camera", "noise_seed"),
                                       ("noise", "meta_gain_db")])
def test_replay_without_a_key_names_it(name, key):
    mod = MODULES[name]()
    params = _params(mod)
    params["intensity"] = torch.full((4,), 0.5) if "intensity" in params else None  # (shake_noise is then needed)
    params = {k: v for k, v in params.items() if v is not None and k != key}
    with pytest.raises(ValueError, match=rf"params lack (\[|the metadata entry )?'{key}'"):
        mod(X, params=params)


# ---------------------------------------------------------------------------------------------- rows
@pytest.mark.parametrize("key", ["defocus_gate", "motion_gate", "noise_gate", "diameter", "length", "shake_noise",
                                 "meta_gain_db", "const_cds_gain", "noise_seed", "batch_prob"])
def test_params_of_another_batch_size_name_both_sizes(key):
    cam = CameraCorruption()
    params = _params(cam)
    params[key] = params[key][:2]
    with pytest.raises(ValueError, match=rf"^params {key} has 2 (values|rows) for a batch of 4 .*give one per sample \(4\)"):
        cam(X, params=params)
    with pytest.raises(ValueError, match=rf"^params {key} has 2 (values|rows) for a batch of 4"):
        cam.labels(params)


def test_params_of_one_row_apply_to_the_whole_batch():
    aug = RandomDefocusBlur((3.0, 7.0))
    params = _params(aug)
    one = {k: (v if k == "forward_input_shape" else v[:1]) for k, v in params.items()}
    y = aug(X, params=one)
    assert torch.equal(y, aug(X, params={k: (v if k == "forward_input_shape" else v[:1].expand(4)) for k, v in one.items()}))


# ---------------------------------------------------------------------------------------------- labels of broadcast params
def test_labels_after_params_of_batch_one_on_a_larger_batch():
    """params_from_metadata of batch-1 metadata on a batch of 4: the call worked, labels() claimed no call was made."""
    aug = RandomSensorNoise()
    x = torch.rand(4, 1, 16, 16)
    meta = CameraMetadata.preset("ICX285")
    y = aug(x, params=RandomSensorNoise.params_from_metadata(meta, seed=1))
    lab = aug.labels()
    ref = RandomSensorNoise()
    assert torch.equal(ref(x, params=RandomSensorNoise.params_from_metadata(meta.expand(4), seed=1)), y)
    want = ref.labels()
    assert lab["sigma_dn"].shape == (4, 3) and lab["metadata"].batch_size == 4
    for k in ("sigma_dn", "sigma_total_dn", "sigma_expected_dn", "clipped_fraction"):
        assert torch.equal(lab[k], want[k]), k


def test_blur_labels_after_params_of_batch_one():
    aug = RandomDefocusBlur((3.0, 7.0))
    params = _params(aug)
    one = {k: (torch.tensor([1, 1, 16, 16]) if k == "forward_input_shape" else v[:1]) for k, v in params.items()}
    aug(X, params=one)
    mtf = aug.labels()["mtf"]
    assert mtf.shape == (4, 16) and torch.equal(mtf, mtf[:1].expand(4, -1))


# ---------------------------------------------------------------------------------------------- sources and seeds
@pytest.mark.parametrize("sources", [None, 3])
def test_sources_must_be_names(sources):
    with pytest.raises(TypeError, match=r"^sources must be a noise source name or a sequence of them"):
        RandomSensorNoise(sources)


@pytest.mark.parametrize("seed, exc, match", [
    (2**70, ValueError, r"seed = 1180591620717411303424 is out of the allowed range \[-2\*\*63, 2\*\*63 - 1\]"),
    ([1, 2**64], ValueError, r"seed = 18446744073709551616 is out of the allowed range"),
    ("7", TypeError, r"seed must be an integer or a 1-D sequence of integers .*str"),
    ([1, "2"], TypeError, r"seed must be an integer or a 1-D sequence of integers .*str"),
    (True, TypeError, r"seed must be an integer .*bool"),
    (1.5, TypeError, r"seed must be an integer .*float"),
    (np.array([1.0, 2.0]), TypeError, r"seed must be an integer .*float64"),
])
def test_params_from_metadata_checks_the_seed(seed, exc, match):
    with pytest.raises(exc, match=match):
        RandomSensorNoise.params_from_metadata(CameraMetadata.preset("ICX285", batch_size=2), seed=seed)


def test_params_from_metadata_takes_integer_seeds_of_every_kind():
    meta = CameraMetadata.preset("ICX285", batch_size=3)
    for seed in ([0, 1, 2], (0, 1, 2), range(3), np.arange(3), torch.arange(3), torch.arange(3, dtype=torch.int32)):
        assert RandomSensorNoise.params_from_metadata(meta, seed=seed)["noise_seed"].tolist() == [0, 1, 2]
    for seed in (-5, np.int64(-5), torch.tensor(-5)):
        assert RandomSensorNoise.params_from_metadata(meta, seed=seed)["noise_seed"].tolist() == [-5] * 3
    assert RandomSensorNoise.params_from_metadata(meta, seed=2**63 - 1)["noise_seed"].dtype == torch.int64


@pytest.mark.parametrize("meta", [{"gain_db": 3.0}, "ICX285", None])
def test_params_from_metadata_needs_metadata(meta):
    with pytest.raises(TypeError, match=r"^meta must be a CameraMetadata"):
        RandomSensorNoise.params_from_metadata(meta)


# ---------------------------------------------------------------------------------------------- input
@pytest.mark.parametrize("shape", [(2, 1, 0, 16), (2, 1, 16, 0), (1, 0, 8)])
@pytest.mark.parametrize("name", sorted(MODULES))
def test_an_empty_height_or_width_names_the_input(name, shape):
    with pytest.raises(ValueError, match=r"^input must have a non-empty height and width"):
        MODULES[name]()(torch.rand(shape))


@pytest.mark.parametrize("dtype", [torch.uint8, torch.int64, torch.bool])
@pytest.mark.parametrize("name", sorted(MODULES))
def test_integer_input_gets_the_dn_hint(name, dtype):
    with pytest.raises(TypeError, match=r"^input must be a floating tensor .*convert integer DN images with x.float\(\) / 255"):
        MODULES[name]()(torch.ones(2, 1, 8, 8, dtype=dtype))


# ---------------------------------------------------------------------------------------------- input type and layout
@pytest.mark.parametrize("name", sorted(MODULES))
def test_an_image_that_is_no_tensor_is_named(name):
    """A list image failed inside Kornia with AttributeError: 'list' object has no attribute 'shape'."""
    with pytest.raises(TypeError, match=r"^input must be a torch.Tensor, got list"):
        MODULES[name]()([[0.5, 0.5], [0.5, 0.5]])


@pytest.mark.parametrize("params", [[1, 2], torch.ones(4)])
@pytest.mark.parametrize("name", sorted(MODULES))
def test_params_that_are_no_dict_are_named(name, params):
    """A list failed inside Kornia with 'list indices must be integers', a tensor with Tensor.__contains__'s error."""
    with pytest.raises(TypeError, match=r"^params must be a dict of parameter tensors .*got (list|Tensor)"):
        MODULES[name]()(X, params=params)


@pytest.mark.parametrize("shape", [(), (16,), (2, 2, 1, 16, 16), (1, 2, 2, 1, 16, 16)])
@pytest.mark.parametrize("name", sorted(MODULES))
def test_images_of_other_dims_name_the_allowed_layouts(name, shape):
    """Kornia's message offered "(*, C, H, W)" and then refused a 5-D batch."""
    with pytest.raises(ValueError, match=rf"^input must have shape B×C×H×W, C×H×W or H×W \(2 to 4 dims\), got shape "
                                         rf"{re.escape(str(shape))}"):
        MODULES[name]()(torch.rand(shape))


@pytest.mark.parametrize("name", sorted(MODULES))
def test_an_image_without_channels_is_named(name):
    """B×0×H×W failed deep in the image formation (aminmax over an empty dimension)."""
    with pytest.raises(ValueError, match=r"^input must have at least one channel \(C ≥ 1; an empty batch is allowed\), "
                                         r"got shape \(2, 0, 8, 8\)"):
        MODULES[name]()(torch.rand(2, 0, 8, 8))
    assert MODULES[name]()(torch.rand(0, 0, 8, 8)).shape == (0, 0, 8, 8)  # an empty batch stays allowed


@pytest.mark.parametrize("name", sorted(MODULES))
def test_a_sparse_image_is_named(name):
    """A sparse image failed with NotImplementedError: Could not run 'aten::aminmax' ... 'SparseCPU'."""
    with pytest.raises(TypeError, match=r"^input must be a dense tensor, got layout torch.sparse_coo"):
        MODULES[name]()(X.to_sparse())


# ---------------------------------------------------------------------------------------------- values of replayed params
@pytest.mark.parametrize("name, key", [("defocus", "diameter"), ("motion", "length"), ("motion", "angle"),
                                       ("motion", "intensity"), ("camera", "diameter"), ("camera", "length")])
@pytest.mark.parametrize("kind", ["float", "list", "ndarray"])
def test_blur_params_as_numbers_lists_or_arrays_replay_as_tensors(name, key, kind):
    """A number, list or array failed with AttributeError: 'float' object has no attribute 'to' (the gates, the
    metadata and the seed took them)."""
    mod = MODULES[name]()
    params = _params(mod)
    y = mod(X, params=params)
    as_kind = {"float": lambda v: float(v[0]), "list": lambda v: v.tolist(), "ndarray": lambda v: v.numpy()}[kind]
    given = dict(params, **{key: as_kind(params[key])})
    want = y if kind != "float" else mod(X, params=dict(params, **{key: params[key][:1].expand(4)}))
    assert torch.equal(mod(X, params=given), want)


@pytest.mark.parametrize("name, key", [("defocus", "diameter"), ("motion", "length"), ("motion", "angle"),
                                       ("motion", "intensity"), ("motion", "shake_noise"), ("camera", "diameter")])
def test_bool_blur_params_are_refused(name, key):
    """A bool diameter or length was read as 1 px (and a False one as no blur) without a word."""
    mod = MODULES[name]()
    params = _params(mod)
    params[key] = params[key] > 0
    with pytest.raises(TypeError, match=rf"^params {key} must hold real numbers .*got dtype torch.bool"):
        mod(X, params=params)


@pytest.mark.parametrize("key", ["defocus_gate", "noise_gate", "motion_gate"])
def test_a_list_of_another_batch_size_names_the_key(key):
    """A gate given as a list of 3 for a batch of 4 failed with torch's 'The size of tensor a (3) must match'."""
    cam = CameraCorruption()
    params = _params(cam)
    params[key] = params[key][:3].tolist()
    with pytest.raises(ValueError, match=rf"^params {key} has 3 values for a batch of 4"):
        cam(X, params=params)


@pytest.mark.parametrize("value", [float("nan"), 0.7, 2.0, -1.0])
@pytest.mark.parametrize("name", sorted(MODULES))
def test_replayed_batch_prob_must_be_0_or_1(name, value):
    """Kornia applies a sample whose batch_prob is above 0.5: NaN left the sample untouched, 0.7 transformed it."""
    mod = MODULES[name](p=0.5)
    params = _params(mod)
    params["batch_prob"] = torch.full((4,), value)
    with pytest.raises(ValueError, match=r"^params batch_prob must hold 0 \(sample left untouched\) or 1 \(transformed\) "
                                         r"per sample, got"):
        mod(X, params=params)
    with pytest.raises(ValueError, match=r"^params batch_prob must hold 0"):
        mod.labels(params)


@pytest.mark.parametrize("name", sorted(MODULES))
def test_replayed_batch_prob_of_bools_or_0_and_1(name):
    mod = MODULES[name](p=0.5)
    params = _params(mod)
    params["batch_prob"] = torch.tensor([1.0, 0.0, 1.0, 0.0])
    y = mod(X, params=params)
    assert torch.equal(y[1], X[1]) and torch.equal(y[3], X[3]) and not torch.equal(y[0], X[0])
    assert torch.equal(mod(X, params=dict(params, batch_prob=params["batch_prob"] > 0.5)), y)
    params["batch_prob"] = [1.0, 0.0, 1.0, 0.0]
    with pytest.raises(TypeError, match=r"^params batch_prob must be a tensor of 0 or 1 per sample, got list"):
        mod(X, params=params)


@pytest.mark.parametrize("name", ["noise", "camera"])
def test_bool_sensor_constants_are_refused(name):
    """const_cds_gain = True was read as a CDS gain of 1."""
    mod = MODULES[name]()
    params = _params(mod)
    params["const_cds_gain"] = torch.ones(4, dtype=torch.bool)
    with pytest.raises(TypeError, match=r"^params const_cds_gain must hold real numbers .*got dtype torch.bool"):
        mod(X, params=params)


# ---------------------------------------------------------------------------------------------- kernel sizes
@pytest.mark.parametrize("make, match, fits", [
    (lambda ks: RandomDefocusBlur(3.0, kernel_size=ks), r"^diameter up to 3 px does not fit kernel_size = 1, which holds "
     r"diameters up to 1 px: pass an odd kernel_size ≥ 3, or leave it unset \(then 5\)$", 3),
    (lambda ks: RandomDefocusBlur((1.0, 40.5), kernel_size=ks), r"^diameter up to 40.5 px does not fit kernel_size = 1, "
     r"which holds diameters up to 1 px: pass an odd kernel_size ≥ 41, or leave it unset \(then 43\)$", 41),
    (lambda ks: RandomMotionBlur(0.5, kernel_size=ks), r"^length up to 0.5 px does not fit kernel_size = 1, which holds "
     r"lengths up to 0 px: pass an odd kernel_size ≥ 3, or leave it unset \(then 5\)$", 3),
    (lambda ks: RandomMotionBlur(41.0, intensity=1.0, kernel_size=ks), r"^length up to 41 px does not fit kernel_size = 1, "
     r"which holds lengths up to 0 px: pass an odd kernel_size ≥ 43, or leave it unset \(then 45\)$", 43),
])
def test_a_kernel_too_small_names_the_sizes_that_fit(make, match, fits):
    """The message named the kernel but not what fits."""
    with pytest.raises(ValueError, match=match):
        make(1)
    with pytest.raises(ValueError, match="does not fit"):
        make(fits - 2)
    assert make(fits)(torch.rand(2, 1, 48, 48)).shape == (2, 1, 48, 48)


# ---------------------------------------------------------------------------------------------- reprs and documented defaults
@pytest.mark.parametrize("make, shown", [
    (lambda: RandomDefocusBlur((2.0, 5.0), kernel_size=41, keepdim=True), ["diameter=(2.0, 5.0)", "keepdim=True",
                                                                           "kernel_size=41"]),
    (lambda: RandomDefocusBlur(), ["diameter=(1.0, 21.0)", "keepdim=False", "kernel_size=23"]),
    (lambda: RandomMotionBlur(5.0, kernel_size=11), ["length=(5.0, 5.0)", "keepdim=False", "kernel_size=11"]),
    (lambda: RandomSensorNoise(gain_uniform_in="db", keepdim=True), ["gain_uniform_in='db'", "keepdim=True"]),
    (lambda: CameraCorruption(keepdim=True), ["kernel_size=23", "kernel_size=25", "gain_uniform_in='factor'",
                                              "same_on_batch=False, keepdim=True)"]),
])
def test_the_repr_names_the_kernel_size_keepdim_and_gain_sampling(make, shown):
    """kernel_size, keepdim and gain_uniform_in change the output but were missing from the repr."""
    text = repr(make())
    for part in shown:
        assert part in text, (part, text)


@pytest.mark.parametrize("cls, arg, documented", [
    (RandomDefocusBlur, "p", "Default 1"), (RandomDefocusBlur, "same_on_batch", "Default False"),
    (RandomDefocusBlur, "keepdim", "Default False"),
    (RandomMotionBlur, "p", "Default p = 1"), (RandomSensorNoise, "p", "Default p = 1"),
    (CameraCorruption, "p", "Default p = 1"), (RandomMotionBlur, "keepdim", "keepdim = False"),
    (RandomSensorNoise, "gain_uniform_in", '``"factor"`` (thesis; default)'), (RandomSensorNoise, "sources", "Default: all three"),
    (RandomMotionBlur, "angle", "in [-360, 360]"),
])
def test_the_docstrings_state_the_defaults_and_ranges_of_the_code(cls, arg, documented):
    """Three modules documented p only as "as in Kornia", whose default is 0.5; the noise module left the defaults of
    sources and gain_uniform_in unstated, the motion blur the range of angle."""
    doc = " ".join(cls.__doc__.split())
    assert " ".join(documented.split()) in doc, (cls.__name__, arg)
    default = inspect.signature(cls).parameters[arg].default
    expected = {"p": 1.0, "same_on_batch": False, "keepdim": False, "gain_uniform_in": "factor",
                "sources": ("photon", "dark", "readout"), "angle": (0.0, 180.0)}[arg]
    assert default == expected
    if arg == "angle":
        with pytest.raises(ValueError, match=r"-360 ≤ low ≤ high ≤ 360"):
            cls(angle=(0.0, 361.0))
