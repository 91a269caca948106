"""Table 2's networks: the implicit encoding and the paper's two explicit ablations, trained with one
recipe, seed and budget (``mushroom-pose train``, resumable), for ``mushroom-pose eval --table 2
--encodings DIR``. The recipe is the shipped model's first stage at a shorter schedule; the table's
implicit row is this run, not the shipped model.
Usage: python bench/encodings.py --out DIR [--iterations 800]
"""

import argparse
import subprocess
import sys
from pathlib import Path

RUNS = ("slim-no", "slim-no-explicit-centre", "slim-no-explicit-orientation")
"""perception.paper_tables.ENCODING_RUNS, without importing the project (this script only starts runs)."""
RECIPE = ["--weight-orientation", "10", "--orientation-on-caps", "--validation-scenes", "0", "--seed", "0",
          "--threads", "1"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--iterations", type=int, default=800)
    args = parser.parse_args()
    command = [str(Path(sys.executable).with_name("mushroom-pose")), "train"]
    for preset in RUNS:
        run = args.out / preset
        if (run / "model.pt").is_file():
            print(f"{run}: done")
            continue
        resume = ["--resume"] if (run / "checkpoint.pt").is_file() else []
        print(f"{run}: training {preset} for {args.iterations} iterations", flush=True)
        subprocess.run(command + ["--out", str(run), "--network", preset, "--iterations", str(args.iterations),
                                  *RECIPE, *resume], check=True)


if __name__ == "__main__":
    main()
