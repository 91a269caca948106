"""``mushroom-pose demo``: the whole chain on a virtual turntable, no hardware."""

from __future__ import annotations

import argparse

from pipeline.commands.common import (CliError, CommandFailed, add_model_flag, add_overwrite_flag, add_quiet_flag,
                                      add_threads_flag, add_viewer_flags, load_model, parse_seed, positive,
                                      refuse_to_replace, torch_threads, viewer_target, writable_dir)

OUTPUTS = ("session.mcap", "detections.json", "demo.rrd")
"""What a demo writes into --out; none is replaced without --overwrite."""

NAME = "demo"
HELP = "the whole chain on a virtual turntable: capture, MCAP, fusion, detection, Rerun (no hardware)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="demo", help="output folder (default ./demo): session.mcap, "
                        "detections.json, demo.rrd")
    parser.add_argument("--seed", type=parse_seed, default=0, help="which synthetic bed")
    parser.add_argument("--views", type=positive(int), default=18, help="turntable views (default 18)")
    add_model_flag(parser)
    add_viewer_flags(parser, rrd=None)
    parser.add_argument("--no-rrd", action="store_true", help="do not write demo.rrd")
    add_threads_flag(parser)
    add_overwrite_flag(parser)
    add_quiet_flag(parser)


def run(args: argparse.Namespace) -> int:
    from pipeline.demo import run_demo

    model, _ = load_model(args.model)
    out_dir = writable_dir(args.out)
    refuse_to_replace([out_dir / name for name in OUTPUTS], args.overwrite)
    viewer = viewer_target(args, rrd=str(out_dir / "demo.rrd"))
    torch_threads(args.threads)
    print(f"a virtual D405 circles synthetic bed {args.seed} ({args.views} views, 848x480); "
          f"model: {args.model or 'shipped'}")
    try:
        result = run_demo(out_dir, model, args.seed, args.views, not args.no_rrd, viewer, progress=not args.quiet)
    except OSError as error:  # a full disk (RecordingError) or another failed write
        raise CommandFailed(f"{error}; {out_dir} is as it was") from None
    except ValueError as error:
        raise CliError(str(error)) from None
    stages = ", ".join(f"{name} {value:.1f} s" for name, value in result.seconds.items())
    axis = f"axis error {result.angle_deg:.1f} deg" if result.caps_found else "no caps matched"
    print(f"{result.caps_found} caps found, {result.caps_true} on the bed: AP@25 {result.ap25:.1%}, "
          f"AP@50 {result.ap50:.1%}, {axis} ({stages})")
    print(f"detections: {result.detections}  session: {result.recording}"
          + (f"  rerun: {result.rrd} (open with: rerun {result.rrd})" if result.rrd else ""))
    return 0
