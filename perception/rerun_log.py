"""Rerun views of perception's outputs: labelled points and caps as boxes and ellipsoids."""

from __future__ import annotations

import numpy as np
import rerun as rr
from scipy.spatial.transform import Rotation

from perception.cap import cap_wireframe
from perception.plan import APPROACH_ARROW, PLAN_COLORS, plan_marks


def log_points(rec: rr.RecordingStream, entity: str, points: np.ndarray, colors: np.ndarray | None = None,
               class_ids: np.ndarray | None = None, radius: float = 0.0015) -> None:
    rec.log(entity, rr.Points3D(points, colors=colors, class_ids=class_ids, radii=radius))


def log_caps(rec: rr.RecordingStream, entity: str, centers: np.ndarray, rotations: np.ndarray,
             scales: np.ndarray, labels: list[str] | None = None, color=(230, 60, 40)) -> None:
    """Each cap as its box ([-s_x, s_x] x [-s_y, s_y] x [0, s_z]), its half-ellipsoid's full ellipsoid,
    both in ``color``, and one label per cap just above its top."""
    if len(centers) == 0:
        for part in ("boxes", "ellipsoids", "labels"):
            rec.log(f"{entity}/{part}", rr.Clear(recursive=False))
        return
    quaternions = Rotation.from_matrix(rotations).as_quat()
    box_centers = centers + rotations[:, :, 2] * (scales[:, 2:3] / 2)
    half = scales * np.array([1.0, 1.0, 0.5])
    rec.log(f"{entity}/boxes", rr.Boxes3D(centers=box_centers, half_sizes=half, quaternions=quaternions,
                                          colors=color, radii=0.0004))
    rec.log(f"{entity}/ellipsoids", rr.Ellipsoids3D(centers=centers, half_sizes=scales, quaternions=quaternions,
                                                    colors=color, line_radii=0.0003))
    if labels is not None:
        tops = centers + rotations[:, :, 2] * (scales[:, 2:3] + 0.004)
        rec.log(f"{entity}/labels", rr.Points3D(tops, labels=labels, radii=0.0001, colors=color,
                                                show_labels=True))


def log_plan(rec: rr.RecordingStream, entity: str, plan: dict) -> None:
    """The pick plan (a detection document's ``"plan"``, in the entity's frame): one arrow per cap from
    its grasp point along its approach, labelled with its place in the order or why it waits."""
    caps = plan["caps"]
    if not caps:
        rec.log(entity, rr.Clear(recursive=False))
        return
    marks = plan_marks(plan)
    rec.log(entity, rr.Arrows3D(origins=[cap["grasp"] for cap in caps],
                                vectors=APPROACH_ARROW * np.array([cap["approach"] for cap in caps]),
                                colors=[PLAN_COLORS[kind] for kind, _ in marks], labels=[label for _, label in marks],
                                radii=0.0012, show_labels=True))


def log_caps_in_image(rec: rr.RecordingStream, entity: str, centers: np.ndarray, rotations: np.ndarray,
                      scales: np.ndarray, T_world_camera: np.ndarray, intrinsics, color=(230, 60, 40)) -> None:
    """The caps' rims as seen by a camera (``entity`` under its pinhole), over its depth image."""
    if len(centers) == 0:
        rec.log(entity, rr.Clear(recursive=False))
        return
    samples = 48
    rims = cap_wireframe(centers, rotations, scales, samples)[:, :samples].reshape(-1, 3)
    T = np.linalg.inv(np.asarray(T_world_camera, np.float64))
    camera = rims @ T[:3, :3].T + T[:3, 3]
    depth = np.maximum(camera[:, 2], 1e-6)
    pixels = np.stack([intrinsics.fx * camera[:, 0] / depth + intrinsics.cx,
                       intrinsics.fy * camera[:, 1] / depth + intrinsics.cy], 1).reshape(len(centers), -1, 2)
    in_front = (camera[:, 2] > 0).reshape(len(centers), -1).all(1)
    closed = np.concatenate([pixels, pixels[:, :1]], axis=1)
    rec.log(entity, rr.LineStrips2D(closed[in_front], colors=color, radii=1.5))
