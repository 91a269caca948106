"""Synthetic mushroom beds with full ground truth (paper Sec. 2), deterministic from a seed.

A bed is casing soil, a few distractors and K mushrooms (the template scaled, deformed, tilted and
stood on the soil without collisions), turned into a point cloud by one of its visibility models:
hidden point removal from a near-overhead viewpoint (the paper's), the virtual depth camera, or that camera
from several viewpoints with its frames merged as a scan is.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

import numpy as np
import open3d as o3d
from scipy import ndimage

from capture.frames import CameraIntrinsics, backproject
from capture.virtual import MeshScene, SensorModel, apply_sensor_model, to_depth_frame
from common.geometry import look_at, transform_points, voxel_representatives
from fusion.integrate import IntegrationConfig, merge_points
from perception.cap import CAP_HEIGHT_RATIO, CAP_RADIUS_AT_UNIT_SCALE, cap_box, cap_rotation
from perception.encoding import EncodingTargets, encode
from perception.synthetic.template import RIM_RATIO, STEM_LENGTH_RATIO, STEM_RADIUS_RATIO, mushroom_template
from perception.synthetic.terrain import (TERRAINS, Distractor, add_mycelium, add_soil_lumps,
                                          deform_along_normals, deform_heightfield_mesh, heightfield_mesh,
                                          random_distractor, soil_bank_heights, soil_heightfield)

VISIBILITY_MODELS = ("hpr", "camera", "fused", "katz")
"""hpr: hidden point removal by z-buffer (fast); camera: the virtual depth camera; fused: the virtual
depth camera from each of the bed's views, merged as a scan is (``fusion.integrate.merge_points``);
katz: the paper's spherical-flip operator (Open3D), slow, kept for reproducing the paper exactly."""
GENERATOR_VERSION = 3
"""Bumped whenever the same seed would give a different scene or the saved fields change (invalidates
cached presets)."""


@dataclass(frozen=True)
class SceneConfig:
    """Paper defaults (Sec. 2); ranges are inclusive (low, high)."""

    bed_size: float = 0.5
    mushrooms: tuple[int, int] = (5, 45)
    scale: tuple[float, float] = (0.5, 1.5)
    axis_factor: tuple[float, float] = (0.8, 1.2)
    cap_height: tuple[float, float] = (1.0, 1.0)
    """Factor on each mushroom's vertical scale (cap, rim and stem alike), on top of ``axis_factor``. The
    template's dome is 2/3 as high as wide; the labelled real caps of ../shared/real/ are shallower
    (sphere fits of the non-partial caps: visible height over rim radius 0.46 median, 0.33-0.70 from
    the 10th to the 90th percentile), so real-like beds draw it below 1. The pose fit's height-ratio gate
    (``perception.pose.HEIGHT_RATIO_RANGE``) is the template's."""
    max_tilt_deg: float = 45.0
    cluster_probability: float = 0.35
    """Chance that a mushroom is placed right beside an existing one: real beds grow in touching
    clusters (docs/DESIGN.md section 6b), which uniform placement alone rarely produces."""
    cluster_spacing: tuple[float, float] = (0.8, 1.15)
    """Distance between the centres of a clustered mushroom and its neighbour, as a factor on the sum
    of their radii, drawn from [low, high]. Below 1 the caps overlap in top view, so one stands
    partly under the other's rim where they do not collide."""
    distractors: tuple[int, int] = (0, 6)
    terrain: str | None = None
    """One of TERRAINS, or None for a random one per scene."""
    spacing: float = 0.003
    """Point spacing (metres): the down-sampling cell of the visibility step, jittered by ``jitter``.
    Finer than the network's 4.1-4.5 mm voxel, so that every voxel the surface crosses holds a point,
    as in a depth camera's or a fused cloud (docs/DESIGN.md section 6b: 1.2 mm spacing). At 5.1 mm a cap is
    a gappy shell of voxels (``perception.detect.predict``)."""
    jitter: tuple[float, float] = (0.8, 1.2)
    oversample: float = 3.0
    """Surface samples per voxel of area before down-sampling, jittered by ``jitter``."""
    visibility: str = "hpr"
    view_height: tuple[float, float] = (0.45, 0.75)
    view_off_nadir_deg: float = 25.0
    views: tuple[int, int] = (1, 1)
    """How many viewpoints a bed is seen from, drawn per bed from [low, high]; their visible points are
    pooled, as in a cloud fused from several camera poses (stems, rims and cap sides that one overhead
    view hides). The views after the first look in from 15-40 degrees off nadir, spread around the bed;
    the scene's ``viewpoint`` is the first. Only with ``hpr`` and ``fused`` visibility."""
    soil_holes: tuple[float, float] = (0.0, 0.0)
    """Share of the bare soil's points lost in blotches a few centimetres across, drawn per bed from [low,
    high]: dark casing soil returns no depth in patches, so a real scan's soil is full of holes, and caps
    stand beside islands of soil. 0 0 draws nothing, so such beds stay as they were."""
    soil_lumps: tuple[int, int] = (0, 0)
    """How many casing-soil lumps a bed has, drawn from [low, high]: rough bare-soil mounds 2-6 cm
    across (``terrain.add_soil_lumps``), as a real bed's casing shows and as tall as a small cap. They
    are soil, so a detector learns that a mound alone is not a cap. 0 0 draws nothing."""
    soil_banks: tuple[int, int] = (0, 0)
    """How many of a bed's smaller caps (radius up to the bed's median) stand in casing soil banked
    against one side, drawn from [low, high]: a rough crest up the stem to below the dome
    (``terrain.soil_bank_heights``), so that soil and cap meet in one slope, as young caps stand on a
    real bed. 0 0 draws nothing."""
    mycelium: tuple[float, float] = (0.0, 0.0)
    """Share of the soil under white mycelium mats, drawn per bed from [low, high]: a fuzzy layer a few
    millimetres thick in soft-edged patches (``terrain.add_mycelium``), as a bed shows before and
    between flushes. 0 0 draws nothing."""
    ground_cell: float = 0.004
    bed_tilt_deg: float = 0.0
    """The whole bed (soil, caps and camera) tilted by up to this many degrees about a random horizontal
    axis, as a bed on an uneven shelf or a rig not square to it is seen; 0 draws no tilt."""
    sensor: SensorModel = field(default_factory=SensorModel)

    def __post_init__(self) -> None:
        low, high = self.mushrooms
        if low < 0 or high < low:
            raise ValueError(f"mushroom count range must satisfy 0 <= low <= high, got {low}..{high}")
        if self.visibility not in VISIBILITY_MODELS:
            raise ValueError(f"unknown visibility model {self.visibility!r}; choose one of {VISIBILITY_MODELS}")
        if self.terrain is not None and self.terrain not in TERRAINS:
            raise ValueError(f"unknown terrain {self.terrain!r}; choose one of {TERRAINS}")
        if not 0 < self.cluster_spacing[0] <= self.cluster_spacing[1]:
            raise ValueError(f"cluster spacing factors must satisfy 0 < low <= high, got {self.cluster_spacing}")
        if not 0 < self.cap_height[0] <= self.cap_height[1]:
            raise ValueError(f"cap height factors must satisfy 0 < low <= high, got {self.cap_height}")
        if any(int(count) != count for count in self.views) or not 1 <= self.views[0] <= self.views[1]:
            raise ValueError(f"view counts must satisfy 1 <= low <= high, got {self.views}")
        if self.views[1] > 1 and self.visibility not in ("hpr", "fused"):
            raise ValueError(f"more than one view needs hpr or fused visibility, not {self.visibility!r}")
        if not 0 <= self.soil_holes[0] <= self.soil_holes[1] <= 1:
            raise ValueError(f"soil hole shares must satisfy 0 <= low <= high <= 1, got {self.soil_holes}")
        if not 0 <= self.mycelium[0] <= self.mycelium[1] <= 1:
            raise ValueError(f"mycelium shares must satisfy 0 <= low <= high <= 1, got {self.mycelium}")
        if any(int(count) != count for count in self.soil_lumps) or not 0 <= self.soil_lumps[0] <= self.soil_lumps[1]:
            raise ValueError(f"soil lump counts must satisfy 0 <= low <= high, got {self.soil_lumps}")
        if any(int(count) != count for count in self.soil_banks) or not 0 <= self.soil_banks[0] <= self.soil_banks[1]:
            raise ValueError(f"soil bank counts must satisfy 0 <= low <= high, got {self.soil_banks}")
        if self.spacing <= 0 or self.bed_size <= 0:
            raise ValueError("spacing and bed size must be positive")


@dataclass(frozen=True)
class BedMeshes:
    """Everything in the bed as one triangle soup with per-triangle labels, plus the true poses."""

    vertices: np.ndarray
    triangles: np.ndarray
    triangle_instance: np.ndarray
    """(T,) mushroom index, -1 for soil and distractors."""
    triangle_is_cap: np.ndarray
    centers: np.ndarray
    rotations: np.ndarray
    scales: np.ndarray
    """(K, 3) true cap semi-axes (s_x, s_y, s_z) in metres."""
    terrain: str

    def cap_of_points(self, points: np.ndarray, within: float) -> np.ndarray:
        """Each point's mushroom (N,) when it lies within ``within`` metres of that mushroom's cap
        surface, -1 otherwise: which points of a cloud made from this bed show a cap."""
        triangle, distance = MeshScene(self.vertices, self.triangles).nearest_triangles(points)
        on_cap = (distance <= within) & self.triangle_is_cap[triangle]
        return np.where(on_cap, self.triangle_instance[triangle], -1)


@dataclass(frozen=True)
class SyntheticScene:
    """A point cloud in the bed frame (z up, metres) with its ground truth and encoding targets."""

    points: np.ndarray
    is_cap: np.ndarray
    instance: np.ndarray
    centers: np.ndarray
    rotations: np.ndarray
    scales: np.ndarray
    existence: np.ndarray
    residual: np.ndarray
    orientation: np.ndarray
    visible_cap_points: np.ndarray
    viewpoint: np.ndarray
    seed: int
    terrain: str
    visibility: str
    spacing: float
    """This bed's point spacing in metres (``SceneConfig.spacing`` times its jitter)."""

    @property
    def targets(self) -> EncodingTargets:
        return EncodingTargets(self.existence, self.residual, self.orientation)

    @property
    def radii(self) -> np.ndarray:
        """True cap radius s of each mushroom: the mean of its two horizontal semi-axes."""
        return self.scales[:, :2].mean(1)

    @property
    def box_corners(self) -> np.ndarray:
        """(K, 8, 3) corners of each cap's oriented box (``perception.cap.cap_box``), bed frame."""
        return np.array([cap_box(c, r, s).vertices() for c, r, s in zip(self.centers, self.rotations, self.scales)]
                        ).reshape(-1, 8, 3)

    def save(self, path) -> None:
        """Compressed .npz; ``box_corners`` is stored too, for readers outside this project."""
        np.savez_compressed(path, **asdict(self), box_corners=self.box_corners, generator_version=GENERATOR_VERSION)

    @staticmethod
    def load(path) -> "SyntheticScene":
        with np.load(path) as data:
            values = {f.name: data[f.name] for f in fields(SyntheticScene)}
        for name, kind in (("seed", int), ("terrain", str), ("visibility", str), ("spacing", float)):
            values[name] = kind(values[name])
        return SyntheticScene(**values)


def _inside_template(local: np.ndarray) -> np.ndarray:
    """Whether points in the unit-scale cap frame are inside the template's solid (cap or stem)."""
    radius = CAP_RADIUS_AT_UNIT_SCALE
    height = radius * CAP_HEIGHT_RATIO
    rim = RIM_RATIO * radius
    r2 = local[..., 0] ** 2 + local[..., 1] ** 2
    in_cap = (r2 / radius**2 + (local[..., 2] / height) ** 2 <= 1.0) & (local[..., 2] >= -rim)
    stem_r = 1.08 * STEM_RADIUS_RATIO * radius
    in_stem = (r2 <= stem_r**2) & (local[..., 2] <= 0) & (local[..., 2] >= -STEM_LENGTH_RATIO * radius)
    return in_cap | in_stem


BOUNDING_RADIUS = CAP_RADIUS_AT_UNIT_SCALE * np.hypot(1.0, STEM_LENGTH_RATIO)
"""Radius of a sphere about the cap centre that holds the whole unit-scale template."""


class _Placer:
    """Rejection sampling of mushroom poses: no two solids may intersect, none may enter a distractor.

    Proposals are drawn in vectorised batches; only the acceptance test runs one by one, because
    each accepted mushroom changes what the next one may collide with.
    """

    def __init__(self, rng: np.random.Generator, config: SceneConfig, field, distractors: list[Distractor],
                 count: int):
        self.rng, self.config, self.field, self.count = rng, config, field, count
        template = mushroom_template()
        self.hull, self.foot = template.hull_samples, template.foot
        self.placed = 0
        self.centers = np.zeros((count, 3))
        self.rotations = np.zeros((count, 3, 3))
        self.axes = np.zeros((count, 3))
        self.samples = np.zeros((count, len(self.hull), 3))
        self.obstacle_centres = np.array([d.center for d in distractors]).reshape(-1, 3)
        self.obstacle_radii = np.array([d.radius for d in distractors])

    def _proposals(self, n: int) -> dict[str, np.ndarray]:
        rng, config = self.rng, self.config
        tilt = np.radians(config.max_tilt_deg)
        axes = rng.uniform(*config.scale, (n, 1)) * rng.uniform(*config.axis_factor, (n, 3))
        if config.cap_height != (1.0, 1.0):  # drawn only when asked, so other configs keep their beds
            axes[:, 2] *= rng.uniform(*config.cap_height, n)
        rotations = cap_rotation(rng.uniform(-tilt, tilt, n), rng.uniform(-tilt, tilt, n),
                                 rng.uniform(-np.pi, np.pi, n))
        radius = CAP_RADIUS_AT_UNIT_SCALE * axes[:, :2].max(1)
        half = (config.bed_size / 2 - radius)[:, None]
        return {"axes": axes, "rotations": rotations, "radius": radius,
                "xy": rng.uniform(-1, 1, (n, 2)) * half,
                "cluster": rng.random(n) < config.cluster_probability,
                "neighbour": rng.random(n), "spacing": rng.uniform(*config.cluster_spacing, n),
                "direction": rng.uniform(0, 2 * np.pi, n),
                "foot": np.einsum("nij,nj->ni", rotations, self.foot * axes),
                "sink": -self.foot[2] * axes[:, 2] * rng.uniform(0.2, 0.7, n)}

    def _collides(self, center: np.ndarray, rotation: np.ndarray, axes: np.ndarray, samples: np.ndarray) -> bool:
        half = self.config.bed_size / 2
        if np.abs(center[:2]).max() > half - CAP_RADIUS_AT_UNIT_SCALE * axes[:2].min():
            return True
        if len(self.obstacle_radii):
            d2 = np.sum((samples[:, None] - self.obstacle_centres) ** 2, axis=-1)
            if (d2 < self.obstacle_radii**2).any():
                return True
        n = self.placed
        reach = BOUNDING_RADIUS * (self.axes[:n].max(1) + axes.max())
        near = np.flatnonzero(np.sum((self.centers[:n] - center) ** 2, axis=1) < reach**2)
        if len(near) == 0:
            return False
        new_in_old = ((samples[None] - self.centers[near, None]) @ self.rotations[near]) / self.axes[near, None]
        if _inside_template(new_in_old).any():
            return True
        old_in_new = ((self.samples[near] - center) @ rotation) / axes
        return bool(_inside_template(old_in_new).any())

    def place(self) -> None:
        """Place up to ``count`` mushrooms, giving up after 40 proposals per mushroom."""
        batch = max(8, 2 * self.count)
        for start in range(0, 40 * self.count, batch):
            p = self._proposals(batch)
            ground_below = self.field.sample(p["xy"][:, 0] + p["foot"][:, 0], p["xy"][:, 1] + p["foot"][:, 1])
            for i in range(batch):
                if self.placed == self.count:
                    return
                axes, rotation = p["axes"][i], p["rotations"][i]
                xy, foot, ground = p["xy"][i], p["foot"][i], ground_below[i]
                if self.placed and p["cluster"][i]:
                    j = int(p["neighbour"][i] * self.placed)
                    spacing = (CAP_RADIUS_AT_UNIT_SCALE * self.axes[j, :2].mean() + p["radius"][i]) * p["spacing"][i]
                    xy = self.centers[j, :2] + spacing * np.array([np.cos(p["direction"][i]), np.sin(p["direction"][i])])
                    ground = float(self.field.sample(xy[0] + foot[0], xy[1] + foot[1]))
                center = np.array([xy[0], xy[1], ground - p["sink"][i] - foot[2]])
                samples = (self.hull * axes) @ rotation.T + center
                if not self._collides(center, rotation, axes, samples):
                    k = self.placed
                    self.centers[k], self.rotations[k], self.axes[k], self.samples[k] = center, rotation, axes, samples
                    self.placed += 1


def _banks_against_small_caps(rng: np.random.Generator, config: SceneConfig, field, centers: np.ndarray,
                              axes: np.ndarray) -> np.ndarray:
    """The soil's rise (the field's grid) where banks stand against some of the bed's smaller caps."""
    radius = CAP_RADIUS_AT_UNIT_SCALE * axes[:, :2].max(1)
    small = np.flatnonzero(radius <= np.median(radius))
    count = min(int(rng.integers(config.soil_banks[0], config.soil_banks[1] + 1)), len(small))
    chosen = rng.choice(small, count, replace=False)
    rise = centers[chosen, 2] - field.sample(centers[chosen, 0], centers[chosen, 1])
    return soil_bank_heights(rng, field, centers[chosen, :2], radius[chosen], rise)


def build_bed(rng: np.random.Generator, config: SceneConfig) -> BedMeshes:
    """Soil, distractors and mushrooms as meshes, with each mushroom's true pose."""
    terrain = config.terrain or TERRAINS[int(rng.integers(len(TERRAINS)))]
    field = soil_heightfield(rng, config.bed_size, config.ground_cell, terrain)
    if config.soil_lumps[1] > 0:  # drawn only when asked, so other configs keep their beds
        field = add_soil_lumps(rng, field, int(rng.integers(config.soil_lumps[0], config.soil_lumps[1] + 1)))
    if config.mycelium[1] > 0:  # drawn only when asked, so other configs keep their beds
        field = add_mycelium(rng, field, float(rng.uniform(*config.mycelium)))
    ground_vertices, ground_triangles = heightfield_mesh(field)
    ground_vertices = deform_heightfield_mesh(rng, field, ground_vertices, count=24, magnitude=0.002,
                                              radius=(0.004, 0.015))
    distractors = [random_distractor(rng, field, margin=0.03)
                   for _ in range(int(rng.integers(config.distractors[0], config.distractors[1] + 1)))]
    placer = _Placer(rng, config, field, distractors, int(rng.integers(config.mushrooms[0], config.mushrooms[1] + 1)))
    placer.place()
    k = placer.placed
    template = mushroom_template()
    centers, rotations, axes = placer.centers[:k], placer.rotations[:k], placer.axes[:k]
    if config.soil_banks[1] > 0 and k:  # drawn only when asked, so other configs keep their beds
        ground_vertices[:, 2] += _banks_against_small_caps(rng, config, field, centers, axes).ravel()
    local = deform_along_normals(rng, np.broadcast_to(template.vertices, (k,) + template.vertices.shape),
                                 template.normals, count=4, magnitude=0.0005, radius=(0.003, 0.008))
    mushroom_vertices = (local * axes[:, None]) @ rotations.transpose(0, 2, 1) + centers[:, None]

    parts_v = [ground_vertices] + [d.vertices for d in distractors] + list(mushroom_vertices)
    parts_t = [ground_triangles] + [d.triangles for d in distractors] + [template.triangles] * k
    offsets = np.cumsum([0] + [len(v) for v in parts_v[:-1]])
    triangles = np.concatenate([t + o for t, o in zip(parts_t, offsets)])
    background = len(triangles) - k * len(template.triangles)
    instance = np.concatenate([np.full(background, -1), np.repeat(np.arange(k), len(template.triangles))])
    is_cap = np.concatenate([np.zeros(background, bool), np.tile(template.is_cap, k)])
    scales = axes * np.array([1.0, 1.0, CAP_HEIGHT_RATIO]) * CAP_RADIUS_AT_UNIT_SCALE
    return BedMeshes(np.concatenate(parts_v), triangles, instance.astype(np.int32), is_cap,
                     centers, rotations, scales, terrain)


def _sample_surface(rng: np.random.Generator, bed: BedMeshes, density: float,
                    eye: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """About ``density`` area-uniform surface points per square metre, their triangles and unit normals.

    Each triangle gets its expected count rounded up or down at random (no search over a cumulative
    distribution), and the points are shuffled so that no triangle order biases later choices. With
    an ``eye``, triangles facing away from it get no samples: nobody could see them.
    """
    vertices = bed.vertices.astype(np.float32)
    a, b, c = (np.take(vertices, bed.triangles[:, i], axis=0) for i in range(3))
    cross = np.cross(b - a, c - a)
    double_area = np.sqrt(np.einsum("ij,ij->i", cross, cross))
    if eye is not None:
        double_area *= np.einsum("ij,ij->i", cross, eye.astype(np.float32) - a) > 0
    expected = double_area * np.float32(density / 2)
    counts = (expected + rng.random(len(expected), dtype=np.float32)).astype(np.int64)
    chosen = rng.permutation(np.repeat(np.arange(len(counts)), counts))
    count = len(chosen)
    u, v = rng.random(count, dtype=np.float32), rng.random(count, dtype=np.float32)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    a = np.take(a, chosen, axis=0)
    points = a + u[:, None] * (np.take(b, chosen, axis=0) - a) + v[:, None] * (np.take(c, chosen, axis=0) - a)
    normals = np.take(cross, chosen, axis=0) / np.maximum(np.take(double_area, chosen), 1e-30)[:, None]
    return points.astype(np.float64), chosen, normals


def _viewpoint(rng: np.random.Generator, config: SceneConfig) -> tuple[np.ndarray, np.ndarray]:
    target = np.append(rng.uniform(-0.08, 0.08, 2), 0.0)
    off_nadir = np.radians(rng.uniform(0, config.view_off_nadir_deg))
    azimuth = rng.uniform(0, 2 * np.pi)
    height = rng.uniform(*config.view_height)
    eye = target + height * np.array([np.sin(off_nadir) * np.cos(azimuth),
                                      np.sin(off_nadir) * np.sin(azimuth), np.cos(off_nadir)])
    return eye, target


EXTRA_VIEW_OFF_NADIR_DEG = (15.0, 40.0)
"""How far from straight down the views after a bed's first look in, in degrees: a scan walks round the bed."""


def _extra_viewpoints(rng: np.random.Generator, config: SceneConfig, target: np.ndarray) -> list[np.ndarray]:
    """The eyes of a bed's views after the first, spread around it (none for a single-view config)."""
    if config.views[1] == 1:
        return []  # draws nothing, so single-view beds stay as they were
    count = int(rng.integers(config.views[0], config.views[1] + 1)) - 1
    azimuth = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(count) / max(count, 1) + rng.uniform(-0.3, 0.3, count)
    off_nadir = np.radians(rng.uniform(*EXTRA_VIEW_OFF_NADIR_DEG, count))
    height = rng.uniform(*config.view_height, count)
    offset = np.stack([np.sin(off_nadir) * np.cos(azimuth), np.sin(off_nadir) * np.sin(azimuth), np.cos(off_nadir)], 1)
    return list(target + height[:, None] * offset)


def visible_from(points: np.ndarray, normals: np.ndarray, eye: np.ndarray, target: np.ndarray,
                 pixel: float) -> np.ndarray:
    """Hidden point removal with a point z-buffer: which dense surface samples the eye sees.

    Back-facing samples are hidden; the rest are splatted into a perspective depth buffer whose
    pixels span about ``pixel`` metres on the bed, and a sample is visible when it is no deeper
    than its pixel's nearest sample plus the depth its own slope spans across one pixel. With
    pixels of 0.7 voxel and 3 samples per voxel of area this agrees with exact ray casting on
    about 95 % of the samples (tests/test_synthetic.py measures it), at a fraction of the cost.
    """
    rotation = look_at(eye, target)[:3, :3]
    local = (points - eye) @ rotation
    facing_dot = -np.einsum("ij,ij->i", normals @ rotation, local)
    facing = facing_dot > 0
    depth = local[:, 2]
    angle = pixel / np.median(depth)
    iu = np.floor(local[:, 0] / depth / angle).astype(np.int64)
    iv = np.floor(local[:, 1] / depth / angle).astype(np.int64)
    iu -= iu.min() - 1
    iv -= iv.min() - 1
    zbuffer = np.full((iv.max() + 2, iu.max() + 2), np.inf)
    np.minimum.at(zbuffer, (iv[facing], iu[facing]), depth[facing])
    cos = np.abs(facing_dot) / np.sqrt(np.einsum("ij,ij->i", local, local))
    slope = np.sqrt(1.0 - np.minimum(cos, 1.0) ** 2) / np.maximum(cos, 0.2)
    tolerance = 0.001 + angle * depth * slope
    return facing & (depth <= zbuffer[iv, iu] + tolerance)


def _visible_points(rng, bed: BedMeshes, config: SceneConfig, spacing: float, eye, target, extra_eyes=()):
    """Visible points at the scene's density and the triangle each came from: seen from ``eye`` and,
    pooled with them, from each of ``extra_eyes`` (hpr and fused only)."""
    if config.visibility == "fused":
        meshes = MeshScene(bed.vertices, bed.triangles)
        points = _fused_points(rng, meshes, config, spacing, [eye, *extra_eyes], target)
        triangle = meshes.nearest_triangles(points)[0]
    elif config.visibility == "camera":
        intrinsics = CameraIntrinsics.realsense_d405()
        T_world_camera = look_at(eye, target)
        render = MeshScene(bed.vertices, bed.triangles).render(intrinsics, T_world_camera)
        depth = apply_sensor_model(render, config.sensor, rng)
        points, pixel = backproject(depth, intrinsics)
        points = transform_points(T_world_camera, points.astype(np.float64))
        triangle = render.triangle_ids.reshape(-1)[pixel]
        hit = triangle >= 0
        points, triangle = points[hit], triangle[hit]
    else:
        density = config.oversample * rng.uniform(*config.jitter) / spacing**2
        cull_for = eye if config.visibility == "hpr" and not len(extra_eyes) else None
        points, triangle, normals = _sample_surface(rng, bed, density, cull_for)
        if config.visibility == "hpr":
            visible = visible_from(points, normals, eye, target, pixel=0.7 * spacing)
            for other in extra_eyes:
                visible |= visible_from(points, normals, other, target, pixel=0.7 * spacing)
            points, triangle = points[visible], triangle[visible]
        else:
            keep = voxel_representatives(points, spacing)
            points, triangle = points[keep], triangle[keep]
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
            diameter = float(np.linalg.norm(points.max(0) - points.min(0)))
            _, visible = cloud.hidden_point_removal(eye, diameter * 100.0)
            visible = np.sort(np.asarray(visible))
            points, triangle = points[visible], triangle[visible]
    if config.visibility != "katz":
        keep = voxel_representatives(points, spacing)
        points, triangle = points[keep], triangle[keep]
    inside = (np.abs(points[:, :2]) <= config.bed_size / 2).all(1)
    return points[inside], triangle[inside]


def _fused_points(rng, meshes: MeshScene, config: SceneConfig, spacing: float, eyes, target) -> np.ndarray:
    """The points a scan of the bed's ``meshes`` gives: the virtual camera's noisy depth image from each
    eye, smoothed, back-projected and merged into voxels of ``spacing`` as fusion merges frames. The
    poses are exact: fusion registers views to well under the sensor's noise."""
    intrinsics = CameraIntrinsics.realsense_d405()
    poses = np.array([look_at(eye, target) for eye in eyes])
    frames = [to_depth_frame(apply_sensor_model(meshes.render(intrinsics, pose), config.sensor, rng), intrinsics,
                             config.sensor, pose) for pose in poses]
    return merge_points(frames, poses, IntegrationConfig(voxel=spacing)).points.astype(np.float64)


SOIL_HOLE_CELL = 0.008
"""Cell of the random field whose high values are a bed's soil holes, metres; smoothed over
``SOIL_HOLE_SMOOTHING`` cells, its blotches are 2-5 cm across, as the holes in the real cloud's soil."""
SOIL_HOLE_SMOOTHING = 1.5


def _outside_soil_holes(rng, config: SceneConfig, points: np.ndarray, soil: np.ndarray) -> np.ndarray:
    """Which points stay: all but the soil's points under the blotches of a smooth random field, a
    share drawn from ``config.soil_holes`` of the soil's points."""
    if config.soil_holes[1] == 0 or not soil.any():
        return np.ones(len(points), bool)
    share = rng.uniform(*config.soil_holes)
    cells = int(np.ceil(config.bed_size / SOIL_HOLE_CELL)) + 2
    field = ndimage.gaussian_filter(rng.standard_normal((cells, cells)), SOIL_HOLE_SMOOTHING)
    where = (points[:, :2].T + config.bed_size / 2) / SOIL_HOLE_CELL
    value = ndimage.map_coordinates(field, where, order=1, mode="nearest")
    return ~soil | (value <= np.quantile(value[soil], 1.0 - share))


def generate_scene(seed: int, config: SceneConfig = SceneConfig()) -> SyntheticScene:
    """One synthetic bed; the same seed and config give the same scene on any machine."""
    rng = np.random.default_rng(seed)
    bed = build_bed(rng, config)
    spacing = config.spacing * rng.uniform(*config.jitter)
    eye, target = _viewpoint(rng, config)
    points, triangle = _visible_points(rng, bed, config, spacing, eye, target, _extra_viewpoints(rng, config, target))
    keep = _outside_soil_holes(rng, config, points, bed.triangle_instance[triangle] < 0)
    points, triangle = points[keep], triangle[keep]
    instance = bed.triangle_instance[triangle]
    is_cap = bed.triangle_is_cap[triangle]
    centers, rotations = bed.centers, bed.rotations
    if config.bed_tilt_deg > 0:  # drawn only when asked, so other configs keep their beds
        tilt = _bed_tilt(rng, config.bed_tilt_deg)
        points, centers, eye = points @ tilt.T, centers @ tilt.T, tilt @ eye
        rotations = tilt @ rotations
    targets = encode(points, instance, is_cap, centers, rotations, bed.scales)
    k = len(bed.centers)
    visible = np.bincount(instance[is_cap], minlength=k)[:k] if k else np.zeros(0, np.int64)
    return SyntheticScene(points.astype(np.float32), is_cap, instance, centers, rotations, bed.scales,
                          targets.existence, targets.residual, targets.orientation, visible, eye, int(seed),
                          bed.terrain, config.visibility, float(spacing))


def _bed_tilt(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    """A rotation by half to all of ``max_deg`` about a random horizontal axis."""
    heading = rng.uniform(0, 2 * np.pi)
    axis = np.array([np.cos(heading), np.sin(heading), 0.0])
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(axis * np.radians(rng.uniform(0.5, 1.0) * max_deg)).as_matrix()
