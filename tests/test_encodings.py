"""The paper's Table 2 ablations: explicit-centre and explicit-orientation targets are the caps' own centres
and axes, and a network that predicted them exactly would give back every cap's pose exactly."""

import numpy as np
import pytest
import torch

from perception.detect import network_input, network_output
from perception.model import MushroomNet
from perception.network import LENGTH_UNIT, NETWORK_PRESETS
from perception.pose import fit_caps
from perception.train import TrainConfig, augmented_sample, explicit_targets, voxel_targets

VOXEL = NETWORK_PRESETS["slim-no"].voxel


@pytest.fixture(scope="module")
def sample():
    from perception.synthetic.scene import SceneConfig

    config = TrainConfig(seed=4, noise=0.0, point_dropout=(0.0, 0.0), scene=SceneConfig(mushrooms=(8, 8)))
    sample = augmented_sample(config, 0)
    # the truth, independently: every cap's centre and axis from its points' own targets
    instance = sample["instance"]
    caps = np.unique(instance[instance >= 0])
    centre = {k: (sample["points"] + sample["residual"])[instance == k].mean(0) for k in caps}
    axis = {k: sample["axis"][instance == k][0] for k in caps}
    return sample, centre, axis


def _voxel_caps(sample):
    """Each voxel's cap when all its points belong to one cap, else -1."""
    point_to_voxel = torch.from_numpy(network_input(sample["points"], VOXEL)[1])
    voxels = int(point_to_voxel.max()) + 1
    instance = torch.from_numpy(sample["instance"])
    high = torch.full((voxels,), -1).scatter_reduce(0, point_to_voxel, instance, "amax")
    low = torch.full((voxels,), 10**6).scatter_reduce(0, point_to_voxel, instance, "amin")
    return torch.where(high == low, high, -1).numpy()


def test_explicit_targets_are_the_caps_centres_and_axes(sample):
    sample, centre, axis = sample
    coords, existence, residual, orientation, centroids, _ = voxel_targets(sample, VOXEL)
    cap_of_voxel = _voxel_caps(sample)
    whole = (cap_of_voxel >= 0) & (existence.numpy() == 1)
    centres, _ = explicit_targets("explicit-centre", sample, VOXEL, existence, residual, orientation, centroids)
    _, axes = explicit_targets("explicit-orientation", sample, VOXEL, existence, residual, orientation, centroids)
    truth_centre = np.array([centre[k] for k in cap_of_voxel[whole]])
    truth_axis = np.array([axis[k] for k in cap_of_voxel[whole]])
    assert np.abs(centres.numpy()[whole] * LENGTH_UNIT - truth_centre).max() < 1e-5  # metres, float32 sums
    assert np.abs(axes.numpy()[whole] - truth_axis).max() < 1e-5
    off = existence.numpy() == 0
    assert (centres.numpy()[off] == 0).all() and (axes.numpy()[off] == 0).all()


def test_exact_explicit_predictions_give_back_every_caps_pose(sample):
    sample, centre, axis = sample
    coords, existence, residual, orientation, centroids, _ = voxel_targets(sample, VOXEL)
    centres, _ = explicit_targets("explicit-centre", sample, VOXEL, existence, residual, orientation, centroids)
    _, axes = explicit_targets("explicit-orientation", sample, VOXEL, existence, residual, orientation, centroids)
    labels = np.where(existence.numpy() > 0.5, _voxel_caps(sample), -1)
    caps = np.unique(labels[labels >= 0])
    relabelled = np.where(labels >= 0, np.searchsorted(caps, labels), -1)
    fit = fit_caps(centroids, centres.numpy().astype(np.float64) * LENGTH_UNIT, axes.numpy().astype(np.float64),
                   existence.numpy().astype(np.float64), relabelled, axis="encoding")
    assert np.abs(fit.centers - np.array([centre[k] for k in caps])).max() < 1e-5
    cosine = np.einsum("ij,ij->i", fit.rotations[:, :, 2], np.array([axis[k] for k in caps]))
    assert np.abs(1 - cosine).max() < 1e-6  # exact to float32 (the targets' precision)


@pytest.mark.parametrize("encoding,orientation_shape", [("implicit", (1,)), ("explicit-centre", (1,)),
                                                         ("explicit-orientation", (3,))])
def test_the_network_decodes_each_encoding(encoding, orientation_shape):
    torch.manual_seed(0)
    model = MushroomNet(NETWORK_PRESETS[f"slim-no-{encoding}" if encoding != "implicit" else "slim-no"]).eval()
    points = np.random.default_rng(0).uniform(0, 0.05, (400, 3))
    coords, _, centroids = network_input(points, VOXEL)
    got_centroids, existence, centers, orientation = network_output(model, coords, centroids, 1.0)
    assert orientation.reshape(len(got_centroids), -1).shape[1] == orientation_shape[0]
    with torch.no_grad():
        from perception.network import voxel_features
        from perception.sparse import SparseTensor

        raw = model(SparseTensor(torch.from_numpy(voxel_features(model.config, centroids)),
                                 torch.from_numpy(coords))).double()
    # the centre is the raw output itself with explicit-centre, the voxel centroid plus it otherwise
    offset = 0 if encoding == "explicit-centre" else got_centroids
    assert np.allclose(centers, offset + raw[:, 1:4].numpy() * LENGTH_UNIT, atol=1e-6)
