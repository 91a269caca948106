"""Pose from the encoding: exact on ideal caps, vectorised over instances."""

import numpy as np
import pytest

from perception import pose
from perception.cap import CAP_HEIGHT_RATIO, cap_rotation, rotation_from_axis
from perception.pose import fit_caps


def axis_to_angles(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(theta_x, theta_y) of R = R_y R_x whose third column is the unit ``axis`` (..., 3)."""
    axis = np.asarray(axis, dtype=np.float64)
    theta_x = -np.arcsin(np.clip(axis[..., 1], -1.0, 1.0))
    theta_y = np.arctan2(axis[..., 0], axis[..., 2])
    return theta_x, theta_y


def ideal_cap(center, theta_x, theta_y, spin, s, s_z, n=400, seed=0):
    """Points on the upper half of the cap ellipsoid with their exact encodings."""
    rng = np.random.default_rng(seed)
    azimuth = rng.uniform(0, 2 * np.pi, n)
    elevation = rng.uniform(0.05, np.pi / 2, n)
    local = np.stack([s * np.cos(elevation) * np.cos(azimuth), s * np.cos(elevation) * np.sin(azimuth),
                      s_z * np.sin(elevation)], 1)
    rotation = cap_rotation(theta_x, theta_y, spin)
    points = local @ rotation.T + center
    orientation = local[:, 2] / s_z
    return points, np.tile(center, (n, 1)), orientation, rotation


def test_axis_angles_round_trip():
    for theta_x, theta_y in [(0.3, -0.5), (-0.7, 0.2), (0.0, 0.0)]:
        axis = cap_rotation(theta_x, theta_y)[:, 2]
        np.testing.assert_allclose(axis_to_angles(axis), (theta_x, theta_y), atol=1e-12)
        np.testing.assert_allclose(rotation_from_axis(axis), cap_rotation(theta_x, theta_y), atol=1e-12)


def test_rotation_from_axis_is_the_spin_free_rotation_of_its_angles():
    axes = np.random.default_rng(3).normal(size=(500, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    np.testing.assert_allclose(rotation_from_axis(axes), cap_rotation(*axis_to_angles(axes)), rtol=0, atol=1e-12)
    # near +-y the angles (an arcsin near 1) lose digits; R_y R_x is still pinned down: a rotation whose
    # third column is the axis, first column in the xz-plane, and R[1, 1] = cos(theta_x) >= 0
    near_y = np.array([[1e-7, 1.0, 0.0], [0.0, -1.0, 1e-6], [-1e-5, 1.0, 1e-5], [0, 1, 0], [0, -1, 0], [0, 0, -1]])
    axes = np.concatenate([axes, near_y / np.linalg.norm(near_y, axis=1, keepdims=True)])
    rotations = rotation_from_axis(axes)
    np.testing.assert_allclose(rotations[:, :, 2], axes, rtol=0, atol=1e-15)
    np.testing.assert_allclose(rotations.transpose(0, 2, 1) @ rotations, np.broadcast_to(np.eye(3), rotations.shape),
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, rtol=0, atol=1e-12)
    assert np.all(rotations[:, 1, 0] == 0) and np.all(rotations[:, 1, 1] >= 0)


@pytest.mark.parametrize("height", ["free", "fixed"])
def test_ideal_caps_are_recovered_exactly_all_at_once(height):
    caps = [((0.0, 0.0, 0.01), 0.4, -0.3, 1.0, 0.02), ((0.1, 0.05, 0.0), -0.6, 0.1, 2.0, 0.012),
            ((-0.08, 0.1, 0.02), 0.0, 0.7, 0.3, 0.028)]
    parts = [ideal_cap(np.array(c), tx, ty, sp, s, CAP_HEIGHT_RATIO * s, seed=i)
             for i, (c, tx, ty, sp, s) in enumerate(caps)]
    points = np.concatenate([p[0] for p in parts])
    centers = np.concatenate([p[1] for p in parts])
    orientation = np.concatenate([p[2] for p in parts])
    labels = np.repeat([2, 0, 1], 400)
    noise_points = np.array([[0.2, 0.2, 0.0]])
    fit = fit_caps(np.vstack([points, noise_points]), np.vstack([centers, noise_points]),
                   np.append(orientation, 0.5), np.ones(len(points) + 1), np.append(labels, -1), height)
    assert len(fit.centers) == 3
    for label, (c, tx, ty, _, s) in zip([2, 0, 1], caps):
        true_axis = cap_rotation(tx, ty)[:, 2]
        np.testing.assert_allclose(fit.centers[label], c, atol=1e-10)
        np.testing.assert_allclose(fit.rotations[label][:, 2], true_axis, atol=1e-9)
        np.testing.assert_allclose(fit.scales[label], [s, s, CAP_HEIGHT_RATIO * s], rtol=1e-9)
    np.testing.assert_array_equal(fit.members, [400, 400, 400])


def test_free_height_fits_flatter_and_taller_caps_the_fixed_ratio_cannot():
    s = 0.02
    for ratio in (0.5, 0.9):
        points, centers, orientation, _ = ideal_cap(np.zeros(3), 0.2, 0.3, 0.0, s, ratio * s)
        labels = np.zeros(len(points), np.int64)
        free = fit_caps(points, centers, orientation, np.ones(len(points)), labels, "free")
        fixed = fit_caps(points, centers, orientation, np.ones(len(points)), labels, "fixed")
        np.testing.assert_allclose(free.scales[0], [s, s, ratio * s], rtol=1e-9)
        assert abs(fixed.scales[0, 0] - s) > 0.02 * s


def test_no_instances_gives_empty_fit():
    fit = fit_caps(np.zeros((5, 3)), np.zeros((5, 3)), np.zeros(5), np.zeros(5), np.full(5, -1))
    assert fit.centers.shape == (0, 3) and fit.rotations.shape == (0, 3, 3)


def test_an_error_in_the_predicted_centre_leaves_the_axis_and_is_removed_along_it():
    """Orientation values are affine in the offset from any wrong centre; the intercept measures it."""
    for tilt_x, tilt_y in [(0.6, -0.4), (-0.2, 0.7)]:
        points, centers, orientation, rotation = ideal_cap(np.zeros(3), tilt_x, tilt_y, 0.5, 0.015, 0.01)
        centre_error = 0.003 * rotation[:, 2] + 0.002 * rotation[:, 0]
        labels = np.zeros(len(points), np.int64)
        fit = fit_caps(points, centers + centre_error, orientation, np.ones(len(points)), labels)
        # the surface fit starts 2 mm off sideways and converges to within 1e-4 degrees
        np.testing.assert_allclose(fit.rotations[0][:, 2], rotation[:, 2], atol=1e-6)
        exact = fit_caps(points, centers + centre_error, orientation, np.ones(len(points)), labels,
                         axis="encoding")
        np.testing.assert_allclose(exact.rotations[0][:, 2], rotation[:, 2], atol=1e-9)
        np.testing.assert_allclose(fit.centers[0], 0.002 * rotation[:, 0], atol=1e-9)
        np.testing.assert_allclose(fit.scales[0], [0.015, 0.015, 0.01], rtol=0.1)
        without_intercept = np.linalg.lstsq(points - centre_error, orientation, rcond=None)[0]
        bias = np.degrees(np.arccos(without_intercept @ rotation[:, 2] / np.linalg.norm(without_intercept)))
        assert bias > 1.0


def oval_caps(count=6, encoding_tilt_deg=10.0, seed=0, position_noise=3e-4):
    """Tilted caps with unequal base semi-axes (as on the synthetic beds), their upward-facing side only,
    ``position_noise`` metres of noise. The orientation values are those of an axis ``encoding_tilt_deg``
    off the true one, plus noise: the network's errors are of that kind, smooth over a cap, so that a
    least squares over its points does not average them away."""
    rng = np.random.default_rng(seed)
    parts, truth = [], []
    for label in range(count):
        s = rng.uniform(0.012, 0.025)
        semi = s * np.array([rng.uniform(0.8, 1.2), rng.uniform(0.8, 1.2), CAP_HEIGHT_RATIO * rng.uniform(0.8, 1.2)])
        rotation = cap_rotation(rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), rng.uniform(0, 2 * np.pi))
        center = np.array([0.1 * label, 0.0, 0.0])
        direction = rng.normal(size=(600, 3))
        local = semi * direction / np.linalg.norm(direction, axis=1, keepdims=True)
        facing_up = (rotation @ (local / semi**2).T)[2] > 0
        local = local[(local[:, 2] > 0) & facing_up][:150]
        points = local @ rotation.T + center + rng.normal(0, position_noise, local.shape)
        wrong_axis = rotation @ cap_rotation(np.radians(encoding_tilt_deg), 0.0)[:, 2]
        orientation = (points - center) @ wrong_axis / semi[2] + rng.normal(0, 0.05, len(local))
        parts.append((points, orientation, np.full(len(points), label)))
        truth.append(rotation[:, 2])
    points, orientation, labels = (np.concatenate(x) for x in zip(*parts))
    centers = np.array([0.1, 0.0, 0.0]) * labels[:, None]
    return points, centers, orientation, labels, np.array(truth)


def axis_errors_deg(fit, truth):
    return np.degrees(np.arccos(np.clip(np.abs(np.einsum("ki,ki->k", fit.rotations[:, :, 2], truth)), 0, 1)))


def test_the_surface_fit_brings_back_most_of_the_axis_the_encoding_has_wrong():
    """Not every cap: a noisy, half-seen oval dome can mislead the fit too, as on val50's tail."""
    points, centers, orientation, labels, truth = oval_caps(count=24)
    args = (points, centers + 0.001, orientation, np.ones(len(points)), labels)
    surface, encoding = axis_errors_deg(fit_caps(*args), truth), axis_errors_deg(fit_caps(*args, axis="encoding"), truth)
    assert np.all(encoding > 7.0)
    assert np.median(surface) < 0.5 * np.median(encoding)
    assert np.mean(surface) < 0.7 * np.mean(encoding)


def test_a_noisy_surface_yields_the_axis_to_the_encoding(monkeypatch):
    """1 mm of noise on the caps' points, an encoding 3 degrees off: the surface would pull the axes
    further off than the encoding has them, and the noise-raised encoding weight holds them back."""
    points, centers, orientation, labels, truth = oval_caps(count=24, encoding_tilt_deg=3.0, position_noise=1e-3)
    args = (points, centers + 0.001, orientation, np.ones(len(points)), labels)
    raised = axis_errors_deg(fit_caps(*args), truth)
    monkeypatch.setattr(pose, "SURFACE_NOISE_REFERENCE", np.inf)
    fixed = axis_errors_deg(fit_caps(*args), truth)
    encoding = axis_errors_deg(fit_caps(*args, axis="encoding"), truth)
    assert np.mean(fixed) > 1.5 * np.mean(encoding)
    assert np.mean(raised) < 0.75 * np.mean(fixed)


def test_the_encoding_weight_is_fixed_up_to_the_reference_noise_then_proportional():
    reference, fixed = pose.SURFACE_NOISE_REFERENCE, pose.SURFACE_ENCODING_WEIGHT
    assert pose.encoding_weight(0.0) == pose.encoding_weight(reference) == fixed
    assert pose.encoding_weight(3 * reference) == pytest.approx(3 * fixed)


def test_the_median_distance_counts_only_the_points_of_fits_that_stand():
    """Padded slots (``real`` 0), clusters whose fit is dropped and non-finite distances stay out."""
    distance = np.array([[1.0, 2.0, 9.0, 9.0], [3.0, 4.0, 5.0, np.nan], [7.0, 7.0, 7.0, 7.0]])
    real = np.array([[1, 1, 0, 0], [1, 1, 1, 1], [1, 1, 1, 1]], float)
    keep = np.array([True, True, False])
    assert pose._median_distance(distance, real, keep) == 3.0  # the median of 1, 2, 3, 4, 5
    assert pose._median_distance(distance, real, np.zeros(3, bool)) == 0.0


def test_a_clean_surface_keeps_the_fixed_encoding_weight(monkeypatch):
    """Below ``SURFACE_NOISE_REFERENCE`` the weight is the fixed one: the same axes to the last bit."""
    points, centers, orientation, labels, _ = oval_caps(count=12, encoding_tilt_deg=1.0, position_noise=1e-4)
    args = (points, centers, orientation, np.ones(len(points)), labels)
    measured, weight_of = [], pose.encoding_weight
    monkeypatch.setattr(pose, "encoding_weight", lambda noise: measured.append(noise) or weight_of(noise))
    default = fit_caps(*args).rotations
    assert len(measured) == 1 and 0 < measured[0] < pose.SURFACE_NOISE_REFERENCE
    monkeypatch.setattr(pose, "SURFACE_NOISE_REFERENCE", np.inf)
    np.testing.assert_array_equal(fit_caps(*args).rotations, default)
    monkeypatch.setattr(pose, "SURFACE_NOISE_REFERENCE", 1e-5)
    assert not np.array_equal(fit_caps(*args).rotations, default)


def test_a_cluster_too_small_for_the_surface_fit_keeps_the_encoding_axis():
    points, centers, orientation, labels, _ = oval_caps(count=1)
    few = slice(0, 7)
    args = (points[few], centers[few], orientation[few], np.ones(7), labels[few])
    np.testing.assert_array_equal(fit_caps(*args).rotations, fit_caps(*args, axis="encoding").rotations)


def test_an_unknown_axis_mode_is_refused():
    with pytest.raises(ValueError, match="axis mode"):
        fit_caps(np.zeros((3, 3)), np.zeros((3, 3)), np.zeros(3), np.ones(3), np.zeros(3, np.int64), axis="magic")


def test_the_fit_does_not_depend_on_how_the_clusters_interleave():
    """The fit sorts points by cluster, keeping each cluster's own order (the surface fit's subset is
    taken along it): interleaving the clusters and noise points at random changes nothing."""
    points, centers, orientation, labels, _ = oval_caps(count=8)
    rng = np.random.default_rng(5)
    noise = rng.uniform(-0.1, 0.1, (40, 3))
    existence = rng.uniform(0.5, 1.0, len(points))
    stacked = [np.concatenate(x) for x in ((points, noise), (centers, noise), (orientation, np.zeros(40)),
                                          (existence, np.zeros(40)), (labels, np.full(40, -1)))]
    labels = stacked[4]
    # a random arrangement of the labels, filled by each cluster's points in their own order
    arrangement = rng.permutation(labels)
    order = np.empty(len(labels), np.int64)
    order[np.argsort(arrangement, kind="stable")] = np.argsort(labels, kind="stable")
    assert np.any(np.diff(labels[order]) < 0)
    fit, interleaved = fit_caps(*stacked), fit_caps(*(x[order] for x in stacked))
    for field in ("centers", "rotations", "scales", "scores", "members"):
        np.testing.assert_allclose(getattr(interleaved, field), getattr(fit, field), rtol=1e-9, atol=1e-12)


def small_caps_with_soil_beside(count=12, soil_offset=0.003):
    """Caps 11 mm across 30 points, position noise 0.1 mm, an encoding 8 degrees off, each with three
    voxels of soil at its downhill rim ``soil_offset`` out from the base: a cluster's typical strays."""
    rng = np.random.default_rng(3)
    parts, truth = [], []
    for label in range(count):
        s, center = 0.011, np.array([0.1 * label, 0.0, 0.0])
        rotation = cap_rotation(*rng.uniform(-0.6, 0.6, 2))
        points = ideal_cap(center, 0.0, 0.0, 0.0, s, CAP_HEIGHT_RATIO * s, n=30, seed=label)[0] - center
        points = points @ rotation.T + center + rng.normal(0, 1e-4, points.shape)
        downhill = np.arctan2(*(rotation.T @ [0.0, 0.0, -1.0])[1::-1]) + np.array([-0.3, 0.0, 0.3])
        soil = np.stack([(s + soil_offset) * np.cos(downhill), (s + soil_offset) * np.sin(downhill),
                         np.full(3, 0.001)], 1) @ rotation.T + center
        wrong_axis = rotation @ cap_rotation(np.radians(8.0), 0.0)[:, 2]
        orientation = np.append((points - center) @ wrong_axis / (CAP_HEIGHT_RATIO * s), [0.2] * 3)
        parts.append((np.vstack([points, soil]), orientation, np.full(33, label), np.tile(center, (33, 1))))
        truth.append(rotation[:, 2])
    points, orientation, labels, centers = (np.concatenate(x) for x in zip(*parts))
    return (points, centers, orientation, np.ones(len(points)), labels), np.array(truth)


def test_soil_voxels_a_few_millimetres_off_the_dome_do_not_tilt_a_small_cap(monkeypatch):
    args, truth = small_caps_with_soil_beside()
    with_cut = axis_errors_deg(fit_caps(*args), truth)
    monkeypatch.setattr(pose, "SURFACE_OUTLIER_FACTOR", np.inf)
    without_cut = axis_errors_deg(fit_caps(*args), truth)
    assert np.median(with_cut) < 3.0
    assert np.median(with_cut) < 0.5 * np.median(without_cut)


def shallow_dome(center, rotation, rim, sphere_radius, n, rng):
    """Points spread evenly over a spherical cap of rim radius ``rim`` cut from a sphere of
    ``sphere_radius`` (a real cap's shallow dome), its rim plane through ``center``, turned by
    ``rotation``; and the height of the dome."""
    cos_max = np.sqrt(1.0 - (rim / sphere_radius) ** 2)
    cos_polar = rng.uniform(cos_max, 1.0, n)  # even in cos: even over the sphere's area
    sin_polar, azimuth = np.sqrt(1.0 - cos_polar**2), rng.uniform(0.0, 2 * np.pi, n)
    local = sphere_radius * np.stack([sin_polar * np.cos(azimuth), sin_polar * np.sin(azimuth),
                                      cos_polar - cos_max], 1)
    return local @ rotation.T + center, sphere_radius * (1.0 - cos_max)


def test_rim_radius_is_the_quantile_of_distances_from_the_axis_on_shallow_domes():
    """On a spherical cap the fraction of the area within distance x of the axis is
    (1 - cos t(x)) / (1 - cos t_max) with sin t(x) = x / R, so its q-quantile is R sin t_q with
    cos t_q = 1 - q (1 - cos t_max); two tilted domes, shuffled together, each get their own."""
    rng = np.random.default_rng(5)
    domes = [(np.array([0.05, -0.02, 0.01]), cap_rotation(0.4, -0.2), 0.028, 0.042),
             (np.array([-0.04, 0.03, 0.0]), cap_rotation(-0.1, 0.5), 0.012, 0.030)]
    points, labels, heights = [], [], []
    for k, (center, rotation, rim, sphere_radius) in enumerate(domes):
        cloud, height = shallow_dome(center, rotation, rim, sphere_radius, 20000, rng)
        points.append(cloud)
        labels.append(np.full(len(cloud), k))
        heights.append(height)
    points, labels = np.vstack(points), np.concatenate(labels)
    order = rng.permutation(len(points))
    points, labels = np.vstack([points[order], [[9.0, 9.0, 9.0]]]), np.append(labels[order], -1)
    caps = pose.Caps(np.array([d[0] for d in domes]), np.array([d[1] for d in domes]),
                     np.array([[d[2], d[2], h] for d, h in zip(domes, heights)]))
    quantile = pose.RIM_QUANTILE
    for k, (_, _, rim, sphere_radius) in enumerate(domes):
        cos_max = np.sqrt(1.0 - (rim / sphere_radius) ** 2)
        expected = sphere_radius * np.sqrt(1.0 - (1.0 - quantile * (1.0 - cos_max)) ** 2)
        # 20000 samples: the quantile's sampling error is about 0.2 % here
        assert pose.rim_radii(points, labels, caps)[k] == pytest.approx(expected, rel=0.01)


def test_the_dome_is_the_ellipsoid_the_points_lie_on():
    """Points on tilted cap ellipsoids of any height (shallower and taller than the template), shuffled
    together with an unlabelled stray: each cap's dome gives back its s and s_z; with 0.2 mm of noise,
    within 2 %; a flat disc (no height to fit) and a cap with too few points give nan."""
    rng = np.random.default_rng(11)
    shapes = [((0.05, -0.02, 0.01), 0.4, -0.2, 0.028, 0.35), ((-0.04, 0.03, 0.0), -0.1, 0.5, 0.012, 0.9),
              ((0.0, 0.09, 0.02), 0.0, 0.0, 0.035, CAP_HEIGHT_RATIO)]
    parts = [ideal_cap(np.array(c), tx, ty, 0.3, s, ratio * s, n=3000, seed=i)
             for i, (c, tx, ty, s, ratio) in enumerate(shapes)]
    disc = np.column_stack([rng.uniform(-0.01, 0.01, (200, 2)), np.zeros(200)]) + [0.2, 0.2, 0.0]
    points = np.vstack([p[0] for p in parts] + [disc, [[0.3, 0.3, 0.0]] * 3, [[9.0, 9.0, 9.0]]])
    labels = np.concatenate([np.full(3000, k) for k in range(3)] + [np.full(200, 3), np.full(3, 4), [-1]])
    rotations = np.array([p[3] for p in parts] + [np.eye(3)] * 2)
    centers = np.array([c for c, *_ in shapes] + [(0.2, 0.2, 0.0), (0.3, 0.3, 0.0)])
    caps = pose.Caps(centers, rotations, np.array([[s, s, r * s] for *_, s, r in shapes] + [[0.01, 0.01, 0.005]] * 2))
    order = rng.permutation(len(points))
    radii, heights = pose.fit_domes(points[order], labels[order], caps, min_points=pose.SURFACE_MIN_POINTS)
    np.testing.assert_allclose(radii[:3], [s for *_, s, _ in shapes], rtol=1e-9)
    np.testing.assert_allclose(heights[:3], [r * s for *_, s, r in shapes], rtol=1e-9)
    assert np.isnan(radii[3:]).all() and np.isnan(heights[3:]).all()
    noisy = points + rng.normal(0.0, 2e-4, points.shape)
    radii, heights = pose.fit_domes(noisy, labels, caps)
    np.testing.assert_allclose(radii[:3], [s for *_, s, _ in shapes], rtol=0.02)
    np.testing.assert_allclose(heights[:3], [r * s for *_, s, r in shapes], rtol=0.03)


def test_the_size_is_the_dome_unless_it_extrapolates_past_the_quantile():
    """A whole dome reports its dome's s and s_z; a crown (elevations 1.0-pi/2 only, whose dome is still
    exact) lies so far inside its rim that the dome is an extrapolation, and reports the quantile's
    distance s cos e at e = 1.0 + 0.1 (pi / 2 - 1.0); a flat disc has no dome and reports the quantile
    too, R sqrt(0.9) for points even over its area; those two keep the pose fit's height; the centres
    and axes stay the caps'."""
    whole, *_ = ideal_cap(np.zeros(3), 0.2, 0.1, 0.0, 0.02, 0.012, n=4000, seed=1)
    rng = np.random.default_rng(2)
    elevation, azimuth = rng.uniform(1.0, np.pi / 2, 4000), rng.uniform(0, 2 * np.pi, 4000)
    crown = 0.03 * np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                             0.6 * np.sin(elevation)], 1) + [0.1, 0.0, 0.0]
    radius, angle = 0.015 * np.sqrt(rng.uniform(0, 1, 4000)), rng.uniform(0, 2 * np.pi, 4000)
    disc = np.column_stack([radius * np.cos(angle), radius * np.sin(angle), np.zeros(4000)]) + [0.0, 0.1, 0.0]
    points, labels = np.vstack([whole, crown, disc]), np.repeat([0, 1, 2], 4000)
    caps = pose.Caps(np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]]),
                     np.stack([cap_rotation(0.2, 0.1), np.eye(3), np.eye(3)]),
                     np.array([[0.05, 0.05, 0.012], [0.05, 0.05, 0.018], [0.05, 0.05, 0.004]]))
    measured = pose.with_dome_sizes(caps, points, labels)
    crown_rim = 0.03 * np.cos(1.0 + (1 - pose.RIM_QUANTILE) * (np.pi / 2 - 1.0))
    np.testing.assert_allclose(measured.radii, [0.02, crown_rim, 0.015 * np.sqrt(pose.RIM_QUANTILE)], rtol=0.01)
    np.testing.assert_allclose(measured.scales[0, 2], 0.012, rtol=1e-9)
    np.testing.assert_array_equal(measured.scales[1:, 2], caps.scales[1:, 2])
    np.testing.assert_array_equal(measured.centers, caps.centers)


def test_the_size_keeps_the_fit_where_a_cap_has_too_few_points():
    caps = pose.Caps(np.zeros((2, 3)), np.stack([np.eye(3)] * 2), np.array([[0.02, 0.02, 0.013]] * 2))
    points = np.array([[0.01, 0.0, 0.0]] * 3 + [[0.015, 0.0, 0.0]] * pose.SURFACE_MIN_POINTS)
    labels = np.array([0] * 3 + [1] * pose.SURFACE_MIN_POINTS)
    measured = pose.with_dome_sizes(caps, points, labels)
    np.testing.assert_allclose(measured.radii, [0.02, 0.015])


def ideal_caps_found(caps, height_ratio):
    """Ideal caps ((centre, theta_x, theta_y, s), s_z = ``height_ratio`` s) through the whole instance
    step, each point its own voxel: the points, the prediction, and the caps found with
    ``radius="fit"`` and by default."""
    from perception.detect import VoxelPrediction, find_caps

    parts = [ideal_cap(np.array(c), tx, ty, 0.0, s, height_ratio * s, n=4000, seed=i)
             for i, (c, tx, ty, s) in enumerate(caps)]
    points = np.concatenate([p[0] for p in parts])
    prediction = VoxelPrediction(points, np.ones(len(points)), np.concatenate([p[1] for p in parts]),
                                 np.concatenate([p[2] for p in parts]), np.arange(len(points)))
    return points, prediction, find_caps(prediction, 0.0045, radius="fit")[1], find_caps(prediction, 0.0045)[1]


def test_find_caps_reports_the_rim_radius_and_with_fit_the_ellipsoids():
    """Three ideal caps through the whole instance step: with ``radius="fit"`` the ellipsoid's s comes
    back exactly, and by default the rim of the dome their points lie on, the same s; with the cloud's
    points given, measured on them rather than on the voxel centroids."""
    from perception.detect import find_caps

    caps = [((0.0, 0.0, 0.01), 0.4, -0.3, 0.02), ((0.1, 0.05, 0.0), -0.6, 0.1, 0.012),
            ((-0.08, 0.1, 0.02), 0.0, 0.7, 0.028)]
    points, prediction, fitted, measured = ideal_caps_found(caps, CAP_HEIGHT_RATIO)
    order = np.argsort(fitted.radii)
    true_radii = np.sort([s for *_, s in caps])
    np.testing.assert_allclose(fitted.radii[order], true_radii, rtol=1e-6)
    np.testing.assert_allclose(measured.radii[order], true_radii, rtol=1e-6)
    np.testing.assert_allclose(measured.scales[:, 2], fitted.scales[:, 2], rtol=1e-6)
    # the points each stand for a voxel at their centre's place: 1.1 times as far out, a dome 1.1 times as wide
    _, on_points = find_caps(prediction, 0.0045, points=1.1 * points - 0.1 * prediction.centers)
    np.testing.assert_allclose(on_points.radii[order], 1.1 * true_radii, rtol=1e-6)
    with pytest.raises(ValueError, match="radius mode"):
        find_caps(prediction, 0.0045, radius="widest")


def test_flat_caps_get_their_own_height_from_the_dome():
    """Opened caps 0.3 times as high as wide lie outside the height ratios the pose fit allows
    (``HEIGHT_RATIO_RANGE``), so its s_z overstates them; the dome fitted to their points gives back
    their s and s_z."""
    assert 0.3 < pose.HEIGHT_RATIO_RANGE[0]
    caps = [((0.0, 0.0, 0.01), 0.2, -0.1, 0.03), ((0.1, 0.05, 0.0), -0.15, 0.1, 0.035)]
    _, _, fitted, measured = ideal_caps_found(caps, 0.3)
    order = np.argsort(measured.radii)
    true_radii = np.sort([s for *_, s in caps])
    np.testing.assert_allclose(measured.radii[order], true_radii, rtol=1e-3)
    np.testing.assert_allclose(measured.scales[order, 2], 0.3 * true_radii, rtol=1e-3)
    assert (fitted.scales[:, 2] > 1.3 * 0.3 * fitted.radii).all()
