"""What the pick plan costs and how far it agrees with the truth of synthetic beds.

On ``--beds`` synthetic beds of ``--caps`` caps each (seeds from ``--seed``), detected with the shipped
model as ``detect`` reads a bed-frame cloud, it prints medians of:
- the plan's cost per bed (``plan_picks`` alone, in process);
- against the true caps (each detection matched to the true cap whose centre lies within its radius):
  the share of ready caps whose approach leans no more than the gripper's tilt limit, and its angle to
  the approach the true axis gives; the share of ``fits`` that agree with a gripper cylinder along the
  approach that hits neither another true cap's surface (the caps it waits for gone) nor the true soil
  (the synthetic bed's own soil and debris points, which lie on its meshes), and with the true caps
  alone (soil the gripper would touch left out); the share of caps whose
  ``blocked_by`` is the set of true caps whose dome the true approach line passes through;
- travel: on subsets of 8 pickable caps per bed, the greedy order's path against the shortest
  precedence-respecting order found by brute force and against a random one.
With ``--cloud`` and ``--detections`` (a detection document of that cloud), the plan's cost there too.

Usage: python bench/plan.py [--beds 10] [--caps 45] [--cloud example_0.pcd --detections detections.json]
"""

import sys
from pathlib import Path

# the bench folder holds fusion.py and perception.py, which would shadow those packages
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import argparse  # noqa: E402
import itertools  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from perception.plan import (CLEARANCE_REACH_MM, BELOW_GRASP_MM, PickConfig, lines_through_domes,  # noqa: E402
                             pick_order, plan_picks, tilted_toward)

SUBSET = 8


def dome_surfaces(centers, rotations, scales, rings: int = 16, around: int = 48) -> np.ndarray:
    """(K, rings * around, 3) points on each cap's dome (the upper half of its ellipsoid)."""
    polar = np.linspace(0.0, np.pi / 2, rings)
    azimuth = np.linspace(0.0, 2 * np.pi, around, endpoint=False)
    p, a = np.meshgrid(polar, azimuth, indexing="ij")
    local = np.stack([np.sin(p) * np.cos(a), np.sin(p) * np.sin(a), np.cos(p)], -1).reshape(-1, 3)
    return centers[:, None] + np.einsum("kij,knj->kni", rotations, local[None] * scales[:, None])


def timed_plan(caps, points, config, labels=None, repeats: int = 15) -> tuple[object, float]:
    """The plan and the median of ``repeats`` timings of it, in ms."""
    times = []
    for _ in range(repeats):
        began = time.perf_counter()
        plan = plan_picks(caps, points, config, point_labels=labels)
        times.append(1000 * (time.perf_counter() - began))
    return plan, statistics.median(times)


def in_gripper(surface: np.ndarray, grasp: np.ndarray, approach: np.ndarray, config: PickConfig) -> bool:
    """Whether any of the ``surface`` points lies in the suction cup's cylinder along ``approach`` from
    ``grasp`` (as tall as the plan looks, from as far below the grasp point as it looks)."""
    offset = surface - grasp
    along = offset @ approach
    across = np.linalg.norm(offset - along[:, None] * approach, axis=1)
    inside = (along >= -BELOW_GRASP_MM / 1000) & (along <= CLEARANCE_REACH_MM / 1000)
    return bool((inside & (across < config.gripper_diameter_mm / 2000)).any())


def truth_agreement(plan, caps, scene, config):
    """Per matched ready cap: approach within the tilt limit, its angle (deg) to the true axis's approach,
    ``fits`` as the true caps and soil say, ``fits`` as the true caps alone say, ``blocked_by`` as the true
    domes say."""
    up = np.array([0.0, 0.0, 1.0])
    true_axes = scene.rotations[:, :, 2]
    distance = np.linalg.norm(caps.centers[:, None] - scene.centers[None], axis=2)
    match = np.where(distance.min(1) < scene.scales[:, :2].mean(1)[distance.argmin(1)], distance.argmin(1), -1)
    true_approach = tilted_toward(true_axes, up, np.radians(config.max_tilt_deg))
    true_grasp = scene.centers + scene.scales[:, 2:3] * true_axes
    from perception.cap import Caps

    truth = Caps(scene.centers, scene.rotations, scene.scales)
    true_blocks = lines_through_domes(truth, true_grasp, true_approach)
    surfaces = dome_surfaces(scene.centers, scene.rotations, scene.scales)
    soil = scene.points[scene.instance < 0]
    rows = []
    for k in np.flatnonzero(plan.ready & (match >= 0)):
        own = match[k]
        tilt_ok = np.degrees(np.arccos(np.clip(plan.approach[k] @ up, -1, 1))) <= config.max_tilt_deg + 1e-6
        angle = np.degrees(np.arccos(np.clip(plan.approach[k] @ true_approach[own], -1, 1)))
        waits_for = {int(match[j]) for j in plan.blocked_by(k) if match[j] >= 0}
        others = [j for j in range(len(scene.centers)) if j != own and j not in waits_for]
        hits_caps = in_gripper(surfaces[others].reshape(-1, 3), plan.grasp[k], plan.approach[k], config)
        hits_soil = in_gripper(soil, plan.grasp[k], plan.approach[k], config)
        truly_blocked = set(np.flatnonzero(true_blocks[:, own]).tolist())
        rows.append((tilt_ok, angle, plan.fits[k] == (not hits_caps and not hits_soil), plan.fits[k] == (not hits_caps),
                     waits_for == truly_blocked))
    return rows


def precedence_orders(blocks: np.ndarray) -> np.ndarray:
    """Every order of the caps in which each comes after the caps that block it: (P, n)."""
    n = len(blocks)
    perms = np.array(list(itertools.permutations(range(n))))
    place = np.argsort(perms, axis=1)
    ok = np.ones(len(perms), bool)
    for j, i in zip(*np.nonzero(blocks)):
        ok &= place[:, j] < place[:, i]
    return perms[ok]


def path_lengths(grasp: np.ndarray, orders: np.ndarray) -> np.ndarray:
    steps = np.linalg.norm(grasp[orders[:, 1:]] - grasp[orders[:, :-1]], axis=2)
    return steps.sum(1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--beds", type=int, default=10)
    parser.add_argument("--caps", type=int, default=45, help="caps per synthetic bed")
    parser.add_argument("--seed", type=int, default=9100, help="the first bed's seed")
    parser.add_argument("--readings", type=int, default=4)
    parser.add_argument("--cloud", help="a real cloud to time the plan on, with --detections")
    parser.add_argument("--detections", help="the detection document of --cloud")
    args = parser.parse_args()

    from perception.detect import detect_points
    from perception.synthetic.scene import SceneConfig, generate_scene
    from pipeline.commands.common import load_model

    model, _ = load_model(None)
    config = PickConfig()
    rng = np.random.default_rng(0)
    costs, caps_per_bed, rows, greedy, random_order = [], [], [], [], []
    for bed in range(args.beds):
        scene = generate_scene(args.seed + bed, SceneConfig(mushrooms=(args.caps, args.caps)))
        result = detect_points(model, scene.points, readings=args.readings)
        plan, cost = timed_plan(result.caps, scene.points, config, result.point_labels)
        costs.append(cost)
        caps_per_bed.append(len(result.caps))
        rows += truth_agreement(plan, result.caps, scene, config)
        pickable = list(plan.order)
        if len(pickable) >= SUBSET:
            for _ in range(3):
                subset = np.sort(rng.choice(pickable, SUBSET, replace=False))
                grasp, blocks = plan.grasp[subset], plan.blocks[np.ix_(subset, subset)]
                orders = precedence_orders(blocks)
                best = path_lengths(grasp, orders).min()
                found = np.array([pick_order(grasp, blocks, np.ones(SUBSET, bool))])
                greedy.append(path_lengths(grasp, found)[0] / best)
                random_order.append(path_lengths(grasp, orders[rng.integers(len(orders))][None])[0] / best)
        print(f"bed {bed}: {len(result.caps)} caps, {int(plan.ready.sum())} ready, {len(plan.order)} in the order, "
              f"plan {cost:.2f} ms", flush=True)
    rows = np.array(rows, dtype=object)
    print(f"\nplan cost per bed ({statistics.median(caps_per_bed):.0f} caps median): median "
          f"{statistics.median(costs):.2f} ms over {args.beds} beds")
    print(f"ready caps matched to a true cap: {len(rows)}")
    print(f"  approach within the {config.max_tilt_deg:g} deg tilt limit: {100 * np.mean(rows[:, 0].astype(bool)):.1f} %;"
          f" angle to the true axis's approach: median {np.median(rows[:, 1].astype(float)):.2f} deg")
    print(f"  fits agrees with the true meshes (caps and soil): {100 * np.mean(rows[:, 2].astype(bool)):.1f} %;"
          f" with the true caps alone: {100 * np.mean(rows[:, 3].astype(bool)):.1f} %")
    print(f"  blocked_by agrees with the true domes: {100 * np.mean(rows[:, 4].astype(bool)):.1f} %")
    if greedy:
        print(f"travel on {len(greedy)} subsets of {SUBSET} pickable caps, against the brute-force best: greedy median "
              f"{statistics.median(greedy):.3f} (worst {max(greedy):.3f}), random order median "
              f"{statistics.median(random_order):.3f}")
    if args.cloud:
        import json

        from common.geometry import transform_points
        from perception.cap import Caps
        from pipeline.clouds import load_cloud

        document = json.loads(Path(args.detections).read_text())
        T_input_bed = np.array(document["T_input_bed"])
        caps = Caps.from_document(document).moved(np.linalg.inv(T_input_bed))
        points = transform_points(np.linalg.inv(T_input_bed), load_cloud(Path(args.cloud), "auto").points)
        plan, cost = timed_plan(caps, points, config)
        print(f"{args.cloud}: {len(caps)} caps, {len(points)} points: plan median {cost:.2f} ms, "
              f"{len(plan.order)} caps in the order")
    return 0


if __name__ == "__main__":
    sys.exit(main())
