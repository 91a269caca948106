"""``mushroom-pose train``: every TrainConfig field as a flag, and the run's own options."""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.commands.common import (CliError, CommandFailed, add_quiet_flag, add_ray_flag, add_threads_flag, at_most,
                                      non_negative, parse_learning_rate, parse_run_fraction, parse_seed, parse_spacing,
                                      parse_zoom, positive, ray_options, torch_threads, writable_dir)

TRAIN_CONFIG = "perception.train:TrainConfig"
SCENE_CONFIG = "perception.synthetic.scene:SceneConfig"
SCENE = "scene_"
"""Prefix of the parsed values that go to TrainConfig.scene."""
RANGE = ("LOW", "HIGH")

TRAIN_FLAGS = {
    "iterations": {"parse": positive(int)},
    "lr": {"parse": parse_learning_rate},
    "milestones": {"parse": parse_run_fraction, "metavar": "FRACTION"},
    "gamma": {"parse": at_most(positive(float), 1.0, " (1 keeps the learning rate)")},
    "weight_existence": {"parse": positive(float)},
    "weight_residual": {"parse": positive(float)},
    "weight_orientation": {"parse": positive(float)},
    "average_from": {"parse": parse_run_fraction, "metavar": "FRACTION"},
    "init_weights": {"name": "init", "metavar": "WEIGHTS"},
    "zoom": {"parse": parse_zoom},
    "seed": {"parse": parse_seed},
    "checkpoint_every": {"parse": positive(int)},
    "validate_every": {"parse": positive(int)},
    "validation_scenes": {"parse": non_negative(int)},
    "queue_size": {"parse": at_most(positive(int), 64, " beds (each waiting bed holds all its points)")},
    "scale_jitter": {"parse": positive(float), "metavar": RANGE},
    "point_dropout": {"parse": at_most(non_negative(float), 0.99, " (a fraction of the points)"), "metavar": RANGE},
    "tilt_deg": {"parse": at_most(non_negative(float), 90.0, " degrees")},
    "noise": {"parse": at_most(non_negative(float), 0.01, " metres (0.0005 is half a millimetre)")},
    "fused_share": {"parse": at_most(non_negative(float), 1.0, " (a share of the beds)"), "metavar": "SHARE"},
    "stereo_share": {"parse": at_most(non_negative(float), 1.0, " (a share of the scanned beds)"), "metavar": "SHARE"},
}
"""Validators and names of TrainConfig's flags where its field's type and name are not enough
(pipeline.flags.FLAG_KEYS)."""

SCENE_FLAGS = {
    "spacing": {"name": "spacing", "parse": parse_spacing, "metavar": "M",
                "help": "Point spacing of the training beds in metres; the weights record it."},
    "jitter": {"name": "spacing-jitter", "parse": positive(float), "metavar": RANGE,
               "help": "Each bed's point spacing is --spacing times a factor from [low, high]."},
    "scale": {"name": "cap-scale", "parse": positive(float), "metavar": RANGE,
              "help": "Cap scale s of the training beds, a 40 mm cap at s = 1 (the paper's)."},
    "cap_height": {"name": "cap-height", "parse": positive(float), "metavar": RANGE,
                   "help": "Factor on each cap's height, from [low, high]: below 1 makes the shallower "
                           "domes of real beds (1 1: the template's, the paper's)."},
    "visibility": {"name": "visibility", "metavar": "MODEL",
                   "help": "How a bed becomes points: hpr (hidden point removal, the paper's), camera (the "
                           "virtual depth camera), fused (that camera from each view, merged as a scan is; "
                           "--spacing is then the merge voxel) or katz."},
    "views": {"name": "views", "parse": positive(int), "metavar": RANGE,
              "help": "Viewpoints each training bed is seen from, from [low, high], their points pooled as "
                      "in a fused cloud (1 1: one overhead view, the paper's)."},
    "soil_holes": {"name": "soil-holes", "parse": at_most(non_negative(float), 1.0, " (a share of the soil)"),
                   "metavar": RANGE, "help": "Share of the bare soil lost in blotches a few centimetres across, "
                   "from [low, high], as dark casing soil leaves holes in a real scan (0 0: none)."},
    "soil_lumps": {"name": "soil-lumps", "parse": non_negative(int), "metavar": RANGE,
                   "help": "Casing-soil lumps per bed, from [low, high]: rough bare-soil mounds 2-6 cm across "
                           "that are not caps, as a real bed's casing shows (0 0: none)."},
    "soil_banks": {"name": "soil-banks", "parse": non_negative(int), "metavar": RANGE,
                   "help": "Caps per bed, from [low, high], among the smaller half, with casing soil banked "
                           "against one side up to below the dome, as young caps stand on a real bed (0 0: none)."},
    "cluster_probability": {"name": "cluster-probability", "parse": at_most(non_negative(float), 1.0),
                            "metavar": "P", "help": "Chance that a cap is placed touching an earlier one."},
    "cluster_spacing": {"name": "cluster-spacing", "parse": positive(float), "metavar": RANGE,
                        "help": "Centre distance of a clustered cap from its neighbour, as a factor on "
                                "their radii's sum, from [low, high]; below 1 one stands partly under the "
                                "other's rim."},
}
"""The fields of TrainConfig.scene that are train flags, with help written for the command line."""

NAME = "train"
HELP = "train the network on fresh synthetic beds (resumable)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from pipeline.flags import add_config_flags  # loads ast: only a parsed train pays it

    parser.add_argument("--out", required=True, help="run folder: checkpoint.pt, history.csv, model.pt, .rrd")
    add_config_flags(parser, TRAIN_CONFIG, TRAIN_FLAGS, exclude=("scene",))
    add_config_flags(parser, SCENE_CONFIG, SCENE_FLAGS, only=tuple(SCENE_FLAGS), prefix=SCENE)
    parser.add_argument("--resume", action="store_true", help="continue the checkpoint in --out exactly, with the "
                        "run's own flags (none need repeating; one given must match); an error when --out holds "
                        "none, so a mistyped folder never starts over")
    parser.add_argument("--max-minutes", type=positive(float),
                        help="stop cleanly with a checkpoint after this many minutes (resume later)")
    parser.add_argument("--device", help="cpu or cuda (default: cuda when available)")
    add_threads_flag(parser)
    add_quiet_flag(parser)
    add_ray_flag(parser, "make the training beds as Ray tasks (the same beds, so the same run)")


def train_config(args: argparse.Namespace):
    """The TrainConfig that ``mushroom-pose train`` runs with these arguments."""
    from perception.synthetic.scene import SceneConfig
    from perception.train import TrainConfig
    from pipeline.flags import config_from_args

    init = str(Path(args.init_weights).resolve()) if args.init_weights else None
    return config_from_args(TrainConfig, args, scene=config_from_args(SceneConfig, args, prefix=SCENE),
                            init_weights=init)


def _check(args: argparse.Namespace) -> None:
    """Refuse flags that parse one by one but not together."""
    from perception.network import NETWORK_PRESETS

    if args.network not in NETWORK_PRESETS:
        raise CliError(f"unknown network {args.network!r}; choose one of {sorted(NETWORK_PRESETS)}")
    if args.init_weights and not args.resume and not Path(args.init_weights).is_file():
        raise CliError(f"--init: no weights file at {args.init_weights}")
    ranges = [(spec.get("name", key.replace("_", "-")), prefix + key)
              for prefix, flags in (("", TRAIN_FLAGS), (SCENE, SCENE_FLAGS))
              for key, spec in flags.items() if spec.get("metavar") == RANGE]
    for name, dest in ranges:
        low, high = getattr(args, dest)
        if low > high:
            raise CliError(f"--{name} wants LOW HIGH with LOW <= HIGH, got {low} {high}")
    if any(later <= earlier for earlier, later in zip(args.milestones, args.milestones[1:])):
        raise CliError(f"--milestones must increase, got {' '.join(map(str, args.milestones))}")


def run(args: argparse.Namespace) -> int:
    from perception.train import TrainingError, train
    from perception.weights import WeightsWriteError
    from pipeline.viewer import TrainingLog

    _check(args)
    try:
        config = train_config(args)
    except ValueError as error:  # flags that parse alone but make no scene together
        raise CliError(str(error)) from None
    if config.averaging_start is not None and config.averaging_start >= config.iterations:
        raise CliError(f"--average-from {args.average_from} leaves no iteration of {args.iterations} to average")
    new_folder = not Path(args.out).exists()
    run_dir = writable_dir(args.out)
    if (run_dir / "checkpoint.pt").exists() and not args.resume:
        raise CliError(f"{run_dir} already holds a checkpoint: add --resume to continue it, or pick a new --out")
    ray_options(args)  # Ray installed, when asked for
    torch_threads(args.threads)
    try:
        weights = train(config, run_dir, resume=args.resume, device=args.device, progress=not args.quiet,
                        metrics_log=TrainingLog, max_minutes=args.max_minutes, ray_address=args.ray)
    except (ValueError, TrainingError, WeightsWriteError) as error:
        if new_folder and not any(run_dir.iterdir()):
            run_dir.rmdir()
        raise (CliError if isinstance(error, ValueError) else CommandFailed)(str(error)) from None
    if weights is None:
        print(f"stopped after {args.max_minutes} minutes with a checkpoint in {run_dir}: continue with the same "
              "flags and --resume")
    else:
        print(f"weights: {weights}")
    return 0
