"""The bed frame: z up along the bed's normal, origin on the bed plane (DESIGN.md section 3)."""

from __future__ import annotations

import numpy as np
import open3d as o3d


CAMERA_RANGE = 3.0
"""Metres. A depth camera looking at a bed is closer than this."""


def estimate_bed_frame(points: np.ndarray, distance: float = 0.008, seed: int = 0,
                       robust_scale: float = 0.05, fit_points: int | None = None,
                       normals: np.ndarray | None = None) -> np.ndarray:
    """T_input_bed for a cloud of a bed (N, 3) in metres, from a RANSAC plane through the soil (inliers
    within ``distance``) refined by Tukey-weighted least squares of scale ``robust_scale`` (metres).

    z points to the side the bed was seen from, decided by the cloud itself (``up_side``), not by where
    the input frame's origin happens to lie. The origin is the centroid's projection onto the plane; x follows the input's x projected onto
    the plane. With ``fit_points``, the plane is fitted to about that many of the points (every k-th):
    a plane needs no more; the centroid is still that of all of them.
    """
    if len(points) < 3:
        raise ValueError("too few points to find the bed plane")
    points = np.asarray(points, np.float64)
    spread = np.linalg.eigvalsh(np.cov(points.T))
    if not spread[1] > 1e-12 * max(spread[2], 1e-300):
        raise ValueError("the points lie on a line or at one point, not on a bed")
    centroid = points.mean(0)
    if fit_points is not None and len(points) > fit_points:
        points = points[::len(points) // fit_points]
    o3d.utility.random.seed(seed)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    (a, b, c, d), _ = cloud.segment_plane(distance, 3, 200)
    normal, offset = _robust_plane(points, np.array([a, b, c]) / np.linalg.norm([a, b, c]),
                                   d / np.linalg.norm([a, b, c]), robust_scale)
    up = up_side(normal, points @ normal + offset, distance, normals, offset, centroid)
    origin = centroid - (centroid @ normal + offset) * normal
    x = np.array([1.0, 0.0, 0.0]) - up[0] * up
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0.0, 1.0, 0.0]) - up[1] * up
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(up, x), up], 1)
    T[:3, 3] = origin
    return T


def up_side(normal: np.ndarray, heights: np.ndarray, distance: float, normals: np.ndarray | None,
            offset: float, centroid: np.ndarray) -> np.ndarray:
    """The bed normal turned to the side the bed was seen from, by the first of these that is clear:
    a relief that says it plainly (caps standing well above everything else: the 99.5th percentile of
    the heights over 1.5 times as far from the plane as the 0.5th); the input origin when it could be
    a camera (off the plane, within ``CAMERA_RANGE``); a milder relief (1.2 times); the cloud's own
    normals (a sensor's normals face it: a clear majority on one side; files carry them of either
    sign); else the side of the input's +z. Cloddy soil goes as deep below the plane as caps stand
    above it, so on many beds the relief alone cannot tell."""
    low, high = np.percentile(heights, [0.5, 99.5])
    above, below = max(high, 0.0), max(-low, 0.0)
    relief = max(above, below) / max(min(above, below), 1e-9) if max(above, below) > 2 * distance else 1.0
    if relief > 1.5:
        return normal if above > below else -normal
    if abs(offset) > 0.05 and np.linalg.norm(centroid) < CAMERA_RANGE:
        return normal if offset > 0 else -normal
    if relief > 1.2:
        return normal if above > below else -normal
    if normals is not None and len(normals):
        facing = np.sign(np.asarray(normals, np.float64) @ normal)
        if abs(facing.sum()) > 0.2 * len(facing):
            return normal if facing.sum() > 0 else -normal
    return normal if normal[2] >= 0 else -normal


def _robust_plane(points: np.ndarray, normal: np.ndarray, offset: float, scale: float,
                  max_iterations: int = 100, settled: float = 1e-12) -> tuple[np.ndarray, float]:
    """The plane refined by Tukey-weighted least squares over everything within ``scale`` of it.

    RANSAC alone maximises the points within a thin band, which on cloddy soil (a few centimetres of
    relief) tilted the plane by 1.8-3.1 degrees on tilted virtual beds; with a scale of about 5 cm
    the weighted fit came within 1 degree of the soil's least-squares plane, caps and all.

    The refinement runs until the plane settles (moves less than ``settled``), and the plane is
    rounded to 1e-9 (a nanometre in the offset): from starts a few hundredths apart it then ends
    bit-identical unless a rounding step falls within the last 1e-13 of spread (about one run in a
    thousand). This matters because Open3D's RANSAC searches in parallel threads and starts it up to
    0.04 off from one run to the next on the same points, and a replay must fuse a session's clouds as
    the run did.
    """
    for _ in range(max_iterations):
        residual = points @ normal + offset
        weight = np.clip(1.0 - (residual / scale) ** 2, 0.0, None) ** 2
        if weight.sum() <= 0:
            break
        centroid = weight @ points / weight.sum()
        centred = (points - centroid) * np.sqrt(weight)[:, None]
        fitted = np.linalg.eigh(centred.T @ centred)[1][:, 0]
        fitted = fitted if fitted @ normal >= 0 else -fitted
        moved = max(float(np.abs(fitted - normal).max()), abs(offset + float(fitted @ centroid)))
        normal, offset = fitted, -float(fitted @ centroid)
        if moved < settled:
            break
    # what is left of where it started (about 1e-13) is rounded away: a nanometre means nothing on a bed
    normal = np.round(normal, 9)
    return normal / np.linalg.norm(normal), round(offset, 9)
