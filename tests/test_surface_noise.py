"""A cloud's surface noise and the smoothing of noisy clouds before the network reads them: the measure
grows with the scatter and holds still with the density, a clean or odd cloud passes unchanged, points
on a quadric stay on it, a partial share blends linearly, a noisy dome comes back near its true surface
without being flattened, a noisy single-view bed gives more of its caps once smoothed, and ``detect``
smooths once, says so, and plans on the cloud as given."""

import numpy as np
import pytest

from perception.evaluate import evaluate, visible_truth
from perception.surface_noise import (CLEAN_NOISE, NOISY_NOISE, quadric_projection, smoothed, smoothing_share,
                                      surface_noise)
from perception.synthetic.families import FAMILIES, family_seeds
from perception.synthetic.scene import SceneConfig, generate_scene

DOME_RADIUS = 0.04


def grid(spacing: float, half: float = 0.08) -> np.ndarray:
    """A square grid of (x, y) with ``spacing``, jittered by a tenth of it."""
    rng = np.random.default_rng(1)
    axis = np.arange(-half, half, spacing)
    xy = np.stack(np.meshgrid(axis, axis), -1).reshape(-1, 2)
    return xy + rng.uniform(-0.1, 0.1, xy.shape) * spacing


def dome(spacing: float, noise: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A sphere's top (radius ``DOME_RADIUS``, centre on z = 0) over a flat floor at z = 0.02, each point
    moved ``noise`` (standard deviation, metres) along z; the noisy points and the clean ones."""
    xy = grid(spacing)
    z = np.sqrt(np.maximum(DOME_RADIUS**2 - (xy**2).sum(1), 0.0))
    clean = np.column_stack([xy, np.maximum(z, 0.02)])
    noisy = clean.copy()
    noisy[:, 2] += np.random.default_rng(seed).normal(0.0, noise, len(clean))
    return noisy, clean


def height_error(points: np.ndarray) -> np.ndarray:
    """Distance along z of each point from the clean dome-and-floor surface."""
    z = np.sqrt(np.maximum(DOME_RADIUS**2 - (points[:, :2] ** 2).sum(1), 0.0))
    return points[:, 2] - np.maximum(z, 0.02)


def test_the_measure_grows_with_the_scatter_and_not_with_the_density():
    readings = {(spacing, noise): surface_noise(dome(spacing, noise * spacing)[0])
                for spacing in (0.002, 0.003, 0.005) for noise in (0.0, 0.3, 1.5)}
    for spacing in (0.002, 0.003, 0.005):
        assert readings[spacing, 0.0] < readings[spacing, 0.3] < readings[spacing, 1.5]
        assert readings[spacing, 0.3] < CLEAN_NOISE < NOISY_NOISE < readings[spacing, 1.5]
    for noise in (0.0, 0.3, 1.5):
        values = [readings[spacing, noise] for spacing in (0.002, 0.003, 0.005)]
        assert max(values) - min(values) < 0.15, values
    assert np.isnan(surface_noise(np.zeros((5, 3))))


def test_the_share_ramps_between_the_two_levels():
    assert smoothing_share(CLEAN_NOISE) == 0.0 and smoothing_share(NOISY_NOISE) == 1.0
    assert smoothing_share((CLEAN_NOISE + NOISY_NOISE) / 2) == pytest.approx(0.5)
    assert smoothing_share(float("nan")) == 0.0 and smoothing_share(0.0) == 0.0 and smoothing_share(5.0) == 1.0


def test_a_clean_cloud_passes_as_it_is():
    points, _ = dome(0.003, 0.0002)
    out, noise = smoothed(points, 0.003)
    assert noise < CLEAN_NOISE and out is points


@pytest.mark.parametrize("spacing, thin", [(0.003, 0.003), (0.001, 0.003)])
def test_a_noisy_dome_comes_back_near_its_surface_and_keeps_its_curvature(spacing, thin):
    noisy, _ = dome(spacing, 0.004)
    out, noise = smoothed(noisy, thin)
    assert noise > NOISY_NOISE and out.shape == noisy.shape
    inside = (np.abs(noisy[:, :2]) < 0.06).all(1)  # away from the cloud's edge
    before, after = np.abs(height_error(noisy[inside])), np.abs(height_error(out[inside]))
    assert np.median(after) < 0.4 * np.median(before), (np.median(before), np.median(after))
    top = inside & ((noisy[:, :2] ** 2).sum(1) < 0.01**2)
    assert abs(np.mean(height_error(out[top]))) < 0.0005  # the crown is not shaved off


def test_a_noisy_single_view_bed_gives_more_caps_once_smoothed():
    from perception.detect import detect_points
    from perception.weights import DEFAULT_WEIGHTS, load_inference_net

    model = load_inference_net(DEFAULT_WEIGHTS)[0]
    scenes = [generate_scene(seed, FAMILIES["single-view"].config) for seed in family_seeds("single-view", 2)]
    truth = [visible_truth(scene) for scene in scenes]
    plain = [detect_points(model, s.points.astype(np.float64), readings=1, noise=0.0).caps for s in scenes]
    results = [detect_points(model, s.points.astype(np.float64), readings=1) for s in scenes]
    assert all(result.surface_noise > CLEAN_NOISE for result in results)
    assert evaluate([r.caps for r in results], truth).ap25 > evaluate(plain, truth).ap25 + 0.05
    clean = generate_scene(3, SceneConfig())
    result = detect_points(model, clean.points.astype(np.float64), readings=1)
    unsmoothed = detect_points(model, clean.points.astype(np.float64), readings=1, noise=0.0)
    assert result.surface_noise < CLEAN_NOISE
    np.testing.assert_array_equal(result.caps.centers, unsmoothed.caps.centers)


def test_detect_says_when_it_smoothed_a_cloud(tmp_path):
    from test_detect_cli import run, write_ply

    noisy = generate_scene(family_seeds("single-view", 1)[0], FAMILIES["single-view"].config).points
    clean = generate_scene(3, SceneConfig()).points
    said = {}
    for name, points in (("noisy", noisy), ("clean", clean)):
        result = run("detect", str(write_ply(tmp_path / f"{name}.ply", points)), "--out", str(tmp_path / f"{name}.json"),
                     "--readings", "1")
        assert result.returncode == 0, result.stderr
        said[name] = "were smoothed" in result.stderr
    assert said == {"noisy": True, "clean": False}


def test_points_on_a_tilted_quadric_stay_on_it():
    xy = grid(0.003, 0.05)
    surface = np.column_stack([xy, 0.3 * xy[:, 0] - 0.2 * xy[:, 1] + 4.0 * xy[:, 0] ** 2 + 2.0 * xy[:, 0] * xy[:, 1]])
    from scipy.spatial.transform import Rotation

    turned = surface @ Rotation.from_euler("xyz", [25, -40, 70], degrees=True).as_matrix().T
    assert np.abs(quadric_projection(turned) - turned).max() < 2e-5


def test_a_partial_share_blends_the_smoothed_cloud_in_linearly(monkeypatch):
    import perception.surface_noise as surface_noise_module

    noisy, _ = dome(0.003, 0.004)
    full, noise = smoothed(noisy, 0.003)
    monkeypatch.setattr(surface_noise_module, "surface_noise", lambda points, spacing=None: (CLEAN_NOISE + NOISY_NOISE) / 2)
    half, _ = surface_noise_module.smoothed(noisy, 0.003)
    np.testing.assert_allclose(half, noisy + 0.5 * (full - noisy), atol=1e-12)


def test_odd_clouds_are_read_as_they_are():
    points, _ = dome(0.003, 0.0002)
    assert np.isnan(surface_noise(np.zeros((0, 3)), 0.003)) and np.isnan(surface_noise(points[:10], 0.003))
    assert np.isnan(surface_noise(np.repeat(points, 2, axis=0)))  # every point twice: no spacing to measure
    as_float32 = points.astype(np.float32)
    assert smoothed(as_float32, 0.003)[0] is as_float32
    assert smoothed(np.zeros((0, 3)), 0.003)[0].shape == (0, 3)


def test_detect_smooths_once_and_plans_on_the_cloud_as_given(monkeypatch):
    import perception.detect as detect_module
    from fusion.bed import estimate_bed_frame
    from perception.weights import DEFAULT_WEIGHTS, load_inference_net

    calls = []

    def counted(points, spacing=None):
        calls.append(len(points))
        return smoothed(points, spacing)

    monkeypatch.setattr(detect_module, "smoothed", counted)
    model = load_inference_net(DEFAULT_WEIGHTS)[0]
    points = generate_scene(family_seeds("single-view", 1)[0], FAMILIES["single-view"].config).points.astype(np.float64)
    T_input_bed, bed_points, result = detect_module.detect_up_side(model, points, estimate_bed_frame(points))
    assert len(calls) == 1 and result.surface_noise > NOISY_NOISE and "smoothing" in result.timings_ms
    np.testing.assert_allclose(bed_points, (points - T_input_bed[:3, 3]) @ T_input_bed[:3, :3], atol=1e-9)
    detect_module.detect_points(model, bed_points)
    assert len(calls) == 2
    with pytest.raises(ValueError, match="give noise too"):
        detect_module.detect_points(model, bed_points, first=detect_module.first_reading(model, bed_points))
