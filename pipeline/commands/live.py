"""``mushroom-pose live``: capture, fuse and detect as frames arrive, shown in Rerun and recorded."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from capture.cameras import CAMERAS
from pipeline.commands.common import (STOP_EXIT, CliError, CommandFailed, add_bed_id_flag, add_grades_flag,
                                      add_model_flag, add_overwrite_flag, add_pick_flags, add_quiet_flag, add_threads_flag,
                                      add_viewer_flags, grade_table, load_model, parse_readings, parse_seed,
                                      parse_threads, pick_config, positive, refuse_to_replace, torch_threads,
                                      viewer_target, writable_file, written_files)

NAME = "live"
HELP = "capture, fuse and detect as frames arrive, shown in Rerun and recorded"

RUN_FLAGS = {"max_units": {"name": "turns", "parse": positive(int), "metavar": "N"},
             "duration_s": {"name": "duration", "parse": positive(float), "metavar": "S"},
             "queue_frames": {"parse": positive(int), "metavar": "N"},
             "perception_threads": {"parse": parse_threads, "metavar": "N"}}
"""RunConfig's flags: names and validators where the field's own are not enough."""
STAGE_FLAGS = {"window": {"parse": positive(int), "metavar": "N"}}
PERCEPTION_FLAGS = {"readings": {"parse": parse_readings, "metavar": "N"}}
BED_FLAGS = {"seed": {"parse": parse_seed}}
CAMERA_FLAGS = {"views": {"parse": positive(int), "help": "Virtual camera: views per turn of the turntable."}}
FOXGLOVE_ADDRESS = "127.0.0.1:8765"
"""Where Foxglove looks for a live robot by default."""


def host_and_port(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``:PORT`` alone: 127.0.0.1) as (host, port)."""
    host, colon, port = text.rpartition(":")
    if not colon or not port.isdigit() or int(port) > 65535:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT with a port 0-65535, got {text!r}")
    return host or "127.0.0.1", int(port)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from pipeline.flags import add_config_flags  # loads ast: only a parsed live pays it

    parser.add_argument("--camera", choices=CAMERAS, required=True,
                        help="the depth camera; virtual renders a synthetic bed on a turntable, in real time at "
                             "15 fps")
    parser.add_argument("--serial", help="which camera (serial number or OAK MxId) when several are attached")
    parser.add_argument("--playback", help="RealSense: play this recorded device file (.db3) through the driver")
    parser.add_argument("--rig", help="rig file from mushroom-pose calibrate (turntable or several cameras)")
    add_config_flags(parser, "fusion.cloud:FusionStage", STAGE_FLAGS, only=("window",))
    parser.add_argument("--record", help="record the session (frames, fused clouds, caps) to this .mcap")
    add_bed_id_flag(parser)
    add_overwrite_flag(parser)
    add_viewer_flags(parser, "save the Rerun recording to this .rrd", serve_until="while the run lasts")
    parser.add_argument("--detections", help="keep the newest caps in this JSON file")
    parser.add_argument("--serve-foxglove", nargs="?", const=FOXGLOVE_ADDRESS, type=host_and_port,
                        metavar="HOST:PORT",
                        help=f"publish every channel of the session (frames, fused clouds, caps, the pick plan on "
                             f"/perception/plan and /perception/plan_json) live on a Foxglove WebSocket server, "
                             f"by default at {FOXGLOVE_ADDRESS} (port 0: any free port)")
    add_config_flags(parser, "pipeline.runner:RunConfig", RUN_FLAGS, only=tuple(RUN_FLAGS))
    add_config_flags(parser, "pipeline.sources:VirtualBed", BED_FLAGS, only=tuple(BED_FLAGS))
    add_config_flags(parser, "capture.virtual:VirtualCameraConfig", CAMERA_FLAGS, only=tuple(CAMERA_FLAGS))
    add_model_flag(parser)
    add_config_flags(parser, "pipeline.runner:PerceptionStage", PERCEPTION_FLAGS)
    add_grades_flag(parser)
    add_pick_flags(parser)
    add_threads_flag(parser)
    add_quiet_flag(parser, "no line per fused unit")


def _checked_outputs(args: argparse.Namespace) -> tuple:
    """The --record file, the viewer (--rrd, --spawn, --serve) and the --detections file, refused before
    any camera opens."""
    if args.playback and args.camera != "realsense":
        raise CliError("--playback plays a RealSense device file: use it with --camera realsense")
    if args.playback and not Path(args.playback).is_file():
        raise CliError(f"--playback: no device file at {args.playback}")
    viewer = viewer_target(args, hold=False)
    outputs = (writable_file(args.record, suffix=".mcap"), viewer, writable_file(args.detections, suffix=".json"))
    refuse_to_replace((outputs[0], viewer.rrd, outputs[2]), args.overwrite)
    return outputs


def run(args: argparse.Namespace) -> int:
    from pipeline.process import let_idle_threads_sleep

    let_idle_threads_sleep()  # before torch and Open3D load: the chain's stages share the cores
    from contextlib import ExitStack

    from capture.mcap.writer import serve_session
    from fusion.turntable import Rig

    files = _checked_outputs(args)
    pick, grades = pick_config(args), grade_table(args)
    rig = None
    if args.rig:
        try:
            rig = Rig.load(args.rig)
        except ValueError as error:
            raise CliError(str(error)) from None
    with ExitStack() as stack:
        publish_to = None
        if args.serve_foxglove:  # a port in use is refused before the model loads and the camera opens
            try:
                publish_to, port = stack.enter_context(serve_session(*args.serve_foxglove))
            except OSError as error:
                raise CliError(str(error)) from None
            print(f"Foxglove server: ws://{args.serve_foxglove[0]}:{port}", flush=True)
        model, _ = load_model(args.model)
        torch_threads(args.threads)
        return _run_live(args, model, rig, pick, grades, files, publish_to)


def _run_live(args: argparse.Namespace, model, rig, pick, grades, files: tuple, publish_to) -> int:
    """The camera through the chain into ``files`` (--record, the viewer, --detections) and a live server."""
    from capture.mcap.writer import RecordingError
    from pipeline.signals import graceful_stop
    from capture.source import SourceError
    from fusion.cloud import FusionStage
    from fusion.turntable import Rig
    from pipeline.flags import config_from_args
    from pipeline.runner import PerceptionStage, RunConfig
    from pipeline.chain import Outputs, run_chain
    from pipeline.sources import make_source

    record, viewer, detections = files
    rrd = viewer.rrd
    try:
        source = make_source(args.camera, args.serial, args.seed, args.views, playback=args.playback, live=True)
    except (SourceError, ImportError, ValueError) as error:
        raise CliError(f"{args.camera} camera: {error}") from None
    if args.camera == "virtual" and rig is None:
        rig = Rig(source.turntable)
    config = config_from_args(RunConfig, args, fusion=FusionStage(rig=rig, window=args.window),
                              perception=config_from_args(PerceptionStage, args),
                              plan=pick, grades=grades, live=True)
    outputs = Outputs(record=record, viewer=viewer, name=f"live {args.camera} {time.strftime('%Y-%m-%d %H:%M:%S')}",
                      detections=detections, quiet=args.quiet, publish_to=publish_to, bed_id=args.bed_id)
    with graceful_stop() as stop:
        try:
            summary = run_chain(source, model, config, outputs,
                                on_start=lambda text: print(f"fused unit: {text}", flush=True),
                                stop_requested=lambda: stop.signal if stop.requested else None,
                                overwrite=args.overwrite)
        except RecordingError as error:  # a full disk
            kept = written_files((record, rrd, detections))
            raise CommandFailed(f"{error}" + (f"; kept {kept}" if kept else "")) from None
        except (SourceError, ValueError, OSError) as error:
            kept = written_files((record, rrd, detections))
            raise CliError(f"{args.camera} camera: {error}" + (f"; kept {kept}" if kept else "")) from None
    outputs_line = written_files((record, rrd, detections)) or "nothing (add --record, --rrd or --detections)"
    line = (f"{summary.frames} frames, {summary.units} fused units, {len(summary.detections)} detected, "
            f"{summary.dropped_frames} frames and {summary.dropped_units} units dropped, {summary.failed_units} "
            f"units skipped; wrote {outputs_line}")
    if summary.stopped_by in STOP_EXIT:
        print(f"stopped by {summary.stopped_by}: {line}", file=sys.stderr)
        return STOP_EXIT[summary.stopped_by]
    print(f"{summary.stopped_by}: {line}")
    return 0
