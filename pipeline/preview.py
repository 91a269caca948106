"""A shaded picture of a synthetic bed seen by the virtual camera: caps white, stems grey, soil brown."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from capture.frames import CameraIntrinsics
from capture.virtual import MeshScene
from common.files import atomic_path
from common.geometry import look_at
from perception.synthetic.scene import SceneConfig, build_bed


def render_bed_preview(seed: int, config: SceneConfig, path: Path, width: int = 960, height: int = 600) -> None:
    """Write a PNG of bed ``seed`` from an oblique viewpoint (the bed is rebuilt from its seed)."""
    import open3d as o3d

    bed = build_bed(np.random.default_rng(seed), config)
    intrinsics = CameraIntrinsics.realsense_d405(width, height)
    T_world_camera = look_at(np.array([0.0, -0.42, 0.38]) * config.bed_size / 0.5, np.zeros(3))
    render = MeshScene(bed.vertices, bed.triangles, threads=0).render(intrinsics, T_world_camera)
    hit = render.triangle_ids >= 0
    triangle = np.where(hit, render.triangle_ids, 0)
    colour = np.empty(hit.shape + (3,))
    colour[:] = [0.36, 0.26, 0.18]
    colour[bed.triangle_instance[triangle] >= 0] = [0.78, 0.76, 0.70]
    colour[bed.triangle_is_cap[triangle]] = [0.97, 0.95, 0.90]
    shade = 0.3 + 0.7 * render.cos_incidence[..., None]
    image = np.where(hit[..., None], colour * shade, 0.08)
    with atomic_path(path, keep_suffix=True) as tmp:
        o3d.io.write_image(str(tmp), o3d.geometry.Image(np.ascontiguousarray((255 * image).astype(np.uint8))))
