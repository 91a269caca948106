"""The cap model, the one definition every part of perception agrees on (docs/DESIGN.md section 4).

A cap is the upper half of an ellipsoid with semi-axes (s_x, s_y, s_z) in its own frame, centred at
the centre of its wide base; the template is round (s_x = s_y = s) with s_z = 2 s / 3. ``R`` maps
the cap frame to the bed frame, R = R_y(theta_y) R_x(theta_x) (times a spin about the cap axis, which
changes nothing); the cap axis is u = R[:, 2].
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from common.geometry import transform_points
from perception.grades import GradeTable

CAP_RADIUS_AT_UNIT_SCALE = 0.020
"""Cap radius in metres of the template at scale s = 1 (a 40 mm cap)."""
CAP_HEIGHT_RATIO = 2.0 / 3.0
"""s_z / s of the cap ellipsoid."""
CAP_COLOR = (255, 40, 200)
"""Detected caps in every viewer (Rerun, Foxglove): magenta stands out against soil, white caps and the
height colouring of the cloud."""


def rotation_x(angle: np.ndarray | float) -> np.ndarray:
    """Rotation matrices about x, shape (..., 3, 3)."""
    c, s = np.cos(angle), np.sin(angle)
    zero, one = np.zeros_like(c), np.ones_like(c)
    return np.stack([one, zero, zero, zero, c, -s, zero, s, c], -1).reshape(np.shape(c) + (3, 3))


def rotation_y(angle: np.ndarray | float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    zero, one = np.zeros_like(c), np.ones_like(c)
    return np.stack([c, zero, s, zero, one, zero, -s, zero, c], -1).reshape(np.shape(c) + (3, 3))


def rotation_z(angle: np.ndarray | float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    zero, one = np.zeros_like(c), np.ones_like(c)
    return np.stack([c, -s, zero, s, c, zero, zero, zero, one], -1).reshape(np.shape(c) + (3, 3))


def cap_rotation(theta_x: np.ndarray | float, theta_y: np.ndarray | float,
                 spin: np.ndarray | float = 0.0) -> np.ndarray:
    """R = R_y(theta_y) R_x(theta_x) R_z(spin): tilt the cap after spinning it about its own axis."""
    return rotation_y(theta_y) @ rotation_x(theta_x) @ rotation_z(spin)


def rotation_from_axis(axis: np.ndarray) -> np.ndarray:
    """The spin-free cap rotation R_y R_x whose cap axis is the unit ``axis`` (..., 3).

    Written out rather than built from the tilt angles: the pose fit calls it on every cap twice.
    With c = cos(theta_x) = |(u_x, u_z)| (not sqrt(1 - u_y^2), which cancels near +-y), the columns of
    R are (u_z, 0, -u_x) / c, (-u_x u_y / c, c, -u_z u_y / c) and u; an axis exactly along +-y (c = 0)
    gets theta_y = 0."""
    u = np.asarray(axis, dtype=np.float64)
    x, y, z = u[..., 0], u[..., 1], u[..., 2]
    c = np.hypot(x, z)
    upright = c > 1e-12
    inv_c = 1.0 / np.where(upright, c, 1.0)
    sin_y, cos_y = np.where(upright, x * inv_c, 0.0), np.where(upright, z * inv_c, 1.0)
    rotation = np.empty(u.shape + (3,))
    rotation[..., 0, 0], rotation[..., 1, 0], rotation[..., 2, 0] = cos_y, 0.0, -sin_y
    rotation[..., 0, 1], rotation[..., 1, 1], rotation[..., 2, 1] = -sin_y * y, c, -cos_y * y
    rotation[..., 2] = u
    return rotation


def cap_wireframe(centers: np.ndarray, rotations: np.ndarray, scales: np.ndarray, samples: int = 48) -> np.ndarray:
    """Points on each cap's rim (the wide base of its half-ellipsoid), then on two meridians of its
    dome, ``samples`` each: shape (K, 3 * samples, 3), for drawing caps as wire domes."""
    angle = np.linspace(0.0, 2 * np.pi, samples, endpoint=False)
    arc = np.linspace(0.0, np.pi, samples)
    local = np.concatenate([np.stack([np.cos(angle), np.sin(angle), 0 * angle], 1),
                            np.stack([np.cos(arc), 0 * arc, np.sin(arc)], 1),
                            np.stack([0 * arc, np.cos(arc), np.sin(arc)], 1)])
    scaled = local[None] * np.asarray(scales, np.float64)[:, None]
    return np.asarray(centers, np.float64)[:, None] + np.einsum("kij,knj->kni", rotations, scaled)


def tilt_deg(axis: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """Angle in degrees between a cap axis and the bed normal."""
    axis = np.asarray(axis, dtype=np.float64)
    cos = axis @ up / np.linalg.norm(axis, axis=-1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


@dataclass(frozen=True)
class OrientedBox:
    """Points ``center + rotation @ q`` with ``lo <= q <= hi`` (box frame), all in metres."""

    center: np.ndarray
    rotation: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    def vertices(self) -> np.ndarray:
        """The 8 corners in the parent frame, shape (8, 3)."""
        corner_index = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)])
        local = np.where(corner_index == 1, self.hi, self.lo)
        return local @ self.rotation.T + self.center

    @property
    def volume(self) -> float:
        return float(np.prod(self.hi - self.lo))


def cap_box(center: np.ndarray, rotation: np.ndarray, scales: np.ndarray) -> OrientedBox:
    """Box of a cap: [-s_x, s_x] x [-s_y, s_y] x [0, s_z] in the cap frame."""
    scales = np.asarray(scales, dtype=np.float64)
    return OrientedBox(np.asarray(center, np.float64), np.asarray(rotation, np.float64),
                       np.array([-scales[0], -scales[1], 0.0]), scales.copy())


@dataclass(frozen=True)
class Caps:
    """The caps of one bed in one frame, one row each: what detect finds, eval scores, the sinks show and
    the detection JSON holds (docs/DESIGN.md section 3). Cap k's id is k.

    ``scores`` is None for ground truth (every cap counts alike); ``members`` is how many of the points
    the caps were found from belong to each (the network's voxels in ``find_caps``, the input cloud's
    points in detect's result), None when unknown."""

    centers: np.ndarray
    """(K, 3) metres: the centre of each cap's wide base."""
    rotations: np.ndarray
    """(K, 3, 3): cap frame to this frame; the cap's axis (up-vector) is the third column."""
    scales: np.ndarray
    """(K, 3) semi-axes (s_x, s_y, s_z) in metres; detections have s_x = s_y = s, the radius."""
    scores: np.ndarray | None = None
    members: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.centers)

    @staticmethod
    def none() -> "Caps":
        return Caps(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))

    @property
    def axes(self) -> np.ndarray:
        return self.rotations[:, :, 2]

    @property
    def radii(self) -> np.ndarray:
        return self.scales[:, :2].mean(axis=1)

    def score_array(self) -> np.ndarray:
        """The scores, or ones for ground truth."""
        return np.ones(len(self)) if self.scores is None else np.asarray(self.scores, np.float64)

    def moved(self, T_frame_caps: np.ndarray) -> "Caps":
        """The same caps in another frame (a rigid 4x4): centres and rotations move, sizes do not."""
        return replace(self, centers=transform_points(T_frame_caps, self.centers),
                       rotations=T_frame_caps[:3, :3] @ self.rotations)

    def to_document(self, frame: str, readings: int, grades: GradeTable = GradeTable(), min_score: float = 0.0) -> dict:
        """The detection document: ``{"frame", "units": "m", "readings", "grades", "min_score", "mushrooms":
        [one entry per cap]}``; ``readings`` says how many turned readings of the cloud the caps come from
        (perception.detect), ``grades`` is the table each cap's ``grade`` comes from, and a cap scored
        under ``min_score`` is ``"uncertain": true``."""
        scores, members = self.score_array(), self.members if self.members is not None else np.zeros(len(self))
        diameters_mm = 2000.0 * self.radii
        caps = [{"id": k, "center": center.tolist(), "axis": rotation[:, 2].tolist(), "rotation": rotation.tolist(),
                 "radius": float(radius), "height": float(scale[2]), "cap_diameter_mm": float(diameter),
                 "grade": grade, "score": float(score), "uncertain": bool(score < min_score), "num_points": int(count)}
                for k, (center, rotation, scale, radius, diameter, grade, score, count) in
                enumerate(zip(self.centers, self.rotations, self.scales, self.radii, diameters_mm,
                              grades.grade_of(diameters_mm), scores, members))]
        return {"frame": frame, "units": "m", "readings": readings, "grades": grades.to_document(),
                "min_score": float(min_score), "mushrooms": caps}

    @staticmethod
    def from_document(document: dict) -> "Caps":
        """The caps of a detection document (``to_document``'s inverse for caps with s_x = s_y); a
        ValueError names what is missing or malformed."""
        try:
            caps = document["mushrooms"]
            n = len(caps)
            centers = np.array([c["center"] for c in caps], np.float64).reshape(n, 3)
            rotations = np.array([c["rotation"] for c in caps], np.float64).reshape(n, 3, 3)
            radii = np.array([c["radius"] for c in caps], np.float64).reshape(n)
            heights = np.array([c["height"] for c in caps], np.float64).reshape(n)
            scores = np.array([c["score"] for c in caps], np.float64).reshape(n)
            members = np.array([c.get("num_points", 0) for c in caps], np.int64).reshape(n)
        except (KeyError, TypeError, ValueError) as error:
            raise ValueError(f"not a detection document ({type(error).__name__}: {error})") from None
        return Caps(centers, rotations, np.column_stack([radii, radii, heights]), scores, members)
