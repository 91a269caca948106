"""``mushroom-pose detect``: the caps in a point cloud file, or in a session's frames fused first."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline.commands.common import (FILE_READINGS, SHIPPED_ZOOM, CliError, add_model_flag, add_overwrite_flag,
                                      add_grades_flag, add_pick_flags, add_viewer_flags, grade_table, load_model,
                                      model_path, parse_readings, parse_zoom, pick_config, refuse_to_replace,
                                      replace_file, viewer_target, writable_file)

NAME = "detect"
HELP = ("find caps in a point cloud (.ply, .pcd, .npz) or a session .mcap (its fused cloud, or its frames fused "
        "first)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from pipeline.flags import add_config_flags  # loads ast: only a parsed detect pays it

    parser.add_argument("cloud", help="the point cloud: a .ply, .pcd or scene .npz, or a session .mcap: its last "
                        "/fusion/cloud, or for a session of raw frames its frames fused as replay fuses them (the "
                        "last unit's caps, in the world frame)")
    parser.add_argument("--out", default="detections.json", help="detections JSON (default detections.json)")
    add_viewer_flags(parser)
    add_model_flag(parser)
    add_config_flags(parser, "perception.instances:ClusterConfig", {"method": {"name": "clustering"}}, only=("method",))
    parser.add_argument("--zoom", type=parse_zoom, help="scale the network reads the cloud at (default: the one "
                        f"the weights record, {SHIPPED_ZOOM} for the shipped model, lowered for clouds sparser than "
                        "its training beds)")
    parser.add_argument("--readings", type=parse_readings, default=FILE_READINGS, metavar="N",
                        help="read the cloud N times, turned about the vertical, and average what the network "
                             f"sees (default {FILE_READINGS}: steadier caps than one reading gives; 1 is "
                             "fastest)")
    parser.add_argument("--units", choices=["auto", "m", "cm", "mm"], default="auto",
                        help="the cloud's length unit (default auto: the one in which its point spacing and width "
                             "are a bed's; a .npz scene is in metres)")
    parser.add_argument("--bed-frame", action="store_true",
                        help="the cloud is already in the bed frame (z up, origin on the bed plane; checked)")
    add_grades_flag(parser)
    add_pick_flags(parser)
    add_overwrite_flag(parser)
    parser.add_argument("--force", action="store_true",
                        help="detect on a cloud that does not look like a bed (most points off its plane, no unit "
                             "in which it is one, more caps than a bed holds), or whose --bed-frame does not fit it")


def run(args: argparse.Namespace) -> int:
    import json

    import numpy as np

    from pipeline.clouds import load_cloud

    pick, grades = pick_config(args), grade_table(args)
    try:
        cloud = load_cloud(Path(args.cloud), args.units)
    except ValueError as error:
        if Path(args.cloud).suffix.lower() == ".mcap" and _is_raw_session(Path(args.cloud)):
            return _detect_session(args)
        raise CliError(str(error)) from None
    out = writable_file(args.out, inputs=(args.cloud, model_path(args.model)))
    viewer = viewer_target(args, inputs=(args.cloud, model_path(args.model)))
    if viewer.rrd is not None and viewer.rrd.resolve() == out.resolve():
        raise CliError(f"--out and --rrd are both {args.out}; give them different names")
    refuse_to_replace([out, viewer.rrd], args.overwrite)

    from common.geometry import transform_points
    from fusion.bed import not_a_bed, too_many_caps
    from perception.detect import detect_points, detect_up_side, transform_result
    from perception.instances import ClusterConfig
    from perception.plan import plan_of_result

    if args.units == "auto" and cloud.units != "m":
        print(f"note: {args.cloud} is read in {UNIT_NAMES[cloud.units]} (its points lie {cloud.spacing:.3g} units "
              f"apart over {cloud.extent:.3g}); give --units to say otherwise", file=sys.stderr)
    model, _ = load_model(args.model, in_torch=False)
    points = cloud.points
    _refuse_unless_forced(args, cloud.unit_doubt)
    T_input_bed, frame = _bed_frame(args, cloud)
    bed_points = transform_points(np.linalg.inv(T_input_bed), points)
    _refuse_unless_forced(args, not_a_bed(bed_points))
    clustering = ClusterConfig(method=args.method)
    try:
        if frame == "input":  # the bed plane was found here: which side is up, its caps say
            T_input_bed, bed_points, result = detect_up_side(model, points, T_input_bed, clustering, args.zoom,
                                                             args.readings)
        else:
            result = detect_points(model, bed_points, clustering, zoom=args.zoom, readings=args.readings)
    except ValueError as error:
        raise CliError(str(error)) from None
    _refuse_unless_forced(args, too_many_caps(bed_points, len(result.caps)))
    plan = plan_of_result(result, bed_points, pick, T_input_bed)
    result = transform_result(result, T_input_bed, frame)
    print(f"{len(result.caps)} caps in {args.cloud} ({len(points)} points, frame: {frame}, metres)")
    _print_caps(result, T_input_bed[:3, 2], grades)
    _note_smoothing(result.surface_noise)
    _warn_outside_range(model, bed_points, result, args.cloud)
    payload = {**result.caps.to_document(frame, args.readings, grades, pick.min_score), "plan": plan,
               "T_input_bed": T_input_bed.tolist()}
    replace_file(out, json.dumps(payload, indent=1))
    print(f"detections: {out}", flush=True)
    if viewer.wanted:
        from pipeline.viewer import PERCEPTION, log_detection, send_blueprint, viewer_stream

        with viewer_stream(viewer, Path(args.cloud).name) as rec:
            send_blueprint(rec, (), T_input_bed, bed_points, stats=False, hidden=(f"{PERCEPTION}/centers",))
            log_detection(rec, result, points, plan=plan)
        if viewer.rrd is not None:
            print(f"rerun: {viewer.rrd}")
    return 0


def _note_smoothing(noise: float) -> None:
    """Say when the cloud's surfaces were noisy enough to be smoothed before reading."""
    from perception.surface_noise import CLEAN_NOISE, smoothing_share

    if noise > CLEAN_NOISE:
        print(f"note: the surfaces scatter {noise:.2f} point spacings (a clean scan: under {CLEAN_NOISE:g}), as a "
              f"single depth frame or passive stereo does; the points were smoothed "
              f"({smoothing_share(noise):.0%}) before reading", file=sys.stderr)


UNIT_NAMES = {"m": "metres", "cm": "centimetres", "mm": "millimetres"}


def _bed_frame(args: argparse.Namespace, cloud):
    """T_input_bed and the name of the frame the caps are given in: the bed frame of a scene or of a
    cloud said to be in it (``--bed-frame``, checked against the cloud's own bed plane), else the
    input's, with the bed plane found in it."""
    import numpy as np

    from fusion.bed import bed_frame_mismatch, estimate_bed_frame

    if cloud.in_bed_frame:
        return np.eye(4), "bed"
    try:
        T_input_bed = estimate_bed_frame(cloud.points)
    except (ValueError, RuntimeError) as error:
        raise CliError(f"cannot find the bed plane: {error}") from None
    if not args.bed_frame:
        return T_input_bed, "input"
    mismatch = bed_frame_mismatch(T_input_bed)
    if mismatch:
        _refuse_unless_forced(args, f"{mismatch}, so it is not in the bed frame: drop --bed-frame")
    return np.eye(4), "bed"


def _refuse_unless_forced(args: argparse.Namespace, reason: str | None) -> None:
    """A one-line refusal for a cloud that is no bed (``reason``), a warning with ``--force``."""
    if reason is None:
        return
    if not args.force:
        raise CliError(f"{args.cloud} does not look like a bed seen from above: {reason} (--force detects anyway)")
    print(f"warning: {args.cloud}: {reason}", file=sys.stderr)


def _is_raw_session(path: Path) -> bool:
    """A recording of depth frames (its fused cloud, if any, could not be read): ``detect`` fuses it first."""
    from capture.mcap.reader import McapSource
    from capture.source import SourceError

    try:
        with McapSource(path) as session:
            return bool(session.sensor_ids)
    except SourceError:
        return False


def _detect_session(args: argparse.Namespace) -> int:
    """``detect`` on a session of raw frames: fused and detected through the runner, caps in the world frame."""
    from capture.mcap.reader import McapSource
    from capture.source import SourceError
    from pipeline.runner import PerceptionStage, RunConfig
    from pipeline.chain import Outputs, run_chain

    out = writable_file(args.out, inputs=(args.cloud, model_path(args.model)), suffix=".json")
    viewer = viewer_target(args, inputs=(args.cloud, model_path(args.model)))
    model, _ = load_model(args.model)
    refuse_to_replace([out, viewer.rrd], args.overwrite)
    source = McapSource(args.cloud)
    try:
        source.open()
        summary = run_chain(source, model, RunConfig(perception=PerceptionStage(args.method, args.readings),
                                                      plan=pick_config(args), grades=grade_table(args)),
                            Outputs(viewer=viewer, name=Path(args.cloud).name, detections=out, quiet=True),
                            sensors=max(1, len(source.sensor_ids)))
    except (SourceError, ValueError) as error:
        raise CliError(str(error)) from None
    if not summary.detections:
        raise CliError(f"{args.cloud}: its frames gave no fused cloud")
    result = summary.last_detection.result
    print(f"{len(result.caps)} caps in {args.cloud} (fused {summary.units} units from {summary.frames} frames; "
          "the last unit's caps, frame: world, metres)")
    _print_caps(result, summary.last_detection.unit.cloud.T_world_bed[:3, 2], grade_table(args))
    print(f"detections: {out}" + (f"  rerun: {viewer.rrd}" if viewer.rrd else ""))
    return 0


def _warn_outside_range(model, bed_points, result, cloud: str) -> None:
    """Say so on stderr when a cloud or its caps lie outside the range the model holds to."""
    from perception.detect import OPERATING_DIAMETER, OPERATING_SPACING, at_training_density, point_spacing

    spacing = point_spacing(bed_points[at_training_density(model, bed_points)])
    if spacing > OPERATING_SPACING:
        filled = (f"; its surface was filled in to {1000 * model.point_spacing:g} mm before reading"
                  if result.voxels.filled_in else "")
        print(f"warning: the points of {cloud} lie as far apart as a bed sampled every {1000 * spacing:.1f} mm; the "
              f"model holds to {1000 * OPERATING_SPACING:g} mm: caps under 30 mm across are found less reliably"
              f"{filled}", file=sys.stderr)
    wide = int((2 * result.caps.radii > OPERATING_DIAMETER).sum())
    if wide:
        print(f"warning: {wide} caps are over {1000 * OPERATING_DIAMETER:.0f} mm across, beyond the sizes the model "
              "holds to: their size and axis are less reliable", file=sys.stderr)
    if not len(result.caps) and len(bed_points) > 1000:
        print(f"warning: no caps in {len(bed_points)} points: if the bed plainly has caps, check the cloud's units "
              "and that it shows a bed seen from above", file=sys.stderr)


def _print_caps(result, up, grades) -> None:
    """One line per cap: centre (mm), tilt from ``up`` (deg), diameter (mm), score and grade."""
    from perception.cap import tilt_deg

    caps = result.caps
    if len(caps):
        print(f"{'id':>3} {'x mm':>8} {'y mm':>8} {'z mm':>8} {'tilt deg':>8} {'cap mm':>7} {'score':>6}  grade")
    for k, ((x, y, z), tilt, radius, score, grade) in enumerate(zip(
            1000 * caps.centers, tilt_deg(caps.axes, up), caps.radii, caps.score_array(),
            grades.grade_of(2000 * caps.radii))):
        print(f"{k:>3} {x:>8.1f} {y:>8.1f} {z:>8.1f} {float(tilt):>8.1f} {2000 * radius:>7.1f} {score:>6.2f}  {grade}")
