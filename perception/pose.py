"""Cap pose from the implicit encoding (paper Sec. 3.4, DESIGN.md section 4), all instances at once.

For a cap with centre c and axis u, the orientation value of a point p is u . (p - c) / s_z, so the
least squares (P - c) lambda = Y_o gives lambda = u / s_z: u = lambda / |lambda|. The c we have is
the cluster's mean predicted centre c', off by some e = c' - c, and then Y_o = (P - c') lambda +
lambda . e exactly: so we solve for an intercept too, [P - c', 1] (lambda, b) = Y_o. The axis no
longer depends on e, and b / |lambda| = u . e is the centre's error along the axis, which we take off.
Without the intercept, e biased the axis towards the vertical (steep caps came out 6 degrees too
upright, median on val50).

With the axis known, the ellipsoid equation gives the size. The paper fixes s_z = 2 s / 3 and fits
one s (``height="fixed"``); by default we fit s and s_z together, (x^2 + y^2) / s^2 + z^2 / s_z^2 = 1
being linear in (1 / s^2, 1 / s_z^2), and keep s_z / s within the range real caps span: with perfect
encodings on val50 that cuts the scale error from 4.9 % to 1.1 %, because caps are not all of one
shape (per-axis factors of 0.8-1.2).

By default (``axis="surface"``) the encoding's axis is then refined by the cap's own surface: an
ellipsoid fitted to the cluster's points, started at the encoding's pose. The encoding values are
noisy on a cap a few voxels across, while the dome's shape pins its axis down; the encoding stays in
the fit, weakly, to hold the axis where the visible dome alone cannot (shipped model, val50: mean
angle 5.91 to 3.55 degrees; see ``refine_axes``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from perception.cap import CAP_HEIGHT_RATIO, rotation_from_axis

HEIGHT_MODES = ("free", "fixed")
AXIS_MODES = ("surface", "encoding")
SURFACE_ITERATIONS = 6
"""Shipped model, val50, mean angle with ``STEP_LIMITS``: 3.74 degrees after 4 iterations, 3.61 after
5, 3.55 after 6. Each costs about 0.3 ms, 8 % of the pose step on 46 caps; 8 iterations with the
earlier, three times tighter limits gave 3.59. The figures of the next three settings were measured
with those (session 9)."""
SURFACE_L1_SCALE = 1e-4
"""Metres. Surface residuals above it are weighted as in an L1 fit, so that a cluster's stray voxels
(rim, gills, a neighbour's edge) do not pull the axis. Val50 mean angle with this at 2, 0.5, 0.1 and
0.03 mm: 5.14, 4.31, 3.60 and 3.85 degrees."""
SURFACE_ENCODING_WEIGHT = 0.04
"""Weight of the encoding residual (a distance along the axis, metres) beside the surface's. Without
it the dome of a small or half-seen cap lets the axis swing off (val50: 4.58 degrees, AP@50 91.7 %);
at 0.02 and 0.1: 3.75 and 4.41 degrees; at 0.04: 3.60, AP@50 94.2 %."""
SURFACE_MIN_POINTS = 8
"""Smaller clusters keep the encoding's axis: nine unknowns need more than a handful of points. So do
clusters whose fitted height ratio leaves ``HEIGHT_RATIO_RANGE``: the fit has turned them over."""
SURFACE_MAX_POINTS = 48
"""A larger cluster is fitted on an even subset of this many points: on 2 cores the fit's cost is
the padded width, and big caps are the well-determined ones (val50, 6 steps: 3.55 degrees, against
3.50 with every point, 3.52 with 64 and 3.72 with 32; median pose step on the saved outputs alone
2.5 ms, against 3.6, 2.9 and 2.4)."""
STEP_LIMITS = np.array([6e-3, 0.45])
"""Largest move of the centre (metres) and turn (radians) in one step of the surface fit. Val50, 6
iterations, mean angle with these limits times 1/3, 2/3, 1 and 4/3: 3.71, 3.58, 3.55 and 3.55 degrees;
a cap that the bound lets swing over is caught by the height-ratio gate."""
HEIGHT_RATIO_RANGE = (CAP_HEIGHT_RATIO * 0.8 / 1.2, CAP_HEIGHT_RATIO * 1.2 / 0.8)
"""s_z / s of the template under per-axis factors in [0.8, 1.2]."""


@dataclass(frozen=True)
class CapFit:
    centers: np.ndarray
    rotations: np.ndarray
    scales: np.ndarray
    """(K, 3) = (s, s, 2 s / 3)."""
    scores: np.ndarray
    counts: np.ndarray


def _sum_by_label(values: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """Per-label sums of ``values`` (N, ...) -> (k, ...), with one bincount per component."""
    flat = values.reshape(len(values), -1)
    sums = np.stack([np.bincount(labels, flat[:, j], minlength=k) for j in range(flat.shape[1])], 1)
    return sums.reshape((k,) + values.shape[1:])


def fit_caps(points: np.ndarray, predicted_centers: np.ndarray, orientation: np.ndarray,
             existence: np.ndarray, labels: np.ndarray, height: str = "free", axis: str = "surface") -> CapFit:
    """Fit every labelled instance (labels 0..K-1; -1 ignored) in one vectorised pass.

    ``axis="surface"`` refines the encoding's axes by each cluster's surface (``refine_axes``);
    ``"encoding"`` keeps the encoding's, as the paper does."""
    if height not in HEIGHT_MODES:
        raise ValueError(f"unknown height mode {height!r}; choose one of {HEIGHT_MODES}")
    if axis not in AXIS_MODES:
        raise ValueError(f"unknown axis mode {axis!r}; choose one of {AXIS_MODES}")
    mask = labels >= 0
    k = int(labels.max()) + 1 if mask.any() else 0
    if k == 0:
        return CapFit(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))
    p, y, lab = points[mask].astype(np.float64), orientation[mask].astype(np.float64), labels[mask]
    counts = np.bincount(lab, minlength=k)
    centers = _sum_by_label(predicted_centers[mask].astype(np.float64), lab, k) / counts[:, None]
    d = p - centers[lab]
    design = np.concatenate([d, np.ones((len(d), 1))], 1)
    normal = _sum_by_label(design[:, :, None] * design[:, None, :], lab, k)
    rhs = _sum_by_label(design * y[:, None], lab, k)
    ridge = 1e-12 * np.eye(4)
    solution = np.linalg.solve(normal + ridge, rhs[:, :, None])[:, :, 0]
    lam, intercept = solution[:, :3], solution[:, 3]
    norm = np.linalg.norm(lam, axis=1)
    posed = norm > 1e-12
    cap_axis = np.where(posed[:, None], lam / np.maximum(norm, 1e-12)[:, None], [0.0, 0.0, 1.0])
    # clipped: a cluster flat along its axis leaves the intercept poorly determined
    rms_radius = np.sqrt(np.bincount(lab, (d**2).sum(1), minlength=k) / counts)
    along_axis = np.clip(np.where(posed, intercept / np.maximum(norm, 1e-12), 0.0), -rms_radius, rms_radius)
    centers -= along_axis[:, None] * cap_axis
    d = p - centers[lab]
    rotations, scales = _orient_and_size(d, lab, counts, cap_axis, height)
    if axis == "surface":
        cap_axis = refine_axes(p, y, lab, centers, rotations, scales)
        rotations, scales = _orient_and_size(d, lab, counts, cap_axis, height)
    scores = np.bincount(lab, existence[mask], minlength=k) / counts
    return CapFit(centers, rotations, scales, scores, counts)


def _orient_and_size(d: np.ndarray, lab: np.ndarray, counts: np.ndarray, cap_axis: np.ndarray,
                     height: str) -> tuple[np.ndarray, np.ndarray]:
    """Spin-free rotations (axis turned up) and (s, s, s_z) for offsets ``d`` from the cap centres;
    ``counts``: points per label."""
    k = len(counts)
    cap_axis = cap_axis * np.where(cap_axis[:, 2:3] < 0, -1.0, 1.0)
    rotations = rotation_from_axis(cap_axis)
    axial = (d * cap_axis[lab]).sum(1)
    axial2 = axial**2
    radial2 = np.maximum((d**2).sum(1) - axial2, 0.0)
    s = np.bincount(lab, np.sqrt(radial2 + axial2 / CAP_HEIGHT_RATIO**2), minlength=k) / counts
    s_z = CAP_HEIGHT_RATIO * s
    if height == "free":
        s, s_z = _fit_two_axes(radial2, axial2, lab, k, fallback=s)
    return rotations, np.stack([s, s, s_z], 1)


def refine_axes(points: np.ndarray, orientation: np.ndarray, lab: np.ndarray, centers: np.ndarray,
                rotations: np.ndarray, scales: np.ndarray, iterations: int = SURFACE_ITERATIONS) -> np.ndarray:
    """Cap axes (K, 3) from an ellipsoid fitted to each cluster's points, all clusters at once.

    Gauss-Newton from the encoding's pose over centre, rotation and three semi-axes: the two base
    semi-axes may differ, as on real caps (and the synthetic ones, per-axis factors 0.8-1.2); a surface
    of revolution fitted to an oval cap tilts its axis. The residual of a point is its radial distance
    to the surface, (rho - 1) times the mean base semi-axis, rho^2 = sum_i (q_i / a_i)^2 in the cap
    frame q, reweighted towards L1; beside it, ``SURFACE_ENCODING_WEIGHT`` times the encoding's miss
    along the axis, q_z - y a_z. Steps are bounded (0.45 rad, 6 mm, 20 % in size), and a fit that has
    turned a flat, half-seen dome over fails the height-ratio gate. Only the axis is kept: the fitted
    centre and semi-axes are worse than the encoding's on small caps.
    """
    k = len(centers)
    counts = np.bincount(lab, minlength=k)
    # clusters as zero-padded rows, (K, component, width): every step is a batched array operation
    # whose innermost loop runs along a cluster's points
    slot = np.empty(len(lab), np.int64)
    first_of_label = np.cumsum(counts) - counts
    slot[np.argsort(lab, kind="stable")] = np.arange(len(lab)) - np.repeat(first_of_label, counts)
    if SURFACE_MAX_POINTS:
        stride = np.maximum(counts / SURFACE_MAX_POINTS, 1.0)[lab]
        spread = np.floor(slot / stride)
        chosen = (slot == 0) | (spread != np.floor((slot - 1) / stride))
        points, orientation, lab = points[chosen], orientation[chosen], lab[chosen]
        slot = spread[chosen].astype(np.int64)
    width = int(slot.max()) + 1
    real = np.zeros((k, width))
    real[lab, slot] = 1.0
    padded_points = np.zeros((k, 3, width))
    padded_points[lab, :, slot] = points
    values = np.zeros((k, width))
    values[lab, slot] = orientation
    center, rotation = centers.copy(), rotations.copy()
    log_axes = np.log(np.maximum(scales, 1e-6))
    rows = np.zeros((k, 9, 2 * width))
    surface_rows, encoding_rows = rows[:, :, :width], rows[:, :, width:]
    residuals = np.zeros((k, 2 * width, 1))
    diagonal = np.arange(9)
    for _ in range(iterations):
        semi = np.exp(log_axes)[:, :, None]
        q = rotation.transpose(0, 2, 1) @ (padded_points - center[:, :, None])
        rho = np.maximum(np.sqrt(((q / semi) ** 2).sum(1)), 1e-9)
        mean_radius = 0.5 * (semi[:, 0] + semi[:, 1])
        surface = (rho - 1.0) * mean_radius
        d_rho = q / semi**2 / rho[:, None]
        scale = real * np.sqrt(SURFACE_L1_SCALE / np.maximum(np.abs(surface), SURFACE_L1_SCALE))
        residuals[:, :width, 0] = scale * surface
        scale *= mean_radius
        surface_rows[:, :3] = rotation @ (-scale[:, None] * d_rho)
        surface_rows[:, 3] = scale * (d_rho[:, 1] * q[:, 2] - d_rho[:, 2] * q[:, 1])
        surface_rows[:, 4] = scale * (d_rho[:, 2] * q[:, 0] - d_rho[:, 0] * q[:, 2])
        surface_rows[:, 5] = scale * (d_rho[:, 0] * q[:, 1] - d_rho[:, 1] * q[:, 0])
        surface_rows[:, 6:] = -scale[:, None] * q * d_rho
        surface_rows[:, 6:8] += (0.5 * scale * (rho - 1.0) / mean_radius)[:, None] * semi[:, :2]
        scale = SURFACE_ENCODING_WEIGHT * real
        encoding_rows[:, :3] = -scale[:, None] * rotation[:, :, 2:]
        encoding_rows[:, 3], encoding_rows[:, 4] = -scale * q[:, 1], scale * q[:, 0]
        encoding_rows[:, 8] = -scale * values * semi[:, 2]
        residuals[:, width:, 0] = scale * (q[:, 2] - values * semi[:, 2])
        normal = rows @ rows.transpose(0, 2, 1)
        gradient = rows @ residuals
        normal[:, diagonal, diagonal] = normal[:, diagonal, diagonal] * (1.0 + 1e-3) + 1e-18
        step = -np.linalg.solve(normal, gradient)[:, :, 0]
        lengths = np.linalg.norm(step[:, :6].reshape(k, 2, 3), axis=2)
        step[:, :6] *= np.repeat(np.minimum(1.0, STEP_LIMITS / np.maximum(lengths, 1e-12)), 3, axis=1)
        center += step[:, :3]
        rotation = rotation @ Rotation.from_rotvec(step[:, 3:6]).as_matrix()
        log_axes += np.clip(step[:, 6:], -0.2, 0.2)
    refined = rotation[:, :, 2]
    semi = np.exp(log_axes)
    height_ratio = semi[:, 2] / (0.5 * (semi[:, 0] + semi[:, 1]))
    plausible = (height_ratio >= HEIGHT_RATIO_RANGE[0]) & (height_ratio <= HEIGHT_RATIO_RANGE[1])
    keep = (counts >= SURFACE_MIN_POINTS) & np.isfinite(refined).all(1) & plausible
    return np.where(keep[:, None], refined, rotations[:, :, 2])


def _fit_two_axes(radial2: np.ndarray, axial2: np.ndarray, lab: np.ndarray, k: int,
                  fallback: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares a r^2 + b z^2 = 1 per instance: s = a^-1/2, s_z = b^-1/2, s_z / s clamped.

    Instances whose system is degenerate (e.g. a sliver of points at one height) keep ``fallback``,
    the fixed-ratio size.
    """
    a11 = np.bincount(lab, radial2 * radial2, minlength=k)
    a12 = np.bincount(lab, radial2 * axial2, minlength=k)
    a22 = np.bincount(lab, axial2 * axial2, minlength=k)
    b1, b2 = np.bincount(lab, radial2, minlength=k), np.bincount(lab, axial2, minlength=k)
    det = a11 * a22 - a12**2
    safe = np.where(det > 0, det, 1.0)
    a, b = (b1 * a22 - b2 * a12) / safe, (a11 * b2 - a12 * b1) / safe
    good = (det > 1e-9 * a11 * a22) & (a > 0)
    s = np.where(good, 1.0 / np.sqrt(np.where(good, a, 1.0)), fallback)
    ratio = np.where(good & (b > 0), 1.0 / np.sqrt(np.where(b > 0, b, 1.0)) / s, CAP_HEIGHT_RATIO)
    return s, np.clip(ratio, *HEIGHT_RATIO_RANGE) * s
