"""Instance segmentation from the encoding (paper Sec. 3.3): which voxels form which cap.

MeanShift (default) groups the "collapsed" points p + predicted residual, which gather densely at
cap centres; DBSCAN groups the existence points themselves and relies on the gap the touching rule
teaches the network to leave between caps. Both come from scikit-learn.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from sklearn.cluster import DBSCAN, MeanShift

METHODS = ("meanshift", "dbscan")


@dataclass(frozen=True)
class ClusterConfig:
    method: str = "meanshift"
    existence_threshold: float = 0.5
    bandwidth_voxels: float = 2.0
    """MeanShift bandwidth in voxels: collapsed points of one cap lie within a few millimetres."""
    eps_voxels: float = 1.6
    """DBSCAN neighbourhood in voxels (input points are about one voxel apart)."""
    min_points: int = 4
    """Clusters smaller than this are dropped (noise, slivers of caps seen edge-on)."""

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"unknown clustering method {self.method!r}; choose one of {METHODS}")


def cluster(points: np.ndarray, collapsed: np.ndarray, existence: np.ndarray, voxel: float,
            config: ClusterConfig = ClusterConfig()) -> np.ndarray:
    """Instance label per point (-1: not a cap), labels 0..K-1 ordered by cluster size."""
    labels = np.full(len(points), -1, np.int64)
    candidates = np.flatnonzero(existence > config.existence_threshold)
    if len(candidates) < config.min_points:
        return labels
    if config.method == "meanshift":
        model = MeanShift(bandwidth=config.bandwidth_voxels * voxel, bin_seeding=True,
                          min_bin_freq=max(1, config.min_points // 2), cluster_all=False)
        found = model.fit_predict(collapsed[candidates])
    else:
        found = DBSCAN(eps=config.eps_voxels * voxel, min_samples=3).fit_predict(points[candidates])
    counts = np.bincount(found[found >= 0]) if (found >= 0).any() else np.zeros(0, np.int64)
    kept = np.flatnonzero(counts >= config.min_points)
    kept = kept[np.argsort(-counts[kept], kind="stable")]
    relabel = np.full(len(counts) + 1, -1, np.int64)
    relabel[kept] = np.arange(len(kept))
    labels[candidates] = relabel[np.where(found >= 0, found, len(counts))]
    return labels
