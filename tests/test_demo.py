"""``mushroom-pose demo``: the chain from virtual camera to detections, with its files."""

import json

import numpy as np
import pytest

from capture.mcap_io import McapSource, read_point_cloud
from helpers import rrd_entity_rows, write_tiny_weights
from test_detect_cli import run


@pytest.fixture(scope="module")
def tiny_weights(tmp_path_factory):
    return write_tiny_weights(tmp_path_factory.mktemp("model") / "tiny.pt")


def test_demo_records_fuses_detects_and_logs(tmp_path, tiny_weights):
    result = run("demo", "--out", tmp_path / "demo", "--views", 4, "--model", tiny_weights, "--quiet")
    assert result.returncode == 0, result.stderr
    out = tmp_path / "demo"
    assert sorted(p.name for p in out.iterdir()) == ["demo.rrd", "detections.json",
                                                     "session.mcap"]
    document = json.loads((out / "detections.json").read_text())
    assert document["frame"] == "world" and isinstance(document["mushrooms"], list)
    with McapSource(out / "session.mcap") as replay:
        frames = list(replay)
    assert len(frames) == 4 and all(f.T_world_camera is not None for f in frames)
    cloud, frame_id = read_point_cloud(out / "session.mcap")
    assert frame_id == "world" and len(cloud) > 10000 and np.isfinite(cloud).all()
    rows = rrd_entity_rows(out / "demo.rrd")
    assert rows["/world/fusion/cloud"] == 1 and rows["/world/camera/virtual/depth"] == 4
    assert "AP@25" in result.stdout and "caps found" in result.stdout


def test_demo_with_a_missing_model_file_fails_in_one_line(tmp_path):
    result = run("demo", "--out", tmp_path / "demo", "--model", tmp_path / "missing.pt")
    assert result.returncode == 2 and "does not exist" in result.stderr


def test_a_failed_demo_leaves_the_folder_as_it_was(tmp_path, tiny_weights, monkeypatch):
    import perception.detect

    out = tmp_path / "demo"
    out.mkdir()
    (out / "detections.json").write_text("{}")

    def broken(*args, **kwargs):
        raise ValueError("the network broke")

    monkeypatch.setattr(perception.detect, "detect_points", broken)
    result = run("demo", "--out", out, "--views", 2, "--model", tiny_weights, "--quiet")
    assert result.returncode == 2 and result.stderr.strip() == "mushroom-pose demo: error: the network broke"
    assert sorted(p.name for p in out.iterdir()) == ["detections.json"]
    assert (out / "detections.json").read_text() == "{}"


def test_demo_into_a_file_is_refused(tmp_path, tiny_weights):
    target = tmp_path / "taken"
    target.write_text("keep me")
    result = run("demo", "--out", target, "--model", tiny_weights)
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1
    assert target.read_text() == "keep me"
