"""Tests of perception.evaluate against analytic volumes and hand-computed AP."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from perception.cap import Caps, OrientedBox, cap_box, cap_rotation, rotation_z
from perception.evaluate import (align_spin, average_precision, box_iou, evaluate,
                                 intersection_volume, iou_matrix)

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


def test_box_iou_agrees_with_monte_carlo_on_tilted_boxes():
    """Points drawn uniformly in box a: the fraction inside box b estimates |a & b| / |a|, to within
    5 standard errors sqrt(p (1 - p) / n) of the exact value (a 1 in 1.7 million miss per pair)."""
    rng = np.random.default_rng(1)
    n = 200_000
    for _ in range(5):
        a = OrientedBox(rng.normal(size=3) * 0.1, random_rotation(rng), -rng.uniform(0.2, 0.6, 3),
                        rng.uniform(0.2, 0.6, 3))
        b = OrientedBox(a.center + rng.normal(size=3) * 0.2, random_rotation(rng), -rng.uniform(0.2, 0.6, 3),
                        rng.uniform(0.2, 0.6, 3))
        local = rng.uniform(a.lo, a.hi, size=(n, 3))
        world = local @ a.rotation.T + a.center
        in_b = (world - b.center) @ b.rotation
        fraction = np.mean(np.all((in_b >= b.lo) & (in_b <= b.hi), axis=1))
        margin = 5 * math.sqrt(fraction * (1 - fraction) / n) * a.volume
        low, high = (fraction * a.volume + sign * margin for sign in (-1, 1))
        assert low <= intersection_volume(a, b) <= high
        # IoU = I / (|a| + |b| - I) grows with I, so the bounds on I bound it
        iou = box_iou(a, b)
        assert 0.0 < iou < 1.0
        assert low / (a.volume + b.volume - low) <= iou <= high / (a.volume + b.volume - high)


def _halfspaces(box: OrientedBox) -> np.ndarray:
    """The box as 6 half-spaces in scipy's form [n, d] with n . x + d <= 0: in the box frame,
    q_i <= hi_i and -q_i <= -lo_i, where q = R^T (x - c), i.e. R[:, i] . x - (R[:, i] . c + hi_i) <= 0."""
    along = box.rotation.T @ box.center
    normals = np.vstack([box.rotation.T, -box.rotation.T])
    offsets = np.concatenate([-along - box.hi, along + box.lo])
    return np.column_stack([normals, offsets])


def reference_intersection_volume(a: OrientedBox, b: OrientedBox) -> float:
    """Volume of the intersection of two boxes, independently of perception.evaluate: the 12 half-spaces
    intersected by qhull (scipy's HalfspaceIntersection) around the deepest interior point, which a
    linear program finds (the Chebyshev centre: max r with n_k . x + r |n_k| <= -d_k), then the convex
    hull's volume. No interior point (infeasible, or r = 0: touching boxes) means an empty intersection."""
    from scipy.optimize import linprog
    from scipy.spatial import ConvexHull, HalfspaceIntersection

    halfspaces = np.vstack([_halfspaces(a), _halfspaces(b)])
    normals, offsets = halfspaces[:, :3], halfspaces[:, 3]
    program = linprog(np.array([0.0, 0.0, 0.0, -1.0]),
                      A_ub=np.column_stack([normals, np.linalg.norm(normals, axis=1)]), b_ub=-offsets,
                      bounds=[(None, None)] * 3 + [(0.0, None)], method="highs")
    if program.status == 2 or program.x[3] <= 1e-9:
        return 0.0
    assert program.status == 0, program.message
    corners = HalfspaceIntersection(halfspaces, program.x[:3]).intersections
    return float(ConvexHull(corners).volume)


def test_box_iou_equals_a_halfspace_intersection_on_random_tilted_pairs():
    """300 random pairs, from b a copy of a to b far off in another shape and orientation: 55 of them
    disjoint, the rest spread over IoU 0-1 (measured with this seed: 80 below 0.1, 59 in 0.1-0.25,
    53 in 0.25-0.5, 29 in 0.5-0.75 and 24 above). box_iou is exact, so it agrees with qhull to
    rounding (measured: 3e-15 at worst); 1e-9 leaves room for other platforms' rounding."""
    rng = np.random.default_rng(0)
    ious = []
    for _ in range(300):
        lo, hi = -rng.uniform(0.1, 1.0, 3), rng.uniform(0.1, 1.0, 3)
        a = OrientedBox(rng.normal(size=3), random_rotation(rng), lo, hi)
        closeness = rng.uniform()  # 0: b is a copy of a; 1: b is off by about its size, turned by ~1 rad
        turn = Rotation.from_rotvec(rng.normal(size=3) * closeness).as_matrix()
        grow = rng.uniform(1 - 0.5 * closeness, 1 + closeness, (2, 3))
        b = OrientedBox(a.center + rng.normal(size=3) * (hi - lo) * closeness, turn @ a.rotation, lo * grow[0],
                        hi * grow[1])
        inter = reference_intersection_volume(a, b)
        expected = inter / (a.volume + b.volume - inter)
        assert box_iou(a, b) == pytest.approx(expected, abs=1e-9)
        assert box_iou(b, a) == pytest.approx(expected, abs=1e-9)
        ious.append(expected)
    counts = np.histogram(ious, bins=[0.0, 1e-12, 0.25, 0.5, 1.0])[0]
    assert counts.min() >= 25, f"the pairs no longer cover IoU 0-1: {counts}"


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
    gt = Caps(center[None], gt_rotation[None], scales[None])
    pred = Caps(center[None], spun[None], scales[None], np.ones(1))
    assert iou_matrix(pred, gt)[0, 0] == pytest.approx(1.0, abs=1e-9)

    tilted = cap_rotation(*rng.uniform(-0.5, 0.5, size=3))
    result = align_spin(tilted, gt_rotation)
    np.testing.assert_allclose(result @ result.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(result) == pytest.approx(1.0)
    np.testing.assert_allclose(result[:, 2], tilted[:, 2], atol=1e-12)


def ground_truth_scene(n: int, rng: np.random.Generator) -> Caps:
    """n caps on a line 0.1 m apart (far enough that their boxes never overlap)."""
    centers = np.column_stack([0.1 * np.arange(n), rng.uniform(-0.01, 0.01, n), np.zeros(n)])
    rotations = cap_rotation(*rng.uniform(-0.4, 0.4, size=(3, n)))
    radius = rng.uniform(0.015, 0.03, n)
    scales = np.column_stack([radius, radius * rng.uniform(0.9, 1.1, n), 2 * radius / 3])
    return Caps(centers, rotations, scales)


def as_predictions(gt: Caps, scores, keep=None) -> Caps:
    keep = np.arange(len(gt)) if keep is None else np.asarray(keep)
    return Caps(gt.centers[keep], gt.rotations[keep], gt.scales[keep], np.asarray(scores, float))


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
    pred = Caps(gt.centers, rotation[None], np.array([[s_pred, s_pred, 2 * s_pred / 3]]), np.ones(1))
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
    pred = Caps(gt.centers, rotations, gt.scales, np.ones(3))
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


def with_duplicate(gt: Caps, scores, dup_of: int, dup_score: float) -> Caps:
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
    empty = Caps(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)))
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


def moved(gt: Caps, index: int, axis: int, fraction: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cap ``index`` of ``gt`` moved along its own x (axis 0) or z (axis 2) by ``fraction`` of its
    extent there: s_x for x, s_z for z (centre, rotation, scales)."""
    rotation = gt.rotations[index]
    step = fraction * gt.scales[index, axis] * rotation[:, axis]
    return gt.centers[index] + step, rotation, gt.scales[index]


@pytest.mark.parametrize("axis", [0, 2])
@pytest.mark.parametrize("fraction", [0.2, 0.5, 1.0, 1.6, 1.95])
def test_iou_of_a_cap_moved_along_its_own_axes(axis, fraction):
    """A cap's box spans 2 s_x along its x and s_z along its z. Moved by d along x, it overlaps its
    truth over (2 s_x - d) 2 s_y s_z, so IoU = (2 s_x - d) / (2 s_x + d); moved by d along z,
    IoU = (s_z - d) / (s_z + d). Moving by f s_x along x gives (2 - f) / (2 + f) (1/3 at f = 1), by
    f s_z along z gives (1 - f) / (1 + f) (0 past f = 1). Tilted caps, so no box is axis-aligned,
    and iou_matrix, whose bounding-sphere pre-filter must keep every pair that overlaps."""
    rng = np.random.default_rng(10)
    gt = ground_truth_scene(3, rng)
    for index in range(3):
        pred = Caps(*(value[None] for value in moved(gt, index, axis, fraction)), np.ones(1))
        expected = (2 - fraction) / (2 + fraction) if axis == 0 else max(1 - fraction, 0.0) / (1 + fraction)
        assert iou_matrix(pred, gt)[0, index] == pytest.approx(expected, abs=1e-9)


def test_ap25_and_ap50_of_displaced_and_duplicated_detections():
    """Four caps, four detections: ranked by score
      0.9 exactly on cap 0                               IoU 1
      0.8 on cap 1 moved by s_x along its x             IoU (2 - 1) / (2 + 1) = 1/3
      0.7 exactly on cap 0 again (a duplicate)           IoU 1, but cap 0 is taken
      0.6 on cap 2 moved by 0.2 s_x along its x         IoU 1.8 / 2.2 = 0.82
    and cap 3 is missed.
    At IoU 0.25: TP TP FP TP; precision 1, 1, 2/3, 3/4 at recall 1/4, 1/2, 1/2, 3/4; the envelope is
    1, 1, 3/4, 3/4, so AP = 1/4 + 1/4 + 1/4 * 3/4 = 11/16.
    At IoU 0.5: TP FP FP TP; precision 1, 1/2, 1/3, 1/2 at recall 1/4, 1/4, 1/4, 1/2; the envelope is
    1, 1/2, 1/2, 1/2, so AP = 1/4 + 1/4 * 1/2 = 3/8.
    At IoU 0.85 only the exact one counts: AP = 1/4 * 1 = 1/4."""
    rng = np.random.default_rng(11)
    gt = ground_truth_scene(4, rng)
    caps = [moved(gt, 0, 0, 0.0), moved(gt, 1, 0, 1.0), moved(gt, 0, 0, 0.0), moved(gt, 2, 0, 0.2)]
    pred = Caps(*(np.array(values) for values in zip(*caps)), np.array([0.9, 0.8, 0.7, 0.6]))
    result = evaluate([pred], [gt], thresholds=(0.25, 0.5, 0.85))
    assert result.ap25 == pytest.approx(11 / 16)
    assert result.ap50 == pytest.approx(3 / 8)
    assert dict(result.ap)[0.85] == pytest.approx(1 / 4)
    # the scale and axis errors are over the three matches at IoU 0.25; all have the true size and axis
    assert result.n_matched == 3 and result.scale_err == pytest.approx(0.0, abs=1e-12)


def test_a_higher_scored_loose_detection_takes_the_cap_at_ap25_but_not_at_ap50():
    """Two caps; ranked by score: 0.9 on cap 0 moved by s_x along x (IoU 1/3), 0.8 exactly on cap 0,
    0.7 exactly on cap 1. Greedy matching in score order gives different pairs per threshold:
    at 0.25 the loose one takes cap 0 and the exact one is a duplicate: TP FP TP, precision 1, 1/2, 2/3
    at recall 1/2, 1/2, 1, envelope 1, 2/3, 2/3, AP = 1/2 + 1/2 * 2/3 = 5/6;
    at 0.5 the loose one matches nothing and the exact one takes cap 0: FP TP TP, precision 0, 1/2, 2/3
    at recall 0, 1/2, 1, envelope 2/3, 2/3, 2/3, AP = 1/2 * 2/3 + 1/2 * 2/3 = 2/3."""
    rng = np.random.default_rng(12)
    gt = ground_truth_scene(2, rng)
    caps = [moved(gt, 0, 0, 1.0), moved(gt, 0, 0, 0.0), moved(gt, 1, 0, 0.0)]
    pred = Caps(*(np.array(values) for values in zip(*caps)), np.array([0.9, 0.8, 0.7]))
    result = evaluate([pred], [gt])
    assert result.ap25 == pytest.approx(5 / 6)
    assert result.ap50 == pytest.approx(2 / 3)
    assert result.n_matched == 2


def test_the_bounding_sphere_prefilter_keeps_every_overlapping_pair():
    """iou_matrix skips pairs whose bounding spheres are apart; on 40 caps crowded in a 6 cm square
    (most pairs overlap, some barely) it must equal box_iou over every pair, spin aligned to the truth."""
    rng = np.random.default_rng(13)
    n = 40
    radius = rng.uniform(0.01, 0.02, n)
    gt = Caps(np.column_stack([rng.uniform(-0.03, 0.03, (n, 2)), rng.uniform(-0.005, 0.005, n)]),
                   cap_rotation(*rng.uniform(-0.6, 0.6, size=(3, n))),
                   np.column_stack([radius, radius * rng.uniform(0.8, 1.2, n), 2 * radius / 3]))
    pred = Caps(gt.centers + rng.normal(0, 0.01, (n, 3)), cap_rotation(*rng.uniform(-0.6, 0.6, size=(3, n))),
                     gt.scales * rng.uniform(0.7, 1.3, (n, 3)), rng.uniform(size=n))
    full = np.array([[box_iou(cap_box(pred.centers[i], align_spin(pred.rotations[i], gt.rotations[j]), pred.scales[i]),
                              cap_box(gt.centers[j], gt.rotations[j], gt.scales[j])) for j in range(n)]
                     for i in range(n)])
    assert 0 < np.mean(full > 0) < 1 and (full[full > 0] < 0.02).any()
    np.testing.assert_allclose(iou_matrix(pred, gt), full, atol=1e-12)
