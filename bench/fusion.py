"""Fusion accuracy and speed on virtual turntable sessions with known poses (848x480, D405-like noise).

Each bed is seen from N views on a circle; the prior (the rig the refinement starts from) is off by up
to 3 degrees per view in angle and 5 mm in axis position. Reported after refinement: rotation and
translation errors of the camera poses, the fused surface's distance to the true meshes, and seconds
per stage. Targets for 18 views: rotation <= 0.3 deg, translation <= 1.5 mm, surface RMS <= 2 mm,
<= 5 s on 2 cores. Baseline in the same run: Open3D multiway registration with no prior (FPFH + RANSAC
global registration and ICP on every pair, then the pose graph), as in Open3D's multiway tutorial.
Usage: python bench/fusion.py [--beds 3] [--views 18] [--no-baseline]
"""

import sys
from pathlib import Path

# bench/fusion.py would shadow the fusion package: take this folder off the import path
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import open3d as o3d  # noqa: E402

from common.geometry import Turntable  # noqa: E402
from fusion.cloud import FusionConfig, fuse  # noqa: E402
from fusion.registration import (RegistrationConfig, fpfh, pose_change, prepare_view, register_global,  # noqa: E402
                                 register_pair)
from fusion.turntable import Rig  # noqa: E402
from capture.virtual import VirtualCameraConfig  # noqa: E402
from pipeline.sources import VirtualBed, virtual_bed_source  # noqa: E402
from pipeline.process import reuse_freed_memory  # noqa: E402

reg = o3d.pipelines.registration
SUCCESS_DEG, SUCCESS_M = 1.0, 0.005
"""A view is registered when its pose is within this of the truth."""


def session(seed: int, views: int):
    """Frames of one bed, their true poses, the frames as a blind recording (perturbed encoder angles,
    no poses) and the rig with a shifted axis."""
    source, bed = virtual_bed_source(VirtualBed(seed=seed, camera=VirtualCameraConfig(views=views)))
    turntable = source.config.turntable
    frames = list(source)
    rng = np.random.default_rng(1000 + seed)
    angle_error = np.radians(3.0) * rng.uniform(-1, 1, views)
    angle_error[0] = 0.0
    shift = rng.normal(size=3)
    shift *= 0.005 / np.linalg.norm(shift)
    rig = Rig(Turntable(turntable.axis_point + shift, turntable.axis_direction, turntable.T_world_reference))
    blind = [dataclasses.replace(f, T_world_camera=None, turntable_angle=f.turntable_angle + e)
             for f, e in zip(frames, angle_error)]
    return bed, np.stack([f.T_world_camera for f in frames]), blind, rig


def surface_rms(bed, world_points: np.ndarray) -> float:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(bed.vertices.astype(np.float32)),
                        o3d.core.Tensor(bed.triangles.astype(np.uint32)))
    distance = scene.compute_distance(o3d.core.Tensor(np.ascontiguousarray(world_points, np.float32))).numpy()
    return float(np.sqrt(np.mean(distance ** 2)))


def multiway_baseline(frames, truth: np.ndarray, config: RegistrationConfig = RegistrationConfig()):
    """Open3D multiway registration with no prior: global registration + ICP for every pair, odometry
    edges between consecutive views and uncertain loop closures for the rest, then the pose graph.
    Global registration runs on the coarse 8 mm level, one RANSAC seed per pair, as this baseline was
    measured in docs/RESULTS.md."""
    config = dataclasses.replace(config, global_level=0)
    start = time.perf_counter()
    views = [prepare_view(f, config) for f in frames]
    features = [fpfh(v, config) for v in views]
    n = len(views)
    graph = reg.PoseGraph()
    odometry = np.eye(4)
    graph.nodes.append(reg.PoseGraphNode(odometry))
    for i in range(n):
        for j in range(i + 1, n):
            init = register_global(views[j], views[i], config, seed=i * n + j, features=(features[j], features[i]))
            pair = register_pair(views[j], views[i], init, config, (j, i))
            if j == i + 1:
                odometry = odometry @ pair.T_target_source
                graph.nodes.append(reg.PoseGraphNode(odometry))
                graph.edges.append(reg.PoseGraphEdge(j, i, pair.T_target_source, pair.information, uncertain=False))
            elif pair.fitness >= config.min_fitness:
                graph.edges.append(reg.PoseGraphEdge(j, i, pair.T_target_source, pair.information, uncertain=True))
    option = reg.GlobalOptimizationOption(max_correspondence_distance=config.distances[-1],
                                          edge_prune_threshold=0.25, reference_node=0)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                reg.GlobalOptimizationConvergenceCriteria(), option)
    T_first = np.stack([np.asarray(node.pose) for node in graph.nodes])
    poses = truth[0] @ np.linalg.inv(T_first[0]) @ T_first
    return poses, time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--beds", type=int, default=3)
    parser.add_argument("--views", type=int, default=18)
    parser.add_argument("--no-baseline", action="store_true", help="skip the (slow) multiway baseline")
    args = parser.parse_args()
    reuse_freed_memory()
    ours, baseline = [], []
    for seed in range(args.beds):
        bed, truth, blind, rig = session(seed, args.views)
        prior_rotation, prior_translation = pose_change(
            np.stack([rig.T_world_camera(f.sensor_id, f.turntable_angle) for f in blind]), truth)
        start = time.perf_counter()
        fused = fuse(blind, FusionConfig(), rig)
        seconds = time.perf_counter() - start
        rotation, translation = pose_change(fused.T_world_cameras, truth)
        rms = surface_rms(bed, fused.world_points)
        stages = "  ".join(f"{k} {v:.2f}" for k, v in fused.seconds.items())
        print(f"bed {seed}: prior max {prior_rotation.max():.2f} deg {1000 * prior_translation.max():.1f} mm -> "
              f"refined median {np.median(rotation):.3f} deg (max {rotation.max():.3f}) "
              f"{1000 * np.median(translation):.2f} mm (max {1000 * translation.max():.2f}); "
              f"surface RMS {1000 * rms:.2f} mm; {len(fused)} points; {seconds:.2f} s ({stages}); "
              f"flagged {len(fused.flagged)}", flush=True)
        ours.append((np.median(rotation), rotation.max(), np.median(translation), translation.max(), rms, seconds))
        if not args.no_baseline:
            poses, base_seconds = multiway_baseline(blind, truth)
            b_rotation, b_translation = pose_change(poses, truth)
            success = np.mean((b_rotation <= SUCCESS_DEG) & (b_translation <= SUCCESS_M))
            print(f"   multiway baseline (no prior): median {np.median(b_rotation):.3f} deg "
                  f"(max {b_rotation.max():.2f}) {1000 * np.median(b_translation):.2f} mm "
                  f"(max {1000 * b_translation.max():.1f}); views within {SUCCESS_DEG} deg and "
                  f"{1000 * SUCCESS_M:.0f} mm: {100 * success:.0f}%; {base_seconds:.1f} s", flush=True)
            baseline.append((np.median(b_rotation), b_rotation.max(), np.median(b_translation), b_translation.max(),
                             success, base_seconds))
    ours = np.array(ours)
    print(f"ours, median over {args.beds} beds of {args.views} views: rotation {np.median(ours[:, 0]):.3f} deg "
          f"(worst view {ours[:, 1].max():.3f}), translation {1000 * np.median(ours[:, 2]):.2f} mm "
          f"(worst {1000 * ours[:, 3].max():.2f}), surface RMS {1000 * np.median(ours[:, 4]):.2f} mm, "
          f"{np.median(ours[:, 5]):.2f} s; targets 0.3 deg, 1.5 mm, 2 mm, 5 s")
    if baseline:
        baseline = np.array(baseline)
        print(f"baseline, same beds: rotation {np.median(baseline[:, 0]):.3f} deg (worst view "
              f"{baseline[:, 1].max():.2f}), translation {1000 * np.median(baseline[:, 2]):.2f} mm "
              f"(worst {1000 * baseline[:, 3].max():.1f}), success {100 * np.mean(baseline[:, 4]):.0f}% of views, "
              f"{np.median(baseline[:, 5]):.1f} s = {np.median(baseline[:, 5]) / np.median(ours[:, 5]):.1f}x ours")


if __name__ == "__main__":
    main()
