"""What the network is, without torch: its config and presets, the features it reads per voxel, and the
unit of its residual output. ``perception.model`` builds the torch network from it (training, the live
chain, ``eval``), ``perception.inference`` runs a trained one in numpy (``detect`` on a cloud file)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

LENGTH_UNIT = 0.1
"""Residual centres are predicted, and their loss measured, in decimetres: the paper's x100 weight on
their squared error then balances the other two terms."""

INFERENCE_ZOOM = 1.05
"""The zoom new models are read at when training names none (weights record their own, the shipped one
1.2): the network reads the cloud scaled up by it, so small caps span more voxels, within training's
scale jitter. Clustering stays in the cloud's own metres."""


NORM_AFTER = {"conv1": "norm1", "conv2": "norm2", "conv": "norm"}
"""The batch norm right after each convolution, by attribute name in the network's blocks and stages:
what folding the batch norms into the convolutions pairs up."""

ENCODINGS = ("implicit", "explicit-centre", "explicit-orientation")


@dataclass(frozen=True)
class NetworkConfig:
    channels: tuple[int, int, int, int] = (32, 64, 128, 256)
    up_channels: tuple[int, int, int, int] = (64, 64, 64, 128)
    first_kernel: int = 7
    head_hidden: tuple[int, int] = (64, 32)
    dropout: float = 0.1
    voxel: float = 0.0045
    """Voxel edge in metres."""
    normals: bool = False
    """Besides the constant 1, give each voxel the unit normal of the surface through the voxel
    centroids (oriented to +z, the bed normal): tilt shows in normals long before it shows in the
    occupancy of 4.5 mm voxels."""
    offsets: bool = False
    """Also give the centroid's place inside its voxel, scaled to [-1, 1) per axis: voxels drop where
    in the 4.5 mm cell a point lies, and a small cap spans only 4-6 voxels."""
    encoding: str = "implicit"
    """What the head predicts per voxel besides existence: ``implicit`` (the paper's: the residual to
    the cap centre and the orientation value), or one of the paper's Table 2 ablations,
    ``explicit-centre`` (the cap centre itself) or ``explicit-orientation`` (the cap's unit axis)."""

    def __post_init__(self) -> None:
        if self.encoding not in ENCODINGS:
            raise ValueError(f"unknown encoding {self.encoding!r}; use one of {', '.join(ENCODINGS)}")

    @property
    def in_channels(self) -> int:
        return 1 + 3 * self.normals + 3 * self.offsets

    @property
    def out_channels(self) -> int:
        """Existence, centre (3), orientation value (1) or axis (3)."""
        return 7 if self.encoding == "explicit-orientation" else 5

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(values: dict) -> "NetworkConfig":
        values = dict(values)
        for key in ("channels", "up_channels", "head_hidden"):
            values[key] = tuple(values[key])
        return NetworkConfig(**values)


NETWORK_PRESETS = {
    "fcgf": NetworkConfig(),
    "slim": NetworkConfig(channels=(32, 48, 64, 96), up_channels=(48, 48, 64, 64), first_kernel=3),
    "slim-n": NetworkConfig(channels=(32, 48, 64, 96), up_channels=(48, 48, 64, 64), first_kernel=3, normals=True),
    "slim-no": NetworkConfig(channels=(32, 48, 64, 96), up_channels=(48, 48, 64, 64), first_kernel=3, normals=True,
                             offsets=True),
}
# slim-no with the coarser levels (stride 2 to 8) wider and the full-resolution ones unchanged
NETWORK_PRESETS["wide-no"] = replace(NETWORK_PRESETS["slim-no"], channels=(32, 64, 128, 192), up_channels=(48, 48, 96, 128))
# the paper's Table 2 ablations: slim-no predicting the centre or the axis explicitly
NETWORK_PRESETS["slim-no-explicit-centre"] = replace(NETWORK_PRESETS["slim-no"], encoding="explicit-centre")
NETWORK_PRESETS["slim-no-explicit-orientation"] = replace(NETWORK_PRESETS["slim-no"], encoding="explicit-orientation")
# slim-no with a 5^3 first convolution, which reaches more of a sparse cap's surface voxels than 3^3
NETWORK_PRESETS["slim-no-k5"] = replace(NETWORK_PRESETS["slim-no"], first_kernel=5)
# slim-no with 32 channels in the full-resolution up block instead of 48: that block's two 3^3
# convolutions on every voxel take a third of slim-no's time
NETWORK_PRESETS["lean-no"] = replace(NETWORK_PRESETS["slim-no"], up_channels=(48, 32, 64, 64))


def voxel_features(config: NetworkConfig, centroids: np.ndarray) -> np.ndarray:
    """(V, in_channels) float32 network input for voxels with these centroids (bed frame, metres)."""
    centroids = np.asarray(centroids, np.float64)
    columns = [np.ones((len(centroids), 1), np.float32)]
    if config.normals:
        columns.append(_oriented_normals(config, centroids))
    if config.offsets:
        cell = centroids / config.voxel
        columns.append((2.0 * (cell - np.floor(cell)) - 1.0).astype(np.float32))
    return np.hstack(columns)


NORMAL_NEIGHBOURS = 16
"""Most neighbours (the voxel itself included) a voxel's normal is fitted to."""
NORMAL_RADIUS_VOXELS = 3.0
"""Voxel edges within which those neighbours lie."""


def _oriented_normals(config: NetworkConfig, centroids: np.ndarray) -> np.ndarray:
    """Unit normals (V, 3) float32 of the surface through the voxel centroids, turned to +z: per voxel
    the least-variance axis of its nearest ``NORMAL_NEIGHBOURS`` within ``NORMAL_RADIUS_VOXELS``
    voxels, (0, 0, 1) with fewer than three. Open3D's ``estimate_normals`` with a hybrid search gives
    the same normals (``tests/test_inference.py``); this runs without importing Open3D."""
    from scipy.spatial import cKDTree

    if len(centroids) == 0:
        return np.zeros((0, 3), np.float32)
    distance, index = cKDTree(centroids, balanced_tree=False).query(
        centroids, NORMAL_NEIGHBOURS, workers=-1, distance_upper_bound=NORMAL_RADIUS_VOXELS * config.voxel)
    found = np.isfinite(distance)
    count, weight, index = found.sum(1), found.astype(np.float64), np.where(found, index, 0)
    axes = [centroids[:, axis][index] for axis in range(3)]
    deviations = [(values - (values * weight).sum(1, keepdims=True) / count[:, None]) * weight for values in axes]
    covariance = np.empty((len(centroids), 3, 3))
    for i in range(3):
        for j in range(i, 3):
            covariance[:, i, j] = covariance[:, j, i] = np.einsum("mk,mk->m", deviations[i], deviations[j])
    normals = np.linalg.eigh(covariance)[1][:, :, 0].astype(np.float32)
    normals[count < 3] = (0.0, 0.0, 1.0)
    normals *= np.where(normals[:, 2:3] < 0, -1.0, 1.0).astype(np.float32)
    return normals
