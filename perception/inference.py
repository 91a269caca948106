"""The trained network's forward pass in numpy: what ``detect`` runs on a cloud file, so that it starts
without importing torch (1.4 s of its start-up on 2 cores); the live chain and ``eval`` run torch's.

``InferenceNet`` holds a ``MushroomNet``'s weights with each batch norm folded into the convolution
before it (``perception.model.fold_batch_norms`` does the same in torch) and runs the same layers in
the same order: per kernel offset, gather -> matmul -> add onto the output rows, the sum starting at
the identity offset plus the bias. Kernel maps are those of ``perception.sparse`` (a dense table of
rows over the voxels' bounding box, sorted packed keys beyond it); ``tests/test_inference.py`` holds
the maps and the outputs to torch's. Training, which needs gradients, stays in torch.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from perception.calibration import UNCALIBRATED, Calibration
from perception.network import INFERENCE_ZOOM, NORM_AFTER, NetworkConfig

BATCH_BITS, COORD_BITS = 15, 16
COORD_MARGIN = 8
"""Room kept inside each coordinate field, so a neighbour's key is the voxel's key plus a constant."""
COORD_MIN = -(1 << (COORD_BITS - 1)) + COORD_MARGIN
COORD_MAX = (1 << (COORD_BITS - 1)) - 1 - COORD_MARGIN
BATCH_MAX = (1 << BATCH_BITS) - 1

DENSE_TABLE_CELLS = 1 << 23
"""Largest bounding box (cells, margin included) looked up in a dense table: 64 MB of int64 rows. A 0.5 m
bed at 4.3 mm voxels (zoom 1.05) and 0.1 m of relief spans about 0.4 M cells, at 3.75 mm (zoom 1.2, the
shipped model's) about 0.6 M; a fused cloud with a stray point metres away falls back to sorted keys,
which build the kernel maps more slowly (docs/DESIGN.md section 9; ``tests/test_sparse.py`` and
``tests/test_inference.py`` hold both to the same maps)."""
TABLE_MARGIN = 4
"""Cells of room around the box: a stride-2 map asks from doubled parents up to one cell outside the
fine voxels, plus its offsets. Queries that reach outside the padded box use the sorted keys."""
BATCH_NORM_EPS = 1e-5
"""torch's BatchNorm1d epsilon, which the trained running variances were normalised with."""


def pack(coords: np.ndarray) -> np.ndarray:
    """One int64 key per (b, x, y, z) row, ordered by batch then x, y, z."""
    u = coords[..., 1:] + (1 << (COORD_BITS - 1))
    return ((coords[..., 0] << (3 * COORD_BITS)) + (u[..., 0] << (2 * COORD_BITS))
            + (u[..., 1] << COORD_BITS) + u[..., 2])


def unpack(keys: np.ndarray) -> np.ndarray:
    """Inverse of ``pack``: (N,) keys -> (N, 4) coords."""
    mask, bias = (1 << COORD_BITS) - 1, 1 << (COORD_BITS - 1)
    return np.stack([keys >> (3 * COORD_BITS), *[((keys >> s) & mask) - bias
                                                  for s in (2 * COORD_BITS, COORD_BITS, 0)]], 1)


def voxelize(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Occupied voxels of ``points`` (N, 3) in batch 0: coords (V, 4) sorted, and each point's voxel."""
    grid = np.floor(np.asarray(points, np.float64) / voxel)
    if len(grid) and not (grid.min() >= COORD_MIN and grid.max() <= COORD_MAX):
        raise ValueError(f"voxel coords out of the packable range [{COORD_MIN}, {COORD_MAX}]: got "
                         f"[{grid.min():.0f}, {grid.max():.0f}]")
    grid = grid.astype(np.int64)
    keys, point_to_voxel = np.unique(pack(np.concatenate([np.zeros((len(grid), 1), np.int64), grid], 1)),
                                     return_inverse=True)
    return unpack(keys), point_to_voxel.reshape(-1)


def kernel_offsets(kernel_size: int, centred: bool) -> np.ndarray:
    """(K, 3) offsets, x slowest and z fastest (the weights' order); {-r..r}^3 or {0..k-1}^3."""
    start = -(kernel_size // 2) if centred else 0
    steps = range(start, start + kernel_size)
    return np.array(list(itertools.product(steps, steps, steps)), np.int64).reshape(-1, 3)


class VoxelLevel:
    """The voxels of one stride and their look-up: the row holding a given voxel, or -1."""

    def __init__(self, coords: np.ndarray):
        self.coords = coords
        margin = np.array([0, TABLE_MARGIN, TABLE_MARGIN, TABLE_MARGIN])
        self.low, self.high = coords.min(0) - margin, coords.max(0) + margin
        extent = self.high + 1 - self.low
        self.table = None
        if float(np.prod(extent.astype(np.float64))) <= DENSE_TABLE_CELLS:
            self.strides = np.array([int(np.prod(extent[i + 1:])) for i in range(4)], np.int64)
            self.table = np.full(int(np.prod(extent)), -1, np.int64)
            self.table[(coords - self.low) @ self.strides] = np.arange(len(coords))
        self._sorted: tuple[np.ndarray, np.ndarray] | None = None

    def lookup(self, coords: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """(K, M): the row holding voxel coords[m] + offsets[k], or -1 where that voxel is empty."""
        if len(offsets) == 0 or len(coords) == 0:
            return np.full((len(offsets), len(coords)), -1, np.int64)
        reach = np.concatenate([np.zeros((len(offsets), 1), np.int64), offsets], 1)
        if (self.table is not None and (coords.min(0) + reach.min(0) >= self.low).all()
                and (coords.max(0) + reach.max(0) <= self.high).all()):
            return self.table[((coords - self.low) @ self.strides)[None] + (reach @ self.strides)[:, None]]
        if self._sorted is None:  # the sorted keys, made once, for queries the table does not cover
            keys = pack(self.coords)
            order = np.argsort(keys, kind="stable")
            self._sorted = keys[order], order
        sorted_keys, order = self._sorted
        keys = pack(coords)[None] + (pack(reach) - pack(np.zeros(4, np.int64)))[:, None]
        position = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
        return np.where(sorted_keys[position] == keys, order[position], -1)

    def parents(self) -> np.ndarray:
        """The occupied parent voxels unique(floor(coords / 2)), sorted."""
        halved = self.coords.copy()
        halved[:, 1:] //= 2
        return unpack(np.unique(pack(halved)))


KernelMap = list
"""Per kernel offset, (input rows, output rows) it connects, or None for the identity offset."""


def _pairs(found: np.ndarray) -> KernelMap:
    """(K, M) input rows found for output m at offset k -> per offset (input rows, output rows)."""
    hit = found >= 0
    bounds = np.cumsum(hit.sum(1))[:-1]
    return list(zip(np.split(found[hit], bounds), np.split(np.nonzero(hit)[1], bounds)))


def submanifold_map(level: VoxelLevel, kernel_size: int) -> KernelMap:
    """Output voxel o gathers input voxel o + d for every offset d of a centred cube; offset K-1-k is
    -d, whose pairs are those of d swapped."""
    offsets = kernel_offsets(kernel_size, True)
    half = _pairs(level.lookup(level.coords, offsets[:len(offsets) // 2]))
    return half + [None] + [(o, i) for i, o in reversed(half)]


def downsample_map(fine: VoxelLevel, coarse: np.ndarray, kernel_size: int) -> KernelMap:
    """Coarse voxel o gathers fine voxels 2 o + d, d in {-1, 0, 1}^3 (k=3) or {0, 1}^3 (k=2)."""
    doubled = np.concatenate([coarse[:, :1], 2 * coarse[:, 1:]], 1)
    return _pairs(fine.lookup(doubled, kernel_offsets(kernel_size, kernel_size == 3)))


def convolve(features: np.ndarray, weight: np.ndarray, bias: np.ndarray | None, kmap: KernelMap,
             n_out: int) -> np.ndarray:
    """out[o] += features[i] @ weight[k] for every pair (i, o) of offset k, plus ``bias``. Within one
    offset each output row occurs once, so a fancy-indexed add is exact."""
    identity = next((k for k, pairs in enumerate(kmap) if pairs is None), None)
    if identity is not None:
        out = features @ weight[identity]
        if bias is not None:
            out += bias
    else:
        out = np.zeros((n_out, weight.shape[2]), np.float32) if bias is None else np.tile(bias, (n_out, 1))
    for k, pairs in enumerate(kmap):
        if pairs is not None and len(pairs[0]):
            rows_in, rows_out = pairs
            out[rows_out] += features[rows_in] @ weight[k]
    return out


def _relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, 0, out=x)


@dataclass
class InferenceNet:
    """A trained MushroomNet for inference: folded weights by layer name, and what its file records."""

    config: NetworkConfig
    layers: dict
    """Per convolution or linear layer name, (weight, bias or None); convolutions (K, C_in, C_out)."""
    point_spacing: float | None = None
    inference_zoom: float = INFERENCE_ZOOM
    calibration: Calibration = UNCALIBRATED

    @staticmethod
    def from_state_dict(config: NetworkConfig, state: dict, **recorded) -> InferenceNet:
        """The folded layers of a MushroomNet ``state_dict`` (numpy arrays); ``recorded``: the other fields."""
        layers = {}
        for name in [key[:-len(".weight")] for key in state if key.endswith(".weight")]:
            if f"{name}.running_var" in state:
                continue  # a batch norm, folded into the convolution before it
            weight, bias = np.array(state[f"{name}.weight"], np.float32), state.get(f"{name}.bias")
            bias = None if bias is None else np.array(bias, np.float32)
            parent, _, last = name.rpartition(".")
            norm = f"{parent}.{NORM_AFTER.get(last)}" if parent else NORM_AFTER.get(last)
            if f"{norm}.running_var" in state:
                scale = (np.asarray(state[f"{norm}.weight"], np.float32)
                         / np.sqrt(np.asarray(state[f"{norm}.running_var"], np.float32) + np.float32(BATCH_NORM_EPS)))
                shift = np.asarray(state[f"{norm}.bias"], np.float32) - np.asarray(state[f"{norm}.running_mean"], np.float32) * scale
                weight = weight * scale
                bias = shift if bias is None else shift + bias * scale
            layers[name] = (weight.T.copy() if weight.ndim == 2 else weight, bias)
        return InferenceNet(config, layers, **recorded)

    def __call__(self, coords: np.ndarray, features: np.ndarray) -> np.ndarray:
        """(V, out_channels) raw outputs per voxel of ``coords`` (V, 4) with input ``features``."""
        h = self.features(coords, np.asarray(features, np.float32))
        for k, name in enumerate(("head.0", "head.3", "head.6")):
            weight, bias = self.layers[name]
            h = h @ weight + bias
            if k < 2:
                _relu(h)
        return h

    def features(self, coords: np.ndarray, x: np.ndarray) -> np.ndarray:
        """(V, up_channels[0]) features the head reads (``MushroomNet.features``)."""
        levels = [VoxelLevel(coords)]
        for _ in range(3):
            levels.append(VoxelLevel(levels[-1].parents()))
        maps: dict = {}

        def submanifold(name: str, x: np.ndarray, level: int, kernel: int) -> np.ndarray:
            if (level, kernel) not in maps:
                maps[level, kernel] = submanifold_map(levels[level], kernel)
            return convolve(x, *self.layers[name], maps[level, kernel], len(x))

        def block(name: str, x: np.ndarray, level: int) -> np.ndarray:
            out = _relu(submanifold(f"{name}.conv1", x, level, 3))
            out = submanifold(f"{name}.conv2", out, level, 3)
            out += x
            return _relu(out)

        def down_map(level: int) -> KernelMap:
            if ("down", level) not in maps:
                maps["down", level] = downsample_map(levels[level], levels[level + 1].coords, 3)
            return maps["down", level]

        def down(name: str, x: np.ndarray, level: int) -> np.ndarray:
            out = convolve(x, *self.layers[f"{name}.conv"], down_map(level), len(levels[level + 1].coords))
            return block(f"{name}.block", _relu(out), level + 1)

        def up(name: str, x: np.ndarray, level: int) -> np.ndarray:
            transposed = [(o, i) for i, o in down_map(level - 1)]
            out = convolve(x, *self.layers[f"{name}.conv"], transposed, len(levels[level - 1].coords))
            return block(f"{name}.block", _relu(out), level - 1)

        s1 = block("block1", _relu(submanifold("conv1", x, 0, self.config.first_kernel)), 0)
        s2 = down("down2", s1, 0)
        s4 = down("down3", s2, 1)
        s8 = down("down4", s4, 2)
        h = up("up4", s8, 3)
        h = up("up3", np.concatenate([s4, h], 1), 2)
        h = up("up2", np.concatenate([s2, h], 1), 1)
        weight, bias = self.layers["conv1_tr"]
        h = np.concatenate([s1, h], 1) @ weight[0]
        if bias is not None:
            h += bias
        return _relu(h)
