"""``mushroom-pose track`` on one bed's sessions: scans put in time order, caps keep their ids, growth in
track.json and a scan timeline in track.rrd; sessions of another bed, or of one moment twice, refused."""

import json
import subprocess
import sys

import numpy as np
import pytest

from capture.frames import CameraIntrinsics, DepthFrame
from capture.mcap.schema import DETECTIONS_TOPIC, FUSED_CLOUD_TOPIC, UNIT_TOPIC
from capture.mcap.writer import McapRecorder
from helpers import rrd_entity_rows
from perception.cap import Caps
from perception.synthetic.days import SECONDS_PER_DAY, GrowthConfig, bed_over_days
from perception.synthetic.scene import SceneConfig

START_NS = 1_800_000_000_000_000_000
CONFIG = SceneConfig(mushrooms=(8, 12), spacing=0.004)


def write_session(path, scan, bed_id, started_ns):
    """A session as live records one: a frame, then the unit's fused cloud (world = the scan's frame)
    and its caps (here the true ones)."""
    frame = DepthFrame(np.full((4, 4), 1000, np.uint16), 1e-4, CameraIntrinsics(4, 4, 3.0, 3.0, 1.5, 1.5),
                       started_ns)
    caps = Caps(scan.centers, scan.rotations, scan.scales)
    with McapRecorder(path, bed_id=bed_id) as recorder:
        recorder.write(frame)
        t = started_ns + 1
        recorder.write_point_cloud(FUSED_CLOUD_TOPIC, scan.points, t, "world")
        recorder.write_json(UNIT_TOPIC, {"index": 0, "kind": "turn", "T_world_bed": scan.T_scan_bed.ravel().tolist(),
                                         "frame_ids": []}, t)
        recorder.write_json(DETECTIONS_TOPIC, {**caps.to_document("world", 1), "unit": 0}, t)
    return path


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bed")
    history = bed_over_days(21, CONFIG, GrowthConfig(days=3, pick_probability=0.0))
    paths = [write_session(folder / f"day{scan.day}.mcap", scan, "bay 1",
                           START_NS + int(scan.time_s * 1e9)) for scan in history.scans]
    return history, paths


def run(*args):
    return subprocess.run([sys.executable, "-m", "pipeline.cli", "track", *map(str, args)], capture_output=True,
                          text=True, timeout=300)


def test_track_follows_each_cap_through_the_sessions(tmp_path, sessions):
    history, paths = sessions
    out = tmp_path / "out"
    result = run(paths[2], paths[0], paths[1], "--bed", "bay 1", "--out", out)  # out of time order
    assert result.returncode == 0, result.stderr
    document = json.loads((out / "track.json").read_text())
    assert [scan["session"] for scan in document["scans"]] == ["day0.mcap", "day1.mcap", "day2.mcap"]
    assert [scan["day"] for scan in document["scans"]] == pytest.approx([0.0, 1.0, 2.0])
    diameters = history.diameters_mm
    for cap in document["caps"]:
        truth = [int(history.scans[seen["scan"]].cap_ids[seen["detection"]]) for seen in cap["seen"]]
        assert len(set(truth)) == 1  # one cap throughout
        true_id = truth[0]
        assert [seen["diameter_mm"] for seen in cap["seen"]] == pytest.approx(
            diameters[true_id, [seen["scan"] for seen in cap["seen"]]].tolist())
        if len(cap["seen"]) >= 2:
            assert cap["growth_mm_per_day"] == pytest.approx(history.growth_mm_per_day[true_id], abs=1e-6)
    assert len(document["caps"]) == int((~np.isnan(diameters)).any(1).sum())
    rows = rrd_entity_rows(out / "track.rrd")
    assert rows["/world/track/cloud"] == 3 and rows["/world/track/mushrooms/labels"] == 3


def test_sessions_of_another_bed_or_one_moment_twice_are_refused(tmp_path, sessions):
    history, paths = sessions
    other_id = write_session(tmp_path / "other-id.mcap", history.scans[1], "bay 2", START_NS + 5)
    result = run(paths[0], other_id, "--bed", "bay 1", "--out", tmp_path / "a")
    assert result.returncode == 2 and "scans bed 'bay 2', not 'bay 1'" in result.stderr
    twice = write_session(tmp_path / "again.mcap", history.scans[1], "bay 1", START_NS)
    result = run(paths[0], twice, "--bed", "bay 1", "--out", tmp_path / "b")
    assert result.returncode == 2 and "began at the same moment" in result.stderr
    other_bed = bed_over_days(22, CONFIG, GrowthConfig(days=1)).scans[0]
    stranger = write_session(tmp_path / "stranger.mcap", other_bed, "bay 1", START_NS + 9 * int(SECONDS_PER_DAY * 1e9))
    result = run(paths[0], stranger, "--bed", "bay 1", "--out", tmp_path / "c")
    assert result.returncode == 2 and "are not of one bed" in result.stderr
    for out in ("a", "b", "c"):
        assert not (tmp_path / out / "track.json").exists()
    assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr


def test_the_report_of_a_track_shows_growth_the_ready_caps_and_the_grades_to_come(tmp_path, sessions):
    import re

    _, paths = sessions
    out = tmp_path / "out"
    assert run(*paths, "--bed", "bay 1", "--out", out).returncode == 0
    document = json.loads((out / "track.json").read_text())
    report = tmp_path / "report.html"
    result = subprocess.run([sys.executable, "-m", "pipeline.cli", "report", str(out / "track.json"), "--out",
                             str(report)], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    page = report.read_text()
    assert "Growth of bed bay 1" in page and len(re.findall(r'src="data:image/png;base64,', page)) == 2
    for name, counts in document["forecast"]["grades"].items():
        assert re.search(rf"{re.escape(name)}</td>" + "".join(f"<td>{count}</td>" for count in counts), page)
