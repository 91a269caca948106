"""The commands around many sessions and the paper's tables: ``replay SESSIONS...`` (a corrupt session is
one failed row), ``recover``, ``eval --table`` and strict JSON."""

import json
import math
from pathlib import Path

import pytest

from pipeline.cli import main

RECORDINGS = Path(__file__).resolve().parents[1] / "recordings"


def test_replaying_several_sessions_reports_one_row_each_and_a_corrupt_one_fails_alone(tmp_path, capsys):
    corrupt = tmp_path / "corrupt.mcap"
    corrupt.write_bytes((RECORDINGS / "single-view.mcap").read_bytes()[:3000])
    out = tmp_path / "farm"
    code = main(["replay", str(RECORDINGS / "single-view.mcap"), str(corrupt), "--check", "--out", str(out), "--quiet"])
    printed = capsys.readouterr().out
    assert code == 1  # one session failed
    report = json.loads((out / "report.json").read_text())
    rows = {Path(row["session"]).name: row for row in report["sessions"]}
    assert set(rows) == {"single-view.mcap", "corrupt.mcap"}
    good, bad = rows["single-view.mcap"], rows["corrupt.mcap"]
    expected_caps = len(json.loads((RECORDINGS / "single-view.expected.json").read_text())[-1]["mushrooms"])
    assert good["error"] is None and good["changes"] == [] and good["caps"] == expected_caps
    assert bad["caps"] is None and bad["error"] and "\n" not in bad["error"]
    assert "2 sessions: 1 ok, 0 changed, 1 failed" in printed


def test_a_folder_of_sessions_expands_to_its_recordings(tmp_path):
    from pipeline.farm import expand_sessions

    sessions = expand_sessions([str(RECORDINGS), str(RECORDINGS / "single-view.mcap")])
    assert sessions == sorted(p for p in RECORDINGS.iterdir() if p.suffix in (".mcap", ".db3"))
    with pytest.raises(ValueError, match="matches no session"):
        expand_sessions([str(tmp_path / "*.mcap")])


def test_recover_command_rebuilds_a_cut_recording_and_refuses_to_replace_one(tmp_path, capsys):
    data = (RECORDINGS / "turntable-12.mcap").read_bytes()
    partial = tmp_path / "cut.mcap.partial"
    partial.write_bytes(data[:len(data) // 2])
    assert main(["recover", str(partial)]) == 0
    assert "recovered" in capsys.readouterr().out and (tmp_path / "cut.mcap").is_file()
    before = (tmp_path / "cut.mcap").read_bytes()
    assert main(["recover", str(partial)]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert (tmp_path / "cut.mcap").read_bytes() == before


def test_json_output_is_strict_an_undefined_figure_is_null():
    from pipeline.commands.common import json_text

    text = json_text({"a": math.nan, "b": [1.0, math.inf], "c": {"d": -math.inf, "e": 2}})
    assert json.loads(text) == {"a": None, "b": [1.0, None], "c": {"d": None, "e": 2}}
    assert "NaN" not in text and "Infinity" not in text


def test_eval_table_prints_the_papers_figures_beside_ours(tmp_path, capsys):
    report = tmp_path / "tables.json"
    assert main(["eval", "--table", "3", "--set", "val50", "--scenes", "1", "--quiet", "--json", str(report)]) == 0
    printed = capsys.readouterr().out
    assert "Table 3 (val50, first 1 beds)" in printed and "| meanshift | 99.57 % |" in printed
    rows = json.loads(report.read_text())["val50"]["3"]
    assert [row["method"] for row in rows] == ["dbscan", "meanshift"]
    assert all(0.0 <= row["ap25"] <= 1.0 and row["ms_per_bed"] > 0 for row in rows)


def test_eval_table_2_without_its_networks_says_how_to_make_them(tmp_path, capsys):
    assert main(["eval", "--table", "2", "--set", "val50", "--scenes", "1", "--encodings", str(tmp_path)]) == 2
    assert "bench/encodings.py" in capsys.readouterr().err
