"""docs/CLI.md, the command-line reference, rendered from the parsers ``pipeline.cli`` builds: for
``mushroom-pose`` and each of its commands, the description and every argument with its metavar,
default and help.

``python -m pipeline.cli_reference`` rewrites docs/CLI.md; ``python -m pipeline.cli_reference --check``
changes nothing and exits 1 when docs/CLI.md is not what the parsers give (tests hold it to them).
The text is built from the parsers' actions, with no terminal-width formatting, so it is the same on
every terminal.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

REFERENCE = Path(__file__).resolve().parents[1] / "docs" / "CLI.md"
REGENERATE = "python -m pipeline.cli_reference"

INTRO = f"""# Command-line reference

Every command of `mushroom-pose` with every argument it takes, generated from the parsers
(`pipeline/cli.py`, `pipeline/commands/`) by `{REGENERATE}`: edit the parsers, not this file.
`mushroom-pose COMMAND --help` prints a command's flags in the terminal; every command takes `-h`, `--help`."""


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """Each command's parser by name, in ``parser``'s order."""
    return dict(_subparsers_action(parser).choices)


def arguments(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """The arguments ``parser``'s help lists, in its order (positionals first), bar ``--help`` and the
    commands' choice."""
    return [action for group in parser._action_groups for action in group._group_actions
            if action.help is not argparse.SUPPRESS
            and not isinstance(action, (argparse._HelpAction, argparse._SubParsersAction))]


def render(parser: argparse.ArgumentParser | None = None) -> str:
    """The reference of ``parser`` (default: ``mushroom-pose``'s) and of each of its commands, as Markdown."""
    if parser is None:
        from pipeline.cli import build_parser

        parser = build_parser()
    commands = _subparsers_action(parser)
    helps = {choice.dest: choice.help for choice in commands._choices_actions}
    sections = [INTRO, _section(parser, parser.description, commands)]
    sections += [_section(command, command.description or helps.get(name)) for name, command in commands.choices.items()]
    return "\n\n".join(sections) + "\n"


def _section(parser: argparse.ArgumentParser, description: str | None,
             commands: argparse._SubParsersAction | None = None) -> str:
    """One parser's heading, description, synopsis and table of arguments (or of commands)."""
    formatter = argparse.HelpFormatter(parser.prog, width=100)
    lines = [f"## {parser.prog}", ""]
    if description:
        lines += [_text(description), ""]
    lines.append(f"`{_synopsis(parser, formatter)}`")
    if commands is not None:
        helps = {choice.dest: choice.help for choice in commands._choices_actions}
        lines += ["", "| command | what it does |", "|---|---|"]
        lines += [f"| [`{name}`](#{_anchor(command.prog)}) | {_text(helps.get(name) or '')} |"
                  for name, command in commands.choices.items()]
    rows = arguments(parser)
    if rows:
        lines += ["", "| argument | default | what it does |", "|---|---|---|"]
        for action in rows:
            default = _default(action)
            lines.append(f"| `{_invocation(action, formatter)}` | {default} | {_help(parser, action, formatter, default)} |")
    return "\n".join(lines)


def _synopsis(parser: argparse.ArgumentParser, formatter: argparse.HelpFormatter) -> str:
    """The command with what it requires: its required options, its positionals and ``[options]``."""
    words = [parser.prog]
    optional = False
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            words.append(f"{action.dest.upper()} ...")
        elif isinstance(action, argparse._HelpAction) or action.help is argparse.SUPPRESS:
            continue
        elif not action.option_strings:
            words.append(_metavars(action, formatter))
        elif action.required:
            words.append(f"{action.option_strings[0]} {_metavars(action, formatter)}".strip())
        else:
            optional = True
    return " ".join(words + (["[options]"] if optional else []))


def _metavars(action: argparse.Action, formatter: argparse.HelpFormatter) -> str:
    """What an argument's values are called, as ``--help`` shows them (``LOW HIGH``, ``N [N ...]``)."""
    if action.nargs == 0:
        return ""
    default = action.dest.upper() if action.option_strings else action.dest
    return formatter._format_args(action, default)


def _invocation(action: argparse.Action, formatter: argparse.HelpFormatter) -> str:
    """An argument as it is typed: its option strings and their values."""
    if not action.option_strings:
        return _metavars(action, formatter)
    return f"{', '.join(action.option_strings)} {_metavars(action, formatter)}".strip()


def _default(action: argparse.Action) -> str:
    """An argument's default as it would be typed, ``required``, or nothing (the argument's absence)."""
    if action.required or (not action.option_strings and action.nargs not in ("?", "*")):
        return "required"
    if isinstance(action, argparse.BooleanOptionalAction):
        return f"`{action.option_strings[0 if action.default else 1]}`"
    value = action.default
    if action.nargs == 0 or value is None or value is argparse.SUPPRESS:
        return ""
    shown = " ".join(map(str, value)) if isinstance(value, (list, tuple)) else str(value)
    return f"`{shown}`"


STATED_DEFAULT = re.compile(r"\s*\(default: [^()]*\)$")
"""The default ``pipeline.flags`` appends to a flag's help, which the default column shows."""


def _help(parser: argparse.ArgumentParser, action: argparse.Action, formatter: argparse.HelpFormatter,
          default: str) -> str:
    """An argument's help as ``--help`` expands it, without the default it ends on when ``default``
    shows it, and the arguments it cannot be given with."""
    text = formatter._expand_help(action) if action.help else ""
    if default:
        text = STATED_DEFAULT.sub("", text)
    rivals = [other.option_strings[0] for group in parser._mutually_exclusive_groups
              if action in group._group_actions for other in group._group_actions if other is not action]
    if rivals:
        text += (" " if text else "") + "(not with " + ", ".join(rivals) + ")"
    return _text(text)


def _text(text: str) -> str:
    """Prose as one Markdown line: whitespace collapsed, and the characters escaped that would
    otherwise make markup or break a table (``_`` only where it could start or end emphasis)."""
    text = " ".join(text.split())
    return re.sub(r"[\\*<|]|(?<![A-Za-z0-9])_|_(?![A-Za-z0-9])", lambda mark: "\\" + mark[0], text)


def _anchor(heading: str) -> str:
    """The link target of a Markdown heading, as GitHub makes it."""
    return re.sub(r"[^\w\- ]", "", heading.lower()).replace(" ", "-")


def _subparsers_action(parser: argparse.ArgumentParser) -> argparse._SubParsersAction:
    return next(action for action in parser._actions if isinstance(action, argparse._SubParsersAction))


def main(argv: list[str] | None = None, reference: Path = REFERENCE) -> int:
    """Write ``reference`` (docs/CLI.md), or with ``--check`` say whether it is current: 0 yes, 1 no."""
    from pipeline.cli import OneLineErrorParser

    parser = OneLineErrorParser(prog=REGENERATE, description="Write docs/CLI.md from the parsers of mushroom-pose.")
    parser.add_argument("--check", action="store_true",
                        help="write nothing; exit 1 when docs/CLI.md differs from what the parsers give")
    args = parser.parse_args(argv)
    text = render()
    if args.check:
        current = reference.read_text() if reference.is_file() else None
        if current != text:
            state = "is missing" if current is None else "differs from the parsers"
            print(f"{reference} {state}: run {REGENERATE} to remake it", file=sys.stderr)
            return 1
        return 0
    try:
        reference.write_text(text)
    except OSError as error:
        print(f"cannot write {reference}: {error.strerror or error}", file=sys.stderr)
        return 1
    print(f"wrote {reference}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
