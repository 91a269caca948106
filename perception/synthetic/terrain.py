"""Casing soil and distractors: the background every synthetic bed stands on.

Real casing soil is clumpy: clods a few centimetres across, cracks between them, crumbs on top,
and the whole bed undulating by a few centimetres. Two procedural terrains give that texture
differently (Voronoi clods, billowed crumbs); both are then deformed locally along their normals,
as in the paper's Sec. 2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from perception.cap import cap_rotation

TERRAINS = ("clods", "crumbs")


@dataclass(frozen=True)
class Heightfield:
    """z = height[i, j] over the regular grid x = xs[j], y = ys[i] (metres, bed frame)."""

    xs: np.ndarray
    ys: np.ndarray
    height: np.ndarray

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear height at arbitrary (x, y) inside the grid."""
        step = self.xs[1] - self.xs[0]
        fx = np.clip((np.asarray(x) - self.xs[0]) / step, 0, len(self.xs) - 1.000001)
        fy = np.clip((np.asarray(y) - self.ys[0]) / step, 0, len(self.ys) - 1.000001)
        j, i = fx.astype(int), fy.astype(int)
        tx, ty = fx - j, fy - i
        h = self.height
        return ((1 - ty) * ((1 - tx) * h[i, j] + tx * h[i, j + 1])
                + ty * ((1 - tx) * h[i + 1, j] + tx * h[i + 1, j + 1]))


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma_cells: float) -> np.ndarray:
    """Unit-variance Gaussian-filtered noise; wide filters run on a coarse grid and are upsampled."""
    coarsen = max(1.0, sigma_cells / 2.0)
    coarse_shape = tuple(int(np.ceil(n / coarsen)) + 2 for n in shape)
    field = ndimage.gaussian_filter(rng.standard_normal(coarse_shape), sigma_cells / coarsen, mode="wrap")
    if coarsen > 1.0:
        field = ndimage.zoom(field, (shape[0] / coarse_shape[0], shape[1] / coarse_shape[1]), order=1)
    field = field[: shape[0], : shape[1]]
    return field / (field.std() + 1e-12)


def soil_heightfield(rng: np.random.Generator, size: float, cell: float, kind: str) -> Heightfield:
    """A size x size patch of casing soil centred on the origin, mean height 0."""
    n = int(round(size / cell)) + 1
    xs = np.linspace(-size / 2, size / 2, n)
    shape = (n, n)
    if kind == "clods":
        # Voronoi clods on the grid: each cell takes its nearest seed's height, and sinks into a
        # crack near the border with the next clod (distance to that border ~ (d2 - d1) / 2)
        seeds = rng.integers(0, n, (int(rng.integers(150, 350)), 2))
        clod_height = rng.uniform(0.004, 0.014, len(seeds))
        marker = np.ones(shape, bool)
        marker[seeds[:, 0], seeds[:, 1]] = False
        owner = np.full(shape, -1)
        owner[seeds[:, 0], seeds[:, 1]] = np.arange(len(seeds))
        _, (ri, rj) = ndimage.distance_transform_edt(marker, return_indices=True)
        label = owner[ri, rj]
        border = np.zeros(shape, bool)
        border[:, 1:] |= label[:, 1:] != label[:, :-1]
        border[1:, :] |= label[1:, :] != label[:-1, :]
        to_border = ndimage.distance_transform_edt(~border) * cell
        crack = np.clip(2 * to_border / rng.uniform(0.004, 0.008), 0, 1)
        height = clod_height[label] * np.sqrt(crack)
        height = ndimage.gaussian_filter(height, 0.6)
        height += 0.0012 * _smooth_noise(rng, shape, 1.0)
    elif kind == "crumbs":
        height = np.zeros(shape)
        for sigma_m, amplitude in ((0.012, 0.006), (0.005, 0.003), (0.0025, 0.0012)):
            height += amplitude * np.abs(_smooth_noise(rng, shape, sigma_m / cell))
    else:
        raise ValueError(f"unknown terrain {kind!r}; choose one of {TERRAINS}")
    height += rng.uniform(0.004, 0.015) * _smooth_noise(rng, shape, 0.12 / cell)
    return Heightfield(xs, xs.copy(), height - height.mean())


SOIL_LUMP_WIDTH = (0.008, 0.02)
"""Width of a lump's blobs (a Gaussian's standard deviation along each of its axes), metres: lumps
2-6 cm across."""
SOIL_LUMP_HEIGHT = (0.005, 0.02)
"""Height of a lump's main blob, metres: as high as a small cap stands."""
SOIL_LUMP_ROUGHNESS = 0.25
"""Crumbs on a lump, as a share of its height (cell-scale noise): a lump is rough, a cap smooth."""


def add_soil_lumps(rng: np.random.Generator, field: Heightfield, count: int) -> Heightfield:
    """``field`` with ``count`` casing-soil lumps raised on it: rough mounds 2-6 cm across, each two or
    three overlapping blobs, so irregular in outline. A real bed's casing stands up in such lumps,
    and a detector that has never seen one takes a bare-soil mound for a cap."""
    if count == 0:
        return field
    gx, gy = np.meshgrid(field.xs, field.ys)
    half = field.xs[-1]
    blobs = rng.integers(2, 4, count)
    owner = np.repeat(np.arange(count), blobs)
    centre = rng.uniform(-half, half, (count, 2))[owner] + rng.normal(0, SOIL_LUMP_WIDTH[0], (len(owner), 2))
    width = rng.uniform(*SOIL_LUMP_WIDTH, (len(owner), 2))
    angle = rng.uniform(0, np.pi, len(owner))
    height = rng.uniform(*SOIL_LUMP_HEIGHT, count)[owner] * rng.uniform(0.5, 1.0, len(owner))
    lumps = _blob_heights(gx, gy, centre, width, angle, height)
    crumbs = SOIL_LUMP_ROUGHNESS * np.abs(_smooth_noise(rng, field.height.shape, 0.7))
    return Heightfield(field.xs, field.ys, field.height + lumps * (1.0 + crumbs))


MYCELIUM_THICKNESS = (0.0015, 0.004)
"""Thickness of a bed's mycelium mats, metres: a white, fluffy layer over the casing."""
MYCELIUM_PATCH = 0.015
"""Spread (the noise filter's standard deviation, metres) of the mats' outline: patches a few
centimetres to a decimetre across."""
MYCELIUM_FUZZ = 0.3
"""Fuzz on a mat, as a share of its thickness (cell-scale noise)."""
MYCELIUM_FILL = 0.008
"""Metres: a mat fills the casing's crevices narrower than about this (the soil smoothed over it)."""


def add_mycelium(rng: np.random.Generator, field: Heightfield, share: float) -> Heightfield:
    """``field`` with white mycelium mats over about ``share`` of it: a fuzzy layer a few millimetres
    thick over the casing, filling its crevices, in patches with soft edges, as a bed shows before and
    between flushes. Only the surface's shape changes (the network reads no colour), so a mat is a
    low, smoother, fuzzy plateau on the soil."""
    if share <= 0:
        return field
    cell = field.xs[1] - field.xs[0]
    outline = _smooth_noise(rng, field.height.shape, MYCELIUM_PATCH / cell)
    level = np.quantile(outline, 1.0 - share)
    cover = np.clip((outline - level) / 0.5, 0.0, 1.0)  # soft edges over half a standard deviation
    fuzz = np.maximum(1.0 + MYCELIUM_FUZZ * _smooth_noise(rng, field.height.shape, 0.7), 0.0)
    filled = np.maximum(field.height, ndimage.gaussian_filter(field.height, MYCELIUM_FILL / cell))
    surface = filled + rng.uniform(*MYCELIUM_THICKNESS) * fuzz
    return Heightfield(field.xs, field.ys, field.height + cover * (surface - field.height))


def _blob_heights(gx: np.ndarray, gy: np.ndarray, centre: np.ndarray, width: np.ndarray, angle: np.ndarray,
                  height: np.ndarray) -> np.ndarray:
    """The highest of anisotropic Gaussian blobs over the grid (gx, gy): blob b peaks at ``height[b]``
    over ``centre[b]``, with standard deviations ``width[b]`` along the axes turned by ``angle[b]``."""
    raised = np.zeros(gx.shape)
    cos, sin = np.cos(angle), np.sin(angle)
    for blob in range(len(height)):  # a few dozen blobs, each over the grid: 2.5x faster than all at once
        dx, dy = gx - centre[blob, 0], gy - centre[blob, 1]
        u, v = (cos[blob] * dx + sin[blob] * dy) / width[blob, 0], (cos[blob] * dy - sin[blob] * dx) / width[blob, 1]
        raised = np.maximum(raised, height[blob] * np.exp(-0.5 * (u * u + v * v)))
    return raised


SOIL_BANK_DISTANCE = (0.7, 1.1)
"""Distance of a bank's crest from its cap's axis, as a factor on the cap's radius."""
SOIL_BANK_WIDTH = ((0.4, 0.8), (0.6, 1.2))
"""A bank's standard deviations towards its cap and along its rim, as factors on the cap's radius."""
SOIL_BANK_RISE = (0.4, 0.9)
"""A bank's height as a share of its cap's centre's height over the soil: up its stem, short of the dome."""


def soil_bank_heights(rng: np.random.Generator, field: Heightfield, cap_xy: np.ndarray, cap_radius: np.ndarray,
                      cap_rise: np.ndarray) -> np.ndarray:
    """How far the soil of ``field`` rises (its grid's shape) where casing soil is banked against one side of
    each cap given (centre xy, radius, centre's height over the soil, metres): a rough crest beside the cap,
    up its stem to below the dome, so that soil and cap meet in one slope. On a real bed young caps push
    up through the casing and stand in such banks, which a detector must not take for part of the cap."""
    n = len(cap_radius)
    if n == 0:
        return np.zeros(field.height.shape)
    gx, gy = np.meshgrid(field.xs, field.ys)
    direction = rng.uniform(0, 2 * np.pi, n)
    reach = cap_radius * rng.uniform(*SOIL_BANK_DISTANCE, n)
    centre = cap_xy + reach[:, None] * np.stack([np.cos(direction), np.sin(direction)], 1)
    width = cap_radius[:, None] * np.stack([rng.uniform(*SOIL_BANK_WIDTH[0], n), rng.uniform(*SOIL_BANK_WIDTH[1], n)], 1)
    height = np.maximum(cap_rise, 0.0) * rng.uniform(*SOIL_BANK_RISE, n)
    banks = _blob_heights(gx, gy, centre, width, direction, height)
    return banks * (1.0 + SOIL_LUMP_ROUGHNESS * np.abs(_smooth_noise(rng, field.height.shape, 0.7)))


def heightfield_mesh(field: Heightfield) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and upward-facing triangles (T, 3) of a heightfield."""
    n_y, n_x = field.height.shape
    gx, gy = np.meshgrid(field.xs, field.ys)
    vertices = np.stack([gx.ravel(), gy.ravel(), field.height.ravel()], 1)
    i, j = np.meshgrid(np.arange(n_y - 1), np.arange(n_x - 1), indexing="ij")
    a = (i * n_x + j).ravel()
    b, c, d = a + 1, a + n_x, a + n_x + 1
    triangles = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return vertices, triangles


def deform_along_normals(rng: np.random.Generator, vertices: np.ndarray, normals: np.ndarray,
                         count: int, magnitude: float, radius: tuple[float, float]) -> np.ndarray:
    """Push ``count`` random vertices along their normals and drag neighbours with a Gaussian falloff.

    ``vertices`` and ``normals`` may carry leading batch dimensions (..., V, 3): each batch item is
    deformed independently, all at once.
    """
    batch, n_vertices = vertices.shape[:-2], vertices.shape[-2]
    picks = rng.integers(0, n_vertices, batch + (count,))
    centres = np.take_along_axis(vertices, picks[..., None], axis=-2)
    push = rng.normal(0.0, magnitude, batch + (count,))
    width = rng.uniform(*radius, batch + (count,))
    offset = np.zeros(vertices.shape[:-1])
    for bump in range(count):
        d2 = np.sum((vertices - centres[..., bump, None, :]) ** 2, -1)
        offset += push[..., bump, None] * np.exp(d2 * (-0.5 / width[..., bump, None] ** 2))
    return vertices + offset[..., None] * normals


def heightfield_normals(field: Heightfield) -> np.ndarray:
    step = field.xs[1] - field.xs[0]
    dz_dy, dz_dx = np.gradient(field.height, step)
    normals = np.stack([-dz_dx, -dz_dy, np.ones_like(dz_dx)], -1).reshape(-1, 3)
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def deform_heightfield_mesh(rng: np.random.Generator, field: Heightfield, vertices: np.ndarray, count: int,
                            magnitude: float, radius: tuple[float, float]) -> np.ndarray:
    """``deform_along_normals`` for a heightfield mesh, each bump computed only in its 3-sigma window."""
    step = field.xs[1] - field.xs[0]
    n_y, n_x = field.height.shape
    offset = np.zeros((n_y, n_x))
    for _ in range(count):
        i, j = int(rng.integers(n_y)), int(rng.integers(n_x))
        push, width = rng.normal(0.0, magnitude), rng.uniform(*radius)
        reach = int(np.ceil(3 * width / step))
        rows, cols = slice(max(i - reach, 0), i + reach + 1), slice(max(j - reach, 0), j + reach + 1)
        dy = (np.arange(rows.start, min(rows.stop, n_y)) - i)[:, None] * step
        dx = (np.arange(cols.start, min(cols.stop, n_x)) - j)[None, :] * step
        offset[rows, cols] += push * np.exp(-(dx**2 + dy**2) / (2 * width**2))
    return vertices + offset.reshape(-1, 1) * heightfield_normals(field)


_CUBE_VERTICES = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) / 2
_CUBE_TRIANGLES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                            [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


def _cone(segments: int = 16) -> tuple[np.ndarray, np.ndarray]:
    angle = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    rim = np.stack([0.5 * np.cos(angle), 0.5 * np.sin(angle), np.full(segments, -0.5)], 1)
    vertices = np.concatenate([rim, [[0, 0, 0.5], [0, 0, -0.5]]])
    k = np.arange(segments)
    side = np.stack([k, (k + 1) % segments, np.full(segments, segments)], 1)
    base = np.stack([(k + 1) % segments, k, np.full(segments, segments + 1)], 1)
    return vertices, np.concatenate([side, base])


_CONE_VERTICES, _CONE_TRIANGLES = _cone()


@dataclass(frozen=True)
class Distractor:
    vertices: np.ndarray
    triangles: np.ndarray
    center: np.ndarray
    radius: float
    """Bounding-sphere radius, used to keep mushrooms out of it."""


def random_distractor(rng: np.random.Generator, field: Heightfield, margin: float) -> Distractor:
    """A cube or cone of random size and pose, half sunk into the soil."""
    vertices, triangles = ((_CUBE_VERTICES, _CUBE_TRIANGLES) if rng.random() < 0.5
                           else (_CONE_VERTICES, _CONE_TRIANGLES))
    scale = rng.uniform(0.008, 0.035, 3)
    rotation = cap_rotation(*rng.uniform(-np.pi, np.pi, 3))
    half = field.xs[-1] - margin
    x, y = rng.uniform(-half, half, 2)
    center = np.array([x, y, float(field.sample(x, y)) + rng.uniform(-0.3, 0.3) * scale.min()])
    placed = (vertices * scale) @ rotation.T + center
    return Distractor(placed, triangles, center, float(np.linalg.norm(scale) / 2))
