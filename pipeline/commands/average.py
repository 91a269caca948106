"""``mushroom-pose average``: the mean of the weights of models fine-tuned from one start (a model soup)."""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.commands.common import CliError, CommandFailed, add_overwrite_flag, refuse_to_replace, writable_file

NAME = "average"
HELP = "average the weights of models fine-tuned from one start (a model soup)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("weights", nargs="+", help="two or more model.pt files that share a start (--init)")
    parser.add_argument("--out", required=True, help="the weights file (.pt) to write")
    add_overwrite_flag(parser)


def run(args: argparse.Namespace) -> int:
    from perception.weights import WeightsWriteError, average_weights, save_weights

    for path in args.weights:
        if not Path(path).is_file():
            raise CliError(f"no weights file at {path}")
    out = writable_file(args.out, inputs=tuple(args.weights), suffix=".pt")
    refuse_to_replace([out], args.overwrite)
    try:
        model, meta = average_weights([Path(path) for path in args.weights])
    except ValueError as error:
        raise CliError(str(error)) from None
    try:
        save_weights(model, out, **meta)
    except WeightsWriteError as error:
        raise CommandFailed(f"{error}; no weights were written") from None
    print(f"averaged {len(args.weights)} models, {len(meta['runs'])} training runs behind them, "
          f"{meta['total_iterations']} iterations in {meta['total_train_seconds'] / 60:.1f} min: {out}")
    return 0
