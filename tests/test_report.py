"""The grower's report: caps graded and counted as their diameters say, partial and uncertain caps
flagged, one self-contained HTML file with a PNG map per bed, bad inputs refused in one line."""

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from perception.cap import Caps, rotation_from_axis
from perception.grades import Grade, GradeTable
from pipeline.report import PARTIAL_BELOW, footprint_coverage, make_report, read_bed

PNG = b"\x89PNG\r\n\x1a\n"


def caps_of(centers_mm, diameters_mm, scores) -> Caps:
    centers = np.asarray(centers_mm, np.float64) / 1000
    radii = np.asarray(diameters_mm, np.float64) / 2000
    rotations = np.repeat(rotation_from_axis(np.array([0.0, 0.0, 1.0]))[None], len(centers), 0)
    return Caps(centers, rotations, np.column_stack([radii, radii, 0.6 * radii]), np.asarray(scores, np.float64))


def write_document(path, caps: Caps, frame="bed", **extra):
    path.write_text(json.dumps({**caps.to_document(frame, 1), **extra}))
    return path


def run(*args):
    return subprocess.run([sys.executable, "-m", "pipeline.cli", "report", *map(str, args)], capture_output=True,
                          text=True, timeout=300)


def test_caps_are_counted_by_the_grade_their_diameter_falls_in(tmp_path):
    diameters = [12.0, 24.9, 25.0, 39.0, 41.0, 56.0, 70.0, 88.0]
    centers = [[60.0 * k, 0.0, 20.0] for k in range(len(diameters))]
    bed = read_bed(write_document(tmp_path / "bed.json", caps_of(centers, diameters, [0.9] * 8)), GradeTable())
    expected = ["small button", "small button", "button", "button", "closed cup", "open cup", "flat", "flat"]
    assert bed.grades == expected
    report = make_report([bed], GradeTable())
    for name in set(expected):
        count = expected.count(name)
        assert re.search(rf"{name}</td><td>{count}</td><td>{count / len(expected):.0%}</td>", report.html)


def test_the_growers_table_regrades_every_cap(tmp_path):
    path = write_document(tmp_path / "bed.json", caps_of([[0, 0, 20], [80, 0, 20]], [30.0, 50.0], [0.9, 0.9]))
    table = GradeTable((Grade("small", 0), Grade("large", 45)))
    assert read_bed(path, table).grades == ["small", "large"]


def test_uncertain_and_partial_caps_are_flagged(tmp_path):
    """A cap scored under the plan's ready score is uncertain; a cap on the scan's edge (half its
    footprint outside the scan) is partial; one inside it is not."""
    grid = np.stack(np.meshgrid(np.arange(-0.2, 0.0, 0.002), np.arange(-0.1, 0.1, 0.002)), -1).reshape(-1, 2)
    scan = np.column_stack([grid, np.zeros(len(grid))])
    caps = caps_of([[-100.0, 0.0, 20.0], [0.0, 0.0, 20.0]], [40.0, 40.0], [0.3, 0.9])
    coverage = footprint_coverage(caps.centers, caps.radii, scan)
    assert coverage[0] == 1.0 and abs(coverage[1] - 0.5) < 0.1 and coverage[1] < PARTIAL_BELOW
    bed = read_bed(write_document(tmp_path / "bed.json", caps), GradeTable())
    assert bed.uncertain.tolist() == [True, False] and bed.partial.tolist() == [False, False]  # no scan in JSON


def test_caps_in_the_input_frame_are_mapped_in_the_bed_frame(tmp_path):
    T_input_bed = np.eye(4)
    T_input_bed[:3, :3] = rotation_from_axis(np.array([0.3, -0.2, 0.93]) / np.linalg.norm([0.3, -0.2, 0.93]))
    T_input_bed[:3, 3] = [0.1, -0.2, 0.5]
    in_bed = caps_of([[10.0, 20.0, 15.0], [-40.0, 60.0, 18.0]], [30.0, 45.0], [0.9, 0.9])
    in_input = in_bed.moved(T_input_bed)
    path = write_document(tmp_path / "bed.json", in_input, "input", T_input_bed=T_input_bed.tolist())
    np.testing.assert_allclose(read_bed(path, GradeTable()).centers, in_bed.centers, atol=1e-9)


def test_report_of_beds_writes_one_self_contained_html_and_a_map_each(tmp_path):
    """A session (its caps over its fused cloud) and a detection document: one page with the histogram
    and both maps embedded, each map also beside it as a PNG."""
    import base64

    from pipeline.recordings import RECORDINGS_DIR

    session = RECORDINGS_DIR / "turntable-12.mcap"
    assert read_bed(session, GradeTable()).scan is not None
    document = write_document(tmp_path / "bed.json", caps_of([[0, 0, 20], [80, 0, 20]], [30.0, 50.0], [0.9, 0.9]))
    out = tmp_path / "report.html"
    result = run(session, document, "--out", out)
    assert result.returncode == 0, result.stderr
    page = out.read_text()
    assert page.startswith("<!DOCTYPE html>") and "turntable-12.mcap" in page and "bed.json" in page
    assert not re.search(r"(src|href)=\"(https?:|//)", page)  # nothing to fetch to open it
    images = [base64.b64decode(image) for image in re.findall(r'src="data:image/png;base64,([^"]+)"', page)]
    assert len(images) == 3 and all(image.startswith(PNG) for image in images)  # the histogram, two maps
    assert [(tmp_path / f"report-{k}.png").read_bytes() for k in (1, 2)] == images[1:]


@pytest.mark.parametrize("name, content, message", [
    ("notes.txt", "hello", "neither a session"),
    ("list.json", "[1, 2]", "no detection document"),
    ("broken.json", "{", "not readable JSON"),
    ("empty", None, "holds no session"),
    ("missing.json", False, "does not exist"),
])
def test_an_input_that_is_no_bed_is_one_line_and_nothing_is_written(tmp_path, name, content, message):
    path = tmp_path / name
    if content is None:
        path.mkdir()
    elif content is not False:
        path.write_text(content)
    out = tmp_path / "report.html"
    result = run(path, "--out", out)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and message in result.stderr, result.stderr
    assert not out.exists() and not (tmp_path / "report.png").exists()


def test_an_existing_report_is_kept_without_overwrite(tmp_path):
    path = write_document(tmp_path / "bed.json", caps_of([[0, 0, 20]], [30.0], [0.9]))
    out = tmp_path / "report.html"
    (tmp_path / "report.png").write_bytes(b"earlier")
    result = run(path, "--out", out)
    assert result.returncode == 2 and "--overwrite" in result.stderr
    assert (tmp_path / "report.png").read_bytes() == b"earlier" and not out.exists()
    assert run(path, "--out", out, "--overwrite").returncode == 0
    assert (tmp_path / "report.png").read_bytes().startswith(PNG)


def test_a_folder_gives_its_sessions_and_documents_but_not_a_sessions_expectation(tmp_path):
    import shutil

    from pipeline.recordings import RECORDINGS_DIR
    from pipeline.report import expand_inputs

    shutil.copy(RECORDINGS_DIR / "turntable-12.mcap", tmp_path)
    shutil.copy(RECORDINGS_DIR / "turntable-12.expected.json", tmp_path)
    write_document(tmp_path / "other.json", caps_of([[0, 0, 20]], [30.0], [0.9]))
    assert [path.name for path in expand_inputs([str(tmp_path)])] == ["other.json", "turntable-12.mcap"]
