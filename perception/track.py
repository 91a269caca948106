"""Caps followed across scans of one bed: the scans aligned on the soil (which does not move between
days; the caps grow), caps matched scan to scan so that each keeps its id, and per cap its diameter
over time, growth rate and the day it reaches the pick size; per bed the count per grade to come."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from perception.cap import Caps
from perception.grades import GradeTable

SECONDS_PER_DAY = 86400.0


@dataclass(frozen=True)
class Scan:
    """One scan of a bed: its points and detected caps in the scan's own frame, and when it was made."""

    time_s: float
    points: np.ndarray
    caps: Caps
    name: str = ""


@dataclass(frozen=True)
class TrackConfig:
    match_mm: float = 12.0
    """Caps whose centres lie farther apart than this once the scans are aligned are not one cap."""
    soil_margin_mm: float = 8.0
    """Points within a cap's radius plus this of its centre are the cap's, not soil: only soil aligns."""
    pick_mm: float = 50.0
    """The pick size a cap's ready day is forecast for."""
    horizon_days: int = 7
    """How many days ahead the bed's count per grade is forecast."""
    max_gap: int = 1
    """Scans a cap may go unseen (a missed detection) and still keep its id; unseen longer, it is gone."""
    min_soil_overlap: float = 0.5
    """The least share of a scan's soil the first scan's soil must cover once aligned: less, and the scans
    are not of one bed."""


class NotOneBed(ValueError):
    """Scans whose soil does not align: they are not of one bed."""


@dataclass(frozen=True)
class CapTrack:
    """One cap over the scans: where it was seen (scan index, cap index there), its diameters (mm) and
    times (days since the first scan), and what its growth says."""

    id: int
    scans: tuple[int, ...]
    caps: tuple[int, ...]
    days: np.ndarray
    diameters_mm: np.ndarray
    center: np.ndarray
    """Its last centre, in the first scan's frame."""
    growth_mm_per_day: float | None
    """The slope of a line through its diameters (None: seen once)."""
    ready_day: float | None
    """When it reaches the pick size (days since the first scan; None: not growing toward it)."""
    present: bool
    """Seen in the last scan (else picked or lost)."""


@dataclass(frozen=True)
class BedTracks:
    tracks: tuple[CapTrack, ...]
    T_first_scan: tuple[np.ndarray, ...]
    """Each scan's pose in the first scan's frame (the soil's alignment)."""
    soil_overlap: tuple[float, ...]
    forecast: dict = field(default_factory=dict)
    """{"days": [...], "grades": {name: [count per day]}}: the caps there on the last scan, grown on."""


def soil_points(points: np.ndarray, caps: Caps, margin_m: float) -> np.ndarray:
    """The points of a scan that lie within no detected cap's radius plus ``margin_m`` of its centre."""
    if len(caps) == 0:
        return points
    from scipy.spatial import cKDTree

    inside = cKDTree(points).query_ball_point(caps.centers, r=caps.radii + margin_m)
    keep = np.ones(len(points), bool)
    keep[np.concatenate([np.asarray(near, np.int64) for near in inside])] = False
    return points[keep]


def align(source: np.ndarray, target: np.ndarray, voxel: float = 0.003) -> tuple[np.ndarray, float]:
    """T_target_source of two scans' soil by point-to-plane ICP (Open3D), coarse to fine from where
    they lie, and the share of the source's soil within a voxel of the target's once aligned."""
    import open3d as o3d

    reg = o3d.pipelines.registration

    def cloud(points: np.ndarray, size: float):
        c = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64))).voxel_down_sample(size)
        c.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * size, max_nn=30))
        c.orient_normals_to_align_with_direction([0.0, 0.0, 1.0])
        return c

    T = np.eye(4)
    for size, distance in ((3 * voxel, 0.04), (2 * voxel, 0.015), (voxel, 0.006)):
        result = reg.registration_icp(cloud(source, size), cloud(target, size), distance, T,
                                      reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=distance / 2)),
                                      reg.ICPConvergenceCriteria(1e-7, 1e-7, 60))
        T = result.transformation
    fine_source, fine_target = cloud(source, voxel), cloud(target, voxel)
    overlap = reg.evaluate_registration(fine_source, fine_target, 1.5 * voxel, T).fitness
    return np.array(T), float(overlap)


def track_bed(scans: list[Scan], grades: GradeTable = GradeTable(), config: TrackConfig = TrackConfig()) -> BedTracks:
    """Align every scan onto the first on the soil, match caps scan to scan (nearest centres, one to
    one, within ``match_mm``), and fit each cap's growth; raises NotOneBed when a scan's soil does not
    align with the first's."""
    from scipy.optimize import linear_sum_assignment

    if not scans:
        raise ValueError("no scans to track")
    margin = config.soil_margin_mm / 1000
    first_soil = soil_points(scans[0].points, scans[0].caps, margin)
    poses, overlaps = [np.eye(4)], [1.0]
    for scan in scans[1:]:
        T, overlap = align(soil_points(scan.points, scan.caps, margin), first_soil)
        if overlap < config.min_soil_overlap:
            raise NotOneBed(f"{scan.name or 'a scan'} and {scans[0].name or 'the first scan'} are not of one bed: "
                            f"{overlap:.0%} of the soil aligns (at least {config.min_soil_overlap:.0%} wanted)")
        poses.append(T)
        overlaps.append(overlap)
    days = np.array([(scan.time_s - scans[0].time_s) / SECONDS_PER_DAY for scan in scans])
    # each track: [scans, caps, centres, last seen scan]
    tracks: list[dict] = []
    for index, (scan, T) in enumerate(zip(scans, poses)):
        centers = scan.caps.centers @ T[:3, :3].T + T[:3, 3]
        alive = [t for t in tracks if index - t["scans"][-1] <= 1 + config.max_gap]
        matched_caps: set[int] = set()
        if alive and len(centers):
            last = np.array([t["centers"][-1] for t in alive])
            cost = np.linalg.norm(centers[:, None] - last[None], axis=2)
            rows, cols = linear_sum_assignment(cost)
            for row, col in zip(rows, cols):
                if cost[row, col] <= config.match_mm / 1000:
                    alive[col]["scans"].append(index)
                    alive[col]["caps"].append(int(row))
                    alive[col]["centers"].append(centers[row])
                    matched_caps.add(int(row))
        for cap in range(len(centers)):
            if cap not in matched_caps:
                tracks.append({"scans": [index], "caps": [cap], "centers": [centers[cap]]})
    results = []
    for number, track in enumerate(tracks):
        seen_days = days[track["scans"]]
        diameters = np.array([2000 * scans[s].caps.radii[c] for s, c in zip(track["scans"], track["caps"])])
        rate = float(np.polyfit(seen_days, diameters, 1)[0]) if len(set(seen_days)) >= 2 else None
        results.append(CapTrack(number, tuple(track["scans"]), tuple(track["caps"]), seen_days, diameters,
                                track["centers"][-1], rate, _ready_day(seen_days, diameters, rate, config.pick_mm),
                                track["scans"][-1] == len(scans) - 1))
    return BedTracks(tuple(results), tuple(poses), tuple(overlaps),
                     forecast(results, days[-1], grades, config.horizon_days))


def _ready_day(days: np.ndarray, diameters: np.ndarray, rate: float | None, pick_mm: float) -> float | None:
    """When the cap's fitted line reaches ``pick_mm`` (its first day at or over it, if it has)."""
    if (diameters >= pick_mm).any():
        return float(days[np.argmax(diameters >= pick_mm)])
    if rate is None or rate <= 0:
        return None
    intercept = float(np.mean(diameters) - rate * np.mean(days))
    return (pick_mm - intercept) / rate


def forecast(tracks: list[CapTrack], last_day: float, grades: GradeTable, horizon_days: int) -> dict:
    """The count per grade on each of the next days of the caps there on the last scan, each grown on
    at its rate (one seen once stays as it is)."""
    present = [t for t in tracks if t.present]
    ahead = np.arange(1, horizon_days + 1)
    last = np.array([t.diameters_mm[-1] for t in present])
    rates = np.array([t.growth_mm_per_day or 0.0 for t in present])
    grown = last[:, None] + np.maximum(rates, 0)[:, None] * ahead[None] if present else np.zeros((0, len(ahead)))
    counts = {name: [0] * len(ahead) for name in (*grades.names,)}
    for day in range(len(ahead)):
        for name in grades.grade_of(grown[:, day]):
            counts.setdefault(name, [0] * len(ahead))[day] += 1
    return {"days": (last_day + ahead).tolist(), "grades": counts}
