"""Instance segmentation from the encoding (paper Sec. 3.3): which voxels form which cap.

MeanShift (default) groups the "collapsed" points p + predicted residual, which gather densely at
cap centres; DBSCAN groups the existence points themselves and relies on the gap the touching rule
teaches the network to leave between caps. Both come from scikit-learn.

scikit-learn's MeanShift makes a neighbour query per seed and step, and each call has a fixed
overhead; so the seeds climb together first, one query for all per step (``_climb``), and
scikit-learn then takes the last step of each and drops duplicate centres: the same labels in about
a third of the queries (``bench/perception.py`` times both).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from common.geometry import cell_lookup

ClusteringMethod = Literal["meanshift", "dbscan"]
"""How the network's cap-centre votes are grouped into caps: MeanShift on the collapsed points, or
DBSCAN on the cap points themselves."""
METHODS = get_args(ClusteringMethod)
MEAN_SHIFT_MAX_ITER = 300
"""scikit-learn MeanShift's default ``max_iter``: the steps a seed may take, our climb and its own together."""
CLIMB_MAX_STEPS = MEAN_SHIFT_MAX_ITER
"""Most steps a seed climbs before scikit-learn's MeanShift takes over with what is left of
``MEAN_SHIFT_MAX_ITER``; with all of it, scikit-learn takes exactly the one step left to each seed."""
SEEDINGS = ("peaks", "bins")


@dataclass(frozen=True)
class ClusterConfig:
    method: ClusteringMethod = "meanshift"
    """How the network's cap-centre votes are grouped into caps."""
    existence_threshold: float = 0.5
    bandwidth_voxels: float = 2.0
    """MeanShift bandwidth in voxels: collapsed points of one cap lie within a few millimetres."""
    eps_voxels: float = 1.6
    """DBSCAN neighbourhood in voxels (input points are about one voxel apart)."""
    min_points: int = 4
    """Clusters smaller than this are dropped (noise, slivers of caps seen edge-on)."""
    merge_ratio: float | None = 1.2
    """Caps whose fitted centres lie closer than this times the smaller fitted radius are pieces of one
    cap and are merged (``perception.detect.find_caps``): caps larger than the training beds' come out
    in two or three pieces. Touching caps are at least 2 smaller radii apart. None: no merging."""
    seeding: str = "peaks"
    """MeanShift seeds: "bins" = scikit-learn's bin seeding (every bandwidth-sized bin holding
    min_points / 2 collapsed points); "peaks" = only those of them that hold at least as many points as
    each of their 6 face neighbours, then a second pass over the points left over, which finds small
    caps beside big ones that have no peak bin of their own."""

    def __post_init__(self) -> None:
        if self.merge_ratio is not None and not self.merge_ratio > 0:
            raise ValueError(f"merge_ratio must be positive (or None), got {self.merge_ratio}")
        if self.method not in METHODS:
            raise ValueError(f"unknown clustering method {self.method!r}; choose one of {METHODS}")
        if self.seeding not in SEEDINGS:
            raise ValueError(f"unknown MeanShift seeding {self.seeding!r}; choose one of {SEEDINGS}")


def cluster(points: np.ndarray, collapsed: np.ndarray, existence: np.ndarray, voxel: float,
            config: ClusterConfig = ClusterConfig()) -> np.ndarray:
    """Instance label per point (-1: not a cap), labels 0..K-1 ordered by cluster size."""
    labels = np.full(len(points), -1, np.int64)
    usable = (existence > config.existence_threshold) & np.isfinite(collapsed).all(1) & np.isfinite(points).all(1)
    candidates = np.flatnonzero(usable)
    if len(candidates) < config.min_points:
        return labels
    if config.method == "meanshift":
        found = _mean_shift(collapsed[candidates], config.bandwidth_voxels * voxel, config.min_points,
                            config.seeding)
    else:
        from sklearn.cluster import DBSCAN

        found = DBSCAN(eps=config.eps_voxels * voxel, min_samples=3).fit_predict(points[candidates])
    counts = np.bincount(found[found >= 0]) if (found >= 0).any() else np.zeros(0, np.int64)
    kept = np.flatnonzero(counts >= config.min_points)
    kept = kept[np.argsort(-counts[kept], kind="stable")]
    relabel = np.full(len(counts) + 1, -1, np.int64)
    relabel[kept] = np.arange(len(kept))
    labels[candidates] = relabel[np.where(found >= 0, found, len(counts))]
    return labels


def _mean_shift(collapsed: np.ndarray, bandwidth: float, min_points: int, seeding: str) -> np.ndarray:
    """scikit-learn MeanShift labels (-1: no cluster) of finite collapsed points; seeds are bins
    holding min_points / 2 points, sent up their hill together first (``_climb``)."""
    import sklearn
    from sklearn.cluster import MeanShift, get_bin_seeds
    from sklearn.neighbors import KDTree

    def fit(points: np.ndarray, seeds: np.ndarray) -> MeanShift:
        # our inputs are finite: skipping scikit-learn's per-call checks makes MeanShift ~20 % faster
        with sklearn.config_context(assume_finite=True, skip_parameter_validation=True):
            return MeanShift(bandwidth=bandwidth, seeds=seeds, cluster_all=False,
                             max_iter=MEAN_SHIFT_MAX_ITER - CLIMB_MAX_STEPS).fit(points)

    seeds = (peak_seeds if seeding == "peaks" else get_bin_seeds)(collapsed, bandwidth, max(1, min_points // 2))
    if len(seeds) == 0:
        return np.full(len(collapsed), -1, np.int64)
    tree = KDTree(collapsed)
    first = fit(collapsed, _climb(tree, collapsed, seeds, bandwidth, CLIMB_MAX_STEPS))
    labels = first.labels_.astype(np.int64)
    if seeding != "peaks":
        return labels
    # a small cap right beside a big one may have no peak bin of its own: seed the peaks of what is
    # left over (bins of min_points, so that scattered leftovers seed nothing) and climb on all points,
    # so that seeds in a big cap's tail climb back to its centre; centres a bandwidth away from every
    # first-pass centre are new caps
    left = np.flatnonzero(labels < 0)
    seeds = peak_seeds(collapsed[left], bandwidth, min_points)
    if len(seeds) == 0:
        return labels
    second = fit(collapsed, _climb(tree, collapsed, seeds, bandwidth, CLIMB_MAX_STEPS))
    gap = np.linalg.norm(second.cluster_centers_[:, None] - first.cluster_centers_[None], axis=2).min(1)
    new = np.flatnonzero(gap > bandwidth)
    renumber = np.full(len(second.cluster_centers_) + 1, -1, np.int64)
    renumber[new] = len(first.cluster_centers_) + np.arange(len(new))
    labels[left] = renumber[second.labels_[left]]
    return labels


def peak_seeds(points: np.ndarray, bin_size: float, min_bin_freq: int = 1) -> np.ndarray:
    """Centres of the bins (scikit-learn's ``get_bin_seeds`` grid) that hold ``min_bin_freq`` points or
    more and at least as many as each of their 6 face neighbours (all 26 would lose small caps beside
    big ones)."""
    bins, counts = np.unique(np.round(points / bin_size).astype(np.int64), axis=0, return_counts=True)
    keep = counts >= min_bin_freq
    bins, counts = bins[keep], counts[keep]
    offsets = np.concatenate([np.eye(3, dtype=np.int64), -np.eye(3, dtype=np.int64)])
    neighbour = cell_lookup(bins, bins[:, None, :] + offsets[None])
    neighbour_counts = np.where(neighbour >= 0, counts[neighbour], 0)
    return bins[counts >= neighbour_counts.max(1)] * bin_size


def _climb(tree, points: np.ndarray, seeds: np.ndarray, bandwidth: float, max_steps: int) -> np.ndarray:
    """The distinct ``seeds`` after MeanShift's own iteration (each moves to the mean of the points
    within ``bandwidth``), all at once, one neighbour query per step: a seed stops where its next step
    would be within scikit-learn's stopping distance (1e-3 bandwidths), so that scikit-learn takes
    that step and ends where it would have from the start (up to rounding: its mean sums the points in
    another order). A seed with no point in reach stays."""
    seeds = seeds.copy()
    moving = np.arange(len(seeds))
    for _ in range(max_steps):
        if not len(moving):
            break
        neighbours = tree.query_radius(seeds[moving], r=bandwidth)
        counts = np.fromiter(map(len, neighbours), np.int64, len(neighbours))
        reached = counts > 0
        moving, counts = moving[reached], counts[reached]
        if not len(moving):
            break
        sums = np.add.reduceat(points[np.concatenate(neighbours[reached])], np.cumsum(counts) - counts, axis=0)
        means = sums / counts[:, None]
        far = np.linalg.norm(means - seeds[moving], axis=1) > 1e-3 * bandwidth
        moving = moving[far]
        seeds[moving] = means[far]
    # seeds that met on the way have the same path from there on, and scikit-learn's result does not
    # depend on the seeds' order
    return np.unique(seeds, axis=0)
