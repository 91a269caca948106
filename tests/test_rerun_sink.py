"""The Rerun sink: files appear whole, timelines are set, cameras log pose, pinhole and depth."""

import numpy as np

from capture.frames import CameraIntrinsics, DepthFrame, log_rerun
from helpers import rrd_entity_rows
from pipeline.rerun_sink import default_blueprint, rerun_stream, set_frame


def test_camera_frames_land_under_world_camera(tmp_path):
    intrinsics = CameraIntrinsics(64, 48, 50, 50, 31.5, 23.5)
    path = tmp_path / "run.rrd"
    with rerun_stream(path, blueprint=default_blueprint(["a", "b"])) as rec:
        assert not path.exists()
        for index in range(3):
            set_frame(rec, index, capture_ns=1_000_000_000 + index * 66_666_667)
            for sensor in ("a", "b"):
                depth = np.full((48, 64), 4000 + index, np.uint16)
                color = np.zeros((48, 64, 3), np.uint8) if sensor == "b" else None
                log_rerun(rec, DepthFrame(depth, 1e-4, intrinsics, sensor_id=sensor, color=color,
                                          T_world_camera=np.eye(4)))
    rows = rrd_entity_rows(path)
    assert rows["/world/camera/a/depth"] == 3 and rows["/world/camera/b/depth"] == 3
    assert rows["/world/camera/b/color"] == 3 and "/world/camera/a/color" not in rows
    assert rows["/world/camera/a"] == 6  # transform + pinhole per frame
    assert not list(tmp_path.glob("*.partial"))


def test_no_stream_when_nothing_asked_for():
    with rerun_stream(None) as rec:
        assert rec is None
