"""record: a virtual session round-trips bit-exact through MCAP; bad cameras fail in one line."""

from pathlib import Path

import numpy as np
import pytest

from capture.mcap.reader import McapSource
from capture.virtual import VirtualCameraConfig
from pipeline.sources import VirtualBed, virtual_bed_source
from test_detect_cli import one_line_error, run

RECORDINGS = Path(__file__).resolve().parents[1] / "recordings"


def test_record_virtual_round_trips_bit_exact(tmp_path):
    out = tmp_path / "session.mcap"
    result = run("record", "--camera", "virtual", "--views", "3", "--seed", "2", "--out", out, "--quiet")
    assert result.returncode == 0, result.stderr
    assert "recorded 3 frames" in result.stdout
    expected = list(virtual_bed_source(VirtualBed(seed=2, camera=VirtualCameraConfig(views=3)))[0])
    with McapSource(out) as replay:
        got = list(replay)
    assert len(got) == len(expected) == 3
    for a, b in zip(got, expected):
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.T_world_camera, b.T_world_camera)
        assert (a.depth_scale, a.intrinsics, a.timestamp_ns, a.sensor_id, a.turntable_angle) == \
               (b.depth_scale, b.intrinsics, b.timestamp_ns, b.sensor_id, b.turntable_angle)


def test_record_refuses_unknown_camera_and_existing_file(tmp_path):
    one_line_error(run("record", "--camera", "kinect", "--out", tmp_path / "x.mcap"), "invalid choice")
    existing = tmp_path / "old.mcap"
    existing.write_bytes(b"keep me")
    one_line_error(run("record", "--camera", "virtual", "--out", existing), "--overwrite")
    assert existing.read_bytes() == b"keep me"


class UnpluggedAfter:
    """A camera that delivers a few frames and is then pulled out."""

    def __init__(self, frames):
        self.frames = list(frames)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None

    def read(self):
        from capture.source import SourceError

        if not self.frames:
            raise SourceError("no frames for 5 s: the camera was unplugged")
        return self.frames.pop(0)


def test_unplugged_camera_keeps_the_recording_and_says_so(tmp_path, monkeypatch):
    import pipeline.sources

    frames = list(virtual_bed_source(VirtualBed(seed=1, camera=VirtualCameraConfig(views=3)))[0])
    monkeypatch.setattr(pipeline.sources, "make_source", lambda *a, **k: UnpluggedAfter(frames))
    out = tmp_path / "cut.mcap"
    one_line_error(run("record", "--camera", "realsense", "--out", out, "--quiet"), "unplugged")
    with McapSource(out) as replay:
        kept = list(replay)
    assert len(kept) == 3
    np.testing.assert_array_equal(kept[-1].depth, frames[-1].depth)


def test_a_camera_that_gives_nothing_says_so_and_keeps_the_old_file(tmp_path, monkeypatch):
    import pipeline.sources

    monkeypatch.setattr(pipeline.sources, "make_source", lambda *a, **k: UnpluggedAfter([]))
    out = tmp_path / "old.mcap"
    out.write_bytes(b"an earlier session")
    one_line_error(run("record", "--camera", "realsense", "--out", out, "--overwrite", "--quiet"),
                   "nothing was recorded")
    assert out.read_bytes() == b"an earlier session"


def test_a_recording_that_fails_inside_its_first_frame_keeps_the_old_file(tmp_path, monkeypatch):
    """The depth image is written before the pose: a pose that cannot be written fails the frame half
    way, and the earlier session must survive that."""
    import dataclasses

    import pipeline.sources

    frame = next(iter(virtual_bed_source(VirtualBed(seed=1, camera=VirtualCameraConfig(views=1)))[0]))
    broken = dataclasses.replace(frame, T_world_camera=np.full((4, 4), np.nan))
    monkeypatch.setattr(pipeline.sources, "make_source", lambda *a, **k: UnpluggedAfter([broken]))
    out = tmp_path / "old.mcap"
    out.write_bytes(b"an earlier session")
    result = run("record", "--camera", "realsense", "--out", out, "--overwrite", "--quiet")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "nothing was recorded" in result.stderr and "pose" in result.stderr, result.stderr
    assert out.read_bytes() == b"an earlier session"


class EndsAfter(UnpluggedAfter):
    """A playback that ends after a few frames."""

    def read(self):
        return self.frames.pop(0) if self.frames else None


@pytest.mark.parametrize("source_frames, duration, message", [
    ([], None, "the source ended before its first frame"),
    (None, 1e-9, "no frame arrived within 1e-09 s"),
])
def test_a_recording_of_no_frames_is_an_error_and_keeps_the_old_file(tmp_path, monkeypatch, source_frames,
                                                                     duration, message):
    import pipeline.sources

    if source_frames is None:
        source_frames = list(virtual_bed_source(VirtualBed(seed=1, camera=VirtualCameraConfig(views=1)))[0])
    monkeypatch.setattr(pipeline.sources, "make_source", lambda *a, **k: EndsAfter(source_frames))
    out = tmp_path / "old.mcap"
    out.write_bytes(b"an earlier session")
    args = ["record", "--camera", "realsense", "--out", out, "--overwrite", "--quiet"]
    one_line_error(run(*args, *(["--duration", duration] if duration is not None else [])),
                   f"{message}; nothing was recorded, {out} is as it was")
    assert out.read_bytes() == b"an earlier session" and sorted(p.name for p in tmp_path.iterdir()) == ["old.mcap"]


def test_ctrl_c_that_a_library_turns_into_another_error_is_reported_as_an_interrupt(tmp_path, monkeypatch):
    """A C extension loading when Ctrl-C arrives raises ImportError("initialization failed")."""
    import signal

    import pipeline.sources

    def load(interrupt: bool):
        def make_source(*args, **kwargs):
            try:
                if interrupt:
                    signal.raise_signal(signal.SIGINT)
            except KeyboardInterrupt:
                pass
            raise ImportError("initialization failed")
        return make_source

    handler = signal.getsignal(signal.SIGINT)
    args = ("record", "--camera", "realsense", "--out", tmp_path / "r.mcap", "--quiet")
    monkeypatch.setattr(pipeline.sources, "make_source", load(interrupt=False))
    one_line_error(run(*args), "initialization failed")
    monkeypatch.setattr(pipeline.sources, "make_source", load(interrupt=True))
    result = run(*args)
    assert result.returncode == 130 and result.stderr == "mushroom-pose record: interrupted\n"
    assert signal.getsignal(signal.SIGINT) is handler and not list(tmp_path.iterdir())


def test_depth_and_colour_of_different_sizes_are_refused():
    from capture.frames import CameraIntrinsics, DepthFrame

    with pytest.raises(ValueError, match="align them first"):
        DepthFrame(np.zeros((48, 64), np.uint16), 1e-3, CameraIntrinsics(64, 48, 50, 50, 32, 24),
                   color=np.zeros((24, 32, 3), np.uint8))


def test_calibrate_recovers_the_virtual_turntable(tmp_path):
    from fusion.turntable import Rig

    session = tmp_path / "turn.mcap"
    assert run("record", "--camera", "virtual", "--views", "8", "--out", session, "--quiet").returncode == 0
    result = run("calibrate", "--session", session, "--out", tmp_path / "rig.json")
    assert result.returncode == 0, result.stderr
    rig = Rig.load(tmp_path / "rig.json")
    # the virtual rig turns about +z through the bed centre (pipeline.sources.VirtualBed), 45 deg a view.
    # Measured on sessions of beds 0-4 (record --seed): axis 0.004-0.019 deg off, through 0.02-0.15 mm of
    # the centre, step off by 0.0003-0.0067 deg; bounds twice the worst
    axis = np.asarray(rig.turntable.axis_direction) * np.sign(rig.turntable.axis_direction[2])
    assert np.degrees(np.arccos(min(1.0, axis[2]))) < 0.04
    assert np.linalg.norm(np.asarray(rig.turntable.axis_point)[:2]) < 0.0003
    assert abs(np.degrees(rig.angle_step) - 45.0) < 0.015


def test_calibrate_warns_when_the_session_is_less_than_a_turn(tmp_path):
    from capture.mcap.writer import McapRecorder

    frames = list(McapSource(RECORDINGS / "turntable-12.mcap"))
    part = tmp_path / "part.mcap"
    with McapRecorder(part) as recorder:
        for frame in frames[:5]:
            recorder.write(frame)
    partial = run("calibrate", "--session", part, "--out", tmp_path / "part.json")
    assert partial.returncode == 0
    warnings = [line for line in partial.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "covers about 150 deg" in warnings[0] and "5 views 30.0 deg apart" in warnings[0]
    whole = run("calibrate", "--session", RECORDINGS / "turntable-12.mcap", "--out", tmp_path / "whole.json")
    assert whole.returncode == 0 and "warning" not in whole.stderr


def test_calibrate_rejects_a_file_that_is_not_mcap(tmp_path):
    bogus = tmp_path / "notes.mcap"
    bogus.write_text("hello")
    one_line_error(run("calibrate", "--session", bogus, "--out", tmp_path / "rig.json"), "not an MCAP file")


def test_sigterm_stops_record_with_exit_143_and_a_whole_recording(tmp_path):
    """A supervisor stopping ``record`` (SIGTERM) gets 143, not 0, and the frames so far in a valid MCAP."""
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    out = tmp_path / "r.mcap"
    partial = tmp_path / "r.mcap.partial"
    process = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "record", "--camera", "virtual", "--views", "600",
                                "--out", str(out), "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, cwd=Path(__file__).resolve().parents[1])
    deadline = time.monotonic() + 90
    while not (partial.exists() and partial.stat().st_size > 1_000_000):  # some frames recorded
        assert process.poll() is None and time.monotonic() < deadline, "record ended or wrote too little"
        time.sleep(0.2)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 143
    assert stderr.startswith("stopped by SIGTERM: recorded ") and len(stderr.strip().splitlines()) == 1
    with McapSource(out) as replay:
        assert sum(1 for _ in replay) > 0
    assert not partial.exists()
