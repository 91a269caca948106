"""The grower's report: the caps of one or more beds graded, counted and mapped in one HTML file a
person reads (plots embedded as PNG, nothing fetched to open it), with each bed's map also as a PNG.

A bed is a session MCAP (its last unit's caps, over its fused cloud), a detection document (JSON, as
``detect`` writes it; a list of them gives its last) or a folder of those. Every cap is graded afresh by
one table, so beds recorded under another table still read alike; it is flagged ``uncertain`` when it
scores under the pick plan's ``min_score`` (or its document says so) and ``partial`` when the scan
does not cover its footprint (or its document says so)."""

from __future__ import annotations

import base64
import html
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from perception.grades import UNDERSIZE, GradeTable
from perception.plan import PickConfig

COVERED_WITHIN_M = 0.005
"""A point of a cap's footprint is covered when the scan has a point this near it in top view: about two
scan spacings, so a gap between points is no hole."""
PARTIAL_BELOW = 0.75
"""A cap is partial when less than this share of its footprint is covered (cut by the scan's edge or
hidden): its size and grade are less sure."""
MAP_POINTS = 20000
"""The most scan points a bed map draws: enough to show the soil, few enough to draw 20 beds quickly."""


class ReportError(ValueError):
    """An input that is no session, no detection document and no folder of them (one line)."""


@dataclass(frozen=True)
class Bed:
    """One bed's caps, in the bed frame (z up): their ids, centres (m), diameters (mm), scores, grades
    and flags, the pick plan's order, and the scan's points when the input holds them."""

    name: str
    ids: np.ndarray
    centers: np.ndarray
    diameters_mm: np.ndarray
    scores: np.ndarray
    grades: list[str]
    uncertain: np.ndarray
    partial: np.ndarray
    pick_order: list[int | None]
    scan: np.ndarray | None


def expand_inputs(inputs: list[str]) -> list[Path]:
    """The files the inputs name: each file itself, each folder's .mcap and .json files (sorted), bar
    the ``<stem>.expected.json`` beside a session (``replay --check``'s expectation, not a bed of its own)."""
    files = []
    for text in inputs:
        path = Path(text)
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.suffix.lower() in (".mcap", ".json") and p.is_file()
                           and not _beside_its_session(p))
            if not found:
                raise ReportError(f"{path} holds no session (.mcap) and no detection document (.json)")
            files.extend(found)
        elif path.is_file():
            files.append(path)
        else:
            raise ReportError(f"{path} does not exist")
    return files


def _beside_its_session(path: Path) -> bool:
    stem = path.name.removesuffix(".expected.json")
    return stem != path.name and any(path.with_name(stem + suffix).is_file() for suffix in (".mcap", ".db3"))


@dataclass(frozen=True)
class Growth:
    """One bed's caps over the days, as ``track`` wrote them (``track.json``)."""

    name: str
    bed_id: str
    pick_mm: float
    scan_days: list[float]
    caps: list[dict]
    forecast: dict


def is_track_document(document) -> bool:
    return isinstance(document, dict) and {"bed_id", "scans", "caps", "forecast"} <= document.keys()


def read_input(path: Path, grades: GradeTable, pick: PickConfig = PickConfig()) -> "Bed | Growth":
    """A session MCAP or a detection document as a bed, or a track document as its growth; a
    ReportError when it is none of them."""
    if path.suffix.lower() == ".json":
        document = _read_json(path)
        if is_track_document(document):
            return Growth(path.name, str(document["bed_id"]), float(document["pick_mm"]),
                          [float(scan["day"]) for scan in document["scans"]], document["caps"], document["forecast"])
    return read_bed(path, grades, pick)


def read_bed(path: Path, grades: GradeTable, pick: PickConfig = PickConfig()) -> Bed:
    """The bed of a session MCAP or a detection document; a ReportError when it is neither."""
    document, scan_world, T_world_bed = _read_input(path)
    from perception.cap import Caps

    try:
        caps = Caps.from_document(document)
    except ValueError as error:
        raise ReportError(f"{path}: {error}") from None
    T_frame_bed = _bed_frame(document, T_world_bed, path)
    T_bed_frame = np.linalg.inv(T_frame_bed)
    centers = caps.centers @ T_bed_frame[:3, :3].T + T_bed_frame[:3, 3]
    scan = None if scan_world is None else scan_world @ T_bed_frame[:3, :3].T + T_bed_frame[:3, 3]
    diameters = 2000.0 * caps.radii
    entries = document["mushrooms"]
    said = lambda key: np.array([bool(entry.get(key, False)) for entry in entries], bool)  # noqa: E731
    uncertain = said("uncertain") | (caps.score_array() < pick.min_score)
    partial = said("partial")
    if scan is not None:
        partial |= footprint_coverage(centers, caps.radii, scan) < PARTIAL_BELOW
    order = {cap_id: place for place, cap_id in enumerate((document.get("plan") or {}).get("order", []), 1)}
    ids = np.array([entry.get("id", k) for k, entry in enumerate(entries)], np.int64)
    return Bed(path.name, ids, centers, diameters, caps.score_array(), grades.grade_of(diameters), uncertain, partial,
               [order.get(int(cap_id)) for cap_id in ids], scan)


def footprint_coverage(centers: np.ndarray, radii: np.ndarray, scan: np.ndarray, samples: int = 24) -> np.ndarray:
    """Per cap (bed frame), the share of points on its rim circle, seen from above, that have a scan point
    within ``COVERED_WITHIN_M``."""
    from scipy.spatial import cKDTree

    if len(centers) == 0:
        return np.zeros(0)
    angles = 2 * np.pi * np.arange(samples) / samples
    rim = centers[:, None, :2] + radii[:, None, None] * np.stack([np.cos(angles), np.sin(angles)], 1)[None]
    distance, _ = cKDTree(scan[:, :2]).query(rim.reshape(-1, 2), distance_upper_bound=COVERED_WITHIN_M)
    return np.isfinite(distance).reshape(len(centers), samples).mean(1)


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ReportError(f"{path} is not readable JSON: {error}") from None


def _read_input(path: Path) -> tuple[dict, np.ndarray | None, np.ndarray | None]:
    """(the bed's detection document, the scan's points in the world frame, T_world_bed) of an input."""
    suffix = path.suffix.lower()
    if suffix == ".json":
        document = _read_json(path)
        if isinstance(document, list) and document:
            document = document[-1]
        if not isinstance(document, dict) or not isinstance(document.get("mushrooms"), list):
            raise ReportError(f"{path} is no detection document ({{\"mushrooms\": [...]}}, as detect writes)")
        return document, None, None
    if suffix == ".mcap":
        from capture.mcap.reader import read_documents, read_fused_units
        from capture.source import SourceError

        try:
            documents = read_documents(path)
            units = read_fused_units(path)
        except SourceError as error:
            raise ReportError(str(error)) from None
        if not documents:
            raise ReportError(f"{path} records no detections (/perception/mushrooms_json): replay it first")
        unit = units[-1] if units else None
        return documents[-1][1], None if unit is None else unit.points, None if unit is None else unit.T_world_bed
    raise ReportError(f"{path} is neither a session (.mcap) nor a detection document (.json)")


def _bed_frame(document: dict, T_world_bed: np.ndarray | None, path: Path) -> np.ndarray:
    """T_frame_bed of the document's frame: the bed's own, the input's (``T_input_bed``), or the world's
    (``T_world_bed``, from the document or the session's last unit)."""
    frame = document.get("frame", "bed")
    known = {"bed": np.eye(4), "input": document.get("T_input_bed"),
             "world": document.get("T_world_bed", T_world_bed)}
    if frame not in known:
        raise ReportError(f"{path}: unknown frame {frame!r} (bed, input or world)")
    if known[frame] is None:
        raise ReportError(f"{path}: its caps are in the {frame} frame, and it does not say where the bed lies "
                          f"in it (T_{frame}_bed)")
    return np.asarray(known[frame], np.float64).reshape(4, 4)


@dataclass(frozen=True)
class Report:
    """The report's files, made in memory and written together."""

    html: str
    maps: list[bytes]
    """One PNG per bed, in the order of the beds."""


def grade_colors(grades: GradeTable) -> dict[str, str]:
    """One colour per grade (small to large along a perceptual ramp), grey for undersize."""
    from matplotlib import colormaps

    ramp = colormaps["viridis"]
    count = len(grades.grades)
    colors = {name: _hex(ramp(0.1 + 0.8 * k / max(1, count - 1))) for k, name in enumerate(grades.names)}
    return {**colors, UNDERSIZE: "#9a9a9a"}


def make_report(beds: list[Bed], grades: GradeTable, title: str = "Mushroom bed report",
                growths: list[Growth] = ()) -> Report:
    """Counts and share per grade, the diameter histogram with the grade boundaries, each bed's map
    coloured by grade with cap ids, a table of every cap with its flags; for each tracked bed its caps'
    growth curves, a timeline of when each reaches the pick size and the count per grade to come."""
    import matplotlib

    matplotlib.use("Agg")
    colors = grade_colors(grades)
    names = [*grades.names, *([UNDERSIZE] if any(UNDERSIZE in bed.grades for bed in beds) else [])]
    counts = {name: sum(bed.grades.count(name) for bed in beds) for name in names}
    total = sum(counts.values())
    maps = [_png(_bed_map(bed, grades, colors)) for bed in beds]
    parts = [f"<h1>{html.escape(title)}</h1>",
             f"<p>{len(beds)} bed{'s' if len(beds) != 1 else ''}, {total} caps"
             + (f", {len(growths)} tracked over days" if growths else "") + ". Grades by cap diameter: "
             + ", ".join(f"{html.escape(g.name)} from {g.from_mm:g} mm" for g in grades.grades) + ".</p>",
             *(["<h2>Caps per grade</h2>", _grade_table(names, counts, total, colors),
                _img(_png(_histogram(beds, grades, colors)), "diameters with the grade boundaries")] if beds else [])]
    for bed, png in zip(beds, maps):
        flagged = int((bed.uncertain | bed.partial).sum())
        in_order = sum(place is not None for place in bed.pick_order)
        per_grade = ", ".join(f"{bed.grades.count(name)} {html.escape(name)}" for name in names
                              if name in bed.grades)
        parts += [f"<h2>{html.escape(bed.name)}</h2>",
                  f"<p>{len(bed.ids)} caps ({per_grade or 'none'}); {in_order} in the pick order; {flagged} "
                  "flagged (uncertain or partial).</p>",
                  _img(png, f"map of {bed.name}"), _cap_table(bed, colors)]
    for growth in growths:
        parts += _growth_section(growth, grades, colors)
    return Report(_page(title, "\n".join(parts)), maps)


def _hex(rgba) -> str:
    return "#" + "".join(f"{round(255 * channel):02x}" for channel in rgba[:3])


def _ink(background: str) -> str:
    """Black or white, whichever reads on ``background`` (by its luma)."""
    red, green, blue = (int(background[k:k + 2], 16) for k in (1, 3, 5))
    return "black" if 0.299 * red + 0.587 * green + 0.114 * blue > 150 else "white"


def _png(figure) -> bytes:
    import matplotlib.pyplot as plt

    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110, bbox_inches="tight")
    plt.close(figure)
    return buffer.getvalue()


def _img(png: bytes, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode()}">'


def _histogram(beds: list[Bed], grades: GradeTable, colors: dict[str, str]):
    """Cap diameters of every bed, stacked by grade, with a line where each grade begins."""
    import matplotlib.pyplot as plt

    diameters = np.concatenate([bed.diameters_mm for bed in beds]) if beds else np.zeros(0)
    labels = np.array(sum((bed.grades for bed in beds), []), object)
    top = max(grades.boundaries_mm[-1] + 20, float(diameters.max(initial=0)) + 5)
    bins = np.arange(0, top + 2.5, 2.5)
    figure, axes = plt.subplots(figsize=(8, 3.2))
    names = [name for name in (*grades.names, UNDERSIZE) if (labels == name).any()]
    if names:
        axes.hist([diameters[labels == name] for name in names], bins=bins, stacked=True,
                  color=[colors[name] for name in names], label=names)
    for grade in grades.grades:
        axes.axvline(grade.from_mm, color="#444444", linewidth=0.8, linestyle="--")
        axes.annotate(grade.name, (grade.from_mm, 1), xycoords=("data", "axes fraction"), xytext=(3, -12),
                      textcoords="offset points", fontsize=8, color="#444444")
    axes.set_xlabel("cap diameter (mm)")
    axes.set_ylabel("caps")
    axes.set_xlim(0, top)
    axes.spines[["top", "right"]].set_visible(False)
    return figure


def _bed_map(bed: Bed, grades: GradeTable, colors: dict[str, str]):
    """The bed from above (bed frame, mm): the scan in grey, each cap its true size in its grade's colour
    with its id; uncertain caps dashed, partial ones hatched."""
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Patch

    figure, axes = plt.subplots(figsize=(7, 7))
    if bed.scan is not None and len(bed.scan):
        step = max(1, len(bed.scan) // MAP_POINTS)
        soil = 1000 * bed.scan[::step]
        axes.scatter(soil[:, 0], soil[:, 1], s=0.6, c="#c4bcb0", linewidths=0, rasterized=True)
    for k in range(len(bed.ids)):
        x, y = 1000 * bed.centers[k, :2]
        axes.add_patch(Circle((x, y), bed.diameters_mm[k] / 2, facecolor=colors[bed.grades[k]], alpha=0.85,
                              edgecolor="black", linewidth=0.8, linestyle="--" if bed.uncertain[k] else "-",
                              hatch="///" if bed.partial[k] else None))
        axes.annotate(str(bed.ids[k]), (x, y), ha="center", va="center", fontsize=8, fontweight="bold",
                      color=_ink(colors[bed.grades[k]]))
    reach = [1000 * bed.centers[:, :2]] + ([1000 * bed.scan[:, :2]] if bed.scan is not None and len(bed.scan) else [])
    everything = np.concatenate(reach) if len(bed.ids) or len(reach) > 1 else np.zeros((1, 2))
    margin = 10 + (bed.diameters_mm.max(initial=0) / 2)
    low, high = everything.min(0) - margin, everything.max(0) + margin
    axes.set_xlim(low[0], high[0])
    axes.set_ylim(low[1], high[1])
    axes.set_aspect("equal")
    axes.set_xlabel("x (mm, bed frame)")
    axes.set_ylabel("y (mm)")
    axes.set_title(f"{bed.name}: {len(bed.ids)} caps")
    shown = [name for name in (*grades.names, UNDERSIZE) if name in bed.grades]
    handles = [Patch(facecolor=colors[name], edgecolor="black", label=name) for name in shown]
    handles += [Patch(facecolor="white", edgecolor="black", linestyle="--", label="uncertain"),
                Patch(facecolor="white", edgecolor="black", hatch="///", label="partial")]
    axes.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1), frameon=False, fontsize=8)
    return figure


def _growth_section(growth: Growth, grades: GradeTable, colors: dict[str, str]) -> list[str]:
    """A tracked bed: growth curves, the ready timeline and the forecast count per grade."""
    present = [cap for cap in growth.caps if cap["present"]]
    last = growth.scan_days[-1]
    coming = sorted((cap["ready_day"], cap["id"]) for cap in present
                    if cap["ready_day"] is not None and cap["seen"][-1]["diameter_mm"] < growth.pick_mm)
    days = growth.forecast["days"]
    header = "<tr><th>grade</th>" + "".join(f"<th>day {day:g}</th>" for day in days) + "</tr>"
    rows = "".join(f'<tr><td><span class="swatch" style="background:{colors.get(name, "#9a9a9a")}"></span>'
                   f"{html.escape(name)}</td>" + "".join(f"<td>{count}</td>" for count in counts) + "</tr>"
                   for name, counts in growth.forecast["grades"].items())
    return [f"<h2>Growth of bed {html.escape(growth.bed_id)} ({html.escape(growth.name)})</h2>",
            f"<p>{len(growth.scan_days)} scans over {last:.1f} days, {len(growth.caps)} caps followed, "
            f"{len(present)} on the last scan; {len(coming)} not yet {growth.pick_mm:g} mm are forecast to "
            "reach it.</p>",
            _img(_png(_growth_curves(growth, grades, colors)), f"growth of bed {growth.bed_id}"),
            _img(_png(_ready_timeline(growth, coming)), f"when the caps of bed {growth.bed_id} are ready"),
            "<h3>Caps per grade, days ahead</h3>", f"<table>{header}{rows}</table>"]


def _growth_curves(growth: Growth, grades: GradeTable, colors: dict[str, str]):
    """Each cap's diameter over the scans, coloured by its last grade, its line carried on to the pick
    size for those still growing toward it."""
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(8, 4))
    last = growth.scan_days[-1]
    for cap in growth.caps:
        days = [seen["day"] for seen in cap["seen"]]
        diameters = [seen["diameter_mm"] for seen in cap["seen"]]
        color = colors.get(grades.grade_of([diameters[-1]])[0], "#9a9a9a")
        axes.plot(days, diameters, marker="o", markersize=3, linewidth=1.2, color=color,
                  alpha=1.0 if cap["present"] else 0.45)
        ready = cap["ready_day"]
        if cap["present"] and ready is not None and diameters[-1] < growth.pick_mm and ready > days[-1]:
            axes.plot([days[-1], ready], [diameters[-1], growth.pick_mm], linestyle=":", linewidth=1, color=color)
    axes.axhline(growth.pick_mm, color="#444444", linestyle="--", linewidth=0.8)
    axes.annotate(f"pick size {growth.pick_mm:g} mm", (0, growth.pick_mm), xytext=(2, 3), textcoords="offset points",
                  fontsize=8, color="#444444")
    axes.axvline(last, color="#888888", linewidth=0.8)
    axes.set_xlabel("day (since the first scan)")
    axes.set_ylabel("cap diameter (mm)")
    axes.spines[["top", "right"]].set_visible(False)
    return figure


def _ready_timeline(growth: Growth, coming: list[tuple[float, int]]):
    """The day each cap on the last scan that is still under the pick size is forecast to reach it."""
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(8, max(1.6, 0.22 * len(coming) + 0.8)))
    if coming:
        ready, ids = zip(*coming)
        rows = np.arange(len(coming))
        axes.scatter(ready, rows, s=18, color="#2a7d4f")
        axes.set_yticks(rows, [f"#{cap}" for cap in ids], fontsize=7)
        axes.invert_yaxis()
    else:
        axes.set_yticks([])
        axes.text(0.5, 0.5, "no cap is forecast to reach the pick size", ha="center", va="center",
                  transform=axes.transAxes, fontsize=9)
    axes.axvline(growth.scan_days[-1], color="#888888", linewidth=0.8)
    axes.set_xlabel(f"day it reaches {growth.pick_mm:g} mm (the grey line: the last scan)")
    axes.spines[["top", "right"]].set_visible(False)
    return figure


def _grade_table(names: list[str], counts: dict[str, int], total: int, colors: dict[str, str]) -> str:
    rows = "".join(f'<tr><td><span class="swatch" style="background:{colors[name]}"></span>{html.escape(name)}</td>'
                   f"<td>{counts[name]}</td><td>{counts[name] / total:.0%}</td></tr>" if total else
                   f"<tr><td>{html.escape(name)}</td><td>0</td><td>-</td></tr>" for name in names)
    return f"<table><tr><th>grade</th><th>caps</th><th>share</th></tr>{rows}</table>"


def _cap_table(bed: Bed, colors: dict[str, str]) -> str:
    header = ("<tr><th>id</th><th>x mm</th><th>y mm</th><th>diameter mm</th><th class='grade'>grade</th><th>score</th>"
              "<th>pick order</th><th>flags</th></tr>")
    rows = []
    for k in range(len(bed.ids)):
        flags = ", ".join(name for name, on in (("uncertain", bed.uncertain[k]), ("partial", bed.partial[k])) if on)
        x, y = 1000 * bed.centers[k, :2]
        rows.append(f'<tr class="{"flagged" if flags else ""}"><td>{bed.ids[k]}</td><td>{x:.0f}</td><td>{y:.0f}</td>'
                    f"<td>{bed.diameters_mm[k]:.1f}</td>"
                    f'<td class="grade"><span class="swatch" style="background:{colors[bed.grades[k]]}"></span>'
                    f"{html.escape(bed.grades[k])}</td><td>{bed.scores[k]:.2f}</td>"
                    f"<td>{bed.pick_order[k] or ''}</td><td>{flags}</td></tr>")
    return f"<table>{header}{''.join(rows)}</table>"


def _page(title: str, body: str) -> str:
    style = ("body{font-family:system-ui,sans-serif;max-width:1000px;margin:2em auto;color:#222}"
             "table{border-collapse:collapse;margin:1em 0}td,th{border-bottom:1px solid #ddd;padding:3px 10px;"
             "text-align:right}td:first-child,th:first-child,.grade{text-align:left}tr.flagged{background:#fff4e0}"
             ".swatch{display:inline-block;width:.8em;height:.8em;margin-right:.4em;border:1px solid #555}"
             "img{max-width:100%}")
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
            f"<style>{style}</style></head><body>\n{body}\n</body></html>\n")
