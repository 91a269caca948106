"""RealSense through the real driver: virtual-camera frames recorded as a device file, played back by rs.pipeline."""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
import pytest

rs = pytest.importorskip("pyrealsense2")

from capture.frames import CameraIntrinsics, DepthFrame  # noqa: E402
from capture.realsense import (RealSenseConfig, RealSenseSource, find_cameras,  # noqa: E402
                               write_device_recording)
from capture.source import SourceError  # noqa: E402
from capture.virtual import SensorModel, VirtualCameraConfig, VirtualSource  # noqa: E402
from common.geometry import look_at  # noqa: E402

INTRINSICS = CameraIntrinsics(160, 120, 100.0, 100.0, 79.5, 59.5)
COLOR_INTRINSICS = CameraIntrinsics(320, 240, 200.0, 200.0, 159.5, 119.5)
"""A colour camera with twice the resolution and the same optical centre: depth pixel u covers colour 2u, 2u+1."""


def virtual_frames(depth_scale: float, views: int = 4, color: bool = True) -> list[DepthFrame]:
    """A bed slab with one block on it, seen from a few poses by the virtual camera, with a gradient as colour."""
    bed = o3d.geometry.TriangleMesh.create_box(0.3, 0.3, 0.02).translate([-0.15, -0.15, -0.02])
    block = o3d.geometry.TriangleMesh.create_box(0.05, 0.04, 0.03).translate([-0.02, -0.03, 0.0])
    mesh = bed + block
    poses = tuple(look_at(np.array([0.02 * k, 0.01, 0.25]), np.zeros(3)) for k in range(views))
    config = VirtualCameraConfig(intrinsics=INTRINSICS, sensor=SensorModel(depth_scale=depth_scale), poses=poses,
                                 sensor_id="virtual-d405", start_ns=1_000_000_000)
    frames = list(VirtualSource(np.asarray(mesh.vertices), np.asarray(mesh.triangles), config))
    if not color:
        return frames
    u, v = np.meshgrid(np.arange(INTRINSICS.width), np.arange(INTRINSICS.height))
    gradient = np.stack([u * 255 // (INTRINSICS.width - 1), v * 255 // (INTRINSICS.height - 1),
                         np.full_like(u, 128)], -1).astype(np.uint8)
    return [dataclasses.replace(f, color=np.roll(gradient, 7 * k, axis=1)) for k, f in enumerate(frames)]


@pytest.fixture(scope="module")
def rgbd_frames() -> list[DepthFrame]:
    return virtual_frames(depth_scale=1e-4)


@pytest.fixture(scope="module")
def rgbd_recording(rgbd_frames, tmp_path_factory):
    """D405-like: colour on the depth pixels, from the depth sensor."""
    return write_device_recording(rgbd_frames, tmp_path_factory.mktemp("rs") / "virtual.db3")


@pytest.fixture(scope="module")
def d435_colors(rgbd_frames) -> list[np.ndarray]:
    return [np.repeat(np.repeat(f.color, 2, 0), 2, 1) for f in rgbd_frames]


@pytest.fixture(scope="module")
def d435_recording(rgbd_frames, d435_colors, tmp_path_factory):
    """D435-like: a separate RGB sensor with its own pixel grid."""
    return write_device_recording(rgbd_frames, tmp_path_factory.mktemp("rs") / "d435like.db3",
                                  color_images=d435_colors, color_intrinsics=COLOR_INTRINSICS)


def test_virtual_frames_are_realistic(rgbd_frames):
    valid = np.mean([(f.depth > 0).mean() for f in rgbd_frames])
    assert 0.5 < valid < 1.0
    assert len({f.depth.tobytes() for f in rgbd_frames}) == len(rgbd_frames)


def test_playback_returns_every_frame_exactly(rgbd_frames, rgbd_recording):
    with RealSenseSource(RealSenseConfig(playback=rgbd_recording)) as source:
        played = list(source)
        assert source.read() is None
    assert len(played) == len(rgbd_frames)
    for written, frame in zip(rgbd_frames, played):
        assert frame.depth.dtype == np.uint16
        np.testing.assert_array_equal(frame.depth, written.depth)
        np.testing.assert_array_equal(frame.color, written.color)
        assert frame.depth_scale == written.depth_scale == 1e-4
        assert frame.intrinsics == INTRINSICS
        assert frame.timestamp_ns == written.timestamp_ns
        assert frame.sensor_id == "virtual-d405"


@pytest.mark.parametrize("recording", ["rgbd_recording", "d435_recording"])
def test_playback_is_repeatable(recording, rgbd_frames, request):
    """Started plainly, librealsense's pipeline drops a file's first frames now and then (it starts the
    sensors one after the other); our source must deliver every frame, every time, for either layout."""
    path = request.getfixturevalue(recording)
    for _ in range(5):
        stamps = [f.timestamp_ns for f in RealSenseSource(RealSenseConfig(playback=path))]
        assert stamps == [f.timestamp_ns for f in rgbd_frames]


def test_depth_only_recording(tmp_path):
    frames = virtual_frames(depth_scale=1e-3, views=3, color=False)
    path = write_device_recording(frames, tmp_path / "depth.db3")
    played = list(RealSenseSource(RealSenseConfig(playback=path)))
    assert [f.color for f in played] == [None] * 3
    for written, frame in zip(frames, played):
        np.testing.assert_array_equal(frame.depth, written.depth)
        assert frame.depth_scale == 1e-3
        assert frame.intrinsics == INTRINSICS


def test_color_off_plays_depth_only(rgbd_frames, rgbd_recording):
    played = list(RealSenseSource(RealSenseConfig(playback=rgbd_recording, color=False)))
    assert len(played) == len(rgbd_frames)
    assert all(f.color is None for f in played)
    np.testing.assert_array_equal(played[-1].depth, rgbd_frames[-1].depth)


def expected_alignment(depth: np.ndarray) -> np.ndarray:
    """librealsense's depth-to-colour for COLOR_INTRINSICS: each depth pixel's corners are reprojected and
    rounded, so pixel u fills colour pixels 2u..2u+2 (one of dilation), and the nearest depth wins."""
    z = np.where(depth > 0, depth, np.iinfo(np.uint16).max).astype(np.int64)
    up = np.repeat(np.repeat(z, 2, 0), 2, 1)
    shifted_x = np.pad(up, ((0, 0), (2, 0)), constant_values=np.iinfo(np.int64).max)[:, :-2]
    nearest = np.minimum(up, np.where(np.arange(up.shape[1]) % 2 == 0, shifted_x, up))
    shifted_y = np.pad(nearest, ((2, 0), (0, 0)), constant_values=np.iinfo(np.int64).max)[:-2]
    nearest = np.minimum(nearest, np.where((np.arange(up.shape[0]) % 2 == 0)[:, None], shifted_y, nearest))
    return np.where(nearest >= np.iinfo(np.uint16).max, 0, nearest).astype(np.uint16)


def test_playback_aligns_depth_to_a_separate_colour_camera(rgbd_frames, d435_colors, d435_recording):
    played = list(RealSenseSource(RealSenseConfig(playback=d435_recording)))
    assert len(played) == len(rgbd_frames)
    for written, color, frame in zip(rgbd_frames, d435_colors, played):
        assert frame.intrinsics == COLOR_INTRINSICS
        np.testing.assert_array_equal(frame.color, color)
        assert set(np.unique(frame.depth)) <= set(np.unique(written.depth))
        assert np.mean(frame.depth == expected_alignment(written.depth)) > 0.98
    unaligned = list(RealSenseSource(RealSenseConfig(playback=d435_recording, align_to_color=False)))
    np.testing.assert_array_equal(unaligned[0].depth, rgbd_frames[0].depth)
    assert unaligned[0].intrinsics == INTRINSICS and unaligned[0].color is None


def test_missing_recording_is_a_source_error(tmp_path):
    with pytest.raises(SourceError, match="no RealSense recording"):
        RealSenseSource(RealSenseConfig(playback=tmp_path / "absent.db3")).read()


def test_only_db3_can_be_written(rgbd_frames, tmp_path):
    with pytest.raises(ValueError, match=".db3"):
        write_device_recording(rgbd_frames, tmp_path / "virtual.bag")


def test_live_camera():
    devices = rs.context().query_devices()
    if len(devices) == 0:
        assert find_cameras() == []
        with pytest.raises(SourceError):
            RealSenseSource(RealSenseConfig()).read()
        pytest.skip("no RealSense camera attached (rs.context().query_devices() is empty)")
    serial = devices[0].get_info(rs.camera_info.serial_number)
    assert serial in [c.serial for c in find_cameras()]
    with RealSenseSource(RealSenseConfig(serial=serial, width=640, height=480, fps=30)) as source:
        frame = source.read()
    assert frame.sensor_id == serial and frame.depth.shape == (480, 640) and frame.depth_scale > 0
    assert frame.color is not None and frame.color.shape == (480, 640, 3)
