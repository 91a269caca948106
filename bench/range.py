"""The operating range of the shipped model: AP@25 / AP@50 (MeanShift) on synthetic beds by point
spacing and by cap diameter, each bin its own beds (caps of that size only), so a bin is scored on the
caps it holds. The model is trained on caps 16-72 mm across (scale 0.5-1.5 of a 40 mm cap, per axis
0.8-1.2, beds scaled 1.05-1.35) at 3 mm spacing; the table says how far beyond that it holds.
``--cap-height LOW HIGH`` draws every cap's height as that factor of the template's (2/3 of its
radius): opened, flatter caps than the model was trained on.

Usage: python bench/range.py [--beds 6] [--spacings 1 3 4 5] [--cap-height LOW HIGH] [--model PATH]
"""

import sys
from pathlib import Path

# the bench folder holds fusion.py and perception.py, which would shadow those packages
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import argparse  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402

import torch  # noqa: E402

from perception.cap import CAP_RADIUS_AT_UNIT_SCALE  # noqa: E402
from perception.detect import FILE_READINGS, find_caps, predict  # noqa: E402
from perception.weights import DEFAULT_WEIGHTS  # noqa: E402
from perception.cap import Caps  # noqa: E402
from perception.evaluate import evaluate  # noqa: E402
from perception.synthetic.dataset import ground_truth_mask  # noqa: E402
from perception.synthetic.scene import SceneConfig, generate_scene  # noqa: E402
from perception.weights import load_weights  # noqa: E402
from pipeline.process import reuse_freed_memory  # noqa: E402

DIAMETER_BINS_MM = ((15, 30), (30, 45), (45, 60), (60, 80), (80, 100), (100, 120))


def score(model, scenes, readings: int) -> tuple[float, float, int]:
    preds, gts = [], []
    for scene in scenes:
        _, fit = find_caps(predict(model, scene.points, readings=readings), model.config.voxel, points=scene.points)
        preds.append(fit)
        visible = ground_truth_mask(scene)
        gts.append(Caps(scene.centers[visible], scene.rotations[visible], scene.scales[visible]))
    result = evaluate(preds, gts)
    return result.ap25, result.ap50, result.n_gt


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--beds", type=int, default=6, help="beds per cell of the table")
    parser.add_argument("--spacings", type=float, nargs="+", default=[1, 3, 4, 5], help="millimetres")
    parser.add_argument("--diameters", type=int, nargs="+", help="only the bins starting at these diameters (mm)")
    parser.add_argument("--cap-height", type=float, nargs=2, default=(1.0, 1.0), metavar=("LOW", "HIGH"),
                        help="cap heights drawn as this factor of the template's (default 1 1: the template)")
    parser.add_argument("--model", type=Path, default=DEFAULT_WEIGHTS)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--readings", type=int, default=FILE_READINGS,
                        help=f"turned readings averaged (default {FILE_READINGS}, as detect reads)")
    args = parser.parse_args()
    low, high = args.cap_height
    if not (math.isfinite(high) and 0 < low <= high):
        parser.error(f"--cap-height needs finite 0 < LOW <= HIGH, got {low:g} {high:g}")
    reuse_freed_memory()
    torch.set_num_threads(args.threads)
    model, _ = load_weights(args.model)
    print(f"model: {args.model}, {args.readings} readings; {args.beds} beds per cell, 5-25 round caps each, "
          "MeanShift; AP@25 / AP@50 (caps)"
          + (f"; cap heights x {args.cap_height[0]:g}-{args.cap_height[1]:g}" if tuple(args.cap_height) != (1, 1) else "")
          + "\n")
    print("| cap diameter | " + " | ".join(f"{s:g} mm spacing" for s in args.spacings) + " |")
    print("|---|" + "---|" * len(args.spacings))
    started = time.perf_counter()
    for low, high in DIAMETER_BINS_MM:
        if args.diameters and low not in args.diameters:
            continue
        # a cap's diameter is 2 x 20 mm x s (round caps: no per-axis factor), so s spans the bin
        scale = (low / 2000 / CAP_RADIUS_AT_UNIT_SCALE, high / 2000 / CAP_RADIUS_AT_UNIT_SCALE)
        cells = []
        for spacing in args.spacings:
            config = SceneConfig(mushrooms=(5, 25), scale=scale, axis_factor=(1.0, 1.0), spacing=spacing / 1000,
                                 cap_height=tuple(args.cap_height))
            scenes = [generate_scene(int(1000 * high + seed), config) for seed in range(args.beds)]
            ap25, ap50, caps = score(model, scenes, args.readings)
            cells.append(f"{100 * ap25:.1f} / {100 * ap50:.1f} % ({caps})")
        print(f"| {low}-{high} mm | " + " | ".join(cells) + " |", flush=True)
    print(f"\n{time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
