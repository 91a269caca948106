"""The overwrite rule, one for every command: an output that exists is never replaced without
--overwrite; the command stops before any work, in one line that names the file, exit status 2."""

import contextlib
import io
import json
from pathlib import Path

import pytest

from helpers import write_tiny_weights

RECORDINGS = Path(__file__).resolve().parents[1] / "recordings"


def run(*args) -> tuple[int, str]:
    from pipeline.cli import main

    stderr = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(stderr):
        code = main([str(a) for a in args])
    return code, stderr.getvalue()


def _cloud(tmp_path: Path) -> Path:
    from perception.synthetic.dataset import write_ply
    from perception.synthetic.scene import SceneConfig, generate_scene

    path = tmp_path / "bed.ply"
    write_ply(generate_scene(1, SceneConfig(mushrooms=(4, 4))), path)
    return path


CASES = {
    "detect": lambda t, w: (["detect", _cloud(t), "--model", w, "--out", t / "taken.json"], t / "taken.json"),
    "eval": lambda t, w: (["eval", "--model", w, "--scenes", 1, "--json", t / "taken.json"], t / "taken.json"),
    "synth": lambda t, w: (["synth", "--scenes", 2, "--out", t, "--quiet"], t / "scene_0001.npz"),
    "average": lambda t, w: (["average", w, w, "--out", t / "taken.pt"], t / "taken.pt"),
    "calibrate": lambda t, w: (["calibrate", "--session", RECORDINGS / "turntable-12.mcap", "--out", t / "taken.json"],
                               t / "taken.json"),
    "replay": lambda t, w: (["replay", RECORDINGS / "single-view.mcap", "--out", t, "--quiet"], t / "detections.json"),
    "replay many": lambda t, w: (["replay", RECORDINGS / "single-view.mcap", RECORDINGS / "dense-bed.mcap", "--out", t],
                                 t / "report.json"),
    "live": lambda t, w: (["live", "--camera", "virtual", "--turns", 1, "--rrd", t / "taken.rrd"], t / "taken.rrd"),
    "record": lambda t, w: (["record", "--camera", "virtual", "--out", t / "taken.mcap"], t / "taken.mcap"),
    "demo": lambda t, w: (["demo", "--out", t, "--quiet"], t / "demo.rrd"),
}


@pytest.mark.parametrize("command", CASES)
def test_an_existing_output_is_kept_without_overwrite(tmp_path, command):
    (tmp_path / "weights").mkdir()
    weights = write_tiny_weights(tmp_path / "weights" / "tiny.pt")
    args, taken = CASES[command](tmp_path, weights)
    taken.write_bytes(b"the user's")
    code, stderr = run(*args)
    assert code == 2
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and f"{taken} exists: pass --overwrite" in lines[0], stderr
    assert taken.read_bytes() == b"the user's"
    assert not [p for p in tmp_path.rglob("*") if "partial" in p.name]


def test_overwrite_replaces_the_output(tmp_path):
    weights = write_tiny_weights(tmp_path / "tiny.pt")
    out = tmp_path / "taken.json"
    out.write_text("the user's")
    assert run("detect", _cloud(tmp_path), "--model", weights, "--out", out, "--overwrite")[0] == 0
    assert json.loads(out.read_text())["frame"] == "input"
