"""A virtual depth camera: ray casting over any triangle meshes, with a RealSense-like sensor model.

It knows nothing of mushrooms: callers hand it triangles and a pose and get depth back, plus the id
of the triangle every pixel sees, so they can carry their own labels through the rendering.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import open3d as o3d

from capture.frames import CameraIntrinsics, DepthFrame, backproject
from capture.source import Source
from common.geometry import Turntable, look_at


@dataclass(frozen=True)
class SensorModel:
    """Active-stereo depth errors. Defaults follow a D405-class camera at bed range."""

    depth_scale: float = 1e-4
    """Metres per depth unit (the D405 reports 0.1 mm units)."""
    noise_at_1m: float = 0.006
    """Standard deviation in metres of depth noise at 1 m; stereo noise grows with range squared."""
    grazing_deg: float = 78.0
    """Beyond this incidence angle pixels start to drop out (no stereo match at grazing angles)."""
    edge_jump: float = 0.012
    """A depth step above this (metres) between neighbours invalidates the far side (stereo shadow)."""
    dropout: float = 0.002
    """Fraction of random pixels lost."""
    min_depth: float = 0.07
    max_depth: float = 1.5
    speckle_at_1m: float = 0.0
    """Standard deviation in metres at 1 m of range error correlated over ``speckle_pixels`` (a stereo
    matcher's texture-dependent blotches); 0 draws none."""
    speckle_pixels: float = 4.0
    flying_pixels: float = 0.0
    """Share of the far-side pixels at a depth step that take a depth between the two sides (mixed
    pixels flying off edges) instead of dropping out; 0 draws none."""


SENSOR_MODELS = {
    "d405": SensorModel(),
    "oak": SensorModel(noise_at_1m=0.015, dropout=0.01, speckle_at_1m=0.008, flying_pixels=0.5),
}
"""Named sensor models: the D405-class active stereo at bed range, and a noisier passive-stereo
OAK-class camera (more range noise, speckle, flying pixels at edges)."""


@dataclass(frozen=True)
class Render:
    """Ideal ray-cast result: metric depth along the optical axis (0 = miss) and hit triangles."""

    depth: np.ndarray
    triangle_ids: np.ndarray
    cos_incidence: np.ndarray


class MeshScene:
    """Triangle meshes ready for ray casting; build once, render from many poses."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, threads: int = 1) -> None:
        """``threads`` = 0 uses every core (live rendering); 1 keeps data generation on one core."""
        if len(triangles) == 0:
            raise ValueError("nothing to render: the mesh has no triangles")
        self._threads = threads
        self._scene = o3d.t.geometry.RaycastingScene(nthreads=threads)
        self._scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),
                                  o3d.core.Tensor(np.ascontiguousarray(triangles, np.uint32)))
        self._inverse_lengths: dict[CameraIntrinsics, np.ndarray] = {}

    def render(self, intrinsics: CameraIntrinsics, T_world_camera: np.ndarray) -> Render:
        # Open3D builds the rays in C++. A numpy matmul here (OpenBLAS, both cores) leaves its threads
        # spinning for tens of milliseconds after it returns, and the ray caster then shares a core with
        # them: cast_rays takes 70 ms after such a matmul against 40 ms without. Open3D aims its rays at
        # pixel centres, u + 0.5; ours (CameraIntrinsics) are at u, hence the half-pixel shift.
        shifted = np.array([[intrinsics.fx, 0.0, intrinsics.cx + 0.5], [0.0, intrinsics.fy, intrinsics.cy + 0.5],
                            [0.0, 0.0, 1.0]])
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            o3d.core.Tensor(shifted), o3d.core.Tensor(np.linalg.inv(T_world_camera)), intrinsics.width,
            intrinsics.height)
        hit = self._scene.cast_rays(rays, nthreads=self._threads)
        depth = hit["t_hit"].numpy()
        missed = ~np.isfinite(depth)
        depth[missed] = 0.0
        triangle_ids = hit["primitive_ids"].numpy().astype(np.int64)
        triangle_ids[missed] = -1
        directions, normals = rays.numpy()[..., 3:], hit["primitive_normals"].numpy()
        cos_incidence = normals[..., 0] * directions[..., 0]
        cos_incidence += normals[..., 1] * directions[..., 1]
        cos_incidence += normals[..., 2] * directions[..., 2]
        np.abs(cos_incidence, out=cos_incidence)
        cos_incidence *= self._inverse_length(intrinsics)
        return Render(depth, triangle_ids, cos_incidence)

    def nearest_triangles(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The triangle nearest each point (N,) and the distance to it in metres (N,)."""
        points = np.ascontiguousarray(points, np.float32)
        closest = self._scene.compute_closest_points(o3d.core.Tensor(points), nthreads=self._threads)
        return (closest["primitive_ids"].numpy().astype(np.int64),
                np.linalg.norm(closest["points"].numpy() - points, axis=1))

    def _inverse_length(self, intrinsics: CameraIntrinsics) -> np.ndarray:
        """1 / |direction| per pixel: the rays have unit z in the camera frame, so the hit distance is the
        depth, and rotating them does not change their length."""
        if intrinsics not in self._inverse_lengths:
            unit_depth = np.ones((intrinsics.height, intrinsics.width), np.float32)
            directions = backproject(unit_depth, intrinsics)[0]
            self._inverse_lengths[intrinsics] = (1.0 / np.linalg.norm(directions, axis=1)).reshape(unit_depth.shape)
        return self._inverse_lengths[intrinsics]


def apply_sensor_model(render: Render, sensor: SensorModel, rng: np.random.Generator,
                       gaussian: np.ndarray | None = None) -> np.ndarray:
    """Measured depth in metres (0 = invalid): range noise, grazing and edge holes, dropout, quantisation.

    ``gaussian``: standard normal samples of the image's shape for the range noise; drawn from ``rng``
    when not given."""
    depth = render.depth.astype(np.float32, copy=False)
    grazing_cos = np.float32(np.cos(np.radians(sensor.grazing_deg)))
    keep_probability = np.minimum(render.cos_incidence / grazing_cos, 1.0) ** 2 * np.float32(1.0 - sensor.dropout)
    valid = (depth >= sensor.min_depth) & (depth <= sensor.max_depth)
    valid &= rng.random(depth.shape, dtype=np.float32) < keep_probability
    hits = np.where(depth > 0, depth, np.float32(np.inf))
    nearest_neighbour = np.full_like(hits, np.inf)
    nearest_neighbour[:, 1:] = hits[:, :-1]
    np.minimum(nearest_neighbour[:, :-1], hits[:, 1:], out=nearest_neighbour[:, :-1])
    np.minimum(nearest_neighbour[1:], hits[:-1], out=nearest_neighbour[1:])
    np.minimum(nearest_neighbour[:-1], hits[1:], out=nearest_neighbour[:-1])
    behind_edge = depth - nearest_neighbour > sensor.edge_jump
    if sensor.flying_pixels > 0:  # drawn only when asked, so other sensors keep their frames
        flying = behind_edge & (rng.random(depth.shape, dtype=np.float32) < sensor.flying_pixels)
        mix = rng.random(int(flying.sum()), dtype=np.float32)
        depth = depth.copy()
        depth[flying] = nearest_neighbour[flying] + mix * (depth[flying] - nearest_neighbour[flying])
        behind_edge &= ~flying
    valid &= ~behind_edge
    if gaussian is None:
        gaussian = rng.standard_normal(depth.shape, dtype=np.float32)
    noisy = depth + gaussian * np.float32(sensor.noise_at_1m) * depth**2
    if sensor.speckle_at_1m > 0:
        from scipy.ndimage import gaussian_filter

        field = gaussian_filter(rng.standard_normal(depth.shape, dtype=np.float32), sensor.speckle_pixels)
        field /= max(float(field.std()), 1e-9)
        noisy = noisy + field * np.float32(sensor.speckle_at_1m) * depth**2
    quantised = np.round(noisy / np.float32(sensor.depth_scale)) * np.float32(sensor.depth_scale)
    return np.where(valid, quantised, np.float32(0.0))


def to_depth_frame(depth_m: np.ndarray, intrinsics: CameraIntrinsics, sensor: SensorModel,
                   T_world_camera: np.ndarray | None = None, timestamp_ns: int = 0,
                   sensor_id: str = "virtual", turntable_angle: float | None = None) -> DepthFrame:
    units = np.round(depth_m / sensor.depth_scale)
    return DepthFrame(np.clip(units, 0, 65535).astype(np.uint16), sensor.depth_scale, intrinsics,
                      timestamp_ns, sensor_id, None, T_world_camera, turntable_angle)


def circle_turntable(target: np.ndarray, radius: float, height: float,
               axis: np.ndarray = np.array([0.0, 0.0, 1.0])) -> Turntable:
    """A camera ``radius`` off the axis through ``target``, ``height`` above it, looking at ``target``."""
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    side = np.cross(axis, [0.0, 1.0, 0.0] if abs(axis[1]) < 0.9 else [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    eye = np.asarray(target, np.float64) + radius * side + height * axis
    return Turntable(np.asarray(target, np.float64), axis, look_at(eye, target, up_hint=axis))


@dataclass(frozen=True)
class VirtualCameraConfig:
    """A virtual depth camera over given meshes: fixed poses, or N views of a turntable."""

    intrinsics: CameraIntrinsics = CameraIntrinsics.realsense_d405()
    sensor: SensorModel = SensorModel()
    poses: tuple = ()
    """Fixed T_world_camera poses (4x4); used when no turntable is given."""
    turntable: Turntable | None = None
    views: int = 18
    turns: int | None = 1
    """Turns of the turntable to render (None: it keeps turning, as a real one does)."""
    fps: float = 15.0
    """Frame rate of the timestamps (the frames themselves come as fast as they render)."""
    seed: int = 0
    sensor_id: str = "virtual"
    start_ns: int = 0

    def pose(self, index: int) -> tuple[np.ndarray, float | None]:
        """T_world_camera of view ``index`` and its turntable angle (None for fixed poses)."""
        if self.turntable is not None:
            angle = 2 * np.pi * index / self.views
            return self.turntable.T_world_camera(angle), angle
        return np.asarray(self.poses[index], np.float64), None

    def __len__(self) -> int:
        """Frames to render (for an endless turntable, those of one turn)."""
        return self.views * (self.turns or 1) if self.turntable is not None else len(self.poses)

    @property
    def endless(self) -> bool:
        return self.turntable is not None and self.turns is None


NOISE_TABLE_FRAMES = 4


@lru_cache(maxsize=4)
def _gaussian_table(seed: int, pixels: int) -> np.ndarray:
    """``NOISE_TABLE_FRAMES`` frames' worth of standard normal samples, drawn once per seed and size.

    A frame's range noise is a window of it at a random offset: within a frame the samples are
    independent, as with fresh draws. Drawing 407 k fresh ones takes 7-8 ms a frame at 848x480, a ninth
    of the time 15 fps allows. Two frames share values only at pixels shifted by the difference of their
    offsets; a surface point seen in both lands on pixels unrelated to that shift.
    """
    table = np.random.default_rng([seed, 1 << 32]).standard_normal(NOISE_TABLE_FRAMES * pixels, dtype=np.float32)
    table.flags.writeable = False
    return table


def render_view(scene: MeshScene, config: VirtualCameraConfig, index: int) -> DepthFrame:
    """View ``index`` with its own noise stream, so frames do not depend on who renders them or in what order."""
    return sense_view(scene.render(config.intrinsics, config.pose(index)[0]), config, index)


def sense_view(render: Render, config: VirtualCameraConfig, index: int) -> DepthFrame:
    """The frame the sensor makes of view ``index``'s ideal ``render``."""
    T_world_camera, angle = config.pose(index)
    rng = np.random.default_rng([config.seed, index])
    pixels = render.depth.size
    table = _gaussian_table(config.seed, pixels)
    start = int(rng.integers(0, len(table) - pixels + 1))
    depth = apply_sensor_model(render, config.sensor, rng, table[start:start + pixels].reshape(render.depth.shape))
    timestamp = config.start_ns + int(round(index * 1e9 / config.fps))
    return to_depth_frame(depth, config.intrinsics, config.sensor, T_world_camera, timestamp, config.sensor_id,
                          angle)


class VirtualSource(Source):
    """Renders each view of the config in turn, with the true pose on every frame."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, config: VirtualCameraConfig):
        if config.turntable is None and not config.poses:
            raise ValueError("a virtual camera needs fixed poses or a turntable")
        self.config = config
        self._vertices, self._triangles = vertices, triangles
        self._scene: MeshScene | None = None
        self._index = 0

    def __len__(self) -> int:
        return len(self.config)

    @property
    def turntable(self) -> Turntable | None:
        return self.config.turntable

    def open(self) -> None:
        if self._scene is None:
            self._scene = MeshScene(self._vertices, self._triangles, threads=0)

    def read(self) -> DepthFrame | None:
        if self._index >= len(self) and not self.config.endless:
            return None
        self.open()
        frame = render_view(self._scene, self.config, self._index)
        self._index += 1
        return frame

    def close(self) -> None:
        self._scene = None
