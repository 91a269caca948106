"""OAK conversion code on real depthai host objects (ImgFrame, CalibrationHandler); device parts need an OAK."""

from __future__ import annotations

import dataclasses
from datetime import timedelta

import numpy as np
import open3d as o3d
import pytest

dai = pytest.importorskip("depthai")

from capture.frames import CameraIntrinsics, DepthFrame, backproject  # noqa: E402
from capture.oak import (COLOR_SOCKET, OakConfig, OakSource, depth_frame_from_imgframe,  # noqa: E402
                         find_cameras, intrinsics_from_calibration, rgb_from_imgframe)
from capture.virtual import SensorModel, VirtualCameraConfig, VirtualSource  # noqa: E402
from common.geometry import look_at  # noqa: E402

INTRINSICS = CameraIntrinsics(160, 120, 100.0, 100.0, 79.5, 59.5)


@pytest.fixture(scope="module")
def frames() -> list[DepthFrame]:
    """Virtual-camera frames in millimetre units, as StereoDepth reports them, with a gradient as colour."""
    bed = o3d.geometry.TriangleMesh.create_box(0.3, 0.3, 0.02).translate([-0.15, -0.15, -0.02])
    block = o3d.geometry.TriangleMesh.create_box(0.05, 0.04, 0.03).translate([-0.02, -0.03, 0.0])
    mesh = bed + block
    poses = tuple(look_at(np.array([0.03 * k, 0.01, 0.25]), np.zeros(3)) for k in range(3))
    config = VirtualCameraConfig(intrinsics=INTRINSICS, sensor=SensorModel(depth_scale=1e-3), poses=poses,
                                 start_ns=5_000_000_000)
    rendered = list(VirtualSource(np.asarray(mesh.vertices), np.asarray(mesh.triangles), config))
    u, v = np.meshgrid(np.arange(INTRINSICS.width), np.arange(INTRINSICS.height))
    gradient = np.stack([u * 255 // (INTRINSICS.width - 1), v * 255 // (INTRINSICS.height - 1),
                         np.full_like(u, 64)], -1).astype(np.uint8)
    return [dataclasses.replace(f, color=np.roll(gradient, 5 * k, axis=0)) for k, f in enumerate(rendered)]


def calibration(intrinsics: CameraIntrinsics, socket=COLOR_SOCKET) -> dai.CalibrationHandler:
    calib = dai.CalibrationHandler()
    calib.setCameraIntrinsics(socket, intrinsics.matrix.tolist(), intrinsics.width, intrinsics.height)
    return calib


def imgframe(array: np.ndarray, kind: dai.ImgFrame.Type, timestamp_ns: int = 0) -> dai.ImgFrame:
    img = dai.ImgFrame()
    img.setType(kind)
    img.setWidth(array.shape[1])
    img.setHeight(array.shape[0])
    img.setFrame(array)
    img.setTimestamp(timedelta(microseconds=timestamp_ns // 1000))
    return img


def test_intrinsics_round_trip_through_calibration():
    calib = calibration(INTRINSICS)
    assert intrinsics_from_calibration(calib, COLOR_SOCKET, 160, 120) == INTRINSICS
    doubled = intrinsics_from_calibration(calib, COLOR_SOCKET, 320, 240)
    assert (doubled.width, doubled.height, doubled.fx, doubled.fy) == (320, 240, 200.0, 200.0)
    assert (doubled.cx, doubled.cy) == (159.0, 119.0)


def test_calibration_without_the_socket_is_a_value_error():
    with pytest.raises(ValueError, match="no intrinsics"):
        intrinsics_from_calibration(calibration(INTRINSICS), dai.CameraBoardSocket.CAM_C, 160, 120)


def test_depth_round_trips_exactly_through_imgframe(frames):
    """Depth, colour and intrinsics exactly; the timestamp to the microsecond depthai keeps."""
    intrinsics = intrinsics_from_calibration(calibration(INTRINSICS), COLOR_SOCKET, 160, 120)
    for frame in frames:
        img = imgframe(frame.depth, dai.ImgFrame.Type.RAW16, frame.timestamp_ns)
        back = depth_frame_from_imgframe(img, intrinsics, "oak-test", rgb_from_imgframe(
            imgframe(frame.color, dai.ImgFrame.Type.RGB888i)))
        assert back.depth.dtype == np.uint16
        np.testing.assert_array_equal(back.depth, frame.depth)
        np.testing.assert_array_equal(back.color, frame.color)
        assert back.depth_scale == frame.depth_scale == 0.001
        assert back.intrinsics == INTRINSICS
        assert back.timestamp_ns == frame.timestamp_ns // 1000 * 1000
        assert back.sensor_id == "oak-test"
        np.testing.assert_array_equal(backproject(back.depth_m, back.intrinsics)[0],
                                      backproject(frame.depth_m, frame.intrinsics)[0])


def test_colour_conversions(frames):
    rgb = frames[0].color
    np.testing.assert_array_equal(rgb_from_imgframe(imgframe(np.ascontiguousarray(rgb[..., ::-1]),
                                                             dai.ImgFrame.Type.BGR888i)), rgb)
    nv12 = dai.ImgFrame()
    nv12.setCvFrame(np.ascontiguousarray(rgb[..., ::-1]), dai.ImgFrame.Type.NV12)
    converted = rgb_from_imgframe(nv12)
    assert converted.shape == rgb.shape and converted.dtype == np.uint8
    assert np.abs(converted.astype(int) - rgb).mean() < 8


def test_only_raw16_is_depth(frames):
    with pytest.raises(ValueError, match="RAW16"):
        depth_frame_from_imgframe(imgframe(frames[0].color, dai.ImgFrame.Type.RGB888i), INTRINSICS, "oak")


def test_device():
    if not dai.Device.getAllAvailableDevices():
        assert find_cameras() == []
        pytest.skip("no OAK device attached (dai.Device.getAllAvailableDevices() is empty)")
    camera = find_cameras()[0]
    with OakSource(OakConfig(mxid=camera.serial, width=640, height=400)) as source:
        frame = source.read()
    assert frame.sensor_id == camera.serial and frame.depth_scale == 0.001
    assert frame.depth.shape == (400, 640) and frame.color.shape == (400, 640, 3)
    assert (frame.intrinsics.width, frame.intrinsics.height) == (640, 400)
