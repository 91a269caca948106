"""What the commands share: the one-line user error, argument validators, output-path checks and the
model they load. Imports no numpy: the parser is built before any heavy library loads."""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path


class CliError(Exception):
    """A problem with the user's input: reported in one line, exit status 2."""


class CommandFailed(Exception):
    """A command that could not finish although its input was good (a full disk, a failed write):
    reported in one line that says what was kept, exit status 1."""


# ---- output paths

def writable_dir(path: str) -> Path:
    """The folder ``path``, created if missing and checked writable."""
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


def writable_file(path: str | None, inputs: tuple[str | None, ...] = (), suffix: str | None = None) -> Path | None:
    """An output file's path, its folder created; refused when it is a folder, a device or other
    special file, one of ``inputs`` (writing it would destroy the input), or, for a fixed format,
    named without its ``suffix``. A symlink resolves to its target, which is then replaced; a
    dangling one is refused."""
    if path is None:
        return None
    file = Path(path)
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
    if suffix is not None and Path(path).suffix.lower() != suffix:
        raise CliError(f"{path}: this file is written as {suffix[1:].upper()}; name it with {suffix}")
    writable_dir(str(file.parent if str(file.parent) else "."))
    return file


OVERWRITE_HELP = "replace outputs that exist (without it no command replaces a file it did not just make)"


def add_overwrite_flag(parser: argparse.ArgumentParser) -> None:
    """``--overwrite``: the one switch with which a command replaces its earlier outputs."""
    parser.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)


def refuse_to_replace(paths, overwrite: bool) -> None:
    """A CliError naming the first of ``paths`` (None ignored) that exists, unless ``overwrite``."""
    taken = [Path(path) for path in paths if path is not None and Path(path).exists()]
    if taken and not overwrite:
        raise CliError(f"{taken[0]} exists: pass --overwrite to replace it, or choose another output")


def replace_file(path: Path, text: str) -> None:
    """Write through a temporary file renamed over ``path``: a failed write leaves an earlier file
    whole and no temporary file behind."""
    from common.files import write_atomically

    try:
        write_atomically(path, text)
    except OSError as error:
        raise CliError(f"cannot write {path}: {error.strerror or error}") from None


def written_files(paths) -> str:
    """The paths among ``paths`` that exist, comma-separated."""
    return ", ".join(str(p) for p in paths if p is not None and Path(p).exists())


STOP_EXIT = {"SIGINT": 130, "SIGTERM": 143}
"""Exit status of a run stopped by a signal (128 + its number), so a supervisor can tell."""


# ---- argument validators: each turns one word into a value or raises a one-line ArgumentTypeError

MAX_COUNT = 2**31 - 1
"""Counts (scenes, views, iterations, threads) beyond this are typing slips, and overflow numpy's seeds."""


def _number(kind, text: str):
    """``text`` as an int or a finite float."""
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {'a whole number' if kind is int else 'a number'}, "
                                         f"got {text!r}") from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def positive(kind):
    """A parser of positive ``kind`` (int or float) values; ints at most MAX_COUNT."""
    def parse(text: str):
        value = _number(kind, text)
        if kind is int and value > MAX_COUNT:
            raise argparse.ArgumentTypeError(f"at most {MAX_COUNT}, got {text}")
        if value <= 0:
            raise argparse.ArgumentTypeError(f"must be positive, got {text}")
        return value
    return parse


def non_negative(kind):
    """A parser of ``kind`` (int or float) values of zero or more."""
    def parse(text: str):
        value = _number(kind, text)
        if value < 0:
            raise argparse.ArgumentTypeError(f"must not be negative, got {text}")
        return value
    return parse


def at_most(parse, limit, reason: str = ""):
    """``parse``, refusing values above ``limit``."""
    return _bounded(parse, lambda value: value <= limit, f"at most {limit}{reason}")


def at_least(parse, limit, reason: str = ""):
    """``parse``, refusing values below ``limit``."""
    return _bounded(parse, lambda value: value >= limit, f"at least {limit}{reason}")


def _bounded(parse, accept, wanted: str):
    def bounded(text: str):
        value = parse(text)
        if not accept(value):
            raise argparse.ArgumentTypeError(f"{wanted}, got {text}")
        return value
    return bounded


MAX_MUSHROOMS = 300
"""More than a 0.5 m bed holds (about 260 caps when packed): asking for more only slows the placer."""
CORES = os.cpu_count() or 1

parse_seed = at_most(non_negative(int), 2**63 - 1, " (seeds are below 2^63)")
parse_threads = at_most(positive(int), 4 * CORES, f" (4 per core; this machine has {CORES})")
parse_learning_rate = at_most(positive(float), 1.0, " (Adam's steps are about this size in every weight)")
parse_run_fraction = at_most(positive(float), 1.0, " (a fraction of the run's iterations)")
parse_mushroom_count = at_most(non_negative(int), MAX_MUSHROOMS, " (a 0.5 m bed is full at about 260)")
parse_spacing = at_least(at_most(positive(float), 0.02, " metres (0.003 is 3 mm)"), 0.001,
                         " metres: a finer spacing only multiplies the points (0.003 is 3 mm)")
MAX_READINGS = 12
"""perception.detect.MAX_READINGS: the most turned readings detection takes."""
parse_readings = at_most(positive(int), MAX_READINGS, " (each reading is a pass of the network)")
parse_zoom = at_least(at_most(positive(float), 2.0, " (the network would read caps twice their size)"), 0.5,
                      " (the network would read caps half their size)")

# Named here, not imported, because the parser imports no numpy (Ctrl-C while libraries load); tests
# hold them to their sources.
SPACING_HELP = "0.003, the generator's: every 4.5 mm voxel a surface crosses holds a point"
"""SceneConfig.spacing and what it gives."""
SHIPPED_ZOOM = 1.2
"""The zoom the shipped model's weights record (trained with --scale-jitter 1.05 1.35)."""
FILE_READINGS = 4
"""perception.detect.FILE_READINGS: how many turned readings of a cloud ``detect`` and ``eval`` average."""
VISIBILITY = ("hpr", "camera", "fused", "katz")
"""perception.synthetic.scene.VISIBILITY_MODELS: how a synthetic bed becomes points."""


# ---- flags several commands share

def add_model_flag(parser: argparse.ArgumentParser) -> None:
    """``--model``: the weights a command reads (``load_model``)."""
    parser.add_argument("--model", help="weights file (default: the shipped model)")


def add_threads_flag(parser: argparse.ArgumentParser) -> None:
    """``--threads``: torch's threads (``torch_threads``)."""
    parser.add_argument("--threads", type=parse_threads, help="torch threads (default: all cores)")


def add_quiet_flag(parser: argparse.ArgumentParser, what: str = "no progress bar") -> None:
    """``--quiet``: ``what`` the command then leaves out of its output."""
    parser.add_argument("--quiet", action="store_true", help=what)


def add_viewer_flags(parser: argparse.ArgumentParser, rrd: str | None = "also write the Rerun recording to "
                     "this .rrd", serve_until: str = "until Ctrl-C") -> None:
    """Where a run shows in Rerun: ``--rrd`` (with the help ``rrd``; None: the command names its own
    file), and one of ``--spawn`` and ``--serve``; read back by ``viewer_target``."""
    if rrd is not None:
        parser.add_argument("--rrd", help=rrd)
    viewer = parser.add_mutually_exclusive_group()
    viewer.add_argument("--spawn", action="store_true", help="also show the run in a Rerun viewer")
    viewer.add_argument("--serve", action="store_true", help="serve the Rerun web viewer (port 9090) for a "
                        f"browser on another machine, {serve_until}")


def viewer_target(args: argparse.Namespace, inputs: tuple[str | None, ...] = (), rrd: str | None = None,
                  hold: bool = True):
    """The ``pipeline.viewer_target.ViewerTarget`` of ``add_viewer_flags``' flags, its .rrd checked as an output
    (``rrd``: the file when the command names its own); with ``hold``, ``--serve`` keeps serving after
    the command's work is done."""
    from pipeline.viewer_target import ViewerTarget

    path = writable_file(rrd if rrd is not None else getattr(args, "rrd", None), inputs, suffix=".rrd")
    return ViewerTarget(path, args.spawn, args.serve, hold)


DEFAULT_GRADES_HELP = "small button from 0 mm, button from 25, closed cup from 40, open cup from 55, flat from 70"
"""perception.grades.GradeTable's default, as ``--grades`` says it (numpy is not loaded to build a parser)."""


def add_bed_id_flag(parser: argparse.ArgumentParser) -> None:
    """``--bed-id ID``: which bed a recorded session scans, so that ``track`` can follow it over days."""
    parser.add_argument("--bed-id", metavar="ID", help="the bed this session scans (recorded with it; track "
                        "follows one bed's sessions over the days)")


def add_grades_flag(parser: argparse.ArgumentParser) -> None:
    """``--grades FILE``: the grower's grade table (``perception.grades``), read back by ``grade_table``."""
    parser.add_argument("--grades", metavar="FILE", help="grade each cap by this table of named classes by cap "
                        "diameter (.json or .toml: grades = a list of {name, from_mm}, smallest first; default: "
                        f"{DEFAULT_GRADES_HELP})")


def grade_table(args: argparse.Namespace):
    """The ``perception.grades.GradeTable`` of ``--grades`` (the default table without it)."""
    from perception.grades import GradeTable

    if args.grades is None:
        return GradeTable()
    try:
        return GradeTable.load(args.grades)
    except ValueError as error:
        raise CliError(str(error)) from None


def add_pick_flags(parser: argparse.ArgumentParser) -> None:
    """The gripper and the pick size (``perception.plan.PickConfig``), read back by ``pick_config``."""
    from pipeline.flags import add_config_flags

    add_config_flags(parser, "perception.plan:PickConfig")


def pick_config(args: argparse.Namespace):
    """The ``PickConfig`` of ``add_pick_flags``' flags; values it refuses are a CliError."""
    from perception.plan import PickConfig
    from pipeline.flags import config_from_args

    try:
        return config_from_args(PickConfig, args)
    except ValueError as error:
        raise CliError(str(error)) from None


# ---- the model and torch

def torch_threads(threads: int | None) -> None:
    """Let torch use ``threads`` threads (None: its default, every core)."""
    import torch

    if threads:
        torch.set_num_threads(threads)


def model_path(path: str | None) -> Path:
    """The weights file ``--model`` names, or the shipped one."""
    from perception.weights import DEFAULT_WEIGHTS

    return Path(path) if path else DEFAULT_WEIGHTS


def load_model(path: str | None, in_torch: bool = True):
    """The model and metadata of the weights ``--model`` names (default: the shipped model): the torch
    network, or with ``in_torch=False`` the numpy one (``perception.inference``), read without torch."""
    from perception.weights import load_inference_net, load_weights

    weights = model_path(path)
    if not weights.exists():
        if path:
            raise CliError(f"model file {weights} does not exist")
        raise CliError(f"no shipped model at {weights}: train one (mushroom-pose train) and pass --model")
    try:
        return load_weights(weights) if in_torch else load_inference_net(weights)
    except ValueError as error:
        raise CliError(str(error)) from None


def add_ray_flag(parser: argparse.ArgumentParser, what: str) -> None:
    """``--ray [ADDRESS]``: run on Ray, a local one started for the command or the cluster at ADDRESS."""
    parser.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                        help=f"{what}: on a local Ray, or on the Ray cluster at ADDRESS (needs pip install -e "
                             "'.[ray]')")


def ray_options(args: argparse.Namespace) -> dict:
    """``use_ray`` and ``ray_address`` from ``--ray``; a one-line error when Ray is not installed."""
    if args.ray is None:
        return {"use_ray": False, "ray_address": None}
    from common.distributed import require_ray

    try:
        require_ray()
    except ValueError as error:
        raise CliError(str(error)) from None
    return {"use_ray": True, "ray_address": None if args.ray == "local" else args.ray}


def json_text(document) -> str:
    """``document`` as strict JSON: an undefined figure (NaN, infinite) is null, never a bare NaN that
    JSON readers reject."""
    import json

    def strict(value):
        if isinstance(value, float) and not math.isfinite(value):
            return None
        if isinstance(value, dict):
            return {key: strict(item) for key, item in value.items()}
        if isinstance(value, (list, tuple)):
            return [strict(item) for item in value]
        return value

    return json.dumps(strict(document), indent=1, allow_nan=False)
