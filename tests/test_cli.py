"""The command line: bad input gives one clear line and a non-zero exit, good input writes what it says."""

import subprocess
import sys

import numpy as np
import pytest
from helpers import rrd_entity_rows

from perception.synthetic.scene import SyntheticScene


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "pipeline.cli", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


@pytest.mark.parametrize("args, message", [
    (["synth", "--scenes", "-3", "--out", "OUT"], "must be positive"),
    (["synth", "--mushrooms", "30", "5", "--out", "OUT"], "inverted"),
    (["synth", "--seed", "-1", "--out", "OUT"], "must not be negative"),
    (["synth", "--out", "FILE/sub"], "cannot create output folder"),
    (["synth", "--visibility", "xray", "--out", "OUT"], "invalid choice"),
])
def test_bad_synth_arguments_give_one_line_and_exit_2(tmp_path, args, message):
    (tmp_path / "FILE").write_text("not a folder")
    args = [a.replace("OUT", str(tmp_path / "out")).replace("FILE", str(tmp_path / "FILE")) for a in args]
    result = run(*args)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], result.stderr


def test_synth_writes_scenes_ply_and_rrd(tmp_path):
    out, rrd = tmp_path / "beds", tmp_path / "beds.rrd"
    result = run("synth", "--scenes", "2", "--seed", "4", "--mushrooms", "6", "9", "--out", str(out),
                 "--rrd", str(rrd), "--quiet")
    assert result.returncode == 0, result.stderr
    scenes = [SyntheticScene.load(p) for p in sorted(out.glob("*.npz"))]
    assert len(scenes) == 2 and len(list(out.glob("*.ply"))) == 2
    total_mushrooms = sum(len(s.centers) for s in scenes)
    assert all(6 <= len(s.centers) <= 9 for s in scenes)
    assert f"scenes: 2  mushrooms: {total_mushrooms} " in result.stdout
    assert f"points: {sum(len(s.points) for s in scenes)} " in result.stdout
    assert not list(tmp_path.glob("*.partial"))
    rows = rrd_entity_rows(rrd)
    assert rows["/world/synthetic/points"] == 2
    assert rows["/world/synthetic/mushrooms/boxes"] == 2 and rows["/world/synthetic/mushrooms/ellipsoids"] == 2


def test_synth_preview_png(tmp_path):
    from pipeline.cli import main

    assert main(["synth", "--scenes", "1", "--out", str(tmp_path), "--no-ply", "--quiet",
                 "--preview", str(tmp_path / "bed.png")]) == 0
    import open3d as o3d

    image = np.asarray(o3d.io.read_image(str(tmp_path / "bed.png")))
    assert image.shape == (600, 960, 3)
    # white caps and brown soil are both in the picture
    assert (image.min(axis=2) > 200).sum() > 500 and ((image[..., 0] > image[..., 2] + 30)).sum() > 10000


def test_train_flags_set_the_loss_weights_and_defaults_are_the_papers():
    from pipeline.cli import build_parser, train_config
    from perception.train import TrainConfig

    parse = build_parser().parse_args
    default = train_config(parse(["train", "--out", "RUN"]))
    paper = TrainConfig()
    assert (default.weight_existence, default.weight_residual, default.weight_orientation,
            default.orientation_on_caps, default.cap_balance, default.scale_jitter, default.milestones,
            default.average_from) == (
        paper.weight_existence, paper.weight_residual, paper.weight_orientation, paper.orientation_on_caps,
        paper.cap_balance, paper.scale_jitter, paper.milestones, paper.average_from)
    tuned = train_config(parse(["train", "--out", "RUN", "--weight-existence", "2", "--weight-residual", "50",
                                "--weight-orientation", "10", "--orientation-on-caps", "--cap-balance",
                                "--scale-jitter", "1.0", "1.2", "--milestones", "0.75", "0.9",
                                "--average-from", "0.5", "--zoom", "1.1"]))
    assert (tuned.weight_existence, tuned.weight_residual, tuned.weight_orientation, tuned.orientation_on_caps,
            tuned.cap_balance, tuned.scale_jitter, tuned.milestones, tuned.average_from, tuned.zoom) == (
        2.0, 50.0, 10.0, True, True, (1.0, 1.2), (0.75, 0.9), 0.5, 1.1)
    assert default.zoom is None
    with pytest.raises(SystemExit) as refused:
        parse(["train", "--out", "RUN", "--zoom", "3"])
    assert refused.value.code == 2
    assert default.scene == paper.scene
    from perception.detect import DEFAULT_WEIGHTS
    from perception.model import INFERENCE_ZOOM
    from perception.train import load_weights
    from pipeline.cli import DEFAULT_ZOOM, SHIPPED_ZOOM, SPACING_HELP
    assert SPACING_HELP.startswith(f"{paper.scene.voxel:g},")
    assert DEFAULT_ZOOM == INFERENCE_ZOOM and SHIPPED_ZOOM == load_weights(DEFAULT_WEIGHTS)[0].inference_zoom
    spaced = train_config(parse(["train", "--out", "RUN", "--spacing", "0.004"]))
    assert spaced.scene.voxel == 0.004 and spaced.scene == type(paper.scene)(voxel=0.004)


def test_a_spacing_in_millimetres_or_too_fine_gives_one_line_and_exit_2(tmp_path):
    for command in (["train", "--out", str(tmp_path / "run")], ["eval"], ["synth", "--out", str(tmp_path / "s")]):
        for spacing in ("3", "1e-9"):
            result = run(*command, "--spacing", spacing)
            assert result.returncode == 2 and "Traceback" not in result.stderr
            lines = result.stderr.strip().splitlines()
            assert len(lines) == 1 and "--spacing" in lines[0] and "0.003 is 3 mm" in lines[0], result.stderr
    assert not (tmp_path / "run").exists() and not (tmp_path / "s").exists()


def test_a_scale_jitter_upside_down_gives_one_line_and_exit_2(tmp_path):
    result = run("train", "--out", str(tmp_path / "run"), "--scale-jitter", "1.2", "1.0")
    assert result.returncode != 0 and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "--scale-jitter" in lines[0], result.stderr
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


def test_milestones_out_of_order_give_one_line_and_exit_2(tmp_path):
    result = run("train", "--out", str(tmp_path / "run"), "--milestones", "0.8", "0.6")
    assert result.returncode != 0 and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "--milestones must increase" in lines[0], result.stderr
    assert not (tmp_path / "run").exists()


def test_averaging_that_leaves_no_iteration_gives_one_line_and_exit_2(tmp_path):
    result = run("train", "--out", str(tmp_path / "run"), "--iterations", "10", "--average-from", "1")
    assert result.returncode != 0 and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "--average-from 1.0 leaves no iteration" in lines[0], result.stderr
    assert not (tmp_path / "run").exists()


def test_a_loss_weight_that_is_not_positive_gives_one_line_and_exit_2(tmp_path):
    result = run("train", "--out", str(tmp_path / "run"), "--weight-existence", "0")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "--weight-existence" in lines[0] and "positive" in lines[0], result.stderr


@pytest.mark.parametrize("args, message", [
    (["synth", "--mushrooms", "5", "100000", "--out", "OUT"], "at most 300"),
    (["train", "--out", "OUT", "--lr", "nan"], "must be a finite number"),
    (["train", "--out", "OUT", "--lr", "2"], "at most 1"),
    (["train", "--out", "OUT", "--milestones", "0.6", "1.5"], "a fraction of the run's iterations"),
    (["synth", "--out", "OUT", "--scenes", "9" * 400], "at most 2147483647"),
    (["train", "--out", "OUT", "--scale-jitter", "1", "inf"], "must be a finite number"),
    (["train", "--out", "OUT", "--seed", "99999999999999999999999"], "below 2^63"),
    (["train", "--out", "OUT", "--threads", "100000"], "4 per core"),
    (["train", "--out", "OUT", "--resume"], "no checkpoint to resume"),
    (["train", "--out", "OUT", "--device", "gpu", "--validation-scenes", "0"], "unknown device"),
    (["record", "--camera", "virtual", "--out", "OUT/r.mcap", "--duration", "inf"], "must be a finite number"),
    (["synth", "--out", "OUT", "--preview", "OUT.txt"], "name it with .png"),
])
def test_bad_numbers_and_runs_give_one_line_and_exit_2(tmp_path, capsys, args, message):
    from pipeline.cli import main

    args = [a.replace("OUT", str(tmp_path / "out")) for a in args]
    try:
        code = main(args)
    except SystemExit as exit_:
        code = exit_.code
    stderr = capsys.readouterr().err
    assert code == 2 and "Traceback" not in stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], stderr
    assert not (tmp_path / "out").exists()


def test_synth_says_when_a_bed_is_full(tmp_path, capsys):
    from pipeline.cli import main

    assert main(["synth", "--scenes", "1", "--mushrooms", "290", "290", "--no-ply", "--quiet",
                 "--out", str(tmp_path)]) == 0
    placed = len(SyntheticScene.load(next(tmp_path.glob("*.npz"))).centers)
    assert placed < 290
    assert "1 of 1 scenes hold fewer than 290 mushrooms" in capsys.readouterr().err
