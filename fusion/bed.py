"""The bed frame: z up along the bed's normal, origin on the bed plane (DESIGN.md section 3)."""

from __future__ import annotations

import numpy as np
import open3d as o3d


def estimate_bed_frame(points: np.ndarray, distance: float = 0.008, seed: int = 0) -> np.ndarray:
    """T_input_bed for a cloud of a bed (N, 3) in metres, from a RANSAC plane through the soil.

    z points to the side the sensor looked from: the input origin when it is off the plane (a
    camera-frame cloud), otherwise the side where most off-plane points lie (caps stand up from
    the soil). The origin is the centroid's projection onto the plane; x follows the input's x
    projected onto the plane.
    """
    if len(points) < 3:
        raise ValueError("too few points to find the bed plane")
    o3d.utility.random.seed(seed)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    (a, b, c, d), inliers = cloud.segment_plane(distance, 3, 200)
    normal = np.array([a, b, c]) / np.linalg.norm([a, b, c])
    offset = d / np.linalg.norm([a, b, c])
    if abs(offset) > 0.05:
        up = normal if offset > 0 else -normal
    else:
        heights = points @ normal + offset
        up = normal if np.sum(heights > distance) >= np.sum(heights < -distance) else -normal
    centroid = points.mean(0)
    origin = centroid - (centroid @ normal + offset) * normal
    x = np.array([1.0, 0.0, 0.0]) - up[0] * up
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0.0, 1.0, 0.0]) - up[1] * up
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(up, x), up], 1)
    T[:3, 3] = origin
    return T
