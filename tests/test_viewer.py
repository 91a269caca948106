"""The Rerun viewer's stream: files appear whole, every target gets the data, timelines are set,
cameras log pose, pinhole and depth."""

import numpy as np
import pytest

from capture.frames import CameraIntrinsics, DepthFrame
from helpers import rerun_matrix, rrd_entity_rows, rrd_values
from pipeline.viewer import blueprint, log_frame, send_blueprint, set_frame, viewer_stream
from pipeline.viewer_target import ViewerTarget


def test_camera_frames_land_under_world_camera(tmp_path):
    """Three frames of two cameras, each at its own pose: read back, every row sits on the frame and
    capture timelines at the values set for it, with the pose and depth logged for it."""
    from scipy.spatial.transform import Rotation

    intrinsics = CameraIntrinsics(64, 48, 50, 50, 31.5, 23.5)
    path = tmp_path / "run.rrd"
    rng = np.random.default_rng(0)
    poses = {}
    with viewer_stream(ViewerTarget(path)) as rec:
        send_blueprint(rec, ["a", "b"])
        assert not path.exists()
        for index in range(3):
            set_frame(rec, index, capture_ns=1_000_000_000 + index * 66_666_667)
            for sensor in ("a", "b"):
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = Rotation.random(random_state=rng).as_matrix(), rng.uniform(-0.5, 0.5, 3)
                poses[sensor, index] = T
                depth = np.full((48, 64), 4000 + index, np.uint16)
                color = np.zeros((48, 64, 3), np.uint8) if sensor == "b" else None
                log_frame(rec, DepthFrame(depth, 1e-4, intrinsics, sensor_id=sensor, color=color, T_world_camera=T))
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
    with viewer_stream(ViewerTarget()) as rec:
        assert rec is None


def test_a_served_run_still_writes_its_file(tmp_path, monkeypatch):
    """--rrd with --serve: the file holds every row and the web viewer is served at the same time (each
    of Rerun's save and serve calls alone replaces the other's sink); without ``hold`` the command ends."""
    import socket

    import pipeline.viewer as viewer

    def free_port() -> int:
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            return probe.getsockname()[1]

    monkeypatch.setattr(viewer, "GRPC_PORT", free_port())
    monkeypatch.setattr(viewer, "WEB_PORT", free_port())
    served = []
    monkeypatch.setattr(viewer.rr, "serve_web_viewer", lambda **options: served.append(options["connect_to"]))
    path = tmp_path / "served.rrd"
    with viewer_stream(ViewerTarget(path, serve=True), name="served") as rec:
        for index in range(3):
            set_frame(rec, index)
            viewer.log_stat(rec, "counts/caps", index)
    assert served == [f"rerun+http://127.0.0.1:{viewer.GRPC_PORT}/proxy"]
    assert rrd_entity_rows(path)["/stats/counts/caps"] == 3
    with pytest.raises(ValueError, match="not both"):
        ViewerTarget(spawn=True, serve=True)


def test_the_run_opens_on_its_newest_frame():
    """A saved run opens where it ended (the last unit's cloud and caps), not on frame 0 playing through
    frames that hold no cloud yet; a live viewer keeps up with the run."""
    time_panel = blueprint(["a"]).time_panel
    assert (str(time_panel.timeline), str(time_panel.play_state)) == ("frame", "following")


def test_a_command_that_serves_keeps_serving_until_ctrl_c(tmp_path):
    """``synth --serve`` writes its beds and .rrd, then keeps the web viewer up until SIGINT, and exits 0."""
    import signal
    import subprocess
    import sys
    import threading

    rrd = tmp_path / "beds.rrd"
    command = [sys.executable, "-m", "pipeline.cli", "synth", "--scenes", "1", "--mushrooms", "3", "3", "--no-ply",
               "--quiet", "--out", str(tmp_path / "beds"), "--rrd", str(rrd), "--serve"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    watchdog = threading.Timer(120, process.kill)  # a command that never says it serves fails, not hangs
    watchdog.start()
    try:
        for line in iter(process.stderr.readline, ""):
            if "until Ctrl-C" in line:
                break
        else:
            raise AssertionError("the command ended without serving")
        assert process.poll() is None  # still serving
        process.send_signal(signal.SIGINT)
        stdout, _ = process.communicate(timeout=30)
    finally:
        watchdog.cancel()
        process.kill()
    assert process.returncode == 0
    assert "scenes: 1" in stdout
    assert rrd_entity_rows(rrd)["/world/synthetic/points"] == 1
