"""``mushroom-pose report``: the grower's report of one or more beds, one HTML file and a PNG map per bed."""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.commands.common import (CliError, CommandFailed, add_grades_flag, add_overwrite_flag, grade_table,
                                      refuse_to_replace, writable_file)

NAME = "report"
HELP = "the caps of beds graded, counted and mapped in one HTML report (and a PNG map per bed)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("inputs", nargs="+", metavar="INPUT", help="a session .mcap (its last unit's caps over its "
                        "fused cloud), a detections .json (as detect writes it), a track.json (as track writes it: "
                        "growth curves, when caps are ready, the grades to come), or a folder of them")
    parser.add_argument("--out", default="report.html", help="the report (default report.html); each bed's map "
                        "is written beside it as OUT_STEM.png (one bed) or OUT_STEM-N.png (bed N of several)")
    parser.add_argument("--title", default="Mushroom bed report", help="the report's heading")
    add_grades_flag(parser)
    add_overwrite_flag(parser)


def map_paths(out: Path, beds: int) -> list[Path]:
    """Where each bed's map PNG goes, beside the report."""
    if beds == 1:
        return [out.with_suffix(".png")]
    return [out.with_name(f"{out.stem}-{k}.png") for k in range(1, beds + 1)]


def run(args: argparse.Namespace) -> int:
    from contextlib import ExitStack

    from common.files import atomic_path
    from pipeline.report import Bed, Growth, ReportError, expand_inputs, make_report, read_input

    grades = grade_table(args)
    try:
        files = expand_inputs(args.inputs)
    except ReportError as error:
        raise CliError(str(error)) from None
    out = writable_file(args.out, inputs=tuple(map(str, files)), suffix=".html")
    try:
        items = [read_input(path, grades) for path in files]
    except ReportError as error:
        raise CliError(str(error)) from None
    beds = [item for item in items if isinstance(item, Bed)]
    maps = map_paths(out, len(beds))
    refuse_to_replace([out, *maps], args.overwrite)
    report = make_report(beds, grades, args.title, [item for item in items if isinstance(item, Growth)])
    try:  # every file under a temporary name first, renamed together once all are whole
        with ExitStack() as stack:
            for path, content in [*zip(maps, report.maps), (out, report.html.encode())]:
                stack.enter_context(atomic_path(path)).write_bytes(content)
    except OSError as error:
        raise CommandFailed(f"cannot write the report: {error.strerror or error}; no file was changed") from None
    caps = sum(len(bed.ids) for bed in beds)
    print(f"{len(beds)} bed{'s' if len(beds) != 1 else ''}, {caps} caps"
          + (f", {len(items) - len(beds)} tracked over days" if len(items) > len(beds) else "")
          + f": {out}" + (f" (maps: {', '.join(str(path) for path in maps)})" if maps else ""))
    return 0
