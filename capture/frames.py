"""What every source yields: depth frames with their intrinsics (DESIGN.md section 3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels, OpenCV camera frame (x right, y down, z forward)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @staticmethod
    def realsense_d405(width: int = 848, height: int = 480) -> "CameraIntrinsics":
        """A D405-class close-range depth camera (about 87 x 58 degrees field of view)."""
        fx = width / (2.0 * np.tan(np.radians(87.0) / 2.0))
        return CameraIntrinsics(width, height, fx, fx, (width - 1) / 2.0, (height - 1) / 2.0)


@dataclass(frozen=True)
class DepthFrame:
    """One depth image; ``depth * depth_scale`` is metres along the optical axis, 0 = invalid."""

    depth: np.ndarray
    depth_scale: float
    intrinsics: CameraIntrinsics
    timestamp_ns: int = 0
    sensor_id: str = "camera"
    color: np.ndarray | None = None
    T_world_camera: np.ndarray | None = None
    turntable_angle: float | None = None

    @property
    def depth_m(self) -> np.ndarray:
        """The depth image in metres (float32, 0 = invalid)."""
        return self.depth.astype(np.float32) * np.float32(self.depth_scale)

    def __post_init__(self) -> None:
        if self.depth.ndim != 2 or self.depth.dtype != np.uint16:
            raise ValueError(f"depth must be a 2-D uint16 image, got {self.depth.dtype} {self.depth.shape}")
        if self.depth.shape != (self.intrinsics.height, self.intrinsics.width):
            raise ValueError(f"depth is {self.depth.shape[1]}x{self.depth.shape[0]} but the intrinsics "
                             f"say {self.intrinsics.width}x{self.intrinsics.height}")
        if self.color is not None and self.color.shape[:2] != self.depth.shape:
            raise ValueError(f"colour is {self.color.shape[1]}x{self.color.shape[0]}, depth is "
                             f"{self.depth.shape[1]}x{self.depth.shape[0]}: align them first")


def backproject(depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Valid pixels of a metric depth image as camera-frame points (N, 3) and their flat pixel indices."""
    flat = depth_m.reshape(-1)
    index = np.flatnonzero(flat > 0)
    z = flat[index]
    v, u = np.divmod(index, intrinsics.width)
    points = np.stack([(u - intrinsics.cx) * z / intrinsics.fx, (v - intrinsics.cy) * z / intrinsics.fy, z], 1)
    return points.astype(np.float32), index


def frame_to_points(frame: DepthFrame) -> np.ndarray:
    """A frame's valid depth as points (N, 3) in metres in the camera frame."""
    return backproject(frame.depth_m, frame.intrinsics)[0]


def transform_points(T_parent_child: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points given in the child frame, expressed in the parent frame."""
    return (points @ T_parent_child[:3, :3].T + T_parent_child[:3, 3]).astype(points.dtype, copy=False)


def look_at(eye: np.ndarray, target: np.ndarray, up_hint: np.ndarray = np.array([0.0, 1.0, 0.0])) -> np.ndarray:
    """T_world_camera of an OpenCV camera at ``eye`` looking at ``target``."""
    eye, target = np.asarray(eye, np.float64), np.asarray(target, np.float64)
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up_hint)
    if np.linalg.norm(right) < 1e-6:
        right = np.cross(forward, np.array([1.0, 0.0, 0.0]))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, forward], 1)
    T[:3, 3] = eye
    return T


def voxel_representatives(points: np.ndarray, voxel: float) -> np.ndarray:
    """Indices of one point per occupied voxel (the first one met), in ascending order.

    A dense grid of first indices replaces sorting whenever the cloud's box holds few enough voxels
    (a bed at a few millimetres does): writing indices in reverse leaves each cell's first point.
    """
    keys = np.floor(points / voxel).astype(np.int64)
    keys -= keys.min(0)
    span = keys.max(0) + 1
    flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    cells = int(np.prod(span))
    if cells > 20 * len(points) + 1_000_000:
        return np.sort(np.unique(flat, return_index=True)[1])
    first = np.full(cells, -1, np.int64)
    first[flat[::-1]] = np.arange(len(points) - 1, -1, -1)
    kept = first[first >= 0]
    kept.sort()
    return kept


def cell_lookup(cells: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Row of ``cells`` (M, 3) integer grid cells equal to each query cell (..., 3), or -1 if none."""
    cells, queries = np.asarray(cells, np.int64), np.asarray(queries, np.int64)
    flat_queries = queries.reshape(-1, 3)
    if len(cells) == 0 or len(flat_queries) == 0:
        return np.full(queries.shape[:-1], -1, np.int64)
    low = np.minimum(cells.min(0), flat_queries.min(0))
    span = np.maximum(cells.max(0), flat_queries.max(0)) - low + 1

    def key(grid: np.ndarray) -> np.ndarray:
        grid = grid - low
        return (grid[..., 0] * span[1] + grid[..., 1]) * span[2] + grid[..., 2]

    cell_keys = key(cells)
    order = np.argsort(cell_keys)
    query_keys = key(queries)
    row = order[np.minimum(np.searchsorted(cell_keys[order], query_keys), len(order) - 1)]
    return np.where(cell_keys[row] == query_keys, row, -1)


def log_rerun(rec, frame: DepthFrame, entity: str | None = None, pinhole: bool = True) -> None:
    """A frame in Rerun under ``world/camera/<id>``: its pose, depth image and colour, and with
    ``pinhole`` its intrinsics, logged as static (a camera's intrinsics do not change in a run)."""
    import rerun as rr

    entity = entity or f"world/camera/{frame.sensor_id}"
    if frame.T_world_camera is not None:
        rec.log(entity, rr.Transform3D(translation=frame.T_world_camera[:3, 3], mat3x3=frame.T_world_camera[:3, :3]))
    if pinhole:
        rec.log(entity, rr.Pinhole(image_from_camera=frame.intrinsics.matrix,
                                   resolution=[frame.intrinsics.width, frame.intrinsics.height],
                                   camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.05), static=True)
    rec.log(f"{entity}/depth", rr.DepthImage(frame.depth, meter=1.0 / frame.depth_scale, colormap="turbo"))
    if frame.color is not None:
        rec.log(f"{entity}/color", rr.Image(frame.color))
