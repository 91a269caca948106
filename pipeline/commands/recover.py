"""``mushroom-pose recover``: a recording whose process died (power loss, SIGKILL) made a valid MCAP."""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.commands.common import CliError

NAME = "recover"
HELP = "rebuild a valid MCAP from a recording whose process died (X.mcap.partial), keeping every whole message"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("partial", help="the cut recording, e.g. session.mcap.partial")
    parser.add_argument("--out", help="the recovered MCAP (default: the name without .partial)")
    parser.add_argument("--overwrite", action="store_true", help="replace --out when it exists")


def run(args: argparse.Namespace) -> int:
    from capture.mcap.recovery import recover_recording

    partial = Path(args.partial)
    if not partial.is_file():
        raise CliError(f"{partial} does not exist" if not partial.exists() else f"{partial} is not a file")
    try:
        recovered = recover_recording(partial, args.out, overwrite=args.overwrite)
    except FileExistsError as error:
        raise CliError(f"{error}: --overwrite replaces it") from None
    except (ValueError, OSError) as error:
        raise CliError(str(error)) from None
    print(f"recovered {recovered.messages} messages ({recovered.depth_images} depth images) into {recovered.path}; "
          f"{partial} is kept (delete it once the recovered file replays)")
    return 0
