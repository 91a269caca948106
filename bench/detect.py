"""How long ``mushroom-pose detect`` takes on a cloud, as a user runs it, and where the time goes.

The command runs ``--runs`` times in a fresh process each (wall time, start-up and imports included);
the median, the fastest and the slowest are printed, with ``mushroom-pose --help`` beside them for the
start-up alone. One more run in a child process times each stage: the imports the command pulls in
(numpy, SciPy, scikit-learn, the project; it prints which of torch, Open3D, scikit-learn and SciPy
the command loaded), then its library calls (loading the weights and the cloud, the bed plane, the up
side, the surface noise, each pass of the network, clustering, pose fit, writing), so the stages and their sum can be
set against the wall time.

Usage: python bench/detect.py --cloud example_0.pcd [--runs 5] [--detect-arg=--readings --detect-arg=1]
"""

import sys
from pathlib import Path

# the bench folder holds fusion.py and perception.py, which would shadow those packages
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

REPO = Path(__file__).resolve().parent.parent

STAGE_TIMER = r'''
import json, sys, time
marks = {}
start = time.perf_counter()

def timed(module, name, stage):
    import importlib
    owner = importlib.import_module(module)
    inner = getattr(owner, name)
    def wrapper(*args, **kwargs):
        began = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            marks.setdefault(stage, []).append(time.perf_counter() - began)
    setattr(owner, name, wrapper)

for module in ("numpy", "scipy.spatial", "sklearn.cluster"):
    began = time.perf_counter()
    __import__(module)
    marks["import " + module] = [time.perf_counter() - began]
began = time.perf_counter()
import pipeline.cli, pipeline.commands.detect, perception.detect, perception.plan, fusion.bed, pipeline.clouds
marks["import project"] = [time.perf_counter() - began]
# each pass of the network, and the calls the command makes, by the name of its stage
timed("perception.detect", "network_output", "network passes")
timed("perception.detect", "voxel_features", "voxel normals and offsets (within the passes)")
timed("pipeline.commands.detect", "load_model", "weights")
timed("pipeline.clouds", "load_cloud", "load cloud")
timed("fusion.bed", "estimate_bed_frame", "bed plane")
timed("fusion.bed", "side_with_caps", "up side (network, each side read at most once)")
timed("perception.detect", "smoothed", "surface noise (smoothing a noisy cloud)")
timed("perception.detect", "predict", "predict")
timed("perception.detect", "find_caps", "clustering and pose")
timed("pipeline.commands.detect", "replace_file", "write detections")
code = pipeline.cli.main(sys.argv[1:])
marks["total in process"] = [time.perf_counter() - start]
loaded = [name for name in ("torch", "open3d", "sklearn", "scipy") if name in sys.modules]
print(json.dumps({"code": code, "marks": marks, "loaded": loaded}), file=sys.stderr)
'''


def wall_times(command: list[str], runs: int) -> list[float]:
    """Seconds of ``command`` run ``runs`` times, each in a fresh process; a failed run stops the bench."""
    seconds = []
    for _ in range(runs):
        start = time.perf_counter()
        done = subprocess.run(command, cwd=REPO, capture_output=True, text=True)
        seconds.append(time.perf_counter() - start)
        if done.returncode != 0:
            sys.exit(f"{' '.join(command)} failed: {done.stderr.strip().splitlines()[-1:]}")
    return seconds


def stage_split(detect: list[str]) -> tuple[dict[str, list[float]], list[str]]:
    """Seconds per stage of one ``detect`` run in a child process (``STAGE_TIMER``), and which of the
    heavy libraries it loaded."""
    done = subprocess.run([sys.executable, "-c", STAGE_TIMER, *detect], cwd=REPO, capture_output=True, text=True)
    report = json.loads(done.stderr.strip().splitlines()[-1])
    if report["code"] != 0:
        sys.exit(f"detect failed in the timed run: {done.stderr.strip().splitlines()[-2:]}")
    return report["marks"], report["loaded"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cloud", required=True, help="the cloud file detect reads (.pcd, .ply, .npz, .mcap)")
    parser.add_argument("--runs", type=int, default=5, help="wall-time runs of the command (default 5)")
    parser.add_argument("--detect-arg", action="append", default=[], help="one more argument for detect")
    args = parser.parse_args()
    cloud = str(Path(args.cloud).resolve())
    with tempfile.TemporaryDirectory() as scratch:
        detect = ["detect", cloud, "--out", str(Path(scratch) / "detections.json"), "--overwrite", *args.detect_arg]
        walls = wall_times([sys.executable, "-m", "pipeline.cli", *detect], args.runs)
        helps = wall_times([sys.executable, "-m", "pipeline.cli", "--help"], args.runs)
        marks, loaded = stage_split(detect)
    print(f"detect {Path(cloud).name} {' '.join(args.detect_arg)}".rstrip())
    print(f"  wall, {args.runs} runs: median {statistics.median(walls):.2f} s (fastest {min(walls):.2f}, "
          f"slowest {max(walls):.2f})")
    print(f"  mushroom-pose --help: median {statistics.median(helps):.3f} s")
    print("  one run, by stage (s):")
    for stage, seconds in marks.items():
        calls = f" ({len(seconds)} calls)" if len(seconds) > 1 else ""
        print(f"    {stage:48s} {sum(seconds):6.2f}{calls}")
    imports = sum(sum(seconds) for stage, seconds in marks.items() if stage.startswith("import"))
    print(f"  libraries the command loaded: {', '.join(loaded) or 'none of torch, Open3D, scikit-learn, SciPy'}")
    print(f"  imports {imports:.2f} s of {sum(marks['total in process']):.2f} s in process "
          "(passes of the network are counted once in 'network passes' and again within their stages)")


if __name__ == "__main__":
    main()
