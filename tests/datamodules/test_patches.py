"""PatchDataset and the shared DataModule machinery: crops, augmentation, rejection, splits, file errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from camhealth.data import group_key
from datamodules import NoiseDataModule, PatchDataset, is_hard_patch
from tests.datamodules.conftest import SMALL, save_png, textured


def _img(arr: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(arr.astype(np.float32))[None]


def test_train_patches_shape_augmentation_and_length():
    ds = PatchDataset([_img(textured(64, 0)), _img(textured(80, 1))], ["a", "b"], 32, "train", patches_per_image=3)
    assert len(ds) == 6
    s = ds[1]
    assert s["clean"].shape == (1, 32, 32) and s["clean"].dtype == torch.float32
    assert s["stage"] == "train" and s["image_id"] == "b" and s["index"] == 1
    assert 0.0 <= float(s["clean"].min()) and float(s["clean"].max()) <= 1.0
    with pytest.raises(IndexError):
        ds[6]


def test_brightness_offset_is_within_20_dn():
    flat = _img(np.full((40, 40), 0.5))
    ds = PatchDataset([flat], ["flat"], 16, "train", patches_per_image=50, keep_hard_patches=True, brightness_dn=20.0)
    offsets = torch.stack([ds[i]["clean"].mean() - 0.5 for i in range(50)]) * 255
    assert float(offsets.abs().max()) <= 20.0 + 1e-3
    assert float(offsets.std()) > 5.0  # really random, roughly uniform in ±20 DN
    # each patch is shifted as a whole (a constant offset)
    assert float(ds[0]["clean"].std()) < 1e-6


def test_flips_and_rot90_only_permute_pixels():
    img = _img(textured(32, 3))
    ds = PatchDataset([img], ["x"], 32, "train", patches_per_image=20, brightness_dn=0.0)
    seen = set()
    for i in range(20):
        p = ds[i]["clean"]
        assert torch.equal(p.flatten().sort().values, img.flatten().sort().values)
        seen.add(p.numpy().tobytes())
    assert len(seen) > 2  # several of the 8 symmetries occurred


def test_fixed_val_crops_depend_only_on_seed():
    imgs, ids = [_img(textured(96, 0)), _img(textured(96, 1))], ["a", "b"]
    a = PatchDataset(imgs, ids, 32, "val", patches_per_image=4, seed=5)
    b = PatchDataset(imgs, ids, 32, "val", patches_per_image=4, seed=5)
    c = PatchDataset(imgs, ids, 32, "val", patches_per_image=4, seed=6)
    assert torch.equal(a.crops, b.crops) and not torch.equal(a.crops, c.crops)
    assert all(torch.equal(a[i]["clean"], a[i]["clean"]) for i in range(len(a)))  # no random augmentation
    assert torch.equal(a[3]["clean"], b[3]["clean"])


def test_hard_patch_rejection_and_keep_flag():
    arr = textured(64, 0)
    arr[:, :32] = 0.4  # left half uniform
    arr[:16, 32:] = 1.0  # a saturated block
    img = _img(arr)
    assert is_hard_patch(img[:, :, :20], min_std_dn=2.0)
    assert is_hard_patch(img[:, :16, 32:], max_clipped_fraction=0.05)
    assert not is_hard_patch(img[:, 32:, 32:])
    ds = PatchDataset([img], ["x"], 16, "val", patches_per_image=40, seed=0)
    assert not any(is_hard_patch(ds[i]["clean"]) for i in range(len(ds)))
    kept = PatchDataset([img], ["x"], 16, "val", patches_per_image=40, seed=0, keep_hard_patches=True)
    assert any(is_hard_patch(kept[i]["clean"]) for i in range(len(kept)))
    train = PatchDataset([img], ["x"], 16, "train", patches_per_image=40, brightness_dn=0.0)
    assert not any(is_hard_patch(train[i]["clean"]) for i in range(len(train)))


def test_too_small_image_is_named():
    with pytest.raises(ValueError, match="tiny.*smaller than the patch size"):
        PatchDataset([_img(textured(16, 0))], ["tiny"], 32)


def test_splits_never_leak_images_or_clips(tmp_path):
    root = tmp_path / "clips"
    for c in "ABCDEFGH":
        for i in range(2):
            save_png(root / f"clip{c}" / f"frame{i}.png", textured(40, ord(c) * 10 + i))
    dm = NoiseDataModule(source=str(root), group_by="folder", **{**SMALL, "seed": 3})
    dm.setup()
    seen = {}
    for stage, ds in dm.datasets.items():
        if ds is None:
            continue
        ids = {ds[i]["image_id"] for i in range(len(ds))}
        seen[stage] = ids
    assert len(seen) == 3  # seed 3: 3 train, 3 val, 2 test clips
    stages = list(seen)
    for i, s in enumerate(stages):
        for t in stages[i + 1 :]:
            assert not seen[s] & seen[t]
            assert not {x.split("/")[0] for x in seen[s]} & {x.split("/")[0] for x in seen[t]}
    # the default grouping keeps the frames "<clip>#<n>" of one clip together (the street sample)
    assert group_key("street:vtest#000101") == group_key("street:vtest#000102")


def test_corrupt_file_error_names_the_file(image_folder):
    (image_folder / "broken.png").write_bytes(b"this is not a png")
    dm = NoiseDataModule(source=str(image_folder), **SMALL)
    with pytest.raises(ValueError, match="broken.png"):
        dm.setup()


def test_empty_folder_error(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    dm = NoiseDataModule(source=str(empty), **SMALL)
    with pytest.raises(ValueError, match="no images found in folder .*empty"):
        dm.setup()


def test_small_images_are_skipped_with_a_warning(image_folder):
    save_png(image_folder / "img03.png", textured(20, 3))  # img03 is a train image
    dm = NoiseDataModule(source=str(image_folder), **SMALL)
    with pytest.warns(UserWarning, match="img03.png"):
        dm.setup("fit")
    assert "img03.png" not in dm.datasets["train"].ids


def test_16bit_and_colour_images(tmp_path):
    root = tmp_path / "mixed"
    ramp = np.linspace(0.2, 0.8, 64 * 64).reshape(64, 64)
    for i in range(10):
        save_png(root / f"deep{i:02d}.png", 0.5 * ramp + 0.5 * textured(64, i), bits=16)
    rgb = np.stack([textured(64, 20), textured(64, 21), textured(64, 22)], -1)
    Image.fromarray((rgb * 255).round().astype(np.uint8)).save(root / "colour.png")
    dm = NoiseDataModule(source=str(root), **SMALL)
    dm.setup()
    images = {dm.source.ids[i]: img for i, img in dm._cache.items()}
    assert images["colour.png"].shape == (1, 64, 64)
    deep = images["deep02.png"] * 255
    assert float((deep - deep.round()).abs().max()) > 0.01  # finer than 8-bit steps: 16-bit kept
    batch = dm.on_after_batch_transfer(next(iter(dm.train_dataloader())))
    assert batch["image"].shape == (4, 1, 32, 32)
    assert torch.isfinite(batch["image"]).all()


def test_training_crops_differ_per_rank_of_a_multi_process_run_without_workers(image_folder):
    from types import SimpleNamespace

    from datamodules import NoiseDataModule
    from tests.datamodules.conftest import SMALL

    dm = NoiseDataModule(source=str(image_folder), **SMALL)
    firsts = []
    for rank in (0, 1):
        dm.trainer = SimpleNamespace(world_size=2, global_rank=rank, training=True)
        torch.manual_seed(0)  # seed_everything: the same global state on every rank
        dm.train_dataloader()
        firsts.append(torch.stack([dm.datasets["train"][i]["clean"] for i in range(4)]))
    assert not torch.equal(firsts[0], firsts[1])
    dm.trainer = None
    dm.datasets["train"].generator = None  # a single process: torch's global generator, as seeded
    torch.manual_seed(0)
    a = dm.datasets["train"][0]["clean"]
    torch.manual_seed(0)
    assert torch.equal(a, dm.datasets["train"][0]["clean"])


def test_featureless_images_are_named_and_their_fallback_patches_marked(tmp_path):
    """A folder of uniform frames (a lens cap, a saturated or flat scene) trained on featureless patches without a
    word: ``n_fallback`` was counted and never reported."""
    import warnings

    from tests.datamodules.conftest import save_png

    for i in range(10):
        save_png(tmp_path / f"flat{i}.png", np.full((64, 64), 0.5))
    dm = NoiseDataModule(source=str(tmp_path), **SMALL)
    with pytest.warns(UserWarning) as caught:
        dm.setup("fit")
    messages = [str(w.message) for w in caught if "hard-patch check" in str(w.message)]
    assert len(messages) == 2  # train and val
    train = next(m for m in messages if " train image(s)" in m)
    assert train.startswith(f"NoiseDataModule: {len(dm.datasets['train'].ids)} of {len(dm.datasets['train'].ids)} "
                            "train image(s) of source")
    assert "max_tries = 20 draws" in train and "min_std_dn = 2 DN" in train and "keep_hard_patches: true" in train
    assert dm.datasets["train"].ids[0] in train
    val = next(m for m in messages if " val image(s)" in m)
    assert f"{dm.datasets['val'].n_fallback} of its {len(dm.datasets['val'])} fixed crops" in val
    batch = dm.on_after_batch_transfer(next(iter(dm.train_dataloader())), 0)
    assert batch["fallback"].dtype == torch.bool and bool(batch["fallback"].all())
    assert bool(dm.on_after_batch_transfer(next(iter(dm.val_dataloader())), 0)["fallback"].all())
    # textured images: no warning, no fallback; kept on purpose: no warning either
    for i in range(10):
        save_png(tmp_path / f"flat{i}.png", textured(64, i))
    textured_dm = NoiseDataModule(source=str(tmp_path), **SMALL)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        textured_dm.setup("fit")
    assert not textured_dm.datasets["train"].featureless and not bool(textured_dm.datasets["val"][0]["fallback"])
    for i in range(10):
        save_png(tmp_path / f"flat{i}.png", np.full((64, 64), 0.5))
    kept = NoiseDataModule(source=str(tmp_path), **SMALL, keep_hard_patches=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        kept.setup("fit")


def test_the_featureless_probe_leaves_torchs_generator_alone():
    torch.manual_seed(3)
    before = torch.get_rng_state()
    ds = PatchDataset([_img(np.full((64, 64), 0.5)), _img(textured(64, 1))], ["flat", "tex"], 32, "train")
    assert ds.featureless == ["flat"] and torch.equal(torch.get_rng_state(), before)
