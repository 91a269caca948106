"""The Agaricus bisporus template: a domed cap with a rounded rim over a short stem.

Built as a surface of revolution in the cap frame (metres, scale s = 1): the cap's outer dome is
exactly the upper half of the cap ellipsoid of ``perception.cap`` (radius 20 mm, height 2/3 of
that), so a fitted ellipsoid recovers the true scale; the rim curls under it, the gills close it
below, and the stem goes down to its foot.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from perception.cap import CAP_HEIGHT_RATIO, CAP_RADIUS_AT_UNIT_SCALE

RIM_RATIO = 0.12
"""Radius of the rim's curl, as a fraction of the cap radius; the gills sit that far below the base."""
STEM_RADIUS_RATIO = 0.32
STEM_LENGTH_RATIO = 0.85
"""Stem length below the cap base, as a fraction of the cap radius (most of it ends up in the soil)."""


@dataclass(frozen=True)
class TemplateMesh:
    vertices: np.ndarray
    """(V, 3) float64, cap frame, metres at s = 1."""
    triangles: np.ndarray
    """(T, 3) int64."""
    normals: np.ndarray
    """(V, 3) outward unit vertex normals."""
    is_cap: np.ndarray
    """(T,) bool: triangles of the cap (dome, rim and gills), not the stem."""
    foot: np.ndarray
    """The stem's lowest point (cap frame), the point that stands on the ground."""
    hull_samples: np.ndarray
    """(S, 3) a coarse subset of surface points used for collision checks."""


def _profile() -> tuple[np.ndarray, np.ndarray]:
    """(r, z) of the silhouette from the cap top to the stem foot, and whether each point is cap."""
    radius, height = CAP_RADIUS_AT_UNIT_SCALE, CAP_RADIUS_AT_UNIT_SCALE * CAP_HEIGHT_RATIO
    rim = RIM_RATIO * radius
    stem_r, stem_len = STEM_RADIUS_RATIO * radius, STEM_LENGTH_RATIO * radius
    elevation = np.linspace(np.pi / 2, 0.0, 14)
    dome = np.stack([radius * np.cos(elevation), height * np.sin(elevation)], 1)
    curl = np.linspace(0.0, np.pi / 2, 5)[1:]
    rim_pts = np.stack([radius - rim + rim * np.cos(curl), -rim * np.sin(curl)], 1)
    gills = np.stack([np.linspace(radius - rim, stem_r, 4)[1:], np.full(3, -rim)], 1)
    stem = np.stack([np.linspace(stem_r, 1.08 * stem_r, 4)[1:], np.linspace(-rim, -stem_len, 4)[1:]], 1)
    foot = np.array([[0.0, -stem_len]])
    profile = np.concatenate([dome, rim_pts, gills, stem, foot])
    is_cap = np.zeros(len(profile), bool)
    is_cap[: len(dome) + len(rim_pts) + len(gills)] = True
    return profile, is_cap


@lru_cache(maxsize=4)
def mushroom_template(segments: int = 24) -> TemplateMesh:
    profile, profile_is_cap = _profile()
    rings = len(profile)
    angle = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    vertices = np.stack([profile[:, None, 0] * np.cos(angle), profile[:, None, 0] * np.sin(angle),
                         np.broadcast_to(profile[:, None, 1], (rings, segments))], -1).reshape(-1, 3)
    ring, seg = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    a = ring * segments + seg
    b = ring * segments + (seg + 1) % segments
    c, d = a + segments, b + segments
    triangles = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    triangle_ring = np.concatenate([ring.reshape(-1), ring.reshape(-1)])
    is_cap = profile_is_cap[triangle_ring] & profile_is_cap[triangle_ring + 1]
    normals = _vertex_normals(vertices, triangles)
    coarse = vertices.reshape(rings, segments, 3)[::2, ::2].reshape(-1, 3)
    return TemplateMesh(vertices, triangles.astype(np.int64), normals, is_cap,
                        np.array([0.0, 0.0, profile[-1, 1]]), coarse)


def _vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    face = np.cross(vertices[triangles[:, 1]] - vertices[triangles[:, 0]],
                    vertices[triangles[:, 2]] - vertices[triangles[:, 0]])
    normals = np.zeros_like(vertices)
    for corner in range(3):
        np.add.at(normals, triangles[:, corner], face)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.where(length > 0, length, 1.0)
