"""Clouds denser than the training scenes reach the network at the training density."""

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from common.geometry import voxel_representatives
from perception.detect import predict
from helpers import tiny_network_config
from perception.model import MushroomNet
from perception.synthetic.scene import SceneConfig, generate_scene

TINY = tiny_network_config()
SPACING = SceneConfig().spacing


@pytest.mark.parametrize("zoom", [1.0, 1.1])
def test_a_dense_cloud_is_thinned_to_the_training_spacing_and_every_point_keeps_a_prediction(zoom):
    torch.manual_seed(0)
    model = MushroomNet(TINY, point_spacing=SPACING).eval()
    scene = generate_scene(2, SceneConfig(mushrooms=(5, 5)))
    rng = np.random.default_rng(0)
    dense = np.concatenate([scene.points + rng.normal(0, 0.0007, scene.points.shape) for _ in range(6)])
    kept = voxel_representatives(dense, SPACING)
    assert len(dense) > 2 * len(kept)

    thinned = predict(model, dense, zoom=zoom)
    direct = predict(model, dense[kept], thin=False, zoom=zoom)
    assert np.array_equal(thinned.centroids, direct.centroids)
    assert np.allclose(thinned.existence, direct.existence) and np.allclose(thinned.centers, direct.centers)
    assert np.array_equal(thinned.point_to_voxel[kept], direct.point_to_voxel)
    # every other point takes its own voxel when that is occupied, else the voxel with the nearest centroid
    others = np.setdiff1d(np.arange(len(dense)), kept)
    # the network's cells are the model's voxel on the zoomed cloud
    voxel = model.config.voxel / zoom
    occupied = {tuple(cell) for cell in np.floor(thinned.centroids / voxel).astype(int)}
    own = np.floor(dense[others] / voxel).astype(int)
    has_own = np.array([tuple(cell) in occupied for cell in own])
    assert 0 < has_own.sum() < len(others)
    chosen = thinned.centroids[thinned.point_to_voxel[others]]
    assert np.array_equal(np.floor(chosen[has_own] / voxel).astype(int), own[has_own])
    nearest = cKDTree(thinned.centroids).query(dense[others][~has_own])[0]
    assert np.allclose(np.linalg.norm(dense[others][~has_own] - chosen[~has_own], axis=1), nearest)


def test_a_cloud_at_training_density_is_used_as_it_is():
    torch.manual_seed(0)
    model = MushroomNet(TINY, point_spacing=SPACING).eval()
    points = generate_scene(3, SceneConfig(mushrooms=(5, 5))).points
    assert np.array_equal(predict(model, points).existence, predict(model, points, thin=False).existence)


def test_zoom_is_the_same_network_on_the_scaled_cloud_with_answers_in_the_cloud_metres():
    torch.manual_seed(0)
    model = MushroomNet(TINY, point_spacing=SPACING).eval()
    points = generate_scene(4, SceneConfig(mushrooms=(5, 5))).points
    zoomed = predict(model, points, zoom=1.1)
    scaled = predict(model, 1.1 * points, thin=False, zoom=1.0)
    np.testing.assert_allclose(zoomed.centroids * 1.1, scaled.centroids, atol=1e-12)
    np.testing.assert_allclose(zoomed.centers * 1.1, scaled.centers, atol=1e-9)
    np.testing.assert_array_equal(zoomed.existence, scaled.existence)
    np.testing.assert_array_equal(zoomed.orientation, scaled.orientation)
    assert len(zoomed.centroids) > len(predict(model, points, zoom=1.0).centroids)


def test_a_model_thins_clouds_to_the_spacing_it_was_trained_at(tmp_path):
    from perception.train import TrainConfig
    from perception.weights import load_weights, save_weights

    torch.manual_seed(0)
    points = generate_scene(3, SceneConfig(mushrooms=(5, 5), spacing=0.003)).points
    for spacing in (0.003, 0.0051):
        path = tmp_path / f"{spacing}.pt"
        save_weights(MushroomNet(TINY), path, train_config=TrainConfig(scene=SceneConfig(spacing=spacing)).to_dict())
        model, _ = load_weights(path)
        assert model.point_spacing == spacing
        kept = voxel_representatives(points, spacing)
        thinned = len(points) > 2 * len(kept)
        assert thinned == (spacing == 0.0051)
        expected = predict(model, points[kept] if thinned else points, thin=False)
        np.testing.assert_array_equal(predict(model, points).centroids, expected.centroids)


def test_a_model_is_read_at_the_zoom_its_weights_record_and_older_weights_at_1_1(tmp_path):
    from perception.weights import UNRECORDED_ZOOM, load_weights, save_weights

    torch.manual_seed(0)
    points = generate_scene(3, SceneConfig(mushrooms=(5, 5))).points
    path = tmp_path / "zoomed.pt"
    save_weights(MushroomNet(TINY, point_spacing=SPACING, inference_zoom=1.3), path)
    model, _ = load_weights(path)
    assert model.inference_zoom == 1.3
    np.testing.assert_array_equal(predict(model, points).centroids, predict(model, points, zoom=1.3).centroids)
    assert len(predict(model, points).centroids) > len(predict(model, points, zoom=1.0).centroids)
    state = torch.load(path, weights_only=False)
    del state["inference_zoom"]
    torch.save(state, tmp_path / "older.pt")
    assert UNRECORDED_ZOOM == 1.1 and load_weights(tmp_path / "older.pt")[0].inference_zoom == 1.1


def test_a_sparser_cloud_is_read_at_a_lower_zoom(tmp_path):
    """Beds at the training spacing are read at the model's zoom; the same bed at 5 mm spacing lower
    (about 1.67 times the training beds' neighbour distance: zoom x 1.67^-0.56 = 0.75 x zoom)."""
    from helpers import write_tiny_weights
    from perception.detect import reading_zoom
    from perception.synthetic.scene import SceneConfig, generate_scene
    from perception.weights import load_weights

    model, _ = load_weights(write_tiny_weights(tmp_path / "tiny.pt"))
    model.inference_zoom = 1.2
    dense = generate_scene(7, SceneConfig(spacing=model.point_spacing, jitter=(1.0, 1.0)))
    sparse = generate_scene(7, SceneConfig(spacing=0.005, jitter=(1.0, 1.0)))
    assert reading_zoom(model, dense.points) == pytest.approx(1.2, abs=0.02)
    assert 0.85 < reading_zoom(model, sparse.points) < 0.97
    model.point_spacing = None
    assert reading_zoom(model, sparse.points) == 1.2
