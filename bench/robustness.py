"""The robustness suite: the shipped model on each family of synthetic beds
(``perception.synthetic.families``), each bed read as ``mushroom-pose detect`` reads a cloud (bed plane
found, up side chosen by the caps, four turned readings). One row per family: AP@25 / AP@50, the axis
angle (arccos of the mean cosine) and radius error of the matches, precision and recall at
``--min-score``, and the expected calibration error of the scores; all rows and every detection's
score and outcome go to ``--json``.

Usage: python bench/robustness.py [--beds 6] [--families NAME ...] [--model PATH] [--json robustness.json]
"""

import sys
from pathlib import Path

# the bench folder holds fusion.py and perception.py, which would shadow those packages
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from tqdm import tqdm  # noqa: E402

from perception.cap import Caps  # noqa: E402
from perception.detect import FILE_READINGS, detect_cloud  # noqa: E402
from perception.evaluate import detection_outcomes, evaluate, visible_truth  # noqa: E402
from perception.synthetic.families import FAMILIES, family_seeds  # noqa: E402
from perception.synthetic.scene import generate_scene  # noqa: E402
from perception.weights import DEFAULT_WEIGHTS, load_weights  # noqa: E402
from pipeline.process import reuse_freed_memory  # noqa: E402

CALIBRATION_BINS = 10


def score_bins(scores: np.ndarray, bins: int = CALIBRATION_BINS) -> np.ndarray:
    """The equal-width score bin of each score (a score of 1 in the top bin)."""
    return np.minimum((scores * bins).astype(int), bins - 1)


def expected_calibration_error(scores: np.ndarray, correct: np.ndarray, bins: int = CALIBRATION_BINS) -> float:
    """Mean |frequency correct - mean score| over equal-width score bins, weighted by their counts."""
    if not len(scores):
        return float("nan")
    which = score_bins(scores, bins)
    counts = np.bincount(which, minlength=bins)
    gap = np.abs(np.bincount(which, correct, bins) - np.bincount(which, scores, bins))
    return float(gap.sum() / counts.sum())


def print_reliability(scores: np.ndarray, correct: np.ndarray, bins: int = CALIBRATION_BINS) -> None:
    """The reliability table (per score bin: detections, mean score, share correct) and the lowest
    score threshold whose detections are correct 95 % of the time or more."""
    if not len(scores):
        return
    which = score_bins(scores, bins)
    print("\n| score | detections | mean score | correct |\n|---|---|---|---|")
    for b in np.unique(which):
        inside = which == b
        print(f"| {b / bins:.1f}-{(b + 1) / bins:.1f} | {int(inside.sum())} | {scores[inside].mean():.3f} | "
              f"{correct[inside].mean():.3f} |")
    order = np.argsort(-scores, kind="stable")
    precision = np.cumsum(correct[order]) / np.arange(1, len(order) + 1)
    good = np.flatnonzero(precision >= 0.95)
    if len(good):
        cut = scores[order][good[-1]]
        above = scores >= cut
        print(f"precision >= 0.95 down to score {cut:.3f}: precision {correct[above].mean():.3f}, "
              f"{int(above.sum())} of {len(scores)} detections")


def family_row(model, name: str, beds: int, readings: int, min_score: float) -> dict:
    preds, gts, unread = [], [], 0
    for seed in tqdm(family_seeds(name, beds), desc=name, unit="bed", leave=False):
        scene = generate_scene(seed, FAMILIES[name].config)
        points = scene.points.astype(np.float64)
        try:
            preds.append(detect_cloud(model, points, readings=readings))
        except (ValueError, RuntimeError) as error:  # no bed plane: the bed counts as all missed
            print(f"  {name} bed {seed}: {error}", file=sys.stderr)
            preds.append(Caps.none())
            unread += 1
        gts.append(visible_truth(scene))
    result = evaluate(preds, gts)
    scores, correct = detection_outcomes(preds, gts)
    above = scores >= min_score
    true_above = int(correct[above].sum())
    return {"family": name, "group": FAMILIES[name].group, "in_range": FAMILIES[name].in_range,
            "description": FAMILIES[name].description, "beds": beds, "unread_beds": unread,
            "caps": sum(len(g) for g in gts), **result.as_dict(),
            "precision": true_above / max(int(above.sum()), 1),
            "recall": true_above / max(sum(len(g) for g in gts), 1),
            "ece": expected_calibration_error(scores, correct),
            "scores": scores.tolist(), "correct": correct.astype(int).tolist()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--beds", type=int, default=6, help="beds per family (default 6)")
    parser.add_argument("--families", nargs="+", choices=list(FAMILIES), help="only these families")
    parser.add_argument("--model", type=Path, default=DEFAULT_WEIGHTS)
    parser.add_argument("--readings", type=int, default=FILE_READINGS,
                        help=f"turned readings averaged (default {FILE_READINGS}, as detect reads)")
    parser.add_argument("--min-score", type=float, default=0.0, help="precision and recall of caps scored at least this")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", type=Path, help="write every row, with each detection's score and outcome")
    args = parser.parse_args()
    reuse_freed_memory()
    torch.set_num_threads(args.threads)
    model, _ = load_weights(args.model)
    print(f"model: {args.model}; {args.beds} beds per family, read as detect reads ({args.readings} readings); "
          f"precision / recall at score >= {args.min_score:g}; matches at IoU >= 0.25\n")
    print("| family | group | in range | caps | AP@25 | AP@50 | angle (deg) | radius error | precision | recall | ECE |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    rows, started = [], time.perf_counter()
    for name in args.families or FAMILIES:
        row = family_row(model, name, args.beds, args.readings, args.min_score)
        rows.append(row)
        print(f"| {name} | {row['group']} | {'yes' if row['in_range'] else 'no'} | {row['caps']} | "
              f"{100 * row['ap25']:.1f} % | {100 * row['ap50']:.1f} % | {row['angle_deg']:.2f} | "
              f"{100 * row['scale_err_true']:.1f} % | {row['precision']:.3f} | {row['recall']:.3f} | {row['ece']:.3f} |",
              flush=True)
    inside = [row for row in rows if row["in_range"]]
    if inside:
        worst = min(inside, key=lambda row: row["ap25"])
        print(f"\ninside the range: worst AP@25 {100 * worst['ap25']:.1f} % ({worst['family']}), mean AP@50 "
              f"{100 * np.mean([row['ap50'] for row in inside]):.1f} %")
    scores = np.concatenate([row["scores"] for row in rows] + [[]])
    correct = np.concatenate([row["correct"] for row in rows] + [[]])
    print(f"all families: ECE {expected_calibration_error(scores, correct):.3f} over {len(scores)} detections; "
          f"{time.perf_counter() - started:.0f} s")
    print_reliability(scores, correct)
    if args.json:
        args.json.write_text(json.dumps({"model": str(args.model), "beds": args.beds, "readings": args.readings,
                                         "min_score": args.min_score, "families": rows}, indent=1))
        print(f"rows: {args.json}")


if __name__ == "__main__":
    main()
