"""Monitor / as_frame on bad input: a frame label the JSON line cannot hold is refused before the frame is read (a NumPy
or torch integer index and a path as source_id are taken as their values), tensors without dense pixel data are refused
naming their kind, and a defect map asked for pixels flagged in more frames than an int32 count holds is empty. NumPy
numbers are taken as constructor arguments; a sensor key in a frame's metadata is named as no per-frame field."""

from __future__ import annotations

import json
import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from camhealth.monitor import Monitor, as_frame
from tests.monitor.conftest import FakeMTF, FakeNoise


@pytest.fixture
def frame():
    return np.random.default_rng(0).integers(0, 256, (256, 320), dtype=np.uint8)


def _monitor():
    return Monitor(FakeNoise(), FakeMTF(), sensor="ICX285", warmup=False)


@pytest.mark.parametrize("index, shown", [(np.int64(3), 3), (np.uint16(7), 7), (torch.tensor(5), 5), (-1, -1), (None, None)])
def test_numpy_and_torch_integer_indices_are_written_as_integers(frame, index, shown):
    """index=np.int64(3) (a loop over np.arange) was kept as it was: to_json then failed with "Object of type int64 is
    not JSON serializable", after the frame had entered the aggregation."""
    report = _monitor().process(frame, index=index, source_id=Path("cam") / "f3.png")
    line = json.loads(report.to_json())
    assert line["index"] == shown and type(line["index"]) is type(shown)
    assert line["source_id"] == str(Path("cam") / "f3.png")


@pytest.mark.parametrize("kwargs, shown", [
    ({"index": 1.5}, r"index = 1\.5 must be None or an integer \(the frame's index in its source\), got float"),
    ({"index": math.nan}, r"index = nan must be None or an integer"),
    ({"index": True}, r"index = True must be None or an integer .*got bool"),
    ({"index": "3"}, r"index = '3' must be None or an integer .*got str"),
    ({"index": torch.tensor(2.0)}, r"index = tensor\(2\.\) must be None or an integer"),
    ({"source_id": b"f.png"}, r"source_id = b'f\.png' must be None, a text or a path .*got bytes"),
    ({"source_id": 5}, r"source_id = 5 must be None, a text or a path .*got int"),
])
def test_a_label_the_json_line_cannot_hold_is_refused_before_the_frame_is_read(frame, kwargs, shown):
    """index=nan made to_json fail ("Out of range float values are not JSON compliant"), bytes "not JSON serializable" —
    after the monitor had counted the frame."""
    mon = _monitor()
    with pytest.raises(TypeError, match=shown):
        mon.process(frame, **kwargs)
    assert mon.frames == 0 and mon.summary()["alarms"] == {}


@pytest.mark.parametrize("make, shown", [
    (lambda: torch.eye(64).to_sparse(), "a torch.sparse_coo tensor: .to_dense() it first"),
    (lambda: torch.eye(64).to_sparse_csr(), "a torch.sparse_csr tensor: .to_dense() it first"),
    (lambda: torch.empty(64, 64, device="meta"), "a meta tensor, which holds no data"),
    (lambda: torch.quantize_per_tensor(torch.rand(64, 64), 0.01, 0, torch.quint8), "a quantized tensor: .dequantize() it first"),
], ids=["sparse_coo", "sparse_csr", "meta", "quantized"])
def test_a_tensor_without_dense_pixel_data_is_refused_naming_its_kind(make, shown):
    """A sparse, meta or quantized tensor failed deep inside torch (NotImplementedError "Could not run 'aten::ne.Scalar'
    with arguments from the 'SparseCPU' backend", "Cannot copy out of meta tensor; no data!", a RuntimeError)."""
    with warnings.catch_warnings():  # (torch's beta/deprecation notes on making such tensors)
        warnings.simplefilter("ignore")
        tensor = make()
    with pytest.raises(TypeError, match=re.escape(f"frame must be a dense tensor holding its pixel values, got {shown}")):
        as_frame(tensor)
    if "sparse" in shown:  # the hint works
        assert torch.equal(as_frame(tensor.to_dense()), as_frame(torch.eye(64)))


@pytest.mark.parametrize("min_frames", [2**31, 2**40, 10**20])
def test_a_defect_map_of_more_frames_than_an_int32_count_holds_is_empty(min_frames):
    """found_defects(2**31) compared the int32 counts with a value that wrapped to −2^31: every pixel of the frame was
    "defective" (a --defects-out map of all pixels); from 2^63 it raised OverflowError."""
    from tests.monitor.test_defect_map import _defect_frame

    frame, _ = _defect_frame()
    mon = Monitor("noise_source_full", None, sensor="ICX285", mode="map", warmup=False, adaptive=False)
    mon.process(frame)
    mon.process(frame)
    found2, counts = mon.found_defects(2)
    assert 0 < int(found2.sum()) < found2.numel() and int(counts.max()) == 2
    found, counts_again = mon.found_defects(min_frames)
    assert found.shape == found2.shape and found.dtype == torch.bool and not bool(found.any())
    assert torch.equal(counts_again, counts)
    assert int(mon.found_defects(2**31 - 1)[0].sum()) == 0  # the largest int32 count itself


# ------------------------------------------------------------------ NumPy numbers as constructor arguments
@pytest.mark.parametrize("name, value, kept", [
    ("window", np.int64(5), 5), ("window", np.uint8(3), 3), ("noise_samples", np.int32(4), 4),
    ("mtf_samples", np.int16(3), 3), ("mtf_views", np.int64(2), 2), ("batch_size", np.int64(64), 64),
    ("xi_threshold_dn", np.float32(1.0), 1.0), ("xi_threshold_dn", np.int64(2), 2.0),
    ("xi_sigmas", np.float32(2.5), 2.5), ("xi_sigmas", np.float16(3.0), 3.0),
])
def test_numpy_numbers_are_taken_as_the_python_numbers_they_hold(name, value, kept):
    """Monitor(window=np.int64(5)) was refused ("window = np.int64(5) must be an integer 1…1000"), and so was
    xi_threshold_dn=np.float32(1.0) ("must be a finite number >= 0"): a value read from a NumPy array or config."""
    mon = Monitor(FakeNoise(), FakeMTF(), sensor="ICX285", warmup=False, **{name: value})
    got = {"noise_samples": lambda: mon.n_samples["noise"], "mtf_samples": lambda: mon.n_samples["mtf"]}.get(
        name, lambda: getattr(mon, name))()
    assert got == kept and type(got) is type(kept)


@pytest.mark.parametrize("name, value, shown", [
    ("window", np.int64(0), r"window = 0 must be an integer 1…"),
    ("window", np.float64(5.0), r"window = 5\.0 must be an integer 1…"),
    ("window", np.bool_(True), r"window = (np\.)?True_? must be an integer 1…"),
    ("noise_samples", np.int64(10**6), r"noise_samples = 1000000 must be an integer 1…"),
    ("batch_size", np.int64(-1), r"batch_size = -1 must be an integer >= 1"),
    ("mtf_views", np.int64(3), r"mtf_views = 3 must be 1, 2 or 4"),
    ("xi_threshold_dn", np.float32(-1.0), r"xi_threshold_dn = -1\.0 must be a finite number >= 0"),
    ("xi_sigmas", np.float64(np.nan), r"xi_sigmas = nan must be a finite number >= 0"),
    ("xi_sigmas", np.bool_(True), r"xi_sigmas = (np\.)?True_? must be a finite number >= 0"),
])
def test_numpy_numbers_keep_the_range_checks_and_bools_stay_refused(name, value, shown):
    with pytest.raises(ValueError, match=shown):
        Monitor(FakeNoise(), FakeMTF(), sensor="ICX285", warmup=False, **{name: value})


def test_found_defects_takes_a_numpy_integer(frame):
    mon = _monitor()
    mon.process(frame)
    assert torch.equal(mon.found_defects(np.int64(1))[1], mon.found_defects(1)[1])


# ------------------------------------------------------------------ sensor keys in a frame's metadata
@pytest.mark.parametrize("metadata, key, instead", [
    ({"sensor": "ICX285"}, "sensor", r"Monitor\(sensor=…\).*--sensor.*CameraMetadata\.preset\('ICX285'"),
    ({"gain_db": 6.0, "sensor": "EV76C661"}, "sensor", r"CameraMetadata\.preset\('EV76C661'"),
    ({"sensor_type": "CMOS"}, "sensor_type", r"give is_cmos \(1 CMOS, 0 CCD\) for a frame.*Monitor\(sensor=…\)"),
])
def test_a_sensor_key_in_a_frames_metadata_is_named_as_no_per_frame_field(frame, metadata, key, instead):
    """process(frame, metadata={"sensor": "ICX285"}) said "field sensor = 'ICX285' must be a number in physical units"
    — no number would do: the key names the camera, not a field of a frame's state."""
    mon = _monitor()
    shown = rf"per-frame metadata: {key} = '\w+' is not a per-frame field .*{instead}"
    with pytest.raises(ValueError, match=shown) as err:
        mon.process(frame, metadata=metadata)
    assert "physical units" not in str(err.value)
    assert mon.frames == 0
    report = mon.process(frame, metadata={"gain_db": 6.0, "is_cmos": 1.0})  # what the message points to
    assert report.metadata["gain_db"] == 6.0
