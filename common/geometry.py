"""Geometry every stage shares: rigid transforms, integer voxel grids and the turntable model.

Transforms are 4x4 ``T_parent_child`` matrices in metres (docs/DESIGN.md section 3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def transform_points(T_parent_child: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points given in the child frame, expressed in the parent frame."""
    return (points @ T_parent_child[:3, :3].T + T_parent_child[:3, 3]).astype(points.dtype, copy=False)


def turn_about_z(angle: float) -> np.ndarray:
    """The 3x3 rotation by ``angle`` radians about the vertical (z), counter-clockwise seen from above."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def turning_about_z(angle: float, pivot: np.ndarray) -> np.ndarray:
    """T_turned_original: the rigid turn by ``angle`` radians about the vertical through ``pivot``."""
    T = np.eye(4)
    T[:3, :3] = turn_about_z(angle)
    T[:3, 3] = pivot - T[:3, :3] @ pivot
    return T


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


@dataclass(frozen=True)
class Turntable:
    """A camera turning about an axis: ``T_world_camera(angle)`` is the reference pose rotated by ``angle``."""

    axis_point: np.ndarray
    axis_direction: np.ndarray
    T_world_reference: np.ndarray

    def rotation(self, angle: float) -> np.ndarray:
        """T_world_world of a turn by ``angle`` (radians, right-handed about the axis)."""
        from scipy.spatial.transform import Rotation

        direction = np.asarray(self.axis_direction, np.float64)
        direction = direction / np.linalg.norm(direction)
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(angle * direction).as_matrix()
        T[:3, 3] = self.axis_point - T[:3, :3] @ self.axis_point
        return T

    def T_world_camera(self, angle: float) -> np.ndarray:
        return self.rotation(angle) @ self.T_world_reference


def median_neighbour_distance(points: np.ndarray, queries: int = 4000, sample: int | None = None) -> float:
    """Median distance from a point to its nearest neighbour, over ``queries`` random points (seeded,
    so a cloud always gives the same figure); nan for fewer than two points. A cloud of more than
    ``sample`` points is measured on a random sample of them and scaled back (on a surface, spacing
    goes as one over the square root of density)."""
    from scipy.spatial import cKDTree

    if len(points) < 2:
        return float("nan")
    rng = np.random.default_rng(0)
    kept = points if sample is None or len(points) <= sample else points[rng.choice(len(points), sample, replace=False)]
    asked = kept[rng.choice(len(kept), min(queries, len(kept)), replace=False)]
    distances = cKDTree(kept).query(asked, k=2)[0][:, 1]
    return float(np.median(distances)) * float(np.sqrt(len(kept) / len(points)))


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
