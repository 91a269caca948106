"""``mushroom-pose track``: one bed's sessions over the days, each cap followed with its growth."""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.commands.common import (CliError, add_grades_flag, add_overwrite_flag, grade_table, positive,
                                      refuse_to_replace, writable_dir)

NAME = "track"
HELP = "follow one bed's caps over its sessions: ids kept, growth per day, the day each reaches the pick size"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("sessions", nargs="+", metavar="SESSION", help="session .mcap files of one bed (from live, "
                        "record or replay, with fused clouds and caps), in any order")
    parser.add_argument("--bed", required=True, metavar="ID", help="the bed they scan (as recorded with --bed-id); "
                        "a session of another bed is refused")
    parser.add_argument("--out", default="track", help="output folder (default ./track): track.json, track.rrd")
    parser.add_argument("--pick-mm", type=positive(float), default=50.0, help="the pick size, in mm of cap "
                        "diameter, whose day each cap's growth forecasts (default 50)")
    parser.add_argument("--horizon", type=positive(int), default=7, metavar="DAYS",
                        help="days ahead the bed's count per grade is forecast (default 7)")
    add_grades_flag(parser)
    add_overwrite_flag(parser)


def run(args: argparse.Namespace) -> int:
    import json

    from common.files import write_atomically
    from perception.track import NotOneBed, TrackConfig, track_bed
    from pipeline.growth import SessionError, read_scans, track_document, write_track_rrd

    grades = grade_table(args)
    try:
        scans = read_scans([Path(s) for s in args.sessions], args.bed)
    except SessionError as error:
        raise CliError(str(error)) from None
    out = writable_dir(args.out)
    refuse_to_replace([out / "track.json", out / "track.rrd"], args.overwrite)
    config = TrackConfig(pick_mm=args.pick_mm, horizon_days=args.horizon)
    try:
        tracks = track_bed(scans, grades, config)
    except NotOneBed as error:
        raise CliError(str(error)) from None
    document = track_document(args.bed, scans, tracks, grades, config)
    write_track_rrd(out / "track.rrd", scans, tracks)
    write_atomically(out / "track.json", json.dumps(document, indent=1))
    present = [cap for cap in document["caps"] if cap["present"]]
    ripe = [cap["id"] for cap in present if cap["seen"][-1]["diameter_mm"] >= args.pick_mm]
    coming = sorted((cap["ready_day"], cap["id"]) for cap in present
                    if cap["id"] not in ripe and cap["ready_day"] is not None)
    print(f"bed {args.bed}: {len(scans)} scans over {document['scans'][-1]['day']:.1f} days, {len(document['caps'])} "
          f"caps followed, {len(present)} on the last scan, {len(ripe)} of them at {args.pick_mm:g} mm or more"
          + (f" (caps {', '.join(map(str, ripe))})" if ripe else ""))
    for day, cap in coming[:10]:
        print(f"  cap {cap} reaches {args.pick_mm:g} mm on day {day:.1f}")
    if len(coming) > 10:
        print(f"  ... and {len(coming) - 10} more (track.json)")
    print(f"track: {out / 'track.json'}  rerun: {out / 'track.rrd'}")
    return 0
