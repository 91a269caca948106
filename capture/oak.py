"""Luxonis OAK stereo cameras through depthai 3.x: stereo depth aligned to the colour camera.

The device part (Camera + StereoDepth + Sync nodes) needs hardware. The conversion from depthai's
host-side objects (``ImgFrame``, ``CalibrationHandler``) to ``DepthFrame`` is kept in plain functions so
it is the same code live and in tests without a device (docs/DESIGN.md section 6).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from datetime import timedelta

# depthai warns on import about USB access even when no OAK is wanted; keep its log to errors
os.environ.setdefault("DEPTHAI_LEVEL", "error")
import depthai as dai  # noqa: E402
import numpy as np

from capture.frames import CameraIntrinsics, DepthFrame
from capture.source import CameraInfo, Source, SourceError

DEPTH_SCALE = 0.001
"""StereoDepth reports depth in millimetres."""

COLOR_SOCKET = dai.CameraBoardSocket.CAM_A
LEFT_SOCKET = dai.CameraBoardSocket.CAM_B
RIGHT_SOCKET = dai.CameraBoardSocket.CAM_C


@dataclass(frozen=True)
class OakConfig:
    """One OAK camera (by device id / MxId, or the first found)."""

    mxid: str | None = None
    width: int = 640
    height: int = 400
    fps: float = 30.0
    align_to_color: bool = True
    """Depth on the colour camera's pixels (with colour); otherwise depth from the left camera, without colour."""
    timeout_s: float = 5.0


def intrinsics_from_calibration(calib: dai.CalibrationHandler, socket: dai.CameraBoardSocket, width: int,
                                height: int) -> CameraIntrinsics:
    """Pinhole intrinsics of ``socket`` at ``width`` x ``height``, scaled and cropped by depthai itself.

    Lens distortion is not part of ``CameraIntrinsics``; depthai keeps it in the calibration.
    """
    try:
        K = np.asarray(calib.getCameraIntrinsics(socket, width, height), np.float64)
    except RuntimeError as error:
        raise ValueError(f"the calibration has no intrinsics for {socket}: {error}") from error
    return CameraIntrinsics(width, height, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))


def imgframe_timestamp_ns(img: dai.ImgFrame) -> int:
    """The frame's host-synchronised timestamp (depthai's steady clock) in ns; depthai keeps microseconds."""
    return img.getTimestamp() // timedelta(microseconds=1) * 1000


def rgb_from_imgframe(img: dai.ImgFrame) -> np.ndarray:
    """An (H, W, 3) uint8 RGB image of any colour ImgFrame (RGB/BGR interleaved as is, others via depthai)."""
    kind = img.getType()
    if kind == dai.ImgFrame.Type.RGB888i:
        return np.array(img.getFrame(), np.uint8)
    if kind == dai.ImgFrame.Type.BGR888i:
        return np.ascontiguousarray(img.getFrame()[..., ::-1])
    bgr = img.getCvFrame()
    if bgr.ndim == 2:
        return np.repeat(bgr[..., None], 3, axis=2)
    return np.ascontiguousarray(bgr[..., ::-1])


def depth_frame_from_imgframe(img: dai.ImgFrame, intrinsics: CameraIntrinsics, sensor_id: str,
                              color: np.ndarray | None = None) -> DepthFrame:
    """A StereoDepth ``depth`` message (RAW16, millimetres) as a DepthFrame with depth_scale 0.001."""
    if img.getType() != dai.ImgFrame.Type.RAW16:
        raise ValueError(f"depth must be a RAW16 ImgFrame, got {img.getType()}")
    return DepthFrame(np.array(img.getFrame(), np.uint16), DEPTH_SCALE, intrinsics, imgframe_timestamp_ns(img),
                      sensor_id, color)


class OakSource(Source):
    """Depth (+ colour) frames of one OAK camera; run one source per camera for several."""

    def __init__(self, config: OakConfig = OakConfig()) -> None:
        self.config = config
        self._device: dai.Device | None = None
        self._pipeline: dai.Pipeline | None = None
        self._queue: dai.MessageQueue | None = None
        self._intrinsics: CameraIntrinsics | None = None
        self._serial = config.mxid or "oak"

    def _describe(self) -> str:
        return f"OAK {self._serial}"

    def open(self) -> None:
        if self._pipeline is not None:
            return
        config = self.config
        try:
            device = dai.Device(dai.DeviceInfo(config.mxid)) if config.mxid else dai.Device()
        except RuntimeError as error:
            raise SourceError(f"{self._describe()}: cannot open: {error}") from error
        self._device = device
        self._serial = device.getDeviceId()
        size = (config.width, config.height)
        try:
            pipeline = dai.Pipeline(device)
            left = pipeline.create(dai.node.Camera).build(LEFT_SOCKET, sensorFps=config.fps)
            right = pipeline.create(dai.node.Camera).build(RIGHT_SOCKET, sensorFps=config.fps)
            stereo = pipeline.create(dai.node.StereoDepth)
            stereo.setDefaultProfilePreset(dai.node.StereoDepth.PresetMode.DEFAULT)
            stereo.setLeftRightCheck(True)
            left.requestOutput(size, fps=config.fps).link(stereo.left)
            right.requestOutput(size, fps=config.fps).link(stereo.right)
            sync = pipeline.create(dai.node.Sync)
            sync.setSyncThreshold(timedelta(seconds=0.5 / config.fps))
            depth_socket = COLOR_SOCKET if config.align_to_color else LEFT_SOCKET
            stereo.setDepthAlign(depth_socket)
            if config.align_to_color:
                color = pipeline.create(dai.node.Camera).build(COLOR_SOCKET, sensorFps=config.fps)
                color.requestOutput(size, dai.ImgFrame.Type.RGB888i, fps=config.fps).link(sync.inputs["rgb"])
                stereo.setOutputSize(config.width, config.height)
            stereo.depth.link(sync.inputs["depth"])
            self._queue = sync.out.createOutputQueue(maxSize=4, blocking=False)
            self._intrinsics = intrinsics_from_calibration(device.readCalibration(), depth_socket, *size)
            pipeline.start()
        except (RuntimeError, ValueError) as error:
            self.close()
            raise SourceError(f"{self._describe()}: cannot start the pipeline: {error}") from error
        self._pipeline = pipeline

    def read(self) -> DepthFrame | None:
        self.open()
        try:
            group = self._queue.get(timedelta(seconds=self.config.timeout_s))
        except (RuntimeError, dai.MessageQueue.QueueException) as error:
            raise SourceError(f"{self._describe()}: streaming failed: {error}") from error
        if group is None:
            raise SourceError(f"{self._describe()}: no frames for {self.config.timeout_s:g} s (unplugged?)")
        color = rgb_from_imgframe(group["rgb"]) if self.config.align_to_color else None
        return depth_frame_from_imgframe(group["depth"], self._intrinsics, self._serial, color)

    def close(self) -> None:
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except RuntimeError:
                pass
        if self._device is not None:
            self._device.close()
        self._device, self._pipeline, self._queue = None, None, None


def find_cameras() -> list[CameraInfo]:
    """Attached OAK cameras (an empty list when none)."""
    try:
        infos = dai.Device.getAllAvailableDevices()
    except RuntimeError:
        return []
    return [CameraInfo("oak", info.getDeviceId(), f"OAK ({info.name})") for info in infos]
