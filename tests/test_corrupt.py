import json

import numpy as np
import pytest
import torch
from PIL import Image
from skimage.io import imread, imsave

from camhealth._cli import run_cli
from camhealth.corrupt import main, random_patches


def _folder(tmp_path, n=3, size=80):
    d = tmp_path / "imgs"
    d.mkdir()
    g = torch.Generator().manual_seed(0)
    for i in range(n):
        arr = (torch.rand(size, size, generator=g) * 255).to(torch.uint8).numpy()
        imsave(d / f"img{i}.png", arr, check_contrast=False)
    return d


def test_cli_writes_pngs_and_labels(tmp_path):
    src = _folder(tmp_path)
    out = tmp_path / "out"
    assert main([str(src), "--n", "3", "--size", "48", "--out", str(out), "--sensor", "ICX285", "--defocus", "1", "5",
                 "--motion", "1", "5", "--shake", "0", "1"]) == 0
    lines = [json.loads(line) for line in (out / "labels.jsonl").read_text().splitlines()]
    assert len(lines) == 3
    rec = lines[0]
    assert len(rec["mtf_h"]) == 8 and len(rec["mtf_v"]) == 8
    assert set(rec["sigma_dn"]) == {"photon", "dark", "readout"}
    assert rec["metadata"]["full_well_e"] == pytest.approx(14000)
    img = imread(out / rec["corrupted"])
    assert img.shape == (48, 48) and img.dtype.name == "uint8"


def test_cli_blur_only_and_overview(tmp_path):
    src = _folder(tmp_path, n=1, size=64)
    out = tmp_path / "o"
    main([str(src), "--n", "2", "--size", "32", "--out", str(out), "--no-noise", "--defocus", "1", "3", "--motion", "0", "0",
          "--overview"])
    rec = json.loads((out / "labels.jsonl").read_text().splitlines()[0])
    assert "sigma_dn" not in rec and "mtf_h" in rec
    assert (out / "overview.png").stat().st_size > 0


def test_patch_larger_than_image_is_a_clear_error(tmp_path):
    from camhealth.data import build_source

    src = build_source(_folder(tmp_path, n=1, size=40))
    with pytest.raises(ValueError, match=r"smaller than the patch size 64×64 px \(--size 64\); the largest patch they hold is 40×40"):
        random_patches(src, 1, 64, torch.Generator().manual_seed(0))


def test_patches_come_only_from_images_at_least_the_patch_size(tmp_path):
    """A source with a small and a large image: every seed succeeds, every crop is from the large one."""
    from camhealth.data import build_source

    d = tmp_path / "mixed"
    d.mkdir()
    imsave(d / "big.png", np.full((80, 80), 100, np.uint8), check_contrast=False)
    imsave(d / "small.png", np.full((40, 80), 200, np.uint8), check_contrast=False)
    src = build_source(d)
    for seed in range(5):
        patches, ids = random_patches(src, 4, 64, torch.Generator().manual_seed(seed))
        assert patches.shape == (4, 1, 64, 64) and all(i.startswith("big.png@") for i in ids)


def test_missing_source_is_a_clear_error(tmp_path):
    with pytest.raises((FileNotFoundError, ValueError), match="nope"):
        main([str(tmp_path / "nope"), "--out", str(tmp_path / "o")])


@pytest.mark.parametrize("option,values,message", [
    ("--defocus", ["-5", "-1"], "--defocus -5 -1: MIN and MAX must be >= 0 px"),  # was: no defocus, without a word
    ("--defocus", ["21", "1"], "--defocus 21 1: MIN must be <= MAX"),
    ("--motion", ["-3", "-1"], "--motion -3 -1: MIN and MAX must be >= 0 px"),
    ("--shake", ["0.5", "2"], "--shake 0.5 2: MAX must be <= 1"),
    ("--defocus", ["1", "300"], "--defocus 1 300: MAX must be <= 253 px"),  # the largest blur kernel's disk
    ("--motion", ["1", "300"], "--motion 1 300: MAX must be <= 252 px"),
])
def test_ranges_are_checked_naming_the_option(option, values, message, tmp_path):
    with pytest.raises(ValueError, match=message):  # (before the source is read: it does not exist)
        main([str(tmp_path / "nope"), "--out", str(tmp_path / "o"), option, *values])
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("option, value, least", [("--size", "0", 2), ("--size", "1", 2), ("--n", "0", 1)])
def test_size_and_count_below_their_least_are_refused_by_the_parser_before_any_file(option, value, least, tmp_path, capsys):
    """--size 1 crashed inside imageio (a 1×1 patch squeezed to a 0-d array) after labels.jsonl was opened, and its
    noise labels (a standard deviation over one pixel) would have been NaN: at least 2 px, said by the parser."""
    src = _folder(tmp_path, n=1, size=40)
    with pytest.raises(SystemExit) as info:
        main([str(src), "--out", str(tmp_path / "o"), option, value])
    assert info.value.code == 2 and f"argument {option}: must be >= {least}, got {value}" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_a_one_pixel_patch_is_written_as_a_one_pixel_png(tmp_path):
    from camhealth.corrupt import _save_png

    _save_png(tmp_path / "p.png", torch.full((1, 1, 1), 0.5))
    img = imread(tmp_path / "p.png")
    assert img.shape == (1, 1) and int(img[0, 0]) == 128


@pytest.mark.parametrize("quantize", [False, True])
def test_the_total_sigma_label_is_that_of_the_png_written(quantize, tmp_path):
    """labels.jsonl's sigma_total_dn was the realised σ of the float image before the 8-bit rounding of the PNG (also
    with --quantize, whose image form_image measures before it rounds): 2 % low at 1.4 DN. It is the σ of the PNG's
    values minus the noise-free image (here, without blur, the clean PNG), unbiased over the patch's pixels."""
    d = tmp_path / "flat"
    d.mkdir()
    imsave(d / "flat.png", np.full((64, 64), 100, np.uint8), check_contrast=False)
    out = tmp_path / "o"
    assert main([str(d), "--n", "4", "--size", "48", "--out", str(out), "--sensor", "ICX285", "--defocus", "0", "0",
                 "--motion", "0", "0", *(["--quantize"] if quantize else [])]) == 0
    for rec in map(json.loads, (out / "labels.jsonl").read_text().splitlines()):
        noise = imread(out / rec["corrupted"]).astype(np.float64) - imread(out / rec["clean"]).astype(np.float64)
        assert rec["sigma_total_dn"] == pytest.approx(noise.std(ddof=1), abs=6e-5)


def test_shake_without_motion_blur_is_refused_naming_both_flags(tmp_path):
    with pytest.raises(ValueError, match="--shake 0.5 1: camera shake needs motion blur; --motion 0 0 switches it off"):
        main([str(tmp_path / "nope"), "--out", str(tmp_path / "o"), "--motion", "0", "0", "--shake", "0.5", "1"])
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("where", ["same", "inside", "contains"])
def test_out_is_refused_when_it_is_in_or_around_the_source_folder(where, tmp_path, capsys):
    src = _folder(tmp_path, n=1, size=40)
    before = (src / "img0.png").read_bytes()
    out = {"same": src, "inside": src / "sub", "contains": tmp_path}[where]
    rc = run_cli(main, "python -m camhealth.corrupt", [str(src), "--n", "1", "--size", "32", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and f"--out {out}" in err and f"source folder {src}" in err
    assert sorted(p.name for p in src.rglob("*")) == ["img0.png"] and (src / "img0.png").read_bytes() == before


def test_earlier_output_is_kept_without_overwrite_and_replaced_whole_with_it(tmp_path, capsys):
    src = _folder(tmp_path, n=1, size=40)
    out = tmp_path / "o"
    args = [str(src), "--size", "32", "--out", str(out), "--no-noise", "--motion", "0", "0"]
    assert main([*args, "--n", "3"]) == 0
    (out / "mine.txt").write_text("not an output")
    first = {p.name: p.read_bytes() for p in out.iterdir()}
    assert run_cli(main, "python -m camhealth.corrupt", [*args, "--n", "1", "--seed", "1"]) == 2
    err = capsys.readouterr().err
    assert f"--out {out} already holds the output of a run" in err and "--overwrite" in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == first
    assert main([*args, "--n", "1", "--seed", "1", "--overwrite"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["0000_clean.png", "0000_corrupted.png", "labels.jsonl", "mine.txt"]
    assert len((out / "labels.jsonl").read_text().splitlines()) == 1


def _png16(path, top):
    arr = np.full((64, 64), 500, np.uint16)  # DN 500 everywhere but one pixel: the file's largest value
    arr[0, 0] = top
    Image.fromarray(arr).save(path)


def test_bit_depth_reads_every_file_of_a_folder_at_one_scale(tmp_path):
    """A 12-bit camera's dark and bright frames (16-bit PNGs, no sBIT): with --bit-depth 12 DN 500 is 500/4095 in both."""
    d = tmp_path / "raw16"
    d.mkdir()
    _png16(d / "dark.png", 1000)  # "auto" would guess 10 bits: DN 500 read 4× too bright
    _png16(d / "bright.png", 4000)
    out = tmp_path / "o"
    assert main([str(d), "--n", "4", "--size", "64", "--out", str(out), "--no-noise", "--defocus", "1", "1", "--motion", "0",
                 "0", "--bit-depth", "12"]) == 0
    for rec in map(json.loads, (out / "labels.jsonl").read_text().splitlines()):
        assert np.median(imread(out / rec["clean"])) == round(500 / 4095 * 255)


@pytest.mark.parametrize("value", ["20", "twelve"])
def test_bad_bit_depth_is_refused_by_the_parser(value, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main([str(tmp_path / "nope"), "--out", str(tmp_path / "o"), "--bit-depth", value])
    assert info.value.code == 2 and "argument --bit-depth: must be 'auto' or an integer number of bits" in capsys.readouterr().err
