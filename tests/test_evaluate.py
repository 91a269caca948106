"""Tests of perception.evaluate against analytic volumes and hand-computed AP."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from perception.cap import OrientedBox, cap_box, cap_rotation, rotation_z
from perception.evaluate import (SceneCaps, align_spin, average_precision, box_iou, evaluate,
                                 iou_matrix)

OCTAGON_AREA = 2.0 * (math.sqrt(2.0) - 1.0)
"""Unit square cut by its 45-degree rotation: |x|, |y| <= 1/2 and |x| + |y| <= sqrt(2)/2 leave the
square minus four corner triangles with legs 1 - sqrt(2)/2, i.e. 1 - 2 (1 - sqrt(2)/2)^2."""


def unit_cube(center=(0.0, 0.0, 0.0), rotation=None) -> OrientedBox:
    rotation = np.eye(3) if rotation is None else np.asarray(rotation, np.float64)
    return OrientedBox(np.asarray(center, np.float64), rotation, np.full(3, -0.5), np.full(3, 0.5))


def iou_from_intersection(inter: float, vol_a: float = 1.0, vol_b: float = 1.0) -> float:
    return inter / (vol_a + vol_b - inter)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    return Rotation.random(random_state=rng).as_matrix()


def test_identical_boxes_have_iou_one():
    rng = np.random.default_rng(0)
    for _ in range(5):
        box = cap_box(rng.normal(size=3), random_rotation(rng), rng.uniform(0.01, 0.03, size=3))
        assert box_iou(box, box) == pytest.approx(1.0, abs=1e-9)


def test_shifted_cube():
    assert box_iou(unit_cube(), unit_cube((0.5, 0.0, 0.0))) == pytest.approx(1.0 / 3.0, abs=1e-6)
    dx, dy, dz = 0.2, 0.3, 0.4
    expected = iou_from_intersection((1 - dx) * (1 - dy) * (1 - dz))
    assert box_iou(unit_cube(), unit_cube((dx, dy, dz))) == pytest.approx(expected, abs=1e-6)


def test_cube_rotated_45_degrees_about_its_axis():
    expected = iou_from_intersection(OCTAGON_AREA)
    rotated = unit_cube(rotation=rotation_z(np.pi / 4))
    assert box_iou(unit_cube(), rotated) == pytest.approx(expected, abs=1e-6)

    rng = np.random.default_rng(1)
    points = rng.uniform(-0.5, 0.5, size=(20000, 2))
    local = points @ rotation_z(np.pi / 4)[:2, :2]
    monte_carlo = np.mean(np.all(np.abs(local) <= 0.5, axis=1))
    assert monte_carlo == pytest.approx(OCTAGON_AREA, abs=0.02)


def test_iou_invariant_to_common_rigid_transform():
    rng = np.random.default_rng(2)
    a = OrientedBox(np.zeros(3), random_rotation(rng), np.array([-0.5, -0.3, 0.0]), np.array([0.5, 0.3, 0.4]))
    b = OrientedBox(np.array([0.2, -0.1, 0.1]), random_rotation(rng), np.array([-0.4, -0.4, 0.0]),
                    np.array([0.4, 0.4, 0.3]))
    iou = box_iou(a, b)
    assert 0.0 < iou < 1.0
    for _ in range(3):
        q, t = random_rotation(rng), rng.normal(size=3)
        moved = [OrientedBox(q @ box.center + t, q @ box.rotation, box.lo, box.hi) for box in (a, b)]
        assert box_iou(*moved) == pytest.approx(iou, abs=1e-9)
    assert box_iou(b, a) == pytest.approx(iou, abs=1e-9)


def test_disjoint_boxes_have_iou_zero():
    assert box_iou(unit_cube(), unit_cube((1.5, 0.0, 0.0))) == 0.0
    assert box_iou(unit_cube(), unit_cube((1.0, 1.0, 0.0), rotation_z(0.1))) == 0.0
    assert box_iou(unit_cube(), unit_cube((0.0, 0.0, 5.0))) == 0.0


def test_contained_box():
    rng = np.random.default_rng(3)
    big = OrientedBox(np.zeros(3), np.eye(3), np.zeros(3), np.full(3, 2.0))
    small = OrientedBox(np.ones(3), random_rotation(rng), np.full(3, -0.3), np.full(3, 0.3))
    expected = 0.6 ** 3 / 8.0
    assert box_iou(big, small) == pytest.approx(expected, abs=1e-9)
    assert box_iou(small, big) == pytest.approx(expected, abs=1e-9)


def test_spun_prediction_is_aligned():
    rng = np.random.default_rng(4)
    center, scales = np.array([0.1, 0.2, 0.0]), np.array([0.02, 0.02, 0.04 / 3])
    gt_rotation = cap_rotation(0.3, -0.2, 0.7)
    spun = gt_rotation @ rotation_z(np.pi / 4)
    unaligned = box_iou(cap_box(center, gt_rotation, scales), cap_box(center, spun, scales))
    assert unaligned == pytest.approx(iou_from_intersection(OCTAGON_AREA), abs=1e-6)

    aligned = align_spin(spun, gt_rotation)
    np.testing.assert_allclose(aligned, gt_rotation, atol=1e-12)
    gt = SceneCaps(center[None], gt_rotation[None], scales[None])
    pred = SceneCaps(center[None], spun[None], scales[None], np.ones(1))
    assert iou_matrix(pred, gt)[0, 0] == pytest.approx(1.0, abs=1e-9)

    tilted = cap_rotation(*rng.uniform(-0.5, 0.5, size=3))
    result = align_spin(tilted, gt_rotation)
    np.testing.assert_allclose(result @ result.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(result) == pytest.approx(1.0)
    np.testing.assert_allclose(result[:, 2], tilted[:, 2], atol=1e-12)


def ground_truth_scene(n: int, rng: np.random.Generator) -> SceneCaps:
    """n caps on a line 0.1 m apart (far enough that their boxes never overlap)."""
    centers = np.column_stack([0.1 * np.arange(n), rng.uniform(-0.01, 0.01, n), np.zeros(n)])
    rotations = cap_rotation(*rng.uniform(-0.4, 0.4, size=(3, n)))
    radius = rng.uniform(0.015, 0.03, n)
    scales = np.column_stack([radius, radius * rng.uniform(0.9, 1.1, n), 2 * radius / 3])
    return SceneCaps(centers, rotations, scales)


def as_predictions(gt: SceneCaps, scores, keep=None) -> SceneCaps:
    keep = np.arange(len(gt)) if keep is None else np.asarray(keep)
    return SceneCaps(gt.centers[keep], gt.rotations[keep], gt.scales[keep], np.asarray(scores, float))


def test_ground_truth_as_predictions_is_perfect():
    rng = np.random.default_rng(5)
    gts = [ground_truth_scene(4, rng), ground_truth_scene(3, rng)]
    preds = [as_predictions(g, rng.uniform(size=len(g))) for g in gts]
    result = evaluate(preds, gts)
    assert result.ap25 == pytest.approx(1.0)
    assert result.ap50 == pytest.approx(1.0)
    assert result.scale_err == pytest.approx(0.0, abs=1e-12)
    assert result.scale_err_true == pytest.approx(0.0, abs=1e-12)
    assert result.cosine == pytest.approx(1.0, abs=1e-12)
    assert result.angle_deg == pytest.approx(0.0, abs=1e-4)
    assert (result.n_gt, result.n_pred, result.n_matched) == (7, 7, 7)
    d = result.as_dict()
    assert {"ap25", "ap50", "scale_err", "cosine", "angle_deg", "n_gt", "n_pred"} <= d.keys()
    assert all(type(v) in (float, int) for v in d.values())


def test_scale_and_axis_errors_of_matches():
    rng = np.random.default_rng(6)
    gt = ground_truth_scene(1, rng)
    s_true = gt.scales[0, :2].mean()
    s_pred = 1.1 * s_true
    tilt = 10.0
    rotation = gt.rotations[0] @ Rotation.from_euler("x", tilt, degrees=True).as_matrix()
    pred = SceneCaps(gt.centers, rotation[None], np.array([[s_pred, s_pred, 2 * s_pred / 3]]), np.ones(1))
    result = evaluate([pred], [gt])
    assert result.n_matched == 1
    assert result.scale_err == pytest.approx(abs(s_pred - s_true) / s_pred)
    assert result.scale_err_true == pytest.approx(abs(s_pred - s_true) / s_true)
    assert result.cosine == pytest.approx(math.cos(math.radians(tilt)))
    assert result.angle_deg == pytest.approx(tilt)
    assert result.angle_deg_mean == pytest.approx(tilt)
    assert result.angle_deg_median == pytest.approx(tilt)


def test_angle_is_that_of_the_mean_cosine_as_in_the_paper():
    """Three caps off by 2, 4 and 40 degrees: the paper's angle is arccos of the mean cosine, which the
    one far-off cap pulls much further than it pulls the mean of the three angles."""
    rng = np.random.default_rng(8)
    gt = ground_truth_scene(3, rng)
    tilts = np.array([2.0, 4.0, 40.0])
    rotations = gt.rotations @ Rotation.from_euler("x", tilts[:, None], degrees=True).as_matrix()
    pred = SceneCaps(gt.centers, rotations, gt.scales, np.ones(3))
    result = evaluate([pred], [gt])
    assert result.n_matched == 3
    assert result.cosine == pytest.approx(np.cos(np.radians(tilts)).mean())
    assert result.angle_deg == pytest.approx(math.degrees(math.acos(np.cos(np.radians(tilts)).mean())))
    assert result.angle_deg_mean == pytest.approx(tilts.mean())
    assert result.angle_deg_median == pytest.approx(4.0)
    assert result.angle_deg > result.angle_deg_mean


def test_missing_detection():
    rng = np.random.default_rng(7)
    n = 5
    gt = ground_truth_scene(n, rng)
    result = evaluate([as_predictions(gt, np.linspace(0.9, 0.5, n - 1), keep=np.arange(1, n))], [gt])
    assert result.ap25 == pytest.approx((n - 1) / n)
    assert result.ap50 == pytest.approx((n - 1) / n)


def with_duplicate(gt: SceneCaps, scores, dup_of: int, dup_score: float) -> SceneCaps:
    keep = np.append(np.arange(len(gt)), dup_of)
    return as_predictions(gt, np.append(scores, dup_score), keep)


def test_duplicate_detections():
    rng = np.random.default_rng(8)
    gt = ground_truth_scene(4, rng)
    scores = [0.9, 0.8, 0.7, 0.6]
    # Lowest score: TP TP TP TP FP, precision 1 up to recall 1.
    assert evaluate([with_duplicate(gt, scores, 0, 0.1)], [gt]).ap50 == pytest.approx(1.0)
    # Ranked TP TP FP TP TP: precision 1, 1, 2/3, 3/4, 4/5 at recall 1/4, 1/2, 1/2, 3/4, 1;
    # the envelope is 1, 1, 4/5, 4/5, 4/5, so AP = 1/4 + 1/4 + 1/4 * 4/5 + 1/4 * 4/5 = 0.9.
    assert evaluate([with_duplicate(gt, scores, 0, 0.75)], [gt]).ap50 == pytest.approx(0.9)
    # Highest score: the duplicate takes cap 0 and the original becomes the FP: TP FP TP TP TP,
    # precision 1, 1/2, 2/3, 3/4, 4/5 at recall 1/4, 1/4, 1/2, 3/4, 1; AP = 1/4 + 3/4 * 4/5 = 0.85.
    result = evaluate([with_duplicate(gt, scores, 0, 1.0)], [gt])
    assert result.ap25 == pytest.approx(0.85)
    assert result.ap50 == pytest.approx(0.85)
    assert result.n_matched == 4


def test_matching_stays_within_each_scene():
    rng = np.random.default_rng(9)
    gt = ground_truth_scene(2, rng)
    empty = SceneCaps(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)))
    # Scene 1's prediction sits exactly on scene 0's first cap but scene 1 has no ground truth.
    preds = [as_predictions(gt, [0.5, 0.4]), as_predictions(gt, [0.9], keep=[0])]
    result = evaluate(preds, [gt, empty])
    # Ranked FP TP TP: precision 0, 1/2, 2/3 at recall 0, 1/2, 1; AP = 1/2 * 2/3 + 1/2 * 2/3.
    assert result.ap50 == pytest.approx(2.0 / 3.0)


def test_average_precision_alone():
    # Ranked by score: TP FP TP FP with 3 ground truths: precision 1, 1/2, 2/3, 1/2 at recall 1/3,
    # 1/3, 2/3, 2/3; envelope 1, 2/3, 2/3, 1/2; AP = 1/3 * 1 + 1/3 * 2/3 = 5/9.
    scores = np.array([0.2, 0.9, 0.5, 0.7])
    is_tp = np.array([False, True, True, False])
    assert average_precision(scores, is_tp, 3) == pytest.approx(5.0 / 9.0)
    assert average_precision([], [], 0) == 1.0
    assert average_precision([0.5], [False], 0) == 0.0
    assert average_precision([], [], 2) == 0.0
