"""The depth cameras a run can read, registered by kind: each kind names its config and its source
class, and they are imported only when that kind is used, so pyrealsense2 and depthai load with their
own backend alone and listing the kinds costs nothing at start-up."""

from __future__ import annotations

from dataclasses import dataclass
from importlib import import_module


@dataclass(frozen=True)
class CameraKind:
    """One backend: where its config and source live, and which config field a device id sets."""

    module: str
    config: str
    source: str
    device_field: str | None
    """The config field ``--serial`` sets (None: the kind has no device to choose)."""

    def classes(self) -> tuple[type, type]:
        """The config and source classes, imported on first use."""
        owner = import_module(self.module)
        return getattr(owner, self.config), getattr(owner, self.source)


CAMERA_KINDS = {
    "realsense": CameraKind("capture.realsense", "RealSenseConfig", "RealSenseSource", "serial"),
    "oak": CameraKind("capture.oak", "OakConfig", "OakSource", "mxid"),
    "virtual": CameraKind("capture.virtual", "VirtualCameraConfig", "VirtualSource", None),
}
CAMERAS = tuple(CAMERA_KINDS)
"""The kinds ``record`` and ``live`` take for ``--camera``."""


def camera_kind(name: str) -> CameraKind:
    """The registered kind called ``name``; ValueError naming the kinds there are."""
    if name not in CAMERA_KINDS:
        raise ValueError(f"unknown camera {name!r}; choose one of {', '.join(CAMERAS)}")
    return CAMERA_KINDS[name]


def find_cameras() -> list:
    """Every attached camera of the kinds with a device to choose (``CameraInfo`` each; an empty list
    when none is attached or a kind's library is absent)."""
    found = []
    for kind in CAMERA_KINDS.values():
        if kind.device_field is None:
            continue
        try:
            module = import_module(kind.module)
        except ImportError:
            continue
        found.extend(module.find_cameras())
    return found
