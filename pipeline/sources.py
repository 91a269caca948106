"""Building a frame source from CLI choices; the virtual camera gets a synthetic bed from perception."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from capture.cameras import camera_kind
from capture.source import Source

if TYPE_CHECKING:
    from capture.virtual import VirtualCameraConfig


@dataclass(frozen=True)
class VirtualBed:
    """A synthetic bed under a virtual camera circling it on a turntable: the default scene of demo,
    record, live and tests. The camera's own settings (views per turn, frame rate, the first frame's
    time, turns) are its ``camera``'s; the rig places it from ``radius`` and ``height``."""

    seed: int = 0
    """Virtual camera: the synthetic bed's seed (the bed, and the camera's noise)."""
    mushrooms: tuple[int, int] | None = None
    """Caps on the bed, inclusive range (default: the generator's)."""
    radius: float = 0.22
    """Camera distance from the turntable axis, metres."""
    height: float = 0.42
    """Camera height above the bed, metres."""
    camera: VirtualCameraConfig | None = None
    """The virtual camera (default: a D405 at 15 fps, 18 views, one turn)."""


def virtual_bed_source(setup: VirtualBed = VirtualBed(), sensor_id: str = "virtual"):
    """The source and the bed it looks at (meshes and true caps stay with the caller, for evaluation)."""
    from capture.virtual import VirtualCameraConfig, VirtualSource, circle_turntable
    from perception.synthetic.scene import SceneConfig, build_bed

    bed = build_bed(np.random.default_rng(setup.seed),
                    SceneConfig(mushrooms=setup.mushrooms) if setup.mushrooms else SceneConfig())
    camera = setup.camera if setup.camera is not None else VirtualCameraConfig()  # its len() is 0 before the turntable is set: not `or`
    config = replace(camera, seed=setup.seed, sensor_id=sensor_id,
                     turntable=circle_turntable(np.zeros(3), setup.radius, setup.height))
    return VirtualSource(bed.vertices, bed.triangles, config), bed


def make_source(camera: str, serial: str | None = None, seed: int = 0, views: int = 18, *,
                playback: str | None = None, live: bool = False) -> Source:
    """A source for ``mushroom-pose record`` / ``live``: realsense (a camera, or a recorded device
    file through the same driver), oak or virtual. ``live`` paces the virtual camera in real time at
    its frame rate with wall-clock timestamps and keeps turning, so it behaves as a real one. The
    hardware kinds come from the registry (``capture.cameras``); the virtual camera's bed from the
    synthetic generator."""
    if camera == "virtual":
        import time

        from capture.source import Paced
        from capture.virtual import VirtualCameraConfig

        virtual = VirtualCameraConfig(views=views, start_ns=time.time_ns() if live else 0, turns=None if live else 1)
        setup = VirtualBed(seed=seed, camera=virtual)
        source = virtual_bed_source(setup)[0]
        return Paced(source) if live else source
    kind = camera_kind(camera)
    config_class, source_class = kind.classes()
    fields = {kind.device_field: serial}
    if playback is not None:
        fields["playback"] = playback
    return source_class(config_class(**fields))
