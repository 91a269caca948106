"""Turntable and multi-camera calibration, and the rig file ``live`` / ``replay`` load.

The forward model is ``common.geometry.Turntable``: a camera pose is a reference pose turned by an
angle about an axis (point + direction). Calibration recovers it from one recorded turn: chained
registration of consecutive views (closed into a loop by the pose graph when the turn is complete),
then a plane fit of the camera centres (axis direction) and a circle fit in that plane (axis point).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from capture.frames import DepthFrame
from common.files import write_atomically
from common.geometry import Turntable
from fusion.registration import (RegistrationConfig, chain_poses, check_frames, prepare_view, refine_poses,
                                 register_unknown)

RIG_FORMAT = "mushroom-pose rig"
RIG_VERSION = 1


@dataclass(frozen=True, eq=False)
class Rig:
    """Where the cameras are: an optional turntable, each camera's fixed pose relative to the
    reference camera, and the turntable's fixed angle step when frames carry no encoder angle.

    ``T_world_camera(sensor, angle)`` = turntable rotation(angle) @ T_world_reference @
    T_reference_camera; without a turntable the world is the reference camera's frame.
    """

    turntable: Turntable | None = None
    cameras: dict[str, np.ndarray] = field(default_factory=dict)
    """T_reference_camera per sensor id; empty means a single camera (identity)."""
    angle_step: float | None = None
    """Radians between consecutive frames of one camera, for turntables without an encoder."""

    def T_reference_camera(self, sensor_id: str) -> np.ndarray:
        if not self.cameras:
            return np.eye(4)
        if sensor_id not in self.cameras:
            raise ValueError(f"camera {sensor_id!r} is not in the rig (it has {', '.join(sorted(self.cameras))})")
        return np.asarray(self.cameras[sensor_id], np.float64)

    def T_world_camera(self, sensor_id: str, angle: float = 0.0) -> np.ndarray:
        T = self.T_reference_camera(sensor_id)
        if self.turntable is None:
            return T
        return self.turntable.T_world_camera(float(angle)) @ T

    def to_json(self) -> str:
        turntable = None
        if self.turntable is not None:
            turntable = {"axis_point": np.asarray(self.turntable.axis_point, float).tolist(),
                         "axis_direction": np.asarray(self.turntable.axis_direction, float).tolist(),
                         "T_world_reference": np.asarray(self.turntable.T_world_reference, float).tolist()}
        return json.dumps({"format": RIG_FORMAT, "version": RIG_VERSION, "turntable": turntable,
                           "angle_step": self.angle_step,
                           "cameras": {k: np.asarray(v, float).tolist() for k, v in self.cameras.items()}}, indent=1)

    @staticmethod
    def from_json(text: str, source: str = "rig") -> "Rig":
        """Parse a rig file's text; ValueError with a one-line reason when it is not a valid rig."""
        try:
            data = json.loads(text)
        except (json.JSONDecodeError, UnicodeDecodeError) as error:
            raise ValueError(f"{source} is not a rig file (invalid JSON at line {getattr(error, 'lineno', '?')})") from None
        if not isinstance(data, dict) or data.get("format") != RIG_FORMAT:
            raise ValueError(f"{source} is not a rig file (no \"format\": \"{RIG_FORMAT}\")")
        if data.get("version") != RIG_VERSION:
            raise ValueError(f"{source}: unknown rig file version {data.get('version')!r} (this build reads {RIG_VERSION})")
        try:
            turntable = None
            if data.get("turntable") is not None:
                t = data["turntable"]
                direction = _array(t["axis_direction"], (3,), "turntable.axis_direction")
                if np.linalg.norm(direction) < 1e-9:
                    raise ValueError("turntable.axis_direction is zero")
                turntable = Turntable(_array(t["axis_point"], (3,), "turntable.axis_point"),
                                      direction / np.linalg.norm(direction),
                                      _pose(t["T_world_reference"], "turntable.T_world_reference"))
            cameras = {str(k): _pose(v, f"cameras.{k}") for k, v in (data.get("cameras") or {}).items()}
            step = data.get("angle_step")
            if step is not None and not (isinstance(step, (int, float)) and np.isfinite(step)):
                raise ValueError("angle_step must be a number")
        except (AttributeError, KeyError, TypeError, ValueError) as error:
            what = f"missing {error}" if isinstance(error, KeyError) else str(error)
            raise ValueError(f"{source} is a corrupt rig file: {what}") from None
        return Rig(turntable, cameras, None if step is None else float(step))

    def save(self, path: str | Path) -> None:
        """Write atomically (a temporary name, then renamed), so a crash never leaves half a rig and a
        failed write leaves the earlier file whole."""
        write_atomically(path, self.to_json())

    @staticmethod
    def load(path: str | Path) -> "Rig":
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"rig file {path} does not exist")
        try:
            text = path.read_text()
        except (OSError, UnicodeDecodeError):
            raise ValueError(f"{path} is not a rig file (unreadable or not text)") from None
        return Rig.from_json(text, str(path))


def _array(value, shape: tuple[int, ...], name: str) -> np.ndarray:
    array = np.asarray(value, np.float64)
    if array.shape != shape or not np.isfinite(array).all():
        raise ValueError(f"{name} must be {' x '.join(map(str, shape))} finite numbers")
    return array


def _pose(value, name: str) -> np.ndarray:
    T = _array(value, (4, 4), name)
    if not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-4) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError(f"{name} is not a rigid transform")
    return T


def twist_angles(turntable: Turntable, poses: np.ndarray) -> np.ndarray:
    """Turntable angle of each T_world_camera relative to the reference pose: the twist of the
    relative rotation about the axis, unwrapped along the sequence (radians)."""
    axis = np.asarray(turntable.axis_direction, np.float64)
    axis = axis / np.linalg.norm(axis)
    relative = np.asarray(poses)[:, :3, :3] @ np.asarray(turntable.T_world_reference)[:3, :3].T
    quaternions = Rotation.from_matrix(relative).as_quat()
    return np.unwrap(2 * np.arctan2(quaternions[:, :3] @ axis, quaternions[:, 3]))


def fit_turntable(poses: np.ndarray) -> tuple[Turntable, np.ndarray]:
    """The turntable through camera poses T_world_camera (N >= 3) and the angle of each pose.

    Axis direction: normal of the plane through the camera centres, signed so that the camera
    turns right-handed about it; axis point: centre of the circle through them. The reference
    pose is the first pose.
    """
    poses = np.asarray(poses, np.float64)
    if len(poses) < 3:
        raise ValueError(f"a turntable needs at least 3 views around the turn, got {len(poses)}")
    centres = poses[:, :3, 3]
    mean = centres.mean(0)
    _, singular, basis = np.linalg.svd(centres - mean)
    if singular[1] < 1e-3 * max(singular[0], 1e-12) or singular[0] < 1e-4:
        raise ValueError("the camera centres are (nearly) collinear: the turn is too small to find its axis")
    normal = basis[2]
    turns = Rotation.from_matrix(poses[1:, :3, :3] @ np.transpose(poses[:-1, :3, :3], (0, 2, 1))).as_rotvec()
    if turns.sum(0) @ normal < 0:
        normal = -normal
    uv = (centres - mean) @ basis[:2].T
    design = np.column_stack([2 * uv, np.ones(len(uv))])
    (a, b, _), *_ = np.linalg.lstsq(design, (uv**2).sum(1), rcond=None)
    turntable = Turntable(mean + a * basis[0] + b * basis[1], normal, poses[0].copy())
    return turntable, twist_angles(turntable, poses)


def estimate_turntable(frames: list[DepthFrame], config: RegistrationConfig = RegistrationConfig(),
                       T_world_first: np.ndarray | None = None) -> Turntable:
    """The turntable of one camera from a recorded turn (frames in turn order, about 10-60 degrees apart).

    Consecutive views are registered (seeded by their recorded poses when every frame has one,
    otherwise by FPFH + RANSAC), the chain is closed by the pose graph when the turn overlaps its
    start, and the turntable is fitted to the camera centres. The world frame is ``T_world_first``
    (the first camera's pose when known), else the first frame's recorded pose, else its camera frame.
    """
    return _calibrate_turn(frames, config, T_world_first)[0]


def _calibrate_turn(frames: list[DepthFrame], config: RegistrationConfig,
                    T_world_first: np.ndarray | None) -> tuple[Turntable, np.ndarray]:
    check_frames(frames)
    if len(frames) < 3:
        raise ValueError(f"turntable calibration needs a turn of at least 3 frames, got {len(frames)}")
    recorded = [f.T_world_camera for f in frames]
    have_poses = all(T is not None and np.isfinite(T).all() for T in recorded)
    if T_world_first is None:
        T_world_first = recorded[0] if have_poses else np.eye(4)
    views = [prepare_view(f, config) for f in frames]
    seeds = None
    if have_poses:
        seeds = np.stack([np.linalg.inv(recorded[k]) @ recorded[k + 1] for k in range(len(frames) - 1)])
    chain, pairs = chain_poses(views, config, seeds)
    poses = refine_poses(views, chain, config, pairs).poses
    return fit_turntable(np.asarray(T_world_first, np.float64) @ poses)


def estimate_rig(frames: list[DepthFrame], reference: str | None = None,
                 config: RegistrationConfig = RegistrationConfig()) -> Rig:
    """A rig from a calibration recording: the reference camera's turntable and median angle step
    (when it has 3+ frames), and each other camera's fixed pose relative to it, from its first frame
    registered (FPFH + RANSAC, then ICP) onto the reference frame nearest in time. Cameras turn
    with the table, so that relative pose is the same at every angle."""
    check_frames(frames)
    sensors = list(dict.fromkeys(f.sensor_id for f in frames))
    reference = reference or sensors[0]
    if reference not in sensors:
        raise ValueError(f"reference camera {reference!r} has no frames (cameras: {', '.join(sensors)})")
    own = [f for f in frames if f.sensor_id == reference]
    turntable, step = None, None
    if len(own) >= 3:
        turntable, angles = _calibrate_turn(own, config, None)
        step = float(np.median(np.diff(angles)))
    cameras = {reference: np.eye(4)}
    for sensor in sensors:
        if sensor == reference:
            continue
        first = next(f for f in frames if f.sensor_id == sensor)
        nearest = min(own, key=lambda f: abs(f.timestamp_ns - first.timestamp_ns))
        source, target = prepare_view(first, config), prepare_view(nearest, config)
        result = register_unknown(source, target, config)
        if result.fitness < config.min_fitness:
            raise ValueError(f"camera {sensor!r} does not overlap camera {reference!r} (ICP fitness "
                             f"{result.fitness:.2f}): calibrate with a scene both see")
        cameras[sensor] = result.T_target_source
    return Rig(turntable, cameras if len(sensors) > 1 else {}, step)
