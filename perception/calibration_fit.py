"""Fitting a model's calibration (``perception.calibration``) on its calibration beds, and storing it in
the weights file: ``python -m perception.calibration_fit --model FILE [--beds 12] [--diameters]``."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from perception.calibration import CALIBRATION_SEED, UNCALIBRATED, Calibration, fit_diameters, fit_scores
from perception.cap import Caps

DIAMETER_FAMILIES = ("shallow-domes", "real-domes", "spacing-1mm", "spacing-5mm", "spacing-8mm", "single-view",
                     "fused-views", "oak-stereo", "tilted-uneven", "touching-clusters", "casing-soil", "mycelium")
"""The families the diameter line is fit on: those inside the operating range with closed, domed caps.
Opened flat caps read far smaller (their thin rim holds few voxels), and one line for both would
misstate the domes a bed mostly holds."""


def calibration_outcomes(model, beds: int, progress: bool = True) -> dict[str, list]:
    """What the model, uncalibrated, finds on ``beds`` calibration beds of each family, read as detect
    reads: per family its detections and the truth (``Caps`` lists)."""
    from tqdm import tqdm

    from perception.detect import detect_cloud
    from perception.evaluate import visible_truth
    from perception.synthetic.families import FAMILIES, family_seeds
    from perception.synthetic.scene import generate_scene

    calibration, model.calibration = model.calibration, UNCALIBRATED
    found = {}
    try:
        jobs = [(name, seed) for name in FAMILIES for seed in family_seeds(name, beds, CALIBRATION_SEED)]
        for name, seed in tqdm(jobs, desc="calibration beds", unit="bed", disable=not progress):
            scene = generate_scene(seed, FAMILIES[name].config)
            try:
                caps = detect_cloud(model, scene.points.astype(np.float64))
            except (ValueError, RuntimeError):  # no bed plane: nothing found, the caps all missed
                caps = Caps.none()
            preds, gts = found.setdefault(name, ([], []))
            preds.append(caps)
            gts.append(visible_truth(scene))
    finally:
        model.calibration = calibration
    return found


def fit_calibration(found: dict[str, tuple[list, list]], diameters: bool = False) -> Calibration:
    """The calibration of ``calibration_outcomes``: with ``diameters``, a diameter line on the caps found
    at IoU >= 0.25 in the ``DIAMETER_FAMILIES``; then scores on every family's detections with those
    diameters."""
    from perception.evaluate import detection_outcomes, matched_truth

    measured, true = [], []
    for name, (preds, gts) in found.items():
        if name not in DIAMETER_FAMILIES:
            continue
        _, matched = matched_truth(preds, gts)
        start = 0
        for pred, gt in zip(preds, gts):
            match = matched[start:start + len(pred)]
            start += len(pred)
            measured.append(2000 * pred.radii[match >= 0])
            true.append(2000 * gt.radii[match[match >= 0]])
    scale, offset = fit_diameters(np.concatenate(measured), np.concatenate(true)) if diameters else (1.0, 0.0)
    sized = Calibration(diameter_scale=scale, diameter_offset_mm=offset)
    scores, correct = [], []
    for preds, gts in found.values():
        s, c = detection_outcomes([sized.applied(p) for p in preds], gts)
        scores.append(s)
        correct.append(c)
    knots, values = fit_scores(np.concatenate(scores), np.concatenate(correct))
    return replace(sized, raw_scores=knots, calibrated_scores=values)


def main() -> None:
    """``python -m perception.calibration_fit --model FILE``: fit the model's calibration on its
    calibration beds and store it in the weights file."""
    import argparse
    from pathlib import Path

    import torch

    from perception.weights import DEFAULT_WEIGHTS, load_weights, save_weights

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--model", type=Path, default=DEFAULT_WEIGHTS, help="the weights file (default: the shipped one)")
    parser.add_argument("--beds", type=int, default=6, help="calibration beds per family (default 6)")
    parser.add_argument("--diameters", action="store_true", help="also fit the rim diameters to the synthetic "
                        "truth (the shipped model does not: on the real cloud its caps then read larger than labelled)")
    args = parser.parse_args()
    torch.set_num_threads(2)
    model, meta = load_weights(args.model)
    calibration = fit_calibration(calibration_outcomes(model, args.beds), args.diameters)
    model.calibration = calibration
    save_weights(model, args.model, **meta)
    print(f"{args.model}: diameters x {calibration.diameter_scale:.4f} {calibration.diameter_offset_mm:+.2f} mm; "
          f"scores mapped by {len(calibration.raw_scores)} knots")


if __name__ == "__main__":
    main()
