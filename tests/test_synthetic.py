"""Synthetic beds: the template matches the cap model, scenes are deterministic and their ground truth agrees."""

import dataclasses

import numpy as np
import open3d as o3d
import pytest
from scipy import ndimage

from capture.virtual import MeshScene
from perception.cap import CAP_HEIGHT_RATIO, CAP_RADIUS_AT_UNIT_SCALE, tilt_deg
from perception.encoding import encode
from perception.synthetic.dataset import BED_SETS, load_preset, scene_seeds
from perception.synthetic.scene import (SceneConfig, SyntheticScene, _sample_surface, build_bed, generate_scene,
                                        visible_from)
from perception.synthetic.template import mushroom_template


def test_template_dome_is_the_cap_ellipsoid_of_a_40mm_cap():
    template = mushroom_template()
    v = template.vertices
    dome = v[v[:, 2] >= 0]
    radial = np.hypot(dome[:, 0], dome[:, 1])
    ellipsoid = (radial / 0.020) ** 2 + (dome[:, 2] / (0.020 * 2 / 3)) ** 2
    np.testing.assert_allclose(ellipsoid, 1.0, atol=1e-9)
    assert np.isclose(2 * radial.max(), 0.040)
    assert np.isclose(dome[:, 2].max(), 0.040 / 3)
    assert CAP_RADIUS_AT_UNIT_SCALE == 0.020 and np.isclose(CAP_HEIGHT_RATIO, 2 / 3)
    cap_vertices = np.unique(template.triangles[template.is_cap])
    stem_only = np.setdiff1d(np.unique(template.triangles[~template.is_cap]), cap_vertices)
    assert v[stem_only, 2].max() < 0 and v[cap_vertices, 2].max() > 0


def test_template_is_closed_and_outward():
    template = mushroom_template()
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(template.vertices),
                                     o3d.utility.Vector3iVector(template.triangles))
    mesh.merge_close_vertices(1e-9)
    mesh.remove_degenerate_triangles()
    assert mesh.is_watertight()
    assert mesh.get_volume() > 0


def test_same_seed_same_scene_and_different_seed_differs():
    a, b, c = generate_scene(7), generate_scene(7), generate_scene(8)
    for name in ("points", "instance", "centers", "rotations", "scales", "existence", "residual"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert len(a.points) != len(c.points) or not np.array_equal(a.points, c.points)


def test_scene_ground_truth_is_consistent():
    config = SceneConfig(mushrooms=(20, 30))
    for seed in range(3):
        scene = generate_scene(seed, config)
        k = len(scene.centers)
        assert 20 <= k <= 30
        assert np.all(scene.instance[scene.is_cap] >= 0) and scene.instance.max() < k
        axes = scene.scales / np.array([1, 1, CAP_HEIGHT_RATIO]) / CAP_RADIUS_AT_UNIT_SCALE
        assert np.all(axes >= 0.5 * 0.8 - 1e-9) and np.all(axes <= 1.5 * 1.2 + 1e-9)
        # tilts about x and y of at most 45 degrees each give an axis at most acos(cos^2 45) = 60 degrees off
        assert np.all(tilt_deg(scene.rotations[:, :, 2]) <= 60.0 + 1e-6)
        np.testing.assert_allclose(scene.rotations @ scene.rotations.transpose(0, 2, 1), np.eye(3)[None] * np.ones((k, 1, 1)),
                                   atol=1e-9)
        assert np.all(np.abs(scene.points[:, :2]) <= 0.25 + 1e-6)
        np.testing.assert_array_equal(np.bincount(scene.instance[scene.is_cap], minlength=k), scene.visible_cap_points)


def dome_points(scene):
    """The scene's points on cap domes: in the bed frame, in their cap's frame, and their cap."""
    cap = (scene.existence > 0) & (scene.orientation > 0.05)
    owner, points = scene.instance[cap], scene.points[cap].astype(np.float64)
    return points, np.einsum("nd,nde->ne", points - scene.centers[owner], scene.rotations[owner]), owner


def test_cap_points_lie_on_their_cap_ellipsoid():
    scene = generate_scene(3)
    _, local, owner = dome_points(scene)
    radius = np.sqrt(np.sum((local / scene.scales[owner]) ** 2, axis=1))
    # local deformations move the surface by about half a millimetre
    assert np.median(np.abs(radius - 1.0)) < 0.05


def test_cap_height_flattens_each_cap_and_its_points_follow():
    low, high = 0.4, 0.6
    scene = generate_scene(3, SceneConfig(cap_height=(low, high)))
    ratio = scene.scales[:, 2] / scene.scales[:, :2].mean(1)
    widest = 1.2 / 0.8  # axis_factor's range, on the height and on each horizontal axis
    assert ratio.min() >= CAP_HEIGHT_RATIO * low / widest and ratio.max() <= CAP_HEIGHT_RATIO * high * widest
    assert np.median(ratio) < CAP_HEIGHT_RATIO * high
    _, local, owner = dome_points(scene)
    assert np.median(np.abs(np.sqrt(np.sum((local / scene.scales[owner]) ** 2, axis=1)) - 1.0)) < 0.05
    with pytest.raises(ValueError, match="cap height"):
        SceneConfig(cap_height=(0.6, 0.4))


def test_more_views_show_the_stems_and_sides_one_overhead_view_hides():
    def shares(views):
        """Of each bed's points: the share on stems, and the cap points' share facing away from the first eye."""
        stems, away = [], []
        for seed in (1, 2, 3):
            scene = generate_scene(seed, SceneConfig(views=views, mushrooms=(25, 25)))
            stems.append(np.mean(scene.instance[~scene.is_cap] >= 0))
            points, local, owner = dome_points(scene)
            normal = np.einsum("nde,ne->nd", scene.rotations[owner], local / scene.scales[owner] ** 2)
            away.append(np.mean(np.einsum("nd,nd->n", normal, scene.viewpoint - points) < 0))
        return np.mean(stems), np.mean(away)

    (stems_one, away_one), (stems_four, away_four) = shares((1, 1)), shares((4, 4))
    assert stems_four > 1.5 * stems_one
    # one view sees the far side of a cap only where the dome is deformed; pooled views see it round
    assert away_one < 0.03 and away_four > 3 * away_one
    with pytest.raises(ValueError, match="hpr or fused"):
        SceneConfig(views=(1, 3), visibility="camera")
    with pytest.raises(ValueError, match="view counts"):
        SceneConfig(views=(0, 2))


def test_a_clustered_mushroom_stands_at_the_drawn_spacing_from_an_earlier_one():
    low, high = 0.85, 0.9
    bed = build_bed(np.random.default_rng(4), SceneConfig(mushrooms=(30, 30), cluster_probability=1.0,
                                                          cluster_spacing=(low, high)))
    assert len(bed.centers) > 10
    for k in range(1, len(bed.centers)):
        distance = np.linalg.norm(bed.centers[:k, :2] - bed.centers[k, :2], axis=1)
        ratio = distance / (bed.scales[:k, :2].mean(1) + bed.scales[k, :2].max())
        assert np.any((ratio >= low - 1e-9) & (ratio <= high + 1e-9)), (k, ratio.min())
    with pytest.raises(ValueError, match="cluster spacing"):
        SceneConfig(cluster_spacing=(1.0, 0.5))


@pytest.mark.parametrize("cap_height,cluster_spacing", [((1.0, 1.0), (0.8, 1.15)), ((0.4, 1.1), (0.55, 1.1))])
def test_no_two_mushrooms_interpenetrate(cap_height, cluster_spacing):
    rng = np.random.default_rng(11)
    bed = build_bed(rng, SceneConfig(mushrooms=(45, 45), cluster_probability=0.8, cap_height=cap_height,
                                     cluster_spacing=cluster_spacing))
    template = mushroom_template()
    axes = bed.scales / np.array([1, 1, CAP_HEIGHT_RATIO]) / CAP_RADIUS_AT_UNIT_SCALE
    caps = template.vertices[np.unique(template.triangles[template.is_cap])]
    caps = caps[caps[:, 2] > 0]
    world = np.einsum("vd,ked->kve", caps * 0.98, bed.rotations * axes[:, None, :]) + bed.centers[:, None]
    for i in range(len(bed.centers)):
        local = np.einsum("kvd,de->kve", world - bed.centers[i], bed.rotations[i]) / bed.scales[i]
        depth = 1.0 - np.sum(local**2, axis=-1)
        inside = (depth > 0.05) & (local[..., 2] > 0)
        inside[i] = False
        assert not inside.any(), f"mushroom {i} is entered by another cap"


def test_zbuffer_visibility_agrees_with_exact_ray_casting():
    rng = np.random.default_rng(5)
    config = SceneConfig()
    bed = build_bed(rng, config)
    points, _, normals = _sample_surface(rng, bed, 3 / config.spacing**2)
    eye, target = np.array([0.03, -0.05, 0.55]), np.zeros(3)
    visible = visible_from(points, normals, eye, target, pixel=0.7 * config.spacing)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(bed.vertices.astype(np.float32)),
                        o3d.core.Tensor(bed.triangles.astype(np.uint32)))
    direction = points - eye
    distance = np.linalg.norm(direction, axis=1)
    rays = np.hstack([np.broadcast_to(eye, points.shape), direction / distance[:, None]]).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    exact = hit >= distance - 0.002
    agreement = np.mean(visible == exact)
    assert agreement > 0.93, agreement
    assert 0.3 < visible.mean() < 0.8


@pytest.mark.parametrize("visibility", ["camera", "katz"])
def test_other_visibility_models_give_labelled_clouds(visibility):
    scene = generate_scene(4, SceneConfig(visibility=visibility, mushrooms=(10, 10)))
    assert scene.visibility == visibility
    assert len(scene.points) > 3000
    assert scene.is_cap.sum() > 100
    assert (scene.visible_cap_points > 0).sum() >= 8


def test_a_fused_bed_is_its_noisy_views_merged_and_labelled_by_the_surface_each_point_shows():
    config = SceneConfig(visibility="fused", views=(3, 3), spacing=0.002, mushrooms=(15, 15))
    scene = generate_scene(5, config)
    bed = build_bed(np.random.default_rng(5), config)
    meshes = MeshScene(bed.vertices, bed.triangles)
    triangle, distance = meshes.nearest_triangles(scene.points)
    # the sensor's range noise is about 1.5 mm a pixel at this range; smoothing and merging views average it down
    assert np.median(distance) < 0.001 and np.percentile(distance, 90) < 0.003
    assert np.array_equal(scene.instance, bed.triangle_instance[triangle])
    assert np.array_equal(scene.is_cap, bed.triangle_is_cap[triangle])
    # one point per merge voxel (the bed's jittered spacing): neighbours about a voxel apart, not the far
    # finer pixels of three views
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scene.points.astype(np.float64)))
    assert 0.7 * scene.spacing < np.median(cloud.compute_nearest_neighbor_distance()) < 1.2 * scene.spacing
    assert (scene.visible_cap_points > 0).sum() >= 14
    # every point of a merged voxel is the mean of what the views saw there: none is a raw noisy pixel
    single = generate_scene(5, SceneConfig(visibility="camera", spacing=0.002, mushrooms=(15, 15)))
    single_distance = meshes.nearest_triangles(single.points)[1]
    assert np.median(distance) < 0.7 * np.median(single_distance)


def test_soil_holes_take_blotches_of_bare_soil_and_leave_the_mushrooms_alone():
    from scipy.spatial import cKDTree

    plain = generate_scene(3, SceneConfig(mushrooms=(15, 15)))
    holed = generate_scene(3, SceneConfig(mushrooms=(15, 15), soil_holes=(0.3, 0.3)))
    soil = plain.instance < 0
    np.testing.assert_array_equal(holed.points[holed.instance >= 0], plain.points[~soil])
    assert abs(1 - (holed.instance < 0).sum() / soil.sum() - 0.3) < 0.01
    # blotches, not thinning: of each lost point's 8 nearest soil neighbours most are lost too (about 30 %
    # would be, were the points dropped at random), and the soil left is as dense as it was
    soil_points = plain.points[soil]
    def rows(points):
        return np.ascontiguousarray(points).view(np.dtype((np.void, points.itemsize * 3))).ravel()

    lost = ~np.isin(rows(soil_points), rows(holed.points[holed.instance < 0]))
    neighbours = cKDTree(soil_points[:, :2]).query(soil_points[lost, :2], 9)[1][:, 1:]
    assert lost[neighbours].mean() > 0.8
    spacing = [np.median(cKDTree(p[:, :2]).query(p[:, :2], 2)[0][:, 1]) for p in (soil_points, soil_points[~lost])]
    assert spacing[1] < 1.05 * spacing[0]
    with pytest.raises(ValueError, match="soil hole"):
        SceneConfig(soil_holes=(0.5, 1.5))


def test_soil_lumps_are_rough_mounds_of_soil_a_few_centimetres_across():
    from perception.synthetic.terrain import SOIL_LUMP_HEIGHT, SOIL_LUMP_ROUGHNESS, Heightfield, add_soil_lumps

    xs = np.linspace(-0.25, 0.25, 126)
    flat = Heightfield(xs, xs.copy(), np.zeros((126, 126)))
    rng = np.random.default_rng(4)
    assert add_soil_lumps(rng, flat, 0) is flat and rng.random() == np.random.default_rng(4).random()
    raised = add_soil_lumps(np.random.default_rng(4), flat, 6).height
    labels, count = ndimage.label(raised > 0.002)
    assert 1 <= count <= 6  # one mound per lump, where two do not run together
    sizes = ndimage.sum_labels(np.ones_like(raised), labels, range(1, count + 1)) * 0.004**2
    assert (2 * np.sqrt(sizes / np.pi) < 0.08).all() and (2 * np.sqrt(sizes / np.pi) > 0.015).any()
    assert SOIL_LUMP_HEIGHT[0] < raised.max() < SOIL_LUMP_HEIGHT[1] * (1 + 3 * SOIL_LUMP_ROUGHNESS)
    # rough, not a smooth dome: a smooth mound's slopes are monotone, which a 3x3 median leaves as they
    # are; crumbs are local bumps and dips that it removes, at most of the lumps' cells
    crumbs = np.abs(raised - ndimage.median_filter(raised, 3))[labels > 0]
    assert np.median(crumbs) > 0.004 * raised.max()
    # a bed's soil mesh carries them: the same soil (drawn first) stands up to a few centimetres higher in
    # up to that many patches; beyond them only the soil's small deformations differ (+-2 mm bumps)
    bare = SceneConfig(mushrooms=(0, 0), distractors=(0, 0))
    plain = build_bed(np.random.default_rng(6), bare).vertices[:, 2]
    lumpy = build_bed(np.random.default_rng(6), dataclasses.replace(bare, soil_lumps=(12, 12))).vertices[:, 2]
    patches, count = ndimage.label((lumpy - plain > 0.004).reshape(126, 126))
    cells = ndimage.sum_labels(np.ones(patches.shape), patches, range(1, count + 1))
    assert 1 <= (cells >= 20).sum() <= 12  # patches 2 cm across or more; crumbs at their edges aside
    assert (lumpy - plain).max() > SOIL_LUMP_HEIGHT[0] and np.quantile(np.abs(lumpy - plain), 0.5) < 0.002
    with pytest.raises(ValueError, match="soil lump"):
        SceneConfig(soil_lumps=(3, 1))


def test_mycelium_mats_cover_their_share_of_the_soil_and_fill_its_crevices():
    from perception.synthetic.terrain import MYCELIUM_FUZZ, MYCELIUM_THICKNESS, Heightfield, add_mycelium

    xs = np.linspace(-0.25, 0.25, 126)
    flat = Heightfield(xs, xs.copy(), np.zeros((126, 126)))
    rng = np.random.default_rng(4)
    assert add_mycelium(rng, flat, 0.0) is flat and rng.random() == np.random.default_rng(4).random()
    mats = add_mycelium(np.random.default_rng(4), flat, 0.3).height
    assert abs(np.mean(mats > 0) - 0.3) < 0.02 and mats.min() >= 0
    assert MYCELIUM_THICKNESS[0] * 0.5 < np.median(mats[mats > 0.0005]) < MYCELIUM_THICKNESS[1]
    assert mats.max() < MYCELIUM_THICKNESS[1] * (1 + 4 * MYCELIUM_FUZZ)
    labels, count = ndimage.label(mats > 0)
    sizes = 2 * np.sqrt(ndimage.sum_labels(np.ones_like(mats), labels, range(1, count + 1)) * 0.004**2 / np.pi)
    assert count >= 3 and sizes.max() > 0.03  # several patches, some a few centimetres across or more
    # crevices 8 mm wide and 6 mm deep in every tenth row: under a mat they are filled
    grooved = np.zeros((126, 126))
    grooved[::10] = -0.006
    covered = add_mycelium(np.random.default_rng(4), Heightfield(xs, xs.copy(), grooved), 0.3).height
    under = (mats > 0.001)[::10]
    assert np.median(covered[::10][under]) > -0.002 and np.median(covered[::10][~(mats[::10] > 0)]) == -0.006
    with pytest.raises(ValueError, match="mycelium"):
        SceneConfig(mycelium=(0.5, 0.2))


def test_soil_banks_rise_on_one_side_of_a_cap_up_its_stem():
    from perception.synthetic.terrain import SOIL_BANK_RISE, SOIL_LUMP_ROUGHNESS, Heightfield, soil_bank_heights

    xs = np.linspace(-0.25, 0.25, 126)
    flat = Heightfield(xs, xs.copy(), np.zeros((126, 126)))
    rng = np.random.default_rng(2)
    assert not soil_bank_heights(rng, flat, np.zeros((0, 2)), np.zeros(0), np.zeros(0)).any()
    assert rng.random() == np.random.default_rng(2).random()  # nothing drawn for no caps
    caps, radius, rise = np.array([[-0.1, -0.1], [0.1, 0.1]]), np.array([0.02, 0.025]), np.array([0.01, 0.015])
    raised = soil_bank_heights(np.random.default_rng(2), flat, caps, radius, rise)
    gx, gy = np.meshgrid(xs, xs)
    distance = [np.hypot(gx - x, gy - y) for x, y in caps]
    near = [d < 3.5 * r for d, r in zip(distance, radius)]
    assert raised[~(near[0] | near[1])].max() < 0.05 * raised.max()  # a bank per cap, nothing elsewhere
    for d, n, r, top in zip(distance, near, radius, rise):
        peak = np.unravel_index(np.argmax(np.where(n, raised, 0)), raised.shape)
        # the crest stands 0.7-1.1 radii from the axis (4 mm cells: 0.56-1.24) and reaches 0.4-0.9 of the
        # centre's height (its Gaussian's top may fall between cells; crumbs add up to 3 x 25 %)
        assert 0.5 * r < d[peak] < 1.3 * r
        assert 0.8 * SOIL_BANK_RISE[0] * top < raised[peak] < SOIL_BANK_RISE[1] * top * (1 + 3 * SOIL_LUMP_ROUGHNESS)
        # on one side only: across the axis from the crest the soil stays low
        mirror = tuple(np.clip(2 * np.array(np.unravel_index(np.argmin(d), d.shape)) - peak, 0, 125))
        assert raised[mirror] < 0.4 * raised[peak]
    # in a bed, banks stand only beside its smaller half of caps, below their centres; the caps stay put
    config = SceneConfig(mushrooms=(12, 12), distractors=(0, 0))
    plain = build_bed(np.random.default_rng(8), config)
    banked = build_bed(np.random.default_rng(8), dataclasses.replace(config, soil_banks=(12, 12)))
    np.testing.assert_array_equal(plain.centers, banked.centers)
    ground = 126 * 126
    rise_of_soil = banked.vertices[:ground, 2] - plain.vertices[:ground, 2]
    assert (rise_of_soil >= 0).all() and (rise_of_soil > 0.002).sum() > 20
    radii = plain.scales[:, :2].max(1)
    small = radii <= np.median(radii)
    raised_xy = plain.vertices[:ground][rise_of_soil > 0.001, :2]
    to_cap = np.hypot(*(raised_xy[:, None] - plain.centers[None, :, :2]).transpose(2, 0, 1)) / radii
    assert (to_cap[:, small].min(1) < 3.5).all()
    below = plain.centers[:, 2] - plain.vertices[:ground][np.argmin(np.hypot(
        *(plain.vertices[:ground, None, :2] - plain.centers[None, :, :2]).transpose(2, 0, 1)), 0), 2]
    assert rise_of_soil.max() < below[small].max() * SOIL_BANK_RISE[1] * (1 + 3 * SOIL_LUMP_ROUGHNESS)
    with pytest.raises(ValueError, match="soil bank"):
        SceneConfig(soil_banks=(3, 1))


def test_encoding_follows_the_definitions():
    centers = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0]])
    rotations = np.stack([np.eye(3), np.eye(3)])
    scales = np.array([[0.02, 0.02, 0.02 * 2 / 3]] * 2)
    points = np.array([[0.0, 0.0, 0.02 * 2 / 3],   # top of cap 0: orientation 1
                       [0.01, 0.0, 0.0],            # base of cap 0: orientation 0, d1/d2 = 0.01/0.04
                       [0.025, 0.0, 0.003],         # between the caps: d1 ~= d2, touching rule
                       [0.3, 0.3, 0.0]])            # soil
    instance = np.array([0, 0, 0, -1])
    is_cap = np.array([True, True, True, False])
    targets = encode(points, instance, is_cap, centers, rotations, scales)
    np.testing.assert_array_equal(targets.existence, [1, 1, 0, 0])
    np.testing.assert_allclose(targets.orientation, [1, 0, 0, 0], atol=1e-7)
    np.testing.assert_allclose(targets.residual[0], [0, 0, -0.02 * 2 / 3], atol=1e-7)
    np.testing.assert_allclose(targets.residual[1], [-0.01, 0, 0], atol=1e-7)
    np.testing.assert_array_equal(targets.residual[2:], 0)


def test_scene_round_trips_through_npz(tmp_path):
    scene = generate_scene(2)
    scene.save(tmp_path / "s.npz")
    loaded = SyntheticScene.load(tmp_path / "s.npz")
    for name in ("points", "instance", "centers", "scales", "orientation"):
        np.testing.assert_array_equal(getattr(scene, name), getattr(loaded, name))
    assert loaded.seed == scene.seed and loaded.terrain == scene.terrain
    with np.load(tmp_path / "s.npz") as raw:
        corners = raw["box_corners"]
    # the top face of each box is s_z above the cap base along the cap axis
    axis = scene.rotations[:, :, 2]
    heights = np.einsum("kvd,kd->kv", corners - scene.centers[:, None], axis)
    np.testing.assert_allclose(heights.max(1), scene.scales[:, 2], atol=1e-9)
    np.testing.assert_allclose(heights.min(1), 0.0, atol=1e-9)


def test_presets_have_fixed_distinct_seeds_and_are_cached(tmp_path, monkeypatch):
    assert scene_seeds(BED_SETS["val50"].seed, 50) == scene_seeds(BED_SETS["val50"].seed, 50)
    assert not set(scene_seeds(BED_SETS["val50"].seed, 50)) & set(scene_seeds(BED_SETS["test50"].seed, 50))
    monkeypatch.setenv("MUSHROOM_POSE_CACHE", str(tmp_path))
    monkeypatch.setitem(BED_SETS, "tiny", BED_SETS["val50"].__class__(seed=3, scenes=3))
    first = load_preset("tiny", progress=False)
    files = sorted(tmp_path.rglob("*.npz"))
    assert len(files) == 3
    stamp = [f.stat().st_mtime_ns for f in files]
    second = load_preset("tiny", progress=False)
    assert [f.stat().st_mtime_ns for f in files] == stamp
    np.testing.assert_array_equal(first[1].points, second[1].points)


def test_a_preset_at_another_spacing_is_the_same_beds_cached_apart(tmp_path, monkeypatch):
    monkeypatch.setenv("MUSHROOM_POSE_CACHE", str(tmp_path))
    monkeypatch.setitem(BED_SETS, "tiny", BED_SETS["val50"].__class__(seed=3, scenes=1))
    default, = load_preset("tiny", progress=False)
    coarse, = load_preset("tiny", progress=False, spacing=0.0051)
    assert len({f.parent for f in tmp_path.rglob("*.npz")}) == 2
    np.testing.assert_array_equal(default.centers, coarse.centers)
    jitter = SceneConfig().jitter
    assert jitter[0] * 0.0051 <= coarse.spacing <= jitter[1] * 0.0051
    assert jitter[0] * SceneConfig().spacing <= default.spacing <= jitter[1] * SceneConfig().spacing
    assert len(default.points) > 2 * len(coarse.points)


def test_voxel_representatives_keep_the_first_point_of_every_voxel():
    from common.geometry import voxel_representatives

    rng = np.random.default_rng(0)
    for count, spread in ((7, 0.01), (5000, 0.5), (3000, 40.0)):
        points = rng.uniform(-spread, spread, (count, 3))
        keys = np.floor(points / 0.005).astype(np.int64)
        _, first = np.unique(keys, axis=0, return_index=True)
        np.testing.assert_array_equal(voxel_representatives(points, 0.005), np.sort(first))


def test_a_corrupt_cached_scene_is_made_again(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MUSHROOM_POSE_CACHE", str(tmp_path / "cache"))
    monkeypatch.setitem(BED_SETS, "tiny", BED_SETS["val50"].__class__(seed=3, scenes=2))
    first = load_preset("tiny", progress=False)
    broken = sorted((tmp_path / "cache").rglob("*.npz"))[1]
    broken.write_bytes(broken.read_bytes()[:100])
    again = load_preset("tiny", progress=False)
    assert "unreadable" in capsys.readouterr().err
    np.testing.assert_array_equal(first[1].points, again[1].points)
    np.testing.assert_array_equal(SyntheticScene.load(broken).points, first[1].points)
    monkeypatch.setenv("MUSHROOM_POSE_CACHE", str(broken))
    with pytest.raises(ValueError, match="cannot write the tiny cache"):
        load_preset("tiny", progress=False)


def test_cap_of_points_names_the_cap_a_point_lies_on():
    """A point on a cap triangle belongs to that triangle's mushroom; a point on soil, on a stem or
    clear of the bed belongs to none."""
    rng = np.random.default_rng(11)
    bed = build_bed(rng, SceneConfig(mushrooms=(12, 12)))
    centroids = bed.vertices[bed.triangles].mean(axis=1)
    cap = np.flatnonzero(bed.triangle_is_cap)
    off_cap = np.flatnonzero(~bed.triangle_is_cap)
    cap, off_cap = rng.choice(cap, 300, replace=False), rng.choice(off_cap, 300, replace=False)
    np.testing.assert_array_equal(bed.cap_of_points(centroids[cap], 0.002), bed.triangle_instance[cap])
    assert (bed.cap_of_points(centroids[off_cap], 0.002) == -1).all()
    above = centroids[cap] + [0.0, 0.0, 0.2]  # 20 cm over the tallest cap
    assert (bed.cap_of_points(above, 0.002) == -1).all()
