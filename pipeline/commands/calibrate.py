"""``mushroom-pose calibrate``: turntable axis and camera extrinsics from a recorded turn."""

from __future__ import annotations

import argparse
import sys
import time

from pipeline.commands.common import CliError, add_overwrite_flag, refuse_to_replace, writable_file

NAME = "calibrate"
HELP = "turntable axis and camera extrinsics from a recorded turn"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--session", required=True, help="an MCAP recording of one full turn")
    parser.add_argument("--out", required=True, help="the rig file (JSON) to write")
    parser.add_argument("--reference", help="the camera whose frame defines the rig (default: the first)")
    add_overwrite_flag(parser)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from capture.mcap.reader import McapSource
    from capture.source import SourceError
    from fusion.turntable import estimate_rig

    out = writable_file(args.out, inputs=(args.session,))
    refuse_to_replace([out], args.overwrite)
    try:
        with McapSource(args.session) as session:
            frames = list(session)
        if not frames:
            raise CliError(f"{args.session} holds no complete depth frames")
        started = time.perf_counter()
        rig = estimate_rig(frames, reference=args.reference)
    except (SourceError, ValueError) as error:
        raise CliError(str(error)) from None
    try:
        rig.save(out)
    except OSError as error:
        raise CliError(f"cannot write {out}: {error.strerror or error}") from None
    cameras = ", ".join(sorted(rig.cameras)) or frames[0].sensor_id
    turntable = "no turntable (fewer than 3 frames of the reference camera)"
    if rig.turntable is not None:
        axis = rig.turntable.axis_direction
        turntable = (f"turntable axis ({axis[0]:+.3f}, {axis[1]:+.3f}, {axis[2]:+.3f}) through "
                     f"{np.round(1000 * np.asarray(rig.turntable.axis_point), 1).tolist()} mm, step "
                     f"{np.degrees(rig.angle_step):.2f} deg")
    print(f"rig from {len(frames)} frames of {cameras} in {time.perf_counter() - started:.1f} s: {turntable} -> {out}")
    _warn_on_coverage(rig, frames, args.session)
    return 0


WHOLE_TURN_DEG = 330.0
"""A calibration turn that covers less than this (views times the angle step) is not a whole turn."""


def _warn_on_coverage(rig, frames, session: str) -> None:
    """Say so when the session's reference camera covers less than a whole turn: a turntable's axis
    from part of a circle is less certain (and a truncated recording looks like this)."""
    import numpy as np

    if rig.turntable is None or rig.angle_step is None:
        return
    reference = next(iter(rig.cameras), frames[0].sensor_id)
    views = sum(frame.sensor_id == reference for frame in frames)
    covered = float(np.degrees(abs(rig.angle_step))) * views
    if covered < WHOLE_TURN_DEG:
        print(f"warning: {session} covers about {covered:.0f} deg of the turntable's turn ({views} views "
              f"{np.degrees(abs(rig.angle_step)):.1f} deg apart): the axis is less certain than from a whole turn; "
              "record one whole turn to calibrate", file=sys.stderr)

