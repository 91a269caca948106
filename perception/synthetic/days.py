"""One synthetic bed scanned on several days, with the truth a growth tracker is scored on.

The bed is made once (``scene.build_bed``) with its caps at their size on the last day; each cap grows
at its own rate, so on an earlier day it is smaller by its rate times the days left, scaled about the
centre of its base (a cap that shrinks never collides, so every day's bed is as valid as the last's).
A cap narrower than ``pin_mm`` on a day is not there yet (a new pin appears later); a cap that has
reached ``pick_mm`` may be picked before any later scan, and is gone from then on. The scanning rig is
placed a little differently each day, so each day's points are in that day's scan frame, with the
bed's pose in it (``T_scan_bed``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from perception.synthetic.scene import BedMeshes, SceneConfig, _viewpoint, _visible_points, build_bed

SECONDS_PER_DAY = 86400.0


@dataclass(frozen=True)
class GrowthConfig:
    """How a bed changes between daily scans."""

    days: int = 5
    growth_mm_per_day: tuple[float, float] = (1.5, 5.0)
    """Each cap's growth of diameter per day, drawn per cap from [low, high]."""
    pin_mm: float = 12.0
    """Caps narrower than this are not there yet."""
    pick_mm: float = 50.0
    """The pick size: a cap this wide may be picked before a later scan."""
    pick_probability: float = 0.3
    """Chance that a cap at the pick size is picked before the next scan."""
    rig_shift_m: float = 0.02
    """The rig's placement: each day shifted up to this far across the bed, in x and y."""
    rig_turn_deg: float = 5.0
    """...turned up to this far about the vertical..."""
    rig_tilt_deg: float = 1.0
    """...and tilted up to this far."""

    def __post_init__(self) -> None:
        if self.days < 1:
            raise ValueError(f"a bed is scanned on at least one day, got {self.days}")
        low, high = self.growth_mm_per_day
        if not 0 <= low <= high:
            raise ValueError(f"growth_mm_per_day wants 0 <= LOW <= HIGH, got {low} {high}")


@dataclass(frozen=True)
class DayScan:
    """One day's scan of the bed: points and true caps in the scan frame, and each cap's identity."""

    day: int
    time_s: float
    """Seconds since the first scan."""
    points: np.ndarray
    cap_ids: np.ndarray
    """(K,) which of the bed's caps each true cap is (the same cap keeps its id over the days)."""
    centers: np.ndarray
    rotations: np.ndarray
    scales: np.ndarray
    diameters_mm: np.ndarray
    T_scan_bed: np.ndarray


@dataclass(frozen=True)
class BedHistory:
    """The bed's caps over the days, in the bed frame: each cap's diameter per day (NaN where it is
    not there), its growth rate and the day it was picked (-1: never)."""

    seed: int
    diameters_mm: np.ndarray
    """(caps, days)."""
    growth_mm_per_day: np.ndarray
    picked_on: np.ndarray
    """The first day a picked cap is gone on (-1: it never is)."""
    scans: tuple[DayScan, ...]


def bed_over_days(seed: int, config: SceneConfig = SceneConfig(mushrooms=(10, 25)),
                  growth: GrowthConfig = GrowthConfig()) -> BedHistory:
    """The same bed scanned on ``growth.days`` days; the same seed and configs give the same history."""
    rng = np.random.default_rng(seed)
    bed = build_bed(rng, config)
    caps, days = len(bed.centers), growth.days
    rates = rng.uniform(*growth.growth_mm_per_day, caps)
    final_mm = 2000 * bed.scales[:, :2].mean(1)  # as perception.cap.Caps.radii reads a cap
    diameters = final_mm[:, None] - rates[:, None] * (days - 1 - np.arange(days))[None]
    present = diameters >= growth.pin_mm
    picked_on = np.full(caps, -1)
    for day in range(1, days):  # picked between scans: gone from this day on
        ripe = present[:, day - 1] & (diameters[:, day - 1] >= growth.pick_mm) & (picked_on < 0)
        picked = ripe & (rng.random(caps) < growth.pick_probability)
        picked_on[picked] = day
    for cap in np.flatnonzero(picked_on >= 0):
        present[cap, picked_on[cap]:] = False
    diameters = np.where(present, diameters, np.nan)
    eye, target = _viewpoint(rng, config)
    scans = tuple(_scan(rng, bed, config, day, diameters[:, day], growth, eye, target) for day in range(days))
    return BedHistory(seed, diameters, rates, picked_on, scans)


def _scan(rng, bed: BedMeshes, config: SceneConfig, day: int, diameters_mm: np.ndarray, growth: GrowthConfig,
          eye: np.ndarray, target: np.ndarray) -> DayScan:
    """The bed on one day (caps scaled to their day's size, absent ones dropped), seen by the rig placed
    as it is that day."""
    there = np.isfinite(diameters_mm)
    factor = np.where(there, diameters_mm / (2000 * bed.scales[:, :2].mean(1)), 1.0)
    vertex_cap = np.full(len(bed.vertices), -1)
    cap_triangles = bed.triangle_instance >= 0
    vertex_cap[bed.triangles[cap_triangles].ravel()] = np.repeat(bed.triangle_instance[cap_triangles], 3)
    on_cap = vertex_cap >= 0
    vertices = bed.vertices.copy()
    centers = bed.centers[vertex_cap[on_cap]]
    vertices[on_cap] = centers + factor[vertex_cap[on_cap], None] * (vertices[on_cap] - centers)
    kept = (bed.triangle_instance < 0) | there[np.maximum(bed.triangle_instance, 0)]
    renumber = np.cumsum(there) - 1
    instance = np.where(bed.triangle_instance[kept] >= 0, renumber[np.maximum(bed.triangle_instance[kept], 0)], -1)
    day_bed = BedMeshes(vertices, bed.triangles[kept], instance.astype(np.int32), bed.triangle_is_cap[kept],
                        bed.centers[there], bed.rotations[there], bed.scales[there] * factor[there, None], bed.terrain)
    T_scan_bed = _rig_placement(rng, growth)
    T_bed_scan = np.linalg.inv(T_scan_bed)
    day_eye = T_bed_scan[:3, :3] @ (eye - target) + target  # the rig turns about the bed's centre with it
    spacing = config.spacing * rng.uniform(*config.jitter)
    points, _ = _visible_points(rng, day_bed, config, spacing, day_eye, target)
    R, t = T_scan_bed[:3, :3], T_scan_bed[:3, 3]
    return DayScan(day, day * SECONDS_PER_DAY, (points @ R.T + t).astype(np.float32), np.flatnonzero(there),
                   day_bed.centers @ R.T + t, R @ day_bed.rotations, day_bed.scales, diameters_mm[there], T_scan_bed)


def _rig_placement(rng: np.random.Generator, growth: GrowthConfig) -> np.ndarray:
    """T_scan_bed of one day: a turn about the vertical, a small tilt and a shift across the bed."""
    from scipy.spatial.transform import Rotation

    turn = np.radians(rng.uniform(-growth.rig_turn_deg, growth.rig_turn_deg))
    tilt_axis = rng.uniform(0, 2 * np.pi)
    tilt = np.radians(rng.uniform(0, growth.rig_tilt_deg))
    rotation = (Rotation.from_rotvec([0, 0, turn])
                * Rotation.from_rotvec(tilt * np.array([np.cos(tilt_axis), np.sin(tilt_axis), 0.0])))
    T = np.eye(4)
    T[:3, :3] = rotation.as_matrix()
    T[:3, 3] = [*rng.uniform(-growth.rig_shift_m, growth.rig_shift_m, 2), rng.uniform(-0.005, 0.005)]
    return T


def write_history(history: BedHistory, out_dir) -> list:
    """``bed_<seed>_day_<D>.npz`` per day (its points, true caps and ``T_scan_bed`` in the scan frame,
    ``cap_ids``, ``time_s``) and ``bed_<seed>_history.npz`` (each cap's diameter per day, growth rate
    and the day it was picked), each written whole; returns the paths."""
    from pathlib import Path

    from common.files import atomic_path

    out_dir = Path(out_dir)
    paths = []
    for scan in history.scans:
        path = out_dir / f"bed_{history.seed}_day_{scan.day}.npz"
        with atomic_path(path, keep_suffix=True) as tmp:
            np.savez_compressed(tmp, points=scan.points, cap_ids=scan.cap_ids, centers=scan.centers,
                                rotations=scan.rotations, scales=scan.scales, diameters_mm=scan.diameters_mm,
                                T_scan_bed=scan.T_scan_bed, time_s=scan.time_s, day=scan.day)
        paths.append(path)
    path = out_dir / f"bed_{history.seed}_history.npz"
    with atomic_path(path, keep_suffix=True) as tmp:
        np.savez_compressed(tmp, diameters_mm=history.diameters_mm, growth_mm_per_day=history.growth_mm_per_day,
                            picked_on=history.picked_on, seed=history.seed)
    return [*paths, path]
