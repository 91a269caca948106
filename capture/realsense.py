"""Intel RealSense cameras through librealsense's ``rs.pipeline``, live or from a recorded device file.

A live camera and a recorded ``.db3`` (rosbag2, what pyrealsense2 2.59 records) go through the same
pipeline code, so tests that play back a file made from virtual-camera frames exercise the real driver
path (docs/DESIGN.md section 6). ``write_device_recording`` makes such a file with a software device.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import pyrealsense2 as rs

from capture.frames import CameraIntrinsics, DepthFrame
from capture.source import CameraInfo, Source, SourceError


@dataclass(frozen=True)
class RealSenseConfig:
    """One RealSense camera (by serial, or the first found), or a recorded device file."""

    serial: str | None = None
    width: int = 848
    height: int = 480
    fps: int = 30
    color: bool = True
    align_to_color: bool = True
    """Reproject depth onto the colour camera's pixel grid (``rs.align``), so colour and depth share intrinsics."""
    playback: str | Path | None = None
    """A recorded ``.db3``: played once, as fast as it is read, with the streams it holds (size and fps ignored)."""
    timeout_s: float = 5.0
    """No frame for this long means the camera is gone (or the file is unreadable)."""


_RGB_CHANNELS = {rs.format.rgb8: [0, 1, 2], rs.format.bgr8: [2, 1, 0],
                 rs.format.rgba8: [0, 1, 2], rs.format.bgra8: [2, 1, 0]}


def _float32_decimal(value: float) -> float:
    """The shortest decimal that librealsense's float32 holds: 1e-4 depth units come back as 1e-4."""
    return float(str(np.float32(value)))


def _to_intrinsics(intrinsics: rs.intrinsics) -> CameraIntrinsics:
    return CameraIntrinsics(intrinsics.width, intrinsics.height, float(intrinsics.fx), float(intrinsics.fy),
                            float(intrinsics.ppx), float(intrinsics.ppy))


def _to_rs_intrinsics(intrinsics: CameraIntrinsics) -> rs.intrinsics:
    result = rs.intrinsics()
    result.width, result.height = intrinsics.width, intrinsics.height
    result.fx, result.fy, result.ppx, result.ppy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    result.model = rs.distortion.none
    result.coeffs = [0.0] * 5
    return result


def _same_pixel_grid(depth: rs.video_stream_profile, color: rs.video_stream_profile) -> bool:
    """True when colour already sits on the depth pixels, so ``rs.align`` would only smear depth."""
    a, b = depth.get_intrinsics(), color.get_intrinsics()
    extrinsics = depth.get_extrinsics_to(color)
    return ((a.width, a.height, a.fx, a.fy, a.ppx, a.ppy, a.model, list(a.coeffs))
            == (b.width, b.height, b.fx, b.fy, b.ppx, b.ppy, b.model, list(b.coeffs))
            and list(extrinsics.rotation) == [1, 0, 0, 0, 1, 0, 0, 0, 1] and not any(extrinsics.translation))


class RealSenseSource(Source):
    """Depth (+ colour) frames of one RealSense camera or recording; run one source per camera for several."""

    def __init__(self, config: RealSenseConfig = RealSenseConfig()) -> None:
        self.config = config
        self._pipeline: rs.pipeline | None = None
        self._playback: rs.playback | None = None
        self._resume: threading.Thread | None = None
        self._align: rs.align | None = None
        self._color_channels: list[int] | None = None
        self._serial = config.serial or "camera"
        self._depth_scale = 0.0
        self._ended = False

    @property
    def serial(self) -> str:
        return self._serial

    def _describe(self) -> str:
        return f"RealSense recording {self.config.playback}" if self.config.playback else f"RealSense {self._serial}"

    def _stream_config(self) -> rs.config:
        config = rs.config()
        if self.config.playback is not None:
            path = Path(self.config.playback)
            if not path.is_file():
                raise SourceError(f"no RealSense recording at {path}")
            config.enable_device_from_file(str(path), repeat_playback=False)
            if not self.config.color:
                config.enable_stream(rs.stream.depth)
            return config
        if self.config.serial:
            config.enable_device(self.config.serial)
        config.enable_stream(rs.stream.depth, self.config.width, self.config.height, rs.format.z16, self.config.fps)
        if self.config.color:
            config.enable_stream(rs.stream.color, self.config.width, self.config.height, rs.format.rgb8,
                                 self.config.fps)
        return config

    def open(self) -> None:
        if self._pipeline is not None or self._ended:
            return
        config = self._stream_config()
        pipeline = rs.pipeline()
        try:
            # Resolving first hands back the very device the pipeline will start. A playback device is held
            # paused while the pipeline starts its sensors one after the other (frames of a sensor not yet
            # started are dropped), and plays as fast as it is read rather than in recorded time. Resuming
            # waits until frames are in the pipeline's small queue, which only our reads drain: own thread.
            device = config.resolve(rs.pipeline_wrapper(pipeline)).get_device()
            playback = device.as_playback() if device.is_playback() else None
            if playback is not None:
                playback.set_real_time(False)
                playback.pause()
            profile = pipeline.start(config)
            if playback is not None:
                self._resume = threading.Thread(target=playback.resume, daemon=True)
                self._resume.start()
        except RuntimeError as error:
            raise SourceError(f"{self._describe()}: cannot start streaming: {error}") from error
        device = profile.get_device()
        if device.supports(rs.camera_info.serial_number):
            self._serial = device.get_info(rs.camera_info.serial_number)
        self._depth_scale = _float32_decimal(device.first_depth_sensor().get_depth_scale())
        self._playback = device.as_playback() if device.is_playback() else None
        streams = {s.stream_type(): s.as_video_stream_profile() for s in profile.get_streams()}
        depth, color = streams.get(rs.stream.depth), streams.get(rs.stream.color)
        self._pipeline = pipeline
        if depth is None:
            self._stop()
            raise SourceError(f"{self._describe()}: no depth stream")
        self._align, self._color_channels = None, None
        if color is not None and self.config.color:
            if color.format() not in _RGB_CHANNELS:
                self._stop()
                raise SourceError(f"{self._describe()}: colour format {color.format()} is not supported")
            same_grid = _same_pixel_grid(depth, color)
            if self.config.align_to_color and not same_grid:
                self._align = rs.align(rs.stream.color)
            if self._align is not None or same_grid:
                self._color_channels = _RGB_CHANNELS[color.format()]

    def _wait(self) -> rs.composite_frame | None:
        """The next frameset with depth; None once a recording has played out."""
        deadline = time.monotonic() + self.config.timeout_s
        while True:
            try:
                played_out = (self._playback is not None
                              and self._playback.current_status() == rs.playback_status.stopped)
                ok, frames = self._pipeline.try_wait_for_frames(100)
            except RuntimeError as error:
                raise SourceError(f"{self._describe()}: streaming failed: {error}") from error
            if ok and frames.get_depth_frame():
                return frames
            if played_out:
                return None
            if time.monotonic() > deadline:
                raise SourceError(f"{self._describe()}: no frames for {self.config.timeout_s:g} s (unplugged?)")

    def read(self) -> DepthFrame | None:
        if self._ended:
            return None
        self.open()
        frames = self._wait()
        if frames is None:
            self._stop()
            self._ended = True
            return None
        if self._align is not None:
            frames = self._align.process(frames)
        depth = frames.get_depth_frame()
        intrinsics = _to_intrinsics(depth.get_profile().as_video_stream_profile().get_intrinsics())
        color = None
        if self._color_channels is not None and (color_frame := frames.get_color_frame()):
            color = np.asanyarray(color_frame.get_data())[..., self._color_channels].copy()
        return DepthFrame(np.asanyarray(depth.get_data()).copy(), self._depth_scale, intrinsics,
                          int(round(depth.get_timestamp() * 1e6)), self._serial, color)

    def _stop(self) -> None:
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except RuntimeError:
                pass
        if self._resume is not None:
            self._resume.join(timeout=self.config.timeout_s)
        self._pipeline, self._playback, self._align, self._resume = None, None, None, None

    def close(self) -> None:
        self._stop()
        self._ended = False


def find_cameras() -> list[CameraInfo]:
    """Attached RealSense cameras (an empty list when none, or when USB cannot be queried)."""
    try:
        devices = list(rs.context().query_devices())
    except RuntimeError:
        return []
    return [CameraInfo("realsense", d.get_info(rs.camera_info.serial_number), d.get_info(rs.camera_info.name))
            for d in devices]


def write_device_recording(frames: Sequence[DepthFrame], path: str | Path, fps: int | None = None,
                           color_images: Sequence[np.ndarray] | None = None,
                           color_intrinsics: CameraIntrinsics | None = None) -> Path:
    """Record frames as a RealSense device file (``.db3``) that ``RealSenseSource`` plays back.

    A software device is recorded with ``rs.recorder`` while the frames are injected: serial = the frames'
    sensor id, ``depth_units`` = their depth scale, ``actual_fps`` metadata = ``fps`` (default: the frames'
    own rate; librealsense's syncer pairs depth and colour by it). Colour on the depth pixels comes from the
    depth sensor, as on a D405. ``color_images`` with ``color_intrinsics`` instead make a separate RGB
    sensor with its own pixel grid and the same optical centre, as on a D435, so playback runs ``rs.align``.
    librealsense keeps intrinsics and depth units as float32 and timestamps as float milliseconds.
    """
    frames = list(frames)
    if not frames:
        raise ValueError("nothing to record: no frames")
    path = Path(path)
    if path.suffix != ".db3":
        raise ValueError(f"pyrealsense2 records rosbag2 files only: {path} must end in .db3")
    first = frames[0]
    if any((f.intrinsics, f.depth_scale, f.color is None) != (first.intrinsics, first.depth_scale,
                                                               first.color is None) for f in frames):
        raise ValueError("every frame of one recording needs the same intrinsics, depth scale and colour")
    if color_images is not None:
        if color_intrinsics is None or len(color_images) != len(frames):
            raise ValueError("color_images need color_intrinsics and one image per frame")
        colors = [np.asarray(image) for image in color_images]
    else:
        colors = [frame.color for frame in frames] if first.color is not None else None
        color_intrinsics = first.intrinsics
    size = (color_intrinsics.height, color_intrinsics.width, 3)
    if colors is not None and any(c.dtype != np.uint8 or c.shape != size for c in colors):
        raise ValueError(f"colour must be {size[1]}x{size[0]} rgb8 (uint8, 3 channels)")
    if fps is None:
        step = np.median(np.diff([frame.timestamp_ns for frame in frames])) if len(frames) > 1 else 0
        fps = max(1, int(round(1e9 / step))) if step > 0 else 30
    path.parent.mkdir(parents=True, exist_ok=True)
    path.unlink(missing_ok=True)
    _record(frames, colors, color_intrinsics, color_images is not None, path, fps)
    return path


def _add_stream(sensor: rs.software_sensor, kind: rs.stream, uid: int, fmt: rs.format, bpp: int,
                intrinsics: CameraIntrinsics, fps: int) -> rs.stream_profile:
    stream = rs.video_stream()
    stream.type, stream.index, stream.uid, stream.fmt, stream.bpp = kind, 0, uid, fmt, bpp
    stream.width, stream.height, stream.fps = intrinsics.width, intrinsics.height, fps
    stream.intrinsics = _to_rs_intrinsics(intrinsics)
    return sensor.add_video_stream(stream, True)


def _push(sensor: rs.software_sensor, profile: rs.stream_profile, pixels: np.ndarray, index: int,
          timestamp_ns: int, depth_units: float | None = None) -> None:
    frame = rs.software_video_frame()
    frame.pixels = np.ascontiguousarray(pixels)
    frame.bpp = pixels.itemsize * (pixels.shape[2] if pixels.ndim == 3 else 1)
    frame.stride = pixels.shape[1] * frame.bpp
    frame.timestamp = timestamp_ns / 1e6
    frame.domain = rs.timestamp_domain.system_time
    frame.frame_number = index
    frame.profile = profile.as_video_stream_profile()
    if depth_units is not None:
        frame.depth_units = depth_units
    sensor.on_video_frame(frame)


def _record(frames: list[DepthFrame], colors: list[np.ndarray] | None, color_intrinsics: CameraIntrinsics,
            separate_color_sensor: bool, path: Path, fps: int) -> None:
    """Everything librealsense holds lives in this scope, so the file is complete once it returns."""
    device = rs.software_device()
    device.register_info(rs.camera_info.serial_number, frames[0].sensor_id)
    device.register_info(rs.camera_info.name, "mushroom-pose virtual camera")
    depth_sensor = device.add_sensor("Stereo Module")
    depth_sensor.add_read_only_option(rs.option.depth_units, frames[0].depth_scale)
    depth_profile = _add_stream(depth_sensor, rs.stream.depth, 0, rs.format.z16, 2, frames[0].intrinsics, fps)
    streams = {depth_sensor: [depth_profile]}
    if colors is not None:
        color_sensor = device.add_sensor("RGB Camera") if separate_color_sensor else depth_sensor
        color_profile = _add_stream(color_sensor, rs.stream.color, 1, rs.format.rgb8, 3, color_intrinsics, fps)
        identity = rs.extrinsics()
        identity.rotation, identity.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0, 0.0, 0.0]
        depth_profile.register_extrinsics_to(color_profile, identity)
        streams.setdefault(color_sensor, []).append(color_profile)
    recorder = rs.recorder(str(path), device, False)
    for sensor, profiles in streams.items():
        sensor.set_metadata(rs.frame_metadata_value.actual_fps, fps * 1000)
        sensor.open(profiles)
        sensor.start(lambda frame: None)
    for index, frame in enumerate(frames):
        _push(depth_sensor, depth_profile, frame.depth, index, frame.timestamp_ns, frame.depth_scale)
        if colors is not None:
            _push(color_sensor, color_profile, colors[index], index, frame.timestamp_ns)
    for sensor in streams:
        sensor.stop()
        sensor.close()
    recorder.pause()
