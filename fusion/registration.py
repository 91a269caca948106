"""Pose refinement: coarse-to-fine robust point-to-plane ICP between overlapping views, then an
Open3D pose graph over neighbouring and loop-closing pairs, seeded by a prior (turntable, rig or
recorded poses). Refined poses that leave the prior implausibly far are flagged and the prior kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from capture.frames import DepthFrame

reg = o3d.pipelines.registration


@dataclass(frozen=True)
class RegistrationConfig:
    """Defaults suit a bed seen from 0.3-0.5 m by a D405-class camera (about 1-1.5 mm depth noise)."""

    voxels: tuple[float, ...] = (0.008, 0.004)
    """Point spacing per ICP level, coarse to fine (metres): each level is the depth pyramid level
    whose pixels come nearest to this size at the frame's median depth. A third level at 2 mm
    (4x the points) took refinement of 18 views from 0.45 s to 2.5 s for a worst view of 0.02 deg
    instead of 0.06 deg, both far inside the 0.3 deg target."""
    distances: tuple[float, ...] = (0.024, 0.008)
    """Maximum correspondence distance per level: the coarse one must exceed the prior's error."""
    iterations: tuple[int, ...] = (30, 30)
    kernel: str = "tukey"
    """Robust loss of the point-to-plane residuals: "tukey", "huber" or "none"."""
    kernel_scale: float = 0.5
    """Kernel width as a fraction of the level's correspondence distance."""
    neighbours: int = 2
    """Each view is registered with this many views nearest to it under the prior; on a full turn
    that includes the pair closing the loop. More pairs are more robust and proportionally slower."""
    min_fitness: float = 0.3
    """A pair whose ICP inlier fraction is below this does not overlap and gives no edge."""
    edge_prune_threshold: float = 0.25
    preference_loop_closure: float = 1.0
    max_rotation_deg: float = 5.0
    """Refinement that turns a pose further than this from its prior is implausible: keep the prior."""
    max_translation: float = 0.02
    """Likewise for the camera centre (metres)."""
    global_level: int = 1
    """Level (of ``voxels``) whose points and FPFH features (radius 5 points) registration without a
    prior runs on. The two cameras of tests/test_fusion.py, 48 degrees apart, came out right for 1 and
    5 of 8 RANSAC seeds at 8 mm (two noise draws) and for 16 of 16 at 4 mm, where a try (with ICP)
    costs 2.2-2.6 s against 0.45 s."""
    global_attempts: int = 2
    """RANSAC runs (seeds) per pair registered with no prior; the best after ICP is kept."""
    anchor: int = 0
    """The view that stays at its prior and so fixes the world frame (the pose graph's reference node)."""
    depth_max: float = 1.0
    """Depth beyond this (metres) is ignored for registration."""
    depth_jump: float = 0.01
    """A 2x2 pixel block spanning a larger depth step (metres) is an edge: the pyramid drops it."""

    def __post_init__(self) -> None:
        if not (len(self.voxels) == len(self.distances) == len(self.iterations) > 0):
            raise ValueError("voxels, distances and iterations need one entry per ICP level")
        if self.kernel not in ("tukey", "huber", "none"):
            raise ValueError(f"unknown ICP kernel {self.kernel!r}; use tukey, huber or none")


@dataclass(frozen=True)
class View:
    """A frame's points in its camera frame, down-sampled per ICP level, with normals facing the camera."""

    levels: tuple[o3d.geometry.PointCloud, ...]
    frame_id: str


@dataclass(frozen=True)
class PairResult:
    """ICP of view ``source`` onto view ``target``: ``T_target_source`` and its quality."""

    source: int
    target: int
    T_target_source: np.ndarray
    fitness: float
    rmse: float
    information: np.ndarray


@dataclass(frozen=True)
class RefinedPoses:
    """Refined T_world_camera per view; flagged views kept their prior (``reasons`` says why)."""

    poses: np.ndarray
    prior: np.ndarray
    flagged: np.ndarray
    reasons: tuple[str, ...]
    pairs: tuple[PairResult, ...]

    @property
    def changes(self) -> tuple[np.ndarray, np.ndarray]:
        """Rotation (degrees) and camera-centre (metres) change from prior to result per view."""
        return pose_change(self.prior, self.poses)


def frame_id(frame: DepthFrame) -> str:
    """How fused clouds and messages name a frame: ``sensor@timestamp_ns``."""
    return f"{frame.sensor_id}@{frame.timestamp_ns}"


def check_frames(frames: list[DepthFrame]) -> None:
    """ValueError with a one-line reason unless every frame has intrinsics and some depth."""
    if not frames:
        raise ValueError("no frames")
    for k, frame in enumerate(frames):
        if getattr(frame, "intrinsics", None) is None:
            raise ValueError(f"frame {k} ({getattr(frame, 'sensor_id', '?')}) has no intrinsics: "
                             "record the camera calibration with the depth")
        if not np.any(frame.depth):
            raise ValueError(f"frame {k} ({frame.sensor_id}@{frame.timestamp_ns}) has no valid depth")


def prepare_view(frame: DepthFrame, config: RegistrationConfig = RegistrationConfig()) -> View:
    """The ICP pyramid of one frame (done once per frame; streaming does it as frames arrive).

    Levels come from a depth image pyramid (2x2 block means, which also average out depth noise)
    with normals from neighbouring pixels: about 15x faster than voxel down-sampling the
    back-projected cloud and estimating normals from k-d tree neighbourhoods, and as accurate.
    """
    depth = frame.depth_m
    depth[depth > config.depth_max] = 0.0
    seen = depth[depth > 0]
    footprint = float(np.median(seen)) / frame.intrinsics.fx if len(seen) else config.voxels[-1]
    pyramid = [depth]
    levels = []
    for voxel in config.voxels:
        level = max(0, int(round(np.log2(voxel / footprint))))
        while len(pyramid) <= level:
            pyramid.append(_halve_depth(pyramid[-1], config.depth_jump))
        levels.append(_organised_cloud(pyramid[level], _halved_intrinsics(frame.intrinsics.matrix, level),
                                      config.depth_jump))
    return View(tuple(levels), frame_id(frame))


def _halve_depth(depth: np.ndarray, jump: float) -> np.ndarray:
    """Half-resolution depth: the mean of each 2x2 block that is fully valid and spans no edge."""
    rows, cols = depth.shape[0] // 2, depth.shape[1] // 2
    corners = [depth[r:2 * rows:2, c:2 * cols:2].astype(np.float32) for r in (0, 1) for c in (0, 1)]
    low = np.minimum(np.minimum(corners[0], corners[1]), np.minimum(corners[2], corners[3]))
    high = np.maximum(np.maximum(corners[0], corners[1]), np.maximum(corners[2], corners[3]))
    mean = ((corners[0] + corners[1]) + (corners[2] + corners[3])) * np.float32(0.25)
    return np.where((low > 0) & (high - low < jump), mean, np.float32(0.0))


def _halved_intrinsics(matrix: np.ndarray, times: int) -> np.ndarray:
    """The camera matrix of a depth image halved ``times`` times by 2x2 blocks (pixel centres move)."""
    scaled = np.array(matrix, np.float64)
    scaled[:2, :2] /= 2 ** times
    scaled[:2, 2] = (scaled[:2, 2] + 0.5) / 2 ** times - 0.5
    return scaled


def _organised_cloud(depth: np.ndarray, matrix: np.ndarray, jump: float) -> o3d.geometry.PointCloud:
    """Points of a depth image (camera frame) with normals from the central differences of
    neighbouring pixels (one-sided differences bias point-to-plane ICP by ~0.5 mm), facing the camera;
    pixels next to a hole or a depth step above ``jump`` (an occluding edge) are left out."""
    vertices = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(depth))).create_vertex_map(
        o3d.core.Tensor(matrix), 0.0).as_tensor().numpy()
    normals = np.zeros_like(vertices)
    normals[1:-1, 1:-1] = np.cross(vertices[1:-1, 2:] - vertices[1:-1, :-2], vertices[2:, 1:-1] - vertices[:-2, 1:-1])
    centre = depth[1:-1, 1:-1]
    keep = np.zeros(depth.shape, bool)
    keep[1:-1, 1:-1] = centre > 0
    for neighbour in (depth[1:-1, 2:], depth[1:-1, :-2], depth[2:, 1:-1], depth[:-2, 1:-1]):
        keep[1:-1, 1:-1] &= (neighbour > 0) & (np.abs(neighbour - centre) < jump)
    points, normals = vertices[keep].astype(np.float64), normals[keep].astype(np.float64)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    normals *= -np.sign(np.einsum("ij,ij->i", normals, points))[:, None]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.normals = o3d.utility.Vector3dVector(normals)
    return cloud


def _estimation(config: RegistrationConfig, distance: float) -> reg.TransformationEstimation:
    scale = config.kernel_scale * distance
    if config.kernel == "tukey":
        return reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=scale))
    if config.kernel == "huber":
        return reg.TransformationEstimationPointToPlane(reg.HuberLoss(k=scale))
    return reg.TransformationEstimationPointToPlane()


def register_pair(source: View, target: View, T_target_source: np.ndarray,
                  config: RegistrationConfig = RegistrationConfig(), indices: tuple[int, int] = (0, 0)) -> PairResult:
    """Coarse-to-fine robust point-to-plane ICP from an initial ``T_target_source``; ``indices`` are the
    (source, target) view numbers the result carries for the pose graph."""
    T = np.asarray(T_target_source, np.float64)
    result = None
    for level, (distance, iterations) in enumerate(zip(config.distances, config.iterations)):
        result = reg.registration_icp(source.levels[level], target.levels[level], distance, T,
                                      _estimation(config, distance),
                                      reg.ICPConvergenceCriteria(1e-6, 1e-6, iterations))
        T = result.transformation
    information = reg.get_information_matrix_from_point_clouds(source.levels[-1], target.levels[-1],
                                                               config.distances[-1], T)
    return PairResult(indices[0], indices[1], np.array(T), float(result.fitness), float(result.inlier_rmse),
                      information)


def fpfh(view: View, config: RegistrationConfig = RegistrationConfig()) -> reg.Feature:
    """FPFH features of a view's ``config.global_level`` (radius 5 points), for global registration."""
    param = o3d.geometry.KDTreeSearchParamHybrid(radius=5 * config.voxels[config.global_level], max_nn=100)
    return reg.compute_fpfh_feature(view.levels[config.global_level], param)


def register_global(source: View, target: View, config: RegistrationConfig = RegistrationConfig(), seed: int = 0,
                    features: tuple[reg.Feature, reg.Feature] | None = None) -> np.ndarray:
    """``T_target_source`` with no prior at all: FPFH features + RANSAC on ``config.global_level`` (the
    classic baseline, and the seed of chained registration when nothing else is known)."""
    src, tgt = source.levels[config.global_level], target.levels[config.global_level]
    if len(src.points) < 10 or len(tgt.points) < 10:
        raise ValueError(f"views {source.frame_id} and {target.frame_id} have too few points to register")
    features = features or (fpfh(source, config), fpfh(target, config))
    distance = 1.5 * config.voxels[config.global_level]
    o3d.utility.random.seed(seed)
    result = reg.registration_ransac_based_on_feature_matching(
        src, tgt, features[0], features[1], True, distance, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(distance)],
        reg.RANSACConvergenceCriteria(100000, 0.999))
    return np.array(result.transformation)


def register_unknown(source: View, target: View, config: RegistrationConfig = RegistrationConfig(), seed: int = 0,
                     features: tuple[reg.Feature, reg.Feature] | None = None,
                     indices: tuple[int, int] = (0, 0)) -> PairResult:
    """ICP of ``source`` onto ``target`` with no prior: ``register_global`` from
    ``config.global_attempts`` RANSAC seeds (``seed`` onwards), each refined by ``register_pair``,
    keeping the best ICP fitness.

    Most of a bed is flat soil, and one RANSAC run can settle on a turn about the soil's normal that
    fits the soil well. On the two cameras of tests/test_fusion.py (48 degrees apart) at 8 mm, 3 seeds
    of 6 gave turns of 77-134 degrees (ICP fitness 0.44-0.48), the other 3 the true pose (0.87).
    RANSAC's own inlier fraction did not tell them apart; ICP's does.
    """
    features = features or (fpfh(source, config), fpfh(target, config))
    results = [register_pair(source, target, register_global(source, target, config, seed + attempt, features),
                             config, indices) for attempt in range(config.global_attempts)]
    return max(results, key=lambda result: result.fitness)


def pose_change(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation angle (degrees) and translation distance (metres) between poses (..., 4, 4)."""
    relative = np.einsum("...ji,...jk->...ik", a[..., :3, :3], b[..., :3, :3])
    cos = np.clip((np.trace(relative, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    return np.degrees(np.arccos(cos)), np.linalg.norm(a[..., :3, 3] - b[..., :3, 3], axis=-1)


def candidate_pairs(prior: np.ndarray, neighbours: int, depth: float = 0.4) -> list[tuple[int, int]]:
    """Pairs (i < j) of each view with its nearest views under the prior, plus every consecutive pair.

    Nearness = centre distance + ``depth`` x angle between optical axes, roughly how far the looked-at
    surface moves between the two views.
    """
    n = len(prior)
    centres, axes = prior[:, :3, 3], prior[:, :3, 2]
    angle = np.arccos(np.clip(axes @ axes.T, -1.0, 1.0))
    cost = np.linalg.norm(centres[:, None] - centres[None], axis=2) + depth * angle
    np.fill_diagonal(cost, np.inf)
    nearest = np.argsort(cost, axis=1)[:, :min(neighbours, n - 1)]
    pairs = {(min(i, j), max(i, j)) for i in range(n) for j in nearest[i]}
    pairs |= {(i, i + 1) for i in range(n - 1)}
    return sorted(pairs)


def _check_poses(poses: np.ndarray, what: str) -> np.ndarray:
    poses = np.asarray(poses, np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"{what} must be N x 4 x 4 poses, got shape {poses.shape}")
    bad = np.flatnonzero(~np.isfinite(poses).all((1, 2)))
    if len(bad):
        raise ValueError(f"{what}: pose of view {int(bad[0])} is not finite (NaN or inf); "
                         "drop the frame or give its pose")
    return poses


def refine_poses(views: list[View], prior: np.ndarray, config: RegistrationConfig = RegistrationConfig(),
                 pairs: dict[tuple[int, int], PairResult] | None = None) -> RefinedPoses:
    """Refined T_world_camera of every view from the prior T_world_camera (N, 4, 4).

    ``pairs`` holds ICP results already computed (the streaming ``Fuser`` registers each new frame
    with its predecessor on arrival); missing candidate pairs are registered here. Raises ValueError
    when no two views overlap; a view overlapping no other is flagged and keeps its prior.
    """
    prior = _check_poses(prior, "the prior")
    n = len(views)
    if n != len(prior):
        raise ValueError(f"{n} views but {len(prior)} prior poses")
    if n == 1:
        return RefinedPoses(prior.copy(), prior, np.zeros(1, bool), ("",), ())
    anchor = config.anchor % n
    done = dict(pairs or {})
    results = []
    for i, j in candidate_pairs(prior, config.neighbours):
        if (i, j) not in done:
            done[(i, j)] = register_pair(views[j], views[i], np.linalg.inv(prior[i]) @ prior[j], config, (j, i))
        results.append(done[(i, j)])
    accepted = [r for r in results if r.fitness >= config.min_fitness]
    if not accepted:
        best = max(r.fitness for r in results)
        raise ValueError(f"no two of the {n} views overlap (best ICP fitness {best:.2f} < {config.min_fitness}); "
                         "check the poses, or fuse without refinement")
    graph = reg.PoseGraph()
    for pose in prior:
        graph.nodes.append(reg.PoseGraphNode(pose))
    for r in accepted:
        graph.edges.append(reg.PoseGraphEdge(r.source, r.target, r.T_target_source, r.information,
                                             uncertain=abs(r.source - r.target) != 1))
    option = reg.GlobalOptimizationOption(max_correspondence_distance=config.distances[-1],
                                          edge_prune_threshold=config.edge_prune_threshold,
                                          preference_loop_closure=config.preference_loop_closure,
                                          reference_node=anchor)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                reg.GlobalOptimizationConvergenceCriteria(), option)
    poses = np.stack([np.asarray(node.pose) for node in graph.nodes])
    poses = prior[anchor] @ np.linalg.inv(poses[anchor]) @ poses
    connected = np.zeros(n, bool)
    for r in accepted:
        connected[[r.source, r.target]] = True
    rotation, translation = pose_change(prior, poses)
    reasons = []
    for k in range(n):
        if not connected[k]:
            reasons.append("overlaps no other view")
        elif rotation[k] > config.max_rotation_deg or translation[k] > config.max_translation:
            reasons.append(f"refinement moved it {rotation[k]:.1f} deg, {1000 * translation[k]:.0f} mm from the prior")
        else:
            reasons.append("")
    flagged = np.array([bool(r) for r in reasons])
    poses[flagged] = prior[flagged]
    return RefinedPoses(poses, prior, flagged, tuple(reasons), tuple(results))


def chain_poses(views: list[View], config: RegistrationConfig = RegistrationConfig(),
                seeds: np.ndarray | None = None) -> tuple[np.ndarray, dict[tuple[int, int], PairResult]]:
    """T_first_camera of every view by registering consecutive views (odometry), and those pairs.

    Each step starts from ``seeds[k]`` (T_k_(k+1), e.g. from rough recorded poses) when given,
    otherwise from FPFH + RANSAC; ICP then refines it. Raises ValueError when two consecutive views
    do not overlap, since the chain breaks there.
    """
    poses, pairs = [np.eye(4)], {}
    features = [fpfh(view, config) for view in views] if seeds is None else None
    for k in range(len(views) - 1):
        if seeds is not None:
            result = register_pair(views[k + 1], views[k], seeds[k], config, (k + 1, k))
        else:
            result = register_unknown(views[k + 1], views[k], config, config.global_attempts * k,
                                      (features[k + 1], features[k]), (k + 1, k))
        if result.fitness < config.min_fitness:
            raise ValueError(f"views {k} and {k + 1} ({views[k].frame_id}, {views[k + 1].frame_id}) do not overlap "
                             f"(ICP fitness {result.fitness:.2f}); record the turn with smaller steps")
        poses.append(poses[-1] @ result.T_target_source)
        pairs[(k, k + 1)] = result
    return np.stack(poses), pairs
