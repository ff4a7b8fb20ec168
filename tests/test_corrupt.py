import json

import pytest
import torch
from skimage.io import imread, imsave

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
    with pytest.raises(ValueError, match="smaller than the patch size"):
        random_patches(src, 1, 64, torch.Generator().manual_seed(0))


def test_missing_source_is_a_clear_error(tmp_path):
    with pytest.raises((FileNotFoundError, ValueError), match="nope"):
        main([str(tmp_path / "nope"), "--out", str(tmp_path / "o")])


@pytest.mark.parametrize("option,values,message", [
    ("--defocus", ["-5", "-1"], "--defocus -5 -1: MIN and MAX must be >= 0 px"),  # was: no defocus, without a word
    ("--defocus", ["21", "1"], "--defocus 21 1: MIN must be <= MAX"),
    ("--motion", ["-3", "-1"], "--motion -3 -1: MIN and MAX must be >= 0 px"),
    ("--shake", ["0.5", "2"], "--shake 0.5 2: MAX must be <= 1"),
])
def test_ranges_are_checked_naming_the_option(option, values, message, tmp_path):
    with pytest.raises(ValueError, match=message):  # (before the source is read: it does not exist)
        main([str(tmp_path / "nope"), "--out", str(tmp_path / "o"), option, *values])
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("option", ["--size", "--n"])
def test_size_and_count_below_one_are_refused_by_the_parser(option, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main([str(tmp_path / "nope"), "--out", str(tmp_path / "o"), option, "0"])
    assert info.value.code == 2 and f"argument {option}: must be >= 1, got 0" in capsys.readouterr().err
