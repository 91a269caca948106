"""The implicit pose encoding (paper Sec. 3.2, docs/DESIGN.md section 4): per-point training targets."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

TOUCHING_RATIO = 0.25


@dataclass(frozen=True)
class EncodingTargets:
    existence: np.ndarray
    """(N,) float32: 1 on cap points, except those about as near another cap's centre as their own."""
    residual: np.ndarray
    """(N, 3) float32: c - p on existence points, 0 elsewhere."""
    orientation: np.ndarray
    """(N,) float32 in [0, 1]: 0 at the cap base, 1 at its top, on existence points; 0 elsewhere."""


def encode(points: np.ndarray, instance: np.ndarray, is_cap: np.ndarray, centers: np.ndarray,
           rotations: np.ndarray, scales: np.ndarray, touching_ratio: float = TOUCHING_RATIO) -> EncodingTargets:
    """Targets for ``points`` whose cap membership is ``is_cap`` and mushroom is ``instance`` (-1: none).

    Touching caps: cap points with |1 - d1/d2| < ``touching_ratio`` (d1, d2 their distances to the
    two nearest centres) become non-cap, so that cap regions are separated by a gap.
    """
    n = len(points)
    cap = np.asarray(is_cap, bool) & (np.asarray(instance) >= 0)
    if len(centers) >= 2 and cap.any():
        d, _ = cKDTree(centers).query(points[cap], k=2)
        ambiguous = np.abs(1.0 - d[:, 0] / np.maximum(d[:, 1], 1e-12)) < touching_ratio
        cap[np.flatnonzero(cap)[ambiguous]] = False
    existence = cap.astype(np.float32)
    residual = np.zeros((n, 3), np.float32)
    orientation = np.zeros(n, np.float32)
    owner = instance[cap]
    offset = points[cap].astype(np.float64) - centers[owner]
    residual[cap] = -offset
    height = np.einsum("ij,ij->i", offset, rotations[owner, :, 2]) / scales[owner, 2]
    orientation[cap] = np.clip(height, 0.0, 1.0)
    return EncodingTargets(existence, residual, orientation)
