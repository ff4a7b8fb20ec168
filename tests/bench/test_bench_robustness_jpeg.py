"""The JPEG task of ``python -m camhealth.bench robustness`` (``--task jpeg``): its sets of frames and what the JPEG
grid test reads on them (the full run is a benchmark, not a test)."""

from __future__ import annotations

import argparse
import json

import pytest
import torch

from camhealth.bench import robustness as rb
from camhealth.bench import robustness_jpeg as rj


@pytest.fixture(scope="module")
def frames():
    return rb.make_frames(2, seed=0, paired=True)


def test_every_set_is_scored_and_only_coded_frames_are_coded(frames, monkeypatch, tmp_path):
    monkeypatch.setattr(rb, "make_frames", lambda n, seed=0, paired=False: frames)
    args = argparse.Namespace(task="jpeg", frames=2, seed=0, models=None, json=tmp_path / "j.json", command_line="test")
    res = rb.run(args)
    out = json.loads((tmp_path / "j.json").read_text())
    for cond in rb.CONDITIONS:  # every condition as the benchmark makes it: only the jpeg one is coded
        assert out[f"{cond}, as made"]["coded"] == (1.0 if cond == "jpeg" else 0.0), cond
        assert out[f"{cond}, as made"]["patches"] == 32
    assert out["reference, its scene a JPEG (quality 60) and the noise added afterwards"]["coded"] == 0.0
    for cond in ("reference", "white_noise", "strong"):
        for colour in ("gray", "colour"):
            assert out[f"{cond}, coded again at quality 100, {colour}"]["coded"] == 0.0  # steps of 1 DN: nothing removed
            if cond != "strong":
                assert out[f"{cond}, coded again at quality 75, {colour}"]["coded"] == 1.0
    assert len(out) == len(rb.CONDITIONS) + 1 + 3 * 2 * len(rj.QUALITIES)
    text = "\n".join(res.summary)
    assert "| jpeg, as made | 32 | 100.0 % |" in text and "| reference, as made | 32 | 0.0 % |" in text
    assert res.rows[0].name == "jpeg_grid" and res.rows[0].median_ms > 0


def test_recoding_cuts_the_patch_off_the_codecs_grid(frames):
    from camhealth.estimators.jpeg_quantisation import jpeg_grid

    noisy = frames[0].noisy[:4]
    coded = rj._recode(noisy, 75, colour=False)
    assert coded.shape == noisy.shape and coded.dtype == torch.float32
    g = jpeg_grid(coded)
    assert g.coded.all() and g.offset.tolist() == [[3, 5]] * 4  # cut at (5, 3): the grid starts 3 rows and 5 columns in
