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
    from pipeline.cli import build_parser
    from pipeline.commands.train import train_config
    from perception.train import TrainConfig

    parse = build_parser().parse_args
    default = train_config(parse(["train", "--out", "RUN"]))
    assert default == TrainConfig()
    tuned = train_config(parse(["train", "--out", "RUN", "--weight-existence", "2", "--weight-residual", "50",
                                "--weight-orientation", "10", "--orientation-on-caps", "--cap-balance",
                                "--scale-jitter", "1.0", "1.2", "--milestones", "0.75", "0.9",
                                "--average-from", "0.5", "--zoom", "1.1"]))
    assert (tuned.weight_existence, tuned.weight_residual, tuned.weight_orientation, tuned.orientation_on_caps,
            tuned.cap_balance, tuned.scale_jitter, tuned.milestones, tuned.average_from, tuned.zoom) == (
        2.0, 50.0, 10.0, True, True, (1.0, 1.2), (0.75, 0.9), 0.5, 1.1)
    with pytest.raises(SystemExit) as refused:
        parse(["train", "--out", "RUN", "--zoom", "3"])
    assert refused.value.code == 2
    spaced = train_config(parse(["train", "--out", "RUN", "--spacing", "0.004"]))
    assert spaced.scene.spacing == 0.004 and spaced.scene == type(default.scene)(spacing=0.004)


def test_every_train_config_field_is_a_flag():
    from pipeline.cli import build_parser
    from pipeline.commands.train import train_config
    from perception.synthetic.scene import SceneConfig
    from perception.train import TrainConfig

    parse = build_parser().parse_args
    config = train_config(parse([
        "train", "--out", "RUN", "--iterations", "7", "--lr", "0.01", "--milestones", "0.5", "--gamma", "0.5",
        "--weight-existence", "2", "--weight-residual", "3", "--weight-orientation", "4", "--orientation-on-caps",
        "--cap-balance", "--average-from", "0.9", "--init", "start.pt", "--zoom", "1.2", "--network", "slim",
        "--seed", "5", "--checkpoint-every", "6", "--validate-every", "8", "--validation-scenes", "0",
        "--queue-size", "2", "--no-rotate-z", "--scale-jitter", "1", "1.3", "--point-dropout", "0.1", "0.3",
        "--tilt-deg", "0", "--noise", "0", "--cap-scale", "0.7", "1.2", "--spacing", "0.004",
        "--spacing-jitter", "0.9", "1.1", "--cap-height", "0.4", "1.1", "--cluster-probability", "0.6",
        "--views", "1", "4", "--cluster-spacing", "0.6", "1.1", "--visibility", "fused",
        "--fused-share", "0.3", "--stereo-share", "0.5", "--soil-holes", "0.1", "0.4", "--soil-lumps", "2", "9",
        "--soil-banks", "1", "5"]))
    changed = {name for name, value in vars(config).items() if value != getattr(TrainConfig(), name)}
    assert changed == set(vars(config)), set(vars(config)) - changed
    assert config.init_weights.endswith("/start.pt") and config.point_dropout == (0.1, 0.3)
    assert config.scene == SceneConfig(spacing=0.004, scale=(0.7, 1.2), jitter=(0.9, 1.1), cap_height=(0.4, 1.1),
                                       cluster_probability=0.6, views=(1, 4), cluster_spacing=(0.6, 1.1),
                                       visibility="fused", soil_holes=(0.1, 0.4), soil_lumps=(2, 9),
                                       soil_banks=(1, 5))


def test_config_flags_are_read_from_the_source_as_the_dataclass_has_them():
    import dataclasses

    from pipeline.check import Tolerances
    from pipeline.flags import NO_DEFAULT, config_fields
    from perception.synthetic.scene import SceneConfig
    from perception.train import TrainConfig

    for reference, config in [("perception.train:TrainConfig", TrainConfig),
                              ("perception.synthetic.scene:SceneConfig", SceneConfig),
                              ("pipeline.check:Tolerances", Tolerances)]:
        read = {field.name: field.default for field in config_fields(reference)}
        assert list(read) == [field.name for field in dataclasses.fields(config)]
        for field in dataclasses.fields(config):
            if field.default is not dataclasses.MISSING:
                assert read[field.name] == field.default, (reference, field.name)
            else:
                assert read[field.name] is NO_DEFAULT
    assert all(field.doc for field in config_fields("perception.train:TrainConfig"))


def test_config_flags_of_every_supported_type(tmp_path, monkeypatch, capsys):
    import argparse

    from pipeline.flags import add_config_flags, config_from_args

    (tmp_path / "flag_example.py").write_text('''
from __future__ import annotations
from dataclasses import dataclass, field
from typing import Literal


@dataclass(frozen=True)
class Example:
    count: int = 3
    """How many, 100% of them."""
    rate: float = 0.5
    name: str = "a"
    on: bool = True
    """Whether it runs."""
    limit: float | None = None
    steps: tuple[float, ...] = (0.1, 0.2)
    pair: tuple[int, int] = (1, 2)
    mode: Literal["fast", "slow"] = "fast"
    """``count`` times."""
    kept: int = field(default=4, metadata={"unit": "mm"})
    nested: dict = field(default_factory=dict)
''')
    monkeypatch.syspath_prepend(str(tmp_path))
    import flag_example

    parser = argparse.ArgumentParser()
    add_config_flags(parser, "flag_example:Example", {"rate": {"name": "speed", "help": "How fast."}},
                     exclude=("nested",), prefix="x_")
    assert config_from_args(flag_example.Example, parser.parse_args([]), prefix="x_") == flag_example.Example()
    args = parser.parse_args(["--x-count", "5", "--speed", "2", "--x-name", "b", "--no-x-on", "--x-limit", "1",
                              "--x-steps", "0.3", "--x-pair", "7", "8", "--x-mode", "slow", "--x-kept", "9"])
    assert config_from_args(flag_example.Example, args, prefix="x_", nested={"k": 1}) == flag_example.Example(
        5, 2.0, "b", False, 1.0, (0.3,), (7, 8), "slow", 9, {"k": 1})
    parser.print_help()
    shown = " ".join(capsys.readouterr().out.split())
    assert "How many, 100% of them. (default: 3)" in shown and "How fast. (default: 0.5)" in shown
    assert "--x-on, --no-x-on Whether it runs. (default: --x-on)" in shown
    assert "--x-mode {fast,slow} --x-count times. (default: fast)" in shown
    with pytest.raises(TypeError, match="nested"):
        add_config_flags(argparse.ArgumentParser(), "flag_example:Example")
    with pytest.raises(TypeError, match="unknown flag options"):
        add_config_flags(argparse.ArgumentParser(), "flag_example:Example", {"rate": {"type": float}})
    with pytest.raises(SystemExit):
        parser.parse_args(["--x-mode", "medium"])


def test_the_parser_restates_its_choices_as_the_libraries_define_them():
    from perception.synthetic.scene import VISIBILITY_MODELS
    from pipeline.commands.common import FILE_READINGS, MAX_READINGS, SHIPPED_ZOOM, SPACING_HELP, VISIBILITY
    from perception import detect
    from perception.weights import DEFAULT_WEIGHTS
    from perception.synthetic.scene import SceneConfig
    from perception.weights import load_weights

    assert VISIBILITY == VISIBILITY_MODELS
    assert SPACING_HELP.startswith(f"{SceneConfig.spacing:g},")
    assert SHIPPED_ZOOM == load_weights(DEFAULT_WEIGHTS)[0].inference_zoom
    from pipeline.replay import ReplayOptions
    from pipeline.runner import PerceptionStage

    assert FILE_READINGS == detect.FILE_READINGS
    assert detect.LIVE_READINGS == PerceptionStage.readings  # the runner reads as the library does
    assert ReplayOptions.readings_as_recorded  # a replay reads as often as the session's detections say
    assert MAX_READINGS == detect.MAX_READINGS
    from perception.grades import GradeTable
    from pipeline.commands.common import DEFAULT_GRADES_HELP

    assert DEFAULT_GRADES_HELP == ", ".join(f"{grade.name} from {grade.from_mm:g}" + (" mm" if k == 0 else "")
                                            for k, grade in enumerate(GradeTable().grades))


def test_building_the_parser_imports_no_heavy_library():
    code = ("import sys; from pipeline.cli import build_parser; build_parser(); "
            "print(sorted(m for m in ('numpy', 'torch', 'open3d', 'rerun') if m in sys.modules))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stdout.strip() == "[]", result.stderr


def test_a_spacing_in_millimetres_or_too_fine_gives_one_line_and_exit_2(tmp_path):
    for command in (["train", "--out", str(tmp_path / "run")], ["eval"], ["synth", "--out", str(tmp_path / "s")]):
        for spacing in ("3", "1e-9"):
            result = run(*command, "--spacing", spacing)
            assert result.returncode == 2 and "Traceback" not in result.stderr
            lines = result.stderr.strip().splitlines()
            assert len(lines) == 1 and "--spacing" in lines[0] and "0.003 is 3 mm" in lines[0], result.stderr
    assert not (tmp_path / "run").exists() and not (tmp_path / "s").exists()


@pytest.mark.parametrize("flag,low,high", [(flag, "0.3", "0.2") for flag in (
    "--scale-jitter", "--point-dropout", "--cap-scale", "--spacing-jitter", "--cap-height", "--cluster-spacing",
    "--soil-holes")] + [("--views", "3", "2"), ("--soil-lumps", "5", "2"),
                                  ("--soil-banks", "5", "2")])
def test_a_range_upside_down_gives_one_line_and_exit_2(tmp_path, capsys, flag, low, high):
    from pipeline.cli import main

    assert main(["train", "--out", str(tmp_path / "run"), flag, low, high]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and f"{flag} wants LOW HIGH with LOW <= HIGH" in lines[0], lines
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("flags,message", [(["--visibility", "sonar"], "unknown visibility model 'sonar'"),
                                           (["--visibility", "camera", "--views", "1", "3"], "hpr or fused")])
def test_scene_flags_that_make_no_scene_give_one_line_and_exit_2(tmp_path, capsys, flags, message):
    from pipeline.cli import main

    assert main(["train", "--out", str(tmp_path / "run"), *flags]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], lines
    assert not (tmp_path / "run").exists()


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
    (["train", "--out", "OUT", "--gamma", "0"], "must be positive"),
    (["train", "--out", "OUT", "--noise", "-0.001"], "must not be negative"),
    (["train", "--out", "OUT", "--point-dropout", "0", "1"], "a fraction of the points"),
    (["train", "--out", "OUT", "--queue-size", "1000"], "at most 64"),
    (["train", "--out", "OUT", "--network", "huge"], "unknown network 'huge'"),
    (["train", "--out", "OUT", "--rotate-z", "yes"], "unrecognized arguments: yes"),
    (["replay", "OUT.mcap", "--tol-axis-deg", "0"], "must be positive"),
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


def test_files_are_read_four_times_and_the_live_runner_reads_once():
    """detect's and eval's default is FILE_READINGS (eval's None stands for it, so that --table can refuse
    an explicit count); live reads each unit LIVE_READINGS times; replay reads as the session says."""
    from perception.detect import FILE_READINGS, LIVE_READINGS
    from pipeline.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["detect", "bed.ply"]).readings == FILE_READINGS > LIVE_READINGS
    assert parser.parse_args(["eval"]).readings is None
    assert parser.parse_args(["live", "--camera", "virtual"]).readings == LIVE_READINGS
    assert parser.parse_args(["replay", "session.mcap"]).readings is None


def test_a_reader_that_stops_reading_loses_no_output_file(tmp_path):
    """``mushroom-pose ... | head``: stdout closes before the command prints; it still writes its files,
    exits 0 and prints no traceback."""
    from pathlib import Path

    command = [str(Path(sys.executable).with_name("mushroom-pose")), "synth", "--scenes", "1", "--mushrooms", "3", "3",
               "--no-ply", "--quiet", "--out", str(tmp_path / "beds")]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    process.stdout.close()  # the reader is gone before the first line
    stderr = process.stderr.read()
    assert process.wait(timeout=120) == 0, stderr
    assert "Traceback" not in stderr
    assert list((tmp_path / "beds").glob("*.npz"))
