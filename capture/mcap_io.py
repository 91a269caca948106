"""Depth frames to and from MCAP (docs/DESIGN.md section 5): record any Source, replay a recording as a Source.

Layout of a recording, per sensor ``<id>`` (all messages of one frame share log_time = its timestamp_ns):

- ``/camera/<id>/depth``        ROS 2 sensor_msgs/msg/Image "16UC1" (CDR), the raw little-endian uint16
                                depth units
- ``/camera/<id>/color``        foxglove.RawImage "rgb8", when the frame has colour
- ``/camera/<id>/calibration``  foxglove.CameraCalibration (K, P, plumb_bob with zero D)
- ``/tf``                       foxglove.FrameTransforms world -> camera/<id>, when the pose is known
- ``/camera/<id>/meta``         JSON ``{"timestamp_ns", "depth_scale", "turntable_angle", "T_world_camera",
                                "has_color"}``

Depth is a ROS 2 Image, not a foxglove.RawImage, because viewers show that schema's 16UC1 as depth:
Rerun's MCAP import makes it a DepthImage (a foxglove.RawImage becomes a grey image), and Foxglove reads
ROS 2 messages natively. Recordings whose depth is a foxglove.RawImage are read as well.
The foxglove schemas have no field for a depth scale or a turntable angle, and a pose stored as a
quaternion does not come back bit-exact, so the meta channel carries what replay needs exactly
(JSON floats round-trip exactly); /tf is there for viewers. The meta message also says whether a
colour image belongs to the frame, so the reader knows when a frame is complete.
"""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import struct
import sys
import threading
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import foxglove
import numpy as np
from foxglove.channels import (CameraCalibrationChannel, FrameTransformsChannel, PointCloudChannel,
                               RawImageChannel, SceneUpdateChannel)
from foxglove.mcap import MCAPCompression, MCAPWriteOptions
from foxglove.messages import (CameraCalibration, FrameTransform, FrameTransforms, PackedElementField,
                               PackedElementFieldNumericType, PointCloud, Pose, Quaternion, RawImage,
                               SceneUpdate, Timestamp, Vector3)
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap_protobuf.decoder import DecoderFactory
from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory

from capture.frames import CameraIntrinsics, DepthFrame
from capture.source import Source, SourceError
from common.files import atomic_path

MCAP_MAGIC = b"\x89MCAP0\r\n"
ROS2_IMAGE_SCHEMA = foxglove.Schema(name="sensor_msgs/msg/Image", encoding="ros2msg", data=b"""\
std_msgs/Header header
uint32 height
uint32 width
string encoding
uint8 is_bigendian
uint32 step
uint8[] data
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
""")
_CDR_LITTLE_ENDIAN = b"\x00\x01\x00\x00"
_CAMERA_TOPIC = re.compile(r"^/camera/(?P<sensor>.+)/(?P<kind>depth|color|calibration|meta)$")
_COMPRESSION = {"zstd": MCAPCompression.Zstd, "lz4": MCAPCompression.Lz4, "none": None, None: None}
_META_SCHEMA = {
    "title": "mushroom_pose.DepthFrameMeta",
    "type": "object",
    "properties": {
        "timestamp_ns": {"type": "integer"},
        "depth_scale": {"type": "number", "description": "metres per depth unit"},
        "turntable_angle": {"type": ["number", "null"], "description": "radians"},
        "T_world_camera": {"type": ["array", "null"], "items": {"type": "number"},
                           "description": "row-major 4x4, exact"},
        "has_color": {"type": "boolean"},
    },
    "required": ["timestamp_ns", "depth_scale", "turntable_angle", "T_world_camera", "has_color"],
}


class TruncatedRecordingWarning(UserWarning):
    """A recording without its MCAP footer (the recorder was killed): replayed up to its last whole chunk."""


def _timestamp(ns: int) -> Timestamp:
    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def ros2_image(timestamp_ns: int, frame_id: str, pixels: np.ndarray, encoding: str) -> bytes:
    """One sensor_msgs/msg/Image (``ROS2_IMAGE_SCHEMA``) in little-endian CDR: each field aligned to
    its size from the end of the 4-byte encapsulation header, strings as a uint32 length (with the
    terminating NUL) and the bytes, ``data`` as a uint32 length and the rows. One fixed layout, so it
    is written here; mcap-ros2-support's decoder reads it back (tested)."""
    pixels = np.ascontiguousarray(pixels)
    body = bytearray()

    def uint32(value: int) -> None:
        body.extend(b"\0" * (-len(body) % 4))
        body.extend(struct.pack("<I", value))

    def text(value: str) -> None:
        data = value.encode() + b"\0"
        uint32(len(data))
        body.extend(data)

    seconds, nanoseconds = divmod(int(timestamp_ns), 10**9)
    body.extend(struct.pack("<iI", seconds, nanoseconds))
    text(frame_id)
    uint32(pixels.shape[0])
    uint32(pixels.shape[1])
    text(encoding)
    body.append(0)  # is_bigendian
    uint32(pixels.strides[0])
    uint32(pixels.nbytes)
    return _CDR_LITTLE_ENDIAN + bytes(body) + pixels.tobytes()


def message_decoder(schema: Schema | None, channel: Channel) -> Callable[[bytes], Any] | None:
    """The decoder of a channel's messages: foxglove protobuf or ROS 2 CDR; None for other encodings."""
    for factory in (DecoderFactory(), Ros2DecoderFactory()):
        decoder = factory.decoder_for(channel.message_encoding, schema)
        if decoder is not None:
            return decoder
    return None


def _jsonable(value: Any) -> Any:
    if isinstance(value, (np.ndarray, np.generic)):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


@contextmanager
def _signals_deferred() -> Iterator[None]:
    """Hold SIGINT/SIGTERM until the block ends (then deliver them), so finalising cannot be cut short."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    previous = {sig: signal.signal(sig, lambda signum, _frame: caught.append(signum))
                for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
        for sig in caught:
            signal.raise_signal(sig)


@dataclass
class StopRequest:
    """Set by ``graceful_stop`` when a stop signal arrived; recording loops check ``requested``."""

    requested: bool = False
    signal: str | None = None


@contextmanager
def graceful_stop(signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[StopRequest]:
    """The first SIGINT/SIGTERM sets ``stop.requested`` so the loop ends after the current frame;
    a second one raises KeyboardInterrupt (for a source stuck in a blocking read). Signals the process
    ignores stay ignored; outside the main thread nothing is installed. Previous handlers come back
    on exit."""
    stop = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handle(signum: int, _frame: Any) -> None:
        if stop.requested:
            raise KeyboardInterrupt
        stop.requested, stop.signal = True, signal.Signals(signum).name

    previous = {sig: signal.signal(sig, handle) for sig in signals if signal.getsignal(sig) is not signal.SIG_IGN}
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)


class RecordingError(OSError):
    """A recording that cannot go on: its disk is (nearly) full, or a write to it failed."""


class _WriteFailures(logging.Handler):
    """foxglove-sdk reports a failed MCAP write only as a log record (on the ``foxglove`` logger), never
    as an exception: this keeps the first such report for the recorder, and keeps the hundreds that
    follow off the terminal."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.first: str | None = None

    def emit(self, record: logging.LogRecord) -> None:
        if self.first is None and "McapError" in record.getMessage():
            self.first = record.getMessage()


class SessionChannels:
    """The session's topics as foxglove-sdk channels of one Context: every message goes to whatever the
    context feeds (the session MCAP, a live WebSocket server, or both), as it is written."""

    def __init__(self, context: foxglove.Context | None = None) -> None:
        self.frames = 0
        self._messages = 0  # whole frames, documents and clouds
        self._context = context if context is not None else foxglove.Context()
        self._channels: dict[str, Any] = {}
        self._last_timestamp: dict[str, int] = {}
        self._closed = False

    def _channel(self, topic: str, kind: type, **kwargs: Any) -> Any:
        channel = self._channels.get(topic)
        if channel is None:
            if self._closed:
                raise ValueError("the session's channels are closed")
            channel = self._channels[topic] = kind(topic, context=self._context, **kwargs)
        elif not isinstance(channel, kind):
            raise ValueError(f"{topic} already carries {type(channel).__name__} messages")
        return channel

    def write(self, frame: DepthFrame) -> None:
        """Log one frame on its sensor's topics at log_time = ``frame.timestamp_ns``."""
        sensor, t = frame.sensor_id, int(frame.timestamp_ns)
        if t < 0:
            raise ValueError(f"timestamp_ns must be >= 0 for MCAP, got {t}")
        if self._last_timestamp.get(sensor, -1) >= t:
            raise ValueError(f"sensor {sensor!r}: timestamp {t} ns does not follow {self._last_timestamp[sensor]} ns")
        if frame.color is not None and (frame.color.dtype != np.uint8 or frame.color.ndim != 3
                                        or frame.color.shape[2] != 3):
            raise ValueError(f"colour must be HxWx3 uint8 (rgb8), got {frame.color.dtype} {frame.color.shape}")
        k, stamp, frame_id = frame.intrinsics, _timestamp(t), f"camera/{sensor}"
        prefix = f"/camera/{sensor}"
        self._channel(f"{prefix}/depth", foxglove.Channel, message_encoding="cdr", schema=ROS2_IMAGE_SCHEMA).log(
            ros2_image(t, frame_id, np.asarray(frame.depth, "<u2"), "16UC1"), log_time=t)
        if frame.color is not None:
            self._channel(f"{prefix}/color", RawImageChannel).log(RawImage(
                timestamp=stamp, frame_id=frame_id, width=k.width, height=k.height, encoding="rgb8",
                step=k.width * 3, data=np.ascontiguousarray(frame.color).tobytes()), log_time=t)
        self._channel(f"{prefix}/calibration", CameraCalibrationChannel).log(CameraCalibration(
            timestamp=stamp, frame_id=frame_id, width=k.width, height=k.height, distortion_model="plumb_bob",
            D=[0.0] * 5, K=[float(v) for v in k.matrix.ravel()], R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            P=[float(k.fx), 0.0, float(k.cx), 0.0, 0.0, float(k.fy), float(k.cy), 0.0, 0.0, 0.0, 1.0, 0.0]),
            log_time=t)
        pose = None if frame.T_world_camera is None else np.asarray(frame.T_world_camera, np.float64)
        if pose is not None:
            if not np.isfinite(pose).all():
                raise ValueError(f"sensor {sensor!r}: the camera pose at {t} ns is not finite")
            self._log_transform("world", frame_id, pose, t)
        meta = {"timestamp_ns": t, "depth_scale": float(frame.depth_scale),
                "turntable_angle": None if frame.turntable_angle is None else float(frame.turntable_angle),
                "T_world_camera": None if pose is None else pose.ravel().tolist(),
                "has_color": frame.color is not None}
        self._channel(f"{prefix}/meta", foxglove.Channel, schema=_META_SCHEMA).log(
            json.dumps(meta).encode(), log_time=t)
        self._last_timestamp[sensor] = t
        self.frames += 1
        self._messages += 1
        self._written(frame.depth.nbytes + (0 if frame.color is None else frame.color.nbytes))

    def write_json(self, topic: str, obj: Any, log_time_ns: int, *, schema: dict | None = None) -> None:
        """Log ``obj`` (numpy values allowed) on a JSON channel; ``schema`` is a JSON schema of an object."""
        channel = self._channel(topic, foxglove.Channel, schema=schema or {"type": "object"})
        data = json.dumps(obj, default=_jsonable).encode()
        channel.log(data, log_time=int(log_time_ns))
        self._messages += 1
        self._written(len(data))

    def write_point_cloud(self, topic: str, points: np.ndarray, log_time_ns: int, frame_id: str = "world",
                          colors: np.ndarray | None = None) -> None:
        """Log points (N, 3) in metres as a foxglove.PointCloud with float32 fields x, y, z and, with
        ``colors`` (N, 3) uint8, uint8 fields red, green, blue, alpha that viewers colour it by."""
        points = np.asarray(points)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must be (N, 3), got {points.shape}")
        f32, u8 = PackedElementFieldNumericType.Float32, PackedElementFieldNumericType.Uint8
        fields = [PackedElementField(name=name, offset=4 * i, type=f32) for i, name in enumerate("xyz")]
        if colors is None:
            data, stride = np.ascontiguousarray(points, "<f4").tobytes(), 12
        else:
            colors = np.asarray(colors, np.uint8)
            if colors.shape != points.shape:
                raise ValueError(f"colors must be (N, 3) like the points, got {colors.shape}")
            record = np.zeros(len(points), [("xyz", "<f4", 3), ("rgba", "u1", 4)])
            record["xyz"], record["rgba"][:, :3], record["rgba"][:, 3] = points, colors, 255
            fields += [PackedElementField(name=name, offset=12 + i, type=u8)
                       for i, name in enumerate(("red", "green", "blue", "alpha"))]
            data, stride = record.tobytes(), 16
        self._channel(topic, PointCloudChannel).log(PointCloud(
            timestamp=_timestamp(int(log_time_ns)), frame_id=frame_id,
            pose=Pose(position=Vector3(), orientation=Quaternion(w=1.0)), point_stride=stride, fields=fields,
            data=data), log_time=int(log_time_ns))
        self._messages += 1
        self._written(len(data))

    def write_transform(self, parent: str, child: str, T_parent_child: np.ndarray, log_time_ns: int,
                        topic: str = "/tf") -> None:
        """Log ``T_parent_child`` on ``topic`` (for viewers; the pose is also kept exact where replay needs
        it). A transform written later than the frames around its log time goes on a topic of its own,
        so that every channel's messages stay in log-time order."""
        self._log_transform(parent, child, T_parent_child, log_time_ns, topic)
        self._messages += 1
        self._written(0)

    def _log_transform(self, parent: str, child: str, T_parent_child: np.ndarray, log_time_ns: int,
                       topic: str = "/tf") -> None:
        from scipy.spatial.transform import Rotation

        T = np.asarray(T_parent_child, np.float64)
        x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
        self._channel(topic, FrameTransformsChannel).log(FrameTransforms(transforms=[FrameTransform(
            timestamp=_timestamp(int(log_time_ns)), parent_frame_id=parent, child_frame_id=child,
            translation=Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]), rotation=Quaternion(x=x, y=y, z=z, w=w))]),
            log_time=int(log_time_ns))

    def write_scene_update(self, topic: str, update: SceneUpdate, log_time_ns: int) -> None:
        """Log a foxglove.SceneUpdate (shapes a viewer draws in 3D)."""
        self._channel(topic, SceneUpdateChannel).log(update, log_time=int(log_time_ns))
        self._messages += 1
        self._written(0)

    def _written(self, message_bytes: int) -> None:
        """After a write: what the sinks of the context need checked (nothing for a server)."""

    def close(self, discard: bool = False) -> None:
        """Close every channel (a server unadvertises them); safe to call twice."""
        if not self._closed:
            self._closed = True
            for channel in self._channels.values():
                channel.close()

SERVER_STOP_WAIT_S = 2.0
"""Seconds a live server's clients get to close when the run ends."""


@contextmanager
def serve_session(host: str, port: int) -> Iterator[tuple[foxglove.Context, int]]:
    """A foxglove-sdk WebSocket server on ``host``:``port`` (0: any free port) for the session's channels,
    as the context to write them on and the port it listens on; stopped on leaving. A client that
    stalls loses its oldest messages, never slows the writer. OSError when the port cannot be bound."""
    context = foxglove.Context()
    try:
        server = foxglove.start_server(name="mushroom-pose", host=host, port=port, context=context)
    except RuntimeError as error:  # foxglove-sdk: FoxgloveError
        reason = str(error).split(": ", 1)[-1]
        raise OSError(f"cannot serve Foxglove on {host}:{port}: {reason}") from None
    try:
        yield context, server.port
    finally:
        # stop() waits for every client to close gracefully, which one that never reads does not do:
        # it gets SERVER_STOP_WAIT_S, and the process does not wait for the rest
        stopping = threading.Thread(target=server.stop, name="foxglove server stop", daemon=True)
        stopping.start()
        stopping.join(SERVER_STOP_WAIT_S)


class McapRecorder(SessionChannels):
    """Writes DepthFrames (and JSON, point clouds) to an MCAP file with foxglove-sdk.

    The file is written as ``<path>.partial`` and renamed to ``path`` by ``close()``, which always
    finalises (summary and footer) first, also when leaving ``with`` on KeyboardInterrupt or any other
    exception, and holds off SIGINT/SIGTERM while doing so. A process killed outright (SIGKILL, power
    loss) leaves only the ``.partial`` file, which ``recover_recording`` turns into a valid MCAP.

    A write raises RecordingError when the disk holding the file has less room than one more chunk
    and the summary need (``room_needed``), so the recording stops while it can still be finalised;
    and when a write failed all the same (another process filled the disk), leaving the ``.partial``
    file for ``recover_recording``.
    """

    def __init__(self, path: str | os.PathLike, compression: str | None = "zstd", *,
                 chunk_size: int = 1 << 20, overwrite: bool = False, context: foxglove.Context | None = None) -> None:
        """``compression``: "zstd", "lz4" or None; ``chunk_size``: uncompressed bytes per chunk, which is
        also about how much a hard kill can lose; ``context``: one a live server publishes as well."""
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be 'zstd', 'lz4' or None, got {compression!r}")
        self.path = Path(path)
        self.partial_path = self.path.with_name(self.path.name + ".partial")
        if self.path.exists() and not overwrite:
            raise FileExistsError(f"{self.path} exists (pass overwrite=True to replace it)")
        if self.partial_path.exists() and not overwrite:
            raise FileExistsError(f"{self.partial_path} exists: an earlier recording was interrupted; recover it "
                                  f"(mushroom-pose recover), move it, or overwrite it")
        self.partial_path.unlink(missing_ok=True)
        super().__init__(context)  # with no whole message yet, an error discards the file
        options = MCAPWriteOptions(compression=_COMPRESSION[compression], chunk_size=chunk_size)
        try:
            self._writer = foxglove.open_mcap(self.partial_path, context=self._context, writer_options=options)
        except OSError as error:
            raise type(error)(f"cannot create {self.partial_path}: {error}") from None
        self._chunk_size = chunk_size
        self._failures = _WriteFailures()
        self._foxglove_log = logging.getLogger("foxglove")
        self._foxglove_log.addHandler(self._failures)
        self._foxglove_log.propagate = False

    def room_needed(self, message_bytes: int) -> int:
        """Free bytes the disk must keep for a message of ``message_bytes``: the chunk being filled may
        be flushed with it, and closing writes the summary (indexes and statistics)."""
        return 2 * self._chunk_size + 2 * message_bytes + (1 << 20)

    def _written(self, message_bytes: int) -> None:
        """After a write: a RecordingError if it failed, or if the disk has no room for the next one."""
        if self._failures.first is not None:
            raise RecordingError(f"writing {self.partial_path} failed ({self._failures.first})")
        stat = os.statvfs(self.partial_path.parent)
        free = stat.f_bavail * stat.f_frsize
        if free < self.room_needed(message_bytes):
            raise RecordingError(f"the disk holding {self.partial_path.parent} is full ({free / 1e6:.1f} MB free, "
                                 f"a recording keeps {self.room_needed(message_bytes) / 1e6:.1f} MB in hand)")

    def __enter__(self) -> "McapRecorder":
        return self

    def __exit__(self, kind: Any, *exc: Any) -> None:
        self.close(discard=kind is not None and not self._messages)

    def close(self, discard: bool = False) -> None:
        """Finalise the MCAP and move it to its final name; safe to call twice. If a write or finalising
        failed (disk full), the ``.partial`` file stays for ``recover_recording`` and a RecordingError
        says so. ``discard`` deletes it instead: ``with`` does so when an error ends a recording before
        its first whole message, so that an earlier file of that name is kept, not replaced by an empty
        one."""
        if self._closed:
            return
        self._closed = True
        try:
            with _signals_deferred():
                for channel in self._channels.values():
                    channel.close()
                try:
                    self._writer.close()
                except RuntimeError as error:  # foxglove-sdk: a write failed before, or this one did
                    if discard:
                        self.partial_path.unlink(missing_ok=True)
                        return
                    raise RecordingError(f"{self.partial_path} could not be finalised ({self._failures.first or error})"
                                         f": free some space, then mushroom-pose recover {self.partial_path}") from None
                if discard:
                    self.partial_path.unlink(missing_ok=True)
                else:
                    os.replace(self.partial_path, self.path)
        finally:
            self._foxglove_log.removeHandler(self._failures)
            # foxglove's records reach the terminal again once no recorder is open
            self._foxglove_log.propagate = not any(isinstance(handler, _WriteFailures)
                                                   for handler in self._foxglove_log.handlers)


@dataclass(frozen=True)
class RecordingSummary:
    """What ``record`` wrote: frames, file size, wall-clock seconds, and why it stopped."""

    frames: int
    bytes: int
    seconds: float
    path: Path | None = None
    stopped_by: str = "end"
    """Why recording stopped: end (source exhausted), duration, or the signal's name (SIGINT, SIGTERM)."""


def record(source: Source, path: str | os.PathLike, duration_s: float | None = None, progress: bool = True, *,
           compression: str | None = "zstd", overwrite: bool = False,
           on_frame: Callable[[int, DepthFrame], None] | None = None) -> RecordingSummary:
    """Pull frames from ``source`` into an MCAP until it ends, ``duration_s`` (wall clock) passes, or
    SIGINT/SIGTERM arrives (see ``graceful_stop``). The file is finalised in every case, also when an
    exception propagates. Stopping before the first frame leaves no file (an empty recording would only
    fail later, in ``calibrate`` or ``replay``) and raises ValueError, or KeyboardInterrupt for a
    signal. ``on_frame(frames_written, frame)`` runs after each frame is written. The caller owns the
    source (opens/closes it). A full disk ends it with a RecordingError that says what was kept."""
    start = time.monotonic()
    with graceful_stop() as stop:
        recorder = McapRecorder(path, compression, overwrite=overwrite)
        try:
            stopped_by = _record_into(recorder, stop, source, start, duration_s, progress, on_frame)
        except RecordingError as error:
            if recorder.path.exists():
                frames = "its first frame is" if recorder.frames == 1 else f"its first {recorder.frames} frames are"
                raise RecordingError(f"{error}; {frames} in {recorder.path}") from None
            raise RecordingError(str(error) if recorder.partial_path.exists() else f"{error}; no frame was kept") \
                from None
    return RecordingSummary(recorder.frames, recorder.path.stat().st_size, time.monotonic() - start,
                            recorder.path, stopped_by)


def _record_into(recorder: McapRecorder, stop: StopRequest, source: Source, start: float, duration_s: float | None,
                 progress: bool, on_frame: Callable[[int, DepthFrame], None] | None) -> str:
    """``record``'s loop; returns why it stopped."""
    from tqdm import tqdm

    stopped_by = "end"
    with recorder, tqdm(desc=f"recording {recorder.path.name}", unit="frame", disable=not progress,
                        file=sys.stderr) as bar:
        while True:
            if stop.requested:
                stopped_by = stop.signal or "signal"
                break
            if duration_s is not None and time.monotonic() - start >= duration_s:
                stopped_by = "duration"
                break
            frame = source.read()
            if frame is None:
                break
            recorder.write(frame)
            bar.update(1)
            if on_frame is not None:
                on_frame(recorder.frames, frame)
        if not recorder.frames:
            if stopped_by == "duration":
                raise ValueError(f"no frame arrived within {duration_s:g} s")
            if stopped_by == "end":
                raise ValueError("the source ended before its first frame")
            raise KeyboardInterrupt
    return stopped_by


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
        topics = [c.topic for c in summary.channels.values() if _CAMERA_TOPIC.match(c.topic)]
        self.sensor_ids = sorted({_CAMERA_TOPIC.match(t)["sensor"] for t in topics if t.endswith("/depth")})
        if not self.sensor_ids:
            raise SourceError(f"{self.path} has no depth topics (/camera/<id>/depth)")
        missing = [s for s in self.sensor_ids if f"/camera/{s}/meta" not in topics]
        if missing:
            raise SourceError(f"{self.path} has /camera/{missing[0]}/depth but no /camera/{missing[0]}/meta "
                              f"(depth_scale, pose): not written by McapRecorder")
        file.seek(0)
        return self._assemble(SeekingReader(file).iter_messages(topics, log_time_order=True))

    def _stream(self, file: Any) -> Iterator[tuple[Schema | None, Channel, Message]]:
        """Messages in file order, stopping quietly where the file is cut."""
        file.seek(0)
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        size = os.fstat(file.fileno()).st_size
        records = StreamReader(_ExactReads(file), record_size_limit=size).records
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except (McapError, EOFError, ValueError):
                if not self.truncated:
                    raise
                return
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
                match = _CAMERA_TOPIC.match(record.topic)
                if match and match["kind"] == "depth" and match["sensor"] not in self.sensor_ids:
                    self.sensor_ids.append(match["sensor"])
            elif isinstance(record, Message) and record.channel_id in channels:
                channel = channels[record.channel_id]
                if _CAMERA_TOPIC.match(channel.topic):
                    yield schemas.get(channel.schema_id), channel, record

    def _assemble(self, messages: Iterator[tuple[Schema | None, Channel, Message]]) -> Iterator[DepthFrame]:
        """Group each frame's messages (same sensor, same log_time) and yield it once complete."""
        decoders: dict[int, Callable[[bytes], Any]] = {}
        pending: dict[tuple[str, int], dict[str, Any]] = {}
        for schema, channel, message in messages:
            match = _CAMERA_TOPIC.match(channel.topic)
            sensor, kind = match["sensor"], match["kind"]
            if kind == "meta":
                value = json.loads(message.data)
            else:
                if channel.id not in decoders:
                    decoder = message_decoder(schema, channel)
                    if decoder is None:
                        raise SourceError(f"{self.path}: {channel.topic} is {channel.message_encoding}, "
                                          f"neither foxglove protobuf nor ROS 2 CDR")
                    decoders[channel.id] = decoder
                value = decoders[channel.id](message.data)
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


FUSED_CLOUD_TOPIC = "/fusion/cloud"
DETECTIONS_TOPIC = "/perception/mushrooms_json"
CAPS_TOPIC = "/perception/mushrooms"
CAP_OUTLINES_TOPIC = "/perception/cap_outlines"
"""The caps as wire domes in a point cloud, for viewers that draw no SceneUpdate."""
PLAN_TOPIC = "/perception/plan"
"""The pick plan as a SceneUpdate: one approach arrow per cap, its place in the order as text."""
PLAN_JSON_TOPIC = "/perception/plan_json"
"""The pick plan as the detection document's ``"plan"``, with the unit's index: what a controller reads."""
UNIT_TOPIC = "/fusion/unit"
"""JSON per fused cloud: its frames and its exact T_world_bed, so replay can start from fusion's output."""
BED_TRANSFORM_TOPIC = "/fusion/tf"
"""world -> bed of each fused cloud, for viewers: written when the unit is fused, after later frames'
/tf messages, so on a topic of its own."""


def _decoded(path: Path, topics: list[str]) -> Iterator[tuple[str, int, Any]]:
    """(topic, log_time, decoded message) on ``topics`` in log-time order; JSON channels come back as
    dicts. Raises SourceError with a one-line reason when the file is not a readable MCAP."""
    from mcap.reader import make_reader

    if not path.is_file():
        raise SourceError(f"{path} does not exist")
    try:
        with open(path, "rb") as file:
            reader = make_reader(file)
            decoders = {}
            for schema, channel, message in reader.iter_messages(topics=topics, log_time_order=True):
                if channel.message_encoding == "json":
                    yield channel.topic, message.log_time, json.loads(message.data)
                    continue
                if channel.id not in decoders:
                    decoders[channel.id] = message_decoder(schema, channel)
                    if decoders[channel.id] is None:
                        raise SourceError(f"{path}: {channel.topic} is {channel.message_encoding}, "
                                          f"neither foxglove protobuf nor ROS 2 CDR")
                yield channel.topic, message.log_time, decoders[channel.id](message.data)
    except (McapError, ValueError, EOFError, OSError, json.JSONDecodeError) as error:
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


@dataclass(frozen=True)
class Recovery:
    """What ``recover_recording`` kept of a cut recording."""

    path: Path
    messages: int
    depth_images: int
    """Depth images among the messages (one per frame and sensor; the last may lack its other parts)."""


def recover_recording(partial: str | os.PathLike, out: str | os.PathLike | None = None,
                      overwrite: bool = False) -> Recovery:
    """A valid MCAP (footer, summary, index) from a recording whose process died before closing it
    (``<name>.mcap.partial``): every schema, channel and message of every whole record, in file order,
    written to ``out`` (default: the name without ``.partial``). A chunk the crash cut is lost whole
    (its messages cannot be read). Raises ValueError on a file that is not an MCAP or holds no
    message, FileExistsError when ``out`` exists and ``overwrite`` is not set."""
    from mcap.writer import CompressionType, Writer

    partial = Path(partial)
    out = Path(out) if out is not None else partial.with_name(partial.name.removesuffix(".partial"))
    if out == partial:
        raise ValueError(f"{partial} does not end in .partial: give the recovered file's name")
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists")
    with open(partial, "rb") as file:
        if file.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise ValueError(f"{partial} is not an MCAP recording")
        file.seek(0)
        size = os.fstat(file.fileno()).st_size
        messages = frames = 0
        channels: dict[int, tuple[int, Channel]] = {}
        schemas: dict[int, int] = {0: 0}
        # keep_suffix: the default temporary name, X.mcap.partial, is the input's own
        with atomic_path(out, keep_suffix=True) as scratch, open(scratch, "wb") as target:
            writer = Writer(target, compression=CompressionType.ZSTD)
            writer.start(profile="", library="mushroom-pose recover")
            for record in _whole_records(file, size):
                if isinstance(record, Schema) and record.id not in schemas:
                    schemas[record.id] = writer.register_schema(record.name, record.encoding, record.data)
                elif isinstance(record, Channel) and record.id not in channels and record.schema_id in schemas:
                    channels[record.id] = (writer.register_channel(record.topic, record.message_encoding,
                                                                   schemas[record.schema_id], record.metadata),
                                           record)
                elif isinstance(record, Message) and record.channel_id in channels:
                    channel_id, channel = channels[record.channel_id]
                    writer.add_message(channel_id, record.log_time, record.data, record.publish_time,
                                       record.sequence)
                    messages += 1
                    frames += channel.topic.endswith("/depth")
            writer.finish()
            if messages == 0:
                raise ValueError(f"{partial} holds no whole message to recover")
    return Recovery(out, messages, frames)


def _whole_records(file: Any, size: int) -> Iterator[Any]:
    """The file's records (chunks opened) up to the first one the file cuts."""
    records = StreamReader(_ExactReads(file), record_size_limit=size).records
    while True:
        try:
            yield next(records)
        except StopIteration:
            return
        except (McapError, EOFError, ValueError):
            return
