"""replay on the sessions of recordings/: every one gives back its recorded caps (--check), a changed
expectation fails with a readable diff, and the outputs hold frames, fusion and perception."""

import json
import shutil

import numpy as np
import pytest

from capture.mcap.reader import McapSource, read_documents, read_fused_units
from capture.mcap.writer import McapRecorder
from helpers import rrd_entity_rows, rrd_timelines
from pipeline.recordings import RECORDINGS, RECORDINGS_DIR, expected_path
from test_detect_cli import run


@pytest.mark.parametrize("recording", RECORDINGS, ids=lambda r: r.name)
def test_every_recording_replays_to_its_recorded_caps(recording, tmp_path):
    session = RECORDINGS_DIR / recording.file
    assert session.stat().st_size <= 5e6
    result = run("replay", session, "--out", tmp_path, "--check", "--quiet")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "check PASS" in result.stdout
    expected = json.loads(expected_path(session).read_text())
    assert sum(len(d["mushrooms"]) for d in expected) > 0
    if session.suffix == ".mcap":
        assert [d["mushrooms"] for _, d in read_documents(session)] == [d["mushrooms"] for d in expected]


def test_check_fails_with_a_diff_when_a_cap_goes_missing_from_the_expectation(tmp_path):
    session = RECORDINGS_DIR / "turntable-12.mcap"
    expected = json.loads(expected_path(session).read_text())
    removed = expected[0]["mushrooms"].pop(3)
    expected[0]["mushrooms"][0]["radius"] *= 1.2
    (tmp_path / "expected.json").write_text(json.dumps(expected))
    result = run("replay", session, "--out", tmp_path / "out", "--check", "--expected", tmp_path / "expected.json",
                 "--quiet")
    assert result.returncode == 1
    lines = result.stdout.splitlines()
    rows = [line.split() for line in lines[lines.index(next(l for l in lines if l.split()[:2] == ["unit", "expected"])) + 1:-1]]
    gained = [row for row in rows if row[3] == "gained"]
    changed = [row for row in rows if row[3] == "changed"]
    assert len(gained) == 1 and len(changed) == 1
    assert changed[0][1] == str(expected[0]["mushrooms"][0]["id"]) and float(changed[0][6]) == pytest.approx(
        100 * 0.2 / 1.2, abs=1.0)
    assert "check FAIL" in lines[-1] and "1 changed, 0 lost, 1 gained" in lines[-1]
    assert removed["id"] == int(gained[0][2])


def test_replay_writes_the_session_frames_with_new_fusion_and_perception(tmp_path):
    session = RECORDINGS_DIR / "two-cameras.mcap"
    result = run("replay", session, "--out", tmp_path, "--quiet")
    assert result.returncode == 0, result.stderr
    assert "one fused cloud per synchronised set" in result.stdout
    with McapSource(session) as original, McapSource(tmp_path / "replay.mcap") as copy:
        before, after = list(original), list(copy)
    assert len(after) == len(before) == 4
    assert all(np.array_equal(a.depth, b.depth) and a.timestamp_ns == b.timestamp_ns for a, b in zip(before, after))
    units = read_fused_units(tmp_path / "replay.mcap")
    assert len(units) == 2 and all(len(u.frame_ids) == 2 for u in units)
    # the bed frame's z is the bed's up side: the cameras look down at it from above
    for unit in units:
        camera_heights = [(frame.T_world_camera[:3, 3] - unit.T_world_bed[:3, 3]) @ unit.T_world_bed[:3, 2]
                          for frame in before[:2]]
        assert min(camera_heights) > 0.3
    documents = read_documents(tmp_path / "replay.mcap")
    written = json.loads((tmp_path / "detections.json").read_text())
    assert written["mushrooms"] == documents[-1][1]["mushrooms"]
    rows = rrd_entity_rows(tmp_path / "replay.rrd")
    assert rows["/world/camera/cam0/depth"] == 2 and rows["/world/camera/cam1/depth"] == 2
    assert rows["/world/fusion/cloud"] == 2 and rows["/world/perception/mushrooms/ellipsoids"] == 2
    assert rows["/stats/counts/caps"] == 2 and rows["/stats/latency/perception_ms"] == 2
    assert {"frame", "capture"} <= rrd_timelines(tmp_path / "replay.rrd", "/stats/latency/perception_ms")


def test_replay_from_fusion_reads_the_recorded_clouds(tmp_path):
    session = RECORDINGS_DIR / "dense-bed.mcap"
    result = run("replay", session, "--out", tmp_path, "--from-stage", "fusion", "--check", "--quiet")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "check PASS" in result.stdout


def test_a_cut_session_replays_what_is_readable(tmp_path):
    session = RECORDINGS_DIR / "single-view.mcap"
    data = session.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.warns(UserWarning, match="no valid MCAP footer"), McapSource(cut) as readable:
        whole = len(list(readable))
    assert whole == 1
    result = run("replay", cut, "--out", tmp_path / "out", "--quiet")
    assert result.returncode == 0, result.stderr
    assert "cut short" in result.stderr and "replayed 1 frames" in result.stdout
    with McapSource(tmp_path / "out" / "replay.mcap") as replayed:
        assert len(list(replayed)) == 1


@pytest.mark.parametrize("case, fragment", [
    ("garbage", "not an MCAP file"), ("missing", "does not exist"), ("no-detections", "nothing to check against"),
    ("cameras-without-poses", "mushroom-pose calibrate"), ("fusion-without-clouds", "--from-stage capture"),
])
def test_replay_bad_sessions_fail_in_one_line(tmp_path, case, fragment):
    session = tmp_path / "s.mcap"
    args = []
    if case == "garbage":
        session.write_bytes(b"hello, this is not a recording")
    elif case == "missing":
        session = tmp_path / "none.mcap"
    else:
        with McapSource(RECORDINGS_DIR / "two-cameras.mcap") as source:
            frames = list(source)
        if case == "cameras-without-poses":
            from dataclasses import replace

            frames = [replace(f, T_world_camera=None) for f in frames]
        with McapRecorder(session) as recorder:
            for frame in frames:
                recorder.write(frame)
        args = ["--check"] if case == "no-detections" else ["--from-stage", "fusion"] if "fusion" in case else []
    result = run("replay", session, "--out", tmp_path / "out", "--quiet", *args)
    assert result.returncode == 2, result.stdout + result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and fragment in result.stderr


def test_recordings_are_remade_identically(tmp_path, capsys):
    """The maker's recording of a session gives the caps stored in recordings/ (the model and chain are
    those the expectations were made with); a changed expectation would be printed, and an unchanged
    one keeps its session and expectations as they were (a new session's caps would not be the
    expectations kept beside it)."""
    from pipeline.recordings import main

    session = RECORDINGS_DIR / "single-view.mcap"
    kept = b"the session as it was recorded"  # the maker reads only the expectations, never the old session
    (tmp_path / session.name).write_bytes(kept)
    shutil.copy(expected_path(session), tmp_path)
    assert main(["single-view", "--out", str(tmp_path)]) == 0
    assert "expected detections unchanged" in capsys.readouterr().out
    assert expected_path(tmp_path / session.name).read_bytes() == expected_path(session).read_bytes()
    assert (tmp_path / session.name).read_bytes() == kept
    (tmp_path / session.name).unlink()  # expectations without their session: the session is made again
    assert main(["single-view", "--out", str(tmp_path)]) == 0
    assert "new expected detections" in capsys.readouterr().out
    remade = json.loads(expected_path(tmp_path / session.name).read_text())
    assert [d["mushrooms"] for _, d in read_documents(tmp_path / session.name)] == [d["mushrooms"] for d in remade]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([session.name, expected_path(session).name])
