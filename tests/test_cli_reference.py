"""docs/CLI.md against the parsers: it is what they render, and it names every command and argument."""

import re

import pytest

from pipeline.cli import build_parser
from pipeline.cli_reference import REFERENCE, REGENERATE, arguments, main, render, subcommands


def sections() -> dict[str, str]:
    """Each ``## `` section of docs/CLI.md by its heading."""
    parts = REFERENCE.read_text().split("\n## ")[1:]
    return {part.split("\n", 1)[0]: part for part in parts}


def test_the_reference_is_what_the_parsers_render():
    assert REFERENCE.read_text() == render(), f"docs/CLI.md is out of date: run {REGENERATE}"


def test_every_command_and_argument_is_in_its_section():
    parser = build_parser()
    shown = sections()
    assert parser.prog in shown
    for name, command in subcommands(parser).items():
        assert f"[`{name}`]" in shown[parser.prog], f"{name} is missing from the list of commands"
        section = shown[command.prog]
        for action in arguments(command):
            names = action.option_strings or [action.metavar or action.dest]
            for option in names:
                assert re.search(rf"`(?:[^`]*[ ,])?{re.escape(option)}[ ,`]", section), f"{command.prog}: {option}"


def test_the_reference_does_not_depend_on_the_terminal_width(monkeypatch):
    monkeypatch.setenv("COLUMNS", "30")
    narrow = render()
    monkeypatch.setenv("COLUMNS", "300")
    assert render() == narrow


def test_check_says_in_one_line_when_the_file_differs(tmp_path, capsys):
    reference = tmp_path / "CLI.md"
    assert main(["--check"], reference) == 1
    assert "missing" in capsys.readouterr().err
    reference.write_text(render().replace("mushroom-pose train", "mushroom-pose teach", 1))
    assert main(["--check"], reference) == 1
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and REGENERATE in error
    assert main([], reference) == 0
    assert main(["--check"], reference) == 0
    assert reference.read_text() == render()


def test_bad_arguments_give_one_line_and_exit_2(capsys):
    with pytest.raises(SystemExit) as stopped:
        main(["--chekc"])
    assert stopped.value.code == 2
    assert capsys.readouterr().err.count("\n") == 1
