"""The same work on a local Ray (``ray.init(num_cpus=2)``) and in this process gives the same results:
replaying sessions, generating beds, evaluating. Needs the ray extra: run with ``-m ray``."""

from pathlib import Path

import numpy as np
import pytest

ray = pytest.importorskip("ray")
pytestmark = pytest.mark.ray

RECORDINGS = Path(__file__).resolve().parents[1] / "recordings"


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def test_replaying_three_sessions_on_ray_matches_the_local_run_and_a_corrupt_one_is_one_failed_row(
        tmp_path, local_ray):
    from perception.weights import DEFAULT_WEIGHTS
    from pipeline.check import Tolerances
    from pipeline.farm import FarmJob, replay_sessions
    from pipeline.replay import ReplayOptions

    corrupt = tmp_path / "corrupt.mcap"
    corrupt.write_bytes((RECORDINGS / "single-view.mcap").read_bytes()[:4000])
    sessions = [RECORDINGS / "single-view.mcap", RECORDINGS / "two-cameras.mcap", corrupt,
                RECORDINGS / "dense-bed.mcap"]
    outcomes = {}
    for use_ray in (False, True):
        job = FarmJob(str(DEFAULT_WEIGHTS), str(tmp_path / f"out-{use_ray}"), ReplayOptions(), Tolerances())
        outcomes[use_ray] = replay_sessions(sessions, job, use_ray=use_ray)
    for local, remote in zip(outcomes[False], outcomes[True]):
        assert (local.session, local.caps, local.changes, local.error) == \
            (remote.session, remote.caps, remote.changes, remote.error)
    assert [o.error is None for o in outcomes[True]] == [True, True, False, True]
    assert all(o.passed for o in outcomes[True] if o.error is None)
    detections = [(tmp_path / f"out-{use_ray}" / "000-single-view" / "detections.json").read_text()
                  for use_ray in (False, True)]
    assert detections[0] == detections[1]


def test_beds_generated_on_ray_are_the_local_beds(local_ray):
    from perception.synthetic.dataset import generate_many
    from perception.synthetic.scene import SceneConfig

    config = SceneConfig(mushrooms=(5, 8))
    local = list(generate_many([3, 4, 5], config, progress=False))
    remote = list(generate_many([3, 4, 5], config, progress=False, use_ray=True))
    for a, b in zip(local, remote):
        assert np.array_equal(a.points, b.points) and np.array_equal(a.centers, b.centers)
        assert np.array_equal(a.instance, b.instance)


def test_evaluation_on_ray_gives_the_local_metrics(local_ray):
    import torch

    from perception.evaluate import evaluate_on_scenes

    from perception.weights import DEFAULT_WEIGHTS
    from perception.synthetic.dataset import load_preset
    from perception.weights import load_weights

    model, _ = load_weights(DEFAULT_WEIGHTS)
    scenes = load_preset("val50", progress=False, limit=3)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as in a one-CPU Ray task: the same float sums
    try:
        local = evaluate_on_scenes(model, scenes)
    finally:
        torch.set_num_threads(threads)
    remote = evaluate_on_scenes(model, scenes, use_ray=True)
    for method in local:
        assert local[method].as_dict() == pytest.approx(remote[method].as_dict(), nan_ok=True, rel=1e-12)


def test_a_run_trained_on_beds_made_by_ray_tasks_is_the_local_run(tmp_path, local_ray, monkeypatch):
    import torch

    from perception.network import NETWORK_PRESETS, NetworkConfig
    from perception.synthetic.scene import SceneConfig
    from perception.train import TrainConfig, train
    from perception.weights import load_weights

    monkeypatch.setitem(NETWORK_PRESETS, "tiny", NetworkConfig(channels=(8, 8, 8, 8), up_channels=(8, 8, 8, 8),
                                                      first_kernel=3, head_hidden=(8, 8)))
    config = TrainConfig(iterations=3, network="tiny", checkpoint_every=3, validation_scenes=0,
                         scene=SceneConfig(mushrooms=(3, 5)), queue_size=2)
    local = train(config, tmp_path / "local", progress=False)
    remote = train(config, tmp_path / "ray", progress=False, ray_address="local")
    for a, b in zip(load_weights(local)[0].state_dict().values(), load_weights(remote)[0].state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert (tmp_path / "local" / "history.csv").read_text().count("\n") == 4


def test_a_cluster_that_is_not_there_is_one_line_at_once(tmp_path):
    import socket
    import subprocess
    import sys

    with socket.socket() as probe:  # a port nothing listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    result = subprocess.run([sys.executable, "-m", "pipeline.cli", "synth", "--scenes", "1", "--out", str(tmp_path),
                             "--quiet", "--ray", f"127.0.0.1:{port}"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 1
    assert result.stderr.strip().splitlines() == [f"mushroom-pose synth: error: cannot reach the Ray cluster at "
                                                  f"127.0.0.1:{port}: Connection refused"]
