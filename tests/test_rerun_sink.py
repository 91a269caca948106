"""The Rerun sink: files appear whole, timelines are set, cameras log pose, pinhole and depth."""

import numpy as np
import pytest

from capture.frames import CameraIntrinsics, DepthFrame, log_rerun
from helpers import rerun_matrix, rrd_entity_rows, rrd_values
from pipeline.rerun_sink import default_blueprint, rerun_stream, set_frame


def test_camera_frames_land_under_world_camera(tmp_path):
    """Three frames of two cameras, each at its own pose: read back, every row sits on the frame and
    capture timelines at the values set for it, with the pose and depth logged for it."""
    from scipy.spatial.transform import Rotation

    intrinsics = CameraIntrinsics(64, 48, 50, 50, 31.5, 23.5)
    path = tmp_path / "run.rrd"
    rng = np.random.default_rng(0)
    poses = {}
    with rerun_stream(path, blueprint=default_blueprint(["a", "b"])) as rec:
        assert not path.exists()
        for index in range(3):
            set_frame(rec, index, capture_ns=1_000_000_000 + index * 66_666_667)
            for sensor in ("a", "b"):
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = Rotation.random(random_state=rng).as_matrix(), rng.uniform(-0.5, 0.5, 3)
                poses[sensor, index] = T
                depth = np.full((48, 64), 4000 + index, np.uint16)
                color = np.zeros((48, 64, 3), np.uint8) if sensor == "b" else None
                log_rerun(rec, DepthFrame(depth, 1e-4, intrinsics, sensor_id=sensor, color=color, T_world_camera=T))
    rows = rrd_entity_rows(path)
    assert rows["/world/camera/a/depth"] == 3 and rows["/world/camera/b/depth"] == 3
    assert rows["/world/camera/b/color"] == 3 and "/world/camera/a/color" not in rows
    assert rows["/world/camera/a"] == 6  # transform + pinhole per frame
    assert not list(tmp_path.glob("*.partial"))
    for sensor in ("a", "b"):
        translations = rrd_values(path, f"/world/camera/{sensor}", "Transform3D:translation")
        matrices = rrd_values(path, f"/world/camera/{sensor}", "Transform3D:mat3x3")
        assert [times["frame"] for times, _ in translations] == [0, 1, 2]
        assert [times["capture"] for times, _ in translations] == [1_000_000_000 + i * 66_666_667 for i in range(3)]
        for index, ((_, translation), (_, matrix)) in enumerate(zip(translations, matrices)):
            T = poses[sensor, index]
            np.testing.assert_allclose(translation[0], T[:3, 3], atol=1e-6)  # stored as float32
            np.testing.assert_allclose(rerun_matrix(matrix[0]), T[:3, :3], atol=1e-6)
        depths = rrd_values(path, f"/world/camera/{sensor}/depth", "DepthImage:buffer")
        assert [times["frame"] for times, _ in depths] == [0, 1, 2]
        for index, (_, buffer) in enumerate(depths):
            assert set(np.frombuffer(bytes(buffer[0]), np.uint16)) == {4000 + index}
        meters = rrd_values(path, f"/world/camera/{sensor}/depth", "DepthImage:meter")
        assert [value for _, value in meters] == [[pytest.approx(1e4)]] * 3  # depth units per metre
        pinholes = rrd_values(path, f"/world/camera/{sensor}", "Pinhole:image_from_camera")
        assert pinholes and all(times == {} for times, _ in pinholes)  # static
        np.testing.assert_allclose(rerun_matrix(pinholes[0][1][0]), intrinsics.matrix)


def test_no_stream_when_nothing_asked_for():
    with rerun_stream(None) as rec:
        assert rec is None


def test_the_run_opens_on_its_newest_frame():
    """A saved run opens where it ended (the last unit's cloud and caps), not on frame 0 playing through
    frames that hold no cloud yet; a live viewer keeps up with the run."""
    time_panel = default_blueprint(["a"]).time_panel
    assert (str(time_panel.timeline), str(time_panel.play_state)) == ("frame", "following")
