"""Recording a session to MCAP: its channels on a foxglove-sdk context, the file, and the record loop."""

from __future__ import annotations

import json
import logging
import os
import signal
import sys
import threading
import time
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

from capture.frames import DepthFrame
from capture.mcap.schema import META_SCHEMA, ROS2_IMAGE_SCHEMA, SESSION_TOPIC, ros2_image
from capture.source import Source, StopRequest

_COMPRESSION = {"zstd": MCAPCompression.Zstd, "lz4": MCAPCompression.Lz4, "none": None, None: None}

def _timestamp(ns: int) -> Timestamp:
    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


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

    def __init__(self, context: foxglove.Context | None = None, bed_id: str | None = None) -> None:
        """``bed_id``: the bed the session scans, written with its first frame (``SESSION_TOPIC``)."""
        self.bed_id = bed_id
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
        if self.frames == 0:  # part of the first frame: no whole message until the frame is
            self._channel(SESSION_TOPIC, foxglove.Channel, schema={"type": "object"}).log(
                json.dumps({"bed_id": self.bed_id, "started_ns": t}).encode(), log_time=t)
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
        self._channel(f"{prefix}/meta", foxglove.Channel, schema=META_SCHEMA).log(
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
                 chunk_size: int = 1 << 20, overwrite: bool = False, context: foxglove.Context | None = None,
                 bed_id: str | None = None) -> None:
        """``compression``: "zstd", "lz4" or None; ``chunk_size``: uncompressed bytes per chunk, which is
        also about how much a hard kill can lose; ``context``: one a live server publishes as well;
        ``bed_id``: the bed the session scans."""
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
        super().__init__(context, bed_id)  # with no whole message yet, an error discards the file
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
           on_frame: Callable[[int, DepthFrame], None] | None = None,
           stop: StopRequest | None = None, bed_id: str | None = None) -> RecordingSummary:
    """Pull frames from ``source`` into an MCAP until it ends, ``duration_s`` (wall clock) passes, or
    ``stop`` is requested (``pipeline.signals.graceful_stop`` requests it on SIGINT/SIGTERM). The file
    is finalised in every case, also when an exception propagates. Stopping before the first frame leaves no file (an empty recording would only
    fail later, in ``calibrate`` or ``replay``) and raises ValueError, or KeyboardInterrupt for a
    signal. ``on_frame(frames_written, frame)`` runs after each frame is written. The caller owns the
    source (opens/closes it). A full disk ends it with a RecordingError that says what was kept. ``bed_id``
    names the bed the session scans."""
    start = time.monotonic()
    recorder = McapRecorder(path, compression, overwrite=overwrite, bed_id=bed_id)
    try:
        stopped_by = _record_into(recorder, stop or StopRequest(), source, start, duration_s, progress, on_frame)
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


