"""The fused cloud of a bed and how it is made: pose priors (recorded poses, a rig with encoder or
fixed-step angles, or none), refinement, integration, and the bed frame; in one call (``fuse``) or
frame by frame (``Fuser``, one cloud per turn)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from capture.frames import DepthFrame
from fusion.bed import estimate_bed_frame
from fusion.integrate import IntegrationConfig, integrate
from fusion.registration import (PairResult, RegistrationConfig, View, chain_poses, check_frames, frame_id,
                                 prepare_view, refine_poses)
from fusion.turntable import Rig

ANGLE_SOURCES = ("auto", "pose", "encoder", "step", "unknown")


@dataclass(frozen=True)
class FusionConfig:
    """How frames become one cloud; defaults suit a bed seen from 0.3-0.5 m."""

    integration: IntegrationConfig = field(default_factory=IntegrationConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    refine: bool = True
    """Refine the prior poses by ICP and a pose graph (off: trust the prior)."""
    angles: str = "auto"
    """Where the prior comes from: "pose" (each frame's T_world_camera), "encoder" (the rig at each
    frame's turntable_angle), "step" (the rig at index x angle_step), "unknown" (chained registration),
    or "auto": encoder, then step, with a rig; recorded poses without one; else unknown."""
    angle_step: float | None = None
    """Radians per frame for "step" (default: the rig's)."""
    bed_distance: float = 0.008
    """RANSAC inlier distance of the bed plane (metres)."""

    def __post_init__(self) -> None:
        if self.angles not in ANGLE_SOURCES:
            raise ValueError(f"unknown angle source {self.angles!r}; use one of {', '.join(ANGLE_SOURCES)}")


@dataclass(frozen=True, eq=False)
class FusedCloud:
    """One surface of the bed, in the bed frame (z up, metres), and where it came from."""

    points: np.ndarray
    """(N, 3) float32, bed frame."""
    normals: np.ndarray
    """(N, 3) float32 unit normals, bed frame, facing the cameras."""
    colors: np.ndarray | None
    """(N, 3) uint8 when every frame had colour."""
    T_world_bed: np.ndarray
    frame_ids: tuple[str, ...]
    """``sensor@timestamp_ns`` of each source frame."""
    T_world_cameras: np.ndarray
    """(F, 4, 4) the poses the frames were fused at."""
    flagged: tuple[str, ...] = ()
    """Frames whose refinement was implausible or impossible: fused at their prior pose."""
    seconds: dict[str, float] = field(default_factory=dict)
    """Wall time per stage (views, prior, refine, integrate, bed), for latency plots and benches."""

    def __len__(self) -> int:
        return len(self.points)

    @staticmethod
    def from_world(points: np.ndarray, T_world_bed: np.ndarray, frame_ids: tuple[str, ...] = ()) -> "FusedCloud":
        """A cloud known only by its world-frame points and bed frame (as a session records it)."""
        T = np.asarray(T_world_bed, np.float64)
        bed = ((np.asarray(points, np.float64) - T[:3, 3]) @ T[:3, :3]).astype(np.float32)
        normals = np.zeros_like(bed)
        normals[:, 2] = 1.0
        return FusedCloud(bed, normals, None, T, tuple(frame_ids), np.zeros((0, 4, 4)))

    @property
    def world_points(self) -> np.ndarray:
        return (self.points @ self.T_world_bed[:3, :3].T.astype(np.float32)
                + self.T_world_bed[:3, 3].astype(np.float32))


def _angle_source(frames: list[DepthFrame], rig: Rig | None, config: FusionConfig) -> str:
    if config.angles != "auto":
        return config.angles
    if rig is not None:
        if rig.turntable is None or all(f.turntable_angle is not None for f in frames):
            return "encoder"
        if config.angle_step is not None or rig.angle_step is not None:
            return "step"
        return "unknown" if len(frames) > 1 else "encoder"
    if all(f.T_world_camera is not None for f in frames):
        return "pose"
    return "unknown" if len(frames) > 1 else "first"


def prior_poses(frames: list[DepthFrame], rig: Rig | None = None, config: FusionConfig = FusionConfig(),
                views: list[View] | None = None) -> tuple[np.ndarray, dict[tuple[int, int], PairResult]]:
    """Prior T_world_camera of every frame, and any registrations made on the way (chaining)."""
    source = _angle_source(frames, rig, config)
    if source == "pose":
        missing = [k for k, f in enumerate(frames) if f.T_world_camera is None]
        if missing:
            raise ValueError(f"frame {missing[0]} has no T_world_camera; give a rig or use angles='unknown'")
        poses = np.stack([np.asarray(f.T_world_camera, np.float64) for f in frames])
        _check_finite(poses, frames, "T_world_camera")
        return poses, {}
    if source == "first":
        return np.eye(4)[None], {}
    if source in ("encoder", "step") and rig is None:
        raise ValueError(f"angles={source!r} needs a rig (its turntable turns angles into poses)")
    if source == "encoder":
        if rig.turntable is None:
            return np.stack([rig.T_world_camera(f.sensor_id) for f in frames]), {}
        angles = np.array([np.nan if f.turntable_angle is None else f.turntable_angle for f in frames], np.float64)
        _check_finite(angles, frames, "turntable_angle")
        return np.stack([rig.T_world_camera(f.sensor_id, a) for f, a in zip(frames, angles)]), {}
    if source == "step":
        step = config.angle_step if config.angle_step is not None else rig.angle_step
        if step is None:
            raise ValueError("angles='step' needs an angle_step (in the config or the rig)")
        sensors = np.array([f.sensor_id for f in frames])
        index = np.array([np.count_nonzero(sensors[:k] == s) for k, s in enumerate(sensors)])
        return np.stack([rig.T_world_camera(f.sensor_id, k * step) for f, k in zip(frames, index)]), {}
    views = views or [prepare_view(f, config.registration) for f in frames]
    chain, pairs = chain_poses(views, config.registration)
    first = frames[0].T_world_camera
    T_world_first = rig.T_world_camera(frames[0].sensor_id, 0.0) if rig is not None else (
        np.asarray(first, np.float64) if first is not None and np.isfinite(first).all() else np.eye(4))
    return T_world_first @ chain, pairs


def _check_finite(values: np.ndarray, frames: list[DepthFrame], what: str) -> None:
    bad = np.flatnonzero(~np.isfinite(values.reshape(len(values), -1)).all(1))
    if len(bad):
        k = int(bad[0])
        raise ValueError(f"frame {k} ({frame_id(frames[k])}) has a missing or non-finite {what} "
                         f"({len(bad)} of {len(frames)} frames): drop those frames or fix the recording")


def bed_frame(points: np.ndarray, poses: np.ndarray, distance: float = 0.008) -> np.ndarray:
    """T_world_bed of a world-frame cloud, with z towards the cameras (they look down on the bed from
    closer than ``fusion.bed.CAMERA_RANGE``)."""
    eye = np.asarray(poses)[:, :3, 3].mean(0)
    T = estimate_bed_frame(np.asarray(points, np.float64) - eye, distance)
    T[:3, 3] += eye
    return T


def _fuse(frames: list[DepthFrame], views: list[View] | None, config: FusionConfig, rig: Rig | None) -> FusedCloud:
    seconds: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(stage: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        seconds[stage] = seconds.get(stage, 0.0) + now - clock
        clock = now

    if views is None and len(frames) > 1 and (config.refine or _angle_source(frames, rig, config) == "unknown"):
        views = [prepare_view(f, config.registration) for f in frames]
    lap("views")
    prior, pairs = prior_poses(frames, rig, config, views)
    lap("prior")
    poses, flagged = prior, ()
    if len(frames) > 1 and config.refine:
        refined = refine_poses(views, prior, config.registration, pairs)
        poses = refined.poses
        flagged = tuple(frame_id(frames[k]) for k in np.flatnonzero(refined.flagged))
    lap("refine")
    integration = config.integration
    if len(frames) == 1 and integration.mode != "merge":
        integration = replace(integration, mode="merge")
    surface = integrate(frames, poses, integration)
    lap("integrate")
    T_world_bed = bed_frame(surface.points, poses, config.bed_distance)
    rotation, origin = T_world_bed[:3, :3].astype(np.float32), T_world_bed[:3, 3].astype(np.float32)
    lap("bed")
    return FusedCloud(((surface.points - origin) @ rotation).astype(np.float32),
                      (surface.normals @ rotation).astype(np.float32), surface.colors, T_world_bed,
                      tuple(frame_id(f) for f in frames), poses, flagged, seconds)


def fuse(frames: list[DepthFrame], config: FusionConfig = FusionConfig(), rig: Rig | None = None) -> FusedCloud:
    """One cloud of the bed from depth frames: prior poses, refinement, integration, bed frame.

    A single frame gives its back-projected cloud (voxel-merged) in the bed frame. Raises ValueError
    with a one-line reason on unusable input (no frames, no intrinsics, no depth, non-finite poses
    or angles, no two views overlapping).
    """
    frames = list(frames)
    check_frames(frames)
    return _fuse(frames, None, config, rig)


class Fuser:
    """Fusion as frames arrive: each frame's ICP pyramid is built on arrival, and a cloud is fused
    when a turn is complete (angles from the encoder or the fixed step; every sensor has as many
    frames as the first) or, with ``every``, after that many frames. ``flush`` fuses what is left."""

    def __init__(self, config: FusionConfig = FusionConfig(), rig: Rig | None = None, every: int | None = None):
        if every is not None and every < 1:
            raise ValueError(f"every must be a positive number of frames, got {every}")
        self.config, self.rig, self.every = config, rig, every
        self._frames: list[DepthFrame] = []
        self._views: list[View] = []

    @property
    def pending(self) -> int:
        return len(self._frames)

    def add(self, frame: DepthFrame) -> FusedCloud | None:
        """Take one frame; the fused cloud when this frame completes a turn (or ``every`` frames)."""
        check_frames([frame])
        self._frames.append(frame)
        if self.config.refine or self.config.angles == "unknown":
            self._views.append(prepare_view(frame, self.config.registration))
        if (self.every is not None and len(self._frames) >= self.every) or (self.every is None and self._turn_done()):
            return self.flush()
        return None

    def flush(self) -> FusedCloud | None:
        """Fuse the pending frames (None when there are none) and start afresh."""
        if not self._frames:
            return None
        frames, views = self._frames, self._views
        self._frames, self._views = [], []
        return _fuse(frames, views if len(views) == len(frames) > 1 else None, self.config, self.rig)

    def _turn_done(self) -> bool:
        sensor = self._frames[0].sensor_id
        own = [f for f in self._frames if f.sensor_id == sensor]
        if len(own) < 2:
            return False
        if all(f.turntable_angle is not None for f in own):
            angles = np.unwrap(np.array([f.turntable_angle for f in own], np.float64))
            steps = np.abs(np.diff(angles))
            travelled, step = abs(angles[-1] - angles[0]), float(np.median(steps))
        else:
            step = self.config.angle_step if self.config.angle_step is not None else (
                self.rig.angle_step if self.rig is not None else None)
            if step is None:
                return False
            step, travelled = abs(step), abs(step) * (len(own) - 1)
        counts = {f.sensor_id: 0 for f in self._frames}
        for f in self._frames:
            counts[f.sensor_id] += 1
        return travelled + step >= 2 * np.pi - step / 4 and len(set(counts.values())) == 1


def height_colors(height: np.ndarray, top: float = 0.06) -> np.ndarray:
    """(N, 3) uint8 colours of heights above the bed in metres: dark soil brown at the bed through
    orange to pale cream at ``top`` and above, so caps read as light domes on dark ground."""
    stops = np.array([[60, 42, 30], [150, 90, 45], [235, 170, 90], [250, 240, 220]], np.float64)
    t = np.clip(np.asarray(height, np.float64) / top, 0.0, 1.0) * (len(stops) - 1)
    low = np.minimum(t.astype(np.int64), len(stops) - 2)
    weight = (t - low)[:, None]
    return np.round(stops[low] * (1 - weight) + stops[low + 1] * weight).astype(np.uint8)


def log_rerun(rec, fused: FusedCloud, entity: str = "world/fusion/cloud", radius: float = 0.0008) -> None:
    """The fused cloud in world coordinates (beside ``world/camera/<id>``), in its colours, or by
    height above the bed when it has none."""
    import rerun as rr

    colors = fused.colors if fused.colors is not None else height_colors(fused.points[:, 2])
    rec.log(entity, rr.Points3D(fused.world_points, colors=colors, radii=radius))
