"""detect and eval from the command line: clear one-line errors, JSON written only when it is whole."""

import json
import subprocess
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from perception.synthetic.scene import SceneConfig, generate_scene
from helpers import rrd_entity_rows, write_tiny_weights
from perception.grades import GradeTable
from pipeline.clouds import load_cloud


def run(*args):
    """The CLI in this process (fast); returns what a subprocess would."""
    import contextlib
    import io

    from pipeline.cli import main

    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        try:
            code = main([str(a) for a in args])
        except SystemExit as exit_:
            code = exit_.code
    return subprocess.CompletedProcess(args, code, stdout.getvalue(), stderr.getvalue())


def write_ply(path, points):
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    o3d.io.write_point_cloud(str(path), cloud)
    return path


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    return write_tiny_weights(tmp_path_factory.mktemp("model") / "tiny.pt")


@pytest.fixture(scope="module")
def scene_ply(tmp_path_factory):
    scene = generate_scene(1, SceneConfig(mushrooms=(6, 6)))
    return write_ply(tmp_path_factory.mktemp("cloud") / "bed.ply", scene.points), scene


def one_line_error(result, fragment):
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and fragment in lines[0], result.stderr


def test_detect_writes_json_in_the_input_frame(tmp_path, scene_ply):
    """The document's layout (docs/DESIGN.md section 3), with the shipped model; test_detect_truth.py checks
    its values against the truth."""
    ply, scene = scene_ply
    out = tmp_path / "det.json"
    result = run("detect", ply, "--out", out, "--rrd", tmp_path / "det.rrd")
    assert result.returncode == 0, result.stderr
    payload = json.loads(out.read_text())
    assert payload["frame"] == "input" and payload["units"] == "m"
    T = np.array(payload["T_input_bed"])
    # the synthetic bed lies on z = 0 in its own frame, so the found bed normal is close to +z
    assert T[2, 2] > np.cos(np.radians(5))
    assert len(payload["mushrooms"]) == len(scene.centers) == 6  # measured: all 6 found
    assert [m["id"] for m in payload["mushrooms"]] == list(range(6))
    for m in payload["mushrooms"]:
        assert set(m) == {"id", "center", "axis", "rotation", "radius", "height", "cap_diameter_mm", "grade",
                          "score", "uncertain", "num_points"}
        assert m["uncertain"] == (m["score"] < payload["min_score"])
        assert m["grade"] == GradeTable().grade_of([m["cap_diameter_mm"]])[0]
        assert 0 < m["score"] and 0 < m["height"] < m["radius"] and m["num_points"] > 0
    rows = rrd_entity_rows(tmp_path / "det.rrd")
    assert rows["/world/perception/existence"] == 1 and rows["/world/perception/centers"] == 1


def test_detect_reads_the_cloud_as_many_times_as_asked(tmp_path, scene_ply):
    ply, scene = scene_ply
    caps = {}
    for readings in (1, 3):
        result = run("detect", ply, "--out", tmp_path / f"r{readings}.json", "--readings", readings)
        assert result.returncode == 0, result.stderr
        caps[readings] = np.array([m["center"] for m in json.loads((tmp_path / f"r{readings}.json").read_text())
                                   ["mushrooms"]])
    assert len(caps[3]) == len(scene.centers)  # measured: all 6 found either way
    assert not np.array_equal(np.sort(caps[1], 0), np.sort(caps[3], 0))  # the readings reached the network


@pytest.mark.parametrize("case, fragment", [
    ("nan", "NaN or infinite"), ("empty", "empty"), ("missing", "does not exist"), ("format", "unsupported"),
    ("corrupt-model", "not a mushroom-pose weights file"), ("missing-model", "does not exist"),
    ("folder", "is a folder"), ("line", "on a line"), ("far", "does not look like a bed"),
    ("diverged-model", "not finite"), ("ascii-short", "cut short"), ("unreadable", "cannot read"),
])
def test_detect_bad_input(tmp_path, weights, case, fragment):
    cloud = write_ply(tmp_path / "c.ply", np.random.default_rng(0).uniform(-0.2, 0.2, (500, 3)) * [1, 1, 0.05])
    model = weights
    if case == "nan":
        points = np.random.default_rng(0).uniform(size=(100, 3))
        points[5] = np.nan
        np.savez(tmp_path / "nan.npz", points=points)
        cloud = tmp_path / "nan.npz"
    elif case == "empty":
        np.savez(tmp_path / "empty.npz", points=np.zeros((0, 3)))
        cloud = tmp_path / "empty.npz"
    elif case == "missing":
        cloud = tmp_path / "nothing.ply"
    elif case == "format":
        cloud = tmp_path / "cloud.xyz"
        cloud.write_text("0 0 0\n")
    elif case == "corrupt-model":
        model = tmp_path / "bad.pt"
        model.write_bytes(b"not a torch file")
    elif case == "missing-model":
        model = tmp_path / "none.pt"
    elif case == "folder":
        cloud = tmp_path / "clouds.ply"
        cloud.mkdir()
    elif case == "line":
        cloud = write_ply(tmp_path / "line.ply", np.outer(np.linspace(0, 0.3, 500), [1.0, 0.5, 0.0]))
    elif case == "ascii-short":
        cloud = tmp_path / "short.ply"
        cloud.write_text("ply\nformat ascii 1.0\nelement vertex 10\nproperty float x\nproperty float y\n"
                         "property float z\nend_header\n0 0 0\n0.1 0 0\n")
    elif case == "unreadable":  # reading it fails even for root, which any permission would let read
        if not Path("/proc/self/mem").exists():
            pytest.skip("needs /proc/self/mem, a file whose reads fail")
        cloud = tmp_path / "unreadable.ply"
        cloud.symlink_to("/proc/self/mem")
    elif case == "far":
        points = np.random.default_rng(0).uniform(-0.2, 0.2, (500, 3)) * [1, 1, 0.05] + [0.0, 0.0, 500.0]
        np.savez(tmp_path / "far.npz", points=points)
        cloud = tmp_path / "far.npz"
    elif case == "diverged-model":
        import torch

        from perception.weights import load_weights, save_weights

        network, meta = load_weights(weights)
        with torch.no_grad():
            next(network.parameters()).fill_(float("nan"))
        model = tmp_path / "diverged.pt"
        save_weights(network, model, **meta)
    out = tmp_path / "det.json"
    out.write_text("previous result")
    one_line_error(run("detect", cloud, "--model", model, "--out", out, "--overwrite"), fragment)
    assert out.read_text() == "previous result"


def test_a_cut_short_binary_ply_is_refused(tmp_path, weights, scene_ply):
    ply, _ = scene_ply
    data = ply.read_bytes()
    assert data.startswith(b"ply") and b"binary_little_endian" in data[:200]
    cut = tmp_path / "cut.ply"
    cut.write_bytes(data[: len(data) // 2])
    one_line_error(run("detect", cut, "--model", weights, "--out", tmp_path / "d.json"), "is cut short")
    assert len(load_cloud(ply).points) > 0


@pytest.mark.parametrize("name", ["--out", "--rrd"])
def test_an_output_that_is_the_input_is_refused(tmp_path, weights, scene_ply, name):
    ply, _ = scene_ply
    cloud = tmp_path / "bed.ply"
    cloud.write_bytes(ply.read_bytes())
    args = ["--out", tmp_path / "d.json", "--rrd", tmp_path / "d.rrd"]
    args[args.index(name) + 1] = cloud
    one_line_error(run("detect", cloud, "--model", weights, *args), "also an input")
    assert cloud.read_bytes() == ply.read_bytes()


def test_the_model_file_is_not_an_output(tmp_path, weights, scene_ply):
    ply, _ = scene_ply
    model = tmp_path / "model.pt"
    model.write_bytes(weights.read_bytes())
    one_line_error(run("detect", ply, "--model", model, "--out", model), "also an input")
    one_line_error(run("eval", "--model", model, "--json", model, "--scenes", "1"), "also an input")
    assert model.read_bytes() == weights.read_bytes()
    from perception.weights import DEFAULT_WEIGHTS

    shipped = DEFAULT_WEIGHTS.read_bytes()
    one_line_error(run("eval", "--json", DEFAULT_WEIGHTS, "--scenes", "1"), "also an input")
    assert DEFAULT_WEIGHTS.read_bytes() == shipped


def test_outputs_through_links(tmp_path, weights, scene_ply):
    ply, _ = scene_ply
    target = tmp_path / "real.json"
    target.write_text("old")
    (tmp_path / "link.json").symlink_to(target)
    one_line_error(run("detect", ply, "--model", weights, "--out", tmp_path / "link.json"),
                   "real.json exists: pass --overwrite")  # the file a link points to is an output too
    assert target.read_text() == "old"
    assert run("detect", ply, "--model", weights, "--out", tmp_path / "link.json", "--overwrite").returncode == 0
    assert (tmp_path / "link.json").is_symlink() and json.loads(target.read_text())["frame"] == "input"
    (tmp_path / "dangling.json").symlink_to(tmp_path / "far" / "away.json")
    one_line_error(run("detect", ply, "--model", weights, "--out", tmp_path / "dangling.json"), "link to nothing")
    assert not (tmp_path / "far").exists()
    (tmp_path / "loop.json").symlink_to(tmp_path / "loop.json")
    one_line_error(run("detect", ply, "--model", weights, "--out", tmp_path / "loop.json"), "to itself")


@pytest.mark.parametrize("layout", ["one line", "two per line", "comment"])
def test_ply_length_check_reads_the_header_as_the_format_says(tmp_path, layout):
    points = np.random.default_rng(1).uniform(-0.2, 0.2, (50, 3))
    header = "ply\nformat ascii 1.0\n" + ("comment end_header is not the end\n" if layout == "comment" else "")
    header += "element vertex 50\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    per_line = {"one line": 50, "two per line": 2, "comment": 1}[layout]
    rows = [" ".join(f"{v:.6f}" for v in points[i:i + per_line].ravel()) for i in range(0, 50, per_line)]
    path = tmp_path / "p.ply"
    path.write_text(header + "\n".join(rows) + "\n")
    np.testing.assert_allclose(load_cloud(path).points, points, atol=1e-6)
    path.write_text(header + "\n".join(rows[: len(rows) // 2 or 1])[: 200 if per_line == 50 else None] + "\n")
    with pytest.raises(ValueError, match="cut short"):
        load_cloud(path)


@pytest.mark.parametrize("bad_rows, message", [
    ({3: "nan 0.1 0.2 0 0 1", 7: "0.1 inf 0.3 0 0 1"}, "2 of 10 points are NaN or infinite"),
    ({4: "0.1 abc 0.3 0 0 1"}, "'abc' is not a number"),
    ({4: "0.1 1_0 0.3 0 0 1"}, "cannot read point 4's y value '1_0'"),
    ({6: "0.1 0.2 0.3 0 inf 1"}, "cannot read point 6's ny value 'inf'"),
    ({2: "0.1 0.2 0.3 nan nan nan"}, None),
])
def test_an_ascii_ply_value_open3d_cannot_read_is_named(tmp_path, bad_rows, message):
    """Open3D stops at "inf", "1_0" or a word, in any column, and leaves the rest of the cloud unread;
    NaN normals (where none could be estimated) are fine, only the points must be finite."""
    points = np.random.default_rng(2).uniform(size=(10, 3))
    rows = [" ".join(f"{v:.4f}" for v in p) + " 0 0 1" for p in points]
    for index, row in bad_rows.items():
        rows[index] = row
    path = tmp_path / "p.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 10\n"
                    + "".join(f"property float {name}\n" for name in ("x", "y", "z", "nx", "ny", "nz"))
                    + "end_header\n" + "\n".join(rows) + "\n")
    if message is None:
        points[2] = [0.1, 0.2, 0.3]
        np.testing.assert_allclose(load_cloud(path).points, points, atol=1e-4)
        return
    with pytest.raises(ValueError, match=message):
        load_cloud(path)


def test_a_failed_write_leaves_no_temporary_file(tmp_path):
    from pipeline.commands.common import CliError, replace_file as _replace_file

    target = tmp_path / "taken"
    target.mkdir()
    (target / "inside").write_text("x")
    with pytest.raises(CliError, match="cannot write"):
        _replace_file(target, "{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]


def test_a_bed_beyond_the_voxel_grid_is_refused_even_when_forced(tmp_path, weights):
    points = np.random.default_rng(0).uniform(-0.2, 0.2, (500, 3)) * [1, 1, 0.05] + [0.0, 0.0, 500.0]
    np.savez(tmp_path / "far.npz", points=points)
    result = run("detect", tmp_path / "far.npz", "--model", weights, "--out", tmp_path / "d.json", "--force")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    warning, error = result.stderr.strip().splitlines()
    assert warning.startswith("warning:") and "within 10 cm of its dominant plane" in warning
    assert "beyond the voxel grid" in error and not (tmp_path / "d.json").exists()


def test_a_stray_point_does_not_make_a_metre_cloud_millimetres(tmp_path, scene_ply):
    _, scene = scene_ply
    points = np.vstack([scene.points, [[25.0, 0.0, 0.0]]])
    assert load_cloud(write_ply(tmp_path / "stray.ply", points)).units == "m"


def test_fused_clouds_are_read_from_mcap(tmp_path, scene_ply, weights):
    from capture.mcap.writer import McapRecorder

    _, scene = scene_ply
    with McapRecorder(tmp_path / "fused.mcap") as recorder:
        recorder.write_point_cloud("/fusion/cloud", np.zeros((10, 3), np.float32), 1)
        recorder.write_point_cloud("/fusion/cloud", scene.points, 2)
    cloud = load_cloud(tmp_path / "fused.mcap")
    np.testing.assert_array_equal(cloud.points, scene.points.astype(np.float32).astype(np.float64))
    result = run("detect", tmp_path / "fused.mcap", "--model", weights, "--out", tmp_path / "d.json")
    assert result.returncode == 0, result.stderr
    with McapRecorder(tmp_path / "empty.mcap") as recorder:
        recorder.write_json("/other", {"a": 1}, 1)
    one_line_error(run("detect", tmp_path / "empty.mcap", "--model", weights, "--out", tmp_path / "e.json"),
                   "no point cloud on /fusion/cloud")


def test_millimetre_clouds_are_detected_and_converted(tmp_path, scene_ply):
    _, scene = scene_ply
    path = write_ply(tmp_path / "mm.ply", scene.points * 1000)
    cloud = load_cloud(path)
    assert cloud.units == "mm"
    np.testing.assert_allclose(cloud.points, scene.points, atol=1e-6)


def test_a_bare_plane_has_no_caps(tmp_path):
    """The shipped model on a flat 0.4 m patch at 2.5 mm spacing with 0.5 mm noise: no caps (measured:
    none on each of 6 such patches), and detect says so."""
    rng = np.random.default_rng(4)
    plane = np.column_stack([rng.uniform(-0.2, 0.2, (16000, 2)), rng.normal(0, 0.0005, 16000)])
    result = run("detect", write_ply(tmp_path / "plane.ply", plane), "--out", tmp_path / "d.json")
    assert result.returncode == 0, result.stderr
    payload = json.loads((tmp_path / "d.json").read_text())
    assert payload["mushrooms"] == [] and "warning: no caps in 16000 points" in result.stderr


def test_eval_prints_the_table_and_writes_json(tmp_path, weights, monkeypatch):
    monkeypatch.setenv("MUSHROOM_POSE_CACHE", str(tmp_path / "cache"))
    result = run("eval", "--set", "val50", "--scenes", "2", "--model", weights, "--json", tmp_path / "e.json",
                 "--quiet")
    assert result.returncode == 0, result.stderr
    assert "99.57%" in result.stdout and "AP @ IoU 0.50" in result.stdout
    report = json.loads((tmp_path / "e.json").read_text())
    assert set(report["val50"]) == {"meanshift", "dbscan"}
    assert set(report["val50"]["meanshift"]) >= {"ap25", "ap50", "scale_err", "cosine", "angle_deg", "n_gt", "n_pred"}
    assert report["val50"]["meanshift"]["zoom"] == 1.05 and "read at zoom 1.05" in result.stdout  # as the weights say
    zoomed = run("eval", "--set", "val50", "--scenes", "1", "--model", weights, "--json", tmp_path / "z.json",
                 "--zoom", "1.3", "--quiet")
    assert zoomed.returncode == 0, zoomed.stderr
    assert "read at zoom 1.3" in zoomed.stdout
    assert json.loads((tmp_path / "z.json").read_text())["val50"]["dbscan"]["zoom"] == 1.3
    refused = run("eval", "--zoom", "3", "--model", weights)
    assert refused.returncode == 2 and "at most 2.0" in refused.stderr and "Traceback" not in refused.stderr
    read_twice = run("eval", "--set", "val50", "--scenes", "1", "--model", weights, "--json", tmp_path / "r.json",
                     "--readings", "2", "--quiet")
    assert read_twice.returncode == 0, read_twice.stderr
    assert "2 turned readings averaged" in read_twice.stdout
    assert json.loads((tmp_path / "r.json").read_text())["val50"]["meanshift"]["readings"] == 2
    for flags, fragment in ((["--readings", "0"], "must be positive"), (["--readings", "13"], "at most 12"),
                            (["--table", "3", "--readings", "2"], "--table reads each bed once")):
        refused = run("eval", *flags, "--model", weights)
        assert refused.returncode == 2 and fragment in refused.stderr and len(refused.stderr.strip().splitlines()) == 1


def test_eval_radius_fit_sizes_the_same_caps_by_the_ellipsoid(tmp_path, monkeypatch):
    """The shipped model on two val50 beds: ``--radius fit`` finds the same caps with the same axes and
    gives other sizes."""
    monkeypatch.setenv("MUSHROOM_POSE_CACHE", str(tmp_path / "cache"))
    reports = {}
    for radius in ("rim", "fit"):
        result = run("eval", "--set", "val50", "--scenes", "2", "--json", tmp_path / f"{radius}.json",
                     "--radius", radius, "--quiet")
        assert result.returncode == 0, result.stderr
        reports[radius] = json.loads((tmp_path / f"{radius}.json").read_text())["val50"]["meanshift"]
    rim, fit = reports["rim"], reports["fit"]
    assert rim["n_pred"] == fit["n_pred"] and rim["angle_deg"] == pytest.approx(fit["angle_deg"], abs=1e-9)
    assert rim["scale_err"] != pytest.approx(fit["scale_err"], abs=1e-4)


def test_detect_warns_outside_the_operating_range(tmp_path, weights):
    """A bed sampled every 5 mm is sparser than the model holds to, and one sampled every 8 mm is also
    filled in before reading; the same bed at 3 mm is neither. The tiny model finds no caps on any,
    which detect also says."""
    for spacing in (0.003, 0.005, 0.008):
        scene = generate_scene(11, SceneConfig(spacing=spacing, jitter=(1.0, 1.0)))
        cloud = write_ply(tmp_path / f"bed{spacing}.ply", scene.points)
        result = run("detect", cloud, "--out", tmp_path / f"d{spacing}.json", "--model", weights, "--bed-frame")
        assert result.returncode == 0, result.stderr
        sparse = [line for line in result.stderr.splitlines() if "lie as far apart" in line]
        assert len(sparse) == (spacing > 0.003)
        assert all(("filled in" in line) == (spacing == 0.008) for line in sparse)
        assert "warning: no caps" in result.stderr


@pytest.mark.parametrize("unit, per_metre", [("m", 1), ("cm", 100), ("mm", 1000)])
def test_a_cloud_is_read_in_the_unit_in_which_it_is_a_bed(tmp_path, scene_ply, unit, per_metre):
    _, scene = scene_ply
    cloud = load_cloud(write_ply(tmp_path / "bed.ply", scene.points * per_metre))
    assert cloud.units == unit and cloud.unit_doubt is None
    np.testing.assert_allclose(cloud.points, scene.points, atol=1e-6)
    assert load_cloud(tmp_path / "bed.ply", "m").units == "m"  # --units decides


def test_a_wall_far_behind_a_metre_bed_does_not_change_its_unit(tmp_path, scene_ply):
    _, scene = scene_ply
    rng = np.random.default_rng(1)
    wall = np.column_stack([rng.uniform(-1, 1, len(scene.points) // 33), np.full(len(scene.points) // 33, 25.0),
                            rng.uniform(0, 2, len(scene.points) // 33)])
    assert load_cloud(write_ply(tmp_path / "walled.ply", np.vstack([scene.points, wall]))).units == "m"


def test_detect_on_a_centimetre_bed_gives_the_caps_of_the_metre_bed(tmp_path, scene_ply):
    path, scene = scene_ply
    result = run("detect", write_ply(tmp_path / "cm.ply", scene.points * 100), "--out", tmp_path / "cm.json")
    assert result.returncode == 0 and "read in centimetres" in result.stderr
    assert run("detect", path, "--out", tmp_path / "m.json").returncode == 0
    in_cm, in_m = (json.loads((tmp_path / name).read_text())["mushrooms"] for name in ("cm.json", "m.json"))
    assert len(in_cm) == len(in_m) >= 4
    np.testing.assert_allclose([c["center"] for c in in_cm], [c["center"] for c in in_m], atol=1e-4)


def test_a_cloud_that_is_no_bed_is_refused_unless_forced(tmp_path, weights):
    cube = write_ply(tmp_path / "cube.ply", np.random.default_rng(2).uniform(-0.5, 0.5, (200_000, 3)))
    out = tmp_path / "d.json"
    one_line_error(run("detect", cube, "--model", weights, "--out", out), "does not look like a bed")
    assert not out.exists()
    forced = run("detect", cube, "--model", weights, "--out", out, "--force")
    assert forced.returncode == 0 and "warning:" in forced.stderr and out.exists()


def test_bed_frame_is_refused_for_a_cloud_that_is_not_in_it(tmp_path, scene_ply, weights):
    from scipy.spatial.transform import Rotation

    path, scene = scene_ply
    tilted = write_ply(tmp_path / "tilted.ply", scene.points @ Rotation.from_euler("x", 40, degrees=True).as_matrix().T)
    one_line_error(run("detect", tilted, "--bed-frame", "--model", weights, "--out", tmp_path / "t.json"),
                   "tilted 40 deg")
    lifted = write_ply(tmp_path / "lifted.ply", scene.points + [0.0, 0.0, 0.3])
    one_line_error(run("detect", lifted, "--bed-frame", "--model", weights, "--out", tmp_path / "l.json"),
                   "30 cm from the frame's origin")
    assert run("detect", path, "--bed-frame", "--model", weights, "--out", tmp_path / "b.json").returncode == 0


@pytest.mark.parametrize("shift", [(0.1, -0.2, 0.5), (0.1, -0.2, -0.45)], ids=["origin below", "origin above"])
def test_detect_turns_the_bed_the_way_its_caps_stand_wherever_the_origin_lies(tmp_path, shift):
    """A bed of 15 caps whose input origin lies 0.5 m below it (fusion.bed's plane then faces down,
    tests/test_bed_frame.py): the shipped model sees its caps only the right way up, and detect turns
    the frame so; with the origin above, the frame stands."""
    scene = generate_scene(7, SceneConfig(mushrooms=(15, 15)))
    out = tmp_path / "d.json"
    result = run("detect", write_ply(tmp_path / "bed.ply", scene.points + np.asarray(shift)), "--out", out)
    assert result.returncode == 0, result.stderr
    document = json.loads(out.read_text())
    assert np.asarray(document["T_input_bed"])[2, 2] > 0.99
    assert 13 <= len(document["mushrooms"]) <= 17


def test_detect_grades_caps_by_the_growers_table(tmp_path, scene_ply):
    """--grades: every cap graded by the file's table, the table in the document; a bad table is one line."""
    ply, _ = scene_ply
    table = tmp_path / "grades.toml"
    table.write_text('[[grades]]\nname = "small"\nfrom_mm = 0\n\n[[grades]]\nname = "large"\nfrom_mm = 45\n')
    out = tmp_path / "d.json"
    result = run("detect", ply, "--out", out, "--grades", table, "--readings", "1")  # the shipped model
    assert result.returncode == 0, result.stderr
    document = json.loads(out.read_text())
    assert document["grades"] == [{"name": "small", "from_mm": 0.0}, {"name": "large", "from_mm": 45.0}]
    assert document["mushrooms"]
    for cap in document["mushrooms"]:
        assert cap["grade"] == ("large" if cap["cap_diameter_mm"] >= 45 else "small")
    assert {cap["grade"] for cap in document["mushrooms"]} == {"small", "large"}  # measured: the bed holds both
    table.write_text('[[grades]]\nname = "small"\n')
    one_line_error(run("detect", ply, "--out", tmp_path / "e.json", "--grades", table),
                   "without 'from_mm'")
    assert not (tmp_path / "e.json").exists()


def test_detect_shown_in_no_viewer_loads_no_viewer(tmp_path, scene_ply):
    """rerun-sdk is loaded only by a command shown in Rerun: without --rrd, --spawn or --serve, detect
    pays neither its import nor its exit; and it runs its network in numpy, without torch."""
    import sys

    ply, _ = scene_ply
    code = ("import sys; from pipeline.cli import main; "
            f"code = main(['detect', {str(ply)!r}, '--out', {str(tmp_path / 'd.json')!r}]); "
            "print(code, sorted(m for m in ('rerun', 'torch') if m in sys.modules))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.stdout.strip().splitlines()[-1] == "0 []", result.stderr
    assert json.loads((tmp_path / "d.json").read_text())["mushrooms"]
