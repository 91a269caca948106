"""How well caps are followed across daily scans of synthetic beds, with the truth known.

``--beds`` beds (seeds from ``--seed``) are each scanned on ``--days`` days (``perception.synthetic.days``:
caps grow at their own rates, new pins appear, ripe caps are picked, the rig is placed a little
differently each day). Each scan is read as ``detect`` reads a cloud (``perception.detect.detect_cloud``:
the bed plane and its up side found, the shipped model, four readings) and the scans of a bed are
tracked (``perception.track``). Detections are matched to the true caps of their scan (centres within
half the true radius, at least 8 mm), and it prints:
- identity: of the true caps detected on two consecutive scans, the share that keep one track id; of
  the track's links from scan to scan, the share that join two different caps (or a false detection);
  of the caps that appear (a new pin) the share that start a new track; of the caps picked between two
  scans the share whose track ends;
- growth: the median error of the fitted growth rate (mm/day) over caps followed on three scans or more;
- forecast: of the caps on the last scan not yet at the pick size that reach it within the forecast
  horizon, the share whose predicted day of reaching it is within one day of the truth, and the share
  had each cap's true rate been used with its measured diameters (what the size measure alone allows);
- repeatability: each bed scanned twice with the rig moved and nothing grown, the median change of a
  cap's measured diameter.

``--caps FAMILY`` draws the caps' shapes as the robustness suite's cap-shape family of that name does
(e.g. ``real-domes``, the real caps' height ratios) instead of the template's.

Usage: python bench/growth.py [--beds 10] [--days 5] [--seed 5000] [--readings 4] [--model PATH] [--caps FAMILY]
"""

import sys
from pathlib import Path

# the bench folder holds fusion.py and perception.py, which would shadow those packages
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402

import numpy as np  # noqa: E402
from scipy.optimize import linear_sum_assignment  # noqa: E402
from tqdm import tqdm  # noqa: E402

from perception.synthetic.families import FAMILIES  # noqa: E402
from perception.synthetic.scene import SceneConfig  # noqa: E402

CAP_FAMILIES = ("shallow-domes", "real-domes")
"""The suite's cap-shape families whose sizes a growing bed can take (the others fix the caps' sizes)."""


def truth_of(caps, scan) -> np.ndarray:
    """Per detected cap, the id of the true cap it is (-1: none)."""
    labels = np.full(len(caps), -1)
    if not len(caps) or not len(scan.cap_ids):
        return labels
    distance = np.linalg.norm(caps.centers[:, None] - scan.centers[None], axis=2)
    rows, cols = linear_sum_assignment(distance)
    reach = np.maximum(0.008, 0.5 * scan.scales[:, :2].mean(1))
    good = distance[rows, cols] <= reach[cols]
    labels[rows[good]] = scan.cap_ids[cols[good]]
    return labels


def identity_counts(history, tracks, labels) -> dict[str, list[int]]:
    """[hits, trials] of each identity figure for one bed."""
    track_of = {}  # (scan, cap) -> track id
    for track in tracks.tracks:
        for scan, cap in zip(track.scans, track.caps):
            track_of[scan, cap] = track.id
    counts = {name: [0, 0] for name in ("kept", "wrong", "appeared", "picked")}
    for k in range(1, len(history.scans)):
        before = {int(t): c for c, t in enumerate(labels[k - 1]) if t >= 0}
        now = {int(t): c for c, t in enumerate(labels[k]) if t >= 0}
        for cap_id in before.keys() & now.keys():
            counts["kept"][1] += 1
            counts["kept"][0] += track_of[k - 1, before[cap_id]] == track_of[k, now[cap_id]]
        present_before = set(history.scans[k - 1].cap_ids.tolist())
        for cap_id, cap in now.items():
            if cap_id not in present_before:
                counts["appeared"][1] += 1
                counts["appeared"][0] += min(s for s, c in track_of if track_of[s, c] == track_of[k, cap]) == k
        picked = {int(i) for i in np.flatnonzero(history.picked_on == k)}
        for cap_id in picked & before.keys():
            counts["picked"][1] += 1
            counts["picked"][0] += not any(track_of.get((k, c)) == track_of[k - 1, before[cap_id]]
                                           for c in range(len(labels[k])))
    for track in tracks.tracks:
        ids = [labels[s][c] for s, c in zip(track.scans, track.caps)]
        for a, b in zip(ids, ids[1:]):
            if a >= 0 or b >= 0:  # a false detection followed on is no cap's identity
                counts["wrong"][1] += 1
                counts["wrong"][0] += a != b
    return counts


def true_ready_day(history, cap_id: int, pick_mm: float) -> float:
    """When the cap's true diameter reaches ``pick_mm`` (days since the first scan)."""
    final = history.diameters_mm[cap_id, ~np.isnan(history.diameters_mm[cap_id])][-1]
    last_day = np.flatnonzero(~np.isnan(history.diameters_mm[cap_id]))[-1]
    return float(last_day + (pick_mm - final) / history.growth_mm_per_day[cap_id])


def ready_at_rate(track, rate_mm_per_day: float, pick_mm: float) -> float:
    """When a line of slope ``rate_mm_per_day`` through the track's measured diameters reaches ``pick_mm``:
    the forecast had the rate been known, which splits its error into the rate's and the sizes'."""
    return float(track.days.mean() + (pick_mm - track.diameters_mm.mean()) / rate_mm_per_day)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--beds", type=int, default=10)
    parser.add_argument("--days", type=int, default=5)
    parser.add_argument("--seed", type=int, default=5000)
    parser.add_argument("--readings", type=int, default=4)
    parser.add_argument("--model", type=Path, help="weights file (default: the shipped model)")
    parser.add_argument("--caps", choices=CAP_FAMILIES, help="cap shapes of this suite family (default: the template's)")
    args = parser.parse_args()

    from perception.detect import detect_cloud
    from perception.synthetic.days import GrowthConfig, bed_over_days
    from perception.track import Scan, TrackConfig, track_bed
    from perception.weights import DEFAULT_WEIGHTS, load_weights

    model = load_weights(args.model or DEFAULT_WEIGHTS)[0]
    config, growth = TrackConfig(), GrowthConfig(days=args.days)
    bed_config = SceneConfig(mushrooms=(10, 25))
    if args.caps:
        shapes = FAMILIES[args.caps].config
        bed_config = replace(bed_config, axis_factor=shapes.axis_factor, cap_height=shapes.cap_height)
    totals = {name: [0, 0] for name in ("kept", "wrong", "appeared", "picked")}
    rate_errors, forecasts, forecasts_known_rate, repeat = [], [], [], []
    started = time.perf_counter()
    for bed in tqdm(range(args.beds), desc="beds", unit="bed"):
        history = bed_over_days(args.seed + bed, bed_config, growth)
        found = [detect_cloud(model, scan.points.astype(np.float64), readings=args.readings) for scan in history.scans]
        scans = [Scan(s.time_s, s.points.astype(np.float64), caps, f"day {s.day}")
                 for s, caps in zip(history.scans, found)]
        labels = [truth_of(caps, scan) for caps, scan in zip(found, history.scans)]
        tracks = track_bed(scans, config=config)
        for name, (hits, trials) in identity_counts(history, tracks, labels).items():
            totals[name][0] += hits
            totals[name][1] += trials
        for track in tracks.tracks:
            ids = {int(labels[s][c]) for s, c in zip(track.scans, track.caps)}
            if len(track.scans) >= 3 and len(ids) == 1 and -1 not in ids:
                rate_errors.append(abs(track.growth_mm_per_day - history.growth_mm_per_day[ids.pop()]))
        last_day = len(scans) - 1
        for track in tracks.tracks:
            ids = {int(labels[s][c]) for s, c in zip(track.scans, track.caps)}
            if not track.present or len(ids) != 1 or -1 in ids or track.diameters_mm[-1] >= config.pick_mm:
                continue
            cap_id = ids.pop()
            truth = true_ready_day(history, cap_id, config.pick_mm)
            if truth <= last_day + config.horizon_days:
                forecasts.append(track.ready_day is not None and abs(track.ready_day - truth) <= 1.0)
                known_rate = ready_at_rate(track, history.growth_mm_per_day[cap_id], config.pick_mm)
                forecasts_known_rate.append(abs(known_rate - truth) <= 1.0)
        still = bed_over_days(args.seed + bed, bed_config, replace(growth, days=2, growth_mm_per_day=(0.0, 0.0),
                                                               pick_probability=0.0))
        twice = [Scan(s.time_s, s.points.astype(np.float64), detect_cloud(
            model, s.points.astype(np.float64), readings=args.readings)) for s in still.scans]
        for track in track_bed(twice, config=config).tracks:
            if len(track.scans) == 2:
                repeat.append(abs(track.diameters_mm[1] - track.diameters_mm[0]))
    share = {name: hits / trials if trials else float("nan") for name, (hits, trials) in totals.items()}
    print(f"{args.beds} beds x {args.days} daily scans of {args.caps or 'template'} caps, read {args.readings} times "
          f"({time.perf_counter() - started:.0f} s)")
    print(f"  identity: kept {share['kept']:.1%} of {totals['kept'][1]} (target >= 98 %); wrong links "
          f"{share['wrong']:.1%} of {totals['wrong'][1]} (target < 2 %); appearing caps recognised "
          f"{share['appeared']:.1%} of {totals['appeared'][1]}, picked {share['picked']:.1%} of "
          f"{totals['picked'][1]} (targets >= 95 %)")
    print(f"  growth rate error: median {statistics.median(rate_errors):.2f} mm/day over {len(rate_errors)} caps "
          "(target <= 1)")
    print(f"  ready day within +-1 day: {np.mean(forecasts):.1%} of {len(forecasts)} caps that reach the pick "
          f"size within {config.horizon_days} days (target >= 90 %); {np.mean(forecasts_known_rate):.1%} "
          "with each cap's true rate through its measured diameters")
    print(f"  repeatability (rig moved, no growth): median diameter change {statistics.median(repeat):.2f} mm over "
          f"{len(repeat)} caps (target <= 1)")


if __name__ == "__main__":
    main()
