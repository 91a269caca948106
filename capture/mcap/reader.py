"""Reading sessions back: depth frames as a Source, bit-exact, and the fused clouds, units and documents."""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader

from capture.frames import CameraIntrinsics, DepthFrame
from capture.mcap.schema import (CAMERA_TOPIC, DETECTIONS_TOPIC, FUSED_CLOUD_TOPIC, MCAP_MAGIC, SESSION_TOPIC,
                                 UNIT_TOPIC, Decoders)
from capture.source import Source, SourceError


class TruncatedRecordingWarning(UserWarning):
    """A recording without its MCAP footer (the recorder was killed): replayed up to its last whole chunk."""


def whole_records(file: Any, size: int, stop_at_cut: bool = True) -> Iterator[Any]:
    """The records of an MCAP file of ``size`` bytes read front to back (chunks opened), up to the first
    one the file cuts (or, without ``stop_at_cut``, raising there)."""
    records = StreamReader(_ExactReads(file), record_size_limit=size).records
    while True:
        try:
            yield next(records)
        except StopIteration:
            return
        except (McapError, EOFError, ValueError):
            if stop_at_cut:
                return
            raise


class _ExactReads:
    """A file whose reads fail instead of coming back short, so a cut record is never half-parsed."""

    def __init__(self, file: Any) -> None:
        self._file = file

    def read(self, size: int) -> bytes:
        data = self._file.read(size)
        if len(data) < size:
            raise EOFError(f"file ends inside a record ({len(data)} of {size} bytes)")
        return data


def _image(message: Any, dtype: str, channels: int) -> np.ndarray:
    """The pixels of a foxglove.RawImage or a ROS 2 Image as an owned array (H, W) or (H, W, channels)."""
    width, height, step = message.width, message.height, message.step
    row_bytes = width * channels * np.dtype(dtype).itemsize
    rows = np.frombuffer(message.data, np.uint8, count=height * step).reshape(height, step)[:, :row_bytes]
    pixels = np.array(rows).view(dtype).astype(np.dtype(dtype).newbyteorder("="), copy=False)
    return pixels.reshape(height, width) if channels == 1 else pixels.reshape(height, width, channels)


class McapSource(Source):
    """Replays the DepthFrames of an McapRecorder file in log-time order, bit-exact, all sensors interleaved.

    A finalised file is read through its index (log-time order across chunks). A file without a
    footer (recorder killed, disk full, power loss) is read front to back in file order, which is
    log-time order for recordings of a time-ordered Source, up to its last whole record, with a
    TruncatedRecordingWarning; frames missing a part at the cut are dropped.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.truncated = False
        self.sensor_ids: list[str] = []
        self._file: Any = None
        self._frames: Iterator[DepthFrame] | None = None

    def open(self) -> None:
        if self._file is not None:
            return
        if not self.path.exists():
            raise SourceError(f"{self.path} does not exist")
        try:
            file = open(self.path, "rb")
        except OSError as error:
            raise SourceError(f"cannot read {self.path}: {error.strerror}") from None
        try:
            self._frames = self._start(file)
        except BaseException:
            file.close()
            raise
        self._file = file

    def _start(self, file: Any) -> Iterator[DepthFrame]:
        head = file.read(len(MCAP_MAGIC))
        if not head:
            raise SourceError(f"{self.path} is empty, not an MCAP file")
        if not MCAP_MAGIC.startswith(head):
            raise SourceError(f"{self.path} is not an MCAP file")
        file.seek(0, os.SEEK_END)
        size = file.tell()
        finalised = False
        if size >= 2 * len(MCAP_MAGIC):
            file.seek(size - len(MCAP_MAGIC))
            if file.read(len(MCAP_MAGIC)) == MCAP_MAGIC:
                try:
                    file.seek(0)
                    summary = SeekingReader(file).get_summary()
                    finalised = True
                except (McapError, EOFError, ValueError):
                    pass
        if not finalised:
            self.truncated = True
            warnings.warn(f"{self.path} has no valid MCAP footer (recording not finalised): replaying it up to "
                          f"its last whole chunk", TruncatedRecordingWarning, stacklevel=3)
            return self._assemble(self._stream(file))
        if summary is None:
            return self._assemble(self._stream(file))
        topics = [c.topic for c in summary.channels.values() if CAMERA_TOPIC.match(c.topic)]
        self.sensor_ids = sorted({CAMERA_TOPIC.match(t)["sensor"] for t in topics if t.endswith("/depth")})
        if not self.sensor_ids:
            raise SourceError(f"{self.path} has no depth topics (/camera/<id>/depth)")
        missing = [s for s in self.sensor_ids if f"/camera/{s}/meta" not in topics]
        if missing:
            raise SourceError(f"{self.path} has /camera/{missing[0]}/depth but no /camera/{missing[0]}/meta "
                              f"(depth_scale, pose): not written by McapRecorder")
        file.seek(0)
        return self._assemble(SeekingReader(file).iter_messages(topics, log_time_order=True))

    def _stream(self, file: Any) -> Iterator[tuple[Schema | None, Channel, Message]]:
        """The camera messages in file order, up to where the file is cut when it is truncated."""
        file.seek(0)
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        for record in whole_records(file, os.fstat(file.fileno()).st_size, stop_at_cut=self.truncated):
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
                match = CAMERA_TOPIC.match(record.topic)
                if match and match["kind"] == "depth" and match["sensor"] not in self.sensor_ids:
                    self.sensor_ids.append(match["sensor"])
            elif isinstance(record, Message) and record.channel_id in channels:
                channel = channels[record.channel_id]
                if CAMERA_TOPIC.match(channel.topic):
                    yield schemas.get(channel.schema_id), channel, record

    def _assemble(self, messages: Iterator[tuple[Schema | None, Channel, Message]]) -> Iterator[DepthFrame]:
        """Group each frame's messages (same sensor, same log_time) and yield it once complete."""
        decode = Decoders(self.path)
        pending: dict[tuple[str, int], dict[str, Any]] = {}
        for schema, channel, message in messages:
            match = CAMERA_TOPIC.match(channel.topic)
            sensor, kind = match["sensor"], match["kind"]
            value = decode(schema, channel, message.data)
            key = (sensor, message.log_time)
            parts = pending.setdefault(key, {})
            parts[kind] = value
            meta = parts.get("meta")
            if meta is not None and {"depth", "calibration"} <= parts.keys() and (
                    "color" in parts or not meta["has_color"]):
                del pending[key]
                yield self._frame(sensor, parts)

    def _frame(self, sensor: str, parts: dict[str, Any]) -> DepthFrame:
        depth, calibration, meta = parts["depth"], parts["calibration"], parts["meta"]
        if depth.encoding not in ("16UC1", "mono16"):
            raise SourceError(f"{self.path}: /camera/{sensor}/depth is {depth.encoding}, expected 16UC1")
        K = calibration.K
        intrinsics = CameraIntrinsics(calibration.width, calibration.height, K[0], K[4], K[2], K[5])
        color = None
        if "color" in parts:
            if parts["color"].encoding != "rgb8":
                raise SourceError(f"{self.path}: /camera/{sensor}/color is {parts['color'].encoding}, expected rgb8")
            color = _image(parts["color"], "u1", 3)
        pose = meta["T_world_camera"]
        return DepthFrame(_image(depth, "<u2", 1), meta["depth_scale"], intrinsics, meta["timestamp_ns"], sensor,
                          color, None if pose is None else np.array(pose, np.float64).reshape(4, 4),
                          meta["turntable_angle"])

    def read(self) -> DepthFrame | None:
        self.open()
        try:
            return next(self._frames)
        except StopIteration:
            self._file.close()
            self._frames = iter(())
            return None
        except (McapError, EOFError, ValueError) as error:
            raise SourceError(f"{self.path} is damaged: {error}") from None

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
        self._file, self._frames = None, None


def _decoded(path: Path, topics: list[str]) -> Iterator[tuple[str, int, Any]]:
    """(topic, log_time, decoded message) on ``topics`` in log-time order; JSON channels come back as
    dicts. Raises SourceError with a one-line reason when the file is not a readable MCAP."""
    from mcap.reader import make_reader

    if not path.is_file():
        raise SourceError(f"{path} does not exist")
    try:
        with open(path, "rb") as file:
            decode = Decoders(path)
            for schema, channel, message in make_reader(file).iter_messages(topics=topics, log_time_order=True):
                yield channel.topic, message.log_time, decode(schema, channel, message.data)
    except (McapError, ValueError, EOFError, OSError) as error:
        raise SourceError(f"{path} is not a readable MCAP file, or is cut short ({type(error).__name__})") from None


def _cloud_points(message: Any, path: Path, topic: str) -> np.ndarray:
    offsets = {f.name: f.offset for f in message.fields}
    if not {"x", "y", "z"} <= set(offsets):
        raise SourceError(f"{path}: the cloud on {topic} has no x, y, z fields")
    raw = np.frombuffer(message.data, np.uint8).reshape(-1, message.point_stride)
    return np.stack([raw[:, offsets[a]:offsets[a] + 4].copy().view("<f4")[:, 0] for a in "xyz"], 1).astype(np.float64)


def read_point_cloud(path: str | os.PathLike, topic: str = FUSED_CLOUD_TOPIC) -> tuple[np.ndarray, str]:
    """The last foxglove.PointCloud on ``topic`` (float32 x, y, z fields) as (N, 3) float64 and its frame id;
    empty clouds (a session's announcement of the topic's frame) do not count.

    Raises SourceError with a one-line reason when the file is not MCAP or holds no such cloud.
    """
    path = Path(path)
    last = None
    for _, _, message in _decoded(path, [topic]):
        if message.data:
            last = message
    if last is None:
        raise SourceError(f"{path} has no point cloud on {topic}")
    return _cloud_points(last, path, topic), last.frame_id


@dataclass(frozen=True)
class RecordedUnit:
    """A fused cloud as a session recorded it: world-frame points, T_world_bed, its frames, its time."""

    points: np.ndarray
    T_world_bed: np.ndarray
    frame_ids: tuple[str, ...]
    log_time_ns: int


def read_fused_units(path: str | os.PathLike) -> list[RecordedUnit]:
    """Every fused cloud of a session with the unit record written beside it, in log-time order."""
    path = Path(path)
    clouds: dict[int, np.ndarray] = {}
    units: dict[int, dict] = {}
    for topic, log_time, message in _decoded(path, [FUSED_CLOUD_TOPIC, UNIT_TOPIC]):
        if topic == FUSED_CLOUD_TOPIC:
            if message.data:  # an empty cloud only announces the topic's frame
                clouds[log_time] = _cloud_points(message, path, topic)
        else:
            units[log_time] = message
    return [RecordedUnit(clouds[t], np.array(units[t]["T_world_bed"], np.float64).reshape(4, 4),
                         tuple(units[t].get("frame_ids", ())), t) for t in sorted(clouds) if t in units]


def read_documents(path: str | os.PathLike, topic: str = DETECTIONS_TOPIC) -> list[tuple[int, dict]]:
    """(log_time, document) of every JSON message on ``topic``, in log-time order."""
    return [(log_time, message) for _, log_time, message in _decoded(Path(path), [topic])]


def read_session_info(path: str | os.PathLike) -> dict | None:
    """The session's ``{"bed_id", "started_ns"}`` (``SESSION_TOPIC``), None for a session that does not say."""
    for _, _, message in _decoded(Path(path), [SESSION_TOPIC]):
        return message
    return None
