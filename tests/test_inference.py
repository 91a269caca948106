"""perception.inference (the network in numpy) against the torch network it stands in for, and the
weights read without torch against torch.load."""

import pickle
import zipfile
from dataclasses import replace

import numpy as np
import pytest
import torch

from perception import sparse
from perception.calibration import Calibration
from perception.detect import detect_points, network_input, voxel_average
from perception.inference import (COORD_MAX, DENSE_TABLE_CELLS, InferenceNet, VoxelLevel, downsample_map, pack,
                                  submanifold_map, unpack, voxelize)
from perception.model import MushroomNet, inference_model
from perception.network import NETWORK_PRESETS, _oriented_normals, voxel_features
from perception.synthetic.scene import SceneConfig, generate_scene
from perception.weights import DEFAULT_WEIGHTS, load_inference_net, load_weights, read_payload, save_weights


def test_voxelize_keeps_every_point_in_its_voxel():
    points = np.random.default_rng(7).uniform(-0.1, 0.1, (5000, 3))
    coords, point_to_voxel = voxelize(points, 0.01)
    assert coords.dtype == point_to_voxel.dtype == np.int64
    assert len(np.unique(coords, axis=0)) == len(coords)
    assert (coords[:, 0] == 0).all()
    assert np.array_equal(coords[point_to_voxel, 1:], np.floor(points / 0.01).astype(np.int64))
    assert np.array_equal(unpack(pack(coords)), coords)
    assert np.array_equal(np.unique(point_to_voxel), np.arange(len(coords)))
    assert (np.diff(pack(coords)) > 0).all()  # sorted, as the torch voxeliser sorts them
    mean = voxel_average(points, point_to_voxel, len(coords))
    for v in (0, len(coords) // 2, len(coords) - 1):
        np.testing.assert_allclose(mean[v], points[point_to_voxel == v].mean(0))
    with pytest.raises(ValueError, match="packable range"):
        voxelize(np.array([[0.0, 0.0, (COORD_MAX + 2) * 0.01]]), 0.01)


def _torch_maps(coords: np.ndarray):
    x = sparse.SparseTensor(torch.zeros(len(coords), 1), torch.from_numpy(coords))
    parents = sparse.parent_coords(x).numpy()
    return ({k: sparse.submanifold_map(x, k) for k in (3, 5)}, parents, sparse.downsample_map(x, 3))


def _as_numpy(kmap):
    return [None if i is None else (i.numpy(), o.numpy()) for i, o in kmap]


def _same_map(ours, theirs):
    assert len(ours) == len(theirs)
    for a, b in zip(ours, _as_numpy(theirs)):
        assert (a is None) == (b is None)
        if a is not None:
            assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


@pytest.mark.parametrize("stray", [False, True], ids=["dense table", "sorted keys"])
def test_kernel_maps_are_those_of_the_torch_convolution(stray):
    """The same pairs in the same order as perception.sparse, from its dense table and, with a stray
    voxel far out (a box too big for the table), from its sorted keys."""
    rng = np.random.default_rng(3)
    xyz = np.unique(rng.integers(-12, 12, (1500, 3)), axis=0)
    if stray:
        far = 2 * int(DENSE_TABLE_CELLS ** (1 / 3))
        xyz = np.vstack([xyz, [[far, far, far]]])
    coords = np.hstack([np.zeros((len(xyz), 1), np.int64), xyz])
    coords = coords[np.argsort(pack(coords))]
    level = VoxelLevel(coords)
    assert (level.table is None) == stray
    submanifold, parents, down = _torch_maps(coords)
    for k in (3, 5):
        _same_map(submanifold_map(level, k), submanifold[k])
    assert np.array_equal(level.parents(), parents)
    _same_map(downsample_map(level, parents, 3), down)


def _randomised(config):
    """A torch network with random weights and batch-norm statistics far from their defaults, so that
    folding them into the convolutions is put to the test."""
    torch.manual_seed(0)
    model = MushroomNet(config)
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, sparse.SparseBatchNorm):
                module.running_mean.uniform_(-0.5, 0.5)
                module.running_var.uniform_(0.5, 2.0)
                module.weight.uniform_(0.5, 1.5)
                module.bias.uniform_(-0.2, 0.2)
    return model.eval()


def _bed_voxels(config, seed=2):
    scene = generate_scene(seed, SceneConfig(mushrooms=(6, 6)))
    coords, _, centroids = network_input(1.2 * scene.points[::3], config.voxel)
    return coords, voxel_features(config, centroids)


@pytest.mark.parametrize("preset", ["slim-no", "fcgf"])
def test_the_numpy_network_computes_what_the_torch_one_does(preset):
    """Per voxel, the outputs of the torch network as trained (batch norms apart, in eval mode) and of
    its numpy form agree to float32 round-off, over a bed's voxels."""
    config = NETWORK_PRESETS[preset]
    model = _randomised(config)
    coords, features = _bed_voxels(config)
    with torch.no_grad():
        expected = model(sparse.SparseTensor(torch.from_numpy(features), torch.from_numpy(coords))).numpy()
        folded = inference_model(model)(sparse.SparseTensor(torch.from_numpy(features),
                                                           torch.from_numpy(coords))).numpy()
    state = {name: value.numpy() for name, value in model.state_dict().items()}
    got = InferenceNet.from_state_dict(config, state)(coords, features)
    scale = np.abs(expected).max()
    assert scale > 0.1
    np.testing.assert_allclose(got, expected, atol=2e-5 * scale)
    np.testing.assert_allclose(got, folded, atol=2e-5 * scale)


def test_weights_read_without_torch_are_those_torch_reads(tmp_path):
    model = _randomised(NETWORK_PRESETS["slim-no"])
    model.point_spacing, model.inference_zoom = 0.003, 1.15
    model.calibration = replace(Calibration.from_dict(None), diameter_scale=1.02, diameter_offset_mm=-0.5)
    path = tmp_path / "model.pt"
    save_weights(model, path, iterations=7, train_config={"milestones": (0.6, 0.85)})
    payload = read_payload(path)
    expected = torch.load(path, weights_only=False)
    assert set(payload["model"]) == set(expected["model"])
    for name, value in expected["model"].items():
        assert payload["model"][name].dtype == value.numpy().dtype
        assert np.array_equal(payload["model"][name], value.numpy()), name
    assert {k: v for k, v in payload.items() if k != "model"} == {k: v for k, v in expected.items() if k != "model"}

    net, meta = load_inference_net(path)
    torch_model, torch_meta = load_weights(path)
    assert meta == torch_meta
    assert (net.config, net.point_spacing, net.inference_zoom, net.calibration) == (
        torch_model.config, torch_model.point_spacing, torch_model.inference_zoom, torch_model.calibration)


def test_a_training_checkpoint_is_read_without_torch_as_torch_reads_it(tmp_path, monkeypatch):
    """``--model RUN/checkpoint.pt`` works for ``detect`` as for the torch commands: a checkpoint also
    holds the optimiser's and the scheduler's state."""
    from helpers import tiny_network_config
    from perception.train import TrainConfig, train

    monkeypatch.setitem(NETWORK_PRESETS, "tiny", tiny_network_config())
    config = TrainConfig(iterations=2, network="tiny", validation_scenes=0, scene=SceneConfig(mushrooms=(3, 5)))
    train(config, tmp_path, progress=False, stop_at=1)
    checkpoint = tmp_path / "checkpoint.pt"
    net, meta = load_inference_net(checkpoint)
    model, torch_meta = load_weights(checkpoint)
    assert meta == torch_meta and meta["iteration"] == 1
    coords, features = _bed_voxels(net.config)
    with torch.no_grad():
        expected = inference_model(model)(sparse.SparseTensor(torch.from_numpy(features),
                                                             torch.from_numpy(coords))).numpy()
    np.testing.assert_allclose(net(coords, features), expected, atol=2e-5 * np.abs(expected).max())


def test_a_file_that_holds_no_weights_is_refused(tmp_path):
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a zip at all")
    with pytest.raises(ValueError, match="not a mushroom-pose weights file"):
        load_inference_net(garbage)
    foreign = tmp_path / "foreign.pt"
    torch.save({"model": {"w": torch.zeros(2)}, "hook": pickle.loads}, foreign)  # a callable no weights hold
    with pytest.raises(pickle.UnpicklingError, match="pickle.loads is no part of a weights file"):
        read_payload(foreign)
    with pytest.raises(ValueError, match="not a mushroom-pose weights file"):
        load_inference_net(foreign)
    # a tensor that claims more elements than its storage holds is refused, not read from beyond it
    torch.save({"w": torch.zeros(4)}, tmp_path / "short.pt")
    with zipfile.ZipFile(tmp_path / "short.pt") as archive:
        entries = {name: archive.read(name) for name in archive.namelist()}
    pickled = next(name for name in entries if name.endswith("data.pkl"))
    assert entries[pickled].count(b"K\x04\x85") == 1  # the size tuple (4,) as pickled
    entries[pickled] = entries[pickled].replace(b"K\x04\x85", b"M\x00\x01\x85")  # (256,)
    with zipfile.ZipFile(tmp_path / "long.pt", "w") as archive:
        for name, data in entries.items():
            archive.writestr(name, data)
    with pytest.raises(ValueError):
        read_payload(tmp_path / "long.pt")
    # weights that do not fit their recorded network (its input: no normals, no offsets)
    model = _randomised(NETWORK_PRESETS["slim-no"])
    save_weights(model, tmp_path / "misfit.pt")
    payload = torch.load(tmp_path / "misfit.pt", weights_only=False)
    payload["network"] = {**payload["network"], "normals": False, "offsets": False}
    torch.save(payload, tmp_path / "misfit.pt")
    with pytest.raises(ValueError, match="not a mushroom-pose weights file"):
        load_inference_net(tmp_path / "misfit.pt")
    with pytest.raises(FileNotFoundError):
        load_inference_net(tmp_path / "missing.pt")
    diverged = _randomised(NETWORK_PRESETS["slim-no"])
    with torch.no_grad():
        diverged.conv1.weight[0, 0, 0] = float("nan")
    save_weights(diverged, tmp_path / "nan.pt")
    with pytest.raises(ValueError, match="not finite"):
        load_inference_net(tmp_path / "nan.pt")


def test_voxel_normals_are_those_open3d_estimates():
    """The network's normal input, fitted here without Open3D, is Open3D's hybrid-search estimate turned
    to +z, on a bed's voxels and on isolated ones (which get +z)."""
    import open3d as o3d

    config = NETWORK_PRESETS["slim-no"]
    scene = generate_scene(4, SceneConfig(mushrooms=(8, 8)))
    _, _, centroids = network_input(1.2 * scene.points, config.voxel)
    centroids = np.vstack([centroids, [[1.0, 1.0, 1.0], [1.0, 1.0, 1.001], [2.0, 2.0, 2.0]]])
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(centroids))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * config.voxel, max_nn=16))
    expected = np.asarray(cloud.normals, np.float32)
    expected *= np.where(expected[:, 2:3] < 0, -1.0, 1.0).astype(np.float32)
    got = _oriented_normals(config, centroids)
    assert got.dtype == np.float32
    assert np.abs(got - expected).max() < 1e-5
    assert np.array_equal(got[-3:], np.float32([[0, 0, 1]] * 3))


def test_detect_finds_the_same_caps_with_either_network():
    """The shipped model's caps on a bed, read twice, through the torch network and through its numpy
    form: the same caps, equal to float32 round-off of the network's outputs."""
    net, _ = load_inference_net(DEFAULT_WEIGHTS)
    model, _ = load_weights(DEFAULT_WEIGHTS)
    scene = generate_scene(11, SceneConfig(mushrooms=(8, 8)))
    ours = detect_points(net, scene.points, readings=2).caps
    theirs = detect_points(model, scene.points, readings=2).caps
    assert len(ours) == len(theirs) == 8  # measured: all 8 found
    np.testing.assert_allclose(ours.centers, theirs.centers, atol=1e-6)
    np.testing.assert_allclose(ours.radii, theirs.radii, atol=1e-5)
    np.testing.assert_allclose(ours.scores, theirs.scores, atol=1e-5)
    np.testing.assert_allclose(ours.rotations, theirs.rotations, atol=1e-3)
