"""The detector on a real bed cloud, scored against colour-derived cap labels (../shared/real/README.md).

The cloud is reduced to xyz (colour and normals dropped: the detector sees geometry only), optionally
voxel-thinned to --thin millimetres, written to a temporary .ply and handed to
``python -m pipeline.cli detect`` as a user would run it; its wall time is the end-to-end figure. The
stages of that command (weights, load, bed plane, network, instances, pose) are then timed once in this
process on the same file with the same library calls. The detections are scored with the README's rule: a
prediction and a label pair when their xy centres are closer than 0.5 x the label's radius, greedily
closest first, one-to-one; ``partial`` labels are don't-care for the non-partial figures. Matched-pair
errors follow ../shared/real/score.py exactly: centre error is the 3D distance (the xy distance is
printed beside it), axis error the angle between signed up-vectors, radius error |r_p - r_l| / r_l
(with its signed median, and again against label radii freed of the labels' measured bias,
``FOOTPRINT_RADIUS_BIAS``, and for the non-partial caps of the bias at each label's tilt,
``FOOTPRINT_RADIUS_BIAS_BY_TILT``).
score.py itself is run on the same detections and its precision, recall and F1 compared with ours.
Beside them: where the false positives and misses sit, and (--by-size) recall by label radius.

--caps lists every non-partial label with its matched detection: radii, signed radius error, axis
error, and both tilts from the bed's normal.

--png draws a top view (x right, y up, input frame): points coloured by height above the bed plane,
labels as circles (green: full and found, grey: partial, thick yellow: full and missed), detections as
circles with a line along the projected cap axis (red: matched a full label, orange: matched a partial
one, thick magenta: false positive); white lines from each matched detection to its label; the bar at
the bottom left is 10 cm long.

Usage: python bench/real.py --cloud example_0.pcd --labels ../shared/real/labels_example_0.json
       [--thin MM] [--png OUT.png] [--json OUT.json] [--model PATH] [--by-size] [--caps]
       [--detect-arg=--clustering --detect-arg=dbscan] [--scorer PATH]
"""

import sys
from pathlib import Path

# the bench folder holds fusion.py and perception.py, which would shadow those packages
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import re  # noqa: E402
import shlex  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
DEFAULT_SCORER = REPO.parent / "shared" / "real" / "score.py"
SIZE_BINS_MM = (12.0, 20.0, 30.0)
"""Label radius bin edges for --by-size: <12, 12-20, 20-30, >=30 mm."""
AGREE = 1e-3
FOOTPRINT_RADIUS_BIAS = -0.068
"""Median signed relative error of a footprint radius (the labels' method) against the true radius on
fused synthetic beds, by ``python bench/label_quality.py --beds 10`` (the detector's own is -0.008
there). ../shared/real/README.md says so too: dim or shaded rims shrink a label's radius. The radius
error is also printed against label radii divided by 1 + this bias."""
FOOTPRINT_RADIUS_BIAS_BY_TILT = ((20.0, -0.013), (35.0, -0.047), (90.0, -0.108))
"""The same by a cap's tilt from the bed's normal, up to each bound in degrees (the table by tilt of
``python bench/label_quality.py --beds 10``, binned there by the true tilt): a leaning rim seen from
above covers less area, so the labels of leaning caps fall furthest short. The non-partial caps' radius
error is also printed against label radii freed of the shortfall at each label's own tilt, which stands
in for the true one (``footprint_bias_at``)."""
TURNS_DEG = (0.0, 11.0, 23.0, 37.0, 53.0, 71.0)
"""Turns of the cloud about the vertical through its centroid for --turns. The network's voxel grid is
laid in the bed frame, whose x follows the input's x: turning the cloud lays the grid differently over
every cap, as another scan of the same bed would. One cap moves F1 by 0.04 on 26 labels."""


@dataclass(frozen=True)
class Caps:
    """Caps read from a labels or detections JSON; nan where an entry has no axis or radius."""

    centers: np.ndarray
    """(n, 3) metres."""
    axes: np.ndarray
    """(n, 3) unit up-vectors."""
    radii: np.ndarray
    partial: np.ndarray
    ids: list

    def __len__(self) -> int:
        return len(self.centers)


def read_caps(source) -> Caps:
    """Caps from a path or parsed JSON: a list, or an object with a list under caps / predictions /
    detections / mushrooms (what score.py accepts)."""
    data = json.loads(Path(source).read_text()) if isinstance(source, (str, Path)) else source
    if isinstance(data, dict):
        for key in ("caps", "predictions", "detections", "mushrooms"):
            if isinstance(data.get(key), list):
                data = data[key]
                break
        else:
            lists = [v for v in data.values() if isinstance(v, list)]
            if len(lists) != 1:
                raise ValueError("expected a list of caps or an object holding one")
            data = lists[0]
    n = len(data)
    centers = np.array([c["center"] for c in data], np.float64).reshape(n, 3)
    axes = np.array([c["axis"] if c.get("axis") is not None else [np.nan] * 3 for c in data],
                    np.float64).reshape(n, 3)
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    radii = np.array([c["radius"] if c.get("radius") is not None else np.nan for c in data], np.float64)
    partial = np.array([bool(c.get("partial", False)) for c in data], bool)
    return Caps(centers, axes, radii, partial, [c.get("id", k) for k, c in enumerate(data)])


def match_xy(pred_centers: np.ndarray, label_centers: np.ndarray, label_radii: np.ndarray) -> np.ndarray:
    """Matched (prediction, label) index pairs, (m, 2): every pair whose xy centres are closer than
    0.5 x the label's radius, taken greedily closest first (ties by prediction, then label index),
    each prediction and label at most once."""
    pred_xy = np.asarray(pred_centers, np.float64).reshape(-1, 3)[:, :2]
    label_xy = np.asarray(label_centers, np.float64).reshape(-1, 3)[:, :2]
    delta = pred_xy[:, None, :] - label_xy[None, :, :]
    distance = np.sqrt(delta[..., 0] ** 2 + delta[..., 1] ** 2)
    pi, li = np.nonzero(distance < 0.5 * np.asarray(label_radii, np.float64)[None, :])
    order = np.lexsort((li, pi, distance[pi, li]))
    used_pred = np.zeros(len(pred_xy), bool)
    used_label = np.zeros(len(label_xy), bool)
    pairs = []
    for i, j in zip(pi[order].tolist(), li[order].tolist()):
        if not (used_pred[i] or used_label[j]):
            used_pred[i] = used_label[j] = True
            pairs.append((i, j))
    return np.array(pairs, np.int64).reshape(-1, 2)


def _prf(tp: int, n_pred: int, n_label: int) -> dict:
    precision = tp / n_pred if n_pred else 0.0
    recall = tp / n_label if n_label else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {"precision": precision, "recall": recall, "f1": f1}


def _stats(values: np.ndarray) -> dict:
    values = values[np.isfinite(values)]
    if not len(values):
        return {"n": 0, "mean": math.nan, "median": math.nan}
    return {"n": int(len(values)), "mean": float(np.mean(values)), "median": float(np.median(values))}


def pair_errors(preds: Caps, labels: Caps, pairs: np.ndarray) -> dict:
    """Centre (3D as score.py, and xy; mm), axis (deg) and relative radius errors of matched pairs."""
    p, lab = pairs[:, 0], pairs[:, 1]
    offset = preds.centers[p] - labels.centers[lab]
    unbiased = labels.radii[lab] / (1 + FOOTPRINT_RADIUS_BIAS)
    cosine = np.clip(np.sum(preds.axes[p] * labels.axes[lab], axis=1), -1.0, 1.0)
    return {"n": int(len(pairs)),
            "center_mm": _stats(1000 * np.linalg.norm(offset, axis=1)),
            "center_xy_mm": _stats(1000 * np.linalg.norm(offset[:, :2], axis=1)),
            "axis_deg": _stats(np.degrees(np.arccos(cosine))),
            "radius_rel": _stats(np.abs(preds.radii[p] - labels.radii[lab]) / labels.radii[lab]),
            "radius_rel_signed": _stats((preds.radii[p] - labels.radii[lab]) / labels.radii[lab]),
            "radius_rel_unbiased_labels": _stats(np.abs(preds.radii[p] - unbiased) / unbiased)}


def score(preds: Caps, labels: Caps) -> dict:
    """All figures of the README's xy matching: counts, precision/recall/F1 over all caps and over
    non-partial caps (a prediction matched to a partial label is neither TP nor FP there), errors."""
    if np.any(~(labels.radii > 0)):
        raise ValueError("every label needs a positive radius")
    pairs = match_xy(preds.centers, labels.centers, labels.radii)
    full_pairs = pairs[~labels.partial[pairs[:, 1]]]
    n_pred, n_label, n_full = len(preds), len(labels), int(np.sum(~labels.partial))
    tp, tp_full = len(pairs), len(full_pairs)
    ignored = tp - tp_full
    return {
        "n_predictions": n_pred, "n_labels": n_label, "n_full_labels": n_full,
        "all": {"tp": tp, "fp": n_pred - tp, "fn": n_label - tp, **_prf(tp, n_pred, n_label)},
        "nonpartial": {"tp": tp_full, "fp": n_pred - tp, "fn": n_full - tp_full, "ignored": ignored,
                       **_prf(tp_full, n_pred - ignored, n_full)},
        "diagnosis": diagnose(preds, labels, pairs),
        "errors_all": pair_errors(preds, labels, pairs),
        "errors_nonpartial": pair_errors(preds, labels, full_pairs),
        "pairs": pairs.tolist(),
    }


def diagnose(preds: Caps, labels: Caps, pairs: np.ndarray) -> dict:
    """Where the errors sit (not part of score.py): false positives whose xy centre lies inside a
    label's footprint (a second detection or an off-centre one on a labelled cap) or inside none, and
    missed non-partial labels with or without an unmatched prediction inside their footprint."""
    distance = np.linalg.norm(preds.centers[:, None, :2] - labels.centers[None, :, :2], axis=2)
    inside = distance < labels.radii[None, :]
    free_pred = np.ones(len(preds), bool)
    free_pred[pairs[:, 0]] = False
    missed = np.ones(len(labels), bool)
    missed[pairs[:, 1]] = False
    missed &= ~labels.partial
    return {"fp_on_a_label": int(np.sum(free_pred & inside.any(axis=1))),
            "fp_elsewhere": int(np.sum(free_pred & ~inside.any(axis=1))),
            "fn_with_unmatched_prediction_inside": int(np.sum(missed & inside[free_pred].any(axis=0))),
            "fn_nothing_inside": int(np.sum(missed & ~inside[free_pred].any(axis=0)))}


def recall_by_size(labels: Caps, pairs: np.ndarray) -> list[dict]:
    """Recall per label radius bin (SIZE_BINS_MM), over non-partial labels and over all labels."""
    found = np.zeros(len(labels), bool)
    found[np.asarray(pairs, np.int64).reshape(-1, 2)[:, 1]] = True
    bins = np.digitize(1000 * labels.radii, SIZE_BINS_MM)
    edges = (0.0, *SIZE_BINS_MM, math.inf)
    rows = []
    for b in range(len(edges) - 1):
        in_bin = bins == b
        full = in_bin & ~labels.partial
        rows.append({"radius_mm": [edges[b], edges[b + 1]],
                     "full": int(full.sum()), "full_found": int((full & found).sum()),
                     "all": int(in_bin.sum()), "all_found": int((in_bin & found).sum())})
    return rows


def footprint_bias_at(tilt_deg: np.ndarray) -> np.ndarray:
    """The footprint radius's shortfall (``FOOTPRINT_RADIUS_BIAS_BY_TILT``) at each tilt in degrees; nan
    where the tilt is unknown (a label without an axis)."""
    bounds = [bound for bound, _ in FOOTPRINT_RADIUS_BIAS_BY_TILT[:-1]]
    bias = np.array([bias for _, bias in FOOTPRINT_RADIUS_BIAS_BY_TILT])[np.digitize(tilt_deg, bounds)]
    return np.where(np.isfinite(tilt_deg), bias, np.nan)


def per_cap(preds: Caps, labels: Caps, pairs: np.ndarray, up: np.ndarray) -> list[dict]:
    """One row per non-partial label: its radius and tilt from ``up`` (the bed's normal), and for the
    detection matched to it the radius, signed relative radius error (also against the label's radius
    freed of the footprint's shortfall at its tilt), axis error and tilt (absent when missed). Where the
    mean errors come from, cap by cap."""
    from perception.cap import tilt_deg

    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    match = dict(zip(pairs[:, 1].tolist(), pairs[:, 0].tolist()))
    up = up / np.linalg.norm(up)

    def tilt(axis: np.ndarray) -> float:
        return float(tilt_deg(axis, up))

    rows = []
    for j in np.flatnonzero(~labels.partial):
        row = {"label": labels.ids[j], "radius_mm": 1000 * float(labels.radii[j]), "tilt_deg": tilt(labels.axes[j]),
               "found": j in match}
        if j in match:
            i = match[j]
            cosine = float(np.clip(preds.axes[i] @ labels.axes[j], -1.0, 1.0))
            fair = labels.radii[j] / (1 + float(footprint_bias_at(row["tilt_deg"])))
            row.update(detected_radius_mm=1000 * float(preds.radii[i]),
                       radius_rel_signed=float((preds.radii[i] - labels.radii[j]) / labels.radii[j]),
                       radius_rel_signed_tilt_unbiased=float((preds.radii[i] - fair) / fair),
                       axis_deg=float(np.degrees(np.arccos(cosine))), detected_tilt_deg=tilt(preds.axes[i]))
        rows.append(row)
    return rows


def tilt_unbiased_radius_errors(rows: list[dict]) -> dict:
    """Mean and median of the relative radius errors of per_cap's matched labels against their radii
    freed of the footprint's shortfall at each label's tilt."""
    return _stats(np.array([abs(r["radius_rel_signed_tilt_unbiased"]) for r in rows if r["found"]]))


def cap_report(rows: list[dict]) -> list[str]:
    """per_cap's rows as a table, the largest radius errors first, missed labels last."""
    lines = ["non-partial labels, largest radius error first: label | radius mm label / detected (error) | "
             "axis error deg | tilt deg label / detected"]
    found = sorted((r for r in rows if r["found"]), key=lambda r: -abs(r["radius_rel_signed"]))
    for r in found:
        lines.append(f"  {r['label']!s:>5} | {r['radius_mm']:5.1f} / {r['detected_radius_mm']:5.1f} "
                     f"({100 * r['radius_rel_signed']:+5.1f} %) | {r['axis_deg']:5.1f} | "
                     f"{r['tilt_deg']:4.1f} / {r['detected_tilt_deg']:4.1f}")
    for r in rows:
        if not r["found"]:
            lines.append(f"  {r['label']!s:>5} | {r['radius_mm']:5.1f} / missed | - | {r['tilt_deg']:4.1f} / -")
    return lines


_SCORER_LINE = re.compile(r"^(all caps|non-partial)\s*: TP=(\d+) FP=(\d+) FN=(\d+).*"
                          r"precision=([-\d.na]+) recall=([-\d.na]+) F1=([-\d.na]+)")
_SCORER_ERRORS = re.compile(r"^(all matched|non-partial matched)\s*: n=(\d+)\s+center err=(\S+) mm\s+"
                            r"axis err=(\S+) deg \(n=(\d+)\)\s+radius rel err=(\S+) \(n=(\d+)\)")


def run_scorer(scorer: Path, labels: Path, detections: Path) -> tuple[dict, list[str]]:
    """score.py --match-xy on the same files: its parsed figures and its printed lines."""
    done = subprocess.run([sys.executable, str(scorer), str(labels), str(detections), "--match-xy"],
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{scorer} exited with {done.returncode}: {done.stderr.strip()}")
    lines = done.stdout.splitlines()
    parsed = {}
    for line in lines:
        if m := _SCORER_LINE.match(line):
            key = "all" if m[1] == "all caps" else "nonpartial"
            parsed[key] = {"tp": int(m[2]), "fp": int(m[3]), "fn": int(m[4]), "precision": float(m[5]),
                           "recall": float(m[6]), "f1": float(m[7])}
        elif m := _SCORER_ERRORS.match(line):
            key = "errors_all" if m[1] == "all matched" else "errors_nonpartial"
            parsed[key] = {"n": int(m[2]), "center_mm": float(m[3]), "axis_deg": float(m[4]),
                           "axis_n": int(m[5]), "radius_rel": float(m[6]), "radius_n": int(m[7])}
    return parsed, lines


def _close(a: float, b: float, tolerance: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tolerance


def compare_with_scorer(ours: dict, theirs: dict) -> list[str]:
    """What differs between our figures and score.py's: counts exactly, precision/recall/F1 within
    AGREE, mean errors within the scorer's printed rounding. Empty when they agree."""
    problems = []
    for key in ("all", "nonpartial"):
        if key not in theirs:
            problems.append(f"{key}: not found in the scorer's output")
            continue
        for name in ("tp", "fp", "fn"):
            if ours[key][name] != theirs[key][name]:
                problems.append(f"{key} {name}: ours {ours[key][name]}, scorer {theirs[key][name]}")
        for name in ("precision", "recall", "f1"):
            if not _close(ours[key][name], theirs[key][name], AGREE):
                problems.append(f"{key} {name}: ours {ours[key][name]:.4f}, scorer {theirs[key][name]:.3f}")
    for key in ("errors_all", "errors_nonpartial"):
        if key not in theirs:
            problems.append(f"{key}: not found in the scorer's output")
            continue
        mine, other = ours[key], theirs[key]
        for name, ours_value, theirs_value, tolerance in (
                ("n", mine["n"], other["n"], 0), ("axis n", mine["axis_deg"]["n"], other["axis_n"], 0),
                ("radius n", mine["radius_rel"]["n"], other["radius_n"], 0),
                ("center mm", mine["center_mm"]["mean"], other["center_mm"], 0.051),
                ("axis deg", mine["axis_deg"]["mean"], other["axis_deg"], 0.051),
                ("radius rel", mine["radius_rel"]["mean"], other["radius_rel"], 0.00051)):
            if not _close(float(ours_value), float(theirs_value), tolerance):
                problems.append(f"{key} {name}: ours {ours_value}, scorer {theirs_value}")
    return problems


def thin_xyz(cloud_path: Path, thin_mm: float | None, out_ply: Path) -> np.ndarray:
    """The cloud's xyz only (voxel-thinned to ``thin_mm`` when given), written to ``out_ply``."""
    import open3d as o3d

    cloud = o3d.io.read_point_cloud(str(cloud_path))
    if not cloud.has_points():
        raise SystemExit(f"{cloud_path}: no points")
    xyz = o3d.geometry.PointCloud(cloud.points)
    if thin_mm:
        xyz = xyz.voxel_down_sample(thin_mm / 1000)
    if not o3d.io.write_point_cloud(str(out_ply), xyz):
        raise SystemExit(f"cannot write {out_ply}")
    return np.asarray(xyz.points).copy()


def stage_seconds(ply: Path, detect_args: list[str]) -> tuple[dict, np.ndarray, int]:
    """Seconds per stage of ``detect`` on ``ply`` in this process (weights, load, bed plane, network,
    instances, pose), with the calls of pipeline.cli.cmd_detect; also T_input_bed and the number of caps."""
    from common.geometry import transform_points
    from fusion.bed import estimate_bed_frame
    from perception.detect import detect_points, transform_result
    from perception.weights import DEFAULT_WEIGHTS
    from perception.instances import ClusterConfig
    from perception.weights import load_weights
    from pipeline.cli import build_parser
    from pipeline.clouds import load_cloud
    from pipeline.process import reuse_freed_memory

    args = build_parser().parse_args(["detect", str(ply), *detect_args])
    reuse_freed_memory()
    seconds = {}
    start = time.perf_counter()
    model, _ = load_weights(Path(args.model) if args.model else DEFAULT_WEIGHTS)
    seconds["weights"] = time.perf_counter() - start
    start = time.perf_counter()
    cloud = load_cloud(Path(args.cloud))
    seconds["load"] = time.perf_counter() - start
    start = time.perf_counter()
    T_input_bed = np.eye(4) if cloud.in_bed_frame or args.bed_frame else estimate_bed_frame(cloud.points)
    seconds["bed plane"] = time.perf_counter() - start
    bed_points = transform_points(np.linalg.inv(T_input_bed), cloud.points)
    result = detect_points(model, bed_points, ClusterConfig(method=args.method), zoom=args.zoom,
                           readings=args.readings)
    for name in ("network", "instances", "pose"):
        seconds[name] = result.timings_ms.get(name, math.nan) / 1000
    result = transform_result(result, T_input_bed, "input")
    return seconds, T_input_bed, len(result.caps)


# ---- top view

_HEIGHT_COLOURS = np.array([[48, 18, 59], [70, 107, 227], [41, 187, 236], [49, 242, 153], [163, 253, 61],
                            [237, 208, 58], [251, 128, 34], [210, 49, 5]], np.float64)
"""Dark blue (low) to red (high), after the turbo colour map."""
GREEN, GREY, YELLOW = (60, 220, 60), (150, 150, 150), (255, 235, 0)
RED, ORANGE, MAGENTA, WHITE = (255, 40, 40), (255, 150, 0), (255, 0, 255), (255, 255, 255)


class TopView:
    """A top-view canvas over the xy box of some points, ``size`` pixels along its longer side."""

    def __init__(self, xy: np.ndarray, size: int = 1200, margin: float = 0.02):
        low, high = xy.min(axis=0) - margin, xy.max(axis=0) + margin
        self.scale = (size - 1) / float(np.max(high - low))
        self.low, self.high = low, high
        width, height = np.ceil((high - low) * self.scale).astype(int) + 1
        self.image = np.full((height, width, 3), 16, np.uint8)

    def pixels(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows and columns of xy points (y up)."""
        col = np.round((xy[:, 0] - self.low[0]) * self.scale).astype(np.int64)
        row = np.round((self.high[1] - xy[:, 1]) * self.scale).astype(np.int64)
        return row, col

    def put(self, row: np.ndarray, col: np.ndarray, colour) -> None:
        h, w = self.image.shape[:2]
        inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
        colour = np.asarray(colour, np.uint8)
        self.image[row[inside], col[inside]] = colour[inside] if colour.ndim == 2 else colour

    def points(self, xy: np.ndarray, height: np.ndarray, dot: int) -> None:
        """Points as dot x dot squares coloured by height (2nd-98th percentile range), highest on top."""
        low, high = np.percentile(height, [2, 98])
        t = np.clip((height - low) / max(high - low, 1e-9), 0, 1) * (len(_HEIGHT_COLOURS) - 1)
        k = np.minimum(t.astype(int), len(_HEIGHT_COLOURS) - 2)
        colour = (_HEIGHT_COLOURS[k] * (1 - (t - k))[:, None] + _HEIGHT_COLOURS[k + 1] * (t - k)[:, None])
        row, col = self.pixels(xy)
        offsets = np.arange(dot) - (dot - 1) // 2
        dr, dc = (o.ravel() for o in np.meshgrid(offsets, offsets))
        row, col = (row[:, None] + dr).ravel(), (col[:, None] + dc).ravel()
        source = np.repeat(np.arange(len(xy)), len(dr))
        h, w = self.image.shape[:2]
        inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
        pixel, source = row[inside] * w + col[inside], source[inside]
        order = np.lexsort((height[source], pixel))
        last = np.r_[pixel[order][1:] != pixel[order][:-1], True]  # the highest point of each pixel
        pixel, source = pixel[order][last], source[order][last]
        self.image.reshape(-1, 3)[pixel] = colour[source].astype(np.uint8)

    def circles(self, centers: np.ndarray, radii: np.ndarray, colour, width: int = 1) -> None:
        """Circles of radius ``radii`` (metres) at xy ``centers``, ``width`` pixels wide, one pixel per
        perimeter step."""
        if not len(centers):
            return
        row, col = self.pixels(centers[:, :2])
        radius = radii * self.scale
        rings = [radius + w - (width - 1) / 2 for w in range(width)]
        rows, cols = [], []
        for r0, c0, rs in zip(row, col, np.stack(rings, axis=1)):
            for r in rs:
                angle = np.linspace(0, 2 * np.pi, max(8, int(np.ceil(2 * np.pi * max(r, 1)))), endpoint=False)
                rows.append(np.round(r0 - r * np.sin(angle)).astype(np.int64))
                cols.append(np.round(c0 + r * np.cos(angle)).astype(np.int64))
        self.put(np.concatenate(rows), np.concatenate(cols), colour)

    def lines(self, start: np.ndarray, end: np.ndarray, colour) -> None:
        """Segments between xy points, one sample per pixel."""
        if not len(start):
            return
        r0, c0 = self.pixels(start[:, :2])
        r1, c1 = self.pixels(end[:, :2])
        steps = np.maximum(np.abs(r1 - r0), np.abs(c1 - c0)) + 1
        t = np.concatenate([np.linspace(0, 1, s) for s in steps])
        which = np.repeat(np.arange(len(steps)), steps)
        self.put(np.round(r0[which] + t * (r1 - r0)[which]).astype(np.int64),
                 np.round(c0[which] + t * (c1 - c0)[which]).astype(np.int64), colour)

    def marks(self, centers: np.ndarray, colour, half: int = 2) -> None:
        """Small crosses at xy ``centers``."""
        if not len(centers):
            return
        row, col = self.pixels(centers[:, :2])
        for d in range(-half, half + 1):
            self.put(row + d, col, colour)
            self.put(row, col + d, colour)

    def scale_bar(self, length: float = 0.1) -> None:
        h = self.image.shape[0]
        n = int(round(length * self.scale))
        for dr in range(3):
            self.put(np.full(n, h - 15 + dr), 15 + np.arange(n), WHITE)


def _axis_tips(caps: Caps, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centres and centre + radius x the axis's xy projection (length radius x sin(tilt))."""
    axes = np.nan_to_num(caps.axes[index])
    radii = np.nan_to_num(caps.radii[index])
    return caps.centers[index], caps.centers[index] + radii[:, None] * axes * [1, 1, 0]


def top_view_png(path: Path, points: np.ndarray, height: np.ndarray, labels: Caps, preds: Caps,
                 pairs: np.ndarray, size: int = 1200) -> None:
    """The top view described in the module docstring, written as a PNG."""
    import open3d as o3d

    view = TopView(points[:, :2], size)
    spacing = np.median(np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
                                   .compute_nearest_neighbor_distance()))
    view.points(points[:, :2], height, dot=int(np.clip(np.ceil(1.1 * spacing * view.scale), 1, 9)))
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    found = np.zeros(len(labels), bool)
    found[pairs[:, 1]] = True
    matched = np.zeros(len(preds), bool)
    matched[pairs[:, 0]] = True
    to_partial = np.zeros(len(preds), bool)
    to_partial[pairs[:, 0]] = labels.partial[pairs[:, 1]]
    label_r = np.nan_to_num(labels.radii)
    pred_r = np.nan_to_num(preds.radii, nan=0.003)
    for mask, colour, width in ((labels.partial, GREY, 1), (~labels.partial & found, GREEN, 2),
                                (~labels.partial & ~found, YELLOW, 4)):
        view.circles(labels.centers[mask], label_r[mask], colour, width)
        view.lines(*_axis_tips(labels, np.flatnonzero(mask)), colour)
        view.marks(labels.centers[mask], colour)
    view.lines(preds.centers[pairs[:, 0]], labels.centers[pairs[:, 1]], WHITE)
    for mask, colour, width in ((matched & ~to_partial, RED, 2), (to_partial, ORANGE, 2),
                                (~matched, MAGENTA, 3)):
        view.circles(preds.centers[mask], pred_r[mask], colour, width)
        view.lines(*_axis_tips(preds, np.flatnonzero(mask)), colour)
        view.marks(preds.centers[mask], colour, half=1)
    view.scale_bar()
    o3d.io.write_image(str(path), o3d.geometry.Image(np.ascontiguousarray(view.image)))


# ---- printing

def _fmt(stats: dict, unit: str, digits: int = 1) -> str:
    return f"mean {stats['mean']:.{digits}f} / median {stats['median']:.{digits}f}{unit} (n={stats['n']})"


def report(figures: dict) -> list[str]:
    """The figures as printed lines."""
    lines = [f"{figures['n_predictions']} caps detected; {figures['n_labels']} labels "
             f"({figures['n_full_labels']} non-partial); xy matching, distance < 0.5 x label radius"]
    for key, name in (("nonpartial", "non-partial"), ("all", "all caps")):
        f = figures[key]
        extra = f" (ignored {f['ignored']} matched to partial)" if "ignored" in f else ""
        lines.append(f"{name:<12}: precision={f['precision']:.3f} recall={f['recall']:.3f} F1={f['f1']:.3f}  "
                     f"TP={f['tp']} FP={f['fp']} FN={f['fn']}{extra}")
    d = figures["diagnosis"]
    lines.append(f"false positives: {d['fp_on_a_label']} inside a label's radius (extra or off-centre detections "
                 f"of a labelled cap), {d['fp_elsewhere']} elsewhere; missed non-partial labels: "
                 f"{d['fn_with_unmatched_prediction_inside']} with an unmatched detection inside their radius, "
                 f"{d['fn_nothing_inside']} with none")
    for key, name in (("errors_nonpartial", "non-partial matched"), ("errors_all", "all matched")):
        e = figures[key]
        lines.append(f"{name} (n={e['n']}):")
        lines.append(f"  centre err 3D  {_fmt(e['center_mm'], ' mm')}   (score.py's centre error)")
        lines.append(f"  centre err xy  {_fmt(e['center_xy_mm'], ' mm')}")
        lines.append(f"  axis err       {_fmt(e['axis_deg'], ' deg')}")
        lines.append(f"  radius rel err {_fmt(e['radius_rel'], '', 3)}, signed median "
                     f"{e['radius_rel_signed']['median']:+.3f} (above 0: detections are larger)")
        lines.append(f"    against label radii / {1 + FOOTPRINT_RADIUS_BIAS:g} (footprint bias removed) "
                     f"{_fmt(e['radius_rel_unbiased_labels'], '', 3)}")
        if "radius_rel_tilt_unbiased_labels" in e:
            lines.append(f"    against label radii freed of the footprint's shortfall at each label's tilt "
                         f"{_fmt(e['radius_rel_tilt_unbiased_labels'], '', 3)}")
    return lines


def size_report(rows: list[dict]) -> list[str]:
    """recall_by_size's rows as printed lines."""
    lines = ["recall by label radius: non-partial found/labels (recall) | all found/labels"]
    for r in rows:
        low, high = r["radius_mm"]
        name = (f"< {high:.0f} mm" if low == 0 else f">= {low:.0f} mm" if math.isinf(high)
                else f"{low:.0f}-{high:.0f} mm")
        recall = f"{r['full_found'] / r['full']:.2f}" if r["full"] else "-"
        lines.append(f"  {name:<9}: {r['full_found']:>2}/{r['full']:<2} ({recall}) | {r['all_found']:>2}/{r['all']:<2}")
    return lines


def turned_runs(points: np.ndarray, labels: Caps, detect_args: list[str], folder: Path, count: int,
                first: dict) -> list[dict]:
    """Figures of detect on the cloud turned by each of the first ``count`` TURNS_DEG (the unturned
    run, ``first``, included; detections turned back before scoring), and their mean, min and max, printed."""
    import open3d as o3d
    from scipy.spatial.transform import Rotation

    runs = [{"turn_deg": TURNS_DEG[0], "nonpartial": first["nonpartial"], "all": first["all"]}]
    pivot = points.mean(0)
    for angle in TURNS_DEG[1:count]:
        rotation = Rotation.from_euler("z", angle, degrees=True).as_matrix()
        ply, out = folder / f"turned-{angle:g}.ply", folder / f"turned-{angle:g}.json"
        turned = (points - pivot) @ rotation.T + pivot
        o3d.io.write_point_cloud(str(ply), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(turned)))
        done = subprocess.run([sys.executable, "-m", "pipeline.cli", "detect", str(ply), "--out", str(out),
                               *detect_args], cwd=REPO, capture_output=True, text=True)
        if done.returncode != 0:
            sys.stderr.write(done.stdout + done.stderr)
            raise SystemExit(f"detect on the cloud turned by {angle:g} deg exited with {done.returncode}")
        preds = read_caps(json.loads(out.read_text()))
        back = dataclasses.replace(preds, centers=(preds.centers - pivot) @ rotation + pivot, axes=preds.axes @ rotation)
        figures = score(back, labels)
        runs.append({"turn_deg": angle, "nonpartial": figures["nonpartial"], "all": figures["all"]})
    for subset in ("nonpartial", "all"):
        f1 = np.array([run[subset]["f1"] for run in runs])
        p = np.array([run[subset]["precision"] for run in runs])
        r = np.array([run[subset]["recall"] for run in runs])
        print(f"{subset:<11} over {len(runs)} turns: F1 mean {f1.mean():.3f} (min {f1.min():.3f}, max {f1.max():.3f})  "
              f"precision {p.mean():.3f}  recall {r.mean():.3f}")
    return runs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cloud", type=Path, required=True, help="the real cloud (.pcd or .ply)")
    parser.add_argument("--labels", type=Path, required=True, help="labels JSON (../shared/real/)")
    parser.add_argument("--thin", type=float, help="voxel-thin the cloud to this many millimetres first")
    parser.add_argument("--png", type=Path, help="write a top view here")
    parser.add_argument("--json", type=Path, help="write every figure here")
    parser.add_argument("--model", help="weights file (default: the shipped model)")
    parser.add_argument("--by-size", action="store_true", help="also print recall by label radius")
    parser.add_argument("--caps", action="store_true",
                        help="also print every non-partial label with its matched detection's radius and axis errors")
    parser.add_argument("--detect-arg", action="append", default=[], metavar="ARG",
                        help="pass ARG on to detect (split like a shell word list), e.g. "
                             "--detect-arg=--clustering --detect-arg=dbscan")
    parser.add_argument("--turns", type=int, default=1, choices=range(1, len(TURNS_DEG) + 1), metavar="N",
                        help=f"also detect on the cloud turned about the vertical N-1 times (at most {len(TURNS_DEG)} "
                             "runs in all) and print the mean, min and max F1 over the N runs")
    parser.add_argument("--scorer", type=Path, default=DEFAULT_SCORER,
                        help="score.py to cross-check with (default ../shared/real/score.py from the repository)")
    args = parser.parse_args()
    detect_args = [word for arg in args.detect_arg for word in shlex.split(arg)]
    if args.model:
        detect_args = ["--model", str(Path(args.model).resolve()), *detect_args]
    labels = read_caps(args.labels)

    with tempfile.TemporaryDirectory(prefix="real-bench-") as folder:
        ply, out = Path(folder) / "cloud.ply", Path(folder) / "detections.json"
        points = thin_xyz(args.cloud, args.thin, ply)
        print(f"cloud: {args.cloud}, xyz only, {len(points)} points"
              + (f" after thinning to {args.thin:g} mm" if args.thin else ""), flush=True)
        command = [sys.executable, "-m", "pipeline.cli", "detect", str(ply), "--out", str(out), *detect_args]
        start = time.perf_counter()
        done = subprocess.run(command, cwd=REPO, capture_output=True, text=True)
        wall = time.perf_counter() - start
        if done.returncode != 0:
            sys.stderr.write(done.stdout + done.stderr)
            raise SystemExit(f"detect exited with {done.returncode}")
        detections = json.loads(out.read_text())
        print(f"detect: {wall:.1f} s wall for python -m pipeline.cli detect "
              f"{shlex.join(detect_args) or '(no options)'} (imports and weights included)", flush=True)
        seconds, T_input_bed, n_inprocess = stage_seconds(ply, detect_args)
        print("stages in process: " + "  ".join(f"{k} {v:.2f} s" for k, v in seconds.items())
              + f"  (sum {sum(seconds.values()):.1f} s, {n_inprocess} caps)")
        preds = read_caps(detections)
        figures = score(preds, labels)
        figures["by_size"] = recall_by_size(labels, np.array(figures["pairs"]))
        figures.update(cloud=str(args.cloud), labels=str(args.labels), thin_mm=args.thin, points=len(points),
                       detect_args=detect_args, detect_wall_s=wall, stage_s=seconds,
                       detections_in_process=n_inprocess)
        figures["caps"] = per_cap(preds, labels, np.array(figures["pairs"]), T_input_bed[:3, 2])
        figures["errors_nonpartial"]["radius_rel_tilt_unbiased_labels"] = tilt_unbiased_radius_errors(figures["caps"])
        print("\n".join(report(figures)))
        if args.by_size:
            print("\n".join(size_report(figures["by_size"])))
        if args.caps:
            print("\n".join(cap_report(figures["caps"])))
        if args.scorer.exists():
            theirs, lines = run_scorer(args.scorer, args.labels, out)
            problems = compare_with_scorer(figures, theirs)
            print(f"score.py ({args.scorer}):")
            print("\n".join("  " + line for line in lines if _SCORER_LINE.match(line) or _SCORER_ERRORS.match(line)))
            print(f"score.py agrees with ours (P/R/F1 to {AGREE:g})" if not problems
                  else "score.py DISAGREES: " + "; ".join(problems))
            figures["scorer"] = {"path": str(args.scorer), "figures": theirs, "agrees": not problems,
                                 "differences": problems}
        else:
            print(f"score.py not found at {args.scorer}: no cross-check")
        if args.png:
            height = (points - T_input_bed[:3, 3]) @ T_input_bed[:3, 2]
            top_view_png(args.png, points, height, labels, preds, np.array(figures["pairs"]))
            print(f"top view: {args.png}")
        if args.turns > 1:
            figures["turns"] = turned_runs(points, labels, detect_args, Path(folder), args.turns, figures)
        if args.json:
            args.json.write_text(json.dumps(figures, indent=1))
            print(f"figures: {args.json}")


if __name__ == "__main__":
    main()
