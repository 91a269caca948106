"""Instances: collapsed centres group into caps, small and low-existence groups are dropped."""

import numpy as np

from perception.instances import ClusterConfig, cluster


def blobs(rng, centres, sizes, spread):
    return np.concatenate([c + rng.normal(0, spread, (n, 3)) for c, n in zip(centres, sizes)])


def test_meanshift_separates_collapsed_caps_and_orders_by_size():
    rng = np.random.default_rng(0)
    centres = np.array([[0.0, 0.0, 0.0], [0.03, 0.0, 0.0], [0.0, 0.05, 0.01]])
    collapsed = blobs(rng, centres, [30, 60, 45], 0.0015)
    points = collapsed + rng.normal(0, 0.01, collapsed.shape)
    labels = cluster(points, collapsed, np.ones(len(points)), 0.0045)
    truth = np.repeat([2, 0, 1], [30, 60, 45])
    np.testing.assert_array_equal(labels, truth)


def test_low_existence_and_tiny_clusters_are_not_caps():
    rng = np.random.default_rng(1)
    collapsed = blobs(rng, [[0, 0, 0], [0.1, 0, 0]], [40, 3], 0.001)
    existence = np.ones(len(collapsed))
    existence[:10] = 0.2
    labels = cluster(collapsed, collapsed, existence, 0.0045)
    assert np.all(labels[:10] == -1) and np.all(labels[10:40] == 0) and np.all(labels[40:] == -1)


def test_dbscan_splits_caps_separated_by_a_gap():
    rng = np.random.default_rng(2)
    a = rng.uniform(-0.01, 0.01, (80, 3)) * [1, 1, 0.2]
    b = a + [0.04, 0, 0]
    points = np.concatenate([a, b])
    labels = cluster(points, points, np.ones(len(points)), 0.0045, ClusterConfig(method="dbscan"))
    assert len(set(labels[:80])) == 1 and len(set(labels[80:])) == 1 and labels[0] != labels[-1]


def test_nothing_above_threshold_gives_no_instances():
    points = np.random.default_rng(3).normal(size=(50, 3))
    assert np.all(cluster(points, points, np.zeros(50), 0.0045) == -1)
