"""What every source yields: depth frames with their intrinsics (docs/DESIGN.md section 3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# importable from here too for pipeline/cli.py, fusion/cloud.py and fusion/integrate.py


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels, OpenCV camera frame (x right, y down, z forward)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @staticmethod
    def realsense_d405(width: int = 848, height: int = 480) -> "CameraIntrinsics":
        """A D405-class close-range depth camera (about 87 x 58 degrees field of view)."""
        fx = width / (2.0 * np.tan(np.radians(87.0) / 2.0))
        return CameraIntrinsics(width, height, fx, fx, (width - 1) / 2.0, (height - 1) / 2.0)


@dataclass(frozen=True)
class DepthFrame:
    """One depth image; ``depth * depth_scale`` is metres along the optical axis, 0 = invalid."""

    depth: np.ndarray
    depth_scale: float
    intrinsics: CameraIntrinsics
    timestamp_ns: int = 0
    sensor_id: str = "camera"
    color: np.ndarray | None = None
    T_world_camera: np.ndarray | None = None
    turntable_angle: float | None = None

    @property
    def depth_m(self) -> np.ndarray:
        """The depth image in metres (float32, 0 = invalid)."""
        return self.depth.astype(np.float32) * np.float32(self.depth_scale)

    def __post_init__(self) -> None:
        if self.depth.ndim != 2 or self.depth.dtype != np.uint16:
            raise ValueError(f"depth must be a 2-D uint16 image, got {self.depth.dtype} {self.depth.shape}")
        if self.depth.shape != (self.intrinsics.height, self.intrinsics.width):
            raise ValueError(f"depth is {self.depth.shape[1]}x{self.depth.shape[0]} but the intrinsics "
                             f"say {self.intrinsics.width}x{self.intrinsics.height}")
        if self.color is not None and self.color.shape[:2] != self.depth.shape:
            raise ValueError(f"colour is {self.color.shape[1]}x{self.color.shape[0]}, depth is "
                             f"{self.depth.shape[1]}x{self.depth.shape[0]}: align them first")


def backproject(depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Valid pixels of a metric depth image as camera-frame points (N, 3) and their flat pixel indices."""
    flat = depth_m.reshape(-1)
    index = np.flatnonzero(flat > 0)
    z = flat[index]
    v, u = np.divmod(index, intrinsics.width)
    points = np.stack([(u - intrinsics.cx) * z / intrinsics.fx, (v - intrinsics.cy) * z / intrinsics.fy, z], 1)
    return points.astype(np.float32), index
