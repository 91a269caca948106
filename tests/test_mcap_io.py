"""MCAP recording and replay: bit-exact round trip, plain-reader layout, signals, truncation, bad input."""

import collections
import dataclasses
import json
import shutil
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory
from scipy.spatial.transform import Rotation

from capture.frames import CameraIntrinsics, DepthFrame
from capture.mcap.reader import McapSource, TruncatedRecordingWarning
from capture.mcap.writer import McapRecorder, record
from capture.source import Source, SourceError
from common.geometry import look_at

INTRINSICS = CameraIntrinsics(160, 120, 100, 100, 79.5, 59.5)
REPO = Path(__file__).resolve().parents[1]


class ListSource(Source):
    """Given frames, in order."""

    def __init__(self, frames):
        self._frames = iter(frames)

    def read(self):
        return next(self._frames, None)


class TickSource(Source):
    """An endless live-like camera: a small frame every 20 ms."""

    def __init__(self):
        self.count = 0

    def read(self):
        time.sleep(0.02)
        self.count += 1
        depth = np.full((48, 64), 1000 + self.count, np.uint16)
        return DepthFrame(depth, 1e-4, CameraIntrinsics(64, 48, 40.0, 40.0, 31.5, 23.5), self.count * 20_000_000,
                          "live", turntable_angle=0.01 * self.count)


@pytest.fixture(scope="module")
def frames():
    """Two virtual cameras over two boxes on a slab, interleaved in time: a turntable camera "a"
    (depth only) and a fixed camera "b" with colour, whose last frame has no known pose."""
    import open3d as o3d

    from capture.virtual import VirtualCameraConfig, VirtualSource, circle_turntable

    slab = o3d.geometry.TriangleMesh.create_box(0.4, 0.4, 0.01).translate((-0.2, -0.2, -0.01))
    box = o3d.geometry.TriangleMesh.create_box(0.08, 0.06, 0.05).translate((-0.06, -0.03, 0.0))
    box2 = o3d.geometry.TriangleMesh.create_box(0.04, 0.04, 0.03).translate((0.05, 0.02, 0.0))
    mesh = slab + box + box2
    vertices, triangles = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    start = 1_700_000_000_000_000_000
    a = VirtualSource(vertices, triangles, VirtualCameraConfig(
        INTRINSICS, turntable=circle_turntable(np.zeros(3), 0.25, 0.3), views=4, sensor_id="a", start_ns=start))
    poses = tuple(look_at(np.array([x, 0.05, 0.35]), np.zeros(3)) for x in (-0.1, 0.0, 0.1))
    b = VirtualSource(vertices, triangles, VirtualCameraConfig(
        INTRINSICS, poses=poses, sensor_id="b", start_ns=start + 33_333_333, seed=1))
    b_frames = []
    for i, frame in enumerate(b):
        shade = (frame.depth >> 6).astype(np.uint8)
        color = np.stack([shade, 255 - shade, np.full_like(shade, 40 * i)], -1)
        b_frames.append(dataclasses.replace(frame, color=color,
                                            T_world_camera=None if i == len(poses) - 1 else frame.T_world_camera))
    return sorted(list(a) + b_frames, key=lambda f: f.timestamp_ns)


def assert_same_frames(replayed, expected):
    assert len(replayed) == len(expected)
    for got, want in zip(replayed, expected):
        assert got.depth.dtype == np.uint16 and got.depth.flags.writeable and np.array_equal(got.depth, want.depth)
        assert (got.depth_scale, got.intrinsics, got.timestamp_ns, got.sensor_id, got.turntable_angle) == \
               (want.depth_scale, want.intrinsics, want.timestamp_ns, want.sensor_id, want.turntable_angle)
        assert (got.color is None) == (want.color is None)
        if want.color is not None:
            assert got.color.dtype == np.uint8 and np.array_equal(got.color, want.color)
        assert (got.T_world_camera is None) == (want.T_world_camera is None)
        if want.T_world_camera is not None:
            assert np.array_equal(got.T_world_camera, want.T_world_camera)


def test_record_then_replay_is_bit_exact(tmp_path, frames):
    path = tmp_path / "session.mcap"
    summary = record(ListSource(frames), path, progress=False)
    assert (summary.frames, summary.bytes, summary.stopped_by) == (len(frames), path.stat().st_size, "end")
    assert not (tmp_path / "session.mcap.partial").exists()
    with McapSource(path) as source:
        replayed = list(source)
        assert source.read() is None and not source.truncated and source.sensor_ids == ["a", "b"]
    assert [f.sensor_id for f in replayed] == ["a", "b", "a", "b", "a", "b", "a"]
    assert_same_frames(replayed, frames)


def test_replay_is_in_log_time_order_whatever_the_write_order(tmp_path, frames):
    path = tmp_path / "by_sensor.mcap"
    with McapRecorder(path, compression="lz4") as recorder:
        for frame in sorted(frames, key=lambda f: f.sensor_id):
            recorder.write(frame)
    assert_same_frames(list(McapSource(path)), frames)


def test_plain_mcap_reader_sees_foxglove_topics_and_schemas(tmp_path, frames):
    path = tmp_path / "layout.mcap"
    with McapRecorder(path) as recorder:
        for frame in frames:
            recorder.write(frame)
        t = frames[-1].timestamp_ns
        recorder.write_json("/perception/mushrooms_json", {"mushrooms": [{"id": 0, "center": np.zeros(3)}]}, t)
        recorder.write_point_cloud("/fusion/cloud", np.arange(12, dtype=np.float32).reshape(4, 3), t)
    with open(path, "rb") as file:
        reader = make_reader(file, decoder_factories=[DecoderFactory(), Ros2DecoderFactory()])
        summary = reader.get_summary()
        channels = {c.topic: c for c in summary.channels.values()}
        schema = {topic: summary.schemas[c.schema_id].name for topic, c in channels.items()}
        counts = {topic: summary.statistics.channel_message_counts[c.id] for topic, c in channels.items()}
        assert {topic: schema[topic] for topic in channels
                if not topic.endswith(("/meta", "_json")) and topic != "/session"} == {
            "/camera/a/depth": "sensor_msgs/msg/Image", "/camera/b/depth": "sensor_msgs/msg/Image",
            "/camera/b/color": "foxglove.RawImage", "/camera/a/calibration": "foxglove.CameraCalibration",
            "/camera/b/calibration": "foxglove.CameraCalibration", "/tf": "foxglove.FrameTransforms",
            "/fusion/cloud": "foxglove.PointCloud"}
        assert {"/camera/a/meta", "/camera/b/meta", "/perception/mushrooms_json"} <= channels.keys()
        assert channels["/camera/a/meta"].message_encoding == channels["/session"].message_encoding == "json"
        assert counts["/session"] == 1
        assert counts["/camera/a/depth"] == 4 and counts["/camera/b/color"] == 3 and counts["/tf"] == 6

        by_time = {(f"camera/{f.sensor_id}", f.timestamp_ns): f for f in frames}
        seen = set()
        for schema_record, channel, message, decoded in reader.iter_decoded_messages(
                topics=["/camera/a/depth", "/camera/b/color", "/camera/b/calibration", "/tf"]):
            if channel.topic == "/tf":
                (transform,) = decoded.transforms
                frame = by_time[(transform.child_frame_id, message.log_time)]
                assert transform.parent_frame_id == "world"
                q = transform.rotation
                np.testing.assert_allclose(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(),
                                           frame.T_world_camera[:3, :3], atol=1e-12)
                t = transform.translation
                assert [t.x, t.y, t.z] == frame.T_world_camera[:3, 3].tolist()
            elif channel.topic.endswith("/depth"):  # a ROS 2 Image, read by mcap-ros2-support
                frame = by_time[(decoded.header.frame_id, message.log_time)]
                assert decoded.header.stamp.sec * 10**9 + decoded.header.stamp.nanosec == message.log_time
                assert (decoded.encoding, decoded.step, decoded.width, decoded.height) == ("16UC1", 320, 160, 120)
                assert decoded.is_bigendian == 0
                assert np.array_equal(np.frombuffer(decoded.data, "<u2").reshape(120, 160), frame.depth)
            else:
                frame = by_time[(decoded.frame_id, message.log_time)]
                assert decoded.timestamp.seconds * 10**9 + decoded.timestamp.nanos == message.log_time
                if channel.topic.endswith("/color"):
                    assert (decoded.encoding, decoded.step) == ("rgb8", 480)
                else:
                    assert list(decoded.K) == INTRINSICS.matrix.ravel().tolist()
                    assert decoded.distortion_model == "plumb_bob" and list(decoded.D) == [0.0] * 5
                    assert list(decoded.P) == [100, 0, 79.5, 0, 0, 100, 59.5, 0, 0, 0, 1, 0]
            seen.add(channel.topic)
        assert len(seen) == 4
    with open(path, "rb") as file:
        messages = {c.topic: m for _, c, m in make_reader(file).iter_messages(
            topics=["/perception/mushrooms_json", "/camera/b/meta"])}
        assert json.loads(messages["/perception/mushrooms_json"].data) == {
            "mushrooms": [{"id": 0, "center": [0.0, 0.0, 0.0]}]}
        assert json.loads(messages["/camera/b/meta"].data)["T_world_camera"] is None


def test_leaving_the_recorder_on_keyboard_interrupt_finalises_the_file(tmp_path, frames):
    path = tmp_path / "interrupted.mcap"
    with pytest.raises(KeyboardInterrupt):
        with McapRecorder(path) as recorder:
            recorder.write(frames[0])
            recorder.write(frames[1])
            assert path.with_name("interrupted.mcap.partial").exists() and not path.exists()
            raise KeyboardInterrupt
    assert not path.with_name("interrupted.mcap.partial").exists()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert_same_frames(list(McapSource(path)), frames[:2])


class _CtrlCWhileFinalising:
    """Stands in for the foxglove writer: a Ctrl-C arrives in the middle of its close()."""

    def __init__(self, writer):
        self._writer = writer

    def close(self):
        signal.raise_signal(signal.SIGINT)
        self._writer.close()


def test_ctrl_c_while_finalising_waits_until_the_file_is_in_place(tmp_path, frames):
    path = tmp_path / "late_ctrl_c.mcap"
    recorder = McapRecorder(path)
    recorder.write(frames[0])
    recorder._writer = _CtrlCWhileFinalising(recorder._writer)
    with pytest.raises(KeyboardInterrupt):
        recorder.close()
    assert path.exists() and not path.with_name("late_ctrl_c.mcap.partial").exists()
    assert len(list(McapSource(path))) == 1


def test_record_stops_after_its_duration(tmp_path):
    summary = record(TickSource(), tmp_path / "timed.mcap", duration_s=0.3, progress=False)
    assert summary.stopped_by == "duration" and 1 <= summary.frames <= 16
    assert len(list(McapSource(tmp_path / "timed.mcap"))) == summary.frames


def test_a_stop_signal_before_the_first_frame_leaves_no_file(tmp_path, monkeypatch):
    import capture.mcap.writer
    from pipeline.signals import graceful_stop

    class SignalledWhileOpening(McapRecorder):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            signal.raise_signal(signal.SIGTERM)

    monkeypatch.setattr(capture.mcap.writer, "McapRecorder", SignalledWhileOpening)
    with pytest.raises(KeyboardInterrupt), graceful_stop() as stop:
        record(TickSource(), tmp_path / "r.mcap", progress=False, stop=stop)
    assert not list(tmp_path.iterdir())


CHILD = """
import signal
import sys
signal.signal(signal.SIGINT, signal.default_int_handler)  # as in an interactive shell, even if started ignoring it
sys.path.insert(0, {tests!r})
from test_mcap_io import TickSource
from capture.mcap.writer import record
from pipeline.signals import graceful_stop

def progress(count, frame):
    print("wrote", count, flush=True)

with graceful_stop() as stop:
    summary = record(TickSource(), {path!r}, progress=False, on_frame=progress, stop=stop)
print("done", summary.frames, summary.stopped_by, flush=True)
"""


@pytest.mark.parametrize("stop", [signal.SIGTERM, signal.SIGINT], ids=lambda s: s.name)
def test_a_stop_signal_leaves_a_finalised_file_with_every_written_frame(tmp_path, stop):
    path = tmp_path / "live.mcap"
    script = CHILD.format(tests=str(REPO / "tests"), path=str(path))
    child = subprocess.Popen([sys.executable, "-c", script], cwd=REPO, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)
    watchdog = threading.Timer(60, child.kill)
    watchdog.start()
    try:
        for line in child.stdout:
            if line.split() == ["wrote", "3"]:
                break
        child.send_signal(stop)
        output = child.stdout.read()
        child.wait(timeout=60)
    finally:
        watchdog.cancel()
        child.kill()
        child.stdout.close()
    lines = [line.split() for line in output.splitlines()]
    partial = path.with_name("live.mcap.partial")
    assert child.returncode == 0, output
    written = max([3] + [int(words[1]) for words in lines if words[:1] == ["wrote"]])
    assert [words for words in lines if words[:1] == ["done"]] == [["done", str(written), stop.name]], output
    assert path.exists() and not partial.exists()
    with open(path, "rb") as file:
        assert make_reader(file).get_summary() is not None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        replayed = list(McapSource(path))
    assert [f.timestamp_ns for f in replayed] == [20_000_000 * (i + 1) for i in range(written)]
    assert replayed[-1].depth[0, 0] == 1000 + written and replayed[-1].turntable_angle == 0.01 * written


KILLED_CHILD = """
import functools
import sys
import threading
sys.path.insert(0, {tests!r})
import capture.mcap.writer
from test_mcap_io import TickSource
capture.mcap.writer.McapRecorder = functools.partial(capture.mcap.writer.McapRecorder, chunk_size={chunk_size})

class Stalls(TickSource):
    def read(self):
        if self.count == {frames}:
            threading.Event().wait()  # a camera that stops delivering: record waits here until killed
        return super().read()

capture.mcap.writer.record(Stalls(), {path!r}, progress=False,
                           on_frame=lambda count, frame: print("wrote", count, flush=True))
"""


def _frames_in_closed_chunks(path, frames: int) -> int:
    """Of the frames in a finalised recording, those whose every message lies in a chunk other than the
    file's last one."""
    from mcap.records import Channel, Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    parts, chunks, topics = collections.Counter(), [], {}
    with open(path, "rb") as file:
        for item in StreamReader(file, emit_chunks=True).records:
            if isinstance(item, Chunk):
                chunks.append(breakup_chunk(item))
            elif isinstance(item, Channel):
                topics[item.id] = item.topic
    for chunk in chunks:
        topics.update({item.id: item.topic for item in chunk if isinstance(item, Channel)})
    for chunk in chunks[:-1]:
        for item in chunk:
            if isinstance(item, Message) and topics[item.channel_id] != "/session":  # a frame's own messages
                parts[item.log_time] += 1
    # TickSource's frames have no colour and no pose: depth, calibration and meta
    assert len(chunks) > 2 and sum(parts.values()) < 3 * frames
    return sum(parts[20_000_000 * (k + 1)] == 3 for k in range(frames))


def test_a_killed_recording_keeps_every_frame_of_its_closed_chunks(tmp_path):
    """SIGKILL while the camera stalls after 10 frames: the .partial file replays exactly the frames
    whose messages were in chunks already written. Which those are is read off the same 10 frames
    recorded here with the same 20 kB chunks and closed: foxglove's writer closes a chunk (and writes
    it out) when the next message finds it full, so every chunk but the last one was on disk before the
    kill and the last one was still open (measured: with 1-byte chunks a kill loses only the last message)."""
    frames, chunk_size = 10, 20_000  # about 3 frames of 6.5 kB a chunk
    reference = tmp_path / "reference.mcap"
    source = TickSource()
    with McapRecorder(reference, chunk_size=chunk_size) as recorder:
        for _ in range(frames):
            recorder.write(source.read())
    expected = _frames_in_closed_chunks(reference, frames)
    assert 0 < expected < frames  # 8: frames 9 and 10 end in the last chunk

    path = tmp_path / "killed.mcap"
    script = KILLED_CHILD.format(tests=str(REPO / "tests"), path=str(path), chunk_size=chunk_size, frames=frames)
    child = subprocess.Popen([sys.executable, "-c", script], cwd=REPO, stdout=subprocess.PIPE, text=True)
    watchdog = threading.Timer(60, child.kill)
    watchdog.start()
    try:
        for line in child.stdout:
            if line.split() == ["wrote", str(frames)]:
                break  # every frame is written; the camera stalls
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=60)
    finally:
        watchdog.cancel()
        child.kill()
        child.stdout.close()
    assert child.returncode == -signal.SIGKILL
    partial = path.with_name("killed.mcap.partial")
    assert not path.exists() and partial.exists()
    with pytest.warns(TruncatedRecordingWarning):
        replayed = list(McapSource(partial))
    assert_same_frames(replayed, list(McapSource(reference))[:expected])


def test_a_truncated_recording_replays_a_prefix_with_a_warning(tmp_path, frames):
    path = tmp_path / "whole.mcap"
    with McapRecorder(path, chunk_size=32_000) as recorder:
        for frame in frames:
            recorder.write(frame)
    data = path.read_bytes()
    cut_path = tmp_path / "cut.mcap"
    counts = []
    for cut in (1, 8, 30, len(data) // 4, len(data) // 2, 3 * len(data) // 4, len(data) - 200, len(data) - 1):
        cut_path.write_bytes(data[:cut])
        with pytest.warns(TruncatedRecordingWarning):
            source = McapSource(cut_path)
            replayed = list(source)
        assert source.truncated
        assert_same_frames(replayed, frames[:len(replayed)])
        counts.append(len(replayed))
    assert counts == sorted(counts) and counts[0] == 0 and counts[-1] == len(frames)
    assert any(0 < count < len(frames) for count in counts)


def test_bad_input_gives_one_line_errors(tmp_path):
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording\n")
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    no_depth = tmp_path / "results.mcap"
    with McapRecorder(no_depth) as recorder:
        recorder.write_json("/perception/mushrooms_json", {"mushrooms": []}, 1)
    cases = {text: "is not an MCAP file", tmp_path / "missing.mcap": "does not exist", empty: "is empty",
             no_depth: "has no depth topics (/camera/<id>/depth)"}
    for path, message in cases.items():
        with pytest.raises(SourceError) as error:
            McapSource(path).read()
        assert message in str(error.value) and str(path) in str(error.value) and "\n" not in str(error.value)


def test_recorder_refuses_what_it_cannot_store_faithfully(tmp_path, frames):
    path = tmp_path / "strict.mcap"
    with McapRecorder(path) as recorder:
        recorder.write(frames[0])
        with pytest.raises(ValueError, match="does not follow"):
            recorder.write(frames[0])
        with pytest.raises(ValueError, match="uint8"):
            recorder.write(dataclasses.replace(frames[2], color=np.zeros((120, 160, 3), np.float32)))
        with pytest.raises(ValueError, match=r"\(N, 3\)"):
            recorder.write_point_cloud("/fusion/cloud", np.zeros((4, 2)), 0)
    with pytest.raises(FileExistsError):
        McapRecorder(path)
    assert len(list(McapSource(path))) == 1


def _rerun_mcap_convert():
    rerun = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    if rerun is None:
        return None
    probe = subprocess.run([rerun, "mcap", "convert", "--help"], capture_output=True, timeout=60)
    return rerun if probe.returncode == 0 else None


def test_rerun_cli_converts_a_recording_to_rrd(tmp_path, frames):
    rerun = _rerun_mcap_convert()
    if rerun is None:
        pytest.skip("the rerun CLI (rerun-sdk wheel) with `rerun mcap convert` is not installed")
    from helpers import rrd_entity_rows, rrd_values

    path, rrd = tmp_path / "view.mcap", tmp_path / "view.rrd"
    record(ListSource(frames), path, progress=False)
    subprocess.run([rerun, "mcap", "convert", str(path), "-o", str(rrd), "--application-id", "mushroom_pose_test"],
                   check=True, capture_output=True, timeout=120)
    rows = rrd_entity_rows(rrd)
    assert rows["/camera/a/depth"] >= 4 and rows["/camera/b/color"] >= 3 and rows["/tf"] >= 6
    # depth comes in as a depth image (drawn with a colour map), each with the frame's own pixels
    depths = rrd_values(rrd, "/camera/a/depth", "DepthImage:buffer")
    expected = [f.depth for f in frames if f.sensor_id == "a"]
    assert len(depths) == len(expected)
    for (_, buffer), depth in zip(depths, expected):
        assert np.array_equal(np.asarray(buffer[0], np.uint8).view("<u2").reshape(depth.shape), depth)
    assert len(rrd_values(rrd, "/camera/b/color", "Image:buffer")) == 3


def test_a_session_whose_depth_is_a_foxglove_raw_image_is_read(tmp_path):
    """Sessions may carry depth as a foxglove.RawImage (16UC1), as every channel but depth is: the
    reader takes either schema."""
    import foxglove
    from foxglove.channels import CameraCalibrationChannel, RawImageChannel
    from foxglove.messages import CameraCalibration, RawImage, Timestamp

    depth = np.arange(120 * 160, dtype=np.uint16).reshape(120, 160)
    path, t = tmp_path / "raw-image.mcap", 1_700_000_000_123_456_789
    stamp = Timestamp(sec=t // 10**9, nsec=t % 10**9)
    writer = foxglove.open_mcap(str(path))
    RawImageChannel("/camera/x/depth").log(RawImage(timestamp=stamp, frame_id="camera/x", width=160, height=120,
                                                    encoding="16UC1", step=320, data=depth.tobytes()), log_time=t)
    CameraCalibrationChannel("/camera/x/calibration").log(CameraCalibration(
        timestamp=stamp, frame_id="camera/x", width=160, height=120,
        K=[float(v) for v in INTRINSICS.matrix.ravel()]), log_time=t)
    meta = {"timestamp_ns": t, "depth_scale": 1e-4, "turntable_angle": None, "T_world_camera": None,
            "has_color": False}
    foxglove.Channel("/camera/x/meta", schema={"type": "object"}).log(json.dumps(meta).encode(), log_time=t)
    writer.close()
    (frame,) = list(McapSource(path))
    assert np.array_equal(frame.depth, depth) and frame.timestamp_ns == t and frame.intrinsics == INTRINSICS


def test_a_session_says_which_bed_it_scans_and_when_it_began(tmp_path, frames):
    from capture.mcap.reader import read_session_info

    path = tmp_path / "bed.mcap"
    with McapRecorder(path, bed_id="bay 3, bed 12") as recorder:
        for frame in frames:
            recorder.write(frame)
    first = min(frame.timestamp_ns for frame in frames[:1])
    assert read_session_info(path) == {"bed_id": "bay 3, bed 12", "started_ns": first}
    assert_same_frames(list(McapSource(path)), frames)  # frames read back as they were
