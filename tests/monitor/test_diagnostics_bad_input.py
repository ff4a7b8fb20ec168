"""DiagnosticsWriter and frame_level on bad input: stamps a .mcap or .bag cannot hold are refused, naming the stamp
and the range, before anything of that frame is written; xi_threshold_dn must be a finite number >= 0."""

from __future__ import annotations

import math

import pytest
import torch

from camhealth.monitor import Monitor
from camhealth.monitor.diagnostics import DiagnosticsWriter, frame_level, read_diagnostics
from tests.monitor.conftest import FakeMTF, FakeNoise

T0 = 1_700_000_000 * 10**9


@pytest.fixture(scope="module")
def report():
    frame = torch.rand(256, 256, generator=torch.Generator().manual_seed(0))
    return Monitor(FakeNoise(), FakeMTF(), sensor="ICX285", warmup=False).process(frame)


@pytest.mark.parametrize("suffix, stamp_ns, shown", [
    (".mcap", 2**31 * 10**9, r"stamp_ns = 2147483648000000000 \(2147483648 s\) is out of the range of a ROS 2 \.mcap "
                             r"header stamp: \[-2147483648, 2147483647\] s"),
    (".mcap", -(2**31 + 1) * 10**9, r"\(-2147483649 s\) is out of the range of a ROS 2 \.mcap header stamp"),
    (".bag", 2**33 * 10**9, r"stamp_ns = 8589934592000000000 \(8589934592 s\) is out of the range of a ROS 1 \.bag "
                            r"header stamp: \[0, 2147483647\] s"),
    (".bag", -5, r"stamp_ns = -5 \(-1 s\) is out of the range of a ROS 1 \.bag header stamp: \[0, 2147483647\] s"),
])
@pytest.mark.parametrize("call", ["report", "error"])
def test_stamps_the_file_cannot_hold_are_refused_and_the_file_stays_readable(tmp_path, report, suffix, stamp_ns, shown,
                                                                             call):
    """A stamp >= 2^31 s crashed in the serializer with struct.error: 'i' format requires ... and ended the run."""
    path = tmp_path / f"diag{suffix}"
    w = DiagnosticsWriter(path, "camhealth: /cam")
    assert w.write_report(report, T0, T0) in (0, 1, 2)
    with pytest.raises(ValueError, match=shown):
        if call == "report":
            w.write_report(report, stamp_ns, T0 + 1)
        else:
            w.write_error("bad frame", 1, "/cam@1", stamp_ns, T0 + 1)
    assert w.write_error("bad frame", 2, "/cam@2", None, T0 + 2) == 2  # the writer goes on
    w.close()
    assert [d["stamp_ns"] for d in read_diagnostics(path)] == [T0, T0 + 2]


def test_a_log_time_beyond_a_ros1_bag_is_refused_naming_it(tmp_path, report):
    w = DiagnosticsWriter(tmp_path / "d.bag", "camhealth: /cam")
    with pytest.raises(ValueError, match=r"log_time_ns = 4294967296000000000 is out of the range of a ROS 1 \.bag log "
                                         r"time: \[0, 4294967295999999999\] ns"):
        w.write_report(report, T0, 2**32 * 10**9)
    w.abort()


@pytest.mark.parametrize("value", [math.nan, -1.0, math.inf, "1", True, None])
def test_xi_threshold_must_be_a_finite_number_not_below_zero(tmp_path, report, value):
    """NaN silently disabled every "uncertain" WARN; -1 made every frame a WARN ("exceeds -1 DN")."""
    with pytest.raises(ValueError, match=rf"xi_threshold_dn = {value!r} must be a finite number >= 0 \[DN\]"):
        DiagnosticsWriter(tmp_path / "d.mcap", "camhealth: /cam", xi_threshold_dn=value)
    with pytest.raises(ValueError, match=rf"xi_threshold_dn = {value!r} must be a finite number >= 0"):
        frame_level(report, value)
    assert not list(tmp_path.iterdir())  # nothing was started
    assert frame_level(report, 0.0)[0] in (0, 1, 2) and frame_level(report, 1)[0] == frame_level(report, 1.0)[0]
