"""How good are colour-made cap labels? The labels of ../shared/real/ take a cap's axis as the
least-variance PCA axis of its visible points (checked against a sphere fit) and its radius from the
area of its top-view footprint. This bench makes the same axes and radius on fused synthetic beds,
where the true pose is known, and sets them beside the detector's.

Each virtual bed (18 views, 848x480, D405-like noise) is fused and detected by the product's runner, as
in bench/views.py. A cap's visible points are the fused points within 2 mm of its cap surface; caps
with fewer than 250 (the labels' "small" partial cut) are left out, as the labels leave them out of
the non-partial figures. Prints, over those caps, the angle from the true axis of: the PCA axis, the
sphere-fit axis (centroid minus sphere centre) and the detector's axis; and the angles the real-cloud
bench would score: the detector against the PCA axis, and PCA against the sphere fit. Then the
relative error of the footprint radius (the radius of a circle with the area of the convex hull of the
cap's points seen from above the bed) and of the detector's radius against the true radius, and of
the detector's radius against the footprint radius, as the real-cloud bench scores it, each with the
median of its signed errors (above 0: the first radius is the larger); and those of the footprint
radius by the cap's true tilt.
Usage: python bench/label_quality.py [--beds 10]
"""

import sys
from pathlib import Path

# the bench folder holds fusion.py and pipeline.py, which would shadow the packages
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import argparse  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from scipy.spatial import ConvexHull  # noqa: E402

from perception.cap import tilt_deg  # noqa: E402
from perception.weights import DEFAULT_WEIGHTS  # noqa: E402
from perception.weights import load_weights  # noqa: E402
from pipeline.runner import RunConfig, Runner  # noqa: E402
from capture.virtual import VirtualCameraConfig  # noqa: E402
from pipeline.sources import VirtualBed, virtual_bed_source  # noqa: E402

ON_SURFACE, LABELLED_POINTS = 0.002, 250
TILT_BINS_DEG = (20.0, 35.0)
"""True tilt bin edges of the radius table by tilt: a footprint seen from above shrinks as a cap leans.
bench/real.py reads that table's medians (``FOOTPRINT_RADIUS_BIAS_BY_TILT``, the same edges)."""


def least_variance_axis(points: np.ndarray, up: np.ndarray) -> np.ndarray:
    """The direction of least spread of ``points`` (n, 3), turned to ``up``'s side."""
    axis = np.linalg.eigh(np.cov((points - points.mean(0)).T))[1][:, 0]
    return axis * np.sign(axis @ up)


def sphere_axis(points: np.ndarray) -> np.ndarray:
    """From the least-squares sphere's centre to the points' centroid."""
    solution = np.linalg.lstsq(np.c_[2 * points, np.ones(len(points))], (points**2).sum(1), rcond=None)[0]
    axis = points.mean(0) - solution[:3]
    return axis / np.linalg.norm(axis)


def footprint_radius(bed_points: np.ndarray) -> float:
    """The radius of the circle whose area is that of the points' convex hull in the bed's top view
    (points in the bed frame)."""
    return float(np.sqrt(ConvexHull(bed_points[:, :2]).volume / np.pi))


def describe(name: str, values: list[float], scale: float = 1.0, digits: int = 1) -> str:
    values = scale * np.asarray(values)
    return (f"| {name} | {values.mean():.{digits}f} | {np.median(values):.{digits}f} | "
            f"{np.percentile(values, 90):.{digits}f} |")


def describe_signed(name: str, relative: list[float]) -> str:
    """``describe``'s row of the sizes of relative errors (in %), and the median of their signs kept:
    above 0, the first radius is larger."""
    return describe(name, np.abs(relative), 100)[:-1] + f"| {100 * np.median(relative):+.1f} |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--beds", type=int, default=10)
    parser.add_argument("--model", type=Path, default=DEFAULT_WEIGHTS)
    args = parser.parse_args()
    torch.set_num_threads(2)
    model, _ = load_weights(args.model)
    angles: dict[str, list[float]] = {key: [] for key in ("pca", "sphere", "detector", "detector_pca", "pca_sphere")}
    radius_errors: dict[str, list[float]] = {key: [] for key in ("footprint", "detector", "detector_footprint")}
    tilts: dict[str, list[float]] = {"footprint": [], "detector_footprint": []}
    for seed in range(args.beds):
        source, bed = virtual_bed_source(VirtualBed(seed=100 + seed, camera=VirtualCameraConfig(views=18)))
        summary = Runner(source, model, RunConfig(), []).run()
        fused, caps = summary.last_unit.cloud, summary.last_detection.result.caps
        world = fused.world_points
        cap_of_point = bed.cap_of_points(world, ON_SURFACE)
        up = fused.T_world_bed[:3, 2]
        for k in range(len(bed.centers)):
            mine = cap_of_point == k
            points = world[mine]
            if len(points) < LABELLED_POINTS:
                continue
            truth, pca, sphere = bed.rotations[k][:, 2], least_variance_axis(points, up), sphere_axis(points)
            angles["pca"].append(float(tilt_deg(pca, truth)))
            angles["sphere"].append(float(tilt_deg(sphere, truth)))
            angles["pca_sphere"].append(float(tilt_deg(pca, sphere)))
            true_radius, footprint = bed.scales[k, :2].mean(), footprint_radius(fused.points[mine])
            radius_errors["footprint"].append((footprint - true_radius) / true_radius)
            tilts["footprint"].append(float(tilt_deg(truth, up)))
            distance = np.linalg.norm(caps.centers - bed.centers[k], axis=1) if len(caps) else np.array([np.inf])
            if distance.min() < 0.5 * bed.scales[k, 0]:
                nearest = int(distance.argmin())
                found = caps.axes[nearest]
                angles["detector"].append(float(tilt_deg(found, truth)))
                angles["detector_pca"].append(float(tilt_deg(found, pca)))
                radius = caps.radii[nearest]
                radius_errors["detector"].append((radius - true_radius) / true_radius)
                radius_errors["detector_footprint"].append((radius - footprint) / footprint)
                tilts["detector_footprint"].append(tilts["footprint"][-1])
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
    print("\n| radius, relative error | mean (%) | median (%) | 90th percentile (%) | median signed (%) |")
    print("|---|---|---|---|---|")
    print(describe_signed("footprint radius against the truth", radius_errors["footprint"]))
    print(describe_signed("detector against the truth", radius_errors["detector"]))
    print(describe_signed("detector against the footprint radius (what bench/real.py scores)",
                          radius_errors["detector_footprint"]))
    print("\n| true tilt | caps | footprint against the truth, median signed (%) | "
          "detector against the footprint, mean (%) |")
    print("|---|---|---|---|")
    footprint_bin = np.digitize(tilts["footprint"], TILT_BINS_DEG)
    scored_bin = np.digitize(tilts["detector_footprint"], TILT_BINS_DEG)
    footprint, scored = np.array(radius_errors["footprint"]), np.array(radius_errors["detector_footprint"])
    edges = (0, *TILT_BINS_DEG, 90)
    for b in range(len(edges) - 1):
        if not np.any(footprint_bin == b):
            continue
        mine = scored[scored_bin == b]
        print(f"| {edges[b]:g}-{edges[b + 1]:g} deg | {np.sum(footprint_bin == b)} | "
              f"{100 * np.median(footprint[footprint_bin == b]):+.1f} | "
              + (f"{100 * np.mean(np.abs(mine)):.1f} |" if len(mine) else "- |"))


if __name__ == "__main__":
    main()
