"""How good are colour-made cap axes? The labels of ../shared/real/ take a cap's axis as the
least-variance PCA axis of its visible points (checked against a sphere fit). This bench makes the
same two axes on fused synthetic beds, where the true axis is known, and sets them beside the
detector's.

Each virtual bed (18 views, 848x480, D405-like noise) is fused and detected by the product's runner, as
in bench/views.py. A cap's visible points are the fused points within 2 mm of its cap surface; caps
with fewer than 250 (the labels' "small" partial cut) are left out, as the labels leave them out of
the non-partial figures. Prints, over those caps, the angle from the true axis of: the PCA axis, the
sphere-fit axis (centroid minus sphere centre) and the detector's axis; and the angles the real-cloud
bench would score: the detector against the PCA axis, and PCA against the sphere fit.
Usage: python bench/label_axes.py [--beds 10]
"""

import sys
from pathlib import Path

# the bench folder holds fusion.py and pipeline.py, which would shadow the packages
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import argparse  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from perception.cap import tilt_deg  # noqa: E402
from perception.detect import DEFAULT_WEIGHTS  # noqa: E402
from perception.train import load_weights  # noqa: E402
from pipeline.runner import RunConfig, Runner  # noqa: E402
from pipeline.sources import VirtualBed, virtual_bed_source  # noqa: E402

ON_SURFACE, LABELLED_POINTS = 0.002, 250


def least_variance_axis(points: np.ndarray, up: np.ndarray) -> np.ndarray:
    """The direction of least spread of ``points`` (n, 3), turned to ``up``'s side."""
    axis = np.linalg.eigh(np.cov((points - points.mean(0)).T))[1][:, 0]
    return axis * np.sign(axis @ up)


def sphere_axis(points: np.ndarray) -> np.ndarray:
    """From the least-squares sphere's centre to the points' centroid."""
    solution = np.linalg.lstsq(np.c_[2 * points, np.ones(len(points))], (points**2).sum(1), rcond=None)[0]
    axis = points.mean(0) - solution[:3]
    return axis / np.linalg.norm(axis)


def describe(name: str, angles: list[float]) -> str:
    values = np.asarray(angles)
    return (f"| {name} | {values.mean():.1f} | {np.median(values):.1f} | {np.percentile(values, 90):.1f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--beds", type=int, default=10)
    parser.add_argument("--model", type=Path, default=DEFAULT_WEIGHTS)
    args = parser.parse_args()
    torch.set_num_threads(2)
    model, _ = load_weights(args.model)
    angles: dict[str, list[float]] = {key: [] for key in ("pca", "sphere", "detector", "detector_pca", "pca_sphere")}
    for seed in range(args.beds):
        source, bed = virtual_bed_source(VirtualBed(seed=100 + seed, views=18))
        summary = Runner(source, model, RunConfig(), []).run()
        fused, caps = summary.last_unit.cloud, summary.last_detection.result.caps
        world = fused.world_points
        cap_of_point = bed.cap_of_points(world, ON_SURFACE)
        up = fused.T_world_bed[:3, 2]
        for k in range(len(bed.centers)):
            points = world[cap_of_point == k]
            if len(points) < LABELLED_POINTS:
                continue
            truth, pca, sphere = bed.rotations[k][:, 2], least_variance_axis(points, up), sphere_axis(points)
            angles["pca"].append(float(tilt_deg(pca, truth)))
            angles["sphere"].append(float(tilt_deg(sphere, truth)))
            angles["pca_sphere"].append(float(tilt_deg(pca, sphere)))
            distance = np.linalg.norm(caps.centers - bed.centers[k], axis=1) if len(caps) else np.array([np.inf])
            if distance.min() < 0.5 * bed.scales[k, 0]:
                found = caps.axes[int(distance.argmin())]
                angles["detector"].append(float(tilt_deg(found, truth)))
                angles["detector_pca"].append(float(tilt_deg(found, pca)))
        print(f"bed {seed}: {len(angles['pca'])} caps with {LABELLED_POINTS}+ visible points so far", flush=True)
    print(f"\n{args.beds} beds (seeds 100-{99 + args.beds}), 18 views; {len(angles['pca'])} caps labelled, "
          f"{len(angles['detector'])} of them detected\n")
    print("| axis | mean (deg) | median (deg) | 90th percentile (deg) |")
    print("|---|---|---|---|")
    print(describe("PCA of the visible cap points against the truth", angles["pca"]))
    print(describe("sphere fit against the truth", angles["sphere"]))
    print(describe("detector against the truth", angles["detector"]))
    print(describe("detector against the PCA axis (what bench/real.py scores)", angles["detector_pca"]))
    print(describe("PCA against the sphere fit (the labels' own check)", angles["pca_sphere"]))


if __name__ == "__main__":
    main()
