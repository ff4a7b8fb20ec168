"""noise_gain_db's inputs, the sweep cache on files that are not the cell's record, bfloat16 frames."""

import json
import math
import re

import pytest
import torch

from camhealth.iopc import IOPCSweep, SensorSetting, SweepConfig, SweepGrid, noise_gain_db
from camhealth.physics import CameraMetadata
from tests.iopc.fakes import FakeMTFEstimator, FakeNoiseEstimator, NoiseSensitiveDetector, smooth_frames

BOXES = [[10.0, 10.0, 60.0, 80.0]]
META = CameraMetadata.preset("EV76C661", temperature_c=70.0, exposure_s=0.1)


@pytest.mark.parametrize("kwargs, match", [
    ({"level_dn": -5.0}, r"level_dn = -5.0 is out of the allowed range: a finite number >= 0 DN"),
    ({"level_dn": float("nan")}, r"level_dn = nan is out of the allowed range: a finite number >= 0 DN"),
    ({"level_dn": float("inf")}, r"level_dn = inf is out of the allowed range"),
    ({"sources": ["Dark", "readout_noise"]},
     r"sources \['Dark', 'readout_noise'\] are not noise sources; allowed: a subset of \['photon', 'dark', 'readout'\]"),
    ({"sources": "photon"}, r"sources = 'photon' is not allowed: a list of names from"),
    ({"sources": ["photon"], "mean_intensity": 5.0}, r"mean_intensity = 5.0 is out of the allowed range \[0, 1\]"),
    ({"sources": ["photon"], "mean_intensity": -0.5}, r"mean_intensity = -0.5 is out of the allowed range \[0, 1\]"),
    ({"meta": CameraMetadata.preset("EV76C661", batch_size=2, temperature_c=torch.tensor([20.0, 70.0]))},
     r"meta has batch 2; allowed: 1"),
])
def test_noise_gain_db_refuses_what_has_no_gain(kwargs, match):
    """−5 DN gave the gain of +5 DN (8.0 dB), typos in the sources gave nan, mean_intensity = 5 gave −3.8 dB and
    metadata of batch 2 used its first sample only."""
    args = {"level_dn": 5.0, "meta": META, "sources": ["dark", "readout"], "mean_intensity": 0.5, **kwargs}
    with pytest.raises(ValueError, match=match):
        noise_gain_db(args["level_dn"], args["meta"], args["sources"], args["mean_intensity"])


def _sweep(tmp_path, frames=None):
    frames = smooth_frames(1, 96, 128) if frames is None else frames
    gt = [{"boxes": torch.tensor(BOXES), "labels": torch.tensor([1])}] * frames.shape[0]
    config = SweepConfig(grid=SweepGrid([0.0, 5.0], [0.0], [0.0]), sensor=SensorSetting())
    return IOPCSweep(frames, gt, NoiseSensitiveDetector(BOXES), FakeNoiseEstimator(32), FakeMTFEstimator(0.8, 48),
                     config, cache_dir=tmp_path / "cache" if tmp_path is not None else None)


def _corrupt(path, other):
    """Cache file contents that are not the cell's record."""
    rec = json.loads(path.read_text())
    return {
        "another cell": json.dumps({**json.loads(other.read_text()), "index": rec["index"]}),
        "another index": json.dumps({**rec, "index": rec["index"] + 7}),
        "a JSON list": "[1, 2, 3]",
        "a JSON number": "5",
        "an incomplete record": json.dumps({"index": rec["index"], "key": rec["key"]}),
        "not UTF-8": b"\xff\xfe\x00garbage",
    }


@pytest.mark.parametrize("case", ["another cell", "another index", "a JSON list", "a JSON number",
                                  "an incomplete record", "not UTF-8"])
def test_a_cache_file_that_is_not_the_cells_record_is_recomputed(tmp_path, case):
    """Cell 1's record copied into cell 0's file was collected as cell 0 (L = 7 binned twice, L = 0 never); a file
    holding [1, 2, 3] failed with "'list' object has no attribute 'items'", non-UTF-8 bytes with a UnicodeDecodeError."""
    sw = _sweep(tmp_path)
    recs = [sw.run_cell(c) for c in sw.cells]
    files = {c["index"]: sw._cache_path(c) for c in sw.cells}
    content = _corrupt(files[0], files[1])[case]
    if isinstance(content, bytes):
        files[0].write_bytes(content)
    else:
        files[0].write_text(content)
    assert sw.cached(sw.cells[0]) is None
    assert [c["key"] for c in sw.remaining_cells()] == [sw.cells[0]["key"]]
    again = sw.run_cell(sw.cells[0])  # computed again, and its file rewritten
    assert again["key"] == recs[0]["key"] and again["ap"] == recs[0]["ap"]
    assert [(r["index"], r["key"]) for r in sw.collect()] == [(c["index"], c["key"]) for c in sw.cells]


@pytest.mark.parametrize("cached", [True, False])
def test_bfloat16_frames_are_fingerprinted(tmp_path, cached):
    """bfloat16 frames failed in fingerprint() with "Got unsupported ScalarType BFloat16": at construction with a
    cache, and without one only in to_iopc, after every cell had been computed."""
    frames = smooth_frames(1, 96, 128)
    sw = _sweep(tmp_path if cached else None, frames.bfloat16())
    fp = sw.fingerprint()
    assert re.fullmatch(r"[0-9a-f]{16}", fp) and fp != _sweep(None, frames).fingerprint()
    iopc = sw.to_iopc([sw.run_cell(c) for c in sw.cells])
    assert iopc.provenance["fingerprint"] == fp and math.isfinite(float(iopc.count_2d.sum()))
