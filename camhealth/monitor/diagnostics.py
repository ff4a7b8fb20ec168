"""The monitor's verdicts as ROS diagnostics: one ``diagnostic_msgs/DiagnosticArray`` per frame.

:class:`DiagnosticsWriter` writes them to an MCAP file (``.mcap``, ROS 2 CDR) or a ROS 1 bag (``.bag``) on
``/diagnostics``, each stamped with the image's header time (and logged at the image's log time), so that
Foxglove, rqt_runtime_monitor or PlotJuggler show them beside the recording. Each array holds one
``DiagnosticStatus``:

- ``name``: ``"camhealth: <image topic>"``; ``hardware_id``: the image's ``frame_id`` (else the topic);
- ``level`` (:func:`frame_level`): **ERROR** when the ξ alarm fires (``noisier``/``cleaner``), when noise
  is not assessable (no informative patch: black, saturated, …) or the frame could not be decoded; **WARN**
  when the verdict is uncertain — ξ̃ beyond ``--xi-threshold-dn`` but within k standard errors (the spread
  over the patches leaves it open), ξ not checked (no noise-source model or no metadata), defective pixels from
  ``DEFECT_ALARM_PPM`` per million of the pixels tested on (hot, stuck or dead pixels, impulses; with a defect map,
  those it does not mark), or blur not
  assessable (featureless scene); **OK** otherwise;
- ``message``: the reason in one sentence (the alarm message for ERROR);
- ``values`` (:data:`KEYS`, strings; ``nan`` where a number is missing): the alarm state, ξ̃ and its limit,
  σ of PN/DCSN/RN and the total (temporal + spatial medians, DN of 255) with the total's spread, the row and
  column noise of the frame (``TaskReport.banding``: 0 where none is found; in the total), the defective pixels
  per million tested, how many of them recur at the same place and how many a defect map marks
  (``TaskReport.defects``; 0 where none; ``known`` nan without a map or without defects), the blur
  indicator MTF̃ with its spread and its H and V parts at f_n = 0.1, the patch counts, the camera state
  used (gain, exposure, temperature) and the frame's processing time.

:func:`read_diagnostics` reads such a file back (with :class:`camhealth.data.rosbag.Recording`).
"""

from __future__ import annotations

import math
import numbers
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from camhealth.monitor.api import DEFECT_ALARM_PPM, NOISE_FIELDS, FrameReport, defects_text, new_defect_ppm, top_cause

__all__ = ["OK", "WARN", "ERROR", "LEVEL_NAMES", "KEYS", "DIAGNOSTICS_TOPIC", "DIAGNOSTICS_SUFFIXES",
           "frame_level", "key_values", "check_diagnostics_path", "DiagnosticsWriter", "read_diagnostics"]

OK, WARN, ERROR = 0, 1, 2
#: ``DiagnosticStatus.level`` → name.
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR", 3: "STALE"}
DIAGNOSTICS_TOPIC = "/diagnostics"
DIAGNOSTICS_SUFFIXES = (".mcap", ".bag")
#: Header stamps [s] the files can hold: ROS 2 ``builtin_interfaces/Time.sec`` is int32; ROS 1 time is uint32 seconds,
#: which ``rosbags`` serialises as int32, so [0, 2^31 − 1] is what both ROS 1 and this writer read the same.
_STAMP_SECONDS_ROS2 = (-(2**31), 2**31 - 1)
_STAMP_SECONDS_ROS1 = (0, 2**31 - 1)
#: Largest log time [ns]: a ROS 1 bag stores uint32 seconds + nanoseconds, MCAP a uint64 of ns. (A negative log time
#: is written as the last one, or 0: log times of a file never decrease.)
_LOG_NS_MAX_ROS1 = (2**32 - 1) * 1_000_000_000 + 999_999_999
_LOG_NS_MAX_ROS2 = 2**64 - 1
_MSGTYPE = "diagnostic_msgs/msg/DiagnosticArray"
#: Keys of the ``values`` of every status, in order.
KEYS: tuple[str, ...] = (
    "level", "alarm", "xi_dn", "xi_limit_dn",
    "noise_total_dn", "noise_total_spread_dn", "noise_pn_dn", "noise_dcsn_dn", "noise_rn_dn", "noise_row_dn",
    "noise_col_dn", "noise_defect_ppm", "noise_defects_recurring", "noise_defects_known", "noise_cause", "noise_cause_p",
    "blur_mtf_indicator", "blur_mtf_indicator_spread", "blur_mtf_h_fn0.1", "blur_mtf_v_fn0.1",
    "noise_patches_used", "noise_patches_total", "blur_patches_used", "blur_patches_total",
    "gain_db", "exposure_s", "temperature_c", "frame", "index", "source_id", "processing_ms",
)


def _fmt(x: Any, spec: str = ".4g") -> str:
    if x is None:
        return "nan"
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    return format(v, spec) if math.isfinite(v) else "nan"


def _check_xi_threshold(v: object) -> float:
    """``xi_threshold_dn`` as a float: a finite number >= 0 [DN] (as ``Monitor`` and the CLI require), else
    ``ValueError`` naming it; NaN would silence every "uncertain" WARN, a negative value make every frame one."""
    if isinstance(v, (bool, np.bool_)) or not (isinstance(v, numbers.Real) and math.isfinite(v) and v >= 0):
        raise ValueError(f"xi_threshold_dn = {v!r} must be a finite number >= 0 [DN]")
    return float(v)


def frame_level(report: FrameReport, xi_threshold_dn: float = 1.0) -> tuple[int, str]:
    """(level, message) of one frame's report (see the module docstring for the rules); ``xi_threshold_dn``: a finite
    number >= 0 [DN] (``ValueError`` otherwise)."""
    xi_threshold_dn = _check_xi_threshold(xi_threshold_dn)
    alarm = report.alarm or {}
    state = alarm.get("state")
    if state in ("noisier", "cleaner"):
        return ERROR, f"ξ alarm: {alarm.get('message', state)}"
    if state == "not_assessable":
        why = report.noise.note if report.noise is not None and report.noise.note else alarm.get("message", "")
        return ERROR, f"noise not assessable: {why}"
    if state == "unavailable" or state is None:
        return WARN, f"uncertain: ξ not checked ({alarm.get('message', 'no alarm')})"
    xi, limit = alarm.get("xi_dn"), alarm.get("limit_dn")
    if xi is not None and limit is not None and abs(xi) > xi_threshold_dn:
        return WARN, (f"uncertain: |ξ̃| = {abs(xi):.2f} DN exceeds {xi_threshold_dn:g} DN but not the limit {limit:.2f} DN "
                      "set by the spread over the patches")
    defects = report.noise.defects if report.noise is not None else None
    if defects and new_defect_ppm(defects) >= DEFECT_ALARM_PPM:
        return WARN, f"defective pixels: {defects_text(defects)}; {alarm.get('message', '')}"
    if report.mtf is not None and not report.mtf.assessable:
        return WARN, f"uncertain: blur not assessable ({report.mtf.note or 'no informative patch'}); {alarm.get('message', '')}"
    return OK, str(alarm.get("message", "ok"))


def _used(counts: dict[str, int]) -> int:
    return int(counts.get("estimated", 0) + counts.get("interpolated", 0) + counts.get("reused", 0))


def key_values(report: FrameReport, level: int) -> list[tuple[str, str]]:
    """The ``values`` of a frame's status, as (key, value) strings in the order of :data:`KEYS`."""
    alarm = report.alarm or {}
    noise, mtf = report.noise, report.mtf
    nv = {name: noise.value(name) if noise is not None and noise.assessable else None for name in NOISE_FIELDS}
    spread = None
    if noise is not None and noise.assessable and noise.spread is not None:
        spread = float(noise.spread[NOISE_FIELDS.index("total")])
    ind = mtf.indicator if mtf is not None and mtf.assessable and mtf.indicator else (None, None)
    h01 = v01 = None
    if mtf is not None and mtf.assessable and mtf.median is not None:
        from camhealth.physics.mtf import NORMALIZED_FREQUENCIES

        i = list(NORMALIZED_FREQUENCIES).index(0.1)
        h01, v01 = float(mtf.median[i]), float(mtf.median[len(NORMALIZED_FREQUENCIES) + i])
    band = (noise.banding or {"row_dn": 0.0, "col_dn": 0.0}) if noise is not None and noise.assessable else {}
    defects = ({"ppm": 0.0, "recurring": 0} if noise.defects is None else noise.defects) if noise is not None else {}
    cause = noise.cause if noise is not None and noise.assessable and noise.cause else None
    top = top_cause(cause) if cause else None
    md = report.metadata or {}
    values = {
        "level": LEVEL_NAMES[level], "alarm": str(alarm.get("state", "unavailable")),
        "xi_dn": _fmt(alarm.get("xi_dn")), "xi_limit_dn": _fmt(alarm.get("limit_dn")),
        "noise_total_dn": _fmt(nv["total"]), "noise_total_spread_dn": _fmt(spread), "noise_pn_dn": _fmt(nv["pn"]),
        "noise_dcsn_dn": _fmt(nv["dcsn"]), "noise_rn_dn": _fmt(nv["rn"]),
        "noise_row_dn": _fmt(band.get("row_dn")), "noise_col_dn": _fmt(band.get("col_dn")),
        "noise_defect_ppm": _fmt(defects.get("ppm")), "noise_defects_recurring": _fmt(defects.get("recurring")),
        "noise_defects_known": _fmt(defects.get("known")),
        "noise_cause": top or "", "noise_cause_p": _fmt(cause.get(top) if cause else None),
        "blur_mtf_indicator": _fmt(ind[0]), "blur_mtf_indicator_spread": _fmt(ind[1]),
        "blur_mtf_h_fn0.1": _fmt(h01), "blur_mtf_v_fn0.1": _fmt(v01),
        "noise_patches_used": str(_used(noise.counts)) if noise is not None else "0",
        "noise_patches_total": str(int(noise.counts.get("total", 0))) if noise is not None else "0",
        "blur_patches_used": str(_used(mtf.counts)) if mtf is not None else "0",
        "blur_patches_total": str(int(mtf.counts.get("total", 0))) if mtf is not None else "0",
        "gain_db": _fmt(md.get("gain_db")), "exposure_s": _fmt(md.get("exposure_s")),
        "temperature_c": _fmt(md.get("temperature_c")), "frame": str(report.frame),
        "index": "nan" if report.index is None else str(report.index), "source_id": str(report.source_id or ""),
        "processing_ms": _fmt(report.timing_ms.get("total"), ".1f"),
    }
    return [(k, values[k]) for k in KEYS]


def check_diagnostics_path(path: str | Path) -> Path:
    """``path`` as the file a :class:`DiagnosticsWriter` can write: ending in ``.mcap`` or ``.bag``, not a folder, in a
    folder that exists. Raises ``ValueError`` (``FileNotFoundError`` for a missing folder) naming the path, before
    anything is written (``python -m camhealth.monitor`` checks ``--diagnostics-out`` so before the run)."""
    path = Path(path)
    if path.suffix.lower() not in DIAGNOSTICS_SUFFIXES:
        raise ValueError(f"diagnostics file {path} must end in .mcap (ROS 2) or .bag (ROS 1), got {path.suffix!r}")
    if path.is_dir():
        raise ValueError(f"diagnostics file {path} is a folder; give a file name ending in .mcap or .bag")
    if not path.parent.exists():
        raise FileNotFoundError(f"folder of the diagnostics file does not exist: {path.parent}")
    if not path.parent.is_dir():
        raise ValueError(f"cannot write diagnostics file {path}: {path.parent} is a file, not a folder")
    return path


class DiagnosticsWriter:
    """Writes one ``DiagnosticArray`` per frame to ``path`` (``.mcap``: MCAP with ROS 2 CDR messages;
    ``.bag``: ROS 1 bag). ``hardware_id`` of every status: the one given, else the image's ``frame_id``, else
    ``topic``. The file appears when :meth:`close` is called (written beside it first, then
    moved into place, replacing an older one). ``counts`` holds the number of statuses per level name."""

    def __init__(self, path: str | Path, status_name: str, hardware_id: str = "", xi_threshold_dn: float = 1.0,
                 topic: str = "") -> None:
        self.path = check_diagnostics_path(path)
        suffix = self.path.suffix.lower()
        from rosbags.typesys import Stores, get_typestore

        self.ros1 = suffix == ".bag"
        self.status_name, self.hardware_id = status_name, hardware_id
        self.xi_threshold_dn = _check_xi_threshold(xi_threshold_dn)
        self.topic = topic  # hardware_id when neither hardware_id nor the image's frame_id is set
        self.typestore = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.LATEST)
        self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent))
        self.counts = {name: 0 for name in ("OK", "WARN", "ERROR")}
        self._seq = 0
        try:
            if self.ros1:
                from rosbags.rosbag1 import Writer

                self._file = self._tmp / self.path.name
                self._writer = Writer(self._file)
                self._writer.open()
                self._conn = self._writer.add_connection(DIAGNOSTICS_TOPIC, _MSGTYPE, typestore=self.typestore)
            else:
                from rosbags.rosbag2 import StoragePlugin, Writer

                folder = self._tmp / "bag"
                self._file = folder / "bag.mcap"
                self._writer = Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP)
                self._writer.open()
                self._conn = self._writer.add_connection(DIAGNOSTICS_TOPIC, _MSGTYPE, typestore=self.typestore)
        except Exception:
            shutil.rmtree(self._tmp, ignore_errors=True)
            raise
        self._last_log = 0

    def check_times(self, stamp_ns: int, log_time_ns: int) -> None:
        """``ValueError`` naming the value and the allowed range unless the header stamp and the log time fit the
        file's time fields (checked before anything is written, so the file stays readable)."""
        lo, hi = _STAMP_SECONDS_ROS1 if self.ros1 else _STAMP_SECONDS_ROS2
        sec = int(stamp_ns) // 1_000_000_000
        fmt = "ROS 1 .bag" if self.ros1 else "ROS 2 .mcap"
        if not lo <= sec <= hi:
            kind = "uint32 seconds, written as int32" if self.ros1 else "int32 seconds"
            raise ValueError(f"stamp_ns = {int(stamp_ns)} ({sec} s) is out of the range of a {fmt} header stamp: "
                             f"[{lo}, {hi}] s ({kind})")
        log_hi = _LOG_NS_MAX_ROS1 if self.ros1 else _LOG_NS_MAX_ROS2
        if int(log_time_ns) > log_hi:
            raise ValueError(f"log_time_ns = {int(log_time_ns)} is out of the range of a {fmt} log time: "
                             f"[0, {log_hi}] ns")

    def _message(self, stamp_ns: int, frame_id: str, level: int, message: str, values: list[tuple[str, str]]) -> Any:
        t = self.typestore.types
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        extra = {"seq": self._seq} if self.ros1 else {}
        header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id, **extra)
        kvs = [t["diagnostic_msgs/msg/KeyValue"](key=k, value=v) for k, v in values]
        status = t["diagnostic_msgs/msg/DiagnosticStatus"](level=level, name=self.status_name, message=message,
                                                         hardware_id=self.hardware_id or frame_id or self.topic, values=kvs)
        return t[_MSGTYPE](header=header, status=[status])

    def _write(self, msg: Any, log_time_ns: int) -> None:
        log = max(int(log_time_ns), self._last_log)  # keep the log times of the file non-decreasing
        self._last_log = log
        data = (self.typestore.serialize_ros1(msg, _MSGTYPE) if self.ros1 else self.typestore.serialize_cdr(msg, _MSGTYPE))
        self._writer.write(self._conn, log, data)
        self._seq += 1

    def write_report(self, report: FrameReport, stamp_ns: int | None, log_time_ns: int, frame_id: str = "") -> int:
        """One frame's status; returns its level."""
        stamp = log_time_ns if stamp_ns is None else stamp_ns
        self.check_times(stamp, log_time_ns)
        level, message = frame_level(report, self.xi_threshold_dn)
        msg = self._message(stamp, frame_id, level, message, key_values(report, level))
        self._write(msg, log_time_ns)
        self.counts[LEVEL_NAMES[level]] += 1
        return level

    def write_error(self, error: str, index: int, source_id: str, stamp_ns: int | None, log_time_ns: int,
                    frame_id: str = "") -> int:
        """ERROR status of a frame that could not be decoded (stamped with its log time if its header is unknown)."""
        values = [(k, "nan") for k in KEYS]
        fill = {"level": "ERROR", "alarm": "not_assessable", "noise_patches_used": "0", "noise_patches_total": "0",
                "blur_patches_used": "0", "blur_patches_total": "0", "index": str(index), "source_id": source_id,
                "frame": "nan"}
        values = [(k, fill.get(k, v)) for k, v in values]
        stamp = log_time_ns if stamp_ns is None else stamp_ns
        self.check_times(stamp, log_time_ns)
        msg = self._message(stamp, frame_id, ERROR, f"frame not assessable: {error}", values)
        self._write(msg, log_time_ns)
        self.counts["ERROR"] += 1
        return ERROR

    def close(self) -> None:
        """Finish the file and move it to :attr:`path`."""
        if self._writer is None:
            return
        writer, self._writer = self._writer, None
        try:
            writer.close()
            os.replace(self._file, self.path)
        finally:
            shutil.rmtree(self._tmp, ignore_errors=True)

    def abort(self) -> None:
        """Give up: the file is not written (an older one at :attr:`path` stays as it was)."""
        if self._writer is None:
            return
        writer, self._writer = self._writer, None
        try:
            writer.close()
        except Exception:  # noqa: BLE001 - what it had written is discarded anyway
            pass
        finally:
            shutil.rmtree(self._tmp, ignore_errors=True)

    def summary(self) -> dict[str, Any]:
        return {"path": str(self.path), "topic": DIAGNOSTICS_TOPIC, "messages": sum(self.counts.values()),
                "levels": dict(self.counts)}


def read_diagnostics(path: str | Path) -> list[dict[str, Any]]:
    """Every ``DiagnosticStatus`` on ``/diagnostics`` of a recording: dicts with ``stamp_ns``, ``log_time_ns``,
    ``frame_id``, ``level``, ``level_name``, ``name``, ``message``, ``hardware_id`` and ``values`` (key → str)."""
    from camhealth.data.rosbag import Recording, stamp_to_ns

    out = []
    with Recording(path) as rec:
        for log_ns, msg in rec.read(DIAGNOSTICS_TOPIC):
            for st in msg.status:
                level = int(st.level)
                out.append({
                    "stamp_ns": stamp_to_ns(msg.header.stamp), "log_time_ns": log_ns, "frame_id": msg.header.frame_id,
                    "level": level, "level_name": LEVEL_NAMES.get(level, str(level)), "name": st.name,
                    "message": st.message, "hardware_id": st.hardware_id, "values": {kv.key: kv.value for kv in st.values},
                })
    return out
