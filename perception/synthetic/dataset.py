"""Named, cached sets of synthetic beds (val50, test50) and writing scenes to disk."""

from __future__ import annotations

import errno
import os
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Iterator

import numpy as np
from tqdm import tqdm

from common.files import atomic_path
from perception.synthetic.scene import GENERATOR_VERSION, SceneConfig, SyntheticScene, generate_scene


@dataclass(frozen=True)
class BedSet:
    """A fixed set of synthetic beds (val50, test50): scene k is made from the k-th seed of ``seed``."""

    seed: int
    scenes: int
    config: SceneConfig = SceneConfig()


BED_SETS = {
    "val50": BedSet(seed=2023_0617, scenes=50),
    "test50": BedSet(seed=2023_1001, scenes=50),
}


def scene_seeds(base_seed: int, count: int) -> list[int]:
    """Independent per-scene seeds derived from one base seed."""
    return [int(s) for s in np.random.SeedSequence(base_seed).generate_state(count, dtype=np.uint32)]


CACHE_ENV = "MUSHROOM_POSE_CACHE"
"""Where the evaluation presets are cached (default ~/.cache/mushroom-pose)."""


def cache_root() -> Path:
    return Path(os.environ.get(CACHE_ENV, Path.home() / ".cache" / "mushroom-pose"))


def preset_config(name: str, visibility: str = "hpr", spacing: float | None = None) -> SceneConfig:
    """A preset's scene settings, with another visibility model or point spacing when asked."""
    config = BED_SETS[name].config
    return replace(config, visibility=visibility, spacing=config.spacing if spacing is None else spacing)


def preset_dir(name: str, config: SceneConfig) -> Path:
    return cache_root() / "synthetic" / f"{name}-{config.visibility}-{1000 * config.spacing:g}mm-v{GENERATOR_VERSION}"


def scene_path(out_dir: Path, index: int) -> Path:
    return Path(out_dir) / f"scene_{index:04d}.npz"


def label_colors(scene: SyntheticScene) -> np.ndarray:
    """RGB in [0, 1]: caps white, stems grey, soil and distractors brown."""
    colors = np.tile([0.45, 0.33, 0.22], (len(scene.points), 1))
    colors[scene.instance >= 0] = [0.65, 0.65, 0.62]
    colors[scene.is_cap] = [0.97, 0.96, 0.92]
    return colors


PLY_VERTEX_BYTES = 3 * 8 + 3
"""Bytes per vertex of the binary .ply written here: x, y, z as doubles and r, g, b as bytes."""


def write_ply(scene: SyntheticScene, path: Path) -> None:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scene.points.astype(np.float64)))
    cloud.colors = o3d.utility.Vector3dVector(label_colors(scene))
    with atomic_path(path, keep_suffix=True) as tmp:
        written = o3d.io.write_point_cloud(str(tmp), cloud, compressed=False)
        # Open3D reports a write cut short (a full disk) only on the terminal: the vertices must be there
        if not written or tmp.stat().st_size < PLY_VERTEX_BYTES * len(scene.points):
            raise OSError(errno.EIO, "the .ply came out short (is the disk full?)", str(path))


def write_scene(scene: SyntheticScene, out_dir: Path, index: int, ply: bool = True) -> Path:
    """Write ``scene_NNNN.npz`` (and ``.ply``) atomically: a crash never leaves half a file, and a
    failed .ply takes its .npz with it."""
    path = scene_path(out_dir, index)
    with atomic_path(path, keep_suffix=True) as tmp:
        scene.save(tmp)
    if ply:
        try:
            write_ply(scene, path.with_suffix(".ply"))
        except BaseException:
            path.unlink(missing_ok=True)
            raise
    return path


def generate_many(seeds: list[int], config: SceneConfig, progress: bool = True, description: str = "scenes",
                  use_ray: bool = False, ray_address: str | None = None) -> Iterator[SyntheticScene]:
    """The scenes of ``seeds`` in their order, made here or, with ``use_ray``, as Ray tasks (the same
    scenes: a scene depends on its seed alone)."""
    if use_ray:
        from common.distributed import ray_map

        scenes = ray_map(generate_scene, [(seed, config) for seed in seeds], ray_address)
    else:
        scenes = (generate_scene(seed, config) for seed in seeds)
    yield from tqdm(scenes, desc=description, unit="scene", total=len(seeds), disable=not progress, leave=False)


def load_preset(name: str, visibility: str = "hpr", progress: bool = True,
                limit: int | None = None, spacing: float | None = None) -> list[SyntheticScene]:
    """The scenes (the first ``limit``) of a named preset, generated once and cached on disk (never
    committed); ``spacing`` makes the same beds at another point spacing."""
    if name not in BED_SETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(BED_SETS)}")
    preset = BED_SETS[name]
    config = preset_config(name, visibility, spacing)
    directory = preset_dir(name, config)
    seeds = scene_seeds(preset.seed, preset.scenes)
    count = preset.scenes if limit is None else min(limit, preset.scenes)
    scenes: dict[int, SyntheticScene] = {}
    for index in range(count):
        path = scene_path(directory, index)
        if path.is_file():
            try:
                scenes[index] = SyntheticScene.load(path)
            except Exception as error:
                print(f"warning: the cached {path} is unreadable ({type(error).__name__}); making it again",
                      file=sys.stderr)
    missing = [i for i in range(count) if i not in scenes]
    if missing:
        try:
            directory.mkdir(parents=True, exist_ok=True)
            for index, scene in zip(missing, generate_many([seeds[i] for i in missing], config, progress,
                                                           f"making {name}")):
                scenes[index] = SyntheticScene.load(write_scene(scene, directory, index, ply=False))
        except OSError as error:
            raise ValueError(f"cannot write the {name} cache in {directory}: {error.strerror or error}; set "
                             f"{CACHE_ENV} to a writable folder") from None
    return [scenes[index] for index in range(count)]


MIN_VISIBLE_CAP_POINTS = 5
"""A cap counts as ground truth when at least this many of its points are visible: no method can
find a cap the sensor did not see."""


def ground_truth_mask(scene: SyntheticScene) -> np.ndarray:
    return scene.visible_cap_points >= MIN_VISIBLE_CAP_POINTS
