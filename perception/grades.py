"""Grades: the named classes caps are sold in by cap diameter, and the grade of each cap.

A table lists its grades from the smallest up, each from the diameter where it begins, so the grades
tile the sizes with no gap and no overlap: a cap belongs to the last grade that begins at or below its
diameter (one under the first grade's start is ``UNDERSIZE``). The grower's own table comes from a
JSON or TOML file (``GradeTable.load``):

    {"grades": [{"name": "button", "from_mm": 0}, {"name": "closed cup", "from_mm": 40}]}

    [[grades]]
    name = "button"
    from_mm = 0
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

UNDERSIZE = "undersize"
"""The grade of a cap narrower than where the table's first grade begins."""


@dataclass(frozen=True)
class Grade:
    name: str
    from_mm: float
    """Cap diameter in mm where this grade begins; it ends where the next one begins."""


@dataclass(frozen=True)
class GradeTable:
    """Grades from the smallest up; the default is the trade's common sizes of white button mushrooms
    (Agaricus bisporus), a starting point for a grower's own."""

    grades: tuple[Grade, ...] = (Grade("small button", 0.0), Grade("button", 25.0), Grade("closed cup", 40.0),
                                 Grade("open cup", 55.0), Grade("flat", 70.0))

    def __post_init__(self) -> None:
        if not self.grades:
            raise ValueError("a grade table needs at least one grade")
        names = [grade.name for grade in self.grades]
        if not all(isinstance(name, str) and name.strip() for name in names):
            raise ValueError("every grade needs a name")
        if len(set(names)) < len(names) or UNDERSIZE in names:
            raise ValueError(f"grade names must differ from each other and from {UNDERSIZE!r}: {', '.join(names)}")
        starts = [grade.from_mm for grade in self.grades]
        if not all(isinstance(s, (int, float)) and not isinstance(s, bool) and math.isfinite(s) and s >= 0
                   for s in starts):
            raise ValueError(f"each grade's from_mm is a diameter in mm, 0 or more: got {starts}")
        if any(later <= earlier for earlier, later in zip(starts, starts[1:])):
            raise ValueError(f"grades are listed from the smallest up, each beginning above the one before: "
                             f"from_mm {starts}")

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(grade.name for grade in self.grades)

    @property
    def boundaries_mm(self) -> np.ndarray:
        """Where each grade begins, in mm."""
        return np.array([grade.from_mm for grade in self.grades], np.float64)

    def index_of(self, diameters_mm: np.ndarray) -> np.ndarray:
        """The grade index of each diameter (-1: undersize)."""
        return np.searchsorted(self.boundaries_mm, np.asarray(diameters_mm, np.float64), side="right") - 1

    def grade_of(self, diameters_mm: np.ndarray) -> list[str]:
        """The grade name of each diameter."""
        names = (*self.names, UNDERSIZE)  # index -1 reads the last entry
        return [names[index] for index in self.index_of(diameters_mm)]

    def to_document(self) -> list[dict]:
        return [{"name": grade.name, "from_mm": float(grade.from_mm)} for grade in self.grades]

    @staticmethod
    def from_document(document, where: str = "the grade table") -> "GradeTable":
        """A table from ``{"grades": [{"name", "from_mm"}, ...]}`` (or the list alone); a ValueError
        names ``where`` and what is wrong."""
        entries = document.get("grades") if isinstance(document, dict) else document
        if not isinstance(entries, list) or not all(isinstance(entry, dict) for entry in entries):
            raise ValueError(f"{where}: expected a list of grades, each with a name and a from_mm")
        try:
            return GradeTable(tuple(Grade(entry["name"], entry["from_mm"]) for entry in entries))
        except KeyError as missing:
            raise ValueError(f"{where}: a grade without {missing.args[0]!r} (each has a name and a from_mm)") from None
        except ValueError as error:
            raise ValueError(f"{where}: {error}") from None

    @staticmethod
    def load(path: str | Path) -> "GradeTable":
        """A table from a .json or .toml file; a ValueError (one line) when it cannot be one."""
        import json
        import tomllib

        path = Path(path)
        if path.suffix.lower() not in (".json", ".toml"):
            raise ValueError(f"{path}: a grade table is a .json or .toml file")
        try:
            text = path.read_text()
            document = json.loads(text) if path.suffix.lower() == ".json" else tomllib.loads(text)
        except OSError as error:
            raise ValueError(f"cannot read the grade table {path}: {error.strerror or error}") from None
        except (UnicodeDecodeError, json.JSONDecodeError, tomllib.TOMLDecodeError) as error:
            raise ValueError(f"{path} is not readable {path.suffix[1:].upper()}: {error}") from None
        return GradeTable.from_document(document, str(path))
