"""The paper's Tables 1-4 (section 4.2) on our synthetic sets, its figures beside ours, with the median
milliseconds per bed of every method.

- Table 1: template matching by RANSAC (perception.baselines) with FPFH features, our network's last
  feature layer, and those plus the 5 encoding outputs; AP at IoU 0.25 (and 0.5).
- Table 2: the implicit encoding against the explicit centre and the explicit orientation, three
  networks trained with one recipe, seed and budget (``ENCODING_RUNS``), each read with its encoding's
  own pose (the axis from the encoding, no surface refinement, as the paper's).
- Table 3: our pipeline with DBSCAN and with MeanShift; AP at IoU 0.25 and 0.5.
- Table 4: scale and angle errors of the best RANSAC row, ours, and ours refined by ICP.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from perception.cap import Caps
from perception.evaluate import EvalResult, evaluate

TABLES = (1, 2, 3, 4)
ENCODING_RUNS = {"implicit": "slim-no", "explicit-centre": "slim-no-explicit-centre",
                 "explicit-orientation": "slim-no-explicit-orientation"}
"""Table 2's rows and the network preset (and run folder name) each is trained as."""
PAPER_ENCODINGS = {"explicit-centre": ("explicit center + implicit orientation", 0.2535),
                   "explicit-orientation": ("implicit center + explicit orientation", 0.4390),
                   "implicit": ("implicit center + implicit orientation", 0.9957)}
"""The paper's Table 2, AP at IoU 0.25."""
PAPER_RANSAC = {"fpfh": ("pre-trained FCGF", 0.7574), "network": ("fine-tuned FCGF", 0.8740),
                "network+encoding": ("fine-tuned FCGF + pose encoding", 0.8017)}
"""The paper's Table 1 (its features; ours in their place: FPFH, since FCGF's 3DMatch weights cannot be
had here, and our own network), AP at IoU 0.25."""
PAPER_CLUSTERING = {"dbscan": (0.9920, 0.8148), "meanshift": (0.9957, 0.8195)}
"""The paper's Table 3: AP at IoU 0.25 and 0.5."""
PAPER_ERRORS = {"ransac": (0.067, 0.9643, 15.35), "ours": (0.048, 0.9973, 4.22), "ours+icp": (0.1242, 0.9828, 10.63)}
"""The paper's Table 4: scale relative error, cosine, angle (degrees), over matches at IoU >= 0.25."""


@dataclass(frozen=True)
class Row:
    """One method's line of a table: its result on the set and its median milliseconds per bed."""

    method: str
    result: EvalResult
    ms_per_bed: float

    def as_dict(self) -> dict:
        return {"method": self.method, **self.result.as_dict(), "ms_per_bed": self.ms_per_bed}


def ground_truth(scenes) -> list[Caps]:
    from perception.evaluate import visible_truth

    return [visible_truth(scene) for scene in scenes]


def _row(method: str, found: list[Caps], seconds: list[float], truth: list[Caps]) -> Row:
    return Row(method, evaluate(found, truth), 1000 * float(np.median(seconds)) if seconds else float("nan"))


def ransac_rows(model, scenes, truth: list[Caps], progress: bool = False) -> list[Row]:
    """Table 1: every feature kind of the template-matching baseline."""
    from tqdm import tqdm

    from perception.baselines import FEATURES, TemplateMatching, match_templates

    rows = []
    for features in FEATURES:
        found, seconds = [], []
        for scene in tqdm(scenes, desc=f"RANSAC, {features}", unit="bed", disable=not progress, leave=False):
            start = time.perf_counter()
            found.append(match_templates(scene.points, TemplateMatching(features=features), model))
            seconds.append(time.perf_counter() - start)
        rows.append(_row(features, found, seconds, truth))
    return rows


def encoding_rows(models: dict, scenes, truth: list[Caps], progress: bool = False) -> list[Row]:
    """Table 2: each encoding's network (``models[encoding]``) with MeanShift and the encoding's own axis
    and size, as the paper poses caps."""
    from tqdm import tqdm

    from perception.detect import find_caps, predict
    from perception.instances import ClusterConfig

    rows = []
    for encoding, model in models.items():
        found, seconds = [], []
        for scene in tqdm(scenes, desc=encoding, unit="bed", disable=not progress, leave=False):
            start = time.perf_counter()
            prediction = predict(model, scene.points, readings=1)  # once, as the paper reads
            _, fit = find_caps(prediction, model.config.voxel, ClusterConfig(), axis="encoding", radius="fit")
            seconds.append(time.perf_counter() - start)
            found.append(fit)
        rows.append(_row(encoding, found, seconds, truth))
    return rows


def our_rows(model, scenes, truth: list[Caps], progress: bool = False) -> list[Row]:
    """Tables 3 and 4: ours with DBSCAN and MeanShift, and MeanShift's caps refined by ICP."""
    from tqdm import tqdm

    from perception.baselines import refine_by_icp
    from perception.detect import find_caps, predict
    from perception.instances import ClusterConfig

    found: dict[str, list] = {"dbscan": [], "meanshift": [], "ours+icp": []}
    seconds: dict[str, list] = {name: [] for name in found}
    for scene in tqdm(scenes, desc="ours", unit="bed", disable=not progress, leave=False):
        start = time.perf_counter()
        prediction = predict(model, scene.points, readings=1)  # once, as the paper reads
        network = time.perf_counter() - start
        for method in ("dbscan", "meanshift"):  # one network pass; each method's time is it plus its own
            start = time.perf_counter()
            labels, fit = find_caps(prediction, model.config.voxel, ClusterConfig(method=method), points=scene.points)
            seconds[method].append(network + time.perf_counter() - start)
            found[method].append(fit)
        start = time.perf_counter()
        found["ours+icp"].append(refine_by_icp(fit, points_by_cap(prediction.centroids, labels, len(fit.centers))))
        seconds["ours+icp"].append(seconds["meanshift"][-1] + time.perf_counter() - start)
    return [_row(name, found[name], seconds[name], truth) for name in found]


def points_by_cap(points: np.ndarray, labels: np.ndarray, caps: int) -> list[np.ndarray]:
    """The points of each label 0..caps-1 (one sort, no loop over points)."""
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(caps + 1))
    return [points[order[bounds[k]:bounds[k + 1]]] for k in range(caps)]


def _percent(value: float) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{100 * value:.2f} %"


def _number(value: float | None, form: str) -> str:
    return "-" if value is None or not np.isfinite(value) else form.format(value)


def _markdown(title: str, header: list[str], lines: list[list[str]]) -> list[str]:
    return [title, "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header),
            *("| " + " | ".join(line) + " |" for line in lines), ""]


def format_tables(name: str, rows: dict[int, list[Row]]) -> str:
    """The tables as Markdown, the paper's figures beside ours."""
    out: list[str] = []
    by_method = {row.method: row for table in rows.values() for row in table}
    if 1 in rows:
        out += _markdown(f"Table 1 ({name}): template matching by RANSAC",
                         ["features (ours / paper's)", "AP@25 paper", "AP@25 ours", "AP@50 ours", "ms per bed"],
                         [[f"{row.method} / {PAPER_RANSAC[row.method][0]}", _percent(PAPER_RANSAC[row.method][1]),
                           _percent(row.result.ap25), _percent(row.result.ap50), f"{row.ms_per_bed:.0f}"]
                          for row in rows[1]])
    if 2 in rows:
        out += _markdown(f"Table 2 ({name}): implicit against explicit encodings (networks of one recipe, seed and "
                         "budget)", ["predictions (paper's)", "AP@25 paper", "AP@25 ours", "AP@50 ours",
                                     "angle (deg) ours", "ms per bed"],
                         [[f"{row.method} ({PAPER_ENCODINGS[row.method][0]})", _percent(PAPER_ENCODINGS[row.method][1]),
                           _percent(row.result.ap25), _percent(row.result.ap50),
                           _number(row.result.angle_deg, "{:.2f}"), f"{row.ms_per_bed:.0f}"] for row in rows[2]])
    if 3 in rows:
        out += _markdown(f"Table 3 ({name}): clustering",
                         ["clustering", "AP@25 paper", "AP@25 ours", "AP@50 paper", "AP@50 ours", "ms per bed"],
                         [[method, _percent(PAPER_CLUSTERING[method][0]), _percent(by_method[method].result.ap25),
                           _percent(PAPER_CLUSTERING[method][1]), _percent(by_method[method].result.ap50),
                           f"{by_method[method].ms_per_bed:.0f}"] for method in ("dbscan", "meanshift")])
    if 4 in rows:
        lines = []
        for key, row in (("ransac", best_ransac(rows)), ("ours", by_method.get("meanshift")),
                         ("ours+icp", by_method.get("ours+icp"))):
            if row is not None:
                scale, cosine, angle = PAPER_ERRORS[key]
                lines.append([f"RANSAC, {row.method}" if key == "ransac" else key, _percent(scale),
                              _percent(row.result.scale_err), f"{cosine:.4f}", _number(row.result.cosine, "{:.4f}"),
                              f"{angle:.2f}", _number(row.result.angle_deg, "{:.2f}"), _percent(row.result.ap25),
                              f"{row.ms_per_bed:.0f}"])
        out += _markdown(f"Table 4 ({name}): scale and angle errors over matches at IoU >= 0.25",
                         ["method", "scale error paper", "ours", "cosine paper", "ours", "angle (deg) paper", "ours",
                          "AP@25 ours", "ms per bed"], lines)
    return "\n".join(out)


def best_ransac(rows: dict[int, list[Row]]) -> Row | None:
    """Table 1's row with the highest AP@25 (Table 4's RANSAC column), when Table 1 was run."""
    return max(rows.get(1, []), key=lambda row: row.result.ap25, default=None)


def run_tables(model, scenes, tables: tuple[int, ...], progress: bool = False,
               encoding_models: dict | None = None) -> dict[int, list[Row]]:
    """The rows of the chosen tables (4 needs 1's best row: it runs 1 as well; 2 needs
    ``encoding_models``, a network per encoding of ``ENCODING_RUNS``)."""
    unknown = sorted(set(tables) - set(TABLES))
    if unknown:
        raise ValueError(f"table {unknown[0]} is not available; choose from {', '.join(map(str, TABLES))}")
    truth = ground_truth(scenes)
    rows: dict[int, list[Row]] = {}
    if 2 in tables:
        if not encoding_models:
            raise ValueError("table 2 needs the three encodings' networks (ENCODING_RUNS)")
        rows[2] = encoding_rows(encoding_models, scenes, truth, progress)
    if 1 in tables or 4 in tables:
        rows[1] = ransac_rows(model, scenes, truth, progress)
    if 3 in tables or 4 in tables:
        ours = our_rows(model, scenes, truth, progress)
        rows[3] = [row for row in ours if row.method != "ours+icp"]
        if 4 in tables:
            rows[4] = [row for row in ours if row.method == "ours+icp"]
    return {number: table for number, table in rows.items() if number in tables or number == 1 and 4 in tables}
