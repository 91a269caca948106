"""Reading the point clouds users hand to ``detect``: .ply, .pcd, our .npz scenes, fused clouds in MCAP."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

CLOUD_SUFFIXES = (".ply", ".pcd", ".npz", ".mcap")
MILLIMETRE_EXTENT = 20.0
"""A bed is under a few metres across: a cloud spanning more than this many units is in millimetres."""


@dataclass(frozen=True)
class LoadedCloud:
    points: np.ndarray
    """(N, 3) float64 metres."""
    in_bed_frame: bool
    """True for our synthetic scenes, which are stored in the bed frame."""
    unit_scale: float = 1.0
    """Metres per input unit (0.001 when the file was in millimetres)."""


def load_cloud(path: Path) -> LoadedCloud:
    """A cloud in metres; raises ValueError with a one-line reason when the file cannot be used."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path} does not exist")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        try:
            with np.load(path) as data:
                points = np.asarray(data["points"], np.float64)
        except Exception as error:
            raise ValueError(f"{path} is not a mushroom-pose scene (.npz with 'points'): {type(error).__name__}") from None
        in_bed = True
    elif suffix == ".mcap":
        from capture.mcap_io import read_point_cloud
        from capture.source import SourceError

        try:
            points, _ = read_point_cloud(path)
        except SourceError as error:
            raise ValueError(str(error)) from None
        in_bed = False
    elif suffix in (".ply", ".pcd"):
        import open3d as o3d

        cloud = o3d.io.read_point_cloud(str(path))
        points = np.asarray(cloud.points, np.float64)
        if len(points) == 0:
            raise ValueError(f"{path}: the cloud is empty or not a readable {suffix} file")
        in_bed = False
    else:
        raise ValueError(f"{path}: unsupported cloud format {suffix or '(none)'}; use one of {', '.join(CLOUD_SUFFIXES)}")
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{path}: expected N x 3 points, got shape {points.shape}")
    finite = np.isfinite(points).all(1)
    if not finite.all():
        raise ValueError(f"{path}: {np.count_nonzero(~finite)} of {len(points)} points are NaN or infinite; "
                         "remove them (invalid depth) and try again")
    if len(points) == 0:
        raise ValueError(f"{path}: the cloud is empty")
    scale = 1.0
    extent = float(np.max(points.max(0) - points.min(0)))
    if extent > MILLIMETRE_EXTENT:
        scale = 0.001
        points = points * scale
    return LoadedCloud(points, in_bed, scale)

