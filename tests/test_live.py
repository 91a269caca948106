"""live: the virtual camera in real time through the runner; a stop signal finalises every output;
a camera that dies mid-run keeps what was recorded; a slow stage drops work, never a recorded frame."""

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from capture.frames import CameraIntrinsics, DepthFrame
from capture.mcap.reader import McapSource, read_documents, read_fused_units
from capture.mcap.writer import McapRecorder
from capture.source import Source, SourceError
from helpers import rrd_entity_rows
from fusion.cloud import UnitBuilder
from pipeline.runner import RunConfig, Runner
from pipeline.sinks import McapSink
from test_detect_cli import run

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def model():
    from perception.weights import DEFAULT_WEIGHTS
    from perception.weights import load_weights

    return load_weights(DEFAULT_WEIGHTS)[0]


def test_live_virtual_turn_is_recorded_fused_detected_and_logged(tmp_path):
    result = run("live", "--camera", "virtual", "--views", 6, "--turns", 1, "--record", tmp_path / "s.mcap",
                 "--rrd", tmp_path / "s.rrd", "--detections", tmp_path / "caps.json", "--quiet")
    assert result.returncode == 0, result.stderr
    assert "one fused cloud per turn" in result.stdout
    with McapSource(tmp_path / "s.mcap") as session:
        frames = list(session)
    # the turntable keeps turning until the first turn is fused: every frame until then is recorded
    assert len(frames) >= 6
    # live frames carry wall-clock time, 1/15 s apart
    assert abs(frames[0].timestamp_ns / 1e9 - os.path.getmtime(tmp_path / "s.mcap")) < 600
    assert np.allclose(np.diff([f.timestamp_ns for f in frames]), 1e9 / 15, atol=1)
    units = read_fused_units(tmp_path / "s.mcap")
    documents = read_documents(tmp_path / "s.mcap")
    assert len(units) == len(documents) == 1
    assert units[0].frame_ids == tuple(f"virtual@{f.timestamp_ns}" for f in frames[:6])
    assert documents[0][1]["mushrooms"] and documents[0][0] == frames[5].timestamp_ns
    rows = rrd_entity_rows(tmp_path / "s.rrd")
    assert rows["/world/camera/virtual/depth"] == len(frames) and rows["/stats/latency/fusion_per_frame_ms"] >= 6
    # the turn is fused after later frames were recorded, yet every channel is in log-time order
    from mcap.reader import make_reader

    with open(tmp_path / "s.mcap", "rb") as file:
        in_file_order = [(channel.topic, message.log_time)
                         for _, channel, message in make_reader(file).iter_messages(log_time_order=False)]
    for topic in {topic for topic, _ in in_file_order}:
        times = [t for name, t in in_file_order if name == topic]
        assert times == sorted(times), topic
    assert [t for name, t in in_file_order if name == "/fusion/tf"] == [frames[5].timestamp_ns]
    # the fused cloud's and the cap outlines' topics say their frame from the first frame on, with an
    # empty cloud that readers pass over
    for topic in ("/fusion/cloud", "/perception/cap_outlines"):
        assert [t for name, t in in_file_order if name == topic] == [frames[0].timestamp_ns, frames[5].timestamp_ns]


def test_a_live_session_replays_to_the_caps_it_recorded(tmp_path):
    """The frames that came while the last turn was detected are recorded but were never fused, and the
    session was read twice: replay --check reads it as the run did and finds the same caps."""
    result = run("live", "--camera", "virtual", "--views", 6, "--turns", 1, "--readings", 2, "--record",
                 tmp_path / "s.mcap", "--quiet")
    assert result.returncode == 0, result.stderr
    assert read_documents(tmp_path / "s.mcap")[0][1]["readings"] == 2
    replayed = run("replay", tmp_path / "s.mcap", "--check", "--out", tmp_path / "replay")
    assert replayed.returncode == 0, replayed.stdout + replayed.stderr
    assert "check PASS" in replayed.stdout and "0 changed, 0 lost, 0 gained" in replayed.stdout


def test_sigterm_during_live_finalises_every_output(tmp_path):
    command = [sys.executable, "-m", "pipeline.cli", "live", "--camera", "virtual", "--views", 400,
               "--record", tmp_path / "s.mcap", "--rrd", tmp_path / "s.rrd", "--quiet"]
    process = subprocess.Popen([str(c) for c in command], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    assert process.stdout.readline().startswith("fused unit:")  # the first frame has come
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 143, stderr
    assert stderr.strip().splitlines()[-1].startswith("stopped by SIGTERM:") and str(tmp_path / "s.mcap") in stderr
    with McapSource(tmp_path / "s.mcap") as session:
        frames = list(session)
    assert 1 <= len(frames) < 400
    assert rrd_entity_rows(tmp_path / "s.rrd")["/world/camera/virtual/depth"] == len(frames)
    assert not list(tmp_path.glob("*.partial"))


def _frame(index: int) -> DepthFrame:
    intrinsics = CameraIntrinsics(64, 48, 60.0, 60.0, 31.5, 23.5)
    depth = np.full((48, 64), 4000 + index, np.uint16)
    return DepthFrame(depth, 1e-4, intrinsics, timestamp_ns=1_000_000 * (index + 1), sensor_id="cam")


class ListSource(Source):
    """Frames from a list, then an optional failure (an unplugged camera)."""

    def __init__(self, count: int, fail: bool = False):
        self.count, self.fail, self.index = count, fail, 0
        self.done = threading.Event()

    def read(self):
        if self.index == self.count:
            self.done.set()
            if self.fail:
                raise SourceError("no frame for 5 s: the camera is gone")
            return None
        self.index += 1
        return _frame(self.index - 1)


def test_a_camera_that_dies_keeps_its_recording(tmp_path, model, monkeypatch):
    monkeypatch.setattr(UnitBuilder, "add", lambda self, frame: None)
    recorder = McapRecorder(tmp_path / "s.mcap")
    runner = Runner(ListSource(5, fail=True), model, RunConfig(live=True), [McapSink(recorder)])
    with pytest.raises(SourceError, match="camera is gone"):
        runner.run()
    with McapSource(tmp_path / "s.mcap") as session:
        assert [f.timestamp_ns for f in session] == [_frame(k).timestamp_ns for k in range(5)]


def test_a_slow_fusion_drops_queued_frames_but_records_every_one(tmp_path, model, monkeypatch):
    source = ListSource(40)
    fused = []

    def slow_add(self, frame):
        source.done.wait(timeout=60)  # fusion is stuck until the camera has delivered everything
        fused.append(frame.timestamp_ns)

    monkeypatch.setattr(UnitBuilder, "add", slow_add)
    recorder = McapRecorder(tmp_path / "s.mcap")
    runner = Runner(source, model, RunConfig(live=True, queue_frames=4), [McapSink(recorder)])
    summary = runner.run()
    assert summary.frames == 40
    assert summary.dropped_frames >= 40 - 4 - 1 and summary.dropped_frames + len(fused) == 40
    assert fused[-1] == _frame(39).timestamp_ns  # the newest frames are kept, the oldest dropped
    with McapSource(tmp_path / "s.mcap") as session:
        assert len(list(session)) == 40


def test_a_file_source_waits_for_the_chain_instead_of_dropping(model, monkeypatch):
    source = ListSource(30)
    fused = []
    monkeypatch.setattr(UnitBuilder, "add", lambda self, frame: fused.append(frame.timestamp_ns))
    summary = Runner(source, model, RunConfig(live=False, queue_frames=2), []).run()
    assert summary.dropped_frames == 0 and len(fused) == 30


@pytest.mark.parametrize("args, fragment", [
    (["--camera", "oak", "--playback", "x.db3"], "use it with --camera realsense"),
    (["--camera", "realsense", "--playback", "missing.db3"], "no device file"),
    (["--camera", "virtual", "--rig", "missing.json"], "does not exist"),
    (["--camera", "virtual", "--record", "s.txt"], "name it with .mcap"),
])
def test_live_bad_input_fails_in_one_line(tmp_path, args, fragment):
    result = run("live", *[str(tmp_path / a) if a.endswith((".db3", ".json", ".txt")) else a for a in args])
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1 and fragment in result.stderr


def test_live_plays_a_realsense_device_file_through_the_driver(tmp_path):
    from pipeline.check import compare
    from pipeline.recordings import RECORDINGS_DIR, expected_path

    device_file = RECORDINGS_DIR / "realsense-playback.db3"
    result = run("live", "--camera", "realsense", "--playback", device_file, "--detections", tmp_path / "caps.json",
                 "--quiet")
    assert result.returncode == 0, result.stderr
    assert "each frame alone" in result.stdout and "2 fused units" in result.stdout
    import json

    expected = json.loads(expected_path(device_file).read_text())
    assert compare(expected[-1:], [json.loads((tmp_path / "caps.json").read_text())]).passed


def test_window_fuses_the_last_frames_after_every_frame(tmp_path):
    from pipeline.recordings import RECORDINGS_DIR

    result = run("replay", RECORDINGS_DIR / "single-view.mcap", "--out", tmp_path, "--window", 2, "--quiet")
    assert result.returncode == 0, result.stderr
    assert "the last 2 frames" in result.stdout
    units = read_fused_units(tmp_path / "replay.mcap")
    assert [len(u.frame_ids) for u in units] == [1, 2]


def test_a_unit_fusion_cannot_make_is_skipped_and_the_run_goes_on(model, monkeypatch):
    calls = []

    def add(self, frame):
        calls.append(frame.timestamp_ns)
        if len(calls) == 2:
            raise ValueError("no two of the 2 views overlap")
        return None

    monkeypatch.setattr(UnitBuilder, "add", add)
    summary = Runner(ListSource(5), model, RunConfig(live=True), []).run()
    assert len(calls) == 5 and summary.failed_units == 1 and "overlap" in summary.last_failure
