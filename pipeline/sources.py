"""Building a frame source from CLI choices; the virtual camera gets a synthetic bed from perception."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from capture.cameras import camera_kind
from capture.source import Source


@dataclass(frozen=True)
class VirtualBed:
    """A synthetic bed under a virtual D405 on a turntable: the default scene of demo, record and tests."""

    seed: int = 0
    """The virtual camera's bed: the synthetic generator's seed."""
    views: int = 18
    """Virtual camera: views per turn of the turntable."""
    radius: float = 0.22
    """Camera distance from the turntable axis, metres."""
    height: float = 0.42
    """Camera height above the bed, metres."""
    fps: float = 15.0
    start_ns: int = 0
    """Capture time of the first frame (live runs give the wall clock)."""
    mushrooms: tuple[int, int] | None = None
    """Caps on the bed, inclusive range (default: the generator's)."""
    turns: int | None = 1
    """Turns to render (None: it keeps turning)."""


def virtual_bed_source(setup: VirtualBed = VirtualBed(), sensor_id: str = "virtual"):
    """The source and the bed it looks at (meshes and true caps stay with the caller, for evaluation)."""
    from capture.virtual import VirtualCameraConfig, VirtualSource, circle_turntable
    from perception.synthetic.scene import SceneConfig, build_bed

    bed = build_bed(np.random.default_rng(setup.seed),
                    SceneConfig(mushrooms=setup.mushrooms) if setup.mushrooms else SceneConfig())
    config = VirtualCameraConfig(turntable=circle_turntable(np.zeros(3), setup.radius, setup.height), views=setup.views,
                                 fps=setup.fps, seed=setup.seed, sensor_id=sensor_id, start_ns=setup.start_ns,
                                 turns=setup.turns)
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

        setup = VirtualBed(seed=seed, views=views, start_ns=time.time_ns() if live else 0, turns=None if live else 1)
        source = virtual_bed_source(setup)[0]
        return Paced(source) if live else source
    kind = camera_kind(camera)
    config_class, source_class = kind.classes()
    fields = {kind.device_field: serial}
    if playback is not None:
        fields["playback"] = playback
    return source_class(config_class(**fields))
