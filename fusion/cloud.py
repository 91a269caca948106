"""The fused cloud of a bed and how it is made: pose priors (recorded poses, a rig with encoder or
fixed-step angles, or none), refinement, integration, and the bed frame; in one call (``fuse``) or
frame by frame (``Fuser``, one cloud per turn); ``UnitBuilder`` picks how a run groups frames into fused units."""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from capture.frames import DepthFrame
from common.geometry import transform_points
from fusion.bed import estimate_bed_frame
from fusion.integrate import (CameraPoints, IntegrationConfig, Surface, VoxelMerge, back_project, integrate,
                              merge_back_projected)
from fusion.registration import (PairResult, RegistrationConfig, View, chain_poses, check_frames, frame_id,
                                 prepare_view, refine_poses, register_pair)
from fusion.turntable import Rig

ANGLE_SOURCES = ("auto", "pose", "encoder", "step", "unknown")
BED_FIT_POINTS = 40_000
"""The bed plane is fitted to about this many of a fused cloud's points: the fit on all 130 k points
of a turn took 0.35-0.4 s."""


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
    def display_colors(self) -> np.ndarray:
        """(N, 3) uint8: the cloud's own colours, or its height above the bed on a colour ramp."""
        return self.colors if self.colors is not None else height_colors(self.points[:, 2])

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
    T = estimate_bed_frame(np.asarray(points, np.float64) - eye, distance, fit_points=BED_FIT_POINTS)
    T[:3, 3] += eye
    return T


def _box_corners(points: np.ndarray) -> np.ndarray:
    """The 8 corners of the axis-aligned box around ``points`` (none for no points)."""
    if not len(points):
        return np.zeros((0, 3), np.float32)
    columns = np.ascontiguousarray(points.T)  # a reduction along a short contiguous axis is ~20x slower
    lo, hi = columns.min(1), columns.max(1)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], np.float32)


class StreamingMerge:
    """Merge mode's integration as frames arrive: each frame is back-projected and its voxel sums
    taken at its prior pose; when the unit ends, only frames that refinement moved by more than
    ``MOVED_FRACTION`` of a voxel (0.5 mm at 2 mm, under the depth noise) are taken again at their
    refined pose, and the sums are added up."""

    MOVED_FRACTION = 0.25

    def __init__(self, config: IntegrationConfig, multi_view: bool):
        self.config, self.multi_view = config, multi_view
        self.views: list[CameraPoints] = []
        self._poses: list[np.ndarray | None] = []
        self._corners: list[np.ndarray] = []
        self._merge: VoxelMerge | None = None

    def add(self, frame: DepthFrame, prior: np.ndarray | None) -> None:
        view = back_project(frame, self.config, self.multi_view)
        if self._merge is None:
            self._merge = VoxelMerge(self.config.voxel, view.colors is not None)
        if prior is not None and (view.colors is not None) == self._merge.with_color:
            self._merge.add(len(self.views), view, prior)
        else:
            prior = None
        self.views.append(view)
        self._poses.append(prior)
        self._corners.append(_box_corners(view.points))

    def _moved(self, k: int, before: np.ndarray, after: np.ndarray) -> bool:
        corners = self._corners[k]
        if not len(corners):
            return False
        shift = np.linalg.norm(transform_points(before, corners) - transform_points(after, corners), axis=1).max()
        return shift > self.MOVED_FRACTION * self.config.voxel

    def surface(self, poses: np.ndarray) -> Surface:
        if any((v.colors is not None) != self._merge.with_color for v in self.views):
            return merge_back_projected(self.views, poses, self.config)
        for k, (view, pose) in enumerate(zip(self.views, poses)):
            if self._poses[k] is None or self._moved(k, self._poses[k], pose):
                self._merge.add(k, view, pose)
        return self._merge.surface()


def _fuse(frames: list[DepthFrame], views: list[View] | None, config: FusionConfig, rig: Rig | None,
          pairs: dict[tuple[int, int], PairResult] | None = None,
          merged: StreamingMerge | None = None) -> FusedCloud:
    """Fuse ``frames``; ``views``, ``pairs`` and ``merged`` are work already done as they arrived
    (ICP pyramids, registrations under the prior, merge mode's running voxel sums)."""
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
    prior, chained = prior_poses(frames, rig, config, views)
    lap("prior")
    poses, flagged = prior, ()
    if len(frames) > 1 and config.refine:
        refined = refine_poses(views, prior, config.registration, {**(pairs or {}), **chained})
        poses = refined.poses
        flagged = tuple(frame_id(frames[k]) for k in np.flatnonzero(refined.flagged))
    lap("refine")
    integration = config.integration
    if len(frames) == 1 and integration.mode != "merge":
        integration = replace(integration, mode="merge")
    if merged is not None and integration.mode == "merge":
        surface = merged.surface(poses)
    else:
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
    """Fusion as frames arrive: a cloud is fused when a turn is complete (angles from the encoder or
    the fixed step; every sensor has as many frames as the first) or, with ``every``, after that many
    frames; ``flush`` fuses what is left. What needs no later frame is done on arrival, so little is
    left when the unit ends: each frame's ICP pyramid, its registration with the frame just before
    it under the prior (when the prior is known per frame), and merge mode's back-projection."""

    def __init__(self, config: FusionConfig = FusionConfig(), rig: Rig | None = None, every: int | None = None):
        if every is not None and every < 1:
            raise ValueError(f"every must be a positive number of frames, got {every}")
        self.config, self.rig, self.every = config, rig, every
        self._step: float | None = None
        """The smallest turntable step seen in the run (a dropped frame leaves a larger one)."""
        self._start()

    def _start(self) -> None:
        self._frames: list[DepthFrame] = []
        self._views: list[View] = []
        self._pairs: dict[tuple[int, int], PairResult] = {}
        self._merge = StreamingMerge(self.config.integration, multi_view=self.every != 1)

    @property
    def pending(self) -> int:
        return len(self._frames)

    def add(self, frame: DepthFrame) -> FusedCloud | None:
        """Take one frame; the fused cloud when this frame completes a turn (or ``every`` frames), or
        when it lies a turn past the unit's first frame (then the unit before it; it starts the next)."""
        check_frames([frame])
        if self.every is None and self._overruns(frame):
            finished = self.flush()
            self.add(frame)
            return finished
        self._frames.append(frame)
        prior = self._prior()
        if self.config.integration.mode == "merge":
            self._merge.add(frame, None if prior is None else prior[-1])
        if self.config.refine or self.config.angles == "unknown":
            self._views.append(prepare_view(frame, self.config.registration))
            if prior is not None:
                self._register_on_arrival(prior)
        if (self.every is not None and len(self._frames) >= self.every) or (self.every is None and self._turn_done()):
            return self.flush()
        return None

    def _prior(self) -> np.ndarray | None:
        """The prior poses of the pending frames when each is known on its own (no registration)."""
        if _angle_source(self._frames, self.rig, self.config) not in ("pose", "encoder", "step", "first"):
            return None
        try:
            return prior_poses(self._frames, self.rig, self.config)[0]
        except ValueError:
            return None  # _fuse reports it with the whole unit

    def _register_on_arrival(self, prior: np.ndarray) -> None:
        """ICP of the newest frame onto the frame before it, from the prior: the consecutive pair is
        one refinement always asks for (``candidate_pairs``); pairs that depend on frames still to
        come (a turn's loop-closing pair, nearest views of other cameras) are left to the end."""
        j = len(self._frames) - 1
        if j == 0 or not self.config.refine or self.every == 1:
            return
        self._pairs[(j - 1, j)] = register_pair(self._views[j], self._views[j - 1],
                                                np.linalg.inv(prior[j - 1]) @ prior[j], self.config.registration,
                                                (j, j - 1))

    def flush(self) -> FusedCloud | None:
        """Fuse the pending frames (None when there are none) and start afresh."""
        if not self._frames:
            return None
        frames, views, pairs, merged = self._frames, self._views, self._pairs, self._merge
        self._start()
        # a unit of one frame (a turn cut short) keeps all its pixels, as a single view does
        return _fuse(frames, views if len(views) == len(frames) > 1 else None, self.config, self.rig, pairs,
                     merged if len(merged.views) == len(frames) and (len(frames) > 1 or not merged.multi_view)
                     else None)

    def _angles(self, frames: list[DepthFrame]) -> np.ndarray | None:
        """The unwrapped turntable angles of the first sensor's frames (None without encoder angles)."""
        sensor = self._frames[0].sensor_id if self._frames else frames[0].sensor_id
        own = [f.turntable_angle for f in frames if f.sensor_id == sensor]
        if not own or any(a is None for a in own):
            return None
        angles = np.unwrap(np.array(own, np.float64))
        steps = np.abs(np.diff(angles))
        if len(steps) and steps.max() > 0:
            smallest = float(steps[steps > 0].min())
            self._step = smallest if self._step is None else min(self._step, smallest)
        return angles

    def _overruns(self, frame: DepthFrame) -> bool:
        """The frame lies a whole turn past the unit's first (the frames that closed the turn were
        dropped): the unit ends before it."""
        if not self._frames or frame.sensor_id != self._frames[0].sensor_id:
            return False
        angles = self._angles([*self._frames, frame])
        step = self._step or 0.0
        return angles is not None and abs(angles[-1] - angles[0]) >= 2 * np.pi - step / 4

    def _turn_done(self) -> bool:
        sensor = self._frames[0].sensor_id
        own = [f for f in self._frames if f.sensor_id == sensor]
        if len(own) < 2:
            return False
        angles = self._angles(self._frames)
        if angles is not None:
            travelled, step = abs(angles[-1] - angles[0]), self._step or 0.0
        else:
            step = self.config.angle_step if self.config.angle_step is not None else (
                self.rig.angle_step if self.rig is not None else None)
            if step is None:
                return False
            step, travelled = abs(step), abs(step) * (len(own) - 1)
        counts = {f.sensor_id: 0 for f in self._frames}
        for f in self._frames:
            counts[f.sensor_id] += 1
        return step > 0 and travelled + step >= 2 * np.pi - step / 4 and len(set(counts.values())) == 1


def height_colors(height: np.ndarray, top: float = 0.06) -> np.ndarray:
    """(N, 3) uint8 colours of heights above the bed in metres: dark soil brown at the bed through
    orange to pale cream at ``top`` and above, so caps read as light domes on dark ground."""
    stops = np.array([[60, 42, 30], [150, 90, 45], [235, 170, 90], [250, 240, 220]], np.float64)
    t = np.clip(np.asarray(height, np.float64) / top, 0.0, 1.0) * (len(stops) - 1)
    low = np.minimum(t.astype(np.int64), len(stops) - 2)
    weight = (t - low)[:, None]
    return np.round(stops[low] * (1 - weight) + stops[low + 1] * weight).astype(np.uint8)


@dataclass(frozen=True)
class FusionStage:
    """How frames become fused units: by rig (a turntable: one cloud per turn; several fixed cameras:
    one per synchronised set), or for one camera without a rig each frame alone or, with ``window``,
    the last ``window`` frames registered by ICP."""

    config: FusionConfig = field(default_factory=FusionConfig)
    rig: Rig | None = None
    window: int | None = None
    """One camera without a rig: fuse the last N frames, registered by ICP (default: each frame alone)."""
    recorded: tuple[FusedCloud, ...] | None = None
    """Fused clouds a session recorded: the frames pass through to the sinks unfused and perception
    reads these instead (``replay --from-stage fusion``)."""


class UnitBuilder:
    """Frames in, fused units out, by the policy ``describe`` names."""

    def __init__(self, stage: FusionStage, first: DepthFrame, sensors: int):
        rig, config = stage.rig, stage.config
        self.window = None
        if rig is not None and rig.turntable is not None:
            self.kind, self._fuser = "turn", Fuser(config, rig)
        elif rig is not None and len(rig.cameras) > 1:
            self.kind, self._fuser = "set", Fuser(config, rig, every=len(rig.cameras))
        elif first.turntable_angle is not None and (first.T_world_camera is not None or rig is not None):
            self.kind, self._fuser = "turn", Fuser(config, rig)
        elif sensors > 1:
            if first.T_world_camera is None:
                raise ValueError(f"{sensors} cameras and neither a rig nor recorded poses: calibrate them from a "
                                 "recorded turn (mushroom-pose calibrate --session S --out rig.json) and pass --rig")
            self.kind, self._fuser = "set", Fuser(config, rig, every=sensors)
        elif stage.window and stage.window > 1:
            self.kind, self.window, self._fuser = "window", stage.window, None
            self._frames: deque[DepthFrame] = deque(maxlen=stage.window)
        else:
            self.kind, self._fuser = "frame", Fuser(config, rig, every=1)
        self._stage = stage

    def describe(self) -> str:
        return {"turn": "one fused cloud per turn of the turntable",
                "set": "one fused cloud per synchronised set of the rig's cameras",
                "frame": "each frame alone (single view; --window N fuses the last N frames)",
                "window": f"the last {self.window} frames, registered by ICP, after every frame"}[self.kind]

    @property
    def pending(self) -> int:
        return len(self._frames) if self._fuser is None else self._fuser.pending

    def add(self, frame: DepthFrame) -> FusedCloud | None:
        if self._fuser is not None:
            return self._fuser.add(frame)
        self._frames.append(frame)
        return fuse(list(self._frames), self._stage.config, self._stage.rig)

    def flush(self) -> FusedCloud | None:
        """Fuse an unfinished unit (a partial turn at the end of a session)."""
        return self._fuser.flush() if self._fuser is not None else None
