"""Sparse clouds are filled in on their height-field surface before the network reads them."""

import numpy as np
import pytest
import torch

from perception.densify import MAX_EDGE_SPACINGS, densified
from perception.detect import DENSIFY_RATIOS, densified_for_reading, point_spacing, predict, reading_input
from helpers import tiny_network_config
from perception.model import MushroomNet

TARGET = 0.003


def mesa(x, y):
    """A height field: a plane rising 1 in 10, and on it a flat-topped block 30 mm high (|x|, |y| < 40 mm)
    whose sides are vertical walls."""
    return 0.1 * x + np.where((np.abs(x) < 0.04) & (np.abs(y) < 0.04), 0.03, 0.0)


def sparse_grid(spacing, half=0.1, hole=None):
    """Points of ``mesa`` on a jittered grid ``spacing`` apart, without those inside ``hole`` (x0, x1)."""
    rng = np.random.default_rng(1)
    ticks = np.arange(-half, half, spacing)
    x, y = (v.ravel() + rng.uniform(-0.1, 0.1, v.size) * spacing for v in np.meshgrid(ticks, ticks))
    if hole is not None:
        keep = ~((x > hole[0]) & (x < hole[1]) & (np.abs(y) < 0.05))
        x, y = x[keep], y[keep]
    return np.column_stack([x, y, mesa(x, y)])


def test_a_sparse_height_field_is_filled_in_on_its_surface_and_nowhere_else():
    """New points lie on the surface's faces (the plane and the block's top, away from the walls: within
    a millimetre of the height field), one per empty 3 mm cell, so the cloud comes out about as dense
    as a 3 mm bed; no point is drawn on the vertical walls, nor in a hole wider than the longest edge
    kept; the given points come first, unchanged; and the same cloud is filled the same way."""
    spacing = 0.008
    points = sparse_grid(spacing, hole=(0.05, 0.05 + 3 * MAX_EDGE_SPACINGS * spacing))
    dense = densified(points, spacing, TARGET)
    assert np.array_equal(dense[:len(points)], points)
    new = dense[len(points):]
    assert 4 * len(points) < len(new)
    near_wall = np.abs(np.maximum(np.abs(new[:, 0]), np.abs(new[:, 1])) - 0.04) < spacing
    assert np.abs(new[~near_wall, 2] - mesa(new[~near_wall, 0], new[~near_wall, 1])).max() < 1e-3
    # half-way up the walls, 12-18 mm over the plane: nothing
    height = new[:, 2] - 0.1 * new[:, 0]
    assert not ((height > 0.012) & (height < 0.018)).any()
    inside_hole = (new[:, 0] > 0.05 + spacing) & (new[:, 0] < 0.05 + 3 * MAX_EDGE_SPACINGS * spacing - spacing) \
        & (np.abs(new[:, 1]) < 0.05 - spacing)
    assert not inside_hole.any()
    cells = np.floor(dense / TARGET).astype(np.int64)
    assert len(np.unique(cells, axis=0)) == len(dense)  # at most one point per cell
    assert np.array_equal(densified(points, spacing, TARGET), dense)


@pytest.mark.parametrize("points", [np.zeros((0, 3)), np.array([[0.0, 0, 0], [0.01, 0, 0], [0.02, 0, 0.01]]),
                                    np.column_stack([np.linspace(0, 1, 50), np.zeros(50), np.zeros(50)])])
def test_clouds_with_no_surface_come_back_as_given(points):
    assert np.array_equal(densified(points, 0.008, TARGET), points)


def test_only_clouds_sparser_than_the_threshold_are_filled_in_and_only_their_own_points_labelled():
    """A cloud at 3 mm, or too sparse to fill in, is read as it is; one at 8 mm is read with the points
    filled in after its own, at the zoom of its own spacing, and every prediction maps the cloud's own
    points only, each to the voxel it lies in."""
    torch.manual_seed(0)
    model = MushroomNet(tiny_network_config(), point_spacing=TARGET).eval()
    low, high = DENSIFY_RATIOS
    for spacing in (0.003, 0.02):
        cloud = sparse_grid(spacing, half=0.2)
        assert not low * TARGET < point_spacing(cloud) <= high * TARGET
        assert densified_for_reading(model, cloud) is cloud
    far = sparse_grid(0.008)
    assert low * TARGET < point_spacing(far) <= high * TARGET
    kept, zoom, read, *_ = reading_input(model, far)
    assert len(kept) == len(far) and len(read) > 4 * len(far) and np.array_equal(read[:len(far)], far)
    _, zoom_unfilled, *_ = reading_input(model, far, thin=False)
    assert zoom == zoom_unfilled
    prediction = predict(model, far, readings=2)
    unfilled = predict(model, far, thin=False, readings=2)
    assert len(prediction.centroids) > len(unfilled.centroids)
    assert prediction.filled_in == len(read) - len(far) and unfilled.filled_in == 0
    voxel = model.config.voxel / zoom
    assert np.array_equal(np.floor(prediction.centroids[prediction.point_to_voxel] / voxel), np.floor(far / voxel))


def test_a_cloud_thinned_and_then_filled_in_maps_its_dropped_points_to_their_kept_twins_voxels():
    """Each point of an 8 mm cloud given five times over: the copies are thinned away, the kept points
    filled in, and every copy takes the voxel of the point it copies."""
    torch.manual_seed(0)
    model = MushroomNet(tiny_network_config(), point_spacing=TARGET).eval()
    far = sparse_grid(0.008)
    copies = np.concatenate([far] * 5)
    prediction = predict(model, copies)
    assert prediction.filled_in > 0 and len(prediction.point_to_voxel) == len(copies)
    np.testing.assert_array_equal(prediction.point_to_voxel.reshape(5, len(far)),
                                  np.tile(prediction.point_to_voxel[:len(far)], (5, 1)))
