"""BlurDataModule: real MTF-labelled batches, labels equal to the physics core, determinism, options."""

from __future__ import annotations

from pathlib import Path

import lightning as L
import pytest
import torch

from camhealth.physics import defocus_psf, form_image, linear_motion_psf, mtf_hv, nonlinear_motion_psf
from datamodules import BlurDataModule
from tests.datamodules.conftest import SMALL, save_png, textured

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _clean(b: int = 6, size: int = 48) -> torch.Tensor:
    return torch.stack([torch.from_numpy(textured(size, i)).float()[None] for i in range(b)])


def test_default_source_yields_real_mtf_batches():
    dm = BlurDataModule(batch_size=8)  # embedded default data, 192 px, sizes up to 31 px
    dm.setup("validate")
    batch = dm.on_after_batch_transfer(next(iter(dm.val_dataloader())), 0)
    assert batch["image"].shape == batch["clean"].shape == (8, 1, 192, 192)
    assert batch["mtf"].shape == (8, 16) and batch["family"].dtype == torch.long
    assert batch["size"].shape == (8,) and float(batch["size"].max()) <= 31.0
    assert (batch["mtf"] >= 0).all() and (batch["mtf"] <= 1 + 1e-5).all()
    assert set(batch["family"].tolist()) <= {0, 1, 2}
    assert dm.kernel_size == 35
    # a blurred patch has less high-frequency energy than the clean one
    def hf(x):
        return (x[..., 1:] - x[..., :-1]).abs().mean()

    assert float(hf(batch["image"])) < float(hf(batch["clean"]))


def test_labels_match_the_physics_core(image_folder):
    # 48 px: the 19-px kernel of 15-px blur needs patches of at least 2·19 − 1 = 37 px
    dm = BlurDataModule(source=str(image_folder), size_range=(2.0, 15.0), return_psf=True,
                        **{**SMALL, "batch_size": 8, "patch_size": 48})
    dm.setup("validate")
    batch = next(iter(dm.val_dataloader()))
    out = dm.on_after_batch_transfer(batch)
    # replay the draws: each held-out patch is corrupted on its own, from its own seed
    draws = [dm.sample_params(1, dm.sample_generator("val", int(i))) for i in batch["index"]]
    p = {k: torch.cat([d[k] for d in draws]) for k in draws[0]}
    k = dm.kernel_size
    for i, fam in enumerate(p["family"].tolist()):
        s, a = p["size"][i : i + 1], p["angle"][i : i + 1]
        if fam == 0:
            psf = defocus_psf(s, k)
        elif fam == 1:
            psf = linear_motion_psf(s, a, k)
        else:
            psf = nonlinear_motion_psf(s, a, p["intensity"][i : i + 1], p["shake_noise"][i : i + 1], k)
        assert torch.allclose(out["psf"][i : i + 1], psf)
        assert torch.allclose(out["mtf"][i : i + 1], mtf_hv(psf), atol=1e-6)
    assert torch.equal(out["family"], p["family"]) and torch.equal(out["size"], p["size"])
    ref = form_image(batch["clean"], None, defocus_psf=out["psf"], sources=())
    assert torch.equal(out["image"], ref.image)


def test_same_seed_gives_same_validation_batch(image_folder):
    def first_val():
        dm = BlurDataModule(source=str(image_folder), size_range=(1.0, 11.0), **SMALL)
        dm.setup("validate")
        torch.manual_seed(torch.seed() % 1000)  # the global RNG must not matter for validation
        return dm.on_after_batch_transfer(next(iter(dm.val_dataloader())))

    a, b = first_val(), first_val()
    for key in ("image", "mtf", "family", "size"):
        assert torch.equal(a[key], b[key]), key


def test_family_mix_and_sizes():
    clean = _clean(16, 72)  # 31-px blur: 35-px kernel, patches of at least 69 px
    only = BlurDataModule(source="unused", patch_size=72, families={"linear": 1.0}, size_range=(31.0, 31.0))
    out = only.corrupt(clean, None)
    assert (out["family"] == 1).all() and torch.equal(out["size"], torch.full((16,), 31.0))
    assert (out["intensity"] == 0).all()
    mix = BlurDataModule(source="unused", patch_size=72, families={"defocus": 1, "nonlinear": 3})
    fams = mix.corrupt(_clean(32, 72), torch.Generator().manual_seed(0))["family"]
    assert set(fams.tolist()) == {0, 2}
    with pytest.raises(ValueError, match="famil"):
        BlurDataModule(families={"gaussian": 1.0})
    with pytest.raises(ValueError, match="kernel_size"):
        BlurDataModule(kernel_size=21)


def test_noise_after_blur():
    clean = _clean(6, 72)
    g = torch.Generator().manual_seed(0)
    dm = BlurDataModule(source="unused", patch_size=72, noise=True, families={"defocus": 1.0, "linear": 1.0})
    out = dm.corrupt(clean, g)
    assert out["sigma"].shape == (6, 3) and out["meta_raw"].shape == (6, 11) and out["noisy"].all()
    assert (out["sigma_total"] > 0).all()
    # the MTF label is the blur's alone, the image has noise on top of the blur
    quiet = BlurDataModule(source="unused", patch_size=72, families={"defocus": 1.0, "linear": 1.0})
    ref = quiet.corrupt(clean, torch.Generator().manual_seed(0))
    assert torch.equal(ref["mtf"], out["mtf"]) and not torch.equal(ref["image"], out["image"])
    fast = BlurDataModule(source="unused", patch_size=72, noise=True, families={"defocus": 1.0, "linear": 1.0},
                          train_rng="counter")
    torch.manual_seed(1)
    a = fast.on_after_batch_transfer({"clean": clean, "stage": ["train"] * 6})
    torch.manual_seed(1)
    b = dm.on_after_batch_transfer({"clean": clean, "stage": ["train"] * 6})
    assert torch.equal(a["mtf"], b["mtf"]) and not torch.equal(a["image"], b["image"])  # same blur, other noise draws
    assert torch.allclose(a["sigma"].sum(0), b["sigma"].sum(0), rtol=0.1)
    after = BlurDataModule(source="unused", patch_size=72, noise=True, noise_order="after_blur", noise_probability=0.0)
    out2 = after.corrupt(clean, None)
    assert not out2["noisy"].any() and torch.equal(out2["sigma"], torch.zeros(6, 3))


def test_yaml_config_instantiates_with_lightning_cli():
    from lightning.pytorch import cli as lcli

    if not lcli._JSONARGPARSE_SIGNATURES_AVAILABLE:
        pytest.skip("jsonargparse[signatures] is not installed (it is a declared dependency)")

    class Tiny(L.LightningModule):
        pass

    cli = lcli.LightningCLI(Tiny, run=False, args=["--config", str(CONFIGS / "data_blur.yaml"), "--trainer.logger=false"])
    dm = cli.datamodule
    assert isinstance(dm, BlurDataModule) and dm.patch_size == 192 and dm.size_range == (1.0, 31.0)


def test_corruption_runs_on_the_batch_device(device):
    dm = BlurDataModule(source="unused", patch_size=72, noise=True)
    batch = {"clean": _clean(4, 72).to(device), "index": torch.arange(4, device=device), "stage": ["test"] * 4}
    out = dm.on_after_batch_transfer(batch, 0)
    assert all(v.device.type == device.type for v in out.values() if isinstance(v, torch.Tensor))
    assert torch.equal(out["image"], dm.on_after_batch_transfer({**batch}, 0)["image"])


def test_bench_data_subcommand_reports_patches_per_second(tmp_path, capsys):
    from camhealth.bench.__main__ import main

    folder = tmp_path / "images"  # 80-px images: the bench's 31-px blur (35-px kernel) needs patches >= 69 px
    for i in range(10):
        save_png(folder / f"img{i:02d}.png", textured(80, i))
    argv = ["data", "--source", str(folder), "--batch", "4", "--repeats", "1", "--warmup", "0",
            "--noise-patch", "32", "--blur-patch", "72"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "BlurDataModule train + noise" in out and "patches/s delivered incl. corruption" in out
    assert "NoiseDataModule train, train_rng=counter" in out and "BlurDataModule train + noise, train_rng=counter" in out
    assert "allocator: freed memory kept for reuse" in out
    # the setting is process-wide and cannot be undone: the header says so instead of claiming glibc defaults
    assert main(argv + ["--default-malloc"]) == 0
    assert "set earlier in this process" in capsys.readouterr().out


def test_sharp_sources_option_is_batched_and_seeded():
    """``source_kwargs: {area_downsample: 2, supersample: 4}`` (photos and street frames area-downsampled, dead leaves
    area-rendered): full batches, the same validation batch for the same seed, the same training batches under the
    same global seed, and different ones for another seed."""
    kw = dict(source="default", source_kwargs={"street_stride": 10, "area_downsample": 2, "deadleaves": 6,
                                                 "deadleaves_size": 96, "supersample": 4},
              patch_size=64, batch_size=4, patches_per_image=2, val_patches_per_image=2, size_range=(1.0, 9.0))

    def batches(seed):
        dm = BlurDataModule(**kw, seed=seed)
        dm.setup("fit")
        val = dm.on_after_batch_transfer(next(iter(dm.val_dataloader())), 0)
        torch.manual_seed(123)
        L.seed_everything(123, verbose=False)
        train = dm.on_after_batch_transfer(next(iter(dm.train_dataloader())), 0)
        return dm, val, train

    dm, v1, t1 = batches(0)
    _, v2, t2 = batches(0)
    assert t1["image"].shape == (4, 1, 64, 64) and t1["mtf"].shape == (4, 16) and v1["image"].shape[1:] == (1, 64, 64)
    for key in ("image", "clean", "mtf", "family", "size"):
        assert torch.equal(v1[key], v2[key]), key
        assert torch.equal(t1[key], t2[key]), key
    _, v3, _ = batches(1)
    assert not torch.equal(v1["clean"], v3["clean"])
    src = dm.source
    i = src.ids.index("street:vtest#000100")
    assert src[i][0].shape == (1, 288, 384)  # area-downsampled by 2


def test_noisy_blur_data_need_a_noise_source_and_an_int_kernel_size():
    # noisy samples with no source would be labelled noisy with σ = 0
    with pytest.raises(ValueError, match=r"noise_sources = \[\] must name at least one of \['photon', 'dark', 'readout'\]"):
        BlurDataModule(source="unused", noise=True, noise_sources=())
    assert BlurDataModule(source="unused", noise=False, noise_sources=()).noise_sources == ()
    for ks in (33.5, True):
        with pytest.raises(TypeError, match="kernel_size must be an int"):
            BlurDataModule(source="unused", kernel_size=ks, size_range=(0.0, 1.0))
    with pytest.raises(ValueError, match=r"kernel_size = 34 must be an odd integer"):
        BlurDataModule(source="unused", kernel_size=34, size_range=(0.0, 1.0))
    with pytest.raises(ValueError, match=r"kernel_size = 5 must be odd and >= size_range\[1\] = 9"):
        BlurDataModule(source="unused", kernel_size=5, size_range=(0.0, 9.0))


def test_metadata_ranges_are_checked_also_without_noise():
    with pytest.raises(ValueError, match="gain_db"):
        BlurDataModule(source="unused", noise=False, metadata_ranges={"gain_db": (5.0, 1.0)})


def test_patches_too_small_for_the_kernel_are_refused_naming_both_and_the_rule():
    """A patch hardly larger than its PSF is blurred mostly with the padded border: the MTF label then no longer
    describes the image (31-px linear blur, f_n = 0.1: label 0.204, modulation in a 40-px patch 0.189). The rule
    patch_size >= 2·kernel_size − 1 keeps an exactly blurred centre at least one kernel wide."""
    from datamodules.blur import min_patch_size

    for patch, kw in ((16, {}), (40, {}), (68, {}), (32, {"size_range": (1.0, 25.0)})):
        k = BlurDataModule(source="unused", **kw).kernel_size
        with pytest.raises(ValueError, match=rf"patch_size = {patch} is too small for kernel_size = {k} .*"
                                             rf"patch_size must be >= 2·kernel_size − 1 = {2 * k - 1}"):
            BlurDataModule(source="unused", patch_size=patch, **kw)
    assert min_patch_size(35) == 69 and BlurDataModule(source="unused", patch_size=69).kernel_size == 35
    with pytest.raises(ValueError, match=r"patch_size = 64 is too small for kernel_size = 63"):  # an explicit kernel
        BlurDataModule(source="unused", patch_size=64, size_range=(1.0, 9.0), kernel_size=63)
    # the defaults and every shipped blur config pass (192-px patches; 35- and 29-px kernels)
    import yaml

    assert BlurDataModule(source="unused").patch_size == 192
    for name in ("data_blur.yaml", "mtf.yaml", "mtf_full.yaml"):
        init = dict(yaml.safe_load((CONFIGS / name).read_text())["data"]["init_args"], source="unused")
        dm = BlurDataModule(**init)
        assert dm.patch_size >= min_patch_size(dm.kernel_size), name


@pytest.mark.parametrize("option", ["return_psf", "noise", "flips", "rot90", "keep_hard_patches", "pin_memory"])
@pytest.mark.parametrize("value", ["false", "no", 1, 0, None])
def test_boolean_options_must_be_bools(option, value):
    """``bool("false")`` is True: a string or number is refused naming the option instead of switching it on."""
    with pytest.raises(ValueError, match=rf"{option} = {value!r} must be true or false"):
        BlurDataModule(source="unused", **{option: value})


@pytest.mark.parametrize("ranges, shown", [
    ({"gain_db": 6}, "6"), ({"gain_db": [0, 1, 2]}, r"\[0, 1, 2\]"), ({"gain_db": "0, 12"}, "'0, 12'"),
    ({"gain_db": [0, "12"]}, r"\[0, '12'\]"), ({"gain_db": [True, 3]}, r"\[True, 3\]"),
])
def test_metadata_ranges_entries_must_be_pairs_naming_the_field(ranges, shown):
    """A 3-element range was truncated to its first two values, a single number failed with "'int' object is not
    subscriptable"."""
    for noise in (True, False):
        with pytest.raises(ValueError, match=rf"metadata_ranges\['gain_db'\] = {shown} must be a \[low, high\] pair"):
            BlurDataModule(source="unused", noise=noise, metadata_ranges=ranges)


def test_size_range_and_probabilities_name_the_option():
    with pytest.raises(ValueError, match=r"size_range must be a number or a \[low, high\] pair of numbers, got 'ab'"):
        BlurDataModule(source="unused", size_range="ab")
    with pytest.raises(ValueError, match=r"noise_probability = True must be a finite number in \[0, 1\]"):
        BlurDataModule(source="unused", noise=True, noise_probability=True)
    with pytest.raises(ValueError, match=r"gain_uniform_in = 'linear' is not one of"):
        BlurDataModule(source="unused", gain_uniform_in="linear")  # also with noise off


@pytest.mark.parametrize("families, error, match", [
    ([1, 1, 1], TypeError, r"families = \[1, 1, 1\] must be a mapping of blur family to weight, e.g. \{defocus: 2.0"),
    ({"defocus": "a"}, TypeError, r"families\['defocus'\] = 'a' must be a number"),
    ({"defocus": True}, TypeError, r"families\['defocus'\] = True must be a number"),
])
def test_families_of_another_type_are_named(families, error, match):
    """``BlurDataModule(families=[1, 1, 1])`` raised 'cannot convert dictionary update sequence element #0 to a
    sequence', naming no option."""
    with pytest.raises(error, match=match):
        BlurDataModule(source="unused", families=families)
