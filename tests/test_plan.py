"""The pick plan on constructed beds whose readiness, clearances, blockers and order are worked out by
hand (each expected value's derivation is in the comment beside it)."""

import itertools

import numpy as np
import pytest

from perception.cap import Caps, cap_rotation
from perception.plan import (CLEARANCE_REACH_MM, PickConfig, can_be_picked, pick_order, plan_picks,
                             points_in_boxes, tilted_toward)


def upright_caps(rows):
    """Caps from (x, y, z, radius) rows in metres, upright, dome 2/3 as high as wide, scored 0.9."""
    rows = np.asarray(rows, np.float64)
    radii = rows[:, 3]
    return Caps(rows[:, :3], np.repeat(np.eye(3)[None], len(rows), 0),
                np.column_stack([radii, radii, 2 * radii / 3]), np.full(len(rows), 0.9))


# A and B: 40 mm caps; C: 20 mm (below the 30 mm pick size); E: a 60 mm cap on a stem, its base 30 mm up;
# D: a 32 mm cap under E's rim, 10 mm off E's axis.
BED = [(0.0, 0.0, 0.0, 0.020),     # A
       (0.1, 0.0, 0.0, 0.020),     # B
       (0.2, 0.0, 0.0, 0.010),     # C
       (0.0, 0.21, 0.0, 0.016),    # D
       (0.0, 0.2, 0.03, 0.030)]    # E
A, B, C, D, E = range(5)


# A point on E's dome 8 mm from D's line: E's local (8, 10, z) mm on its ellipsoid of semi-axes
# (30, 30, 20) has z = 20 sqrt(1 - (8/30)^2 - (10/30)^2) = 18.09 mm, 48.09 mm up.
ON_E_OVER_D = (0.008, 0.21, 0.03 + 0.020 * np.sqrt(1 - (8 / 30) ** 2 - (10 / 30) ** 2))


def bed_cloud():
    """Soil 2 mm under the caps' bases, every 5 mm, one stray point 12 mm from B's axis above B's top,
    and an unlabelled point of E's dome over D."""
    grid = np.arange(-0.05, 0.3, 0.005)
    x, y = np.meshgrid(grid, grid)
    soil = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, -0.002)])
    return np.vstack([soil, [[0.112, 0.0, 0.02]], [ON_E_OVER_D]])


def test_constructed_bed_by_hand():
    caps = upright_caps(BED)
    plan = plan_picks(caps, bed_cloud(), PickConfig(gripper="suction", gripper_diameter_mm=30.0,
                                                    pick_diameter_mm=30.0, min_score=0.5))
    # diameters 40, 40, 20, 32, 60 mm against 30 mm, all scored 0.9
    assert plan.ready.tolist() == [True, True, False, True, True]
    # suction takes each upright cap at its top, straight down
    heights = np.array([row[3] for row in BED]) * 2 / 3
    np.testing.assert_allclose(plan.grasp, np.array(BED)[:, :3] + np.c_[0 * heights, 0 * heights, heights])
    np.testing.assert_allclose(plan.approach, np.tile([0.0, 0.0, 1.0], (5, 1)))
    # D's line (x 0, y 0.21) meets E's dome: 10 mm off E's axis its dome stands 20 sqrt(1 - 1/9) = 18.9 mm
    # over E's base, which is above D's top (10.7 mm); no other line meets another dome
    assert [plan.blocked_by(k) for k in range(5)] == [[], [], [], [E], []]
    # B: the stray point is 12 mm from its line and 6.7 mm above its top: room 12 mm < the cup's 15 mm.
    # The soil lies more than 1 mm below every grasp point; E, and with it the point of its dome 8 mm
    # from D's line and 37 mm over D's top, is gone before D's turn; nothing else is within reach
    np.testing.assert_allclose(plan.clearance_mm, [CLEARANCE_REACH_MM, 12.0, CLEARANCE_REACH_MM,
                                                   CLEARANCE_REACH_MM, CLEARANCE_REACH_MM], atol=1e-9)
    assert plan.fits.tolist() == [True, False, True, True, True]
    # pickable: A, D, E (B does not fit, C is not ready); D after E. From A: A-E-D; from E: E-D-A
    grasp = {k: plan.grasp[k] for k in (A, D, E)}
    from_a = np.linalg.norm(grasp[A] - grasp[E]) + np.linalg.norm(grasp[E] - grasp[D])
    from_e = np.linalg.norm(grasp[E] - grasp[D]) + np.linalg.norm(grasp[D] - grasp[A])
    assert from_a < from_e
    assert plan.order == (A, E, D)
    assert plan.travel_m == pytest.approx(from_a)
    document = plan.to_document()
    assert document["order"] == [A, E, D]
    assert [cap["order"] for cap in document["caps"]] == [0, None, None, 2, 1]
    assert document["caps"][D]["blocked_by"] == [E]


def test_fingers_take_the_rim_and_need_room_beside_it():
    caps = upright_caps(BED[:2])
    cloud = np.array([[0.025, 0.0, 0.001]])  # 25 mm from A's axis, 1 mm above its rim
    plan = plan_picks(caps, cloud, PickConfig(gripper="fingers", gripper_diameter_mm=50.0,
                                              finger_clearance_mm=8.0, pick_diameter_mm=30.0))
    np.testing.assert_allclose(plan.grasp, np.array(BED[:2])[:, :3])
    # A needs 20 + 8 = 28 mm beside its axis and has 25; the point is 75 mm from B, A's rim 80 mm: B's
    # room is read as far as fingers opening to 50 mm can need, 25 + 8 = 33 mm
    np.testing.assert_allclose(plan.clearance_mm, [25.0, 33.0], atol=1e-9)
    assert plan.fits.tolist() == [False, True]
    # 40 mm caps in fingers that open to 35 mm: none fits
    narrow = plan_picks(caps, cloud, PickConfig(gripper="fingers", gripper_diameter_mm=35.0))
    assert not narrow.fits.any() and narrow.order == ()


def test_the_approach_turns_toward_vertical_only_past_the_tilt_limit():
    up = np.array([0.0, 0.0, 1.0])
    axes = cap_rotation(np.zeros(3), np.radians([0.0, 20.0, 45.0]))[:, :, 2]
    approach = tilted_toward(axes, up, np.radians(30.0))
    np.testing.assert_allclose(approach[:2], axes[:2])
    # 45 degrees about y, clamped to 30 in the same xz-plane
    np.testing.assert_allclose(approach[2], [np.sin(np.radians(30.0)), 0.0, np.cos(np.radians(30.0))], atol=1e-12)


def test_caps_over_each_other_in_a_ring_and_their_followers_wait_for_ever():
    blocks = np.zeros((4, 4), bool)
    blocks[0, 1] = blocks[1, 0] = True  # 0 and 1 each lie over the other
    blocks[1, 2] = True                 # 2 waits for 1
    assert can_be_picked(np.ones(4, bool), blocks).tolist() == [False, False, False, True]
    blocks[1, 0] = False                # the ring is broken: 0, then 1, then 2
    assert can_be_picked(np.ones(4, bool), blocks).tolist() == [True, True, True, True]
    assert can_be_picked(np.array([False, True, True, True]), blocks).tolist() == [False, False, False, True]


def test_the_order_respects_every_blocker_and_is_near_the_shortest():
    rng = np.random.default_rng(4)
    ratios = []
    for _ in range(30):
        count = 7
        grasp = rng.uniform(0, 0.5, (count, 3))
        blocks = np.triu(rng.random((count, count)) < 0.15, 1)  # blockers only from lower to higher ids
        order = pick_order(grasp, blocks, np.ones(count, bool))
        assert sorted(order) == list(range(count))
        place = {cap: k for k, cap in enumerate(order)}
        assert all(place[j] < place[i] for j, i in zip(*np.nonzero(blocks)))

        def length(path):
            return np.linalg.norm(np.diff(grasp[list(path)], axis=0), axis=1).sum()

        allowed = [path for path in itertools.permutations(range(count))
                   if all(path.index(j) < path.index(i) for j, i in zip(*np.nonzero(blocks)))]
        ratios.append(length(order) / min(length(path) for path in allowed))
    # greedy from every start: never shorter than the best, and on average within a quarter of it
    assert min(ratios) >= 1.0 - 1e-12
    assert np.mean(ratios) < 1.25


def test_a_moved_plan_moves_its_points_and_directions():
    plan = plan_picks(upright_caps(BED), bed_cloud())
    turn = np.eye(4)
    turn[:3, :3] = cap_rotation(0.3, -0.2)
    turn[:3, 3] = [1.0, 2.0, 3.0]
    moved = plan.moved(turn)
    np.testing.assert_allclose(moved.grasp, plan.grasp @ turn[:3, :3].T + turn[:3, 3])
    np.testing.assert_allclose(moved.approach, plan.approach @ turn[:3, :3].T)
    assert moved.order == plan.order


def test_an_empty_bed_has_an_empty_plan():
    plan = plan_picks(Caps.none(), np.zeros((10, 3)))
    assert plan.order == () and plan.to_document() == {"order": [], "travel_m": 0.0, "caps": []}


def test_bad_gripper_settings_are_refused():
    with pytest.raises(ValueError, match="gripper"):
        PickConfig(gripper="claw")
    with pytest.raises(ValueError, match="max_tilt_deg"):
        PickConfig(max_tilt_deg=120.0)


def test_the_replay_check_reports_readiness_and_order_changes_of_matched_caps():
    from pipeline.check import compare

    caps = upright_caps(BED)
    document = {**caps.to_document("bed", 1), "plan": plan_picks(caps, bed_cloud()).to_document()}
    assert compare([document], [document]).passed
    # the new run finds the same caps in another order of ids, and cap C (20 mm) grown past the pick size
    turned = [4, 3, 2, 1, 0]
    grown = upright_caps([BED[k] if k != C else (*BED[C][:3], 0.02) for k in turned])
    again = {**grown.to_document("bed", 1), "plan": plan_picks(grown, bed_cloud()).to_document()}
    report = compare([document], [again])
    new_c = turned.index(C)
    assert [d.status for d in report.diffs if d.expected_id == C] == ["changed"]  # its radius
    ready = [d for d in report.plan_diffs if d.what.endswith("ready")]
    assert [(d.what, d.expected, d.new) for d in ready] == [(f"cap {new_c} ready", False, True)]
    # C now in the order: the expected order (A, E, D) read in the new ids differs from the new one
    order = [d for d in report.plan_diffs if d.what == "order"]
    assert order and order[0].expected == [turned.index(A), turned.index(E), turned.index(D)]
    assert new_c in order[0].new and not report.passed
    assert "pick plan changes" in report.table()
    # documents without a plan (sessions recorded before it) are compared on caps alone
    assert compare([caps.to_document("bed", 1)], [document]).passed


def test_points_in_boxes_holds_every_point_of_each_box_once():
    rng = np.random.default_rng(3)
    points = rng.uniform([-0.3, -0.2, -0.02], [0.3, 0.2, 0.05], (5000, 3))
    low = rng.uniform([-0.35, -0.25, -0.03], [0.3, 0.2, 0.05], (40, 3))
    high = low + rng.uniform(0.0, 0.08, (40, 3))
    box, point = points_in_boxes(points.T, low, high, 0.01)
    found = set(zip(box.tolist(), point.tolist()))
    assert len(found) == len(box)  # no pair twice
    inside = ((points[None] >= low[:, None]) & (points[None] <= high[:, None])).all(2)
    assert set(zip(*map(np.ndarray.tolist, np.nonzero(inside)))) <= found
    # and little more than the cubes of 10 mm around each box hold
    grown = ((points[None] >= low[:, None] - 0.01) & (points[None] <= high[:, None] + 0.01)).all(2)
    assert all(grown[b, p] for b, p in found)
