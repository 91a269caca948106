"""Sparse clouds filled in before the network reads them.

The network learnt caps from beds with a point every 3 mm. A cloud sampled much more sparsely (another
generator's beds, a cloud a user voxelised to 8 mm) shows it a cap as a few scattered voxels. A bed is
seen from above, so its surface is a height field almost everywhere: a Delaunay triangulation of the
points' xy in the bed frame joins neighbours on one surface, and new points drawn on its triangles fill
the surface in. Triangles with a long edge (a gap in the scan) or a steep face (the wall between a
cap's rim and the soil under it, which no camera saw) are no surface and are left empty.
"""

from __future__ import annotations

import numpy as np

from common.geometry import voxel_representatives

MAX_EDGE_SPACINGS = 2.0
"""A triangle whose longest edge is over this many point spacings spans a gap, not a surface."""
MAX_SLOPE_DEG = 60.0
"""A triangle steeper than this (from the horizontal) is an occlusion wall, not a surface."""
CANDIDATES_PER_CELL = 3.0
"""Points drawn per target cell of triangle area, before one per cell is kept: enough that nearly every
cell a triangle crosses gets one."""


def densified(points: np.ndarray, spacing: float, target: float, seed: int = 0) -> np.ndarray:
    """The points (N, 3; bed frame, z up) followed by points drawn on their height-field triangulation,
    one in each ``target`` cell that no given point occupies; ``spacing`` is the cloud's point spacing
    (metres), which sets the longest edge kept. Seeded: a cloud always gets the same points."""
    from scipy.spatial import Delaunay, QhullError

    points = np.asarray(points, np.float64)
    try:
        triangles = Delaunay(points[:, :2]).simplices
    except (QhullError, ValueError):  # too few points, or all on a line in xy
        return points
    a, b, c = (points[triangles[:, k]] for k in range(3))
    longest = np.sqrt(np.max([((b - a) ** 2).sum(1), ((c - b) ** 2).sum(1), ((a - c) ** 2).sum(1)], axis=0))
    normal = np.cross(b - a, c - a)
    double_area = np.linalg.norm(normal, axis=1)
    surface = ((longest <= MAX_EDGE_SPACINGS * spacing) & (double_area > 0)
               & (np.abs(normal[:, 2]) >= np.cos(np.radians(MAX_SLOPE_DEG)) * double_area))
    a, b, c, area = a[surface], b[surface], c[surface], 0.5 * double_area[surface]
    rng = np.random.default_rng(seed)
    counts = np.floor(CANDIDATES_PER_CELL * area / target**2 + rng.random(len(area))).astype(np.int64)
    which = np.repeat(np.arange(len(counts)), counts)
    # even over each triangle: barycentric (1 - sqrt(u), sqrt(u) (1 - v), sqrt(u) v)
    root, v = np.sqrt(rng.random(len(which))), rng.random(len(which))
    drawn = (1 - root)[:, None] * a[which] + (root * (1 - v))[:, None] * b[which] + (root * v)[:, None] * c[which]
    cells = voxel_representatives(np.concatenate([points, drawn]), target)
    return np.concatenate([points, drawn[cells[cells >= len(points)] - len(points)]])
