"""NoiseDataModule: real labelled batches, physics-consistent labels, ξ, determinism, Lightning/CLI use."""

from __future__ import annotations

from dataclasses import fields

from pathlib import Path

import lightning as L
import pytest
import torch

from camhealth.augment import RandomSensorNoise
from camhealth.physics import FULL_FIELDS, CameraMetadata, form_image
from camhealth.physics.image_formation import ImageFormation
from datamodules import NoiseDataModule, expected_sigma_dn
from tests.datamodules.conftest import SMALL, textured

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _clean(b: int = 8, size: int = 32) -> torch.Tensor:
    return torch.stack([torch.from_numpy(textured(size, i)).float()[None] for i in range(b)])


def test_default_source_yields_real_labelled_batches():
    dm = NoiseDataModule(batch_size=8, val_patches_per_image=8)  # embedded default data, no network
    dm.setup("validate")  # only the validation image(s): fast
    batch = dm.on_after_batch_transfer(next(iter(dm.val_dataloader())), 0)
    b = 8
    assert batch["image"].shape == batch["clean"].shape == (b, 1, 128, 128)
    assert batch["meta_raw"].shape == batch["meta_image_raw"].shape == (b, 11)
    assert batch["meta"].shape == (b, 11)  # full metadata set by default
    assert batch["sigma"].shape == batch["sigma_expected"].shape == (b, 3)
    for k in ("sigma_total", "xi", "xi_norm", "altered"):
        assert batch[k].shape == (b,)
    assert batch["altered"].dtype == torch.bool
    assert 0 <= float(batch["image"].min()) and float(batch["image"].max()) <= 1
    assert (batch["sigma"] >= 0).all() and (batch["sigma_total"] > 0).all()
    assert not torch.equal(batch["image"], batch["clean"])
    assert torch.allclose(batch["xi_norm"] * 255, batch["xi"])
    assert all(s == "val" for s in batch["stage"])


def test_default_source_training_batch():
    dm = NoiseDataModule(batch_size=4, patches_per_image=1)
    batch = dm.on_after_batch_transfer(next(iter(dm.train_dataloader())), 0)
    assert batch["image"].shape == (4, 1, 128, 128) and batch["stage"] == ["train"] * 4
    assert torch.isfinite(batch["sigma"]).all()


def test_same_seed_gives_same_validation_batch(image_folder):
    def first_val(seed):
        dm = NoiseDataModule(source=str(image_folder), seed=seed, **SMALL)
        dm.setup("validate")
        torch.manual_seed(seed + 123)  # the global RNG must not matter for validation
        return dm.on_after_batch_transfer(next(iter(dm.val_dataloader())))

    a, b = first_val(0), first_val(0)
    for k in ("image", "clean", "meta_raw", "sigma", "xi", "altered"):
        assert torch.equal(a[k], b[k]), k
    assert a["image_id"] == b["image_id"]
    c = first_val(0)
    torch.manual_seed(999)
    assert torch.equal(c["image"], a["image"])


def test_training_corruption_is_random():
    dm = NoiseDataModule(source="unused", **SMALL)
    clean = _clean(4)
    a, b = dm.corrupt(clean, None), dm.corrupt(clean, None)
    assert not torch.equal(a["meta_raw"], b["meta_raw"]) and not torch.equal(a["image"], b["image"])


def test_labels_match_the_physics_core(image_folder):
    dm = NoiseDataModule(source=str(image_folder), xi_probability=0.5, **{**SMALL, "batch_size": 8})
    dm.setup("validate")
    batch = next(iter(dm.val_dataloader()))
    out = dm.on_after_batch_transfer(batch)
    # replay the parameter draws of this validation batch: each patch from its own seed
    draws = []
    for i in batch["index"]:
        g = dm.sample_generator("val", int(i))
        m, mi, alt = dm.sample_metadata(1, g)
        draws.append((m, mi, alt, int(torch.randint(0, 2**62, (1,), generator=g))))
    meta = CameraMetadata.cat([d[0] for d in draws])
    meta_img = CameraMetadata.cat([d[1] for d in draws])
    altered = torch.cat([d[2] for d in draws])
    parts = [form_image(batch["clean"][k : k + 1], d[1], generator=torch.Generator().manual_seed(d[3])) for k, d in enumerate(draws)]
    ref = ImageFormation(*(torch.cat([getattr(q, f.name) for q in parts]) for f in fields(ImageFormation)))
    assert torch.equal(out["image"], ref.image)
    aug = RandomSensorNoise()  # the Kornia module on the same parameters gives the same image
    params = RandomSensorNoise.params_from_metadata(draws[0][1], draws[0][3])
    assert torch.allclose(aug(batch["clean"][:1], params=params), out["image"][:1])
    assert torch.allclose(out["sigma"], ref.sigma_dn.float())
    assert torch.allclose(out["sigma_total"], ref.sigma_total_dn.float())
    assert torch.allclose(out["sigma_expected"], ref.sigma_expected_dn.float())  # labels refer to M'
    assert torch.equal(out["altered"], altered)
    raw = torch.stack([getattr(meta, n) for n in FULL_FIELDS], 1)
    assert torch.equal(out["meta_raw"], raw) and torch.equal(out["meta"], meta.normalize("full"))
    # ξ = analytic total under M − analytic total under M' (thesis Eq. 4.3)
    ref_m = form_image(batch["clean"], meta, generator=torch.Generator().manual_seed(1))
    xi = ref_m.sigma_total_expected_dn - ref.sigma_total_expected_dn
    assert torch.allclose(out["xi"], xi.float(), rtol=1e-4, atol=1e-4)


def test_expected_sigma_matches_form_image():
    meta = CameraMetadata.sample(6, generator=torch.Generator().manual_seed(0))
    clean = _clean(6)
    ref = form_image(clean, meta).sigma_expected_dn
    assert torch.allclose(expected_sigma_dn(clean, meta), ref)
    only = expected_sigma_dn(clean, meta, ("photon",))
    assert torch.equal(only[:, 1:], torch.zeros(6, 2)) and torch.allclose(only[:, 0], ref[:, 0])


def test_xi_is_zero_when_metadata_agree_and_negative_when_the_image_is_noisier():
    dm = NoiseDataModule(source="unused", **SMALL)
    clean = _clean(8)
    meta = CameraMetadata.sample(8, generator=torch.Generator().manual_seed(1), ranges={"gain_db": (0.0, 12.0)})
    same = dm.corrupt_with(clean, meta, meta, noise_seed=3)
    assert torch.equal(same["xi"], torch.zeros(8)) and not same["altered"].any()
    noisier = dm.corrupt_with(clean, meta, meta.replace(gain_db=meta.gain_db + 6.0), noise_seed=3)
    assert (noisier["xi"] < 0).all() and noisier["altered"].all()
    assert (noisier["sigma_total"] > same["sigma_total"]).all()  # the image really is noisier
    colder = dm.corrupt_with(clean, meta, meta.replace(temperature_c=torch.zeros(8)), 3)
    # a colder sensor than reported: less dark-current noise than the metadata say → ξ ≥ 0
    assert (colder["xi"] >= 0).all() and float(colder["xi"].max()) > 0

    # the sampled ξ cases: sign follows the altered gain
    dm1 = NoiseDataModule(source="unused", xi_probability=1.0, xi_fields=["gain_db"], **SMALL)
    out = dm1.corrupt(_clean(32), torch.Generator().manual_seed(0))
    dg = out["meta_image_raw"][:, 0] - out["meta_raw"][:, 0]
    assert out["altered"].all()
    assert (out["xi"][dg > 0.1] < 0).all() and (out["xi"][dg < -0.1] > 0).all()
    assert torch.equal(out["meta_image_raw"][:, 1:], out["meta_raw"][:, 1:])  # only the gain differs
    dm0 = NoiseDataModule(source="unused", xi_probability=0.0, **SMALL)
    out0 = dm0.corrupt(_clean(8), None)
    assert torch.equal(out0["xi"], torch.zeros(8)) and torch.equal(out0["meta_raw"], out0["meta_image_raw"])


def test_metadata_sets_and_sensor_preset():
    clean = _clean(4)
    for name, k in (("none", 0), ("minimal", 3), ("full", 11)):
        out = NoiseDataModule(source="unused", metadata_set=name, **SMALL).corrupt(clean, None)
        assert out["meta"].shape == (4, k)
    dm = NoiseDataModule(source="unused", sensor="ICX285", xi_probability=0.0, metadata_ranges={"gain_db": (0.0, 6.0)}, **SMALL)
    out = dm.corrupt(clean, None)
    fw = FULL_FIELDS.index("full_well_e")
    assert torch.equal(out["meta_raw"][:, fw], torch.full((4,), 14000.0))
    assert (out["meta_raw"][:, 0] <= 6.0).all()
    with pytest.raises(ValueError, match="metadata_set"):
        NoiseDataModule(metadata_set="some")
    with pytest.raises(ValueError, match="xi_fields"):
        NoiseDataModule(xi_fields=["colour"])


def test_trainer_calls_the_hook_and_validation_repeats(image_folder):
    seen = {"train": [], "val": []}

    class Probe(L.LightningModule):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.zeros(1))

        def training_step(self, batch, i):
            seen["train"].append(batch["xi"].clone())
            return (self.w * batch["image"].mean()).sum()

        def validation_step(self, batch, i):
            seen["val"].append(batch["image"].clone())

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.0)

    dm = NoiseDataModule(source=str(image_folder), **SMALL)
    trainer = L.Trainer(
        max_epochs=2, limit_train_batches=2, limit_val_batches=1, num_sanity_val_steps=0, logger=False,
        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False, accelerator="cpu",
    )
    trainer.fit(Probe(), datamodule=dm)
    assert len(seen["train"]) == 4 and len(seen["val"]) == 2
    assert torch.equal(seen["val"][0], seen["val"][1])  # fixed validation corruption across epochs
    assert dm.throughput_stats()["patches"] == 6 * 4


def test_yaml_config_instantiates_with_lightning_cli():
    from lightning.pytorch import cli as lcli

    if not lcli._JSONARGPARSE_SIGNATURES_AVAILABLE:
        pytest.skip("jsonargparse[signatures] is not installed (it is a declared dependency)")
    LightningCLI = lcli.LightningCLI

    class Tiny(L.LightningModule):
        pass

    cli = LightningCLI(Tiny, run=False, args=["--config", str(CONFIGS / "data_noise.yaml"), "--trainer.logger=false"])
    assert isinstance(cli.datamodule, NoiseDataModule)
    assert cli.datamodule.patch_size == 128 and cli.datamodule.metadata_set == "full"


def test_corruption_runs_on_the_batch_device(device):
    dm = NoiseDataModule(source="unused", **SMALL)
    batch = {"clean": _clean(4).to(device), "index": torch.arange(4, device=device), "stage": ["val"] * 4}
    out = dm.on_after_batch_transfer(batch, 0)
    assert all(v.device.type == device.type for v in out.values() if isinstance(v, torch.Tensor))
    again = dm.on_after_batch_transfer({**batch}, 0)
    assert torch.equal(out["image"], again["image"])


def test_train_rng_counter_applies_to_training_batches_only():
    clean = _clean(8)
    fast, plain = NoiseDataModule(source="unused", train_rng="counter", **SMALL), NoiseDataModule(source="unused", **SMALL)
    torch.manual_seed(0)
    a = fast.on_after_batch_transfer({"clean": clean, "stage": ["train"] * 8})
    torch.manual_seed(0)
    assert torch.equal(a["image"], fast.corrupt(clean, None, rng="counter")["image"])
    torch.manual_seed(0)
    b = plain.on_after_batch_transfer({"clean": clean, "stage": ["train"] * 8})
    assert not torch.equal(a["image"], b["image"])  # other random numbers ...
    assert torch.equal(a["meta_raw"], b["meta_raw"])  # ... for the same metadata draw
    ratio = a["sigma"].sum(0) / a["sigma_expected"].sum(0)  # and the same physics
    assert torch.allclose(ratio, b["sigma"].sum(0) / b["sigma_expected"].sum(0), rtol=0.05)
    val = {"clean": clean, "index": torch.arange(8), "stage": ["val"] * 8}
    assert torch.equal(fast.on_after_batch_transfer(dict(val))["image"], plain.on_after_batch_transfer(dict(val))["image"])
    with pytest.raises(ValueError, match="rng must be one of"):
        NoiseDataModule(source="unused", train_rng="philox", **SMALL)


def test_held_out_corruption_is_per_patch_whatever_the_batch_size(image_folder):
    def val_by_index(batch_size):
        dm = NoiseDataModule(source=str(image_folder), **{**SMALL, "batch_size": batch_size})
        dm.setup("validate")
        out = {}
        for batch in dm.val_dataloader():
            b = dm.on_after_batch_transfer(batch)
            for k, i in enumerate(b["index"].tolist()):
                out[i] = (b["image"][k], b["meta_raw"][k])
        return out

    a, b = val_by_index(4), val_by_index(3)
    assert sorted(a) == sorted(b) and len(a) > 4
    for i in a:
        assert torch.equal(a[i][0], b[i][0]) and torch.equal(a[i][1], b[i][1])


def test_training_corruption_differs_per_rank_of_a_multi_process_run():
    from types import SimpleNamespace

    dm = NoiseDataModule(source="unused", **SMALL)
    assert dm.train_generator() is None  # single process: torch's global generator, as seeded by seed_everything
    draws = []
    for rank in (0, 1):
        dm.trainer = SimpleNamespace(world_size=2, global_rank=rank, training=True)
        torch.manual_seed(0)  # seed_everything: the same global state on every rank
        draws.append(dm.corrupt(_clean(4), dm.train_generator()))
    assert not torch.equal(draws[0]["meta_raw"], draws[1]["meta_raw"])
    assert not torch.equal(draws[0]["image"], draws[1]["image"])


def test_noise_data_need_a_noise_source():
    # every sample is labelled as carrying noise (and ξ as altered metadata): none added would contradict it
    with pytest.raises(ValueError, match=r"noise_sources = \[\] must name at least one of \['photon', 'dark', 'readout'\]"):
        NoiseDataModule(source="unused", noise_sources=[])


def _eight_bit(b: int, size: int = 64, seed: int = 0) -> torch.Tensor:
    """Clean patches already on the 8-bit grid (as photos and street frames are)."""
    g = torch.Generator().manual_seed(seed)
    return ((torch.rand(b, 1, size, size, generator=g) * 0.2 + 0.3) * 255).round() / 255


@pytest.mark.parametrize("sources, ranges", [
    (["readout"], {"gain_db": [0, 0], "temperature_c": [20, 20]}),  # ≈ 0.23 DN: rounding removes noise
    (["photon", "dark", "readout"], {"gain_db": [0, 0], "exposure_s": [0.001, 0.001], "temperature_c": [0, 0]}),
    (["photon", "dark", "readout"], {"gain_db": [12, 12], "temperature_c": [40, 40]}),  # several DN: + 1/12 DN²
])
def test_quantized_sigma_total_is_the_noise_really_in_the_image(sources, ranges):
    """With ``quantize: true`` the label was the σ before rounding: 0.229 DN where the rounded image carries
    0.168–0.174 DN (readout only, ICX285 at 0 dB), 1.226 where it carries 1.259 (all sources). ``sigma_total`` is now
    std(image − clean) of the returned image; the per-source ``sigma`` are documented as before rounding, and with
    ``quantize: false`` nothing changes."""
    clean = _eight_bit(4)
    out = {}
    for q in (False, True):
        dm = NoiseDataModule(source="unused", quantize=q, xi_probability=0.0, sensor="ICX285", noise_sources=sources,
                             metadata_ranges=ranges)
        meta, mi, _ = dm.sample_metadata(4, torch.Generator().manual_seed(0))
        out[q] = dm.corrupt_with(clean, meta, mi, noise_seed=1)
        realised = (out[q]["image"].double() - clean.double()).flatten(1).std(1) * 255
        assert torch.allclose(out[q]["sigma_total"].double(), realised, rtol=1e-5, atol=1e-6), (q, out[q]["sigma_total"], realised)
    plain, rounded = out[False], out[True]
    assert torch.allclose(rounded["image"] * 255, (rounded["image"] * 255).round(), atol=1e-4)  # whole DN
    assert (rounded["image"] - plain["image"]).abs().max() <= 0.5 / 255 + 1e-6  # the same noise field, rounded
    assert torch.equal(rounded["sigma"], plain["sigma"])  # per source: before rounding, as documented
    assert torch.equal(rounded["sigma_expected"], plain["sigma_expected"]) and torch.equal(rounded["xi"], plain["xi"])
    assert not torch.allclose(rounded["sigma_total"], plain["sigma_total"], rtol=1e-3)  # rounding changes the noise


def test_quantize_docs_say_what_the_labels_measure():
    import datamodules.noise as noise_module

    docs = Path(__file__).resolve().parents[2] / "docs" / "data.md"
    yaml_text = (CONFIGS / "data_noise.yaml").read_text()
    for text in (noise_module.__doc__, NoiseDataModule.__doc__, docs.read_text(), yaml_text):
        assert "1/12 DN" in text and "before rounding" in text


@pytest.mark.parametrize("option", ["quantize", "flips", "rot90", "keep_hard_patches", "pin_memory"])
@pytest.mark.parametrize("value", ["false", "no", 1, 0, None])
def test_boolean_options_must_be_bools(option, value):
    """``bool("false")`` is True: ``NoiseDataModule(flips="false")`` trained with flips on."""
    with pytest.raises(ValueError, match=rf"{option} = {value!r} must be true or false"):
        NoiseDataModule(source="unused", **{option: value})


@pytest.mark.parametrize("ranges, shown", [
    ({"gain_db": 6}, "6"), ({"gain_db": [0, 1, 2]}, r"\[0, 1, 2\]"), ({"gain_db": "0, 12"}, "'0, 12'"),
    ({"gain_db": [0, None]}, r"\[0, None\]"),
])
def test_metadata_ranges_entries_must_be_pairs_naming_the_field(ranges, shown):
    """``{gain_db: [0, 1, 2]}`` was truncated to [0, 1]; ``{gain_db: 6}`` failed with "'int' object is not
    subscriptable"."""
    with pytest.raises(ValueError, match=rf"metadata_ranges\['gain_db'\] = {shown} must be a \[low, high\] pair"):
        NoiseDataModule(source="unused", metadata_ranges=ranges)
    with pytest.raises(ValueError, match=r"metadata_ranges = .* must be a mapping"):
        NoiseDataModule(source="unused", metadata_ranges=[0, 12])
    assert NoiseDataModule(source="unused", metadata_ranges={"gain_db": (0, 12)}).metadata_ranges == {"gain_db": (0.0, 12.0)}


@pytest.mark.parametrize("kwargs, match", [
    (dict(val_fraction=1.5), r"val_fraction = 1.5 must be a number in \[0, 1\]"),
    (dict(test_fraction=float("nan")), r"test_fraction = nan must be a number in \[0, 1\]"),
    (dict(val_fraction=0.6, test_fraction=0.6), r"val_fraction \+ test_fraction = 1.2 must be <= 1"),
    (dict(seed=-1), r"seed = -1 must be >= 0"),
    (dict(brightness_dn=-5.0), r"brightness_dn = -5.0 must be a finite number in \[0, 255\]"),
    (dict(brightness_dn=float("inf")), r"brightness_dn = inf must be a finite number in \[0, 255\]"),
    (dict(min_std_dn=float("nan")), r"min_std_dn = nan must be a finite number >= 0"),
    (dict(max_clipped_fraction=1.5), r"max_clipped_fraction = 1.5 must be a finite number in \[0, 1\]"),
    (dict(max_tries=0), r"max_tries = 0 must be a positive int"),
    (dict(xi_probability=True), r"xi_probability = True must be a finite number in \[0, 1\]"),
])
def test_patch_and_split_options_are_checked_at_construction(kwargs, match):
    """These were stored unchecked and refused only at ``setup``, after the CLI had built the model and Trainer."""
    with pytest.raises(ValueError, match=match):
        NoiseDataModule(source="unused", **kwargs)


@pytest.mark.parametrize("source_kwargs, match", [
    ({"dead_leaves": 60}, r"source_kwargs: unknown option\(s\) \['dead_leaves'\] for the built-in source 'default' "
                          r"\(DefaultSource\); allowed: \[.*'deadleaves'.*\]"),
    ({"supersample": 4}, r"source_kwargs: dead-leaves option\(s\) \['supersample'\] given with deadleaves = 0"),
    ([("deadleaves", 60)], r"source_kwargs = \[\('deadleaves', 60\)\] must be a mapping"),
])
def test_source_kwargs_the_source_does_not_take_are_refused_at_construction(source_kwargs, match):
    """``source_kwargs={'dead_leaves': 60}`` trained on the default source without its 60 dead-leaves images."""
    error = TypeError if isinstance(source_kwargs, list) else ValueError
    with pytest.raises(error, match=match):
        NoiseDataModule(source="default", source_kwargs=source_kwargs)
    assert len(NoiseDataModule(source="default", source_kwargs={"deadleaves": 2, "deadleaves_size": 64}).source.ids) \
        == len(NoiseDataModule(source="default").source.ids) + 2


def test_seed_out_of_the_range_of_the_crop_generators_is_refused_at_construction():
    """``seed: 18446744073709551615`` failed at setup with an unnamed 'Overflow when unpacking long long' (the
    val/test crops are seeded with seed + 1 and seed + 2)."""
    for seed in (2**64 - 1, 2**64 - 2, 99999999999999999999):
        with pytest.raises(ValueError, match=rf"seed = {seed} must be >= 0 and <= 18446744073709551613, an integer in "
                                             r"\[0, 18446744073709551613\]"):
            NoiseDataModule(source="unused", seed=seed)
    with pytest.raises(TypeError, match=r"seed = '3' must be an integer in \[0, 18446744073709551613\], got str"):
        NoiseDataModule(source="unused", seed="3")
    assert NoiseDataModule(source="unused", seed=2**64 - 3).seed == 2**64 - 3
