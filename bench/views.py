"""Does fusion help perception? The shipped model on the same virtual beds seen from 1 view, 2 cameras,
4 views and 18 views (848x480, D405-like noise, true poses refined by ICP), fused and detected by the
product's runner (each setting's frames as one fused unit).

A cap counts as ground truth in a setting when at least 5 fused points lie on its cap surface
(within 2 mm), so every setting is scored on the caps it could see; n_gt says how many that was.
Prints a Markdown table (AP@25, AP@50, cosine, axis angle as the paper's and as the mean over caps,
scale error, caps seen) for docs/RESULTS.md.
With --turns N each fused cloud is also detected turned by 90, 180 ... degrees (its caps turned back):
the spread says how much a setting's figures owe to where the voxel grid falls over the caps.
Usage: python bench/views.py [--beds 10] [--model PATH] [--readings N] [--turns N]
"""

import sys
from pathlib import Path

# the bench folder holds fusion.py, which would shadow the fusion package
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from capture.source import Source  # noqa: E402
from common.geometry import transform_points, turning_about_z  # noqa: E402
from perception.detect import LIVE_READINGS, detect_points  # noqa: E402
from perception.weights import DEFAULT_WEIGHTS  # noqa: E402
from perception.cap import Caps  # noqa: E402
from perception.evaluate import evaluate  # noqa: E402
from perception.weights import load_weights  # noqa: E402
from pipeline.process import reuse_freed_memory  # noqa: E402
from pipeline.runner import PerceptionStage, RunConfig, Runner  # noqa: E402
from capture.virtual import VirtualCameraConfig  # noqa: E402
from pipeline.sources import VirtualBed, virtual_bed_source  # noqa: E402

MIN_CAP_POINTS, ON_SURFACE = 5, 0.002
SETTINGS = {"1 view": (0,), "2 cameras (opposite sides)": (0, 9), "4 views": (0, 4, 9, 13),
            "18 views (full turn)": tuple(range(18))}
"""Which of the 18 turntable views each setting fuses."""


def visible_caps(bed, world_points: np.ndarray) -> np.ndarray:
    """Indices of the caps with at least MIN_CAP_POINTS fused points on their cap surface."""
    cap = bed.cap_of_points(world_points, ON_SURFACE)
    counts = np.bincount(cap[cap >= 0], minlength=len(bed.centers))
    return np.flatnonzero(counts >= MIN_CAP_POINTS)


class Frames(Source):
    """Frames already rendered, as a source for the runner."""

    def __init__(self, frames: list):
        self.frames = iter(frames)

    def read(self):
        return next(self.frames, None)


def turned_caps(model, fused, degrees: float, readings: int) -> Caps:
    """The caps ``detect_points`` finds in a fused cloud turned by ``degrees`` about the vertical through
    its centroid (bed frame), turned back and given in the world frame, as the runner gives them."""
    T_turned_bed = turning_about_z(np.radians(degrees), fused.points.mean(0))
    caps = detect_points(model, transform_points(T_turned_bed, fused.points), readings=readings).caps
    return caps.moved(fused.T_world_bed @ np.linalg.inv(T_turned_bed))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--beds", type=int, default=10)
    parser.add_argument("--model", type=Path, default=DEFAULT_WEIGHTS)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--readings", type=int, default=LIVE_READINGS, help="turned readings averaged per fused cloud "
                        f"(default {LIVE_READINGS}, as the runner reads)")
    parser.add_argument("--turns", type=int, default=1, choices=range(1, 5),
                        help="also detect on each fused cloud turned by k x 90 degrees about the vertical through "
                             "its centroid, k = 1 .. N-1, and print AP@25 / AP@50 per turn: how much a setting's "
                             "figures owe to where the voxel grid falls over its caps")
    args = parser.parse_args()
    reuse_freed_memory()
    torch.set_num_threads(args.threads)
    model, meta = load_weights(args.model)
    turned = {(name, k): [] for name in SETTINGS for k in range(1, args.turns)}
    preds = {name: [] for name in SETTINGS}
    gts = {name: [] for name in SETTINGS}
    points = {name: [] for name in SETTINGS}
    all_caps = 0
    for seed in range(args.beds):
        source, bed = virtual_bed_source(VirtualBed(seed=100 + seed, camera=VirtualCameraConfig(views=18)))
        all_caps += len(bed.centers)
        frames = list(source)
        for name, indices in SETTINGS.items():
            start = time.perf_counter()
            config = RunConfig(perception=PerceptionStage(readings=args.readings))
            summary = Runner(Frames([frames[k] for k in indices]), model, config, []).run()
            fused, result = summary.last_unit.cloud, summary.last_detection.result
            seen = visible_caps(bed, fused.world_points)
            preds[name].append(result.caps)
            gts[name].append(Caps(bed.centers[seen], bed.rotations[seen], bed.scales[seen]))
            points[name].append(len(fused))
            for k in range(1, args.turns):
                turned[name, k].append(turned_caps(model, fused, 90.0 * k, args.readings))
            print(f"bed {seed} {name}: {len(fused)} points, {len(seen)}/{len(bed.centers)} caps seen, "
                  f"{len(result.caps)} detected, {time.perf_counter() - start:.1f} s", flush=True)
    iterations = meta.get("total_iterations", meta.get("iterations", "?"))
    print(f"\nmodel: {args.model} ({iterations} iterations); {args.beds} beds "
          f"(seeds 100-{99 + args.beds}); MeanShift, {args.readings} reading(s)\n")
    print("| views | AP@25 | AP@50 | cosine | angle (deg) | mean angle over caps (deg) | scale error "
          "| caps seen / all | points per bed |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in SETTINGS:
        r = evaluate(preds[name], gts[name])
        total = sum(len(g) for g in gts[name])
        print(f"| {name} | {100 * r.ap25:.1f} % | {100 * r.ap50:.1f} % | {r.cosine:.4f} | {r.angle_deg:.2f} "
              f"| {r.angle_deg_mean:.2f} | {100 * r.scale_err:.1f} % "
              f"| {total} / {all_caps} | {np.median(points[name]):.0f} |")
    if args.turns > 1:
        print("\n| views | " + " | ".join(f"turned {90 * k} deg" for k in range(1, args.turns)) + " |")
        print("|---|" + "---|" * (args.turns - 1))
        for name in SETTINGS:
            cells = [evaluate(turned[name, k], gts[name]) for k in range(1, args.turns)]
            print(f"| {name} | " + " | ".join(f"{100 * r.ap25:.1f} / {100 * r.ap50:.1f} %" for r in cells) + " |")


if __name__ == "__main__":
    main()
