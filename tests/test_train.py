"""Training: targets agree with the encoding, the loss is the paper's, resume continues exactly."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from perception.model import MushroomNet
from perception.network import INFERENCE_ZOOM, LENGTH_UNIT, NETWORK_PRESETS, NetworkConfig
from perception.sparse import SparseTensor
from perception.synthetic.scene import SceneConfig
from perception.train import (TrainConfig, TrainingError, augmented_sample, iteration_seed, loss_terms, scene_config,
                              train, voxel_targets)
from perception.weights import UNRECORDED_ZOOM, load_weights

TINY = NetworkConfig(channels=(8, 8, 8, 8), up_channels=(8, 8, 8, 8), first_kernel=3, head_hidden=(8, 8))
SMALL_SCENES = SceneConfig(mushrooms=(3, 5))


@pytest.fixture
def tiny_network(monkeypatch):
    monkeypatch.setitem(NETWORK_PRESETS, "tiny", TINY)
    return "tiny"


def test_augmented_samples_are_deterministic_and_consistent():
    config = TrainConfig(scene=SMALL_SCENES)
    a, b = augmented_sample(config, 3), augmented_sample(config, 3)
    np.testing.assert_array_equal(a["points"], b["points"])
    assert not np.array_equal(a["points"], augmented_sample(config, 4)["points"])
    cap = a["existence"] > 0
    assert cap.any() and np.all(a["residual"][~cap] == 0) and np.all(a["orientation"][~cap] == 0)
    assert np.all((a["orientation"] >= 0) & (a["orientation"] <= 1))
    # every point of one cap instance points at the same centre
    centres = a["points"].astype(np.float64) + a["residual"]
    for k in np.unique(a["instance"][a["instance"] >= 0]):
        assert np.ptp(centres[a["instance"] == k], axis=0).max() < 1e-5


def test_a_fused_share_of_the_beds_are_scans_and_the_rest_stay_as_they_were():
    def fused(config):
        return np.array([scene_config(config, iteration_seed(config.seed, i)).visibility == "fused"
                         for i in range(400)])

    assert not fused(TrainConfig(scene=SMALL_SCENES)).any()
    half = TrainConfig(scene=SMALL_SCENES, fused_share=0.5)
    chosen = fused(half)
    assert 0.4 < chosen.mean() < 0.6  # binomial(400, 0.5): outside this about once in 10^4 runs
    # a bed the share leaves alone is the bed the run without it draws, point for point
    kept = int(np.flatnonzero(~chosen)[0])
    np.testing.assert_array_equal(augmented_sample(half, kept)["points"],
                                  augmented_sample(TrainConfig(scene=SMALL_SCENES), kept)["points"])
    scan = scene_config(half, iteration_seed(half.seed, int(np.flatnonzero(chosen)[0])))
    assert (scan.visibility, scan.views, scan.mushrooms) == ("fused", (2, 6), SMALL_SCENES.mushrooms)
    assert fused(TrainConfig(scene=SMALL_SCENES, fused_share=1.0)).all()


def _row_of_point(coords: torch.Tensor, points: np.ndarray, voxel: float) -> np.ndarray:
    """The row of ``coords`` (batch, x, y, z) holding each point's voxel, found independently of the code under test."""
    voxel_of = np.floor(points.astype(np.float64) / voxel).astype(np.int64)
    rows = {tuple(c): i for i, c in enumerate(coords[:, 1:].tolist())}
    return np.array([rows[tuple(v)] for v in voxel_of.tolist()])


def test_voxel_targets_are_point_targets_averaged_per_voxel():
    sample = augmented_sample(TrainConfig(scene=SMALL_SCENES), 1)
    coords, existence, residual, orientation, centroids, _ = voxel_targets(sample, 0.0045)
    assert centroids.shape == (len(coords), 3)
    voxel_of = np.floor(sample["points"].astype(np.float64) / 0.0045).astype(np.int64)
    _, first, inverse, counts = np.unique(voxel_of, axis=0, return_index=True, return_inverse=True, return_counts=True)
    assert len(coords) == len(first)
    single = np.flatnonzero((counts == 1) & (sample["existence"][first] > 0))
    row_of_point = _row_of_point(coords, sample["points"], 0.0045)
    for v in single[:50]:
        row = row_of_point[first[v]]
        assert existence[row] == 1
        np.testing.assert_allclose(residual[row].numpy() * LENGTH_UNIT, sample["residual"][first[v]], atol=1e-6)
        np.testing.assert_allclose(orientation[row].item(), sample["orientation"][first[v]], atol=1e-6)


def test_loss_is_bce_plus_weighted_mse():
    output = torch.tensor([[0.0, 1.0, 0.0, 0.0, 0.5], [2.0, 0.0, 0.0, 0.0, 0.0]])
    existence, residual, orientation = torch.tensor([1.0, 0.0]), torch.zeros(2, 3), torch.tensor([1.0, 0.0])
    terms = loss_terms(output, existence, residual, orientation, TrainConfig())
    bce = -(np.log(0.5) + np.log(1 - 1 / (1 + np.exp(-2.0)))) / 2
    assert terms["existence"].item() == pytest.approx(bce, rel=1e-6)
    assert terms["residual"].item() == pytest.approx(1.0 / 6, rel=1e-6)
    assert terms["orientation"].item() == pytest.approx(0.25 / 2, rel=1e-6)
    assert terms["total"].item() == pytest.approx(bce + 100 / 6 + 0.125, rel=1e-6)


def test_orientation_loss_on_caps_averages_over_cap_voxels_only():
    output = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.5], [0.0, 0.0, 0.0, 0.0, 0.3], [0.0, 0.0, 0.0, 0.0, 0.0]])
    existence, orientation = torch.tensor([1.0, 0.0, 1.0]), torch.tensor([1.0, 0.0, 0.2])
    config = TrainConfig(orientation_on_caps=True, weight_orientation=10.0)
    terms = loss_terms(output, existence, torch.zeros(3, 3), orientation, config)
    assert terms["orientation"].item() == pytest.approx((0.25 + 0.04) / 2, rel=1e-6)
    assert terms["total"].item() == pytest.approx(terms["existence"].item() + 10 * (0.25 + 0.04) / 2, rel=1e-6)


def test_cap_balance_gives_every_cap_the_same_total_weight():
    sample = augmented_sample(TrainConfig(scene=SMALL_SCENES), 2)
    coords, existence, _, _, _, cap_weight = voxel_targets(sample, 0.0045)
    row_of_point = _row_of_point(coords, sample["points"], 0.0045)
    instances = np.unique(sample["instance"][sample["instance"] >= 0])
    caps = [set(row_of_point[sample["instance"] == k].tolist()) for k in instances]
    assert len(caps) >= 3 and len({len(c) for c in caps}) > 1
    on_cap = (existence > 0).numpy()
    assert np.all(cap_weight.numpy()[~on_cap] == 0) and cap_weight[on_cap].mean().item() == pytest.approx(1.0, rel=1e-5)
    # a voxel belongs to the highest cap instance among its points; it weighs 1 / (that cap's voxels)
    cap_of_row = np.full(len(coords), -1)
    np.maximum.at(cap_of_row, row_of_point, sample["instance"])
    labels, voxels_per_cap = np.unique(cap_of_row[on_cap], return_counts=True)
    expected = on_cap.sum() / (len(labels) * voxels_per_cap[np.searchsorted(labels, cap_of_row[on_cap])])
    np.testing.assert_allclose(cap_weight[on_cap].numpy(), expected, rtol=1e-5)
    soil_only = {**sample, "existence": np.zeros_like(sample["existence"]),
                 "instance": np.full_like(sample["instance"], -1)}
    assert torch.count_nonzero(voxel_targets(soil_only, 0.0045)[5]) == 0


def test_cap_balanced_loss_averages_per_cap_then_over_caps():
    # voxels 0-2: a 3-voxel cap; voxel 3: a 1-voxel cap; voxel 4: soil
    output = torch.tensor([[0.0, 0, 0, 0, 0.5], [0.0, 0, 0, 0, 0.5], [0.0, 0, 0, 0, 0.5], [1.0, 0, 0, 0, 0.2],
                           [-1.0, 0, 0, 0, 0.9]])
    existence = torch.tensor([1.0, 1.0, 1.0, 1.0, 0.0])
    orientation = torch.tensor([0.4, 0.4, 0.4, 0.0, 0.0])
    cap_weight = torch.tensor([4 / 6, 4 / 6, 4 / 6, 4 / 2, 0.0])
    config = TrainConfig(cap_balance=True, weight_orientation=10.0)
    terms = loss_terms(output, existence, torch.zeros(5, 3), orientation, config, cap_weight)
    assert terms["orientation"].item() == pytest.approx((0.01 + 0.04) / 2, rel=1e-6)
    bce = lambda logit, target: -np.log(1 / (1 + np.exp(-logit))) if target else -np.log(1 - 1 / (1 + np.exp(-logit)))
    per_cap = [np.mean([bce(0.0, 1)] * 3), bce(1.0, 1)]
    # cap voxels carry the same total weight as without balancing (4), split evenly between the two caps
    assert terms["existence"].item() == pytest.approx((2 * sum(per_cap) + bce(-1.0, 0)) / 5, rel=1e-6)
    with pytest.raises(ValueError, match="cap weights"):
        loss_terms(output, existence, torch.zeros(5, 3), orientation, config)


def test_fine_tuning_starts_from_the_given_weights_and_adds_their_cost(tmp_path, tiny_network, monkeypatch):
    import hashlib
    import shutil

    base_config = TrainConfig(iterations=2, network=tiny_network, validation_scenes=0, scene=SMALL_SCENES)
    base = train(base_config, tmp_path / "base", progress=False)
    base_model, base_meta = load_weights(base)
    base_hash = hashlib.sha256(base.read_bytes()).hexdigest()
    init = tmp_path / "init.pt"
    shutil.copy(base, init)
    tuned_config = TrainConfig(**{**base_config.__dict__, "iterations": 2, "lr": 1e-12, "seed": 1,
                                  "init_weights": str(init)})
    assert train(tuned_config, tmp_path / "tuned", progress=False, stop_at=1) is None
    shutil.copy(tmp_path / "tuned" / "checkpoint.pt", init)  # the start file changes before the resume
    tuned_model, meta = load_weights(train(tuned_config, tmp_path / "tuned", resume=True, progress=False))
    fresh_model, _ = load_weights(train(TrainConfig(**{**tuned_config.__dict__, "init_weights": None}),
                                        tmp_path / "fresh", progress=False))
    weight = next(k for k, v in base_model.state_dict().items() if v.dim() == 3)  # the first sparse conv
    torch.testing.assert_close(tuned_model.state_dict()[weight], base_model.state_dict()[weight], rtol=0, atol=1e-6)
    assert not torch.allclose(fresh_model.state_dict()[weight], base_model.state_dict()[weight], atol=1e-3)
    assert meta["init"]["sha256"] == base_hash and meta["init"]["total_iterations"] == 2
    assert meta["total_iterations"] == 4
    assert meta["total_train_seconds"] == pytest.approx(meta["train_seconds"] + base_meta["train_seconds"])
    monkeypatch.setitem(NETWORK_PRESETS, "other", NetworkConfig(**{**TINY.__dict__, "channels": (8, 8, 8, 16)}))
    with pytest.raises(ValueError, match="different network"):
        train(TrainConfig(**{**tuned_config.__dict__, "network": "other", "init_weights": str(base)}),
              tmp_path / "other", progress=False)


def test_resume_continues_exactly(tmp_path, tiny_network):
    config = TrainConfig(iterations=4, network=tiny_network, checkpoint_every=2, validation_scenes=0,
                         scene=SMALL_SCENES, queue_size=2)
    straight = train(config, tmp_path / "straight", progress=False)
    assert train(config, tmp_path / "resumed", progress=False, stop_at=2) is None
    checkpoint = torch.load(tmp_path / "resumed" / "checkpoint.pt", weights_only=False)
    assert checkpoint["iteration"] == 2
    # the run keeps the zoom it started with, whatever the default is when it resumes
    torch.save({**checkpoint, "inference_zoom": 1.2}, tmp_path / "resumed" / "checkpoint.pt")
    resumed = train(config, tmp_path / "resumed", resume=True, progress=False)
    assert load_weights(resumed)[0].inference_zoom == 1.2
    model_a, meta = load_weights(straight)
    model_b, _ = load_weights(resumed)
    for a, b in zip(model_a.state_dict().values(), model_b.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert meta["iterations"] == 4 and meta["train_seconds"] > 0
    assert (meta["total_iterations"], meta["total_train_seconds"]) == (4, meta["train_seconds"])
    history = (tmp_path / "resumed" / "history.csv").read_text().splitlines()
    assert [line.split(",")[0] for line in history[1:]] == ["1", "2", "3", "4"]


def test_resume_after_an_interrupt_keeps_one_history_row_per_iteration(tmp_path, tiny_network):
    """A run killed between checkpoints has written rows the resumed run trains again: history.csv
    keeps each iteration once, the resumed run's row (the interrupted run's rows are stood in for by
    rows of a marked learning rate)."""
    config = TrainConfig(iterations=4, network=tiny_network, checkpoint_every=2, validation_scenes=0,
                         scene=SMALL_SCENES, queue_size=2)
    train(config, tmp_path, progress=False, stop_at=2)
    with open(tmp_path / "history.csv", "a") as history:
        history.write("3,-1,0,0,0,0,0,,,,\n")  # written after checkpoint 2 by a run that then died
    train(config, tmp_path, resume=True, progress=False)
    rows = [line.split(",") for line in (tmp_path / "history.csv").read_text().splitlines()[1:]]
    assert [row[0] for row in rows] == ["1", "2", "3", "4"]
    assert all(row[1] != "-1" for row in rows)


def test_resume_with_other_flags_is_refused(tmp_path, tiny_network):
    config = TrainConfig(iterations=2, network=tiny_network, validation_scenes=0, scene=SMALL_SCENES)
    train(config, tmp_path, progress=False, stop_at=1)
    with pytest.raises(ValueError, match=r"different configuration \(lr: 0.001 there, 0.5 here\)"):
        train(TrainConfig(**{**config.__dict__, "lr": 0.5}), tmp_path, resume=True, progress=False)
    with pytest.raises(ValueError, match=r"\(scene.spacing: [0-9.]+ there, 0.0051 here\)"):
        train(replace(config, scene=replace(config.scene, spacing=0.0051)), tmp_path, resume=True, progress=False)


def test_resume_needs_a_readable_checkpoint(tmp_path, tiny_network):
    config = TrainConfig(iterations=2, network=tiny_network, validation_scenes=0, scene=SMALL_SCENES)
    with pytest.raises(ValueError, match="no checkpoint to resume"):
        train(config, tmp_path / "typo", resume=True, progress=False)
    assert not (tmp_path / "typo").exists()
    train(config, tmp_path / "run", progress=False)
    checkpoint = tmp_path / "run" / "checkpoint.pt"
    checkpoint.write_bytes(checkpoint.read_bytes()[:1000])
    with pytest.raises(ValueError, match="not a readable checkpoint"):
        train(config, tmp_path / "run", resume=True, progress=False)
    (tmp_path / "run" / "model.pt").replace(checkpoint)
    with pytest.raises(ValueError, match="not a training checkpoint"):
        train(config, tmp_path / "run", resume=True, progress=False)


def test_a_diverging_run_stops_with_an_error_and_writes_no_model(tmp_path, tiny_network):
    config = TrainConfig(iterations=6, lr=1e30, network=tiny_network, validation_scenes=0, scene=SMALL_SCENES,
                         queue_size=2)
    with pytest.raises(TrainingError, match="no longer finite"):
        train(config, tmp_path, progress=False)
    assert not (tmp_path / "model.pt").exists()


def test_a_dead_scene_generator_stops_the_run(tmp_path, tiny_network, monkeypatch):
    import perception.train as training

    def broken(config, iteration):
        raise RuntimeError("no scene")

    monkeypatch.setattr(training, "augmented_sample", broken)  # the forked generator inherits it
    config = TrainConfig(iterations=2, network=tiny_network, validation_scenes=0, scene=SMALL_SCENES)
    with pytest.raises(TrainingError, match="scene generator stopped"):
        train(config, tmp_path, progress=False)


def test_a_stuck_scene_generator_stops_the_run(tmp_path, tiny_network, monkeypatch):
    import threading

    import perception.train as training

    never = threading.Event()
    monkeypatch.setattr(training, "augmented_sample", lambda config, iteration: never.wait())
    monkeypatch.setattr(training, "SAMPLE_PATIENCE_S", 5.0)
    config = TrainConfig(iterations=2, network=tiny_network, validation_scenes=0, scene=SMALL_SCENES)
    with pytest.raises(TrainingError, match="is stuck"):
        train(config, tmp_path, progress=False)


def test_a_device_torch_cannot_use_is_refused(tmp_path, tiny_network):
    config = TrainConfig(iterations=2, network=tiny_network, validation_scenes=0, scene=SMALL_SCENES)
    with pytest.raises(ValueError, match="unknown device"):
        train(config, tmp_path, device="gpu", progress=False)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA"):
            train(config, tmp_path, device="cuda", progress=False)


def test_network_runs_on_any_device_and_predicts_five_values():
    model = MushroomNet(TINY).eval()
    coords = torch.tensor([[0, x, y, z] for x in range(4) for y in range(3) for z in range(2)])
    out = model(SparseTensor(torch.ones(len(coords), 1), coords))
    assert out.shape == (len(coords), 5)
    if torch.cuda.is_available():
        cuda_out = model.cuda()(SparseTensor(torch.ones(len(coords), 1, device="cuda"), coords.cuda()))
        assert cuda_out.shape == (len(coords), 5)


def test_batch_norms_folded_for_inference_give_the_same_outputs_and_follow_training():
    from perception.model import fold_batch_norms, inference_model
    from perception.sparse import SparseBatchNorm

    torch.manual_seed(3)
    model = MushroomNet(replace(NETWORK_PRESETS["slim-no"], channels=(8, 8, 8, 8), up_channels=(8, 8, 8, 8)))
    norms = [m for m in model.modules() if isinstance(m, SparseBatchNorm)]
    with torch.no_grad():
        for norm in norms:  # statistics and affine terms far from a fresh norm's identity
            norm.running_mean.uniform_(-1, 1), norm.running_var.uniform_(0.2, 3)
            norm.weight.uniform_(0.5, 2), norm.bias.uniform_(-1, 1)
    coords = torch.unique(torch.randint(0, 12, (300, 3)), dim=0)
    coords = torch.cat([torch.zeros(len(coords), 1, dtype=torch.int64), coords], 1)
    features = torch.randn(len(coords), model.config.in_channels)
    with torch.no_grad():
        expected = model.eval()(SparseTensor(features, coords))
        folded = fold_batch_norms(model)
        assert not any(isinstance(m, SparseBatchNorm) for m in folded.modules()) and len(norms) == 21
        torch.testing.assert_close(folded(SparseTensor(features, coords)), expected, rtol=1e-5, atol=1e-5)
        assert inference_model(model) is inference_model(model)
        norms[0].running_mean.add_(0.5)  # what a training step does to the statistics
        moved = model(SparseTensor(features, coords))
        assert not torch.allclose(moved, expected)
        torch.testing.assert_close(inference_model(model)(SparseTensor(features, coords)), moved, rtol=1e-5, atol=1e-5)


def test_normal_features_follow_the_surface_and_point_up():
    from perception.cap import cap_rotation
    from perception.network import voxel_features

    rng = np.random.default_rng(0)
    rotation = cap_rotation(0.4, -0.3)
    plane = np.column_stack([rng.uniform(-0.05, 0.05, (2000, 2)), np.zeros(2000)]) @ rotation.T
    features = voxel_features(NetworkConfig(normals=True), plane)
    assert features.shape == (2000, 4) and np.all(features[:, 0] == 1)
    np.testing.assert_allclose(features[:, 1:], np.tile(rotation[:, 2], (2000, 1)), atol=1e-4)
    assert voxel_features(NetworkConfig(), plane).shape == (2000, 1)


def test_offset_features_place_each_centroid_inside_its_voxel():
    from perception.network import voxel_features

    config = NetworkConfig(offsets=True)
    # a voxel's lower corner maps to -1, its middle to 0 and a point just below the next voxel to almost 1
    voxel = config.voxel
    centroids = np.array([[3.0005, -1.9995, 0.0005], [3.5, -1.5, 0.5], [3.999, -1.001, 0.999]]) * voxel
    features = voxel_features(config, centroids)
    assert features.shape == (3, 4) and np.all(features[:, 0] == 1)
    np.testing.assert_allclose(features[:, 1:], [[-0.999, -0.999, -0.999], [0, 0, 0], [0.998, 0.998, 0.998]], atol=1e-5)
    both = voxel_features(NetworkConfig(normals=True, offsets=True), np.random.default_rng(1).normal(size=(50, 3)))
    assert both.shape == (50, 7) and np.all((both[:, 4:] >= -1) & (both[:, 4:] < 1))


def test_training_with_normal_features_runs(tmp_path, monkeypatch):
    monkeypatch.setitem(NETWORK_PRESETS, "tiny-n", NetworkConfig(**{**TINY.__dict__, "normals": True}))
    config = TrainConfig(iterations=2, network="tiny-n", validation_scenes=0, scene=SMALL_SCENES)
    model, _ = load_weights(train(config, tmp_path, progress=False))
    assert model.conv1.weight.shape[1] == 4


def test_a_time_budget_stops_with_a_resumable_checkpoint(tmp_path, tiny_network):
    config = TrainConfig(iterations=50, network=tiny_network, validation_scenes=0, scene=SMALL_SCENES)
    assert train(config, tmp_path, progress=False, max_minutes=1e-6) is None
    assert torch.load(tmp_path / "checkpoint.pt", weights_only=False)["iteration"] < 50


@pytest.fixture
def validation_zooms(monkeypatch):
    """The zoom of every model that training validates (on no scenes: only the reading matters)."""
    import perception.train as training

    read_at = []

    def validate(model, scenes):
        read_at.append(model.inference_zoom)
        return dict.fromkeys(("ap25", "ap50", "angle_deg", "scale_err"), 0.0)

    monkeypatch.setattr(training, "validate", validate)
    monkeypatch.setattr("perception.synthetic.dataset.load_preset", lambda *args, **kwargs: [])
    return read_at


def test_the_zoom_asked_for_is_recorded_in_the_weights_and_read_at_by_validation(tmp_path, tiny_network,
                                                                                 validation_zooms):
    config = TrainConfig(iterations=2, network=tiny_network, validate_every=1, validation_scenes=1,
                         scene=SMALL_SCENES, zoom=1.2)
    assert load_weights(train(config, tmp_path / "zoomed", progress=False))[0].inference_zoom == 1.2
    assert validation_zooms == [1.2, 1.2]
    plain = TrainConfig(**{**config.__dict__, "zoom": None, "validation_scenes": 0})
    assert load_weights(train(plain, tmp_path / "plain", progress=False))[0].inference_zoom == \
        INFERENCE_ZOOM


def test_a_resumed_averaging_run_validates_and_ships_at_the_zoom_its_checkpoint_records(tmp_path, tiny_network,
                                                                                       validation_zooms):
    config = TrainConfig(iterations=3, network=tiny_network, checkpoint_every=1, validate_every=1,
                         validation_scenes=1, scene=SMALL_SCENES, average_from=0.3)
    train(config, tmp_path, progress=False, stop_at=2)
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    del state["inference_zoom"]  # a checkpoint that records no zoom is read at UNRECORDED_ZOOM
    torch.save(state, tmp_path / "checkpoint.pt")
    validation_zooms.clear()
    weights = train(config, tmp_path, resume=True, progress=False)
    assert validation_zooms == [UNRECORDED_ZOOM] and load_weights(weights)[0].inference_zoom == UNRECORDED_ZOOM
    assert UNRECORDED_ZOOM != INFERENCE_ZOOM


def test_a_checkpoint_from_before_a_new_flag_resumes_with_its_default(tmp_path, tiny_network):
    config = TrainConfig(iterations=2, network=tiny_network, validation_scenes=0, scene=SMALL_SCENES)
    train(config, tmp_path, progress=False, stop_at=1)
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    del state["train_config"]["orientation_on_caps"], state["train_config"]["init_weights"]
    torch.save(state, tmp_path / "checkpoint.pt")
    assert train(config, tmp_path, resume=True, progress=False) is not None
    with pytest.raises(ValueError, match="different configuration"):
        train(TrainConfig(**{**config.__dict__, "orientation_on_caps": True}), tmp_path, resume=True,
              progress=False)


def test_weight_averaging_ships_the_mean_of_the_last_steps_and_resumes_exactly(tmp_path, tiny_network):
    plain = TrainConfig(iterations=4, network=tiny_network, checkpoint_every=1, validation_scenes=0,
                        scene=SMALL_SCENES, queue_size=2)
    steps = []
    for stop in (2, 3, 4):
        train(plain, tmp_path / "plain", resume=stop > 2, progress=False, stop_at=stop)
        steps.append(torch.load(tmp_path / "plain" / "checkpoint.pt", weights_only=False)["model"])
    averaging = replace(plain, average_from=0.5)
    straight, _ = load_weights(train(averaging, tmp_path / "straight", progress=False))
    assert train(averaging, tmp_path / "resumed", progress=False, stop_at=3) is None
    resumed, _ = load_weights(train(averaging, tmp_path / "resumed", resume=True, progress=False))
    averaged_any = False
    for name, value in straight.state_dict().items():
        if not value.is_floating_point():
            continue
        mean = (steps[1][name] + steps[2][name]) / 2
        torch.testing.assert_close(value, mean, rtol=0, atol=1e-6)
        torch.testing.assert_close(resumed.state_dict()[name], value, rtol=0, atol=0)
        averaged_any |= not torch.allclose(mean, steps[2][name], atol=1e-6)
    assert averaged_any


def test_averaging_runs_from_one_start_gives_their_mean_and_counts_the_start_once(tmp_path, tiny_network, capsys):
    from pipeline.cli import main
    from perception.weights import average_weights

    base_config = TrainConfig(iterations=2, network=tiny_network, validation_scenes=0, scene=SMALL_SCENES)
    base = train(base_config, tmp_path / "base", progress=False)
    tuned = [train(TrainConfig(**{**base_config.__dict__, "seed": seed, "init_weights": str(base)}),
                   tmp_path / f"tuned{seed}", progress=False) for seed in (1, 2)]
    metas = [load_weights(path)[1] for path in (base, *tuned)]
    states = [load_weights(path)[0].state_dict() for path in tuned]
    model, meta = average_weights(tuned)
    for name, value in model.state_dict().items():
        if value.is_floating_point():
            torch.testing.assert_close(value, (states[0][name] + states[1][name]) / 2, rtol=0, atol=1e-7)
    weight = next(k for k, v in states[0].items() if v.dim() == 3)
    assert not torch.equal(states[0][weight], states[1][weight])
    assert meta["total_iterations"] == 6 and len(meta["runs"]) == 3
    assert meta["total_train_seconds"] == pytest.approx(sum(m["train_seconds"] for m in metas))
    assert average_weights([base, tuned[0]])[1]["total_iterations"] == 4  # a start and a run from it

    out = tmp_path / "soup.pt"
    assert main(["average", *map(str, tuned), "--out", str(out)]) == 0
    soup, soup_meta = load_weights(out)
    assert soup_meta["total_train_seconds"] == pytest.approx(meta["total_train_seconds"])
    fine_tuned_soup = train(TrainConfig(**{**base_config.__dict__, "seed": 3, "init_weights": str(out)}),
                            tmp_path / "after", progress=False)
    assert load_weights(fine_tuned_soup)[1]["total_iterations"] == 8

    separate = train(TrainConfig(**{**base_config.__dict__, "seed": 9}), tmp_path / "separate", progress=False)
    capsys.readouterr()
    assert main(["average", str(tuned[0]), str(separate), "--out", str(tmp_path / "bad.pt")]) == 2
    assert "not trained from one start" in capsys.readouterr().err
    assert not (tmp_path / "bad.pt").exists()


OVERFIT = NetworkConfig(channels=(16, 16, 16, 16), up_channels=(16, 16, 16, 16), first_kernel=3, head_hidden=(16, 16))
"""Small enough for 300 steps in about 25 s on one thread, big enough to learn one bed by heart."""


def test_training_learns_one_bed_by_heart(tmp_path, monkeypatch):
    """300 steps of ``train`` on one fixed bed (6 caps on 0.25 m, no augmentation): each loss term falls
    by a good factor and the model it writes finds the bed's caps.

    Measured with run seeds 0-3 (bed and initial weights), the mean of the last 10 losses against the
    first 10: total 25.1, 36.0, 19.7, 27.5 times lower; existence 33, 26, 48, 36; residual 24, 45, 11, 25;
    orientation 8.8, 5.6, 3.2, 21. Bounds: half the worst, rounded down. The model found 6 caps on its
    bed each time (not always well placed: a few hundred steps fit the losses, not yet the poses).
    It takes 26-37 s on the two shared cores (5 s of start-up, then 75 ms a step), at the edge of what
    the default run holds; 200 steps saved only 5 s and let the losses fall 10-16 times."""
    import csv

    import perception.train as training
    from perception.detect import detect_points

    monkeypatch.setitem(NETWORK_PRESETS, "overfit", OVERFIT)
    config = TrainConfig(iterations=300, lr=3e-3, milestones=(0.8,), network="overfit", validation_scenes=0,
                         checkpoint_every=1000, rotate_z=False, tilt_deg=0.0, noise=0.0, point_dropout=(0.0, 0.0),
                         scale_jitter=(1.0, 1.0), scene=SceneConfig(mushrooms=(6, 6), bed_size=0.25))
    bed = augmented_sample(config, 0)
    assert (np.unique(bed["instance"]) >= 0).sum() == 6
    monkeypatch.setattr(training, "augmented_sample", lambda config, iteration: bed)  # the forked generator inherits it
    weights = train(config, tmp_path, progress=False)  # one torch thread (conftest.py)
    with open(tmp_path / "history.csv") as file:
        rows = list(csv.DictReader(file))
    assert len(rows) == 300
    for term, factor in {"total": 9.0, "existence": 12.0, "residual": 5.0, "orientation": 1.5}.items():
        losses = np.array([float(row[term]) for row in rows])
        fell = losses[:10].mean() / losses[-10:].mean()
        assert fell >= factor, f"the {term} loss fell only {fell:.1f} times in 300 steps on one bed"
    model, _ = load_weights(weights)
    assert len(detect_points(model, bed["points"].astype(np.float64), zoom=1.0).caps) == 6


def test_resume_goes_on_with_the_runs_own_flags(tmp_path, tiny_network):
    """``train --out RUN --resume`` with none of the run's flags: the same weights as the run straight
    through; a flag given again with its own value is fine."""
    config = TrainConfig(iterations=3, network=tiny_network, validation_scenes=0, scene=SMALL_SCENES, lr=0.002,
                         checkpoint_every=1, queue_size=2)
    straight = train(config, tmp_path / "straight", progress=False)
    assert train(config, tmp_path / "resumed", progress=False, stop_at=2) is None
    resumed = train(TrainConfig(), tmp_path / "resumed", resume=True, progress=False)
    for a, b in zip(load_weights(straight)[0].state_dict().values(), load_weights(resumed)[0].state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert load_weights(resumed)[1]["train_config"]["lr"] == 0.002
    again = TrainConfig(lr=0.002, network=tiny_network)
    assert train(again, tmp_path / "resumed", resume=True, progress=False) is not None


def test_stereo_share_sends_that_share_of_the_scanned_beds_through_the_oak_model():
    from capture.virtual import SENSOR_MODELS
    from perception.train import scene_config

    def sensors(config):
        chosen = [scene_config(config, seed) for seed in range(400)]
        return [c.sensor for c in chosen if c.visibility == "fused"]

    mixed = sensors(TrainConfig(fused_share=0.5, stereo_share=0.5))
    assert 150 < len(mixed) < 250 and 0.35 < np.mean([s == SENSOR_MODELS["oak"] for s in mixed]) < 0.65
    assert not any(s == SENSOR_MODELS["oak"] for s in sensors(TrainConfig(fused_share=0.5)))
    with pytest.raises(ValueError, match="give a fused_share too"):
        TrainConfig(stereo_share=0.5)
