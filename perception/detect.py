"""From a point cloud in the bed frame to caps: voxelise, run the network, cluster, fit poses."""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Union

import numpy as np

from common.geometry import (cell_lookup, median_neighbour_distance, transform_points, turning_about_z,
                             voxel_representatives)
from perception.cap import Caps
from perception.inference import COORD_MAX, InferenceNet, voxelize
from perception.instances import ClusterConfig, cluster
from perception.network import LENGTH_UNIT, voxel_features
from perception.pose import RADIUS_MODES, fit_caps, with_dome_sizes
from perception.surface_noise import smoothed

if TYPE_CHECKING:
    from perception.model import MushroomNet

Network = Union["MushroomNet", InferenceNet]
"""A trained network as inference reads it: the numpy one ``detect`` loads for a cloud file
(``perception.inference``), or the torch one of training, the live chain and ``eval``."""



@dataclass(frozen=True)
class VoxelPrediction:
    """The network's encoding on each occupied voxel (centroid of its points), and the point map."""

    centroids: np.ndarray
    existence: np.ndarray
    centers: np.ndarray
    """Predicted cap centre of each voxel: centroid + residual."""
    orientation: np.ndarray
    point_to_voxel: np.ndarray
    filled_in: int = 0
    """How many points a sparse cloud was filled in with before it was read (``densified_for_reading``)."""


@dataclass(frozen=True)
class SceneResult:
    """Detected caps plus what led to them, per point of the input, in the input's frame."""

    caps: Caps
    point_labels: np.ndarray
    """Each input point's cap (its index in ``caps``), -1 off every cap."""
    point_existence: np.ndarray
    voxels: VoxelPrediction
    frame: str = "bed"
    timings_ms: dict = field(default_factory=dict)
    surface_noise: float = float("nan")
    """The cloud's ``perception.surface_noise.surface_noise``; over ``CLEAN_NOISE`` its points were
    smoothed before the network read them."""


def network_input(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Voxel coords (V, 4), the point-to-voxel map and voxel centroids of a cloud (N, 3) in metres."""
    points = np.asarray(points, np.float64)
    coords, point_to_voxel = voxelize(points, voxel)
    return coords, point_to_voxel, voxel_average(points, point_to_voxel, len(coords))


def voxel_average(values: np.ndarray, point_to_voxel: np.ndarray, voxels: int) -> np.ndarray:
    """Mean of the values (N, C) of the points in each voxel -> (voxels, C)."""
    counts = np.maximum(np.bincount(point_to_voxel, minlength=voxels), 1)
    return np.stack([np.bincount(point_to_voxel, column, voxels) for column in values.T], 1) / counts[:, None]


def _outputs_of(model: Network, coords: np.ndarray, features: np.ndarray) -> np.ndarray:
    """(V, out_channels) float64 network outputs on voxels ``coords`` with input ``features``, the
    existence logit turned into a probability (by the sigmoid of the network's own library)."""
    if isinstance(model, InferenceNet):
        out = model(coords, features).astype(np.float64)
        with np.errstate(over="ignore"):
            out[:, 0] = 1.0 / (1.0 + np.exp(-out[:, 0]))
        return out
    import torch

    from perception.model import inference_model
    from perception.sparse import SparseTensor

    device = next(model.parameters()).device
    with torch.no_grad():
        inputs = SparseTensor(torch.from_numpy(features).to(device), torch.from_numpy(coords).to(device))
        out = inference_model(model)(inputs).double()
        out[:, 0] = torch.sigmoid(out[:, 0])
        return out.cpu().numpy()


def at_training_density(model: Network, points: np.ndarray) -> np.ndarray:
    """Indices of the points the network reads: one per ``model.point_spacing`` cell when the cloud
    has over twice as many points as such cells (training beds have 1-1.5), else all of them."""
    if model.point_spacing:
        representatives = voxel_representatives(points, model.point_spacing)
        if len(points) > 2 * len(representatives):
            return representatives
    return np.arange(len(points))


LIVE_READINGS = 1
"""How many times a cloud is read where someone waits for each answer (the live runner, the demo, and
``predict``'s default): one pass of the network keeps a live turn's caps within the 1.0 s target."""

FILE_READINGS = 4
"""How many times ``detect`` and ``eval`` read a cloud, each reading turned another 90 degrees about the
vertical: the voxel grid falls differently over each cap in every reading, and their average gives
steadier caps with fewer false detections (docs/RESULTS.md, "How the fit's constants were chosen")."""

MAX_READINGS = 12
"""The most readings a command takes: each is a pass of the network, and more than six steady the caps
no further."""

OPERATING_SPACING = 0.0035
"""Metres: beyond this point spacing caps under 30 mm across are found less reliably (the model card's
operating range, ``bench/range.py``)."""
OPERATING_DIAMETER = 0.080
"""Metres: caps wider than this are found less reliably (the same table)."""
NEIGHBOUR_PER_SPACING = 0.645
"""Median distance from a point of a synthetic bed to its nearest neighbour, over the bed's point
spacing: how a cloud's measured neighbour distance is read as a generator's spacing."""
DENSIFY_RATIOS = (2.0, 4.0)
"""A cloud whose points lie from 2 to 4 times as far apart as the training beds' (``point_spacing``; 6-12 mm
for the shipped model) is filled in to their spacing before it is read (``perception.densify``), and still
read at its own spacing's zoom (``reading_zoom``): the filled-in caps lack the steep sides no triangle
spans, and read smaller they are found as the sparse zoom finds caps. A sparser cloud shows too little
of a cap to fill in, and would grow by the square of the ratio."""
SPARSE_ZOOM_EXPONENT = 0.56
"""How much lower a sparse cloud is read: zoom x (spacing ratio)^-0.56, so a bed sampled every 5 mm is
read at 0.9 instead of 1.2, where its AP@50 peaks (docs/RESULTS.md, "How the fit's constants were chosen")."""


def point_spacing(points: np.ndarray, samples: int = 5000) -> float:
    """The spacing (metres) of the synthetic beds whose points lie as far apart as these: their median
    nearest-neighbour distance over ``NEIGHBOUR_PER_SPACING``; nan for fewer than 100 points."""
    if len(points) < 100:
        return float("nan")
    return median_neighbour_distance(points, queries=samples) / NEIGHBOUR_PER_SPACING


def reading_zoom(model: Network, points: np.ndarray, spacing: float | None = None) -> float:
    """The zoom a cloud (at most training density, ``at_training_density``) is read at: the model's,
    lowered for a cloud sparser than the model's training beds. The network learnt caps from beds with
    a point per 3 mm; on sparser ones a cap's voxels are a gappy shell, and reading the cloud smaller
    closes it up (caps then look smaller, which costs less). ``spacing``: the points' ``point_spacing``,
    when measured already."""
    zoom = model.inference_zoom
    spacing = point_spacing(points) if spacing is None else spacing
    if not model.point_spacing or not np.isfinite(spacing):
        return zoom
    return zoom * min(1.0, (spacing / model.point_spacing) ** -SPARSE_ZOOM_EXPONENT)


@dataclass(frozen=True)
class Reading:
    """The network's first reading of a cloud in the bed frame (``first_reading``): which points it
    read, at what zoom, their voxels and what it returned; ``predict`` goes on from it."""

    kept: np.ndarray
    """Indices of the cloud's points read (``at_training_density``)."""
    zoom: float
    read: np.ndarray
    """The points read: the kept ones, then those a sparse cloud is filled in with (``densified_for_reading``)."""
    coords: np.ndarray
    read_to_voxel: np.ndarray
    """Each read point's voxel: the kept points' first."""
    zoomed_centroids: np.ndarray
    output: tuple
    """``network_output``'s centroids, existence, centres and orientation values."""

    @property
    def cap_voxels(self) -> int:
        """How many voxels the network takes for cap (existence over 0.5)."""
        return int((self.output[1] > 0.5).sum())


def densified_for_reading(model: Network, points: np.ndarray, spacing: float | None = None) -> np.ndarray:
    """The points (bed frame), followed by those that fill them in to the training beds' spacing when
    they lie ``DENSIFY_RATIOS`` times as far apart (``perception.densify``); else the points as given.
    ``spacing``: the points' ``point_spacing``, when measured already."""
    from perception.densify import densified

    if not model.point_spacing:
        return points
    spacing = point_spacing(points) if spacing is None else spacing
    low, high = DENSIFY_RATIOS
    if not low * model.point_spacing < spacing <= high * model.point_spacing:
        return points
    return densified(points, spacing, model.point_spacing)


def reading_input(model: Network, points: np.ndarray, thin: bool = True,
                  zoom: float | None = None) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What the network's first reading of a non-empty cloud in the bed frame takes in: the indices of
    the points kept, the zoom (default: the kept points' ``reading_zoom``), the points read (with
    ``thin``, a dense cloud thinned and a sparse one filled in, ``densified_for_reading``), their
    voxels, each read point's voxel and the voxels' zoomed centroids."""
    points = np.asarray(points, np.float64)
    kept = at_training_density(model, points) if thin else np.arange(len(points))
    spacing = point_spacing(points[kept]) if thin or zoom is None else None
    zoom = reading_zoom(model, points[kept], spacing) if zoom is None else zoom
    reach, grid = float(np.abs(points[kept]).max()), COORD_MAX * model.config.voxel / zoom
    if not reach < grid:  # points filled in lie inside the kept ones' hull
        raise ValueError(f"the cloud reaches {reach:.3g} m from the bed origin, beyond the voxel grid's "
                         f"{grid:.0f} m: bring it near the origin")
    read = densified_for_reading(model, points[kept], spacing) if thin else points[kept]
    return kept, zoom, read, *network_input(zoom * read, model.config.voxel)


def first_reading(model: Network, points: np.ndarray, thin: bool = True, zoom: float | None = None,
                  read: tuple | None = None) -> Reading:
    """One pass of the network over a non-empty cloud in the bed frame, as ``predict`` reads it first;
    ``read`` is the cloud's ``reading_input`` when it was made already."""
    kept, zoom, points_read, coords, read_to_voxel, zoomed_centroids = (
        reading_input(model, points, thin, zoom) if read is None else read)
    return Reading(kept, zoom, points_read, coords, read_to_voxel, zoomed_centroids,
                   network_output(model, coords, zoomed_centroids, zoom))


def predict(model: Network, points: np.ndarray, thin: bool = True,
            zoom: float | None = None, readings: int = LIVE_READINGS, first: Reading | None = None) -> VoxelPrediction:
    """The network's encoding for a cloud in the bed frame; ``point_to_voxel`` covers every input point.

    The network was trained on clouds with one point per ``model.point_spacing`` (the synthetic
    scenes' voxel; None: unknown, never thin). A much denser cloud (fused, or straight from a camera)
    is an input it never saw, and the network misreads it. So with ``thin``, such a cloud is first
    thinned (``at_training_density``), and points whose voxel lost its points take the prediction of
    the nearest kept voxel; a much sparser one is filled in (``densified_for_reading``), and only the
    cloud's own points are labelled. Clouds at training density are used as they are. The network then
    reads the cloud scaled by ``zoom`` (default:
    ``reading_zoom``); what it returns is in the cloud's own metres again. With ``readings`` over 1 the
    network reads the cloud that many times, turned about the vertical, and each voxel's encoding is
    the mean of the readings' (``LIVE_READINGS`` and ``FILE_READINGS`` say when). ``first``, the
    cloud's ``first_reading`` made with the same ``thin`` and ``zoom``, saves that pass.
    """
    if not 1 <= readings <= MAX_READINGS:
        raise ValueError(f"readings must be 1-{MAX_READINGS}, got {readings}")
    points = np.asarray(points, np.float64)
    if len(points) == 0:
        empty = np.zeros((0, 3))
        return VoxelPrediction(empty, np.zeros(0), empty, np.zeros(0), np.zeros(0, np.int64))
    first = first_reading(model, points, thin, zoom) if first is None else first
    kept, zoom = first.kept, first.zoom
    centroids, existence, centers, orientation = first.output
    if readings > 1:
        existence, centers, orientation = _averaged_readings(model, first.read, zoom, readings, first.read_to_voxel,
                                                             (existence, centers, orientation))
    kept_to_voxel = first.read_to_voxel[:len(kept)]  # the points filled in come after the kept ones
    if len(kept) == len(points):
        point_to_voxel = kept_to_voxel
    else:
        point_to_voxel = _nearest_voxel(zoom * points, model.config.voxel, first.coords, first.zoomed_centroids)
        point_to_voxel[kept] = kept_to_voxel
    return VoxelPrediction(centroids, existence, centers, orientation, point_to_voxel, len(first.read) - len(kept))


def network_output(model: Network, coords: np.ndarray, zoomed_centroids: np.ndarray, zoom: float):
    """The network on voxels of a cloud scaled by ``zoom`` (from ``network_input``), decoded in the
    cloud's own metres: voxel centroids, existence, predicted cap centres, orientation values."""
    out = _outputs_of(model, coords, voxel_features(model.config, zoomed_centroids))
    centroids = zoomed_centroids / zoom
    encoding = model.config.encoding
    centers = out[:, 1:4] * LENGTH_UNIT / zoom
    if encoding != "explicit-centre":
        centers += centroids
    orientation = out[:, 4:7] if encoding == "explicit-orientation" else np.clip(out[:, 4], 0.0, 1.0)
    return centroids, out[:, 0], centers, orientation


def _averaged_readings(model: Network, points: np.ndarray, zoom: float, readings: int,
                       point_to_voxel: np.ndarray, first: tuple) -> tuple:
    """Existence, centres and orientation values of the voxels of ``point_to_voxel`` averaged over
    ``readings`` readings of ``points``: the first (``first``) as they are, each further one turned by
    another 360/readings degrees about the vertical through their centroid, its centres turned back.
    Each reading lays the voxel grid differently over the caps; a voxel takes the mean of its points'
    values from each reading."""
    count = len(first[0])
    pivot = points.mean(0)
    total = np.column_stack(first)
    for k in range(1, readings):
        T_turned = turning_about_z(2 * np.pi * k / readings, pivot)
        coords, turned_to_voxel, zoomed = network_input(zoom * transform_points(T_turned, points), model.config.voxel)
        _, existence, centers, orientation = network_output(model, coords, zoomed, zoom)
        if orientation.ndim == 2:  # explicit axis vectors turn back with the centres
            orientation = orientation @ T_turned[:3, :3]
        turned_back = transform_points(np.linalg.inv(T_turned), centers.astype(np.float64))
        values = np.column_stack([existence, turned_back, orientation])
        total += voxel_average(values[turned_to_voxel], point_to_voxel, count)
    mean = total / readings
    return mean[:, 0], mean[:, 1:4], mean[:, 4] if first[2].ndim == 1 else mean[:, 4:]


def _nearest_voxel(points: np.ndarray, voxel: float, coords: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """Index of each point's own voxel in ``coords`` (rows batch, x, y, z) when occupied, else of the
    voxel with the nearest centroid."""
    index = cell_lookup(coords[:, 1:], np.floor(points / voxel).astype(np.int64))
    missing = index < 0
    if missing.any():
        from scipy.spatial import cKDTree

        index[missing] = cKDTree(centroids).query(points[missing])[1]
    return index


def merge_pieces(labels: np.ndarray, fit: Caps, ratio: float) -> np.ndarray | None:
    """Voxel labels with the caps whose fitted centres lie closer than ``ratio`` times the smaller
    fitted radius joined into one (relabelled 0..K-1, largest first); None when no two are that close.
    The smaller radius, because one bad fit with a huge radius would otherwise swallow its neighbours."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    radius = fit.radii
    distance = np.linalg.norm(fit.centers[:, None] - fit.centers[None], axis=2)
    close = np.triu(distance < ratio * np.minimum(radius[:, None], radius[None]), 1)
    if not close.any():
        return None
    i, j = np.nonzero(close)
    _, group = connected_components(coo_matrix((np.ones(len(i)), (i, j)), shape=(len(radius),) * 2), directed=False)
    merged = np.where(labels >= 0, group[np.maximum(labels, 0)], -1)
    size = np.bincount(merged[merged >= 0], minlength=group.max() + 1)
    rank = np.empty(len(size), np.int64)
    rank[np.argsort(-size, kind="stable")] = np.arange(len(size))
    return np.where(merged >= 0, rank[np.maximum(merged, 0)], -1)


def find_caps(prediction: VoxelPrediction, voxel: float, cluster_config: ClusterConfig = ClusterConfig(),
              height: str = "free", axis: str = "surface", timings: dict | None = None,
              radius: str = "rim", points: np.ndarray | None = None) -> tuple[np.ndarray, Caps]:
    """Voxel labels and fitted caps from the network's encoding: clusters of collapsed points, their
    poses, pieces of one cap merged (``ClusterConfig.merge_ratio``, at most three rounds), and each
    cap's radius and height measured on its own points (``with_dome_sizes``: ``points``, the cloud the
    prediction was made of, each labelled by its voxel; without them, the voxel centroids).
    ``radius="fit"`` keeps the pose fit's s and s_z, as the paper does."""
    if radius not in RADIUS_MODES:
        raise ValueError(f"unknown radius mode {radius!r}; choose one of {RADIUS_MODES}")
    timings = {} if timings is None else timings
    start = time.perf_counter()
    labels = cluster(prediction.centroids, prediction.centers, prediction.existence, voxel, cluster_config)
    timings["instances"] = 1000 * (time.perf_counter() - start)
    start = time.perf_counter()
    arguments = (prediction.centroids, prediction.centers, prediction.orientation, prediction.existence)
    fit = fit_caps(*arguments, labels, height, axis)
    for _ in range(3 if cluster_config.merge_ratio else 0):
        merged = merge_pieces(labels, fit, cluster_config.merge_ratio)
        if merged is None:
            break
        labels = merged
        fit = fit_caps(*arguments, labels, height, axis)
    if radius == "rim":
        if points is None:
            fit = with_dome_sizes(fit, prediction.centroids, labels)
        else:
            fit = with_dome_sizes(fit, np.asarray(points, np.float64), labels[prediction.point_to_voxel])
    timings["pose"] = 1000 * (time.perf_counter() - start)
    return labels, fit


def detect_points(model: Network, points: np.ndarray, cluster_config: ClusterConfig = ClusterConfig(),
                  zoom: float | None = None, readings: int = LIVE_READINGS, first: Reading | None = None,
                  noise: float | None = None) -> SceneResult:
    """Caps in a cloud already in the bed frame (z up, metres), read ``readings`` times (``predict``) at
    ``zoom`` (default: the model's), a noisy cloud smoothed first (``perception.surface_noise``);
    ``first`` is its first reading when one was made already, and ``noise`` the cloud's surface noise
    when it was measured (and the cloud smoothed) already: both come from the same, final, points."""
    if first is not None and noise is None:
        raise ValueError("a first reading needs the surface noise of the points it read: give noise too")
    timings = {}
    start = time.perf_counter()
    if noise is None:
        points, noise = smoothed(points, model.point_spacing)
        timings["smoothing"] = 1000 * (time.perf_counter() - start)
        start = time.perf_counter()
    prediction = predict(model, points, zoom=zoom, readings=readings, first=first)
    timings["network"] = 1000 * (time.perf_counter() - start)
    voxel_labels, fit = find_caps(prediction, model.config.voxel, cluster_config, timings=timings, points=points)
    fit = model.calibration.applied(fit)
    point_labels = voxel_labels[prediction.point_to_voxel]
    members = np.bincount(point_labels[point_labels >= 0], minlength=len(fit))
    return SceneResult(replace(fit, members=members), point_labels, prediction.existence[prediction.point_to_voxel], prediction,
                       timings_ms=timings, surface_noise=noise)


def detect_up_side(model: Network, points: np.ndarray, T_input_bed: np.ndarray,
                   cluster_config: ClusterConfig = ClusterConfig(), zoom: float | None = None,
                   readings: int = LIVE_READINGS) -> tuple[np.ndarray, np.ndarray, SceneResult]:
    """T_input_bed turned to the side of the bed plane its caps say is up (``fusion.bed.side_with_caps``),
    the cloud in that bed frame (as given: the network reads it smoothed when noisy, as
    ``detect_points`` does), and its caps. The cloud is read once in each frame (the turned one not at
    all when it holds too few voxels to win), and the chosen frame's reading is the first of its
    ``readings``."""
    from fusion.bed import side_with_caps

    inputs, readings_made = {}, {}
    start = time.perf_counter()
    given, (points, noise) = points, smoothed(points, model.point_spacing)
    smoothing_ms = 1000 * (time.perf_counter() - start)

    def read_input(T: np.ndarray) -> tuple:
        if T.tobytes() not in inputs:
            bed_points = transform_points(np.linalg.inv(T), points)
            inputs[T.tobytes()] = bed_points, reading_input(model, bed_points, zoom=zoom)
        return inputs[T.tobytes()]

    def cap_voxels(T: np.ndarray) -> int:
        bed_points, read = read_input(T)
        readings_made[T.tobytes()] = first_reading(model, bed_points, read=read)
        return readings_made[T.tobytes()].cap_voxels

    def voxel_count(T: np.ndarray) -> int:
        return len(read_input(T)[1][3])

    T_input_bed = side_with_caps(T_input_bed, cap_voxels, voxel_count)
    read_points, first = inputs[T_input_bed.tobytes()][0], readings_made[T_input_bed.tobytes()]
    result = detect_points(model, read_points, cluster_config, zoom, readings, first, noise)
    result.timings_ms["smoothing"] = smoothing_ms
    bed_points = read_points if points is given else transform_points(np.linalg.inv(T_input_bed), given)
    return T_input_bed, bed_points, result


def detect_cloud(model: Network, points: np.ndarray, cluster_config: ClusterConfig = ClusterConfig(),
                 readings: int = FILE_READINGS) -> Caps:
    """The caps of a bed's cloud in its own frame, found as ``mushroom-pose detect`` finds them: the bed
    plane (``fusion.bed.estimate_bed_frame``), its up side by the caps, ``readings`` readings."""
    from fusion.bed import estimate_bed_frame

    T_input_bed = estimate_bed_frame(points)
    T_input_bed, _, result = detect_up_side(model, points, T_input_bed, cluster_config, readings=readings)
    return result.caps.moved(T_input_bed)


def transform_result(result: SceneResult, T_frame_bed: np.ndarray, frame: str) -> SceneResult:
    """The same caps expressed in another frame (rotations and centres moved; sizes unchanged)."""
    voxels = VoxelPrediction(transform_points(T_frame_bed, result.voxels.centroids), result.voxels.existence,
                             transform_points(T_frame_bed, result.voxels.centers), result.voxels.orientation,
                             result.voxels.point_to_voxel, result.voxels.filled_in)
    return SceneResult(result.caps.moved(T_frame_bed), result.point_labels, result.point_existence, voxels, frame, result.timings_ms,
                       result.surface_noise)
