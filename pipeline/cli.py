"""The ``mushroom-pose`` command line: one subcommand per job, flags mapped onto config dataclasses."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


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


def _writable_file(path: str | None) -> Path | None:
    if path is None:
        return None
    file = Path(path)
    if file.is_dir():
        raise CliError(f"{file} is a folder, expected a file name")
    _writable_dir(str(file.parent if str(file.parent) else "."))
    return file


def _positive(kind):
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if value <= 0:
            raise argparse.ArgumentTypeError(f"must be positive, got {text}")
        return value
    return parse


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {text}")
    return value


def cmd_synth(args: argparse.Namespace) -> int:
    from perception.synthetic.dataset import (PRESETS, generate_many, log_scene, scene_seeds, write_scene)
    from perception.synthetic.scene import SceneConfig
    from pipeline.rerun_sink import rerun_stream, set_frame

    low, high = args.mushrooms
    if high < low:
        raise CliError(f"--mushrooms range is inverted: {low} > {high}")
    out = _writable_dir(args.out)
    rrd = _writable_file(args.rrd)
    if args.preset:
        preset = PRESETS[args.preset]
        seeds = scene_seeds(preset.seed, preset.scenes)
        config = SceneConfig(**{**preset.config.__dict__, "visibility": args.visibility})
    else:
        seeds = scene_seeds(args.seed, args.scenes)
        config = SceneConfig(mushrooms=(low, high), visibility=args.visibility)
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
    if rrd is not None:
        print(f"rerun recording: {rrd}")
    return 0


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: the message and where to look, no usage dump."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="mushroom-pose", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    synth = sub.add_parser("synth", help="generate synthetic mushroom beds with ground truth")
    synth.add_argument("--preset", choices=["val50", "test50"], help="a fixed evaluation set")
    synth.add_argument("--scenes", type=_positive(int), default=10, help="number of scenes (default 10)")
    synth.add_argument("--seed", type=_non_negative_int, default=0, help="base seed (default 0)")
    synth.add_argument("--mushrooms", type=_non_negative_int, nargs=2, default=(5, 45), metavar=("LOW", "HIGH"),
                       help="mushrooms per scene, inclusive range (default 5 45)")
    synth.add_argument("--visibility", choices=["hpr", "camera", "katz"], default="hpr",
                       help="hpr: hidden point removal (z-buffer); camera: virtual depth camera; "
                            "katz: the paper's spherical-flip operator (slow)")
    synth.add_argument("--out", required=True, help="output folder")
    synth.add_argument("--rrd", help="also log the scenes to this Rerun recording")
    synth.add_argument("--no-ply", action="store_true", help="write only the .npz files")
    synth.add_argument("--quiet", action="store_true", help="no progress bar")
    synth.set_defaults(run=cmd_synth)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.run(args)
    except CliError as error:
        print(f"mushroom-pose {args.command}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"mushroom-pose {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
