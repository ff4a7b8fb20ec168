"""Robot recordings as a monitor source: frames of one image topic plus the camera state recorded beside them.

:class:`RecordingSource` wraps :class:`camhealth.data.rosbag.Recording` (ROS 1 ``.bag``, ROS 2 ``.db3``/
``.mcap`` files and rosbag2 folders; no code from the file is run) with the interface of
:class:`camhealth.monitor.sources.FrameSource`: iteration yields :class:`~camhealth.monitor.sources.SourceFrame`
items whose ``metadata`` holds the camera state of that frame — exposure [s], gain [dB] and temperature [°C]
from the topics named in :class:`RecordingOptions`, converted from their units and checked against the
metadata ranges (thesis Table 4.1). The monitor merges them into its metadata; a change restarts the
temporal aggregation. Fields no topic gives (and every field before its topic's first message) come from the
metadata file or sensor preset.

A frame whose state is out of range, or whose message cannot be decoded, is an item with ``error`` set (the
CLI writes a ``frame_error`` line, counts it and goes on). A ``start`` at or past the topic's message count is a
``ValueError`` when the source is opened, as for the other sources.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from camhealth.data.rosbag import (
    BAYER_MODES,
    Recording,
    RecordingError,
    StateTopic,
    format_stamp,
)
from camhealth.monitor.sources import SourceFrame, _past_end
from camhealth.physics.metadata import METADATA_RANGES, UNITS

__all__ = ["RecordingOptions", "RecordingSource", "EXPOSURE_UNITS", "GAIN_UNITS", "TEMPERATURE_UNITS", "STATE_OPTIONS"]

#: Exposure units of a state topic → seconds per unit.
EXPOSURE_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
#: Gain units of a state topic: dB, or the linear amplitude factor (converted as 20·log10).
GAIN_UNITS = ("db", "factor")
#: Temperature units of a state topic: °C or K.
TEMPERATURE_UNITS = ("c", "k")
#: metadata field → the CLI option that names its topic.
STATE_OPTIONS = {"exposure_s": "--exposure-topic", "gain_db": "--gain-topic", "temperature_c": "--temperature-topic"}
_FIELDS = {"exposure": "exposure_s", "gain": "gain_db", "temperature": "temperature_c"}


@dataclass
class RecordingOptions:
    """What to read from a recording.

    Attributes:
        topic: the image topic (``sensor_msgs/Image`` or ``CompressedImage``); ``None`` is an error that
            lists the recording's image topics.
        exposure_topic, gain_topic, temperature_topic: ``TOPIC`` or ``TOPIC:FIELD.PATH`` of a camera-state
            value (``None``: from the metadata).
        exposure_unit: ``s``, ``ms``, ``us`` or ``ns``; gain_unit: ``db`` or ``factor``; temperature_unit:
            ``c`` or ``k`` — the unit of the matching topic's values: a unit other than the default (``s``, ``db``,
            ``c``) without its topic is refused (ValueError).
        bit_depth: bits that carry data in 16-bit pixels (1…16; ``None`` = 16).
        bayer: ``green`` (half-resolution green samples, raw noise kept) or ``luma`` (demosaic + BT.601).
    """

    topic: str | None = None
    exposure_topic: str | None = None
    gain_topic: str | None = None
    temperature_topic: str | None = None
    exposure_unit: str = "s"
    gain_unit: str = "db"
    temperature_unit: str = "c"
    bit_depth: int | None = None
    bayer: str = "green"

    def __post_init__(self) -> None:
        if self.exposure_unit not in EXPOSURE_UNITS:
            raise ValueError(f"exposure unit {self.exposure_unit!r} must be one of {list(EXPOSURE_UNITS)}")
        if self.gain_unit not in GAIN_UNITS:
            raise ValueError(f"gain unit {self.gain_unit!r} must be one of {list(GAIN_UNITS)}")
        if self.temperature_unit not in TEMPERATURE_UNITS:
            raise ValueError(f"temperature unit {self.temperature_unit!r} must be one of {list(TEMPERATURE_UNITS)}")
        if self.bayer not in BAYER_MODES:
            raise ValueError(f"bayer = {self.bayer!r} must be one of {list(BAYER_MODES)}")
        for name, unit, default, topic in (("exposure", self.exposure_unit, "s", self.exposure_topic),
                                           ("gain", self.gain_unit, "db", self.gain_topic),
                                           ("temperature", self.temperature_unit, "c", self.temperature_topic)):
            if unit != default and not topic:  # a unit of values nobody reads: the user most likely forgot the topic
                raise ValueError(f"--{name}-unit {unit} needs --{name}-topic: it is the unit of that topic's values "
                                 f"(without a topic the {name} comes from the metadata, in {UNITS[_FIELDS[name]]})")

    def state_topics(self) -> list[StateTopic]:
        specs = (("exposure_s", self.exposure_topic), ("gain_db", self.gain_topic), ("temperature_c", self.temperature_topic))
        return [StateTopic.parse(key, spec, STATE_OPTIONS[key]) for key, spec in specs if spec]

    def to_physical(self, key: str, value: float) -> float:
        """A state value in the topic's unit → the metadata field's unit (s, dB, °C)."""
        if key == "exposure_s":
            return value * EXPOSURE_UNITS[self.exposure_unit]
        if key == "gain_db":
            if self.gain_unit == "factor":
                if not value > 0:
                    raise ValueError(f"gain factor {value:g} must be > 0")
                return 20.0 * math.log10(value)
            return value
        return value - 273.15 if self.temperature_unit == "k" else value


class RecordingSource:
    """Frames of one image topic of a recording, with the camera state per frame (``kind = "recording"``)."""

    kind = "recording"

    def __init__(self, path: str | Path, start: int = 0, stride: int = 1, max_frames: int | None = None,
                 options: RecordingOptions | None = None) -> None:
        self.path = Path(path)
        self.options = options or RecordingOptions()
        self.recording = Recording(self.path)
        try:
            topic = self.options.topic
            if not topic:
                raise RecordingError(f"recording {self.path}: choose the camera with --topic; "
                                     f"{self.recording.describe_image_topics()}")
            self.topic = topic
            self.state = [self.recording.read_state(spec) for spec in self.options.state_topics()]
            self.frames = self.recording.frames(topic, self.state, start, stride, max_frames,
                                                self.options.bit_depth, self.options.bayer)
            if start > 0:  # as for images, folders and videos: refused before the run, not after an empty one
                _past_end(start, self.frames.messages, self.path)
        except BaseException:
            self.recording.close()
            raise
        self.state_errors = 0
        self._scalings: dict[str, str] = {}  # encoding → how its frames were scaled (:meth:`scaling`)

    @property
    def length(self) -> int:
        return self.frames.length

    def close(self) -> None:
        self.recording.close()

    def _metadata(self, state: dict[str, float], index: int) -> tuple[dict[str, float] | None, str | None]:
        out: dict[str, float] = {}
        for key, raw in state.items():
            series = next(s for s in self.state if s.spec.key == key)
            where = f"{series.spec.label} {series.spec.describe()}"
            lo, hi = METADATA_RANGES[key]
            try:
                value = self.options.to_physical(key, raw) if math.isfinite(raw) else raw
            except ValueError as exc:
                return None, f"camera state from {where}: {exc}"
            slack = 1e-6 * max(abs(lo), abs(hi))  # float rounding of the range ends, as CameraMetadata.validate
            if not math.isfinite(value):
                return None, (f"camera state {key} = {raw:g} {self._unit_name(key)} from {where} (frame {index}) is not a "
                              f"finite number; allowed: [{lo:g}, {hi:g}] {UNITS[key]}")
            if not lo - slack <= value <= hi + slack:
                unit = UNITS[key]
                shown = f"{raw:g} {self._unit_name(key)}" + (f" = {value:g} {unit}" if self._unit_name(key) != unit else "")
                return None, (f"camera state {key} = {shown} from {where} (frame {index}) is out of the allowed range "
                              f"[{lo:g}, {hi:g}] {unit}; check the topic's unit ({'--' + key.split('_')[0] + '-unit'})")
            out[key] = min(max(value, lo), hi)
        return (out or None), None

    def _unit_name(self, key: str) -> str:
        if key == "exposure_s":
            return self.options.exposure_unit
        if key == "gain_db":
            return "dB" if self.options.gain_unit == "db" else "(factor)"
        return "°C" if self.options.temperature_unit == "c" else "K"

    def scaling(self, encoding: str) -> str:
        """How a frame of ``encoding`` (an ``Image`` encoding or a ``CompressedImage`` format) was scaled to [0, 1] —
        the divisor the reader used (:func:`camhealth.data.rosbag.image_to_gray`): 8-bit data ÷255, 16-bit data
        ÷(2^N − 1), N = ``bit_depth`` (16 unless given); the summary's ``input_scaling`` counts the frames per text."""
        text = self._scalings.get(encoding)
        if text is None:
            from camhealth.data.rosbag import FrameDecodeError, _encoding_info

            bits = 16 if self.options.bit_depth is None else int(self.options.bit_depth)
            wide = f"read as {bits}-bit data (÷{2**bits - 1}{', as given' if self.options.bit_depth else ', the full 16-bit word'})"
            declared = encoding.split(";")[0].strip()
            try:
                sixteen = _encoding_info(declared)[2].itemsize == 2
            except FrameDecodeError:  # a CompressedImage format that names no encoding ("png", "jpeg"): as decoded
                sixteen = None if "png" in encoding.lower() else False
            name = declared or "image"
            text = (f"{name}: 8-bit data (÷255)" if sixteen is False else f"{name} (16-bit) {wide}" if sixteen
                    else f"{name}: 8-bit data ÷255, 16-bit data {wide}")
            self._scalings[encoding] = text
        return text

    def __iter__(self) -> Iterator[SourceFrame]:
        for rf in self.frames:
            source_id = f"{self.topic}@{format_stamp(rf.stamp_ns if rf.stamp_ns is not None else rf.log_time_ns)}"
            item = SourceFrame(rf.index, source_id, rf.frame, rf.error, stamp_ns=rf.stamp_ns, log_time_ns=rf.log_time_ns,
                               frame_id=rf.frame_id, scaling=None if rf.error is not None else self.scaling(rf.encoding))
            if rf.error is None and rf.state:
                item.metadata, err = self._metadata(rf.state, rf.index)
                if err is not None:
                    self.state_errors += 1
                    item.frame, item.error = None, err
            yield item

    def summary(self) -> dict[str, Any]:
        """What was read: format, topic, counts (decoded, undecodable, out of order), state topics, damage, notes."""
        f = self.frames
        out: dict[str, Any] = {
            "format": self.recording.format, "topic": self.topic, "messages": f.messages,
            "decoded": f.decoded, "undecodable": f.undecodable, "state_out_of_range": self.state_errors,
            "out_of_order": f.out_of_order, "first_out_of_order": f.first_out_of_order, "damaged": f.damaged,
            "notes": list(f.notes),
            "state": {
                s.spec.key: {"topic": s.spec.describe(), "type": s.msgtype, "field": s.field, "clock": s.clock,
                             "messages": len(s.times), "unit": self._unit_name(s.spec.key),
                             "frames_before_first": f.missing_state.get(s.spec.key, 0),
                             "out_of_order": s.out_of_order, "dropped": s.dropped}
                for s in self.state
            },
        }
        return out

    def describe(self) -> list[str]:
        """Human-readable lines for the CLI summary."""
        s = self.summary()
        lines = [f"  recording: {self.path} ({s['format']}), topic {s['topic']}: {s['messages']} message(s), "
                 f"{s['decoded']} decoded, {s['undecodable']} undecodable"
                 + (f", {s['state_out_of_range']} with camera state out of range" if s["state_out_of_range"] else "")]
        for key, st in s["state"].items():
            line = (f"  camera state {key}: {st['topic']} ({st['type']}, field {st['field']}, {st['unit']}, "
                    f"{st['messages']} value(s), matched by {'header stamp' if st['clock'] == 'header' else 'log time'})")
            if st["frames_before_first"]:
                line += f"; {st['frames_before_first']} frame(s) before its first value used the metadata's {key}"
            if st["messages"] == 0:
                line += "; the topic has no usable value: the metadata's value is used throughout"
            if st["dropped"]:
                line += f"; {st['dropped']} message(s) undecodable or without a time were skipped"
            lines.append(line)
        if s["out_of_order"]:
            lines.append(f"  warning: {s['out_of_order']} frame(s) with a header stamp earlier than the frame before "
                         f"({s['first_out_of_order']}); each was matched to the camera state by its own stamp and keeps "
                         "it in the diagnostics")
        if s["damaged"]:
            lines.append(f"  warning: {s['damaged']}")
        lines += [f"  note: {n}" for n in s["notes"]]
        return lines
