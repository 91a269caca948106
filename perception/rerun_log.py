"""Rerun views of perception's outputs: labelled points and caps as boxes and ellipsoids."""

from __future__ import annotations

import numpy as np
import rerun as rr
from scipy.spatial.transform import Rotation


def log_points(rec: rr.RecordingStream, entity: str, points: np.ndarray, colors: np.ndarray | None = None,
               class_ids: np.ndarray | None = None, radius: float = 0.0015) -> None:
    rec.log(entity, rr.Points3D(points, colors=colors, class_ids=class_ids, radii=radius))


def log_caps(rec: rr.RecordingStream, entity: str, centers: np.ndarray, rotations: np.ndarray,
             scales: np.ndarray, labels: list[str] | None = None, color=(230, 60, 40)) -> None:
    """Each cap as its box ([-s_x, s_x] x [-s_y, s_y] x [0, s_z]) and its half-ellipsoid's full ellipsoid."""
    if len(centers) == 0:
        rec.log(f"{entity}/boxes", rr.Clear(recursive=False))
        rec.log(f"{entity}/ellipsoids", rr.Clear(recursive=False))
        return
    quaternions = Rotation.from_matrix(rotations).as_quat()
    box_centers = centers + rotations[:, :, 2] * (scales[:, 2:3] / 2)
    half = scales * np.array([1.0, 1.0, 0.5])
    rec.log(f"{entity}/boxes", rr.Boxes3D(centers=box_centers, half_sizes=half, quaternions=quaternions,
                                          colors=color, labels=labels, radii=0.0006))
    rec.log(f"{entity}/ellipsoids", rr.Ellipsoids3D(centers=centers, half_sizes=scales, quaternions=quaternions,
                                                    colors=(250, 250, 240)))

