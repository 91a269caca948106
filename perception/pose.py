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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from perception.cap import CAP_HEIGHT_RATIO, rotation_from_axis

HEIGHT_MODES = ("free", "fixed")
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
             existence: np.ndarray, labels: np.ndarray, height: str = "free") -> CapFit:
    """Fit every labelled instance (labels 0..K-1; -1 ignored) in one vectorised pass."""
    if height not in HEIGHT_MODES:
        raise ValueError(f"unknown height mode {height!r}; choose one of {HEIGHT_MODES}")
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
    axis = np.where(posed[:, None], lam / np.maximum(norm, 1e-12)[:, None], [0.0, 0.0, 1.0])
    # clipped: a cluster flat along its axis leaves the intercept poorly determined
    rms_radius = np.sqrt(np.bincount(lab, (d**2).sum(1), minlength=k) / counts)
    along_axis = np.clip(np.where(posed, intercept / np.maximum(norm, 1e-12), 0.0), -rms_radius, rms_radius)
    centers -= along_axis[:, None] * axis
    d = p - centers[lab]
    axis *= np.where(axis[:, 2:3] < 0, -1.0, 1.0)
    rotations = rotation_from_axis(axis)
    local = np.einsum("nd,nde->ne", d, rotations[lab])
    radial2, axial2 = local[:, 0] ** 2 + local[:, 1] ** 2, local[:, 2] ** 2
    s = np.bincount(lab, np.sqrt(radial2 + axial2 / CAP_HEIGHT_RATIO**2), minlength=k) / counts
    s_z = CAP_HEIGHT_RATIO * s
    if height == "free":
        s, s_z = _fit_two_axes(radial2, axial2, lab, k, fallback=s)
    scales = np.stack([s, s, s_z], 1)
    scores = np.bincount(lab, existence[mask], minlength=k) / counts
    return CapFit(centers, rotations, scales, scores, counts)


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
