"""README's "## Commands" table against the parser: every flag a row shows exists, every command has a row."""

import argparse
import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def command_rows() -> list[tuple[str, list[str]]]:
    """(command, flags its row shows in either column) of each row of the Commands table, the command
    from the row's first column."""
    section = README.read_text().split("\n## Commands\n", 1)[1].split("\n## ", 1)[0]
    rows = []
    for usage, description in re.findall(r"^\| `(mushroom-pose [^`]*)` \|(.*)$", section, re.MULTILINE):
        rows.append((usage.split()[1], re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", usage + description)))
    return rows


def command_parsers() -> dict[str, argparse.ArgumentParser]:
    from pipeline.cli import build_parser
    from pipeline.cli_reference import subcommands

    return subcommands(build_parser())


def test_every_flag_in_the_commands_table_exists():
    parsers = command_parsers()
    rows = command_rows()
    assert rows
    for command, flags in rows:
        assert command in parsers, f"README shows a command the parser lacks: {command}"
        known = {option for action in parsers[command]._actions for option in action.option_strings}
        assert not set(flags) - known, f"mushroom-pose {command}: README shows {sorted(set(flags) - known)}"


def test_every_command_has_a_row():
    shown = {command for command, _ in command_rows()}
    assert set(command_parsers()) <= shown, sorted(set(command_parsers()) - shown)
