"""Regression check of a replay: the new detections against those a session recorded, unit by unit,
caps matched by centre, within tolerances on centre, axis and radius; where both carry a pick plan, the
matched caps' readiness and the order they are picked in."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Tolerances:
    center_mm: float = 2.0
    axis_deg: float = 3.0
    radius_pct: float = 5.0

    def describe(self) -> str:
        return f"centre {self.center_mm:g} mm, axis {self.axis_deg:g} deg, radius {self.radius_pct:g} %"


@dataclass(frozen=True)
class CapDiff:
    """One expected or new cap and what changed: status ok, changed, lost or gained."""

    unit: int
    expected_id: int | None
    new_id: int | None
    status: str
    center_mm: float | None = None
    axis_deg: float | None = None
    radius_pct: float | None = None


@dataclass(frozen=True)
class PlanDiff:
    """A change of the pick plan in one unit: a matched cap's ``ready``, or the ``order`` (in the new
    document's ids, the expected order read through the matched caps)."""

    unit: int
    what: str
    expected: object
    new: object


@dataclass(frozen=True)
class CheckReport:
    diffs: list[CapDiff]
    units_expected: int
    units_new: int
    tolerances: Tolerances
    plan_diffs: list[PlanDiff] = field(default_factory=list)

    @property
    def regressions(self) -> list[CapDiff]:
        return [d for d in self.diffs if d.status != "ok"]

    @property
    def passed(self) -> bool:
        return not self.regressions and not self.plan_diffs and self.units_expected == self.units_new

    def table(self, everything: bool = False) -> str:
        """The per-cap diff (only what changed unless ``everything``) and a one-line verdict."""
        rows = self.diffs if everything else self.regressions
        lines = []
        if rows:
            lines.append(f"{'unit':>4} {'expected':>8} {'new':>4} {'status':<8} {'centre mm':>9} {'axis deg':>8} "
                         f"{'radius %':>8}")
            for d in rows:
                cells = [f"{v:>9.2f}" if v is not None else f"{'-':>9}" for v in (d.center_mm,)]
                cells += [f"{v:>8.2f}" if v is not None else f"{'-':>8}" for v in (d.axis_deg, d.radius_pct)]
                lines.append(f"{d.unit:>4} {'-' if d.expected_id is None else d.expected_id:>8} "
                             f"{'-' if d.new_id is None else d.new_id:>4} {d.status:<8} " + " ".join(cells))
        lines += [f"{d.unit:>4} plan {d.what}: expected {d.expected}, new {d.new}" for d in self.plan_diffs]
        caps = sum(d.expected_id is not None for d in self.diffs)
        counts = {s: sum(d.status == s for d in self.diffs) for s in ("ok", "changed", "lost", "gained")}
        units = "" if self.units_expected == self.units_new else \
            f"; {self.units_new} fused units where the session had {self.units_expected}"
        verdict = "PASS" if self.passed else "FAIL"
        lines.append(f"check {verdict}: {caps} expected caps in {self.units_expected} units: {counts['ok']} within "
                     f"tolerance, {counts['changed']} changed, {counts['lost']} lost, {counts['gained']} gained "
                     f"(tolerances: {self.tolerances.describe()}){units}"
                     + (f"; {len(self.plan_diffs)} pick plan changes" if self.plan_diffs else ""))
        return "\n".join(lines)


def _caps(document: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
    """Centres, axes, radii and ids of a detection document's caps (ids as the document gives them: an
    expected set edited by hand keeps its own)."""
    from perception.cap import Caps

    caps = Caps.from_document(document)
    return caps.centers, caps.axes, caps.radii, [int(c["id"]) for c in document["mushrooms"]]


def match_caps(expected: dict, new: dict, unit: int, tolerances: Tolerances) -> list[CapDiff]:
    """Caps of two detection documents paired by centre: closest pairs first, one to one, a pair only
    when the centres lie within the expected cap's radius of each other."""
    e_centers, e_axes, e_radii, e_ids = _caps(expected)
    n_centers, n_axes, n_radii, n_ids = _caps(new)
    distance = np.linalg.norm(e_centers[:, None] - n_centers[None], axis=2)
    candidates = np.argwhere(distance < e_radii[:, None])
    order = np.argsort(distance[candidates[:, 0], candidates[:, 1]], kind="stable")
    used_e, used_n, diffs = set(), set(), []
    for i, j in candidates[order]:
        if i in used_e or j in used_n:
            continue
        used_e.add(i)
        used_n.add(j)
        center = 1000 * distance[i, j]
        axis = float(np.degrees(np.arccos(np.clip(e_axes[i] @ n_axes[j] / np.linalg.norm(e_axes[i]) /
                                                  np.linalg.norm(n_axes[j]), -1.0, 1.0))))
        radius = 100 * abs(n_radii[j] - e_radii[i]) / e_radii[i]
        within = center <= tolerances.center_mm and axis <= tolerances.axis_deg and radius <= tolerances.radius_pct
        diffs.append(CapDiff(unit, e_ids[i], n_ids[j], "ok" if within else "changed", center, axis, radius))
    diffs += [CapDiff(unit, e_ids[i], None, "lost") for i in range(len(e_ids)) if i not in used_e]
    diffs += [CapDiff(unit, None, n_ids[j], "gained") for j in range(len(n_ids)) if j not in used_n]
    return sorted(diffs, key=lambda d: (d.expected_id is None, d.expected_id or 0, d.new_id or 0))


def compare(expected: list[dict], new: list[dict], tolerances: Tolerances = Tolerances()) -> CheckReport:
    """Unit k of ``new`` against unit k of ``expected``; a unit only one side has counts all its caps
    as lost or gained."""
    diffs, plan_diffs = [], []
    for unit in range(max(len(expected), len(new))):
        empty = {"mushrooms": []}
        before, after = expected[unit] if unit < len(expected) else empty, new[unit] if unit < len(new) else empty
        unit_diffs = match_caps(before, after, unit, tolerances)
        diffs += unit_diffs
        if "plan" in before and "plan" in after:
            plan_diffs += compare_plans(before["plan"], after["plan"], unit_diffs, unit)
    return CheckReport(diffs, len(expected), len(new), tolerances, plan_diffs)


def compare_plans(expected: dict, new: dict, pairs: list[CapDiff], unit: int) -> list[PlanDiff]:
    """What changed between two pick plans of one unit whose caps ``pairs`` matched: a matched cap that
    became ready or stopped being ready, and the order when it is not the same caps in the same turn."""
    ready_before = {cap["id"]: cap["ready"] for cap in expected["caps"]}
    ready_after = {cap["id"]: cap["ready"] for cap in new["caps"]}
    matched = {d.expected_id: d.new_id for d in pairs if d.expected_id is not None and d.new_id is not None}
    changes = [PlanDiff(unit, f"cap {new_id} ready", ready_before.get(old_id), ready_after.get(new_id))
               for old_id, new_id in matched.items() if ready_before.get(old_id) != ready_after.get(new_id)]
    order_before = [matched.get(cap) for cap in expected["order"]]
    if order_before != list(new["order"]):
        changes.append(PlanDiff(unit, "order", order_before, list(new["order"])))
    return changes
