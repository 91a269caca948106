"""From caps to a pick plan: which caps are ready, from where the gripper comes to each, whether it fits
between the neighbours, which caps wait for others, and the order to take them in.

Everything is computed for all caps at once from the detections and the fused cloud, in the caps'
frame, with ``up`` the bed's normal in that frame:

- ``ready``: the cap is as wide as ``PickConfig.pick_diameter_mm`` and scored at least ``min_score``.
- ``grasp`` and ``approach``: a suction cup takes a cap at the top of its dome, fingers at its rim (the
  cap's wide base); the gripper comes along ``approach`` (a unit vector pointing away from the cap, the
  way the gripper moves back out), the cap's axis turned toward ``up`` as far as ``max_tilt_deg`` asks.
- ``clearance_mm``: the free room around the approach line from the grasp point up: the distance from
  that line to the nearest point of the cloud or of another cap's dome, leaving out the cap's own and
  those of the caps it waits for. The cloud is bucketed in cubes once (``points_in_boxes``), so each cap
  looks only at the points near its line.
  ``fits`` says whether the gripper's radius (the cup's; for fingers, the cap's radius plus
  ``finger_clearance_mm``) fits in it, and for fingers whether the cap fits between them.
- ``blocked_by``: the caps whose dome the approach line passes through above the grasp point (a small
  cap under a larger one's rim waits for it).
- ``order``: the caps that can be picked (ready, fitting, and waiting only for caps that can be picked),
  each after the caps that block it, in the shortest order greedy nearest-neighbour steps between grasp
  points find from the best start (``pick_order``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from common.geometry import transform_points
from perception.cap import Caps, cap_wireframe, rotation_from_axis

GripperKind = Literal["suction", "fingers"]
"""A suction cup takes a cap on the top of its dome; fingers close around its rim."""
CLEARANCE_REACH_MM = 30.0
"""Room beyond this around the approach line is not looked for, unless the gripper needs more: the
clearance reads at most this (twice the default cup's radius), or the room the gripper needs."""
APPROACH_REACH_MM = 60.0
"""How far up the approach line, from the grasp point, obstacles count: above the tallest caps."""
OWN_SURFACE = 1.15
"""A point within this many times a cap's semi-axes of its centre is the cap's own (when the cloud
comes without per-point cap labels)."""
BELOW_GRASP_MM = 1.0
"""Points this far below the grasp point (along the approach) still count against the gripper."""
GRID_CELL_MM = 10.0
"""The edge of the cubes the cloud is bucketed in to find the points near each approach: small beside
the reach, so that a cap's search takes little of the soil below its grasp point."""


@dataclass(frozen=True)
class PickConfig:
    """The gripper and when a cap is worth picking."""

    gripper: GripperKind = "suction"
    """The gripper: a suction cup on the cap's top, or fingers around its rim."""
    gripper_diameter_mm: float = 30.0
    """The suction cup's diameter, or the widest cap the fingers open around."""
    finger_clearance_mm: float = 8.0
    """Fingers: the room each needs beside the cap's rim."""
    max_tilt_deg: float = 30.0
    """How far from vertical the gripper may come in."""
    pick_diameter_mm: float = 30.0
    """Caps narrower than this are left to grow."""
    min_score: float = 0.5
    """Caps scored lower than this are uncertain: kept in the detection document, flagged
    ``"uncertain": true``, and not picked."""

    def __post_init__(self):
        if self.gripper not in ("suction", "fingers"):
            raise ValueError(f"unknown gripper {self.gripper!r}; choose suction or fingers")
        if not 0.0 <= self.max_tilt_deg <= 90.0:
            raise ValueError(f"max_tilt_deg must be 0-90, got {self.max_tilt_deg}")
        for name in ("gripper_diameter_mm", "pick_diameter_mm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.finger_clearance_mm < 0:
            raise ValueError(f"finger_clearance_mm must not be negative, got {self.finger_clearance_mm}")


@dataclass(frozen=True)
class PickPlan:
    """The plan over K caps (cap k's id is k), in the caps' frame."""

    ready: np.ndarray
    """(K,) bool."""
    grasp: np.ndarray
    """(K, 3) metres."""
    approach: np.ndarray
    """(K, 3) unit vectors, away from the cap."""
    clearance_mm: np.ndarray
    """(K,) free room around the approach line, at most ``clearance_reach_mm`` of the config."""
    fits: np.ndarray
    """(K,) bool."""
    blocks: np.ndarray
    """(K, K) bool: ``blocks[j, i]`` when cap j lies over cap i's approach (i waits for j)."""
    order: tuple[int, ...]
    """The caps to pick, in order."""
    travel_m: float
    """Length of the path through the grasp points in ``order``."""

    def moved(self, T_frame_caps: np.ndarray) -> "PickPlan":
        """The same plan in another frame (a rigid 4x4): grasp points and approaches move."""
        return replace(self, grasp=transform_points(T_frame_caps, self.grasp),
                       approach=self.approach @ T_frame_caps[:3, :3].T)

    def blocked_by(self, cap: int) -> list[int]:
        return np.flatnonzero(self.blocks[:, cap]).tolist()

    def to_document(self) -> dict:
        """The plan as the detection document's ``"plan"``: the order, the path's length and one entry
        per cap (``id`` as in ``"mushrooms"``; ``order`` is its place in the order, null when it is not
        picked)."""
        place = {cap: k for k, cap in enumerate(self.order)}
        caps = [{"id": k, "ready": bool(self.ready[k]), "grasp": self.grasp[k].tolist(),
                 "approach": self.approach[k].tolist(), "clearance_mm": float(self.clearance_mm[k]),
                 "fits": bool(self.fits[k]), "blocked_by": self.blocked_by(k), "order": place.get(k)}
                for k in range(len(self.ready))]
        return {"order": list(self.order), "travel_m": float(self.travel_m), "caps": caps}


PLAN_COLORS = {"next": (60, 200, 80), "held": (240, 170, 30), "growing": (150, 150, 150)}
"""How viewers colour a plan's approach arrows: caps in the order green, ready caps the gripper cannot
take yet (no room, or waiting for a cap it cannot take) amber, caps not ready grey."""
APPROACH_ARROW = 0.04
"""Metres: the length of an approach arrow in a viewer, about a gripper's reach above a cap."""


def plan_marks(plan: dict) -> list[tuple[str, str]]:
    """What a viewer shows of each cap of a plan document: its kind (a key of PLAN_COLORS) and its label
    (its place in the order from 1, or why it waits)."""
    kinds = ["next" if cap["order"] is not None else "held" if cap["ready"] else "growing" for cap in plan["caps"]]
    return [(kind, f"{cap['order'] + 1}" if kind == "next" else
             ("no room" if not cap["fits"] else "waits") if kind == "held" else "")
            for cap, kind in zip(plan["caps"], kinds)]


def plan_of_result(result, bed_points: np.ndarray, config: PickConfig, T_frame_bed: np.ndarray) -> dict:
    """The detection document's ``"plan"`` for a ``perception.detect.SceneResult`` in the bed frame (its
    cloud ``bed_points``), given in the frame ``T_frame_bed`` puts the caps in."""
    plan = plan_picks(result.caps, bed_points, config, point_labels=result.point_labels)
    return plan.moved(T_frame_bed).to_document()


def plan_picks(caps: Caps, points: np.ndarray, config: PickConfig = PickConfig(),
               up: np.ndarray = np.array([0.0, 0.0, 1.0]), point_labels: np.ndarray | None = None) -> PickPlan:
    """The pick plan of ``caps`` on a cloud ``points`` (N, 3) in the same frame (metres), ``up`` the bed's
    normal there; ``point_labels`` (N,) gives each point's cap (-1: none) when the detector says so."""
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    count = len(caps)
    if count == 0:
        empty = np.zeros((0, 3))
        return PickPlan(np.zeros(0, bool), empty, empty, np.zeros(0), np.zeros(0, bool), np.zeros((0, 0), bool),
                        (), 0.0)
    radii_mm = 1000.0 * caps.radii
    ready = (2 * radii_mm >= config.pick_diameter_mm) & (caps.score_array() >= config.min_score)
    approach = tilted_toward(caps.axes, up, np.radians(config.max_tilt_deg))
    on_top = config.gripper == "suction"
    grasp = caps.centers + (caps.scales[:, 2:3] * caps.axes if on_top else 0.0)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    blocks = lines_through_domes(caps, grasp, approach)
    clearance = clearances_mm(caps, points, point_labels, grasp, approach, blocks, up, clearance_reach_mm(config))
    fits = clearance >= needed_room_mm(config, radii_mm)
    if not on_top:  # fingers open only so wide
        fits &= 2 * radii_mm <= config.gripper_diameter_mm
    pickable = can_be_picked(ready & fits, blocks)
    order = pick_order(grasp, blocks, pickable)
    travel = float(np.linalg.norm(np.diff(grasp[list(order)], axis=0), axis=1).sum()) if len(order) > 1 else 0.0
    return PickPlan(ready, grasp, approach, clearance, fits, blocks, order, travel)


def tilted_toward(axes: np.ndarray, up: np.ndarray, max_tilt: float) -> np.ndarray:
    """Unit ``axes`` (K, 3) turned toward ``up`` in the plane they span with it, so that none leans
    more than ``max_tilt`` radians from it; those within the limit stay as they are."""
    axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    cosine = np.clip(axes @ up, -1.0, 1.0)
    side = axes - cosine[:, None] * up
    length = np.linalg.norm(side, axis=1, keepdims=True)
    side = np.divide(side, length, out=np.zeros_like(side), where=length > 1e-12)
    clamped = np.cos(max_tilt) * up + np.sin(max_tilt) * side
    return np.where((np.arccos(cosine) > max_tilt)[:, None], clamped, axes)


def needed_room_mm(config: PickConfig, radii_mm: np.ndarray) -> np.ndarray:
    """Per cap, the room (mm) the gripper needs around the approach line: the cup's radius, or for
    fingers the cap's radius plus the fingers' clearance."""
    if config.gripper == "suction":
        return np.full(len(radii_mm), config.gripper_diameter_mm / 2)
    return radii_mm + config.finger_clearance_mm


def clearance_reach_mm(config: PickConfig) -> float:
    """How far around the approach line room is looked for: ``CLEARANCE_REACH_MM``, or the most the
    gripper can need (fingers open around caps up to ``gripper_diameter_mm``)."""
    return max(CLEARANCE_REACH_MM, float(needed_room_mm(config, np.array([config.gripper_diameter_mm / 2]))[0]))


def clearances_mm(caps: Caps, points: np.ndarray, point_labels: np.ndarray | None, grasp: np.ndarray,
                  approach: np.ndarray, blocks: np.ndarray, up: np.ndarray, reach_mm: float) -> np.ndarray:
    """Per cap, the distance (mm) from its approach line (from just below the grasp point up to
    ``APPROACH_REACH_MM``) to the nearest obstacle, at most ``reach_mm``: a cloud point, or a point of
    another cap's dome (its rim and two meridians). The cap's own points do not count, nor those of the
    caps it waits for (``blocks``), which are gone when its turn comes: a point is a cap's by the
    detector's label, or, unlabelled, when it lies in the cap's ellipsoid grown by ``OWN_SURFACE`` (a
    dome's edge the detector left out)."""
    count = len(caps)
    domes = cap_wireframe(caps.centers, caps.rotations, caps.scales)
    obstacles = np.concatenate([points, domes.reshape(-1, 3)])
    labels = np.full(len(points), -1, np.int64) if point_labels is None else np.asarray(point_labels, np.int64)
    owner = np.concatenate([labels, np.repeat(np.arange(count), domes.shape[1])])
    reach, below, height = reach_mm / 1000.0, BELOW_GRASP_MM / 1000.0, APPROACH_REACH_MM / 1000.0
    # the search box of each cap bounds its cylinder: the axis from below the grasp point up, widened on
    # each axis of the bed's frame by the reach times the sine of the cylinder's axis's angle to it
    basis = rotation_from_axis(up)  # columns: two directions across the bed, and up
    start, end = (grasp - below * approach) @ basis, (grasp + height * approach) @ basis
    widen = reach * np.sqrt(np.clip(1.0 - np.square(approach @ basis), 0.0, None))
    local = basis.T @ obstacles.T  # (3, M): across the bed twice, and up
    cap_index, obstacle_index = points_in_boxes(local, np.minimum(start, end) - widen,
                                                np.maximum(start, end) + widen, GRID_CELL_MM / 1000.0)
    # the pairs come grouped by cap, so each cap's grasp point and approach are repeated, not gathered
    pairs_per_cap = np.bincount(cap_index, minlength=count)
    grasp_local, approach_local = grasp @ basis, approach @ basis
    offset = [local[d][obstacle_index] - np.repeat(grasp_local[:, d], pairs_per_cap) for d in range(3)]
    along = sum(offset[d] * np.repeat(approach_local[:, d], pairs_per_cap) for d in range(3))
    across_squared = offset[0] ** 2 + offset[1] ** 2 + offset[2] ** 2 - along ** 2
    counted = np.flatnonzero((along >= -below) & (along <= height) & (across_squared < reach ** 2))
    cap_index, obstacle_index = cap_index[counted], obstacle_index[counted]
    across = np.sqrt(np.clip(across_squared[counted], 0.0, None))
    holder = owner[obstacle_index]
    gone = (holder == cap_index) | ((holder >= 0) & blocks[np.maximum(holder, 0), cap_index])
    unlabelled = np.flatnonzero(holder < 0)
    unlabelled_cap = cap_index[unlabelled]
    gone[unlabelled] = in_grown_cap(caps, unlabelled_cap, obstacles[obstacle_index[unlabelled]])
    waiter, waited = np.nonzero(blocks.T)  # grouped by waiter: the unlabelled points of a cap's blockers
    if len(waiter):                         # are gone with them
        blockers_per_cap = np.bincount(waiter, minlength=count)
        first_blocker = np.cumsum(blockers_per_cap) - blockers_per_cap
        pair = np.repeat(unlabelled, blockers_per_cap[unlabelled_cap])
        blocker = waited[ranges(first_blocker[unlabelled_cap], blockers_per_cap[unlabelled_cap])]
        inside = in_grown_cap(caps, blocker, obstacles[obstacle_index[pair]])
        gone[pair[inside]] = True
    clearance = np.full(count, reach)
    np.minimum.at(clearance, cap_index[~gone], across[~gone])
    return 1000.0 * clearance


def in_grown_cap(caps: Caps, cap_index: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Whether each of ``points`` lies in its cap's ellipsoid grown by ``OWN_SURFACE``."""
    local = np.einsum("kyx,ky->kx", caps.rotations[cap_index], points - caps.centers[cap_index])
    return np.square(local / caps.scales[cap_index]).sum(1) <= OWN_SURFACE ** 2


def points_in_boxes(coords: np.ndarray, low: np.ndarray, high: np.ndarray, cell: float) -> tuple[np.ndarray, ...]:
    """Pairs (box, point) holding every point of ``coords`` (3, N) that lies in an axis-aligned box
    (``low``, ``high``: (B, 3)), and some near it: the points are bucketed once in cubes of ``cell``
    (sorted by cube, a radix sort), and each box takes the points of the cubes it overlaps. A KD-tree
    over the whole cloud costs more to build than the plan may take; buckets cost one sort."""
    coords = np.ascontiguousarray(coords)
    origin = coords.min(1)
    span = coords.max(1) - origin
    while True:  # cube indices fit 16 bits, which numpy sorts by radix
        shape = (span / cell).astype(np.int64) + 1
        if shape.prod() < 2 ** 16:
            break
        cell *= 1.25
    cube = np.floor((coords - origin[:, None]) / cell)  # in floats: one cast to integers, not three
    key = ((cube[0] * shape[1] + cube[1]) * shape[2] + cube[2]).astype(np.uint16)
    by_cube = np.argsort(key, kind="stable")
    per_cube = np.bincount(key, minlength=int(shape.prod()))
    cube_start = np.cumsum(per_cube) - per_cube
    first = np.clip(np.floor((low - origin) / cell).astype(np.int64), 0, shape - 1)
    last = np.clip(np.floor((high - origin) / cell).astype(np.int64), 0, shape - 1)
    empty = (high < origin).any(1) | (low > origin + shape * cell).any(1)
    extent = np.where(empty[:, None], 0, last - first + 1)
    cubes_per_box = extent.prod(1)
    box = np.repeat(np.arange(len(low)), cubes_per_box)
    within = ranges(np.zeros(len(low), np.int64), cubes_per_box)
    size = extent[box]
    step = np.stack([within // (size[:, 1] * size[:, 2]), within // size[:, 2] % size[:, 1], within % size[:, 2]], 1)
    at = first[box] + step
    cube_key = (at[:, 0] * shape[1] + at[:, 1]) * shape[2] + at[:, 2]
    taken = per_cube[cube_key]
    return np.repeat(box, taken), by_cube[ranges(cube_start[cube_key], taken)]


def ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The ranges ``starts[i]`` to ``starts[i] + counts[i]`` (exclusive), one after another."""
    return np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts - starts, counts)


def lines_through_domes(caps: Caps, grasp: np.ndarray, approach: np.ndarray) -> np.ndarray:
    """(K, K) bool: ``[j, i]`` when the line from cap i's grasp point along its approach passes through
    cap j's dome (the upper half of its ellipsoid) above the grasp point, i != j."""
    # each line in each cap's frame, scaled so that the cap's ellipsoid is the unit sphere: |o + t d| = 1
    origin = np.einsum("jyx,jay->jax", caps.rotations, grasp[None] - caps.centers[:, None]) / caps.scales[:, None]
    direction = np.einsum("jyx,ay->jax", caps.rotations, approach) / caps.scales[:, None]
    a = np.einsum("jax,jax->ja", direction, direction)
    b = 2 * np.einsum("jax,jax->ja", origin, direction)
    c = np.einsum("jax,jax->ja", origin, origin) - 1.0
    discriminant = b * b - 4 * a * c
    root = np.sqrt(np.clip(discriminant, 0.0, None))
    hits = np.zeros(a.shape, bool)
    for sign in (-1.0, 1.0):
        t = (-b + sign * root) / (2 * a)
        hits |= (discriminant > 0) & (t > 0) & (origin[..., 2] + t * direction[..., 2] >= 0)
    np.fill_diagonal(hits, False)
    return hits


def can_be_picked(candidates: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """The ``candidates`` that can be taken one after another, each once every cap over it is gone: not
    those waiting for a cap that is no candidate, nor caps that lie over each other in a ring."""
    picked = np.zeros(len(candidates), bool)
    while True:
        free = candidates & ~picked & ~(blocks & ~picked[:, None]).any(0)
        if not free.any():
            return picked
        picked |= free


def pick_order(grasp: np.ndarray, blocks: np.ndarray, pickable: np.ndarray) -> tuple[int, ...]:
    """The pickable caps in an order where each comes after every cap that blocks it, short in travel:
    from every start at once, each path steps to the nearest cap whose blockers are all taken; the
    shortest path wins."""
    caps = np.flatnonzero(pickable)
    if len(caps) == 0:
        return ()
    points = grasp[caps]
    distance = np.linalg.norm(points[:, None] - points[None], axis=2)
    waits = blocks[np.ix_(caps, caps)]  # waits[j, i]: i waits for j
    free = ~waits.any(0)
    starts = np.flatnonzero(free)
    paths = np.zeros((len(starts), len(caps)), np.int64)
    paths[:, 0] = starts
    taken = np.zeros((len(starts), len(caps)), bool)
    taken[np.arange(len(starts)), starts] = True
    length = np.zeros(len(starts))
    for step in range(1, len(caps)):
        # a cap is open once every cap it waits for is taken
        open_ = ~taken & ~(waits[None] & ~taken[:, :, None]).any(1)
        here = paths[:, step - 1]
        cost = np.where(open_, distance[here], np.inf)
        nearest = cost.argmin(1)
        length += cost[np.arange(len(starts)), nearest]
        paths[:, step] = nearest
        taken[np.arange(len(starts)), nearest] = True
    best = int(np.argmin(length))
    return tuple(int(caps[k]) for k in paths[best])
