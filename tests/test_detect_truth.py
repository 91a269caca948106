"""``mushroom-pose detect`` with the shipped model against the truth of synthetic beds.

Each bed (15 caps on 0.4 m, perception.synthetic) is handed to ``detect`` as a user would: in the bed
frame (.npz), seen by a camera above it (OpenCV frame, .ply), and turned and moved far away (.ply).
The caps of the JSON are matched one to one to the visible true caps, expressed in the same input frame,
and their centres, axes and radii are compared with the truth.

Tolerances: measured on beds 0-9 (seed = bed) in the three frames, 28 bed-frame pairs (bed 6, whose
relief points the wrong way, has its own test below); each bound is the worst value measured there
times 1.5 (or one cap more), so it holds beds 0, 5 and 7, tested here, with room for the small changes
a refactor brings, and fails when a stage is broken (a flipped axis is 180 degrees off, a wrong frame
centimetres). The figures are in ``BOUNDS``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment
from scipy.spatial.transform import Rotation

from helpers import rrd_values
from perception.synthetic.dataset import ground_truth_mask
from perception.synthetic.scene import SceneConfig, generate_scene
from test_detect_cli import run, write_ply

BED = SceneConfig(mushrooms=(15, 15), bed_size=0.4)


def camera_pose() -> np.ndarray:
    """T_camera_bed of a camera 0.45 m above the bed looking down, tilted 20 degrees: an OpenCV frame
    (z forward, into the bed), built here rather than with capture's look_at."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("x", 200, degrees=True).as_matrix()
    T[:3, 3] = [0.02, -0.03, 0.45]
    return T


def far_pose() -> np.ndarray:
    """T_input_bed of a frame turned every way and 33 m off (a site's survey frame): the bed's up is
    mostly along the input's -x and its origin says nothing about which side is up."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [35, -120, 70], degrees=True).as_matrix()
    T[:3, 3] = [12.0, -7.5, 30.0]
    return T


FRAMES = {"bed": np.eye(4), "camera": camera_pose(), "far": far_pose()}


@dataclass(frozen=True)
class Comparison:
    """Detections of one bed in one frame against its visible true caps."""

    visible: int
    found: int
    """True caps with a detection whose centre lies within the cap's radius (one-to-one)."""
    extra: int
    """Detections matched to no true cap."""
    centre_error: np.ndarray
    """Per match: centre distance over the true radius."""
    angle_deg: np.ndarray
    """Per match: angle between the detected and the true cap axis."""
    radius_error: np.ndarray
    """Per match: |r - r_true| / r_true."""
    normal_deg: float
    """Angle between the document's bed normal (T_input_bed z) and the true one."""


def detect_in_frame(tmp_path, scene, name: str, *extra_args) -> tuple[dict, np.ndarray]:
    """``mushroom-pose detect`` on the scene's points expressed in frame ``name``: (the JSON document,
    the input points)."""
    T = FRAMES[name]
    points = scene.points.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    if name == "bed":
        cloud = tmp_path / "bed.npz"
        np.savez(cloud, points=points)  # our scene format, which detect reads as given in the bed frame
    else:
        cloud = write_ply(tmp_path / f"{name}.ply", points)
    out = tmp_path / f"{name}.json"
    result = run("detect", cloud, "--out", out, *extra_args)
    assert result.returncode == 0, result.stderr
    return json.loads(out.read_text()), points


def compare(document: dict, scene, T_input_bed: np.ndarray) -> Comparison:
    """The document's caps against the scene's visible caps moved into the input frame."""
    visible = ground_truth_mask(scene)
    rotation = T_input_bed[:3, :3]
    return compare_caps(document, scene.centers[visible] @ rotation.T + T_input_bed[:3, 3],
                        scene.rotations[visible][:, :, 2] @ rotation.T, scene.scales[visible][:, :2].mean(1),
                        rotation[:, 2])


def compare_caps(document: dict, true_centres: np.ndarray, true_axes: np.ndarray, true_radii: np.ndarray,
                 true_up: np.ndarray) -> Comparison:
    """A detection document against true caps given in its frame: matched one to one by centre
    distance (Hungarian), a pair counting when the centres lie within the true radius."""
    caps = document["mushrooms"]
    centres = np.array([cap["center"] for cap in caps]).reshape(-1, 3)
    axes = np.array([cap["axis"] for cap in caps]).reshape(-1, 3)
    radii = np.array([cap["radius"] for cap in caps])
    distance = np.linalg.norm(true_centres[:, None] - centres[None], axis=2)
    rows, cols = linear_sum_assignment(distance)
    near = distance[rows, cols] < true_radii[rows]
    rows, cols = rows[near], cols[near]
    cosine = np.clip(np.sum(true_axes[rows] * axes[cols], axis=1), -1.0, 1.0)
    normal = np.array(document.get("T_input_bed", np.eye(4)))[:3, 2]
    return Comparison(len(true_centres), len(rows), len(caps) - len(rows),
                      distance[rows, cols] / true_radii[rows], np.degrees(np.arccos(cosine)),
                      np.abs(radii[cols] - true_radii[rows]) / true_radii[rows],
                      float(np.degrees(np.arccos(np.clip(normal @ true_up, -1.0, 1.0)))))


BOUNDS = {
    # measured worst over the 28 bed-frame pairs -> bound
    "missed": 2,  # true caps without a detection: worst 1 of 15 (bed 5, bed and far frames) -> 2
    "extra": 3,  # detections without a true cap: worst 2 (bed 0, camera frame) -> 3
    "centre_median": 0.13,  # median centre error / true radius: worst 0.086 (bed 1, far) -> 0.13
    "centre_p90": 0.29,  # its 90th percentile: worst 0.192 (bed 7, camera) -> 0.29
    "angle_median": 4.5,  # median axis error, degrees: worst 3.0 (bed 7, bed frame) -> 4.5
    "angle_p80": 12.5,  # its 80th percentile (3 caps of 15 may be worse): worst 8.4 (bed 5, camera) -> 12.5
    "radius_median": 0.045,  # median |r - r_true| / r_true: worst 0.030 (bed 7, camera) -> 0.045
    "normal": 6.0,  # the document's bed normal against the bed's z, degrees: worst 4.0 (bed 5) -> 6.0
}


def check(result: Comparison) -> None:
    assert result.visible - result.found <= BOUNDS["missed"], f"found {result.found} of {result.visible} caps"
    assert result.extra <= BOUNDS["extra"], f"{result.extra} detections match no cap"
    assert np.median(result.centre_error) <= BOUNDS["centre_median"]
    assert np.percentile(result.centre_error, 90) <= BOUNDS["centre_p90"]
    assert np.median(result.angle_deg) <= BOUNDS["angle_median"]
    assert np.percentile(result.angle_deg, 80) <= BOUNDS["angle_p80"]
    assert np.median(result.radius_error) <= BOUNDS["radius_median"]
    assert result.normal_deg <= BOUNDS["normal"]


@pytest.fixture(scope="module")
def beds():
    return {seed: generate_scene(seed, BED) for seed in (0, 5, 7)}


@pytest.mark.parametrize("frame", list(FRAMES))
@pytest.mark.parametrize("seed", [0, 5, 7])
def test_detected_caps_match_the_truth_in_the_input_frame(tmp_path, beds, seed, frame):
    scene = beds[seed]
    document, _ = detect_in_frame(tmp_path, scene, frame)
    assert document["frame"] == ("bed" if frame == "bed" else "input") and document["units"] == "m"
    for cap in document["mushrooms"]:
        rotation = np.array(cap["rotation"])
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-9)
        np.testing.assert_allclose(rotation[:, 2], cap["axis"], atol=1e-12)
        assert cap["cap_diameter_mm"] == pytest.approx(2000 * cap["radius"])
    check(compare(document, scene, FRAMES[frame]))


def test_the_rerun_recording_of_detect_holds_the_input_cloud_and_the_caps_of_the_json(tmp_path, beds):
    """--rrd logs in the input frame: the existence points are the input points, the ellipsoids are the
    JSON's caps (centre, radius, rotation), the boxes stand on them along the cap axis."""
    document, points = detect_in_frame(tmp_path, beds[0], "camera", "--rrd", tmp_path / "det.rrd")
    rrd = tmp_path / "det.rrd"
    [(_, positions)] = rrd_values(rrd, "/world/perception/existence", "Points3D:positions")
    np.testing.assert_allclose(positions, points, atol=1e-5)  # float32 in the file
    caps = document["mushrooms"]
    [(_, centres)] = rrd_values(rrd, "/world/perception/mushrooms/ellipsoids", "Ellipsoids3D:centers")
    [(_, half_sizes)] = rrd_values(rrd, "/world/perception/mushrooms/ellipsoids", "Ellipsoids3D:half_sizes")
    [(_, quaternions)] = rrd_values(rrd, "/world/perception/mushrooms/ellipsoids", "Ellipsoids3D:quaternions")
    assert len(caps) >= 13
    np.testing.assert_allclose(centres, [cap["center"] for cap in caps], atol=1e-5)
    np.testing.assert_allclose(np.array(half_sizes)[:, :2], [[cap["radius"]] * 2 for cap in caps], rtol=1e-5)
    np.testing.assert_allclose(np.array(half_sizes)[:, 2], [cap["height"] for cap in caps], rtol=1e-5)
    axes = Rotation.from_quat(quaternions).as_matrix()[:, :, 2]
    np.testing.assert_allclose(axes, [cap["axis"] for cap in caps], atol=1e-5)
    [(_, box_centres)] = rrd_values(rrd, "/world/perception/mushrooms/boxes", "Boxes3D:centers")
    expected = [np.add(cap["center"], np.multiply(cap["axis"], cap["height"] / 2)) for cap in caps]
    np.testing.assert_allclose(box_centres, expected, atol=1e-5)


def test_a_cloddy_bed_seen_by_a_camera_is_read_right_side_up(tmp_path):
    """Bed 6 (clods): its soil's 0.5th height percentile lies further below the fitted plane than the
    99.5th above it, so its relief points the wrong way; the camera origin must decide (all 15 caps)."""
    scene = generate_scene(6, BED)
    document, _ = detect_in_frame(tmp_path, scene, "camera")
    check(compare(document, scene, FRAMES["camera"]))
