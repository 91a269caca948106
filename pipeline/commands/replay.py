"""``mushroom-pose replay``: a recorded session through fusion and perception again; ``--check``
compares the new caps with those the session recorded."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline.commands.common import (STOP_EXIT, CliError, CommandFailed, add_grades_flag, add_model_flag,
                                      add_overwrite_flag, add_quiet_flag, add_ray_flag, add_threads_flag,
                                      add_viewer_flags, grade_table, load_model, model_path, parse_readings, positive,
                                      ray_options, refuse_to_replace, torch_threads, viewer_target, writable_dir,
                                      written_files)

TOLERANCES = "pipeline.check:Tolerances"
TOLERANCE = "tol_"
"""Prefix of the --tol-* flags and of their values."""
TOLERANCE_FLAGS = {
    "center_mm": {"parse": positive(float), "help": "--check: how far a cap's centre may move, in mm"},
    "axis_deg": {"parse": positive(float), "help": "--check: how far a cap's axis may turn, in degrees"},
    "radius_pct": {"parse": positive(float), "help": "--check: how much a cap's radius may change, in per cent"},
}
"""pipeline.check.Tolerances documents none of its fields: the flags' help is here."""
REPLAY_OPTIONS = "pipeline.replay:ReplayOptions"
FUSION_FLAGS = {"window": {"parse": positive(int), "metavar": "N"}}
PERCEPTION_FLAGS = {"readings": {"parse": parse_readings, "metavar": "N"}}
"""How the stages' flags read their values, where the field's type is not enough."""

NAME = "replay"
HELP = "re-run fusion and perception on a recorded session; --check compares with the detections it recorded"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from pipeline.flags import add_config_flags  # loads ast: only a parsed replay pays it

    parser.add_argument("sessions", nargs="+", metavar="SESSION",
                        help="a session .mcap (from live, record or demo) or a RealSense device file (.db3, played "
                             "through the driver); several, folders or glob patterns replay a farm's sessions, one "
                             "row each in OUT/report.json")
    parser.add_argument("--out", default="replay", help="output folder (default ./replay): replay.mcap, "
                        "detections.json, replay.rrd")
    add_viewer_flags(parser, "the Rerun recording (default OUT/replay.rrd)")
    add_config_flags(parser, REPLAY_OPTIONS, only=("from_stage", "speed"))
    parser.add_argument("--rig", metavar="RIG_JSON", help="rig file from mushroom-pose calibrate (a turntable, or "
                        "several fixed cameras)")
    add_config_flags(parser, "fusion.cloud:FusionStage", FUSION_FLAGS, only=("window",))
    parser.add_argument("--check", action="store_true", help="compare the new caps with the recorded ones (or, "
                        "for a session without them, those of <stem>.expected.json beside it) unit by unit; exit 1 "
                        "when a cap is lost, gained or changed beyond the tolerances")
    parser.add_argument("--expected", help="--check against these detections (JSON: one document or a list, one "
                        "per fused unit) instead of the session's own")
    add_config_flags(parser, TOLERANCES, TOLERANCE_FLAGS, prefix=TOLERANCE)
    parser.add_argument("--verbose", action="store_true", help="--check: list every cap, not only changes")
    add_overwrite_flag(parser)
    add_grades_flag(parser)
    add_model_flag(parser)
    add_config_flags(parser, "pipeline.runner:PerceptionStage", PERCEPTION_FLAGS, only=("clustering",))
    parser.add_argument("--readings", type=parse_readings, metavar="N", help="read each fused cloud N times, turned "
                        "a further 360/N degrees about the vertical each time, the readings averaged (default: as "
                        "often as the session's recorded detections say they were read, once when they do not say)")
    add_threads_flag(parser)
    add_quiet_flag(parser, "no line per fused unit")
    add_ray_flag(parser, "several sessions: one Ray task each")


def run(args: argparse.Namespace) -> int:
    from pipeline.process import let_idle_threads_sleep

    let_idle_threads_sleep()  # before torch and Open3D load: the chain's stages share the cores
    from capture.mcap.writer import RecordingError
    from pipeline.signals import graceful_stop
    from pipeline.check import Tolerances
    from pipeline.flags import config_from_args
    from pipeline.replay import ReplayError, read_expected, run_replay

    if len(args.sessions) > 1 or args.ray is not None or Path(args.sessions[0]).is_dir() \
            or any(mark in args.sessions[0] for mark in "*?["):
        return _replay_many(args)
    session = Path(args.sessions[0])
    if not session.is_file():
        raise CliError(f"{session} does not exist" if not session.exists() else f"{session} is not a file")
    out_dir = writable_dir(args.out)
    viewer = viewer_target(args, inputs=(str(session),), rrd=args.rrd or str(out_dir / "replay.rrd"))
    rrd = viewer.rrd
    if (out_dir / "replay.mcap").exists() and (out_dir / "replay.mcap").samefile(session):
        raise CliError(f"{session} is the replay's own output; pick another --out")
    if args.expected and not args.check:
        raise CliError("--expected is what --check compares with: add --check")
    model, _ = load_model(args.model)
    refuse_to_replace([out_dir / "replay.mcap", out_dir / "detections.json", rrd], args.overwrite)
    torch_threads(args.threads)
    try:
        expected = read_expected(Path(args.expected)) if args.expected else None
    except ReplayError as error:
        raise CliError(str(error)) from None
    options = _options(args)
    tolerances = config_from_args(Tolerances, args, prefix=TOLERANCE) if args.check else None
    with graceful_stop() as stop:
        try:
            result = run_replay(session, model, out_dir, viewer, options, tolerances, quiet=args.quiet,
                                stop_requested=lambda: stop.signal if stop.requested else None,
                                on_start=lambda text: print(f"fused unit: {text}", flush=True), expected=expected)
        except ReplayError as error:
            raise CliError(str(error)) from None
        except RecordingError as error:  # a full disk
            kept = written_files((out_dir / "replay.mcap", rrd, out_dir / "detections.json"))
            raise CommandFailed(f"{error}" + (f"; kept {kept}" if kept else "")) from None
    return _report(result, session, out_dir, rrd, args.verbose)


def _report(result, session: Path, out_dir: Path, rrd: Path, verbose: bool) -> int:
    """Print what the replay wrote (and the check's table); its exit status."""
    summary = result.summary
    if result.frames_lost:
        print(f"warning: {session} was cut short (not finalised): replayed its {summary.frames} whole frames; "
              "what followed the last whole chunk is lost", file=sys.stderr)
    caps = summary.detections[-1].caps if summary.detections else 0
    line = (f"replayed {summary.frames} frames into {summary.units} fused units ({caps} caps in the last) -> "
            f"{written_files((out_dir / 'replay.mcap', out_dir / 'detections.json', rrd))}")
    if summary.stopped_by in STOP_EXIT:
        print(f"stopped by {summary.stopped_by}: {line}", file=sys.stderr)
        return STOP_EXIT[summary.stopped_by]
    print(line)
    if result.check is not None:
        print(result.check.table(everything=verbose))
        return 0 if result.check.passed else 1
    return 0


def _replay_many(args: argparse.Namespace) -> int:
    """Several sessions (``pipeline.farm``): one row each, a failed session a failed row; exit 1 when
    any session failed or (with --check) changed."""
    from pipeline.check import Tolerances
    from pipeline.farm import FarmJob, expand_sessions, replay_sessions, report_table, write_report
    from pipeline.flags import config_from_args

    if args.rrd or args.spawn or args.serve or args.expected:
        raise CliError("--rrd, --spawn, --serve and --expected are for one session: replay that session alone")
    try:
        sessions = expand_sessions(args.sessions)
    except ValueError as error:
        raise CliError(str(error)) from None
    out_dir = writable_dir(args.out)
    load_model(args.model)  # a bad weights file is one error here, not one per session
    refuse_to_replace([out_dir / "report.json"], args.overwrite)
    options = _options(args)
    tolerances = config_from_args(Tolerances, args, prefix=TOLERANCE) if args.check else None
    job = FarmJob(str(model_path(args.model)), str(out_dir), options, tolerances, threads=args.threads or 1)
    ray = ray_options(args)
    print(f"replaying {len(sessions)} sessions " + ("one after another" if not ray["use_ray"] else
          f"as Ray tasks ({ray['ray_address'] or 'local Ray'})"), flush=True)

    def progress(outcome) -> None:
        if not args.quiet:
            print(f"  {outcome.session}: " + (outcome.error or f"{outcome.caps} caps, {len(outcome.changes)} changes"),
                  flush=True)

    outcomes = replay_sessions(sessions, job, ray["ray_address"], ray["use_ray"], on_outcome=progress)
    write_report(outcomes, out_dir / "report.json")
    print(report_table(outcomes))
    print(f"report: {out_dir / 'report.json'}")
    return 0 if all(o.passed for o in outcomes) else 1


def _options(args: argparse.Namespace):
    """The ``pipeline.replay.ReplayOptions`` of the flags, the --rig file read."""
    from fusion.cloud import FusionStage
    from fusion.turntable import Rig
    from pipeline.flags import config_from_args
    from pipeline.replay import ReplayOptions
    from pipeline.runner import PerceptionStage

    rig = None
    if args.rig:
        try:
            rig = Rig.load(args.rig)
        except ValueError as error:
            raise CliError(str(error)) from None
    perception = config_from_args(PerceptionStage, args, readings=args.readings or PerceptionStage.readings)
    return config_from_args(ReplayOptions, args, fusion=config_from_args(FusionStage, args, rig=rig),
                            perception=perception, readings_as_recorded=args.readings is None,
                            grades=grade_table(args))
