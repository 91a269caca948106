"""``mushroom-pose record``: a depth camera session to MCAP."""

from __future__ import annotations

import argparse
import sys

from capture.cameras import CAMERAS
from pipeline.commands.common import (STOP_EXIT, CliError, CommandFailed, add_bed_id_flag, add_overwrite_flag,
                                      add_quiet_flag, parse_seed, positive, refuse_to_replace, writable_file)

NAME = "record"
HELP = "record a depth camera session to MCAP"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--camera", choices=CAMERAS, required=True,
                        help="the depth camera; virtual renders one turn of a synthetic bed on a turntable")
    parser.add_argument("--serial", help="which camera (serial number or OAK MxId) when several are attached")
    parser.add_argument("--out", required=True, help="the .mcap file to write")
    add_bed_id_flag(parser)
    parser.add_argument("--duration", type=positive(float), help="seconds to record (default: until the "
                        "source ends or Ctrl-C)")
    parser.add_argument("--seed", type=parse_seed, default=0, help="virtual camera: which synthetic bed")
    parser.add_argument("--views", type=positive(int), default=18, help="virtual camera: turntable views")
    add_overwrite_flag(parser)
    add_quiet_flag(parser)


def run(args: argparse.Namespace) -> int:
    from capture.mcap.writer import RecordingError, record
    from capture.source import SourceError
    from pipeline.signals import graceful_stop
    from pipeline.sources import make_source

    out = writable_file(args.out)
    refuse_to_replace([out], args.overwrite)
    written = [0]
    try:
        source = make_source(args.camera, args.serial, args.seed, args.views)
        with source, graceful_stop() as stop:
            summary = record(source, out, args.duration, progress=not args.quiet, overwrite=args.overwrite,
                             on_frame=lambda frames, _: written.__setitem__(0, frames), stop=stop,
                             bed_id=args.bed_id)
    except (SourceError, ValueError) as error:
        kept = (f"; the {written[0]} frames recorded so far are in {out}" if written[0]
                else "; nothing was recorded" + (f", {out} is as it was" if out.exists() else ""))
        camera = f"{args.camera} camera: " if isinstance(error, SourceError) else ""
        raise CliError(f"{camera}{error}{kept}") from None
    except (ImportError, FileExistsError) as error:
        raise CliError(str(error)) from None
    except RecordingError as error:
        raise CommandFailed(str(error)) from None
    line = f"recorded {summary.frames} frames in {summary.seconds:.1f} s ({summary.stopped_by}) -> {out} " \
           f"({summary.bytes / 1e6:.1f} MB)"
    if summary.stopped_by in STOP_EXIT:  # stopped, not done: a supervisor must be able to tell
        print(f"stopped by {summary.stopped_by}: {line}", file=sys.stderr)
        return STOP_EXIT[summary.stopped_by]
    print(line)
    return 0
