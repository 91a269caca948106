"""Instances: collapsed centres group into caps, small and low-existence groups are dropped."""

import numpy as np

from perception.instances import ClusterConfig, cluster, peak_seeds


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


def test_peak_seeds_keep_bins_that_outnumber_their_face_neighbours():
    bin_size = 0.01
    cells = {(0, 0, 0): 5, (1, 0, 0): 3, (2, 0, 0): 4, (0, 1, 1): 6, (5, 5, 5): 1}
    points = np.concatenate([np.tile(np.array(c, float) * bin_size, (n, 1)) for c, n in cells.items()])
    points += np.random.default_rng(4).uniform(-0.004, 0.004, points.shape)
    seeds = peak_seeds(points, bin_size, min_bin_freq=2)
    # (0,0,0) beats its face neighbour (1,0,0); (0,1,1) touches it only along an edge; (2,0,0) beats
    # (1,0,0); the lone point is below min_bin_freq
    expected = np.array([[0, 0, 0], [0, 1, 1], [2, 0, 0]], float) * bin_size
    np.testing.assert_allclose(seeds[np.lexsort(seeds.T[::-1])], expected, atol=1e-12)


def test_peak_and_bin_seeding_find_the_same_caps():
    rng = np.random.default_rng(5)
    centres = rng.uniform(-0.2, 0.2, (25, 3)) * [1, 1, 0.1]
    centres = centres[np.all(np.linalg.norm(centres[:, None] - centres[None], axis=2) + np.eye(25) > 0.03, 1)]
    collapsed = blobs(rng, centres, rng.integers(10, 80, len(centres)), 0.0015)
    peaks = cluster(collapsed, collapsed, np.ones(len(collapsed)), 0.0045)
    bins = cluster(collapsed, collapsed, np.ones(len(collapsed)), 0.0045, ClusterConfig(seeding="bins"))
    assert peaks.max() + 1 == len(centres)
    np.testing.assert_array_equal(peaks, bins)


def test_a_small_cap_beside_a_big_one_is_found_without_a_peak_bin_of_its_own():
    voxel = 0.0045
    bandwidth = ClusterConfig().bandwidth_voxels * voxel
    rng = np.random.default_rng(6)
    big = np.array([-0.45 * bandwidth, 0.0, 0.0]) + rng.normal(0, 0.0003, (200, 3))
    small = np.array([1.45 * bandwidth, 0.0, 0.0]) + rng.normal(0, 0.0003, (20, 3))
    collapsed = np.concatenate([big, small])
    # the small cap's bin borders the big cap's, which holds more points: it is no peak
    assert len(peak_seeds(collapsed, bandwidth, 2)) == 1
    labels = cluster(collapsed, collapsed, np.ones(len(collapsed)), voxel)
    np.testing.assert_array_equal(labels, np.repeat([0, 1], [200, 20]))


def test_scattered_or_non_finite_candidates_make_no_caps_and_no_error():
    voxel = 0.0045
    scattered = np.arange(30)[:, None] * np.array([0.05, 0.0, 0.0])  # no two within a bin
    assert np.all(cluster(scattered, scattered, np.ones(30), voxel) == -1)
    rng = np.random.default_rng(7)
    collapsed = rng.normal(0, 0.0005, (40, 3))
    collapsed[:5] = np.nan
    labels = cluster(collapsed, collapsed, np.ones(40), voxel)
    assert np.all(labels[:5] == -1) and np.all(labels[5:] == 0)


def test_cell_lookup_finds_equal_cells_and_nothing_else():
    from common.geometry import cell_lookup

    cells = np.array([[3, -2, 7], [0, 0, 0], [-5, 4, 1]])
    queries = np.array([[[0, 0, 0], [-5, 4, 1]], [[3, -2, 7], [3, -2, 8]]])
    np.testing.assert_array_equal(cell_lookup(cells, queries), [[1, 2], [0, -1]])
    assert cell_lookup(cells[:0], queries).shape == (2, 2) and np.all(cell_lookup(cells[:0], queries) == -1)


def test_climbing_the_seeds_is_meanshifts_own_step_and_changes_no_label(monkeypatch):
    """A step moves each seed to the mean of the points within the bandwidth (brute force here); the
    climb stops each seed where scikit-learn's next step would be its last, so the labels stay the same."""
    import perception.instances as instances
    from sklearn.cluster import MeanShift, get_bin_seeds
    from sklearn.neighbors import KDTree

    rng = np.random.default_rng(6)
    centres = rng.uniform(-0.05, 0.05, (12, 3)) * [1, 1, 0.2]
    collapsed = blobs(rng, centres, rng.integers(8, 80, 12), 0.002)
    tree, bandwidth = KDTree(collapsed), 0.009

    def step(seeds):
        within = np.linalg.norm(seeds[:, None] - collapsed[None], axis=2) <= bandwidth
        return (within[:, :, None] * collapsed[None]).sum(1) / within.sum(1)[:, None]

    seeds = peak_seeds(collapsed, bandwidth, 2)
    first = step(seeds)
    assert (np.linalg.norm(first - seeds, axis=1) > 1e-3 * bandwidth).all()
    np.testing.assert_allclose(instances._climb(tree, collapsed, seeds, bandwidth, 1), np.unique(first, axis=0),
                               rtol=0, atol=1e-15)
    bins = get_bin_seeds(collapsed, bandwidth, 2)
    for start in (seeds, bins):
        climbed = instances._climb(tree, collapsed, start, bandwidth, instances.CLIMB_MAX_STEPS)
        assert (np.linalg.norm(step(climbed) - climbed, axis=1) <= 1e-3 * bandwidth).all()
        # scikit-learn from the climbed seeds, with the steps left, ends where it ends from the start
        ours = MeanShift(bandwidth=bandwidth, seeds=climbed, cluster_all=False,
                         max_iter=instances.MEAN_SHIFT_MAX_ITER - instances.CLIMB_MAX_STEPS).fit(collapsed)
        theirs = MeanShift(bandwidth=bandwidth, seeds=start, cluster_all=False).fit(collapsed)
        np.testing.assert_allclose(ours.cluster_centers_, theirs.cluster_centers_, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(ours.labels_, theirs.labels_)
    assert len(climbed) < len(bins)
    far = np.array([[1.0, 1.0, 1.0]])
    np.testing.assert_array_equal(instances._climb(tree, collapsed, far, bandwidth, 4), far)
    labels = cluster(collapsed, collapsed, np.ones(len(collapsed)), 0.0045)
    monkeypatch.setattr(instances, "CLIMB_MAX_STEPS", 0)
    np.testing.assert_array_equal(cluster(collapsed, collapsed, np.ones(len(collapsed)), 0.0045), labels)
    assert len(set(labels[labels >= 0])) >= 8


def _fit(centers, radii):
    from perception.cap import rotation_from_axis
    from perception.cap import Caps

    centers = np.asarray(centers, np.float64)
    radii = np.asarray(radii, np.float64)
    scales = np.stack([radii, radii, 2 * radii / 3], 1)
    rotations = rotation_from_axis(np.tile([0.0, 0.0, 1.0], (len(centers), 1)))
    return Caps(centers, rotations, scales, np.ones(len(centers)), np.full(len(centers), 10))


def test_pieces_of_one_cap_are_merged_and_touching_caps_are_not():
    from perception.detect import merge_pieces

    # caps 0 and 1: two halves of a 34 mm cap, 12 mm apart; caps 2 and 3: two 20 mm caps touching
    # (centres 40 mm apart); cap 4: a bad fit with a 90 mm radius beside cap 3
    fit = _fit([[0, 0, 0], [0.012, 0, 0], [0.2, 0, 0], [0.24, 0, 0], [0.27, 0.03, 0]],
               [0.030, 0.028, 0.020, 0.020, 0.090])
    labels = np.repeat(np.arange(5), [30, 20, 25, 25, 10])
    labels = np.concatenate([labels, [-1, -1]])
    merged = merge_pieces(labels, fit, 1.2)
    assert merged is not None and merged[-1] == -1 and merged[-2] == -1
    groups = [set(merged[labels == k]) for k in range(5)]
    assert all(len(g) == 1 for g in groups)
    assert groups[0] == groups[1] and len({*groups[2], *groups[3], *groups[4], *groups[0]}) == 4
    assert merged[labels == 0][0] == 0  # the merged cap, 50 voxels, is the largest


def test_no_merge_when_no_two_caps_are_close():
    from perception.detect import merge_pieces

    fit = _fit([[0, 0, 0], [0.05, 0, 0]], [0.02, 0.02])
    assert merge_pieces(np.array([0, 0, 1, 1]), fit, 1.2) is None
