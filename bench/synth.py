"""Synthetic bed generator speed: median ms per scene and points per second, per visibility model, one core.

Reference: the paper authors' generator takes about 340 ms per scene (median, K in [5, 45], about
12.7 k points) on this machine class; the target here is at most 70 ms for the same density, which
is our generator at 5.1 mm spacing (the default here; the beds we train on are 3 mm, --spacing 0.003).
With --views or --cap-height, the hpr and fused beds are drawn as `mushroom-pose train` draws them with
those flags (several viewpoints pooled or merged; shallower caps). `--models fused --spacing 0.002
--views 2 6` costs what a `train --fused-share` scan bed costs.
Usage: python bench/synth.py [--scenes N] [--models hpr camera fused katz] [--spacing M] [--views LOW HIGH]
       [--cap-height LOW HIGH]
"""
import sys
from pathlib import Path

# bench/perception.py would shadow the perception package: take this folder off the import path
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]


import argparse
import os
import resource
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from perception.synthetic.dataset import scene_seeds  # noqa: E402
from perception.synthetic.scene import SceneConfig, generate_scene  # noqa: E402
from pipeline.process import reuse_freed_memory  # noqa: E402

PAPER_MS_PER_SCENE = 340.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=30)
    parser.add_argument("--models", nargs="+", default=["hpr", "camera", "katz"])
    parser.add_argument("--spacing", type=float, default=0.0051, help="point spacing in metres (default 0.0051)")
    parser.add_argument("--views", type=int, nargs=2, default=[1, 1], metavar=("LOW", "HIGH"),
                        help="viewpoints per hpr or fused bed (default 1 1)")
    parser.add_argument("--cap-height", type=float, nargs=2, default=[1.0, 1.0], metavar=("LOW", "HIGH"),
                        help="factor on each cap's height (default 1 1)")
    args = parser.parse_args()
    reuse_freed_memory()
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    seeds = scene_seeds(123, args.scenes)
    generate_scene(seeds[0])
    print(f"{args.spacing * 1000:g} mm spacing; hpr and fused beds seen from {args.views[0]}-{args.views[1]} views, "
          f"cap heights x {args.cap_height[0]:g}-{args.cap_height[1]:g}")
    print(f"{'visibility':<10} {'median ms':>10} {'p90 ms':>8} {'median pts':>11} {'pts/s':>10} {'x paper':>8}")
    for model in args.models:
        drawn = {"views": tuple(args.views), "cap_height": tuple(args.cap_height)}
        extra = drawn if model in ("hpr", "fused") else {}
        config = SceneConfig(visibility=model, spacing=args.spacing, **extra)
        times, points = [], []
        for seed in seeds:
            start = time.perf_counter()
            scene = generate_scene(seed, config)
            times.append(time.perf_counter() - start)
            points.append(len(scene.points))
        median_ms = 1000 * np.median(times)
        print(f"{model:<10} {median_ms:>10.1f} {1000 * np.percentile(times, 90):>8.1f} {np.median(points):>11.0f} "
              f"{np.sum(points) / np.sum(times):>10.0f} {PAPER_MS_PER_SCENE / median_ms:>7.1f}x")
    print(f"peak RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
