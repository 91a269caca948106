"""The paper's baselines beside our pipeline (its Tables 1 and 4, section 4.2).

- Template matching: features of the bed's points matched to features of a cap template, RANSAC over
  a similarity transform (rotation, translation, uniform scale) by Open3D; the consensus cap is a
  detection, its points leave the bed, and the search repeats until no consensus is left. Features:
  FPFH (Open3D; the paper's pre-trained FCGF weights cannot be had here), our network's last feature
  layer, or those plus the network's 5 encoding outputs.
- ICP refinement: the cap template, placed at each of our caps' pose and size, registered onto that
  cap's points by Open3D's point-to-point ICP with scaling.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import open3d.pipelines.registration as reg

from perception.cap import CAP_HEIGHT_RATIO, Caps

TEMPLATE_RADIUS = 0.02
"""Metres: the template cap's s, the synthetic beds' unscaled cap (40 mm across)."""
FEATURES = ("fpfh", "network", "network+encoding")


@dataclass(frozen=True)
class TemplateMatching:
    """How the RANSAC baseline searches a bed for caps."""

    features: str = "fpfh"
    """fpfh, network (its last feature layer) or network+encoding (plus the 5 encoding outputs)."""
    distance: float = 0.0045
    """Metres: a template point within this of a bed point is an inlier (1.5 x the beds' spacing)."""
    min_fitness: float = 0.3
    """A consensus must cover this share of the template's points to count as a cap."""
    scale_range: tuple[float, float] = (0.4, 1.8)
    """Consensus scales (of the template's size) outside this range are no cap."""
    max_caps: int = 80
    misses: int = 3
    """Consecutive searches without a cap that end the search."""
    iterations: int = 100000
    confidence: float = 0.999
    seed: int = 0

    def __post_init__(self) -> None:
        if self.features not in FEATURES:
            raise ValueError(f"unknown features {self.features!r}; use one of {', '.join(FEATURES)}")


def template_points(spacing: float = 0.003) -> tuple[np.ndarray, np.ndarray]:
    """Points about ``spacing`` apart on the template cap's dome (the upper half of the (s, s, 2s/3)
    ellipsoid, s = TEMPLATE_RADIUS, centre at the origin, axis +z) and their outward unit normals."""
    s, s_z = TEMPLATE_RADIUS, CAP_HEIGHT_RATIO * TEMPLATE_RADIUS
    count = max(16, int(round(2 * np.pi * s * s / spacing ** 2)))
    k = np.arange(count) + 0.5
    z = k / count  # a Fibonacci lattice on the unit upper hemisphere: equal areas per point
    ring = np.sqrt(1.0 - z * z)
    angle = np.pi * (1.0 + 5 ** 0.5) * k
    unit = np.stack([ring * np.cos(angle), ring * np.sin(angle), z], 1)
    points = unit * [s, s, s_z]
    normals = unit / [s, s, s_z]
    return points, normals / np.linalg.norm(normals, axis=1, keepdims=True)


def similarity(center: np.ndarray, rotation: np.ndarray, scale: float) -> np.ndarray:
    """The 4x4 transform x -> scale R x + c."""
    transform = np.eye(4)
    transform[:3, :3] = scale * np.asarray(rotation)
    transform[:3, 3] = center
    return transform


def cap_of_transform(transform: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(centre, rotation, s) of the template moved by a similarity ``transform``."""
    transform = np.nan_to_num(np.asarray(transform, np.float64))  # a failed registration: no cap, no warning
    scale = float(np.cbrt(abs(np.linalg.det(transform[:3, :3]))))
    if scale <= 1e-12:
        return transform[:3, 3].copy(), np.eye(3), 0.0
    return transform[:3, 3].copy(), transform[:3, :3] / scale, scale * TEMPLATE_RADIUS


def caps_of(centers: list, rotations: list, radii: list, scores: list) -> Caps:
    """Caps given by centre, rotation and s (semi-axes s, s, 2s/3)."""
    radii = np.asarray(radii, np.float64).reshape(-1)
    return Caps(np.asarray(centers, np.float64).reshape(-1, 3), np.asarray(rotations, np.float64).reshape(-1, 3, 3),
                     np.stack([radii, radii, CAP_HEIGHT_RATIO * radii], 1), np.asarray(scores, np.float64))


def _cloud(points: np.ndarray, normals: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    return cloud


def fpfh_features(points: np.ndarray, normals: np.ndarray | None, spacing: float) -> np.ndarray:
    """(33, N) FPFH features (Open3D) over 5 spacings; normals are estimated, facing up, when not given."""
    cloud = _cloud(points, normals)
    if normals is None:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * spacing, max_nn=30))
        cloud.orient_normals_to_align_with_direction(np.array([0.0, 0.0, 1.0]))
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=5 * spacing, max_nn=100)
    return np.asarray(reg.compute_fpfh_feature(cloud, search).data)


def network_features(model, points: np.ndarray, with_encoding: bool, zoom: float | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Voxel centroids (V, 3, metres) of a cloud and their (D, V) features from the network's last
    feature layer, with the 5 encoding outputs appended when ``with_encoding``."""
    import torch

    from perception.detect import network_input
    from perception.model import inference_model
    from perception.network import voxel_features
    from perception.sparse import SparseTensor

    zoom = model.inference_zoom if zoom is None else zoom
    coords, _, zoomed = network_input(zoom * np.asarray(points, np.float64), model.config.voxel)
    net = inference_model(model)
    with torch.no_grad():
        inputs = torch.from_numpy(voxel_features(model.config, zoomed))
        features = net.features(SparseTensor(inputs, torch.from_numpy(coords)))
        columns = [features]
        if with_encoding:
            out = net.head(features)
            columns.append(torch.cat([torch.sigmoid(out[:, :1]), out[:, 1:4], out[:, 4:5].clamp(0, 1)], 1))
        data = torch.cat(columns, 1).double().numpy()
    return zoomed / zoom, np.ascontiguousarray(data.T)


def _features(points: np.ndarray, normals: np.ndarray | None, config: TemplateMatching, model, spacing: float
              ) -> tuple[np.ndarray, np.ndarray]:
    if config.features == "fpfh":
        return np.asarray(points, np.float64), fpfh_features(points, normals, spacing)
    if model is None:
        raise ValueError(f"{config.features} features need a model")
    return network_features(model, points, config.features == "network+encoding")


def _dome_members(points: np.ndarray, center: np.ndarray, rotation: np.ndarray, radius: float,
                  margin: float = 1.25) -> np.ndarray:
    """Points inside the cap's dome grown by ``margin`` (and a little below its base)."""
    local = (points - center) @ rotation / [radius, radius, CAP_HEIGHT_RATIO * radius]
    return (np.einsum("ij,ij->i", local, local) <= margin ** 2) & (local[:, 2] >= -0.5)


def _fit_scale(template: o3d.geometry.PointCloud, points: np.ndarray, rigid: np.ndarray, distance: float
               ) -> np.ndarray:
    """The rigid consensus made a similarity: ICP with scaling (Open3D) of the template onto the
    points around it. Open3D's RANSAC cannot estimate the scale itself: its final least-squares step
    over every feature match shrinks the template to a point, which then fits perfectly."""
    near = np.linalg.norm(points - rigid[:3, 3], axis=1) < 2.5 * TEMPLATE_RADIUS
    if near.sum() < 3:
        return rigid
    return np.asarray(reg.registration_icp(template, _cloud(points[near]), distance, rigid,
                                           reg.TransformationEstimationPointToPoint(True),
                                           reg.ICPConvergenceCriteria(1e-6, 1e-6, 30)).transformation)


def match_templates(points: np.ndarray, config: TemplateMatching = TemplateMatching(), model=None,
                    spacing: float = 0.003) -> Caps:
    """Caps found by repeated RANSAC template matching (module docstring) in a bed-frame cloud."""
    template, template_normals = template_points(spacing)
    template_at, template_features = _features(template, template_normals, config, model, spacing)
    bed_at, bed_features = _features(points, None, config, model, spacing)
    source, source_features = _cloud(template_at), reg.Feature()
    source_features.data = template_features
    checkers = [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(config.distance)]
    criteria = reg.RANSACConvergenceCriteria(config.iterations, config.confidence)
    remaining = np.ones(len(bed_at), bool)
    found: tuple[list, list, list, list] = ([], [], [], [])
    misses = 0
    o3d.utility.random.seed(config.seed)
    while len(found[0]) < config.max_caps and misses < config.misses and remaining.sum() >= len(template_at) // 4:
        index = np.flatnonzero(remaining)
        target_features = reg.Feature()
        target_features.data = np.ascontiguousarray(bed_features[:, index])
        result = reg.registration_ransac_based_on_feature_matching(
            source, _cloud(bed_at[index]), source_features, target_features, False, config.distance,
            reg.TransformationEstimationPointToPoint(False), 3, checkers, criteria)
        inliers = index[np.asarray(result.correspondence_set, np.int64).reshape(-1, 2)[:, 1]]
        center, rotation, radius = cap_of_transform(_fit_scale(source, bed_at[index], np.asarray(result.transformation),
                                                               config.distance))
        plausible = (result.fitness >= config.min_fitness and rotation[2, 2] > 0
                     and config.scale_range[0] <= radius / TEMPLATE_RADIUS <= config.scale_range[1])
        remaining[inliers] = False  # a rejected consensus still leaves: the next search is a new one
        if not plausible:
            misses += 1
            continue
        misses = 0
        remaining[index[_dome_members(bed_at[index], center, rotation, radius)]] = False
        for store, value in zip(found, (center, rotation, radius, result.fitness)):
            store.append(value)
    return caps_of(*found)


def refine_by_icp(fit, cap_points: list[np.ndarray], distance: float = 0.005, iterations: int = 30,
                  spacing: float = 0.003) -> Caps:
    """Our caps  after Open3D point-to-point ICP with scaling of the template, started
    at each cap's pose and size, onto the cap's own points (``cap_points[k]``)."""
    template = _cloud(template_points(spacing)[0])
    criteria = reg.ICPConvergenceCriteria(1e-6, 1e-6, iterations)
    found: tuple[list, list, list, list] = ([], [], [], [])
    for k, points in enumerate(cap_points):
        start = similarity(fit.centers[k], fit.rotations[k], fit.scales[k, 0] / TEMPLATE_RADIUS)
        transform = start
        if len(points) >= 3:
            transform = np.asarray(reg.registration_icp(template, _cloud(points), distance, start,
                                                        reg.TransformationEstimationPointToPoint(True),
                                                        criteria).transformation)
        for store, value in zip(found, (*cap_of_transform(transform), fit.scores[k])):
            store.append(value)
    return caps_of(*found)
