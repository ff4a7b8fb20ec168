"""Offline built-in sources (scikit-image photos, street sample), DefaultSource, build_source, split_ids."""

from __future__ import annotations

import socket

import numpy as np
import pytest
import torch
from PIL import Image

from camhealth.data import (
    SKIMAGE_PHOTOS,
    STREET_DIR,
    DefaultSource,
    DeadLeavesSource,
    ImageFolderSource,
    SkimagePhotosSource,
    StreetSampleSource,
    build_source,
    group_key,
    split_ids,
    street_sequence,
)

N_STREET = 50


@pytest.fixture
def no_network(monkeypatch):
    def refuse(*args, **kwargs):
        raise OSError("network access attempted during an offline test")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)


def test_skimage_photos_load_offline(no_network):
    src = SkimagePhotosSource()
    assert len(src) == len(SKIMAGE_PHOTOS) == 10
    for i in range(len(src)):
        img, image_id = src[i]
        assert image_id == f"skimage:{SKIMAGE_PHOTOS[i]}"
        assert img.dtype == torch.float32 and img.ndim == 3 and img.shape[0] == 1
        assert min(img.shape[1:]) >= 192, f"{image_id} too small for a 192×192 patch"
        assert 0.0 <= img.min().item() and img.max().item() <= 1.0 and img.std().item() > 0.05
    with pytest.raises(ValueError, match="unknown"):
        SkimagePhotosSource(["moon"])


def test_street_sample_present():
    assert STREET_DIR.is_dir() and (STREET_DIR / "README.md").is_file()
    src = StreetSampleSource()
    assert len(src) == N_STREET
    assert src.ids[0] == "street:vtest#000100" and src.ids[-1] == "street:vtest#000149"
    for i in (0, N_STREET - 1):
        img, _ = src[i]
        assert img.shape == (1, 576, 768) and img.dtype == torch.float32
        assert 0.0 <= img.min().item() and img.max().item() <= 1.0
    assert len(StreetSampleSource(stride=2)) == 25
    with Image.open(src.paths[0]) as im:  # committed as lossless 8-bit gray PNG
        assert im.format == "PNG" and im.mode == "L"
    total_bytes = sum(p.stat().st_size for p in STREET_DIR.iterdir())
    assert total_bytes < 12.5e6


def test_street_sequence_is_consecutive():
    seq = street_sequence(stride=10)
    assert len(seq) == 5
    out = list(seq)
    assert [i for _, i in out] == [0, 10, 20, 30, 40]
    first, _ = out[0]
    assert torch.equal(first, StreetSampleSource()[0][0])
    # consecutive frames are similar (same scene), not identical
    a, b = StreetSampleSource(max_frames=2)[0][0], StreetSampleSource(max_frames=2)[1][0]
    diff = (a - b).abs().mean().item()
    assert 0.0 < diff < 0.05


def test_default_source_concatenates_with_unique_ids():
    src = DefaultSource(deadleaves=3, deadleaves_size=(32, 32))
    assert len(src) == len(SKIMAGE_PHOTOS) + N_STREET + 3
    assert len(set(src.ids)) == len(src.ids)
    assert src[0][1] == "skimage:astronaut"
    assert src[len(SKIMAGE_PHOTOS)][1] == "street:vtest#000100"
    img, image_id = src[-1]
    assert image_id == "deadleaves-000002" and img.shape == (1, 32, 32)
    assert len(DefaultSource(include_street=False)) == len(SKIMAGE_PHOTOS)


def test_default_source_antialiased_dead_leaves_share_the_split_group():
    from camhealth.data import group_key, split_ids

    src = DefaultSource(deadleaves=4, deadleaves_size=(48, 48), deadleaves_antialiased=2, include_street=False)
    assert len(src) == len(SKIMAGE_PHOTOS) + 4 + 2 and len(set(src.ids)) == len(src.ids)
    plain, aa = src[len(SKIMAGE_PHOTOS) + 1], src[len(src) - 1]
    assert aa[1] == "deadleaves-000001#2" and group_key(aa[1]) == plain[1] == "deadleaves-000001"
    # the same scene, rendered with anti-aliased edges: more distinct grey levels, the same mean
    assert len(torch.unique(aa[0])) > len(torch.unique(plain[0]))
    assert abs(float(aa[0].mean() - plain[0].mean())) < 0.02
    splits = split_ids(src.ids, 0.25, 0.25, seed=0)
    where = {i: name for name, idx in splits.items() for i in idx}
    ids = list(src.ids)
    twins = [k for k, image_id in enumerate(ids) if image_id.endswith("#2")]
    assert len(twins) == 2
    for k in twins:
        assert where[k] == where[ids.index(ids[k][:-2])]
    with pytest.raises(ValueError, match="deadleaves_antialiased"):
        DefaultSource(deadleaves=1, deadleaves_antialiased=2)
    with pytest.raises(ValueError, match="supersample"):
        DefaultSource(deadleaves=2, deadleaves_antialiased=1, supersample=2)


def test_default_source_photo_repeat_keeps_each_photo_in_one_split():
    from camhealth.data import group_key, split_ids

    src = DefaultSource(include_street=False, photo_repeat=3)
    n = len(SKIMAGE_PHOTOS)
    assert len(src) == 3 * n and len(set(src.ids)) == 3 * n
    assert src.ids[n] == f"skimage:{SKIMAGE_PHOTOS[0]}#1" and src.ids[2 * n + 1] == f"skimage:{SKIMAGE_PHOTOS[1]}#2"
    assert torch.equal(src[0][0], src[n][0])  # the same pixels; the datamodule draws each copy's own crops
    where = {i: name for name, idx in split_ids(src.ids, 0.3, 0.3, seed=0).items() for i in idx}
    for k, image_id in enumerate(src.ids):
        assert group_key(image_id) == src.ids[k % n]
        assert where[k] == where[k % n]
    assert len(DefaultSource(photo_repeat=1).ids) == len(DefaultSource().ids)
    with pytest.raises(ValueError, match="photo_repeat = 0"):
        DefaultSource(photo_repeat=0)
    with pytest.raises(ValueError, match="include_skimage"):
        DefaultSource(photo_repeat=2, include_skimage=False)


def test_build_source_specs(tmp_path):
    assert isinstance(build_source("default"), DefaultSource)
    dl = build_source("deadleaves", n_images=4, size=(16, 16))
    assert isinstance(dl, DeadLeavesSource) and len(dl) == 4
    assert isinstance(build_source("skimage"), SkimagePhotosSource)
    assert isinstance(build_source("street"), StreetSampleSource)
    for k in range(3):
        Image.fromarray(np.full((5, 5), k, np.uint8)).save(tmp_path / f"f{k}.png")
    assert isinstance(build_source(str(tmp_path)), ImageFolderSource)
    frames = build_source(f"frames:{tmp_path}")
    assert len(frames) == 3 and group_key(frames.ids[0]) == group_key(frames.ids[2])
    with pytest.raises(FileNotFoundError, match="neither a built-in source"):
        build_source(str(tmp_path / "nothing_here"))
    with pytest.raises(ValueError, match="video file"):
        build_source(str(tmp_path / "f0.png"))


def test_build_source_forwards_bit_depth_to_folders_and_refuses_it_elsewhere(tmp_path):
    arr = np.full((8, 8), 500, np.uint16)
    arr[0, 0] = 1000  # "auto" would guess 10 bits
    Image.fromarray(arr).save(tmp_path / "f0.png")
    for spec in (str(tmp_path), f"frames:{tmp_path}"):
        src = build_source(spec, bit_depth=12)
        assert src[0][0][0, 1, 1].item() == pytest.approx(500 / 4095)
    assert build_source(str(tmp_path), bit_depth=12, area_downsample=2)[0][0][0, 1, 1].item() == pytest.approx(500 / 4095)
    assert isinstance(build_source("skimage", bit_depth="auto"), SkimagePhotosSource)
    for spec in ("default", "skimage", "deadleaves"):
        with pytest.raises(ValueError, match=f"bit_depth = 12 applies to a folder of image files; the built-in source '{spec}'"):
            build_source(spec, bit_depth=12)
    with pytest.raises(ValueError, match="bit_depth = 0 must be 'auto'"):
        build_source(str(tmp_path), bit_depth=0)


def test_group_key():
    assert group_key("street:vtest#000123") == "street:vtest"
    assert group_key("video:a#b.avi#000001") == "video:a#b.avi"
    assert group_key("skimage:camera") == "skimage:camera"
    assert group_key("deadleaves-000042") == "deadleaves-000042"
    assert group_key("sub/img#3.png") == "sub/img#3.png"


def _ids(n_photos=200):
    return (
        [f"photo_{k:04d}.png" for k in range(n_photos)]
        + [f"clip{c}#{f:06d}" for c in range(20) for f in range(30)]
        + [f"deadleaves-{k:06d}" for k in range(100)]
    )


def test_split_never_leaks_and_covers_everything():
    ids = _ids()
    parts = split_ids(ids, 0.15, 0.15, seed=3)
    allidx = sorted(i for v in parts.values() for i in v)
    assert allidx == list(range(len(ids)))
    groups = {name: {group_key(ids[i]) for i in idx} for name, idx in parts.items()}
    assert not groups["train"] & groups["val"]
    assert not groups["train"] & groups["test"]
    assert not groups["val"] & groups["test"]
    assert all(parts[name] == sorted(parts[name]) for name in parts)


def test_split_is_stable_when_images_are_added_or_reordered():
    ids = _ids()

    def assignment(id_list, seed=0):
        parts = split_ids(id_list, 0.2, 0.1, seed=seed)
        return {id_list[i]: name for name, idx in parts.items() for i in idx}

    base = assignment(ids)
    grown = assignment(ids + ["new_photo.png", "clip3#000030"])
    assert all(grown[k] == v for k, v in base.items())
    assert grown["clip3#000030"] == base["clip3#000000"]  # a new frame joins its clip's split
    assert assignment(ids[::-1]) == base
    assert assignment(ids, seed=1) != base


def test_split_fractions_are_about_right():
    ids = [f"img{k}" for k in range(4000)]
    parts = split_ids(ids, 0.2, 0.1, seed=0)
    assert len(parts["val"]) / 4000 == pytest.approx(0.2, abs=0.03)
    assert len(parts["test"]) / 4000 == pytest.approx(0.1, abs=0.03)
    assert split_ids(ids, 0.0, 0.0)["train"] == list(range(4000))


def test_split_bad_arguments():
    with pytest.raises(ValueError, match="val_fraction"):
        split_ids(["a"], -0.1, 0.1)
    with pytest.raises(ValueError, match="<= 1"):
        split_ids(["a"], 0.6, 0.5)
    with pytest.raises(TypeError):
        split_ids("abc", 0.1, 0.1)


def test_street_frames_share_one_split():
    ids = DefaultSource().ids
    for seed in range(5):
        parts = split_ids(ids, 0.3, 0.3, seed=seed)
        street_splits = {name for name, idx in parts.items() for i in idx if ids[i].startswith("street:")}
        assert len(street_splits) == 1


def test_area_downsampled_source_is_the_exact_block_mean(tmp_path):
    from camhealth.data import AreaDownsampledSource

    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (10, 13), dtype=np.uint8)
    Image.fromarray(img).save(tmp_path / "a.png")
    src = AreaDownsampledSource(ImageFolderSource(tmp_path), 3)
    x, image_id = src[0]
    assert image_id == "a.png" and src.ids == ["a.png"] and len(src) == 1
    want = img[:9, :12].astype(np.float64).reshape(3, 3, 4, 3).mean((1, 3)) / 255.0  # the last row/column dropped
    assert x.shape == (1, 3, 4) and x.dtype == torch.float32
    assert np.allclose(x[0].numpy(), want, atol=1e-6)
    assert torch.equal(AreaDownsampledSource(ImageFolderSource(tmp_path), 1)[0][0], ImageFolderSource(tmp_path)[0][0])
    for bad, match in ((0, "factor = 0"), (9, r"factor = 9 is out of the allowed range \[1, 8\]")):
        with pytest.raises(ValueError, match=match):
            AreaDownsampledSource(ImageFolderSource(tmp_path), bad)
    with pytest.raises(TypeError, match="factor must be an int"):
        AreaDownsampledSource(ImageFolderSource(tmp_path), 2.5)
    Image.fromarray(img[:5, :5]).save(tmp_path / "a.png")
    with pytest.raises(ValueError, match=r"'a.png' \(5×5 px\) is smaller than one 8×8 block"):
        AreaDownsampledSource(ImageFolderSource(tmp_path), 8)[0]
    with pytest.raises(TypeError, match="not an image source"):
        AreaDownsampledSource([torch.zeros(1, 4, 4)], 2)


def test_area_downsampling_shrinks_the_optics_blur_by_the_factor():
    """A pixel-area-rendered edge blurred by a Gaussian of σ px, area-downsampled by k: the slanted edge (pixel
    aperture divided out) reads the Gaussian of σ/k — the new pixel aperture is an exact box and the optics scale by
    1/k; the native MTF at f_n is the original optics' MTF at f_n/k."""
    from camhealth.data import AreaDownsampledSource
    from camhealth.data.native_mtf import edge_native_mtf
    from camhealth.estimators.charts import slanted_edge_chart, slanted_edge_rois
    from camhealth.physics import apply_psf, gaussian_psf, mtf_from_psf
    from camhealth.physics.mtf import NORMALIZED_FREQUENCIES

    class _One(torch.utils.data.Dataset):
        ids = ["chart"]

        def __init__(self, x):
            self.x = x

        def __len__(self):
            return 1

        def __getitem__(self, i):
            return self.x, "chart"

    sigma, k = 1.2, 2
    chart = slanted_edge_chart(512).double()
    blurred = apply_psf(chart, gaussian_psf(torch.tensor([sigma], dtype=torch.float64), 25))[0]
    small = AreaDownsampledSource(_One(blurred), k)[0][0][None]
    r0, r1, c0, c1 = slanted_edge_rois(256)["left"]
    got = edge_native_mtf(small[:, :, r0:r1, c0:c1].float(), aperture=True)[0]
    psf = gaussian_psf(torch.tensor([sigma], dtype=torch.float64), 25)
    fn = torch.tensor(NORMALIZED_FREQUENCIES, dtype=torch.float64)
    want = mtf_from_psf(psf, (0.0,), fn / k)[0, 0].float()  # the full-size blur's MTF at f_n / k
    assert torch.allclose(got, want, atol=0.03), (got, want)
    full = edge_native_mtf(blurred[None, :, 2 * r0:2 * r1, 2 * c0:2 * c1].float(), aperture=True)[0]
    assert float(got[-1]) > float(full[-1]) + 0.3  # at f_n = 0.6: soft at full size, sharp after downsampling


def test_default_source_area_downsample():
    from camhealth.data import AreaDownsampledSource

    plain = DefaultSource(street_stride=25)
    small = DefaultSource(street_stride=25, area_downsample=2, deadleaves=1, deadleaves_size=64, supersample=4)
    assert small.ids == plain.ids + ["deadleaves-000000"]  # the same ids, so the same split
    for i in range(len(plain)):
        a, b = plain[i][0], small[i][0]
        assert b.shape == (1, a.shape[-2] // 2, a.shape[-1] // 2)
    assert small[len(plain)][0].shape == (1, 64, 64)  # dead leaves are rendered at their size, not downsampled
    assert isinstance(build_source("street", area_downsample=2, stride=25), AreaDownsampledSource)
    assert build_source("street", area_downsample=2, stride=25)[0][0].shape == (1, 288, 384)
    with pytest.raises(ValueError, match="supersample"):
        build_source("deadleaves", area_downsample=2)
    with pytest.raises(ValueError, match=r"area_downsample = 9 is out of the allowed range \[1, 8\]"):
        DefaultSource(area_downsample=9)
    with pytest.raises(ValueError, match="area_downsample = 0"):
        DefaultSource(area_downsample=0)
    with pytest.raises(ValueError, match="switched off"):
        DefaultSource(area_downsample=2, include_skimage=False, include_street=False, deadleaves=2)


def test_split_ids_of_a_folder_with_a_file_name_that_is_not_utf8(tmp_path):
    """A Latin-1 file name (its id holds a surrogate escape) splits like any other id, deterministically, instead of a
    raw UnicodeEncodeError; valid names keep their old digest (plain UTF-8)."""
    import hashlib
    import os

    from camhealth.data.sources import _unit_hash

    root = os.fsencode(tmp_path)
    img = Image.fromarray(np.zeros((8, 8), np.uint8))
    img.save(tmp_path / "a.png")
    try:
        with open(root + b"/caf\xe9.png", "wb") as f:
            img.save(f, format="PNG")
    except (OSError, UnicodeError):
        pytest.skip("this file system does not take non-UTF-8 file names")
    src = ImageFolderSource(tmp_path)
    assert "caf\udce9.png" in src.ids
    parts = split_ids(src.ids, 0.5, 0.0, seed=3)
    assert sorted(i for v in parts.values() for i in v) == [0, 1] and parts == split_ids(src.ids, 0.5, 0.0, seed=3)
    assert _unit_hash(3, "caf\udce9.png") == int.from_bytes(
        hashlib.blake2b(b"3\x1fcaf\xe9.png", digest_size=8).digest(), "big") / 2.0**64  # the file's own bytes
    assert _unit_hash(7, "street#000001") == int.from_bytes(
        hashlib.blake2b("7\x1fstreet#000001".encode(), digest_size=8).digest(), "big") / 2.0**64
    assert 0.0 <= _unit_hash(0, "lone \ud800 surrogate") < 1.0  # any other lone surrogate: still a fixed number


# ------------------------------------------------------------------ options a source does not take
@pytest.mark.parametrize("kwargs, unknown", [
    ({"dead_leaves": 60}, "dead_leaves"),  # misspelt: trained without its 60 dead-leaves scenes
    ({"deadleaf": 60}, "deadleaf"),
    ({"deadleaves": 2, "supersampling": 4}, "supersampling"),
    ({"bogus": 1}, "bogus"),
])
def test_default_source_refuses_an_unknown_option_naming_it_and_the_allowed_ones(kwargs, unknown):
    """``build_source('default', dead_leaves=60)`` built the source without its dead-leaves images, without a word."""
    allowed = r"allowed: \[.*'deadleaves', 'deadleaves_antialiased', 'deadleaves_size'.*'supersample'.*\]"
    with pytest.raises(ValueError, match=rf"unknown option\(s\) \['{unknown}'\] for the built-in source 'default'.*{allowed}"):
        build_source("default", **kwargs)
    with pytest.raises(ValueError, match=rf"DefaultSource: unknown option\(s\) \['{unknown}'\].*{allowed}"):
        DefaultSource(**kwargs)


@pytest.mark.parametrize("kwargs", [{"supersample": 4}, {"r_min": [1, 10]}, {"deadleaves_size": 64}, {"seed": 3}])
def test_dead_leaves_options_without_dead_leaves_images_are_refused(kwargs):
    key = next(iter(kwargs))
    with pytest.raises(ValueError, match=rf"dead-leaves option\(s\) \['{key}'\] given with deadleaves = 0"):
        build_source("default", **kwargs)
    assert len(build_source("default", deadleaves=1, **{"deadleaves_size": 32, **kwargs})) == len(DefaultSource()) + 1


def test_build_source_names_the_options_each_kind_of_source_takes(tmp_path):
    """``source_kwargs: {deadleaves: 5}`` with a folder gave a raw ``TypeError: ImageFolderSource.__init__() got an
    unexpected keyword argument``."""
    from camhealth.data.sources import check_source_options, source_options

    Image.fromarray(np.zeros((8, 8), np.uint8)).save(tmp_path / "a.png")
    with pytest.raises(ValueError, match=r"build_source: unknown option\(s\) \['deadleaves'\] for the image folder "
                                         rf"'{tmp_path}' \(ImageFolderSource\); allowed: \['area_downsample', 'bit_depth', "
                                         r"'extensions', 'recursive'\]"):
        build_source(tmp_path, deadleaves=5)
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['strid'\] for the built-in source 'street' "
                                         r"\(StreetSampleSource\); allowed: \['area_downsample', 'bit_depth', 'max_frames', "
                                         r"'stride'\]"):
        build_source("street", strid=5)
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['bogus'\] for the built-in source 'deadleaves'"):
        build_source("deadleaves", n_images=1, bogus=1)
    with pytest.raises(ValueError, match=r"supersample"):  # (its own message: dead leaves are rendered)
        build_source("deadleaves", area_downsample=2)
    assert "extensions" in source_options(f"frames:{tmp_path}") and "names" in source_options("skimage")
    assert len(build_source(tmp_path, recursive=False, area_downsample=1)) == 1
    with pytest.raises(ValueError, match=r"source_kwargs: unknown option\(s\) \['n_images'\] for the image folder"):
        check_source_options(str(tmp_path), {"n_images": 3})
    check_source_options(str(tmp_path / "not_yet"), {"anything": 1})  # a path that does not exist: named when built
    with pytest.raises(TypeError, match=r"source_kwargs = \[1\] must be a mapping"):
        check_source_options("default", [1])
