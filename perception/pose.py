"""Cap pose from the implicit encoding (paper Sec. 3.4, docs/DESIGN.md section 4), all instances at once.

For a cap with centre c and axis u, the orientation value of a point p is u . (p - c) / s_z, so the
least squares (P - c) lambda = Y_o gives lambda = u / s_z: u = lambda / |lambda|. The c we have is
the cluster's mean predicted centre c', off by some e = c' - c, and then Y_o = (P - c') lambda +
lambda . e exactly: so we solve for an intercept too, [P - c', 1] (lambda, b) = Y_o. The axis no
longer depends on e, and b / |lambda| = u . e is the centre's error along the axis, which we take off.
Without the intercept, e biases the axis towards the vertical.

With the axis known, the ellipsoid equation gives the size (and ``with_dome_sizes`` then measures the
radius and height on the cap's own points: the dome fitted to them, ``fit_domes``). The paper fixes
s_z = 2 s / 3 and fits one s (``height="fixed"``); by default we fit s and s_z together, (x^2 + y^2) /
s^2 + z^2 / s_z^2 = 1 being linear in (1 / s^2, 1 / s_z^2), and keep s_z / s within the range real caps
span, because caps are not all of one shape.

By default (``axis="surface"``) the encoding's axis is then refined by the cap's own surface: an
ellipsoid fitted to the cluster's points, started at the encoding's pose. The encoding values are
noisy on a cap a few voxels across, while the dome's shape pins its axis down; the encoding stays in
the fit, weakly, to hold the axis where the visible dome alone cannot (``refine_axes``), and more strongly on a cloud whose surfaces are noisier than any the synthetic beds
show (``encoding_weight``), as a real scan's are.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from perception.cap import CAP_HEIGHT_RATIO, Caps, rotation_from_axis

HEIGHT_MODES = ("free", "fixed")
AXIS_MODES = ("surface", "encoding")
RADIUS_MODES = ("rim", "fit")
SURFACE_ITERATIONS = 6
"""Steps of the surface fit: the axis stops improving after about six (docs/RESULTS.md, "How the fit's constants were chosen")."""
SURFACE_L1_SCALE = 1e-4
"""Metres. Surface residuals above it are weighted as in an L1 fit, so that a cluster's stray voxels
(rim, gills, a neighbour's edge) do not pull the axis."""
SURFACE_OUTLIER_FACTOR = 8.0
"""A point further from the current surface than this many times the median distance of all the
clusters' points has no say in the next step: voxels where cap and soil meet would turn a small cap
even under L1 weights, and the median scales the cut with the cloud's noise."""
SURFACE_ENCODING_WEIGHT = 0.04
"""Weight of the encoding residual (a distance along the axis, metres) beside the surface's, on a clean
surface (``encoding_weight`` raises it on a noisy one): it keeps a small or half-seen dome's axis from
swinging off."""
SURFACE_MIN_POINTS = 8
"""Smaller clusters keep the encoding's axis: nine unknowns need more than a handful of points. So do
clusters whose fitted height ratio leaves ``HEIGHT_RATIO_RANGE``: the fit has turned them over."""
SURFACE_MAX_POINTS = 64
"""A larger cluster is fitted on an even subset of this many points: on 2 cores the fit's cost is the
padded width, and more points gain little."""
STEP_LIMITS = np.array([6e-3, 0.45])
"""Largest move of the centre (metres) and turn (radians) in one step of the surface fit; a cap the
bound lets swing over is caught by the height-ratio gate."""
RIM_QUANTILE = 0.9
"""This quantile of a cap's points' distances from its axis (``rim_radii``) bounds the dome fit's rim
(``RIM_DOME_RANGE``) and stands in for it where the fit fails."""
RIM_DOME_RANGE = (0.8, 1.25)
"""The dome fitted to a cap's own points (``fit_domes``) gives its radius and height when its rim lies
within these factors of ``RIM_QUANTILE``'s distance; beyond them the fit extrapolates a crown or a stray
piece of soil, and the quantile and the pose fit's height are kept."""
SURFACE_NOISE_REFERENCE = 3e-4
"""Metres. Up to this median distance of the clusters' points from their fitted surfaces the encoding
keeps ``SURFACE_ENCODING_WEIGHT`` (``encoding_weight``): above every synthetic camera's noise, below a
real RealSense cloud's."""
HEIGHT_RATIO_RANGE = (CAP_HEIGHT_RATIO * 0.8 / 1.2, CAP_HEIGHT_RATIO * 1.2 / 0.8)
"""s_z / s of the template under per-axis factors in [0.8, 1.2]."""


class _Clusters:
    """The labelled points sorted by label (stable: each cluster keeps its order), per-point values
    component-major: numpy's small-axis operations on (n, 3) rows cost several times more than the
    same operations on (3, n) rows. Per-label sums are one ``np.add.reduceat`` over stacked rows."""

    def __init__(self, labels: np.ndarray):
        index = np.flatnonzero(labels >= 0)
        small = labels[index].astype(np.int16) if len(index) and labels.max() < 2**15 else labels[index]
        # a stable sort of 16-bit keys is numpy's radix sort, six times faster than of int64
        self.index = index[np.argsort(small, kind="stable")]
        self.lab = labels[self.index]
        self.k = int(self.lab[-1]) + 1 if len(self.lab) else 0
        self.counts = np.bincount(self.lab, minlength=self.k)
        self.starts = np.cumsum(self.counts) - self.counts
        self.present = self.counts > 0

    def take(self, values: np.ndarray) -> np.ndarray:
        """``values`` (n,) or (n, c) of the labelled points, as float64 (m,) or (c, m) in cluster order."""
        return values.take(self.index, axis=0).T.astype(np.float64, order="C")

    def spread(self, per_label: np.ndarray) -> np.ndarray:
        """Per-label rows (k, c) -> (c, m): each labelled point's."""
        return per_label.T.take(self.lab, axis=1)

    def sums(self, rows: np.ndarray) -> np.ndarray:
        """Per-label sums of ``rows`` (c, m) -> (k, c); 0 for absent labels."""
        sums = np.zeros((self.k, len(rows)))
        sums[self.present] = np.add.reduceat(rows, self.starts[self.present], axis=1).T
        return sums


_PAIRS = tuple(index[:-1] for index in np.triu_indices(4))
"""Pairwise products of the rows [d_x, d_y, d_z, y] but (y, y): their sums, the rows' own and the count
make the normal equations of [d, 1] (lambda, b) = y, whose unknowns and right side ``_SYSTEM_INDEX``
places."""
_SYSTEM_INDEX = np.array([0, 1, 2, 4])


def fit_caps(points: np.ndarray, predicted_centers: np.ndarray, orientation: np.ndarray,
             existence: np.ndarray, labels: np.ndarray, height: str = "free", axis: str = "surface") -> Caps:
    """Fit every labelled instance (labels 0..K-1; -1 ignored) in one vectorised pass.

    ``axis="surface"`` refines the encoding's axes by each cluster's surface (``refine_axes``);
    ``"encoding"`` keeps the encoding's, as the paper does."""
    if height not in HEIGHT_MODES:
        raise ValueError(f"unknown height mode {height!r}; choose one of {HEIGHT_MODES}")
    if axis not in AXIS_MODES:
        raise ValueError(f"unknown axis mode {axis!r}; choose one of {AXIS_MODES}")
    clusters = _Clusters(np.asarray(labels))
    k, counts = clusters.k, clusters.counts
    if k == 0:
        return Caps.none()
    p, y = clusters.take(points), clusters.take(orientation)
    sums = clusters.sums(np.vstack([clusters.take(predicted_centers), clusters.take(existence)]))
    centers, scores = sums[:, :3] / counts[:, None], sums[:, 3] / counts
    if np.ndim(orientation) == 2:
        return _fit_explicit_axes(clusters, p, centers, scores, orientation, height)
    d = p - clusters.spread(centers)
    rows = np.vstack([d, y])
    moments = clusters.sums(np.vstack([rows[_PAIRS[0]] * rows[_PAIRS[1]], rows]))
    system = np.zeros((k, 5, 5))
    row, column = _SYSTEM_INDEX[_PAIRS[0]], _SYSTEM_INDEX[_PAIRS[1]]
    system[:, row, column] = system[:, column, row] = moments[:, :len(row)]
    system[:, 3, :3] = system[:, :3, 3] = moments[:, -4:-1]
    system[:, 3, 3], system[:, 3, 4] = counts, moments[:, -1]
    solution = np.linalg.solve(system[:, :4, :4] + 1e-12 * np.eye(4), system[:, :4, 4:])[:, :, 0]
    lam, intercept = solution[:, :3], solution[:, 3]
    norm = np.sqrt(np.einsum("ij,ij->i", lam, lam))
    posed = norm > 1e-12
    cap_axis = np.where(posed[:, None], lam / np.maximum(norm, 1e-12)[:, None], [0.0, 0.0, 1.0])
    # clipped: a cluster flat along its axis leaves the intercept poorly determined
    rms_radius = np.sqrt(np.trace(system[:, :3, :3], axis1=1, axis2=2) / counts)
    along_axis = np.clip(np.where(posed, intercept / np.maximum(norm, 1e-12), 0.0), -rms_radius, rms_radius)
    centers -= along_axis[:, None] * cap_axis
    d = p - clusters.spread(centers)
    rotations, scales = _orient_and_size(d, clusters, cap_axis, height)
    if axis == "surface":
        cap_axis = refine_axes(p, y, clusters.lab, centers, rotations, scales)
        rotations, scales = _orient_and_size(d, clusters, cap_axis, height)
    return Caps(centers, rotations, scales, scores, counts)


def _squared_offsets(points: np.ndarray, labels: np.ndarray, caps: Caps) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The labelled points' labels and squared distances along their cap's axis from its centre and
    from the axis line (labels 0..K-1, -1 ignored)."""
    kept = labels >= 0
    lab = labels[kept]
    offsets = points[kept] - caps.centers[lab]
    along2 = np.einsum("ij,ij->i", offsets, caps.axes[lab]) ** 2
    return lab, along2, np.maximum(np.einsum("ij,ij->i", offsets, offsets) - along2, 0.0)


def _quantile_radii(lab: np.ndarray, radial2: np.ndarray, caps: int, quantile: float, min_points: int) -> np.ndarray:
    """``rim_radii`` from ``_squared_offsets``: one sort of the points by (label, distance), as one float
    key, the label plus the distance scaled into [0, 1) (five times faster than ``np.lexsort``)."""
    scale = 2.0 * float(radial2.max()) if len(radial2) else 1.0
    order = np.argsort(lab + radial2 / max(scale, 1e-300))
    counts = np.bincount(lab, minlength=caps)
    enough = counts >= max(min_points, 1)
    rank = (np.cumsum(counts) - counts)[enough] + np.floor(quantile * (counts[enough] - 1)).astype(np.int64)
    radii = np.full(caps, np.nan)
    radii[enough] = np.sqrt(radial2[order][rank])
    return radii


def _dome_fits(lab: np.ndarray, along2: np.ndarray, radial2: np.ndarray, caps: int,
               min_points: int) -> tuple[np.ndarray, np.ndarray]:
    """``fit_domes`` from ``_squared_offsets``: the normal equations of a r^2 + b z^2 = 1 per cap."""
    rr, rz, zz = (np.bincount(lab, w, caps) for w in (radial2 * radial2, radial2 * along2, along2 * along2))
    r_sum, z_sum = np.bincount(lab, radial2, caps), np.bincount(lab, along2, caps)
    det = rr * zz - rz * rz
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse_s2 = (zz * r_sum - rz * z_sum) / det
        inverse_sz2 = (rr * z_sum - rz * r_sum) / det
    dome = (np.bincount(lab, minlength=caps) >= max(min_points, 1)) & (det > 0) & (inverse_s2 > 0) & (inverse_sz2 > 0)
    radii, heights = np.full(caps, np.nan), np.full(caps, np.nan)
    radii[dome], heights[dome] = 1.0 / np.sqrt(inverse_s2[dome]), 1.0 / np.sqrt(inverse_sz2[dome])
    return radii, heights


def rim_radii(points: np.ndarray, labels: np.ndarray, caps: Caps, quantile: float = RIM_QUANTILE,
              min_points: int = 1) -> np.ndarray:
    """Each cap's ``quantile`` of its points' (N, 3) distances from its axis line (labels 0..K-1, -1
    ignored), nan for a cap with fewer than ``min_points``."""
    lab, _, radial2 = _squared_offsets(points, labels, caps)
    return _quantile_radii(lab, radial2, len(caps), quantile, min_points)


def fit_domes(points: np.ndarray, labels: np.ndarray, caps: Caps, min_points: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Each cap's rim radius s and height s_z of the dome (x^2 + y^2) / s^2 + z^2 / s_z^2 = 1 about its
    centre and axis that fits its points (N, 3; labels 0..K-1, -1 ignored) best, both free: least
    squares in (1 / s^2, 1 / s_z^2), one 2x2 system per cap from per-label sums. nan for a cap with
    fewer than ``min_points`` or whose best fit is no dome (a bowl or a saddle). Every point of the cap
    has its say, where a quantile reads the rim from a few; a dome of any height is fitted, where the
    pose fit holds s_z / s near the template's."""
    return _dome_fits(*_squared_offsets(points, labels, caps), len(caps), min_points)


def with_dome_sizes(caps: Caps, points: np.ndarray, labels: np.ndarray) -> Caps:
    """The caps with their radius s and height s_z measured on their own points: the dome they fit
    (``fit_domes``), or where that dome's rim leaves ``RIM_DOME_RANGE`` of ``RIM_QUANTILE``'s distance,
    that distance and the pose fit's height; the centre and the axis stay the pose fit's. A cap with
    fewer than ``SURFACE_MIN_POINTS`` keeps its fit. The height is what the points show however flat:
    points scattered about one level fit a dome as low as their scatter, and that is where their top
    is."""
    lab, along2, radial2 = _squared_offsets(points, labels, caps)
    rim = _quantile_radii(lab, radial2, len(caps), RIM_QUANTILE, SURFACE_MIN_POINTS)
    radii, heights = _dome_fits(lab, along2, radial2, len(caps), SURFACE_MIN_POINTS)
    low, high = RIM_DOME_RANGE
    with np.errstate(invalid="ignore"):
        trusted = (radii >= low * rim) & (radii <= high * rim)
    radius = np.where(trusted, radii, np.where(np.isfinite(rim), rim, caps.radii))
    height = np.where(trusted, heights, caps.scales[:, 2])
    return replace(caps, scales=np.column_stack([radius, radius, height]))


def _fit_explicit_axes(clusters: _Clusters, p: np.ndarray, centers: np.ndarray, scores: np.ndarray,
                       vectors: np.ndarray, height: str) -> Caps:
    """Caps from the explicit-orientation ablation (the paper's Table 2): every cap voxel predicts its
    cap's axis; a cap's axis is the mean of its voxels' unit vectors, its centre the mean predicted
    centre, its size as for the implicit encoding (no intercept, no surface refinement)."""
    v = clusters.take(vectors)
    v = v / np.maximum(np.linalg.norm(v, axis=0), 1e-12)
    mean = clusters.sums(v)
    norm = np.linalg.norm(mean, axis=1)
    cap_axis = np.where(norm[:, None] > 1e-12, mean / np.maximum(norm, 1e-12)[:, None], [0.0, 0.0, 1.0])
    rotations, scales = _orient_and_size(p - clusters.spread(centers), clusters, cap_axis, height)
    return Caps(centers, rotations, scales, scores, clusters.counts)


def _orient_and_size(d: np.ndarray, clusters: _Clusters, cap_axis: np.ndarray,
                     height: str) -> tuple[np.ndarray, np.ndarray]:
    """Spin-free rotations (axis turned up) and (s, s, s_z) for offsets ``d`` (3, m) from the cap
    centres."""
    cap_axis = cap_axis * np.where(cap_axis[:, 2:3] < 0, -1.0, 1.0)
    rotations = rotation_from_axis(cap_axis)
    axial2 = np.einsum("ij,ij->j", d, clusters.spread(cap_axis)) ** 2
    radial2 = np.maximum(np.einsum("ij,ij->j", d, d) - axial2, 0.0)
    sums = clusters.sums(np.vstack([np.sqrt(radial2 + axial2 / CAP_HEIGHT_RATIO**2), radial2 * radial2,
                                    radial2 * axial2, axial2 * axial2, radial2, axial2]))
    s = sums[:, 0] / clusters.counts
    s_z = CAP_HEIGHT_RATIO * s
    if height == "free":
        s, s_z = _fit_two_axes(*sums[:, 1:].T, fallback=s)
    return rotations, np.stack([s, s, s_z], 1)


def encoding_weight(noise: float) -> float:
    """The encoding residual's weight for a cloud whose points lie a median ``noise`` metres off their
    fitted surfaces: ``SURFACE_ENCODING_WEIGHT`` up to ``SURFACE_NOISE_REFERENCE``, then in proportion.

    The surface pins a cap's axis down only as well as the surface is measured, while the network reads
    a noisy cloud through its voxels and its encoding degrades far less. Val50 beds (the first 10, read
    four times) with Gaussian noise of 0.6 mm added: angle from the truth 6.62 degrees with the fixed
    weight, 4.73 with the encoding alone, 6.09 with this weight. The real cloud of ../shared/real/
    (0.39-0.41 mm off the fitted surfaces): its caps' axes 17.1 degrees from its labels' on average
    with the fixed weight, 12.5 with the encoding alone, 15.0 with this weight (median 12.3, 8.0,
    11.1)."""
    return SURFACE_ENCODING_WEIGHT * max(1.0, noise / SURFACE_NOISE_REFERENCE)


def refine_axes(points: np.ndarray, orientation: np.ndarray, lab: np.ndarray, centers: np.ndarray,
                rotations: np.ndarray, scales: np.ndarray, iterations: int = SURFACE_ITERATIONS) -> np.ndarray:
    """Cap axes (K, 3) from an ellipsoid fitted to each cluster's points (3, n), all clusters at once;
    the points come in cluster order (``lab`` sorted).

    Gauss-Newton from the encoding's pose over centre, rotation and three semi-axes: the two base
    semi-axes may differ, as on real caps (and the synthetic ones, per-axis factors 0.8-1.2); a surface
    of revolution fitted to an oval cap tilts its axis. The residual of a point is its radial distance
    to the surface, (rho - 1) times the mean base semi-axis, rho^2 = sum_i (q_i / a_i)^2 in the cap
    frame q, reweighted towards L1 and zero for a point ``SURFACE_OUTLIER_FACTOR`` median distances off;
    beside it, ``SURFACE_ENCODING_WEIGHT`` times the encoding's miss along the axis, q_z - y a_z. Where
    the points of the fits that stand then lie a median distance off their surfaces above
    ``SURFACE_NOISE_REFERENCE`` (a noisy cloud), the fit runs again from the encoding's pose with the
    weight ``encoding_weight`` gives. Steps are bounded (0.45 rad, 6 mm, 20 % in size), and a fit that
    has turned a flat, half-seen dome over fails the height-ratio gate. Only the axis is kept: the
    fitted centre and semi-axes are worse than the encoding's on small caps.
    """
    counts = np.bincount(lab, minlength=len(centers))
    padded = _padded_clusters(points, orientation, lab, counts)
    refined, semi, distance = _fit_surfaces(padded, centers, rotations, scales, iterations, SURFACE_ENCODING_WEIGHT)
    keep = _kept_fits(refined, semi, counts)
    weight = encoding_weight(_median_distance(distance, padded[2], keep))
    if weight > SURFACE_ENCODING_WEIGHT:
        refined, semi, _ = _fit_surfaces(padded, centers, rotations, scales, iterations, weight)
        keep = _kept_fits(refined, semi, counts)
    return np.where(keep[:, None], refined, rotations[:, :, 2])


def _kept_fits(refined: np.ndarray, semi: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Which clusters' fitted axes stand: enough points, finite, and a height ratio in
    ``HEIGHT_RATIO_RANGE`` (outside it the fit has turned a flat, half-seen dome over)."""
    height_ratio = semi[:, 2] / (0.5 * (semi[:, 0] + semi[:, 1]))
    plausible = (height_ratio >= HEIGHT_RATIO_RANGE[0]) & (height_ratio <= HEIGHT_RATIO_RANGE[1])
    return (counts >= SURFACE_MIN_POINTS) & np.isfinite(refined).all(1) & plausible


def _median_distance(distance: np.ndarray, real: np.ndarray, keep: np.ndarray) -> float:
    """The median of the (K, width) distances from the fitted surfaces over the points (``real``) of
    the clusters whose fits stand (``keep``), finite ones only; 0 when there are none."""
    values = distance[keep][real[keep] > 0]
    values = values[np.isfinite(values)]
    return float(np.median(values)) if len(values) else 0.0


def _in_cap_frames(padded_points: np.ndarray, center: np.ndarray, rotation: np.ndarray,
                   semi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The padded points in each cap's frame q (K, 3, width), the inverse semi-axes (K, 3, 1), the
    points' ellipsoidal radius rho (at least 1e-9; 1 on the surface) and the caps' mean base semi-axes
    (K, 1): a point's distance from its surface is |rho - 1| times that."""
    q = rotation.transpose(0, 2, 1) @ (padded_points - center[:, :, None])
    inverse_semi = (1.0 / semi)[:, :, None]
    q_scaled = q * inverse_semi
    rho = np.sqrt(np.einsum("kiw,kiw->kw", q_scaled, q_scaled))
    np.maximum(rho, 1e-9, out=rho)
    return q, inverse_semi, rho, 0.5 * (semi[:, :1] + semi[:, 1:2])


def _fit_surfaces(padded: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], centers: np.ndarray,
                  rotations: np.ndarray, scales: np.ndarray, iterations: int,
                  weight_of_encoding: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``refine_axes``'s Gauss-Newton steps on the padded clusters (``_padded_clusters``) with the
    encoding residual weighted ``weight_of_encoding``: the fitted axes (K, 3), semi-axes (K, 3), and
    each padded slot's distance from its fitted surface (K, width; metres)."""
    padded_points, values, real, cell = padded
    k, width = real.shape
    center, rotation = centers.copy(), rotations.copy()
    log_axes = np.log(np.maximum(scales, 1e-6))
    # the Jacobian's nine rows and, last, the residuals: one batched product gives J J^T and J r
    rows = np.zeros((k, 10, 2 * width))
    surface_rows, encoding_rows = rows[:, :, :width], rows[:, :, width:]
    encoding_rows_weight = weight_of_encoding * real
    minus_weight, minus_weighted_values = -encoding_rows_weight, -encoding_rows_weight * values
    for _ in range(iterations):
        semi = np.exp(log_axes)
        q, inverse_semi, rho, mean_radius = _in_cap_frames(padded_points, center, rotation, semi)
        miss = rho - 1.0
        surface = miss * mean_radius
        distance = np.abs(surface)
        cut = SURFACE_OUTLIER_FACTOR * np.median(distance.reshape(-1)[cell])
        weight = (real * (distance < cut)) * np.sqrt(SURFACE_L1_SCALE / np.maximum(distance, SURFACE_L1_SCALE))
        np.multiply(weight, surface, out=surface_rows[:, 9])
        # minus the weighted gradient of the residual by the point in the cap frame
        pull = (weight * (-mean_radius) / rho)[:, None] * (q * inverse_semi**2)
        np.matmul(rotation, pull, out=surface_rows[:, :3])
        np.subtract(pull[:, 2] * q[:, 1], pull[:, 1] * q[:, 2], out=surface_rows[:, 3])
        np.subtract(pull[:, 0] * q[:, 2], pull[:, 2] * q[:, 0], out=surface_rows[:, 4])
        np.subtract(pull[:, 1] * q[:, 0], pull[:, 0] * q[:, 1], out=surface_rows[:, 5])
        np.multiply(q, pull, out=surface_rows[:, 6:9])
        half_miss = (0.5 * weight) * miss
        surface_rows[:, 6:8] += half_miss[:, None] * semi[:, :2, None]
        np.multiply(rotation[:, :, 2:], minus_weight[:, None], out=encoding_rows[:, :3])
        np.multiply(q[:, 1], minus_weight, out=encoding_rows[:, 3])
        np.multiply(q[:, 0], encoding_rows_weight, out=encoding_rows[:, 4])
        np.multiply(minus_weighted_values, semi[:, 2:], out=encoding_rows[:, 8])
        np.add(encoding_rows_weight * q[:, 2], encoding_rows[:, 8], out=encoding_rows[:, 9])
        products = rows @ rows.transpose(0, 2, 1)
        normal, gradient = products[:, :9, :9], products[:, :9, 9:]
        diagonal = products.reshape(k, 100)[:, :99:11]
        diagonal *= 1.0 + 1e-3
        diagonal += 1e-18
        step = -np.linalg.solve(normal, gradient)[:, :, 0]
        moves = step.reshape(k, 3, 3)[:, :2]
        lengths = np.sqrt(np.einsum("kij,kij->ki", moves, moves))
        moves *= np.minimum(1.0, STEP_LIMITS / np.maximum(lengths, 1e-12))[:, :, None]
        center += step[:, :3]
        rotation = rotation @ Rotation.from_rotvec(step[:, 3:6]).as_matrix()
        log_axes += np.minimum(np.maximum(step[:, 6:], -0.2), 0.2)
    semi = np.exp(log_axes)
    _, _, rho, mean_radius = _in_cap_frames(padded_points, center, rotation, semi)
    return rotation[:, :, 2], semi, np.abs(rho - 1.0) * mean_radius


def _padded_clusters(points: np.ndarray, orientation: np.ndarray, lab: np.ndarray,
                     counts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The clusters' points (3, n) and orientation values (n,), in cluster order, as zero-padded rows:
    points (K, 3, width), values (K, width), 1 where a row holds a point (K, width), and each kept
    point's index in the flattened (K, width) rows.

    Every step of the surface fit is then a batched array operation whose innermost loop runs along a
    cluster's points. A cluster of n points over ``SURFACE_MAX_POINTS`` = m keeps an even subset: its
    points ceil(j n / m), j < m.
    """
    k = len(counts)
    kept = np.minimum(counts, SURFACE_MAX_POINTS) if SURFACE_MAX_POINTS else counts
    subset_lab = np.repeat(np.arange(k), kept)
    slot = np.arange(len(subset_lab)) - np.repeat(np.cumsum(kept) - kept, kept)
    n, m = counts[subset_lab], kept[subset_lab]
    chosen = np.repeat(np.cumsum(counts) - counts, kept) + (slot * n + m - 1) // m
    points, orientation, lab = points[:, chosen], orientation[chosen], subset_lab
    width = int(kept.max())
    cell = lab * width + slot
    real = np.zeros((k, width))
    real.reshape(-1)[cell] = 1.0
    values = np.zeros((k, width))
    values.reshape(-1)[cell] = orientation
    padded_points = np.zeros((k, 3, width))
    padded_points.reshape(-1)[cell + 2 * width * lab + width * np.arange(3)[:, None]] = points
    return padded_points, values, real, cell

def _fit_two_axes(a11: np.ndarray, a12: np.ndarray, a22: np.ndarray, b1: np.ndarray, b2: np.ndarray,
                  fallback: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares a r^2 + b z^2 = 1 per instance: s = a^-1/2, s_z = b^-1/2, s_z / s clamped; the
    arguments are its per-instance sums of r^4, r^2 z^2, z^4, r^2 and z^2.

    Instances whose system is degenerate (e.g. a sliver of points at one height) keep ``fallback``,
    the fixed-ratio size.
    """
    det = a11 * a22 - a12**2
    safe = np.where(det > 0, det, 1.0)
    a, b = (b1 * a22 - b2 * a12) / safe, (a11 * b2 - a12 * b1) / safe
    good = (det > 1e-9 * a11 * a22) & (a > 0)
    s = np.where(good, 1.0 / np.sqrt(np.where(good, a, 1.0)), fallback)
    ratio = np.where(good & (b > 0), 1.0 / np.sqrt(np.where(b > 0, b, 1.0)) / s, CAP_HEIGHT_RATIO)
    return s, np.clip(ratio, *HEIGHT_RATIO_RANGE) * s
