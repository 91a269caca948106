"""``mushroom-pose eval``: the paper's metrics on val50/test50, beside the paper's numbers."""

from __future__ import annotations

import argparse

from pipeline.commands.common import (FILE_READINGS, SHIPPED_ZOOM, SPACING_HELP, VISIBILITY, CliError, add_model_flag,
                                      add_overwrite_flag, add_quiet_flag, add_ray_flag, json_text, load_model,
                                      model_path, parse_readings, parse_spacing, parse_zoom, positive, ray_options,
                                      refuse_to_replace, replace_file, writable_file)

PAPER = {"ap25": {"meanshift": 0.9957, "dbscan": 0.9920}, "ap50": {"meanshift": 0.8195, "dbscan": 0.8148},
         "scale_err": 0.048, "cosine": 0.9973, "angle_deg": 4.22}
"""The paper's Tables 3-4 (synthetic validation set, MeanShift and DBSCAN). Its angle is arccos of the
mean cosine (``EvalResult``); it gives no per-cap mean or median."""

NAME = "eval"
HELP = "the paper's metrics on val50/test50, beside the paper's numbers"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--set", nargs="+", choices=["val50", "test50"], default=["val50", "test50"],
                        help="the evaluation sets to score (50 beds each, as synth --preset makes them)")
    add_model_flag(parser)
    parser.add_argument("--json", help="also write the figures (fractions) to this JSON file; an undefined "
                        "figure is null")
    parser.add_argument("--visibility", choices=VISIBILITY, default="hpr",
                        help="how the sets' beds become points (as synth --visibility)")
    parser.add_argument("--height", choices=["free", "fixed"], default="free",
                        help="cap height: fitted (default) or the paper's fixed s_z = 2 s / 3")
    parser.add_argument("--axis", choices=["surface", "encoding"], default="surface",
                        help="cap axis: the encoding's refined by the cap's surface (default), or the "
                        "encoding's alone, as in the paper")
    parser.add_argument("--radius", choices=["rim", "fit"], default="rim",
                        help="cap radius and height: of the dome fitted to the cap's own points (default), or "
                        "the pose fit's ellipsoid's, as in the paper")
    parser.add_argument("--spacing", type=parse_spacing,
                        help=f"the same beds at this point spacing in metres (default {SPACING_HELP}; "
                             "e.g. 0.0051 for 5.1 mm sets)")
    parser.add_argument("--zoom", type=parse_zoom, help="scale the network reads clouds at (default: the one the "
                        f"weights record, {SHIPPED_ZOOM} for the shipped model, 1.1 for weights that record none; "
                        "lowered for beds sparser than the training beds)")
    parser.add_argument("--readings", type=parse_readings, metavar="N",
                        help="read each bed N times, turned about the vertical, and average what the network "
                             f"sees (default {FILE_READINGS}, as detect reads; the paper's tables read once)")
    parser.add_argument("--scenes", type=positive(int), help="only the first N scenes of each set")
    parser.add_argument("--table", nargs="+", choices=["1", "2", "3", "4", "all"],
                        help="the paper's tables instead (section 4.2), ours beside its figures with ms per bed: "
                             "1 RANSAC template matching, 2 implicit vs explicit encodings (needs --encodings), "
                             "3 DBSCAN vs MeanShift, 4 scale and angle errors with ICP refinement")
    parser.add_argument("--encodings", help="--table 2: the folder of the three encodings' training runs "
                        "(python bench/encodings.py --out DIR makes them)")
    add_quiet_flag(parser, "no progress bars")
    add_overwrite_flag(parser)
    add_ray_flag(parser, "read the beds as Ray tasks (the same figures as here)")


def eval_table(name: str, results: dict) -> str:
    """Each metric of ``results`` (per clustering method) beside the paper's."""
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


def run(args: argparse.Namespace) -> int:
    from perception.evaluate import evaluate_on_scenes
    from perception.synthetic.dataset import load_preset, preset_config

    if args.table and args.readings is not None:
        raise CliError("--table reads each bed once, as the paper does: drop --readings")
    readings = args.readings or FILE_READINGS
    json_path = writable_file(args.json, inputs=(model_path(args.model),))
    model, meta = load_model(args.model)
    refuse_to_replace([json_path], args.overwrite)
    if args.table:
        return _paper_tables(args, model, json_path)
    zoom = args.zoom
    read_at = (f"zoom {zoom:g}" if zoom is not None else f"zoom {model.inference_zoom:g}, lower where sparser") + \
        (f", {readings} turned readings averaged" if readings > 1 else "")
    report = {}
    for name in args.set:
        try:
            scenes = load_preset(name, args.visibility, progress=not args.quiet, limit=args.scenes,
                                 spacing=args.spacing)
        except ValueError as error:
            raise CliError(str(error)) from None
        results = evaluate_on_scenes(model, scenes, height=args.height, axis=args.axis, radius=args.radius,
                                     progress=not args.quiet,
                                     zoom=zoom, readings=readings, **ray_options(args))
        label = name + (f" at {1000 * args.spacing:g} mm spacing" if args.spacing else "") + \
            f", read at {read_at}" + \
            (f" (first {len(scenes)} scenes)" if args.scenes else "")
        print(eval_table(label, results))
        spacing = preset_config(name, args.visibility, args.spacing).spacing
        report[name] = {method: {**result.as_dict(), "spacing": spacing, "zoom": zoom or model.inference_zoom,
                                 "zoom_lowered_where_sparser": zoom is None,
                                 "readings": readings}
                        for method, result in results.items()}
    if json_path is not None:
        replace_file(json_path, json_text(report))
    return 0


def _paper_tables(args: argparse.Namespace, model, json_path) -> int:
    """``--table``: the paper's tables on each set, printed as Markdown (and in ``--json``)."""
    from perception.paper_tables import TABLES, format_tables, run_tables
    from perception.synthetic.dataset import load_preset

    tables = TABLES if "all" in args.table else tuple(sorted({int(t) for t in args.table}))
    encodings = _encoding_models(args.encodings) if 2 in tables else None
    report = {}
    for name in args.set:
        scenes = load_preset(name, args.visibility, progress=not args.quiet, limit=args.scenes, spacing=args.spacing)
        label = name + (f", first {len(scenes)} beds" if args.scenes else f", {len(scenes)} beds")
        rows = run_tables(model, scenes, tables, progress=not args.quiet, encoding_models=encodings)
        print(format_tables(label, rows), flush=True)
        report[name] = {str(number): [row.as_dict() for row in table] for number, table in rows.items()}
    if json_path is not None:
        replace_file(json_path, json_text(report))
    return 0


def _encoding_models(folder: str | None) -> dict:
    """Table 2's networks: ``<folder>/<preset>/model.pt`` for each encoding."""
    from pathlib import Path

    from perception.paper_tables import ENCODING_RUNS

    if folder is None:
        raise CliError("--table 2 needs --encodings DIR: the three encodings' runs "
                       "(python bench/encodings.py --out DIR makes them)")
    models = {}
    for encoding, preset in ENCODING_RUNS.items():
        path = Path(folder) / preset / "model.pt"
        if not path.is_file():
            raise CliError(f"{path} does not exist: train it with python bench/encodings.py --out {folder}")
        models[encoding] = load_model(str(path))[0]
    return models
