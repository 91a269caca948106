"""The bed frame: z up along the bed's normal, origin on the bed plane (docs/DESIGN.md section 3); which side
of the plane is up; and whether a cloud is a bed seen from above at all."""

from __future__ import annotations

from typing import Callable

import numpy as np


CAMERA_RANGE = 3.0
"""Metres. A depth camera looking at a bed is closer than this."""
RANSAC_POINTS = 20_000
"""RANSAC's start for the bed plane is found on about this many points (every k-th): it only has to
land near the soil's plane, which the Tukey refinement then settles on all of them."""


def estimate_bed_frame(points: np.ndarray, distance: float = 0.008, seed: int = 0,
                       robust_scale: float = 0.05, fit_points: int | None = None,
                       normals: np.ndarray | None = None) -> np.ndarray:
    """T_input_bed for a cloud of a bed (N, 3) in metres, from a RANSAC plane through the soil (inliers
    within ``distance``) refined by Tukey-weighted least squares of scale ``robust_scale`` (metres).

    z points to the side the bed was seen from, decided by the cloud itself (``up_side``), not by where
    the input frame's origin happens to lie; a detector's caps can overrule it (``side_with_caps``). The origin is the centroid's projection onto the plane; x follows the input's x projected onto
    the plane. With ``fit_points``, the plane is fitted to about that many of the points (every k-th):
    a plane needs no more; the centroid is still that of all of them. RANSAC only starts the fit, on
    at most ``RANSAC_POINTS`` of them: the refinement ends on the same plane from any start near it.
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
    start = points[::len(points) // RANSAC_POINTS] if len(points) > RANSAC_POINTS else points
    normal, offset = _robust_plane(points, *ransac_plane(start, distance, seed), robust_scale)
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


RANSAC_TRIALS = 200
"""Planes through three random points that RANSAC tries."""
RANSAC_BLOCK = 20
"""Trials scored together."""


def ransac_plane(points: np.ndarray, distance: float, seed: int = 0) -> tuple[np.ndarray, float]:
    """The unit normal and offset (n . p + offset = 0) of the plane through three of ``points`` that has
    the most of them within ``distance``, of ``RANSAC_TRIALS`` tries drawn with ``seed``. Open3D's
    ``segment_plane`` does the same; all trials in one array pass cost less than importing Open3D."""
    triples = points[np.random.default_rng(seed).integers(0, len(points), (RANSAC_TRIALS, 3))]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    length = np.linalg.norm(normals, axis=1)
    usable = length > 1e-12
    if not usable.any():
        raise ValueError("the points lie on a line or at one point, not on a bed")
    normals = normals[usable] / length[usable, None]
    offsets = -np.einsum("ij,ij->i", normals, triples[usable, 0])
    inliers = np.empty(len(normals), np.int64)
    across = np.ascontiguousarray(points.T)
    for first in range(0, len(normals), RANSAC_BLOCK):  # blocks of trials: a few MB at a time
        residual = normals[first:first + RANSAC_BLOCK] @ across
        residual += offsets[first:first + RANSAC_BLOCK, None]
        inliers[first:first + RANSAC_BLOCK] = np.count_nonzero(np.abs(residual, out=residual) <= distance, axis=1)
    best = int(np.argmax(inliers))
    return normals[best], float(offsets[best])


TURN_EVIDENCE = 4.0
"""How many times more cap evidence the bed turned over must show before it is turned: caps seen from
their right side fill thousands of voxels, seen from the wrong side almost none."""


def turned_over(T_input_bed: np.ndarray) -> np.ndarray:
    """The bed frame turned 180 degrees about its x axis: the same plane, seen from its other side."""
    return T_input_bed @ np.diag([1.0, -1.0, -1.0, 1.0])


def side_with_caps(T_input_bed: np.ndarray, cap_evidence: Callable[[np.ndarray], int],
                   most_evidence: Callable[[np.ndarray], int] | None = None) -> np.ndarray:
    """``T_input_bed``, or the frame turned over when ``cap_evidence`` (how many cap voxels a detector
    sees in the cloud put in a given bed frame) finds far more caps that way. A bed's caps tell the
    plane's two sides apart where its soil relief or the input's origin (``up_side``) can mislead:
    cloddy soil goes as deep below the plane as caps stand above it. ``most_evidence`` bounds the
    evidence a frame can show (its voxel count): when even that falls short, the turned frame is not
    read at all, which on a bed full of caps saves the detector's pass."""
    needed = TURN_EVIDENCE * max(cap_evidence(T_input_bed), 10)
    turned = turned_over(T_input_bed)
    if most_evidence is not None and most_evidence(turned) <= needed:
        return T_input_bed
    return turned if cap_evidence(turned) > needed else T_input_bed


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
    thousand). So the plane does not hang on which points RANSAC drew to start it, and a replay fuses
    a session's clouds as the run did.
    """
    # weighted moments about one fixed point, the coordinates as rows (3, N) so that each step is a few
    # in-place passes and two matrix products over the points
    reference = points.mean(0)
    centred = np.ascontiguousarray((points - reference).T)
    offset += float(normal @ reference)
    for _ in range(max_iterations):
        weight = normal @ centred
        weight += offset
        weight *= 1.0 / scale
        np.square(weight, out=weight)
        np.subtract(1.0, weight, out=weight)
        np.maximum(weight, 0.0, out=weight)
        np.square(weight, out=weight)
        total = weight.sum()
        if total <= 0:
            break
        weighted = centred * weight
        mean = weighted.sum(1) / total
        scatter = weighted @ centred.T - total * np.outer(mean, mean)
        fitted = np.linalg.eigh(scatter)[1][:, 0]
        fitted = fitted if fitted @ normal >= 0 else -fitted
        moved = max(float(np.abs(fitted - normal).max()), abs(offset + float(fitted @ mean)))
        normal, offset = fitted, -float(fitted @ mean)
        if moved < settled:
            break
    offset -= float(normal @ reference)
    # what is left of where it started (about 1e-13) is rounded away: a nanometre means nothing on a bed
    normal = np.round(normal, 9)
    return normal / np.linalg.norm(normal), round(offset, 9)


# ---- is it a bed seen from above?

NEAR_PLANE = 0.10
"""Metres from the bed plane within which a bed's soil and caps lie (caps stand a few cm tall)."""
MIN_NEAR_PLANE = 0.5
"""The least fraction of a bed cloud's points within ``NEAR_PLANE`` of its dominant plane."""
MAX_CAPS_PER_M2 = 1000.0
"""More caps per square metre than the densest bed holds (touching 30 mm caps give about 1100 on a
hexagonal packing, and beds are never packed that tight)."""
BED_FRAME_TILT_DEG = 20.0
"""How far the dominant plane of a cloud said to be in the bed frame may tilt from z = 0."""
BED_FRAME_OFFSET = 0.10
"""How far (metres) that plane may lie from the frame's origin."""


def not_a_bed(bed_points: np.ndarray) -> str | None:
    """Why a cloud in its bed frame is no bed seen from above (most of its points far from its
    dominant plane), or None when it may be one."""
    near = float(np.mean(np.abs(bed_points[:, 2]) <= NEAR_PLANE))
    if near < MIN_NEAR_PLANE:
        return (f"only {near:.0%} of its points lie within {100 * NEAR_PLANE:.0f} cm of its dominant plane, where a "
                "bed has most of them")
    return None


def too_many_caps(bed_points: np.ndarray, caps: int) -> str | None:
    """Why ``caps`` caps on this cloud (in its bed frame) are more than a bed holds, or None."""
    near = bed_points[np.abs(bed_points[:, 2]) <= NEAR_PLANE]
    if len(near) < 3 or caps == 0:
        return None
    area = float(np.prod(np.ptp(np.percentile(near[:, :2], [1, 99], axis=0), axis=0)))
    if caps > MAX_CAPS_PER_M2 * max(area, 1e-6):
        return f"{caps} caps on {area:.2g} m2 are more than a bed holds (at most {MAX_CAPS_PER_M2:.0f} per m2)"
    return None


def bed_frame_mismatch(T_input_bed: np.ndarray) -> str | None:
    """Why a cloud whose own bed plane is ``T_input_bed`` is not in the bed frame, or None."""
    tilt = float(np.degrees(np.arccos(np.clip(abs(T_input_bed[2, 2]), -1.0, 1.0))))
    height = abs(float(T_input_bed[2, 3]))
    if tilt > BED_FRAME_TILT_DEG:
        return f"its bed plane is tilted {tilt:.0f} deg from the frame's xy plane"
    if height > BED_FRAME_OFFSET:
        return f"its bed plane lies {100 * height:.0f} cm from the frame's origin"
    return None
