"""How noisy a cloud's surfaces are, and the smoothing that brings a noisy cloud to the surfaces the
network learnt.

The network trains on beds whose points lie within about 0.5 mm of the surface. One depth frame of a
D405-class camera at 0.6 m, or a passive-stereo OAK-class camera, scatters its points 1.5-3 mm about
it, and the voxel normals the network reads turn to noise. ``surface_noise`` measures that scatter,
relative to the point spacing; ``smoothed`` moves each point onto a quadric fitted to its neighbours,
by a share ramping from 0 at ``CLEAN_NOISE`` to 1 at ``NOISY_NOISE``, so a clean cloud passes as it is.
"""

from __future__ import annotations

import numpy as np

from common.geometry import voxel_representatives

NOISE_NEIGHBOURS = 16
"""Neighbours (the point itself included) whose plane a point's distance is measured from."""
NOISE_SAMPLES = 4000
"""Points the noise is measured at (a seeded draw): enough for a steady median, cheap on any cloud."""
CLEAN_NOISE = 0.55
"""A cloud whose ``surface_noise`` is at most this is left as it is: synthetic beds like the training
beds read 0.29-0.43, the real multi-view scan 0.42, beds sampled every 8 mm 0.41-0.55."""
NOISY_NOISE = 0.65
"""From this ``surface_noise`` on a cloud is smoothed in full: one D405-class frame from 0.45-0.75 m
reads 0.58-0.73, OAK-class stereo views fused 0.67-0.72."""
FIT_NEIGHBOURS = 32
"""Neighbours each point's quadric is fitted to: about 9 mm around a point every 3 mm."""
SMOOTHING_PASSES = 5
"""Quadric projections made one after another: fused stereo views disagree over several millimetres,
and repeated local fits even them out where one wide fit would round the caps off."""


def _neighbourhoods(tree, sites: np.ndarray, queries: np.ndarray, k: int):
    """Per query: the distances to its ``k`` nearest ``sites`` (``tree`` is theirs), those sites'
    offsets from their mean, the mean, and the eigenvalues and axes of their scatter (least first)."""
    distance, index = tree.query(queries, k, workers=-1)
    neighbours = sites[index]
    mean = neighbours.mean(1)
    offsets = neighbours - mean[:, None]
    values, axes = np.linalg.eigh(offsets.transpose(0, 2, 1) @ offsets)
    return distance, offsets, mean, values, axes


def surface_noise(points: np.ndarray, spacing: float | None = None) -> float:
    """The median scatter of points about the plane of their ``NOISE_NEIGHBOURS`` nearest (the root
    mean square distance from it), over their median nearest-neighbour distance; nan for fewer than
    ``NOISE_NEIGHBOURS`` points or points that mostly coincide. With ``spacing``, measured on one point
    per ``spacing`` cell, the sites ``smoothed`` fits its quadrics to."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, np.float64)
    if len(points) >= NOISE_NEIGHBOURS and spacing:
        points = points[voxel_representatives(points, spacing)]
    if len(points) < NOISE_NEIGHBOURS:
        return float("nan")
    queries = points[np.random.default_rng(0).choice(len(points), min(NOISE_SAMPLES, len(points)), replace=False)]
    distance, _, _, values, _ = _neighbourhoods(cKDTree(points, balanced_tree=False), points, queries, NOISE_NEIGHBOURS)
    spacing_between = float(np.median(distance[:, 1]))
    if not spacing_between > 0:
        return float("nan")
    return float(np.median(np.sqrt(np.maximum(values[:, 0] / NOISE_NEIGHBOURS, 0.0))) / spacing_between)


def smoothing_share(noise: float) -> float:
    """How far ``smoothed`` moves points at this ``surface_noise``: 0 up to ``CLEAN_NOISE``, 1 from
    ``NOISY_NOISE``, linear between."""
    if not np.isfinite(noise):
        return 0.0
    return float(np.clip((noise - CLEAN_NOISE) / (NOISY_NOISE - CLEAN_NOISE), 0.0, 1.0))


def quadric_projection(points: np.ndarray, sites: np.ndarray | None = None, k: int = FIT_NEIGHBOURS,
                       chunk: int = 20000) -> np.ndarray:
    """Each point moved onto the quadric z = f(x, y) fitted by least squares to its ``k`` nearest
    ``sites`` (default: the points themselves) in their plane's frame, z along the least-variance axis:
    a moving-least-squares surface, which keeps a cap's curvature where a plane would flatten it."""
    points = np.asarray(points, np.float64)
    sites = points if sites is None else np.asarray(sites, np.float64)
    if len(sites) < k:
        return points.copy()
    from scipy.spatial import cKDTree

    tree = cKDTree(sites, balanced_tree=False)
    moved = np.empty_like(points)
    for start in range(0, len(points), chunk):
        queries = points[start:start + chunk]
        _, offsets, mean, _, axes = _neighbourhoods(tree, sites, queries, k)
        local = offsets @ axes  # columns: height, then the two in-plane axes
        design = _quadric_terms(local[..., 1], local[..., 2])
        design_t = design.transpose(0, 2, 1)
        coefficients = np.linalg.solve(design_t @ design + 1e-12 * np.eye(6), design_t @ local[..., :1])[..., 0]
        query = ((queries - mean)[:, None] @ axes)[:, 0]
        query[:, 0] = np.einsum("ni,ni->n", _quadric_terms(query[:, 1], query[:, 2]), coefficients)
        moved[start:start + chunk] = mean + (query[:, None] @ axes.transpose(0, 2, 1))[:, 0]
    return moved


def _quadric_terms(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The terms 1, x, y, x^2, xy, y^2 of a quadric in the plane, stacked last."""
    return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], -1)


def smoothed(points: np.ndarray, spacing: float | None = None) -> tuple[np.ndarray, float]:
    """The cloud smoothed (``SMOOTHING_PASSES`` quadric projections, each fitted to the last one's
    points) and blended with itself by ``smoothing_share``, and its ``surface_noise``; a clean cloud
    comes back as the very array given. With ``spacing``, the quadrics are fitted to one point per
    ``spacing`` cell of a denser cloud."""
    original = np.asarray(points, np.float64)
    sites = voxel_representatives(original, spacing) if spacing and len(original) else slice(None)
    noise = surface_noise(original[sites])
    share = smoothing_share(noise)
    if share == 0.0:
        return points, noise
    moved = original
    for _ in range(SMOOTHING_PASSES):
        moved = quadric_projection(moved, moved[sites])
    return original + share * (moved - original), noise
