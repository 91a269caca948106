"""bench/real.py's scoring: the README's xy matching on hand-made label and prediction sets, and the
same figures as ../shared/real/score.py on them."""

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

ROOT = Path(__file__).resolve().parent.parent
SCORER = ROOT.parent / "shared" / "real" / "score.py"


def _load_bench():
    spec = importlib.util.spec_from_file_location("bench_real", ROOT / "bench" / "real.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


real = _load_bench()


def cap(x, y, z=0.0, radius=None, axis=None, partial=False):
    entry = {"center": [x, y, z], "partial": partial}
    if radius is not None:
        entry["radius"] = radius
    if axis is not None:
        entry["axis"] = axis
    return entry


# Each case: labels, predictions, and the figures worked out by hand:
# (TP, FP, FN) over all caps, (TP, FP, FN, ignored) over non-partial caps.
CASES = {
    # P0 is 5 mm from L0 in xy (threshold 10 mm; its z is ignored); P1 is 11 mm from L1; P2 is far.
    "xy distance, threshold": (
        [cap(0, 0, radius=0.02), cap(0.1, 0, radius=0.02)],
        [cap(0.005, 0, 0.05, radius=0.02), cap(0.1, 0.011, radius=0.02), cap(0.5, 0.5, radius=0.02)],
        (1, 2, 1), (1, 2, 1, 0)),
    # exactly 0.5 x radius away (binary-exact numbers) is not closer than it: no match
    "strict threshold": (
        [cap(0, 0, radius=0.5)], [cap(0.25, 0)], (0, 1, 1), (0, 1, 1, 0)),
    # two detections on one big cap: the closer one is the match, the other a false positive
    "one-to-one": (
        [cap(0, 0, radius=0.035)], [cap(0.010, 0, radius=0.02), cap(0.003, 0, radius=0.03)],
        (1, 1, 0), (1, 1, 0, 0)),
    # greedy closest first, not the best assignment: P0-A (4 mm) is taken first, so P0-B (8 mm) and
    # P1-A (15 mm) are both blocked although P0-B + P1-A would match both labels
    "greedy, not optimal": (
        [cap(0, 0, radius=0.04), cap(0.012, 0, radius=0.04)],
        [cap(0.004, 0, radius=0.02), cap(-0.015, 0, radius=0.02)],
        (1, 1, 1), (1, 1, 1, 0)),
    # P0 takes F0, P1 takes the partial Q0 (neither TP nor FP for non-partial), P2 is false; F1 is
    # missed; the unmatched partial Q1 is not counted in non-partial recall
    "partial don't-care": (
        [cap(0, 0, radius=0.02), cap(0.1, 0, radius=0.02), cap(0.2, 0, radius=0.02, partial=True),
         cap(0.3, 0, radius=0.02, partial=True)],
        [cap(0.001, 0, radius=0.02), cap(0.201, 0, radius=0.02), cap(0.5, 0.5, radius=0.02)],
        (2, 1, 2), (1, 1, 1, 1)),
    # a partial label closer to the prediction than a full one takes it: the full label is missed
    "partial label takes the prediction": (
        [cap(0, 0, radius=0.04), cap(0.012, 0, radius=0.04, partial=True)], [cap(0.008, 0, radius=0.03)],
        (1, 0, 1), (0, 0, 1, 1)),
    "no predictions": (
        [cap(0, 0, radius=0.02), cap(0.1, 0, radius=0.02, partial=True)], [], (0, 0, 2), (0, 0, 1, 0)),
}


def prf(tp, n_pred, n_label):
    p = tp / n_pred if n_pred else 0.0
    r = tp / n_label if n_label else 0.0
    return p, r, (2 * p * r / (p + r) if p + r else 0.0)


@pytest.mark.parametrize("name", CASES)
def test_matching_by_hand(name):
    labels, preds, (tp, fp, fn), (tp_full, fp_full, fn_full, ignored) = CASES[name]
    figures = real.score(real.read_caps({"caps": preds}), real.read_caps({"caps": labels}))
    got = figures["all"]
    assert (got["tp"], got["fp"], got["fn"]) == (tp, fp, fn)
    assert (got["precision"], got["recall"], got["f1"]) == pytest.approx(prf(tp, len(preds), len(labels)))
    got = figures["nonpartial"]
    assert (got["tp"], got["fp"], got["fn"], got["ignored"]) == (tp_full, fp_full, fn_full, ignored)
    n_full = sum(not lab["partial"] for lab in labels)
    assert (got["precision"], got["recall"], got["f1"]) == pytest.approx(prf(tp_full, len(preds) - ignored, n_full))


def test_greedy_pairs_and_ties():
    # the pairs of the greedy case, closest first
    labels, preds, *_ = CASES["greedy, not optimal"]
    pairs = real.match_xy(np.array([p["center"] for p in preds]), np.array([lab["center"] for lab in labels]),
                          np.array([lab["radius"] for lab in labels]))
    assert pairs.tolist() == [[0, 0]]
    # equal distances: the lower prediction index first, then the lower label index (score.py's tuple sort)
    pairs = real.match_xy(np.array([[0.01, 0, 0], [-0.01, 0, 0]]), np.array([[0.0, 0, 0], [0.02, 0, 0]]),
                          np.array([0.04, 0.04]))
    # P0-A, P0-B and P1-A are all 10 mm (exactly): P0-A comes first and blocks the other two
    assert pairs.tolist() == [[0, 0]]


def test_pair_errors_by_hand():
    labels = real.read_caps([cap(0, 0, 0.01, radius=0.02, axis=[0, 0, 1]),
                             cap(0.1, 0, 0, radius=0.02, axis=[0, 0, 2])])
    preds = real.read_caps([cap(0.003, 0.004, 0, radius=0.025, axis=[1, 0, 1]),  # 45 deg, 25 % too big
                            cap(0.1, 0, 0)])  # no axis, no radius: only its centre error counts
    figures = real.score(preds, labels)
    errors = figures["errors_all"]
    assert errors["n"] == 2
    assert errors["center_mm"]["mean"] == pytest.approx((math.sqrt(9 + 16 + 100) + 0) / 2)
    assert errors["center_xy_mm"]["mean"] == pytest.approx(2.5)
    assert errors["axis_deg"] == pytest.approx({"n": 1, "mean": 45.0, "median": 45.0})
    assert errors["radius_rel"] == pytest.approx({"n": 1, "mean": 0.25, "median": 0.25})
    assert errors["radius_rel_signed"]["median"] == pytest.approx(0.25)
    small = real.score(real.read_caps([cap(0, 0, radius=0.015)]), labels)["errors_all"]  # 25 % too small
    assert small["radius_rel"]["median"] == pytest.approx(0.25)
    assert small["radius_rel_signed"]["median"] == pytest.approx(-0.25)
    # a detection as large as the label's radius without the footprint's bias scores no radius error
    fair = real.read_caps([cap(0, 0, radius=0.02 / (1 + real.FOOTPRINT_RADIUS_BIAS))])
    assert real.score(fair, labels)["errors_all"]["radius_rel_unbiased_labels"]["mean"] == pytest.approx(0.0, abs=1e-12)
    # an axis pointing down is 180 deg off: axes are signed up-vectors
    down = real.score(real.read_caps([cap(0, 0, axis=[0, 0, -1])]), labels)
    assert down["errors_all"]["axis_deg"]["mean"] == pytest.approx(180.0)


def test_per_cap_rows_by_hand():
    """Labels tilted 0 and 45 degrees from a bed normal along y (not z, so that the tilt is taken from
    it); a detection 25 % too big and turned 45 degrees on the first, the second missed, the partial
    one left out, a detection 5 % too big on the last."""
    labels = real.read_caps([cap(0, 0, radius=0.02, axis=[0, 1, 0]), cap(0.1, 0, radius=0.01, axis=[0, 1, 1]),
                             cap(0.2, 0, radius=0.03, axis=[0, 1, 0], partial=True),
                             cap(0.3, 0, radius=0.04, axis=[0, 1, 0])])
    preds = real.read_caps([cap(0.3, 0, radius=0.042, axis=[0, 1, 0]), cap(0.001, 0, radius=0.025, axis=[1, 1, 0])])
    rows = real.per_cap(preds, labels, np.array(real.score(preds, labels)["pairs"]), np.array([0.0, 2.0, 0.0]))
    assert [r["label"] for r in rows] == [0, 1, 3]
    first, second, third = rows
    assert third["radius_rel_signed"] == pytest.approx(0.05) and third["axis_deg"] == pytest.approx(0.0)
    assert first["found"] and not second["found"]
    assert (first["radius_mm"], first["detected_radius_mm"]) == pytest.approx((20.0, 25.0))
    assert first["radius_rel_signed"] == pytest.approx(0.25)
    assert (first["axis_deg"], first["tilt_deg"], first["detected_tilt_deg"]) == pytest.approx((45.0, 0.0, 45.0))
    assert (second["radius_mm"], second["tilt_deg"]) == pytest.approx((10.0, 45.0))
    lines = real.cap_report(rows)  # the largest radius error first, the missed label last
    assert len(lines) == 4 and "+25.0 %" in lines[1] and "+5.0 %" in lines[2] and "missed" in lines[3]


def test_radius_errors_against_labels_freed_of_the_footprint_shortfall_at_their_tilt():
    """Shortfalls 1.3 / 4.7 / 10.8 % under 20, 20-35 and over 35 degrees of tilt; a detection as large as
    a 45-degree label's radius before its shortfall scores nothing, one 25 % over a flat label's
    0.25 x 0.987 + (0.987 - 1) = 23.4 %."""
    assert real.footprint_bias_at(np.array([0.0, 19.9, 20.0, 34.9, 35.0, 80.0, np.nan])) == pytest.approx(
        [-0.013, -0.013, -0.047, -0.047, -0.108, -0.108, np.nan], nan_ok=True)
    labels = real.read_caps([cap(0, 0, radius=0.02, axis=[0, 1, 1]), cap(0.1, 0, radius=0.02, axis=[0, 0, 1])])
    preds = real.read_caps([cap(0, 0, radius=0.02 / 0.892, axis=[0, 1, 1]), cap(0.1, 0, radius=0.025)])
    figures = real.score(preds, labels)
    figures["caps"] = real.per_cap(preds, labels, np.array(figures["pairs"]), np.array([0.0, 0.0, 1.0]))
    assert [r["radius_rel_signed_tilt_unbiased"] for r in figures["caps"]] == pytest.approx([0.0, 0.25 * 0.987 - 0.013])
    figures["errors_nonpartial"]["radius_rel_tilt_unbiased_labels"] = real.tilt_unbiased_radius_errors(figures["caps"])
    line = [line for line in real.report(figures) if "at each label's tilt" in line]
    assert len(line) == 1 and "mean 0.117 / median 0.117 (n=2)" in line[0]


def test_recall_by_size():
    labels = real.read_caps([cap(0, 0, radius=0.010), cap(0.1, 0, radius=0.012), cap(0.2, 0, radius=0.025),
                             cap(0.3, 0, radius=0.031, partial=True), cap(0.4, 0, radius=0.035)])
    preds = real.read_caps([cap(0.1, 0), cap(0.3, 0), cap(0.4, 0)])
    rows = real.recall_by_size(labels, np.array(real.score(preds, labels)["pairs"]))
    assert [(r["full_found"], r["full"], r["all_found"], r["all"]) for r in rows] == \
        [(0, 1, 0, 1), (1, 1, 1, 1), (0, 1, 0, 1), (1, 1, 2, 2)]


def test_detect_json_is_read():
    detections = {"frame": "input", "mushrooms": [
        {"id": 3, "center": [0.0, 0.0, 0.0], "axis": [0.0, 0.0, 1.0], "rotation": np.eye(3).tolist(),
         "radius": 0.02, "height": 0.0133, "cap_diameter_mm": 40.0, "score": 0.9, "num_points": 100}],
        "T_input_bed": np.eye(4).tolist()}
    caps = real.read_caps(detections)
    assert len(caps) == 1 and caps.ids == [3] and caps.radii.tolist() == [0.02]


@pytest.mark.skipif(not SCORER.exists(), reason=f"{SCORER} is not here (it lives beside the repository, "
                    "outside it, and CI does not have it)")
@pytest.mark.parametrize("name", CASES)
def test_same_figures_as_score_py(name, tmp_path):
    labels, preds, (tp, fp, fn), (tp_full, fp_full, fn_full, _) = CASES[name]
    labels = [dict(lab, axis=[0.0, 0.1, 1.0]) for lab in labels]
    preds = [dict(p, axis=[0.1, 0.0, 1.0]) for p in preds]
    (tmp_path / "labels.json").write_text(json.dumps({"caps": labels}))
    (tmp_path / "preds.json").write_text(json.dumps({"mushrooms": preds}))
    theirs, lines = real.run_scorer(SCORER, tmp_path / "labels.json", tmp_path / "preds.json")
    ours = real.score(real.read_caps(tmp_path / "preds.json"), real.read_caps(tmp_path / "labels.json"))
    assert real.compare_with_scorer(ours, theirs) == [], "\n".join(lines)
    assert (theirs["all"]["tp"], theirs["all"]["fp"], theirs["all"]["fn"]) == (tp, fp, fn)
    assert (theirs["nonpartial"]["tp"], theirs["nonpartial"]["fp"], theirs["nonpartial"]["fn"]) == \
        (tp_full, fp_full, fn_full)


def test_thinned_cloud_is_xyz_only(tmp_path):
    rng = np.random.default_rng(0)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.uniform(0, 0.1, (2000, 3))))
    cloud.colors = o3d.utility.Vector3dVector(rng.uniform(0, 1, (2000, 3)))
    cloud.normals = o3d.utility.Vector3dVector(np.tile([0.0, 0.0, 1.0], (2000, 1)))
    o3d.io.write_point_cloud(str(tmp_path / "in.pcd"), cloud)
    points = real.thin_xyz(tmp_path / "in.pcd", 20.0, tmp_path / "out.ply")
    back = o3d.io.read_point_cloud(str(tmp_path / "out.ply"))
    assert not back.has_colors() and not back.has_normals()
    assert len(back.points) == len(points) <= 6 ** 3


def test_top_view_png(tmp_path):
    rng = np.random.default_rng(1)
    points = rng.uniform(-0.1, 0.1, (3000, 3))
    labels = real.read_caps([cap(0, 0, radius=0.02, axis=[0.3, 0, 1]), cap(0.05, 0.05, radius=0.01, partial=True),
                             cap(-0.05, 0.05, radius=0.015)])
    preds = real.read_caps([cap(0.002, 0, radius=0.022, axis=[0, 0.3, 1]), cap(-0.06, -0.06, radius=0.01)])
    real.top_view_png(tmp_path / "top.png", points, points[:, 2], labels, preds,
                      np.array(real.score(preds, labels)["pairs"]), size=300)
    image = np.asarray(o3d.io.read_image(str(tmp_path / "top.png")))
    assert image.shape[2] == 3 and abs(max(image.shape[:2]) - 300) <= 1
    colours = {tuple(c) for c in image.reshape(-1, 3)}
    assert {real.GREEN, real.YELLOW, real.RED, real.MAGENTA, real.GREY} <= colours


def test_diagnosis_by_hand():
    # L0 gets a match (P0) and a second detection 15 mm off (P1, inside its 20 mm radius: not a match);
    # L1 is missed with P2 inside its radius but 12 mm off; L2 is missed with nothing near; P3 is far off
    labels = real.read_caps([cap(0, 0, radius=0.02), cap(0.1, 0, radius=0.02), cap(0.2, 0, radius=0.02),
                             cap(0.3, 0, radius=0.02, partial=True)])
    preds = real.read_caps([cap(0.001, 0), cap(0.015, 0), cap(0.112, 0), cap(0.5, 0.5)])
    figures = real.score(preds, labels)
    assert figures["diagnosis"] == {"fp_on_a_label": 2, "fp_elsewhere": 1,
                                    "fn_with_unmatched_prediction_inside": 1, "fn_nothing_inside": 1}
    assert (figures["nonpartial"]["fp"], figures["nonpartial"]["fn"]) == (3, 2)
