"""The ``mushroom-pose`` command line: one subcommand per job, flags mapped onto config dataclasses."""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import threading
import time
from pathlib import Path

from pipeline.process import reuse_freed_memory


class CliError(Exception):
    """A problem with the user's input: reported in one line, exit status 2."""


def _writable_dir(path: str) -> Path:
    directory = Path(path)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise CliError(f"cannot create output folder {directory}: {error.strerror}") from None
    probe = directory / ".write-test"
    try:
        probe.touch()
        probe.unlink()
    except OSError as error:
        raise CliError(f"output folder {directory} is not writable: {error.strerror}") from None
    return directory


def _writable_file(path: str | None, inputs: tuple[str | None, ...] = (), suffix: str | None = None) -> Path | None:
    """An output file's path, its folder created; refused when it is a folder, a device or other
    special file, one of ``inputs`` (writing it would destroy the input), or, for a fixed format,
    named without its ``suffix``. A symlink resolves to its target, which is then replaced; a
    dangling one is refused."""
    if path is None:
        return None
    file = Path(path)
    if suffix is not None and file.suffix.lower() != suffix:
        raise CliError(f"{path}: this file is written as {suffix[1:].upper()}; name it with {suffix}")
    if file.is_symlink():
        try:
            file = file.resolve(strict=True)
        except (OSError, RuntimeError):
            raise CliError(f"{path} is a link to nothing (or to itself); remove it or pick another name") from None
    if file.is_dir():
        raise CliError(f"{file} is a folder, expected a file name")
    if file.exists() and not file.is_file():
        raise CliError(f"{file} is not a regular file; pick a file name to write")
    for source in inputs:
        if source is not None and Path(source).exists() and file.exists() and file.samefile(source):
            raise CliError(f"{path} is also an input of this command; pick another name to write")
    _writable_dir(str(file.parent if str(file.parent) else "."))
    return file


def _replace_file(path: Path, text: str) -> None:
    """Write through a temporary file renamed over ``path``: a failed write leaves an earlier file
    whole and no temporary file behind."""
    from pipeline.sinks import write_atomically

    try:
        write_atomically(path, text)
    except OSError as error:
        raise CliError(f"cannot write {path}: {error.strerror or error}") from None


MAX_COUNT = 2**31 - 1
"""Counts (scenes, views, iterations, threads) beyond this are typing slips, and overflow numpy's seeds."""


def _positive(kind):
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'a whole number' if kind is int else 'a number'}, "
                                             f"got {text!r}") from None
        if kind is float and not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
        if kind is int and value > MAX_COUNT:
            raise argparse.ArgumentTypeError(f"at most {MAX_COUNT}, got {text}")
        if value <= 0:
            raise argparse.ArgumentTypeError(f"must be positive, got {text}")
        return value
    return parse


def _at_most(parse, limit, reason: str = ""):
    """``parse``, refusing values above ``limit``."""
    def bounded(text: str):
        value = parse(text)
        if value > limit:
            raise argparse.ArgumentTypeError(f"at most {limit}{reason}, got {text}")
        return value
    return bounded


def _at_least(parse, limit, reason: str = ""):
    """``parse``, refusing values below ``limit``."""
    def bounded(text: str):
        value = parse(text)
        if value < limit:
            raise argparse.ArgumentTypeError(f"at least {limit}{reason}, got {text}")
        return value
    return bounded


MAX_MUSHROOMS = 300
"""More than a 0.5 m bed holds (about 260 caps when packed): asking for more only slows the placer."""
CORES = os.cpu_count() or 1


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {text}")
    return value


_seed = _at_most(_non_negative_int, 2**63 - 1, " (seeds are below 2^63)")
_threads = _at_most(_positive(int), 4 * CORES, f" (4 per core; this machine has {CORES})")
_learning_rate = _at_most(_positive(float), 1.0, " (Adam's steps are about this size in every weight)")
_run_fraction = _at_most(_positive(float), 1.0, " (a fraction of the run's iterations)")
_mushroom_count = _at_most(_non_negative_int, MAX_MUSHROOMS, " (a 0.5 m bed is full at about 260)")
_spacing = _at_least(_at_most(_positive(float), 0.02, " metres (0.003 is 3 mm)"), 0.001,
                     " metres: a finer spacing only multiplies the points (0.003 is 3 mm)")
SPACING_HELP = "0.003, the generator's: every 4.5 mm voxel a surface crosses holds a point"
"""The parser imports no numpy (Ctrl-C while libraries load), so SceneConfig's default is named here."""
DEFAULT_ZOOM = 1.05
"""perception.model.INFERENCE_ZOOM, named here for the same reason."""
SHIPPED_ZOOM = 1.2
"""The zoom the shipped model's weights record (trained with --scale-jitter 1.05 1.35)."""
_zoom = _at_least(_at_most(_positive(float), 2.0, " (the network would read caps twice their size)"), 0.5,
                  " (the network would read caps half their size)")


def cmd_synth(args: argparse.Namespace) -> int:
    import numpy as np

    from perception.synthetic.dataset import (PRESETS, generate_many, log_scene, preset_config, scene_seeds,
                                              write_scene)
    from perception.synthetic.scene import SceneConfig
    from pipeline.rerun_sink import rerun_stream, set_frame

    low, high = args.mushrooms
    if high < low:
        raise CliError(f"--mushrooms range is inverted: {low} > {high}")
    preview = _writable_file(args.preview, suffix=".png")
    rrd = _writable_file(args.rrd)
    out = _writable_dir(args.out)
    if args.preset:
        preset = PRESETS[args.preset]
        seeds = scene_seeds(preset.seed, preset.scenes)
        config = preset_config(args.preset, args.visibility, args.spacing)
    else:
        seeds = scene_seeds(args.seed, args.scenes)
        config = SceneConfig(mushrooms=(low, high), visibility=args.visibility, voxel=args.spacing or SceneConfig.voxel)
    mushrooms, points, started = [], [], time.perf_counter()
    with rerun_stream(rrd) as rec:
        for index, scene in enumerate(generate_many(seeds, config, progress=not args.quiet)):
            write_scene(scene, out, index, ply=not args.no_ply)
            mushrooms.append(len(scene.centers))
            points.append(len(scene.points))
            if rec is not None:
                set_frame(rec, index)
                log_scene(rec, scene)
    elapsed = time.perf_counter() - started
    print(f"scenes: {len(seeds)}  mushrooms: {sum(mushrooms)} (per scene {min(mushrooms, default=0)}-"
          f"{max(mushrooms, default=0)})  points: {sum(points)} (median {np.median(points) if points else 0:.0f} "
          f"per scene)  visibility: {config.visibility}  time: {elapsed:.1f} s  -> {out}")
    short = sum(count < config.mushrooms[0] for count in mushrooms)
    if short:
        print(f"note: {short} of {len(seeds)} scenes hold fewer than {config.mushrooms[0]} mushrooms: the bed "
              "had no room for more", file=sys.stderr)
    if rrd is not None:
        print(f"rerun recording: {rrd}")
    if preview is not None:
        from pipeline.preview import render_bed_preview

        render_bed_preview(seeds[0], config, preview)
        print(f"preview of the first scene: {preview}")
    return 0


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: the message and where to look, no usage dump."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def train_config(args: argparse.Namespace):
    """The TrainConfig that ``mushroom-pose train`` runs with these arguments."""
    from perception.synthetic.scene import SceneConfig
    from perception.train import TrainConfig

    return TrainConfig(iterations=args.iterations, lr=args.lr, milestones=tuple(args.milestones),
                       network=args.network, seed=args.seed,
                       checkpoint_every=args.checkpoint_every, validate_every=args.validate_every,
                       validation_scenes=args.validation_scenes, weight_existence=args.weight_existence,
                       weight_residual=args.weight_residual, weight_orientation=args.weight_orientation,
                       orientation_on_caps=args.orientation_on_caps, cap_balance=args.cap_balance,
                       scale_jitter=tuple(args.scale_jitter), average_from=args.average_from, zoom=args.zoom,
                       scene=SceneConfig(voxel=args.spacing or SceneConfig.voxel, scale=tuple(args.cap_scale),
                                         jitter=tuple(args.spacing_jitter)),
                       init_weights=str(Path(args.init).resolve()) if args.init else None)


def cmd_train(args: argparse.Namespace) -> int:
    from perception.model import PRESETS as NETWORK_PRESETS
    from perception.train import TrainingError, train

    if args.network not in NETWORK_PRESETS:
        raise CliError(f"unknown network {args.network!r}; choose one of {sorted(NETWORK_PRESETS)}")
    if args.init and not args.resume and not Path(args.init).is_file():
        raise CliError(f"--init: no weights file at {args.init}")
    for flag in ("scale_jitter", "spacing_jitter", "cap_scale"):
        low, high = getattr(args, flag)
        if low > high:
            raise CliError(f"--{flag.replace('_', '-')} wants LOW HIGH with LOW <= HIGH, got {low} {high}")
    if any(later <= earlier for earlier, later in zip(args.milestones, args.milestones[1:])):
        raise CliError(f"--milestones must increase, got {' '.join(map(str, args.milestones))}")
    config = train_config(args)
    if config.averaging_start is not None and config.averaging_start >= config.iterations:
        raise CliError(f"--average-from {args.average_from} leaves no iteration of {args.iterations} to average")
    new_folder = not Path(args.out).exists()
    run_dir = _writable_dir(args.out)
    if (run_dir / "checkpoint.pt").exists() and not args.resume:
        raise CliError(f"{run_dir} already holds a checkpoint: add --resume to continue it, or pick a new --out")
    torch_threads(args.threads)
    try:
        weights = train(config, run_dir, resume=args.resume, device=args.device, progress=not args.quiet,
                        max_minutes=args.max_minutes)
    except (ValueError, TrainingError) as error:
        if new_folder and not any(run_dir.iterdir()):
            run_dir.rmdir()
        raise CliError(str(error)) from None
    if weights is None:
        print(f"stopped after {args.max_minutes} minutes with a checkpoint in {run_dir}: continue with the same "
              "flags and --resume")
    else:
        print(f"weights: {weights}")
    return 0


def cmd_average(args: argparse.Namespace) -> int:
    from perception.train import average_weights, save_weights

    for path in args.weights:
        if not Path(path).is_file():
            raise CliError(f"no weights file at {path}")
    out = _writable_file(args.out, inputs=tuple(args.weights), suffix=".pt")
    try:
        model, meta = average_weights([Path(path) for path in args.weights])
    except ValueError as error:
        raise CliError(str(error)) from None
    save_weights(model, out, **meta)
    print(f"averaged {len(args.weights)} models, {len(meta['runs'])} training runs behind them, "
          f"{meta['total_iterations']} iterations in {meta['total_train_seconds'] / 60:.1f} min: {out}")
    return 0


def torch_threads(threads: int | None) -> None:
    import torch

    if threads:
        torch.set_num_threads(threads)


def _model_path(path: str | None) -> Path:
    from perception.detect import DEFAULT_WEIGHTS

    return Path(path) if path else DEFAULT_WEIGHTS


def _load_model(path: str | None):
    from perception.train import load_weights

    weights = _model_path(path)
    if not weights.exists():
        if path:
            raise CliError(f"model file {weights} does not exist")
        raise CliError(f"no shipped model at {weights}: train one (mushroom-pose train) and pass --model")
    try:
        return load_weights(weights)
    except ValueError as error:
        raise CliError(str(error)) from None


def cmd_detect(args: argparse.Namespace) -> int:
    import json

    import numpy as np

    from capture.frames import transform_points
    from fusion.bed import estimate_bed_frame
    from perception.cap import detections_document
    from perception.detect import detect_points, log_rerun, transform_result
    from perception.instances import ClusterConfig
    from pipeline.clouds import load_cloud
    from pipeline.rerun_sink import rerun_stream

    if Path(args.cloud).suffix.lower() == ".mcap" and _is_raw_session(Path(args.cloud)):
        return _detect_session(args)
    try:
        cloud = load_cloud(Path(args.cloud))
    except ValueError as error:
        raise CliError(str(error)) from None
    out = _writable_file(args.out, inputs=(args.cloud, _model_path(args.model)))
    rrd = _writable_file(args.rrd, inputs=(args.cloud, _model_path(args.model)))
    if rrd is not None and rrd.resolve() == out.resolve():
        raise CliError(f"--out and --rrd are both {args.out}; give them different names")
    if cloud.unit_scale != 1.0:
        print(f"note: {args.cloud} spans {cloud.extent:.3g} units, "
              "so it is read as millimetres and converted to metres", file=sys.stderr)
    model, _ = _load_model(args.model)
    points = cloud.points
    if cloud.in_bed_frame or args.bed_frame:
        T_input_bed, frame = np.eye(4), "bed"
    else:
        try:
            T_input_bed = estimate_bed_frame(points)
        except (ValueError, RuntimeError) as error:
            raise CliError(f"cannot find the bed plane: {error}") from None
        frame = "input"
    bed_points = transform_points(np.linalg.inv(T_input_bed), points)
    try:
        result = detect_points(model, bed_points, ClusterConfig(method=args.clustering), zoom=args.zoom)
    except ValueError as error:
        raise CliError(str(error)) from None
    result = transform_result(result, T_input_bed, frame)
    print(f"{len(result.mushrooms)} caps in {args.cloud} ({len(points)} points, frame: {frame}, metres)")
    _print_caps(result, T_input_bed[:3, 2])
    _warn_outside_range(model, bed_points, result, args.cloud)
    payload = {**detections_document(result.mushrooms, frame), "T_input_bed": T_input_bed.tolist()}
    _replace_file(out, json.dumps(payload, indent=1))
    with rerun_stream(rrd) as rec:
        if rec is not None:
            log_rerun(rec, result, points)
    print(f"detections: {out}" + (f"  rerun: {rrd}" if rrd else ""))
    return 0


def _is_raw_session(path: Path) -> bool:
    """A recording of depth frames with no fused cloud: ``detect`` fuses it first."""
    from capture.mcap_io import McapSource, read_point_cloud
    from capture.source import SourceError

    try:
        read_point_cloud(path)
        return False
    except SourceError:
        pass
    try:
        with McapSource(path) as session:
            return bool(session.sensor_ids)
    except SourceError:
        return False


def _detect_session(args: argparse.Namespace) -> int:
    """``detect`` on a session of raw frames: fused and detected through the runner, caps in the world frame."""
    from capture.mcap_io import McapSource
    from capture.source import SourceError
    from pipeline.runner import PerceptionStage, RunConfig
    from pipeline.session import Outputs, run_chain

    out = _writable_file(args.out, inputs=(args.cloud, _model_path(args.model)), suffix=".json")
    rrd = _writable_file(args.rrd, inputs=(args.cloud, _model_path(args.model)), suffix=".rrd")
    model, _ = _load_model(args.model)
    source = McapSource(args.cloud)
    try:
        source.open()
        summary = run_chain(source, model, RunConfig(perception=PerceptionStage(args.clustering)),
                            Outputs(rrd=rrd, detections=out, name=Path(args.cloud).name, quiet=True),
                            sensors=max(1, len(source.sensor_ids)))
    except (SourceError, ValueError) as error:
        raise CliError(str(error)) from None
    if not summary.detections:
        raise CliError(f"{args.cloud}: its frames gave no fused cloud")
    result = summary.last_detection.result
    print(f"{len(result.mushrooms)} caps in {args.cloud} (fused {summary.units} units from {summary.frames} frames; "
          "the last unit's caps, frame: world, metres)")
    _print_caps(result, summary.last_detection.unit.cloud.T_world_bed[:3, 2])
    print(f"detections: {out}" + (f"  rerun: {rrd}" if rrd else ""))
    return 0


def _warn_outside_range(model, bed_points, result, cloud: str) -> None:
    """Say so on stderr when a cloud or its caps lie outside the range the model holds to."""
    from perception.detect import OPERATING_DIAMETER, OPERATING_SPACING, at_training_density, point_spacing

    spacing = point_spacing(bed_points[at_training_density(model, bed_points)])
    if spacing > OPERATING_SPACING:
        print(f"warning: the points of {cloud} lie as far apart as a bed sampled every {1000 * spacing:.1f} mm; the "
              f"model holds to {1000 * OPERATING_SPACING:g} mm: caps under 30 mm across are found less reliably",
              file=sys.stderr)
    wide = sum(2 * m.radius > OPERATING_DIAMETER for m in result.mushrooms)
    if wide:
        print(f"warning: {wide} caps are over {1000 * OPERATING_DIAMETER:.0f} mm across, beyond the sizes the model "
              "holds to: their size and axis are less reliable", file=sys.stderr)
    if not result.mushrooms and len(bed_points) > 1000:
        print(f"warning: no caps in {len(bed_points)} points: if the bed plainly has caps, check the cloud's units "
              "and that it shows a bed seen from above", file=sys.stderr)


def _print_caps(result, up) -> None:
    from perception.cap import tilt_deg

    if result.mushrooms:
        print(f"{'id':>3} {'x mm':>8} {'y mm':>8} {'z mm':>8} {'tilt deg':>8} {'cap mm':>7} {'score':>6}")
    for m in result.mushrooms:
        x, y, z = 1000 * m.center
        print(f"{m.id:>3} {x:>8.1f} {y:>8.1f} {z:>8.1f} {float(tilt_deg(m.axis, up)):>8.1f} "
              f"{2000 * m.radius:>7.1f} {m.score:>6.2f}")


PAPER = {"ap25": {"meanshift": 0.9957, "dbscan": 0.9920}, "ap50": {"meanshift": 0.8195, "dbscan": 0.8148},
         "scale_err": 0.048, "cosine": 0.9973, "angle_deg": 4.22}
"""The paper's Tables 3-4 (synthetic validation set, MeanShift and DBSCAN). Its angle is arccos of the
mean cosine (``EvalResult``); it gives no per-cap mean or median."""


def _eval_table(name: str, results: dict) -> str:
    rows = [("AP @ IoU 0.25", "ap25", "{:.2%}"), ("AP @ IoU 0.50", "ap50", "{:.2%}"),
            ("scale rel. error", "scale_err", "{:.2%}"), ("orientation cosine", "cosine", "{:.4f}"),
            ("orientation angle (deg)", "angle_deg", "{:.2f}"),
            ("  mean over caps (deg)", "angle_deg_mean", "{:.2f}"),
            ("  median over caps (deg)", "angle_deg_median", "{:.2f}")]
    methods = list(results)
    lines = [f"{name}: {results[methods[0]].n_gt} caps in the ground truth",
             f"{'metric':<24}" + "".join(f"{'paper ' + m:>18}{'ours ' + m:>18}" for m in methods)]
    for label, key, fmt in rows:
        line = f"{label:<24}"
        for method in methods:
            paper = PAPER.get(key)
            paper = paper.get(method) if isinstance(paper, dict) else (paper if method == "meanshift" else None)
            ours = fmt.format(getattr(results[method], key))
            line += f"{fmt.format(paper) if paper is not None else '-':>18}{ours:>18}"
        lines.append(line)
    return "\n".join(lines)


def cmd_eval(args: argparse.Namespace) -> int:
    import json

    from perception.detect import evaluate_on_scenes
    from perception.synthetic.dataset import load_preset, preset_config

    json_path = _writable_file(args.json, inputs=(_model_path(args.model),))
    model, meta = _load_model(args.model)
    zoom = args.zoom
    read_at = f"zoom {zoom:g}" if zoom is not None else f"zoom {model.inference_zoom:g}, lower where sparser"
    report = {}
    for name in args.set:
        try:
            scenes = load_preset(name, args.visibility, progress=not args.quiet, limit=args.scenes,
                                 spacing=args.spacing)
        except ValueError as error:
            raise CliError(str(error)) from None
        results = evaluate_on_scenes(model, scenes, height=args.height, axis=args.axis, progress=not args.quiet,
                                     zoom=zoom)
        label = name + (f" at {1000 * args.spacing:g} mm spacing" if args.spacing else "") + \
            f", read at {read_at}" + \
            (f" (first {len(scenes)} scenes)" if args.scenes else "")
        print(_eval_table(label, results))
        spacing = preset_config(name, args.visibility, args.spacing).voxel
        report[name] = {method: {**result.as_dict(), "spacing": spacing, "zoom": zoom or model.inference_zoom,
                                 "zoom_lowered_where_sparser": zoom is None}
                        for method, result in results.items()}
    if json_path is not None:
        _replace_file(json_path, json.dumps(report, indent=1))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from pipeline.demo import run_demo

    model, _ = _load_model(args.model)
    out_dir = _writable_dir(args.out)
    torch_threads(args.threads)
    print(f"a virtual D405 circles synthetic bed {args.seed} ({args.views} views, 848x480); "
          f"model: {args.model or 'shipped'}")
    try:
        result = run_demo(out_dir, model, args.seed, args.views, not args.no_rrd, args.spawn, progress=not args.quiet)
    except (OSError, ValueError) as error:
        raise CliError(str(error)) from None
    stages = ", ".join(f"{name} {value:.1f} s" for name, value in result.seconds.items())
    axis = f"axis error {result.angle_deg:.1f} deg" if result.caps_found else "no caps matched"
    print(f"{result.caps_found} caps found, {result.caps_true} on the bed: AP@25 {result.ap25:.1%}, "
          f"AP@50 {result.ap50:.1%}, {axis} ({stages})")
    print(f"detections: {result.detections}  session: {result.recording}"
          + (f"  rerun: {result.rrd} (open with: rerun {result.rrd})" if result.rrd else ""))
    return 0


def cmd_cameras(args: argparse.Namespace) -> int:
    from capture.source import find_cameras

    cameras = find_cameras()
    if not cameras:
        print("no RealSense or OAK camera attached (the virtual camera is always available: --camera virtual)")
    for camera in cameras:
        print(f"{camera.kind:<10} {camera.serial:<24} {camera.name}")
    return 0


def cmd_record(args: argparse.Namespace) -> int:
    from capture.mcap_io import record
    from capture.source import SourceError
    from pipeline.sources import make_source

    out = _writable_file(args.out)
    if out.exists() and not args.overwrite:
        raise CliError(f"{out} exists: pass --overwrite to replace it")
    written = [0]
    try:
        source = make_source(args.camera, args.serial, args.seed, args.views)
        with source:
            summary = record(source, out, args.duration, progress=not args.quiet, overwrite=args.overwrite,
                             on_frame=lambda frames, _: written.__setitem__(0, frames))
    except (SourceError, ValueError) as error:
        kept = (f"; the {written[0]} frames recorded so far are in {out}" if written[0]
                else "; nothing was recorded" + (f", {out} is as it was" if out.exists() else ""))
        camera = f"{args.camera} camera: " if isinstance(error, SourceError) else ""
        raise CliError(f"{camera}{error}{kept}") from None
    except (ImportError, FileExistsError) as error:
        raise CliError(str(error)) from None
    print(f"recorded {summary.frames} frames in {summary.seconds:.1f} s ({summary.stopped_by}) -> {out} "
          f"({summary.bytes / 1e6:.1f} MB)")
    return 0


STOP_EXIT = {"SIGINT": 130, "SIGTERM": 143}
"""Exit status of a run stopped by a signal (128 + its number), so a supervisor can tell."""


def _tolerances(args: argparse.Namespace):
    from pipeline.check import Tolerances

    return Tolerances(args.tol_center_mm, args.tol_axis_deg, args.tol_radius_pct)


def _wrote(paths) -> str:
    return ", ".join(str(p) for p in paths if p is not None and Path(p).exists())


def cmd_live(args: argparse.Namespace) -> int:
    from capture.mcap_io import graceful_stop
    from capture.source import SourceError
    from fusion.turntable import Rig
    from pipeline.runner import FusionStage, PerceptionStage, RunConfig
    from pipeline.session import Outputs, run_chain
    from pipeline.sources import make_source

    if args.playback and args.camera != "realsense":
        raise CliError("--playback plays a RealSense device file: use it with --camera realsense")
    if args.playback and not Path(args.playback).is_file():
        raise CliError(f"--playback: no device file at {args.playback}")
    record = _writable_file(args.record, suffix=".mcap")
    if record is not None and record.exists() and not args.overwrite:
        raise CliError(f"{record} exists: pass --overwrite to replace it")
    rrd = _writable_file(args.rrd, suffix=".rrd")
    detections = _writable_file(args.detections, suffix=".json")
    rig = None
    if args.rig:
        try:
            rig = Rig.load(args.rig)
        except ValueError as error:
            raise CliError(str(error)) from None
    model, _ = _load_model(args.model)
    torch_threads(args.threads)
    try:
        source = make_source(args.camera, args.serial, args.seed, args.views, playback=args.playback, live=True)
    except (SourceError, ImportError, ValueError) as error:
        raise CliError(f"{args.camera} camera: {error}") from None
    if args.camera == "virtual" and rig is None:
        rig = Rig(source.source.config.turntable)
    config = RunConfig(fusion=FusionStage(rig=rig, window=args.window), perception=PerceptionStage(args.clustering),
                       live=True, max_units=args.turns, duration_s=args.duration)
    outputs = Outputs(record=record, rrd=rrd, detections=detections, spawn=args.spawn, serve=args.serve,
                      name=f"live {args.camera} {time.strftime('%Y-%m-%d %H:%M:%S')}", quiet=args.quiet)
    with graceful_stop() as stop:
        try:
            summary = run_chain(source, model, config, outputs, on_start=lambda text: print(f"fused unit: {text}", flush=True),
                                stop_requested=lambda: stop.signal if stop.requested else None,
                                overwrite=args.overwrite)
        except (SourceError, ValueError, OSError) as error:
            kept = _wrote((record, rrd, detections))
            raise CliError(f"{args.camera} camera: {error}" + (f"; kept {kept}" if kept else "")) from None
    outputs_line = _wrote((record, rrd, detections)) or "nothing (add --record, --rrd or --detections)"
    line = (f"{summary.frames} frames, {summary.units} fused units, {len(summary.detections)} detected, "
            f"{summary.dropped_frames} frames and {summary.dropped_units} units dropped, {summary.failed_units} "
            f"units skipped; wrote {outputs_line}")
    if summary.stopped_by in STOP_EXIT:
        print(f"stopped by {summary.stopped_by}: {line}", file=sys.stderr)
        return STOP_EXIT[summary.stopped_by]
    print(f"{summary.stopped_by}: {line}")
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from capture.mcap_io import graceful_stop
    from pipeline.replay import ReplayError, ReplayOptions, read_expected, run_replay

    session = Path(args.session)
    if not session.is_file():
        raise CliError(f"{session} does not exist" if not session.exists() else f"{session} is not a file")
    out_dir = _writable_dir(args.out)
    rrd = _writable_file(args.rrd or str(out_dir / "replay.rrd"), inputs=(args.session,), suffix=".rrd")
    if (out_dir / "replay.mcap").exists() and (out_dir / "replay.mcap").samefile(session):
        raise CliError(f"{session} is the replay's own output; pick another --out")
    if args.expected and not args.check:
        raise CliError("--expected is what --check compares with: add --check")
    model, _ = _load_model(args.model)
    torch_threads(args.threads)
    try:
        expected = read_expected(Path(args.expected)) if args.expected else None
    except ReplayError as error:
        raise CliError(str(error)) from None
    options = ReplayOptions(args.from_stage, args.speed == "realtime", Path(args.rig) if args.rig else None,
                            args.window, args.clustering)
    with graceful_stop() as stop:
        try:
            result = run_replay(session, model, out_dir, rrd, options, _tolerances(args) if args.check else None,
                                quiet=args.quiet, stop_requested=lambda: stop.signal if stop.requested else None,
                                on_start=lambda text: print(f"fused unit: {text}", flush=True), expected=expected)
        except ReplayError as error:
            raise CliError(str(error)) from None
    summary = result.summary
    if result.frames_lost:
        print(f"warning: {session} was cut short (not finalised): replayed its {summary.frames} whole frames; "
              "what followed the last whole chunk is lost", file=sys.stderr)
    caps = summary.detections[-1].caps if summary.detections else 0
    line = (f"replayed {summary.frames} frames into {summary.units} fused units ({caps} caps in the last) -> "
            f"{_wrote((out_dir / 'replay.mcap', out_dir / 'detections.json', rrd))}")
    if summary.stopped_by in STOP_EXIT:
        print(f"stopped by {summary.stopped_by}: {line}", file=sys.stderr)
        return STOP_EXIT[summary.stopped_by]
    print(line)
    if result.check is not None:
        print(result.check.table(everything=args.verbose))
        return 0 if result.check.passed else 1
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    import numpy as np

    from capture.mcap_io import McapSource
    from capture.source import SourceError
    from fusion.turntable import estimate_rig

    out = _writable_file(args.out, inputs=(args.session,))
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
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="mushroom-pose", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    synth = sub.add_parser("synth", help="generate synthetic mushroom beds with ground truth")
    synth.add_argument("--preset", choices=["val50", "test50"], help="a fixed evaluation set")
    synth.add_argument("--scenes", type=_positive(int), default=10, help="number of scenes (default 10)")
    synth.add_argument("--seed", type=_seed, default=0, help="base seed (default 0)")
    synth.add_argument("--mushrooms", type=_mushroom_count, nargs=2, default=(5, 45), metavar=("LOW", "HIGH"),
                       help="mushrooms per scene, inclusive range (default 5 45)")
    synth.add_argument("--visibility", choices=["hpr", "camera", "katz"], default="hpr",
                       help="hpr: hidden point removal (z-buffer); camera: virtual depth camera; "
                            "katz: the paper's spherical-flip operator (slow)")
    synth.add_argument("--spacing", type=_spacing, help=f"point spacing in metres (default {SPACING_HELP})")
    synth.add_argument("--out", required=True, help="output folder")
    synth.add_argument("--rrd", help="also log the scenes to this Rerun recording")
    synth.add_argument("--no-ply", action="store_true", help="write only the .npz files")
    synth.add_argument("--preview", help="also render the first bed to this PNG (shaded meshes, oblique view)")
    synth.add_argument("--quiet", action="store_true", help="no progress bar")
    synth.set_defaults(run=cmd_synth)

    train = sub.add_parser("train", help="train the network on fresh synthetic beds (resumable)")
    train.add_argument("--out", required=True, help="run folder: checkpoint.pt, history.csv, model.pt, .rrd")
    train.add_argument("--iterations", type=_positive(int), default=20000, help="default 20000 (the paper's)")
    train.add_argument("--lr", type=_learning_rate, default=1e-3, help="Adam learning rate, at most 1 (default 1e-3)")
    train.add_argument("--milestones", type=_run_fraction, nargs="+", default=[0.6, 0.85], metavar="FRACTION",
                       help="fractions of --iterations where the learning rate drops tenfold (default 0.6 0.85)")
    train.add_argument("--average-from", type=_run_fraction, metavar="FRACTION",
                       help="from this fraction of --iterations on, average the weights after every step "
                            "(stochastic weight averaging); model.pt is the average (default: the last weights)")
    train.add_argument("--network", default="slim-no", help="network preset: slim-no (default, the shipped "
                       "model's: slim U-Net fed normals and each centroid's place in its voxel), slim-n (normals "
                       "only), slim (occupancy only, as the paper), wide-no (slim-no with wider coarse levels), "
                       "slim-no-k5 (slim-no with a 5^3 first convolution), lean-no (slim-no with 32 channels "
                       "in the full-resolution up block) or fcgf (the paper's full backbone)")
    train.add_argument("--seed", type=_seed, default=0)
    train.add_argument("--checkpoint-every", type=_positive(int), default=200)
    train.add_argument("--validate-every", type=_positive(int), default=1000)
    train.add_argument("--validation-scenes", type=_non_negative_int, default=5,
                       help="val50 scenes scored at each validation (0: none)")
    train.add_argument("--weight-existence", type=_positive(float), default=1.0,
                       help="weight of the existence loss (default 1, the paper's)")
    train.add_argument("--weight-residual", type=_positive(float), default=100.0,
                       help="weight of the residual-centre loss (default 100, the paper's)")
    train.add_argument("--weight-orientation", type=_positive(float), default=1.0,
                       help="weight of the orientation loss (default 1, the paper's)")
    train.add_argument("--orientation-on-caps", action="store_true",
                       help="average the orientation loss over cap voxels only (default: every voxel, the paper's)")
    train.add_argument("--cap-balance", action="store_true",
                       help="weigh cap voxels so every cap counts the same in the existence and orientation losses, "
                            "whatever its size (orientation then on caps only)")
    train.add_argument("--scale-jitter", type=_positive(float), nargs=2, default=[0.9, 1.1], metavar=("LOW", "HIGH"),
                       help="scale each training bed by a factor drawn from [LOW, HIGH] (default 0.9 1.1; "
                            "the shipped model was fine-tuned at 1.05 1.35)")
    train.add_argument("--zoom", type=_zoom, help="the scale the trained model reads clouds at, recorded in its "
                       f"weights and used by validation (default {DEFAULT_ZOOM}, for the default jitter; the "
                       f"shipped model's is {SHIPPED_ZOOM})")
    train.add_argument("--spacing", type=_spacing, help=f"point spacing of the training beds in metres (default "
                       f"{SPACING_HELP})")
    train.add_argument("--spacing-jitter", type=_positive(float), nargs=2, default=[0.8, 1.2], metavar=("LOW", "HIGH"),
                       help="each bed's point spacing is --spacing times a factor from [LOW, HIGH] (default 0.8 1.2)")
    train.add_argument("--cap-scale", type=_positive(float), nargs=2, default=[0.5, 1.5], metavar=("LOW", "HIGH"),
                       help="cap scale s of the training beds, a 40 mm cap at s = 1 (default 0.5 1.5, the paper's)")
    train.add_argument("--init", help="start from these weights (fine-tuning), e.g. perception/weights/default.pt; "
                       "the run is read at --zoom, not at its start's zoom")
    train.add_argument("--resume", action="store_true", help="continue the checkpoint in --out exactly")
    train.add_argument("--max-minutes", type=_positive(float),
                       help="stop cleanly with a checkpoint after this many minutes (resume later)")
    train.add_argument("--device", help="cpu or cuda (default: cuda when available)")
    train.add_argument("--threads", type=_threads, help="torch threads (default: all cores)")
    train.add_argument("--quiet", action="store_true", help="no progress bar")
    train.set_defaults(run=cmd_train)

    average = sub.add_parser("average", help="average the weights of models fine-tuned from one start "
                             "(a model soup)")
    average.add_argument("weights", nargs="+", help="two or more model.pt files that share a start (--init)")
    average.add_argument("--out", required=True, help="the weights file (.pt) to write")
    average.set_defaults(run=cmd_average)

    detect = sub.add_parser("detect", help="find caps in a point cloud (.ply, .pcd, .npz) or a session .mcap "
                            "(its fused cloud, or its frames fused first)")
    detect.add_argument("cloud", help="the point cloud file")
    detect.add_argument("--out", default="detections.json", help="detections JSON (default detections.json)")
    detect.add_argument("--rrd", help="also write a Rerun recording of the result")
    detect.add_argument("--model", help="weights file (default: the shipped model)")
    detect.add_argument("--clustering", choices=["meanshift", "dbscan"], default="meanshift")
    detect.add_argument("--zoom", type=_zoom, help="scale the network reads the cloud at (default: the one the "
                        f"weights record, {SHIPPED_ZOOM} for the shipped model, lowered for clouds sparser than its "
                        "training beds)")
    detect.add_argument("--bed-frame", action="store_true",
                        help="the cloud is already in the bed frame (z up, origin on the bed plane)")
    detect.set_defaults(run=cmd_detect)

    evaluate = sub.add_parser("eval", help="the paper's metrics on val50/test50, beside the paper's numbers")
    evaluate.add_argument("--set", nargs="+", choices=["val50", "test50"], default=["val50", "test50"])
    evaluate.add_argument("--model", help="weights file (default: the shipped model)")
    evaluate.add_argument("--json", help="also write the figures (fractions) to this JSON file")
    evaluate.add_argument("--visibility", choices=["hpr", "camera", "katz"], default="hpr")
    evaluate.add_argument("--height", choices=["free", "fixed"], default="free",
                          help="cap height: fitted (default) or the paper's fixed s_z = 2 s / 3")
    evaluate.add_argument("--axis", choices=["surface", "encoding"], default="surface",
                          help="cap axis: the encoding's refined by the cap's surface (default), or the "
                          "encoding's alone, as in the paper")
    evaluate.add_argument("--spacing", type=_spacing,
                          help=f"the same beds at this point spacing in metres (default {SPACING_HELP}; "
                               "e.g. 0.0051 for 5.1 mm sets)")
    evaluate.add_argument("--zoom", type=_zoom, help="scale the network reads clouds at (default: the one the weights record, "
                          f"{SHIPPED_ZOOM} for the shipped model, 1.1 for weights that record none; lowered for beds "
                          "sparser than the training beds)")
    evaluate.add_argument("--scenes", type=_positive(int), help="only the first N scenes of each set")
    evaluate.add_argument("--quiet", action="store_true")
    evaluate.set_defaults(run=cmd_eval)

    demo = sub.add_parser("demo", help="the whole chain on a virtual turntable: capture, MCAP, fusion, "
                          "detection, Rerun (no hardware)")
    demo.add_argument("--out", default="demo", help="output folder (default ./demo): session.mcap, "
                      "detections.json, demo.rrd")
    demo.add_argument("--seed", type=_seed, default=0, help="which synthetic bed")
    demo.add_argument("--views", type=_positive(int), default=18, help="turntable views (default 18)")
    demo.add_argument("--model", help="weights file (default: the shipped model)")
    demo.add_argument("--spawn", action="store_true", help="also show the run in a Rerun viewer")
    demo.add_argument("--no-rrd", action="store_true", help="do not write demo.rrd")
    demo.add_argument("--threads", type=_threads, help="torch threads (default: all cores)")
    demo.add_argument("--quiet", action="store_true", help="no progress bar")
    demo.set_defaults(run=cmd_demo)

    cameras = sub.add_parser("cameras", help="list attached RealSense and OAK cameras")
    cameras.set_defaults(run=cmd_cameras)

    rec = sub.add_parser("record", help="record a depth camera session to MCAP")
    rec.add_argument("--camera", choices=["realsense", "oak", "virtual"], required=True)
    rec.add_argument("--serial", help="which camera (serial number or OAK MxId) when several are attached")
    rec.add_argument("--out", required=True, help="the .mcap file to write")
    rec.add_argument("--duration", type=_positive(float), help="seconds to record (default: until the "
                     "source ends or Ctrl-C)")
    rec.add_argument("--seed", type=_seed, default=0, help="virtual camera: which synthetic bed")
    rec.add_argument("--views", type=_positive(int), default=18, help="virtual camera: turntable views")
    rec.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    rec.add_argument("--quiet", action="store_true")
    rec.set_defaults(run=cmd_record)

    live = sub.add_parser("live", help="capture, fuse and detect as frames arrive, shown in Rerun and recorded")
    live.add_argument("--camera", choices=["realsense", "oak", "virtual"], required=True)
    live.add_argument("--serial", help="which camera (serial number or OAK MxId) when several are attached")
    live.add_argument("--playback", help="RealSense: play this recorded device file (.db3) through the driver")
    live.add_argument("--rig", help="rig file from mushroom-pose calibrate (turntable or several cameras)")
    live.add_argument("--window", type=_positive(int), help="one camera without a rig: fuse the last N frames "
                      "(registered by ICP) after every frame (default: each frame alone)")
    live.add_argument("--record", help="record the session (frames, fused clouds, caps) to this .mcap")
    live.add_argument("--overwrite", action="store_true", help="replace an existing --record file")
    live.add_argument("--rrd", help="save the Rerun recording to this .rrd")
    live.add_argument("--detections", help="keep the newest caps in this JSON file")
    viewer = live.add_mutually_exclusive_group()
    viewer.add_argument("--spawn", action="store_true", help="show the run in a Rerun viewer")
    viewer.add_argument("--serve", action="store_true", help="serve the Rerun web viewer (a headless machine)")
    live.add_argument("--duration", type=_positive(float), help="seconds to capture (default: until the camera "
                      "ends, --turns, or Ctrl-C)")
    live.add_argument("--turns", type=_positive(int), help="stop after this many fused units (turns of a turntable)")
    live.add_argument("--seed", type=_seed, default=0, help="virtual camera: which synthetic bed")
    live.add_argument("--views", type=_positive(int), default=18, help="virtual camera: views per turn")
    live.add_argument("--model", help="weights file (default: the shipped model)")
    live.add_argument("--clustering", choices=["meanshift", "dbscan"], default="meanshift")
    live.add_argument("--threads", type=_threads, help="torch threads (default: all cores)")
    live.add_argument("--quiet", action="store_true", help="no line per fused unit")
    live.set_defaults(run=cmd_live)

    replay = sub.add_parser("replay", help="re-run fusion and perception on a recorded session; --check "
                            "compares with the detections it recorded")
    replay.add_argument("session", help="a session .mcap (from live, record or demo) or a RealSense device file "
                        "(.db3, played through the driver)")
    replay.add_argument("--out", default="replay", help="output folder (default ./replay): replay.mcap, "
                        "detections.json, replay.rrd")
    replay.add_argument("--rrd", help="the Rerun recording (default OUT/replay.rrd)")
    replay.add_argument("--from-stage", choices=["capture", "fusion"], default="capture",
                        help="capture: fuse the recorded frames again (default); fusion: detect on the recorded "
                             "fused clouds")
    replay.add_argument("--speed", choices=["max", "realtime"], default="max",
                        help="max: as fast as the chain runs (default); realtime: at the recorded frame rate")
    replay.add_argument("--rig", help="rig file from mushroom-pose calibrate")
    replay.add_argument("--window", type=_positive(int), help="one camera without a rig: fuse the last N frames")
    replay.add_argument("--check", action="store_true", help="compare the new caps with the recorded ones unit by "
                        "unit; exit 1 when a cap is lost, gained or changed beyond the tolerances")
    replay.add_argument("--expected", help="--check against these detections (JSON: one document or a list, one "
                        "per fused unit) instead of the session's own")
    replay.add_argument("--tol-center-mm", type=_positive(float), default=2.0, help="default 2")
    replay.add_argument("--tol-axis-deg", type=_positive(float), default=3.0, help="default 3")
    replay.add_argument("--tol-radius-pct", type=_positive(float), default=5.0, help="default 5")
    replay.add_argument("--verbose", action="store_true", help="--check: list every cap, not only changes")
    replay.add_argument("--model", help="weights file (default: the shipped model)")
    replay.add_argument("--clustering", choices=["meanshift", "dbscan"], default="meanshift")
    replay.add_argument("--threads", type=_threads, help="torch threads (default: all cores)")
    replay.add_argument("--quiet", action="store_true", help="no line per fused unit")
    replay.set_defaults(run=cmd_replay)

    calibrate = sub.add_parser("calibrate", help="turntable axis and camera extrinsics from a recorded turn")
    calibrate.add_argument("--session", required=True, help="an MCAP recording of one full turn")
    calibrate.add_argument("--out", required=True, help="the rig file (JSON) to write")
    calibrate.add_argument("--reference", help="the camera whose frame defines the rig (default: the first)")
    calibrate.set_defaults(run=cmd_calibrate)
    return parser


def main(argv: list[str] | None = None) -> int:
    interrupted: list[int] = []

    def on_interrupt(signum: int, frame) -> None:
        interrupted.append(signum)
        raise KeyboardInterrupt

    # Installed before numpy and each command's libraries load: C extensions turn a Ctrl-C during
    # their loading into other errors, such as ImportError("initialization failed"). An ignored
    # SIGINT (a background job) stays ignored.
    previous = signal.getsignal(signal.SIGINT) if threading.current_thread() is threading.main_thread() else None
    if previous in (signal.SIG_IGN, None):
        previous = None
    else:
        signal.signal(signal.SIGINT, on_interrupt)
    command = "mushroom-pose"
    try:
        args = build_parser().parse_args(argv)
        command = f"mushroom-pose {args.command}"
        reuse_freed_memory()
        return args.run(args)
    except CliError as error:
        if not interrupted:
            print(f"{command}: error: {error}", file=sys.stderr)
            return 2
    except KeyboardInterrupt:
        pass
    except Exception:
        if not interrupted:
            raise
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
    print(f"{command}: interrupted", file=sys.stderr)
    return 130


def console_main() -> None:
    """The ``mushroom-pose`` command. After an interrupt it exits without running exit handlers:
    Open3D, interrupted while it loaded, would print a leak report and turn status 130 into 1."""
    code = main()
    if code == 130:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    console_main()
