"""Grades by cap diameter: each cap in the grade whose range holds it, tables read from JSON and TOML."""

import numpy as np
import pytest

from perception.grades import UNDERSIZE, Grade, GradeTable


def reference_grade(table: GradeTable, diameter: float) -> str:
    """The definition read literally: the last grade that begins at or below the diameter."""
    begun = [grade.name for grade in table.grades if grade.from_mm <= diameter]
    return begun[-1] if begun else UNDERSIZE


def test_each_diameter_gets_the_grade_whose_range_holds_it():
    table = GradeTable((Grade("button", 20.0), Grade("cup", 40.0), Grade("flat", 65.5)))
    diameters = np.concatenate([np.random.default_rng(0).uniform(0, 100, 500), [20.0, 40.0, 65.5, 19.999, 65.49]])
    assert table.grade_of(diameters) == [reference_grade(table, d) for d in diameters]
    assert table.grade_of([19.999, 20.0, 39.9, 40.0, 65.5]) == [UNDERSIZE, "button", "button", "cup", "flat"]


def test_the_default_table_grades_every_size():
    table = GradeTable()
    assert table.grades[0].from_mm == 0 and UNDERSIZE not in table.grade_of(np.linspace(0, 200, 101))
    assert len(set(table.grade_of(np.linspace(0, 200, 101)))) == len(table.grades)


def test_json_and_toml_tables_read_the_same(tmp_path):
    (tmp_path / "g.json").write_text('{"grades": [{"name": "small", "from_mm": 0}, {"name": "large", "from_mm": 45}]}')
    (tmp_path / "g.toml").write_text('[[grades]]\nname = "small"\nfrom_mm = 0\n\n[[grades]]\nname = "large"\n'
                                     'from_mm = 45\n')
    expected = GradeTable((Grade("small", 0), Grade("large", 45)))
    assert GradeTable.load(tmp_path / "g.json") == GradeTable.load(tmp_path / "g.toml") == expected
    assert GradeTable.from_document({"grades": expected.to_document()}) == expected


@pytest.mark.parametrize("text, message", [
    ('{"grades": []}', "at least one grade"),
    ('{"grades": [{"name": "a", "from_mm": 30}, {"name": "b", "from_mm": 20}]}', "from the smallest up"),
    ('{"grades": [{"name": "a", "from_mm": 0}, {"name": "a", "from_mm": 20}]}', "must differ"),
    ('{"grades": [{"name": "a"}]}', "without 'from_mm'"),
    ('{"grades": [{"name": "a", "from_mm": -1}]}', "0 or more"),
    ('{"grades": [{"name": "a", "from_mm": "ten"}]}', "0 or more"),
    ('{"grades": {"name": "a"}}', "expected a list"),
    ('{"grades": [', "not readable JSON"),
])
def test_a_bad_table_is_one_clear_line(tmp_path, text, message):
    path = tmp_path / "grades.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as error:
        GradeTable.load(path)
    assert "\n" not in str(error.value) and str(path) in str(error.value)


def test_a_table_is_a_json_or_toml_file(tmp_path):
    with pytest.raises(ValueError, match="a .json or .toml file"):
        GradeTable.load(tmp_path / "grades.csv")
    with pytest.raises(ValueError, match="cannot read"):
        GradeTable.load(tmp_path / "missing.json")
