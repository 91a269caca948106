"""Perception in a process of its own (live runs): the same caps as in this process, the model's
errors raised here, and a child that dies is one clear error, not a hang."""

import numpy as np
import pytest

from perception.detect import detect_points
from perception.instances import ClusterConfig
from pipeline.perception_process import PerceptionProcess, PerceptionProcessError


@pytest.fixture(scope="module")
def model():
    from perception.weights import DEFAULT_WEIGHTS
    from perception.weights import load_weights

    return load_weights(DEFAULT_WEIGHTS)[0]


@pytest.fixture(scope="module")
def bed_points():
    from perception.synthetic.scene import SceneConfig, generate_scene

    return generate_scene(3, SceneConfig()).points


def test_the_process_finds_the_caps_this_process_finds(model, bed_points):
    here = detect_points(model, bed_points, ClusterConfig(), readings=3)  # not the default: it must reach the child
    worker = PerceptionProcess(model, threads=1)
    try:
        there = worker.detect(bed_points, ClusterConfig(), 3)
        again = worker.detect(bed_points[::2], ClusterConfig(), 1)
    finally:
        worker.close()
    assert len(here.caps) >= 5
    np.testing.assert_allclose(there.caps.centers, here.caps.centers, atol=1e-9)
    np.testing.assert_allclose(there.caps.rotations, here.caps.rotations, atol=1e-9)
    np.testing.assert_array_equal(there.point_labels, here.point_labels)
    assert len(again.point_labels) == len(bed_points[::2])


def test_an_error_of_the_model_is_raised_here(model):
    worker = PerceptionProcess(model, threads=1)
    try:
        far = np.full((200, 3), 1e6)  # beyond the network's voxel grid: detect_points refuses it
        with pytest.raises(ValueError, match="voxel grid"):
            worker.detect(far, ClusterConfig(), 1)
    finally:
        worker.close()


def test_a_child_that_dies_is_one_error(model, bed_points):
    worker = PerceptionProcess(model, threads=1)
    worker._process.kill()
    worker._process.join()
    with pytest.raises(PerceptionProcessError, match="perception process ended"):
        worker.detect(bed_points, ClusterConfig(), 1)
    worker.close()
