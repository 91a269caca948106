"""How long ``mushroom-pose report`` takes on a farm's worth of sessions, as a user runs it.

The project's recorded sessions (``recordings/*.mcap``) are copied round-robin into ``--sessions``
files, and the report over all of them runs ``--runs`` times in a fresh process each (start-up
included); the median, fastest and slowest wall times are printed.

Usage: python bench/report.py [--sessions 20] [--runs 3]
"""

import sys
from pathlib import Path

# the bench folder holds fusion.py and perception.py, which would shadow those packages
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import argparse  # noqa: E402
import shutil  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=20)
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    recordings = sorted((REPO / "recordings").glob("*.mcap"))
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch) / "sessions"
        folder.mkdir()
        for k in range(args.sessions):
            shutil.copy(recordings[k % len(recordings)], folder / f"bed-{k:02d}.mcap")
        command = [sys.executable, "-m", "pipeline.cli", "report", str(folder), "--out", str(Path(scratch) / "r.html"),
                   "--overwrite"]
        seconds = []
        for _ in range(args.runs):
            started = time.perf_counter()
            subprocess.run(command, check=True, capture_output=True, cwd=REPO)
            seconds.append(time.perf_counter() - started)
    print(f"report on {args.sessions} sessions ({len(recordings)} recordings round-robin), {args.runs} runs: "
          f"median {statistics.median(seconds):.2f} s (fastest {min(seconds):.2f}, slowest {max(seconds):.2f}); "
          "target 30 s")


if __name__ == "__main__":
    main()
