"""python -m camhealth.corrupt and random_patches on bad input: each refusal names the option or argument and its
value, and comes before the source is read."""

from __future__ import annotations

import os

import pytest
import torch

from camhealth._cli import run_cli
from camhealth.corrupt import main, random_patches


@pytest.mark.parametrize("n, size, match", [
    (0, 16, r"n = 0 must be an integer >= 1"),
    (-1, 16, r"n = -1 must be an integer >= 1"),
    (True, 16, r"n = True must be an integer >= 1"),
    (1, 0, r"size = 0 must be an integer >= 2"),
    (1, -4, r"size = -4 must be an integer >= 2"),
    (1, 1, r"size = 1 must be an integer >= 2"),
    (1, 8.0, r"size = 8\.0 must be an integer >= 2"),
])  # fmt: skip
def test_random_patches_refuses_counts_and_sizes_below_their_least(n, size, match):
    """n = 0 failed as "stack expects a non-empty TensorList", size = -4 as "invalid shape dimension -4", and size = 0
    returned 0×0 patches."""
    source = [(torch.rand(1, 64, 64), "a")]
    with pytest.raises(ValueError, match=match):
        random_patches(source, n, size, torch.Generator().manual_seed(0))


@pytest.mark.parametrize("seed", [str(2**64), "99999999999999999999999", str(-(2**63) - 1)])
def test_a_seed_out_of_range_is_refused_naming_the_option(seed, tmp_path, capsys):
    """It failed as "Overflow when unpacking long long", which names no option."""
    rc = run_cli(main, "python -m camhealth.corrupt", ["deadleaves", "--n", "1", "--size", "16", "--seed", seed,
                                                       "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2 and f"argument --seed: must be an integer in [-9223372036854775808, 18446744073709551615]" in err
    assert seed in err and not (tmp_path / "out").exists()


def test_nothing_to_corrupt_is_refused_naming_the_flags_before_the_source_is_read(tmp_path):
    """The error named the class ("CameraCorruption(defocus=None, motion=None, noise=None) corrupts nothing"), after the
    source had been read."""
    with pytest.raises(ValueError, match=r"--no-noise with --defocus 0 0 and --motion 0 0 corrupts nothing"):
        main([str(tmp_path / "not_read"), "--no-noise", "--defocus", "0", "0", "--motion", "0", "0",
              "--out", str(tmp_path / "out")])


@pytest.mark.parametrize("n, size", [(1000, 128), (40, 512)])
def test_patches_that_need_more_memory_than_the_machine_has_are_refused_naming_n_and_size(n, size, tmp_path, monkeypatch):
    """Every patch is corrupted in one batch: --n 12000 --size 256 stopped with "MemoryError: Unable to allocate 256.
    KiB", naming neither option (or the system killed the process). Here the machine has 64 MiB."""
    real = os.sysconf
    monkeypatch.setattr(os, "sysconf", lambda key: {"SC_PAGE_SIZE": 4096, "SC_PHYS_PAGES": 16384}.get(key) or real(key))
    with pytest.raises(ValueError, match=rf"--n {n} --size {size}: the {n} patches of {size}×{size} px are corrupted in "
                                         rf"one batch, which needs about \d+\.\d GiB of memory .*this process can use "
                                         rf"0\.1 GiB\. Give a smaller --n or --size"):
        main([str(tmp_path / "not_read"), "--n", str(n), "--size", str(size), "--out", str(tmp_path / "out")])
    assert not (tmp_path / "out").exists()
