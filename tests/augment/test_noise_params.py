"""The noise modules' parameters: fixed sensor constants, per-sample noise seeds, metadata given as a dict."""

import pytest
import torch

from camhealth.augment import CameraCorruption, RandomDefocusBlur, RandomMotionBlur, RandomSensorNoise
from camhealth.physics.image_formation import form_image
from camhealth.physics.metadata import CameraMetadata, SensorConstants
from camhealth.physics.readout_noise import readout_sigma_dn

CUSTOM = SensorConstants(cds_sample_time_s=0.5e-6, flicker_corner_hz=1e4)


def _with_constants(meta: CameraMetadata, constants: SensorConstants) -> CameraMetadata:
    return CameraMetadata(**{n: getattr(meta, n) for n in meta.to_dict()}, constants=constants)


def _sub(params, idx, shape):
    """The parameters of the samples ``idx`` (a sub-batch of shape ``shape``)."""
    i = torch.as_tensor(idx)
    return {k: (torch.tensor(shape) if k == "forward_input_shape" else v[i]) for k, v in params.items()}


@pytest.fixture(params=["torch", "counter"])
def rng(request):
    return request.param


# ---------------------------------------------------------------------------------------------- sensor constants
def test_custom_sensor_constants_are_used_for_noise_and_labels(rng):
    """A CameraMetadata with its own SensorConstants (t_s = 0.5 µs, f_c = 10 kHz: σ_RN 0.678 DN instead of the
    defaults' 0.908 DN at 12 dB) is corrupted and labelled with them, given as the module's metadata or as params."""
    meta = _with_constants(CameraMetadata.preset("ICX285", gain_db=12.0), CUSTOM)
    want = float(readout_sigma_dn(meta))
    assert want == pytest.approx(0.678, abs=1e-3) and float(readout_sigma_dn(_with_constants(meta, SensorConstants()))) > 0.9
    x = torch.full((2, 1, 96, 96), 0.5)
    aug = RandomSensorNoise(sources=("readout",), metadata=meta, rng=rng)
    y = aug(x)
    lab = aug.labels()
    assert lab["metadata"].constants == CUSTOM
    assert torch.allclose(lab["sigma_expected_dn"][:, 2], torch.full((2,), want, dtype=lab["sigma_expected_dn"].dtype))
    assert torch.allclose(lab["sigma_dn"][:, 2], lab["sigma_expected_dn"][:, 2], rtol=0.05)
    ref = form_image(x, meta.expand(2), sources=("readout",), rng=rng,
                     generator=torch.Generator().manual_seed(int(aug._params["noise_seed"][0])))
    assert torch.equal(y, ref.image)
    assert torch.equal(aug(x, params=aug._params), y)  # the replay keeps them
    plain = RandomSensorNoise(sources=("readout",), rng=rng)  # params_from_metadata carries them too
    plain(x, params=RandomSensorNoise.params_from_metadata(meta.expand(2), seed=0))
    assert plain.labels()["metadata"].constants == CUSTOM
    assert torch.allclose(plain.labels()["sigma_expected_dn"][:, 2].double(), torch.full((2,), want, dtype=torch.float64))


def test_the_source_follower_cache_follows_the_constants():
    """One module, the same W, clock, A_SN and sensor type, other constants: σ_RN must follow the constants."""
    base = CameraMetadata.preset("ICX285", batch_size=2, gain_db=12.0)
    aug = RandomSensorNoise(sources=("readout",))
    x = torch.full((2, 1, 16, 16), 0.5)
    aug(x, params=RandomSensorNoise.params_from_metadata(base, seed=0))
    default = aug.labels()["sigma_expected_dn"][:, 2].clone()
    aug(x, params=RandomSensorNoise.params_from_metadata(_with_constants(base, CUSTOM), seed=0))
    custom = aug.labels()["sigma_expected_dn"][:, 2]
    assert torch.allclose(default.double(), readout_sigma_dn(base).double())
    assert torch.allclose(custom.double(), readout_sigma_dn(_with_constants(base, CUSTOM)).double())


@pytest.mark.parametrize("preset", ["ICX285", "EV76C661"])
@pytest.mark.parametrize("dtype", [torch.float16, torch.float32, torch.float64])
def test_a_presets_noise_is_form_image_with_its_constants(preset, dtype, rng):
    """The parameters carry the preset's constants (the EV76C661's 3.3 V reference voltage, read by no noise
    formula): the module's output is exactly form_image's for the preset, as with the default constants."""
    meta = CameraMetadata.preset(preset, batch_size=3, gain_db=[0.0, 12.0, 24.0], temperature_c=60.0)
    x = torch.rand(3, 1, 24, 24).to(dtype)
    aug = RandomSensorNoise(rng=rng)
    params = RandomSensorNoise.params_from_metadata(meta, seed=11)
    assert params["const_reference_voltage_v"].tolist() == [meta.constants.reference_voltage_v] * 3
    y = aug(x, params=params)
    ref = form_image(x, meta, generator=torch.Generator().manual_seed(11), rng=rng)
    assert torch.equal(y, ref.image) and torch.equal(aug.labels()["sigma_dn"], ref.sigma_dn)
    assert aug.labels()["metadata"].constants == meta.constants


def test_constants_in_params_must_be_one_value_for_the_batch():
    meta = CameraMetadata.preset("ICX285", batch_size=2)
    params = RandomSensorNoise.params_from_metadata(meta, seed=0)
    params["const_cds_sample_time_s"] = torch.tensor([1e-6, 2e-6], dtype=torch.float64)
    with pytest.raises(ValueError, match=r"const_cds_sample_time_s = \[1e-06, 2e-06\] must hold one finite value"):
        RandomSensorNoise()(torch.rand(2, 1, 8, 8), params=params)
    del params["const_cds_sample_time_s"]
    with pytest.raises(ValueError, match=r"lack \['const_cds_sample_time_s'\]"):
        RandomSensorNoise()(torch.rand(2, 1, 8, 8), params=params)


# ---------------------------------------------------------------------------------------------- metadata dicts
def test_metadata_dict_is_read_as_from_dict():
    aug = RandomSensorNoise(metadata={"sensor_type": "CMOS", "gain_db": 6.0})
    aug(torch.rand(3, 1, 8, 8))
    assert aug.labels()["metadata"].is_cmos.tolist() == [1.0, 1.0, 1.0]
    with pytest.raises(ValueError, match=r"unknown metadata field\(s\) \['gain'\]; known fields"):
        RandomSensorNoise(metadata={"gain": 6.0})
    with pytest.raises(ValueError, match="sensor_type = 'DSLR' is not one of"):
        RandomSensorNoise(metadata={"sensor_type": "DSLR"})


# ---------------------------------------------------------------------------------------------- noise seeds
def _modules(rng):
    return {
        "noise": RandomSensorNoise(rng=rng),
        "camera": CameraCorruption(RandomDefocusBlur((1.0, 7.0)), RandomMotionBlur((1.0, 7.0), intensity=(0.0, 1.0)),
                                   RandomSensorNoise(rng=rng)),
    }


@pytest.mark.parametrize("name", ["noise", "camera"])
@pytest.mark.parametrize("dtype", [torch.float16, torch.float32, torch.float64])
def test_per_sample_seeds_replay_in_any_sub_batch(name, dtype, rng):
    """With a seed per sample, each sample's noise depends on its own seed only: the replay of any sub-batch with its
    slice of the params gives the same samples and labels (the blur parameters always did)."""
    aug = _modules(rng)[name]
    x = torch.rand(5, 1, 24, 24).to(dtype)
    aug(x)
    params = dict(aug._params)
    params["noise_seed"] = torch.tensor([10, 11, 12, 13, 14])
    y = aug(x, params=params)
    lab = aug.labels()
    for idx in ([2, 3], [4], [0, 3, 4]):
        ys = aug(x[idx], params=_sub(params, idx, [len(idx), 1, 24, 24]))
        assert torch.equal(ys, y[idx])
        sub = aug.labels()
        for key in ("sigma_dn", "sigma_total_dn", "sigma_expected_dn", "clipped_fraction"):
            assert torch.equal(sub[key], lab[key][idx]), key


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_sample_with_its_own_seed_is_form_image_of_that_sample(dtype, rng):
    meta = CameraMetadata.preset("ICX285", batch_size=4, gain_db=[0.0, 8.0, 16.0, 24.0])
    x = torch.rand(4, 1, 32, 32, dtype=dtype)
    aug = RandomSensorNoise(rng=rng)
    y = aug(x, params=RandomSensorNoise.params_from_metadata(meta, seed=[5, 6, 7, 8]))
    for i, s in enumerate([5, 6, 7, 8]):
        alone = form_image(x[i : i + 1], meta[i], generator=torch.Generator().manual_seed(s), rng=rng)
        assert torch.equal(y[i : i + 1], alone.image)


def test_samples_that_share_a_seed_draw_together():
    """Seeds [3, 9, 3, 4, 9]: samples 0 and 2 are one batch of seed 3 (in batch order), 1 and 4 one of seed 9, 3 alone;
    a sub-batch of whole seed groups replays exactly."""
    meta = CameraMetadata.preset("EV76C661", batch_size=5, gain_db=18.0)
    x = torch.rand(5, 1, 16, 16)
    aug = RandomSensorNoise()
    seeds = [3, 9, 3, 4, 9]
    params = RandomSensorNoise.params_from_metadata(meta, seed=seeds)
    y = aug(x, params=params)
    for s, idx in ((3, [0, 2]), (9, [1, 4]), (4, [3])):
        ref = form_image(x[idx], meta[idx], generator=torch.Generator().manual_seed(s))
        assert torch.equal(y[idx], ref.image)
    assert torch.equal(aug(x[[0, 2, 3]], params=_sub(params, [0, 2, 3], [3, 1, 16, 16])), y[[0, 2, 3]])


@pytest.mark.parametrize("batch", [1, 4])
def test_one_seed_for_the_batch_is_one_stream(batch, rng):
    """A scalar seed, a (B,) seed of equal values and the generator's own draw all corrupt the batch in one pass,
    as form_image with a generator seeded with it (the data the training and benchmarks are made of)."""
    meta = CameraMetadata.preset("ICX285", batch_size=batch, gain_db=24.0)
    x = torch.rand(batch, 1, 16, 16)
    aug = RandomSensorNoise(rng=rng)
    ref = form_image(x, meta, generator=torch.Generator().manual_seed(7), rng=rng).image
    params = RandomSensorNoise.params_from_metadata(meta, seed=7)
    assert params["noise_seed"].tolist() == [7] * batch
    assert torch.equal(aug(x, params=params), ref)
    params["noise_seed"] = torch.tensor(7)
    assert torch.equal(aug(x, params=params), ref)
    y = aug(x)
    drawn = aug._params["noise_seed"]
    assert bool((drawn == drawn[0]).all())
    ref = form_image(x, aug.labels()["metadata"], generator=torch.Generator().manual_seed(int(drawn[0])), rng=rng).image
    assert torch.equal(y, ref)


def test_seed_errors():
    meta = CameraMetadata.preset("ICX285", batch_size=3)
    with pytest.raises(ValueError, match="seed has 2 values for metadata of batch size 3"):
        RandomSensorNoise.params_from_metadata(meta, seed=[1, 2])
    with pytest.raises(TypeError, match="seed must be an integer or a 1-D sequence of integers"):
        RandomSensorNoise.params_from_metadata(meta, seed=1.5)
    params = RandomSensorNoise.params_from_metadata(meta, seed=1)
    params["noise_seed"] = torch.tensor([1, 2])
    with pytest.raises(ValueError, match="noise_seed has 2 values for a batch of 3"):
        RandomSensorNoise()(torch.rand(3, 1, 8, 8), params=params)
