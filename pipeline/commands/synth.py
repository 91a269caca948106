"""``mushroom-pose synth``: synthetic mushroom beds with their ground truth."""

from __future__ import annotations

import argparse
import sys
import time

from pipeline.commands.common import (SPACING_HELP, VISIBILITY, CliError, CommandFailed, add_overwrite_flag,
                                      add_quiet_flag, add_ray_flag, add_viewer_flags, parse_mushroom_count, parse_seed,
                                      parse_spacing, positive, ray_options, refuse_to_replace, viewer_target,
                                      writable_dir, writable_file)

NAME = "synth"
HELP = "generate synthetic mushroom beds with ground truth"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", choices=["val50", "test50"], help="a fixed evaluation set: 50 beds of 5-45 caps "
                        "each, val50 and test50 from different seeds (--spacing: the same beds at another spacing)")
    parser.add_argument("--family", help="beds of one family of the robustness suite (bench/robustness.py): "
                        "shallow-domes, real-domes, flats, large-brown, dense-pins, spacing-1mm, spacing-5mm, "
                        "spacing-8mm, single-view, fused-views, oak-stereo, tilted-uneven, touching-clusters, "
                        "casing-soil, mycelium (--spacing overrides its spacing)")
    parser.add_argument("--scenes", type=positive(int), default=10, help="number of scenes (default 10)")
    parser.add_argument("--seed", type=parse_seed, default=0, help="base seed (default 0)")
    parser.add_argument("--mushrooms", type=parse_mushroom_count, nargs=2, default=(5, 45), metavar=("LOW", "HIGH"),
                        help="mushrooms per scene, inclusive range (default 5 45)")
    parser.add_argument("--visibility", choices=VISIBILITY, default="hpr",
                        help="hpr: hidden point removal (z-buffer); camera: virtual depth camera; fused: that "
                             "camera's frame smoothed and merged as fusion does; katz: the paper's spherical-flip "
                             "operator (slow)")
    parser.add_argument("--spacing", type=parse_spacing, help=f"point spacing in metres (default {SPACING_HELP})")
    parser.add_argument("--out", required=True, help="output folder")
    add_viewer_flags(parser, "also log the beds to this Rerun recording (one per step of the frame timeline)")
    parser.add_argument("--days", type=positive(int), help="scan each bed on N days instead, as a grower's rig "
                        "does: caps grow at their own rates, new pins appear, ripe caps are picked, the rig is placed "
                        "a little differently each day (bed_<seed>_day_<D>.npz per scan in its own frame, and "
                        "bed_<seed>_history.npz with every cap's diameter per day)")
    parser.add_argument("--no-ply", action="store_true", help="write only the .npz files")
    parser.add_argument("--preview", help="also render the first bed to this PNG (shaded meshes, oblique view)")
    add_quiet_flag(parser)
    add_overwrite_flag(parser)
    add_ray_flag(parser, "make the beds as Ray tasks (the same beds as here)")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from perception.synthetic.dataset import (BED_SETS, generate_many, preset_config, scene_path, scene_seeds,
                                              write_scene)
    from perception.synthetic.scene import SceneConfig
    from pipeline.viewer import log_scene, set_frame, viewer_stream

    low, high = args.mushrooms
    if high < low:
        raise CliError(f"--mushrooms range is inverted: {low} > {high}")
    preview = writable_file(args.preview, suffix=".png")
    viewer = viewer_target(args)
    if args.family:
        from dataclasses import replace

        from perception.synthetic.families import FAMILIES

        if args.preset or args.family not in FAMILIES:
            raise CliError("--family and --preset are two kinds of beds: give one" if args.preset else
                           f"unknown bed family {args.family!r}; choose one of {', '.join(FAMILIES)}")
        seeds = scene_seeds(args.seed, args.scenes)
        config = FAMILIES[args.family].config
        config = replace(config, spacing=args.spacing) if args.spacing else config
    elif args.preset:
        preset = BED_SETS[args.preset]
        seeds = scene_seeds(preset.seed, preset.scenes)
        config = preset_config(args.preset, args.visibility, args.spacing)
    else:
        seeds = scene_seeds(args.seed, args.scenes)
        config = SceneConfig(mushrooms=(low, high), visibility=args.visibility,
                             spacing=args.spacing or SceneConfig.spacing)
    out = writable_dir(args.out)
    if args.days:
        return _synth_days(args, seeds, config, out)
    refuse_to_replace([scene_path(out, index) for index in range(len(seeds))] + [viewer.rrd, preview], args.overwrite)
    mushrooms, points, started = [], [], time.perf_counter()
    with viewer_stream(viewer, f"synthetic beds in {out}") as rec:
        for index, scene in enumerate(generate_many(seeds, config, progress=not args.quiet,
                                                                   **ray_options(args))):
            try:
                write_scene(scene, out, index, ply=not args.no_ply)
            except OSError as error:
                kept = {0: "no scene was written", 1: "scene 0 is whole"}.get(index, f"scenes 0-{index - 1} are whole")
                raise CommandFailed(f"cannot write scene {index} into {out}: {error.strerror or error}; {kept}") \
                    from None
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
    if viewer.rrd is not None:
        print(f"rerun recording: {viewer.rrd}")
    if preview is not None:
        from pipeline.preview import render_bed_preview

        render_bed_preview(seeds[0], config, preview)
        print(f"preview of the first scene: {preview}")
    return 0


def _synth_days(args: argparse.Namespace, seeds: list[int], config, out) -> int:
    """``synth --days N``: each bed scanned on N days, with the truth of its caps over them."""
    from tqdm import tqdm

    from perception.synthetic.days import GrowthConfig, bed_over_days, write_history

    if args.preset or args.rrd or args.spawn or args.serve or args.preview:
        raise CliError("--days makes beds over days: give it without --preset, --rrd, --spawn, --serve or --preview")
    names = [f"bed_{seed}_day_{day}.npz" for seed in seeds for day in range(args.days)]
    refuse_to_replace([out / name for name in names] + [out / f"bed_{seed}_history.npz" for seed in seeds],
                      args.overwrite)
    growth = GrowthConfig(days=args.days)
    caps = 0
    for seed in tqdm(seeds, desc="beds", unit="bed", disable=args.quiet):
        history = bed_over_days(seed, config, growth)
        try:
            write_history(history, out)
        except OSError as error:
            raise CommandFailed(f"cannot write bed {seed} into {out}: {error.strerror or error}") from None
        caps += len(history.diameters_mm)
    print(f"beds: {len(seeds)} scanned on {args.days} days  caps: {caps}  -> {out}")
    return 0
