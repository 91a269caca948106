"""Replaying a farm's sessions: in one process, on a local Ray, and on a local Ray cluster.

20 sessions (the recordings/ sessions, repeated) are replayed with ``--check`` as ``mushroom-pose replay
SESSIONS...`` does (pipeline/farm.py): one after another in this process, then as Ray tasks on a local
Ray (``ray.init``), then on a cluster started here with ``ray start`` (a head on 127.0.0.1 and worker
processes joining it, stopped at the end). Prints the wall time of each and their ratios, and the cost
model per session (seconds, MB read and written) with what N machines do for a farm of B beds a day.
Then a short training run (the default recipe) the same three ways: its beds made in a worker process,
as Ray tasks, and on the cluster's workers; prints the wall times and whether the weights are identical.
Usage: python bench/scale.py [--session-count 20] [--workers 2] [--train-iterations 20] [--skip-cluster]
"""

import sys
from pathlib import Path

# the bench folder holds fusion.py and perception.py, which would shadow those packages
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import argparse  # noqa: E402
import os  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from perception.weights import DEFAULT_WEIGHTS  # noqa: E402
from pipeline.check import Tolerances  # noqa: E402
from pipeline.farm import FarmJob, replay_sessions  # noqa: E402
from pipeline.replay import ReplayOptions  # noqa: E402

RECORDINGS = Path(__file__).resolve().parents[1] / "recordings"
PORT = 6391


def make_sessions(folder: Path, count: int) -> list[Path]:
    """``count`` session files: the recordings cycled (with their expected detections beside them)."""
    originals = sorted(p for p in RECORDINGS.iterdir() if p.suffix in (".mcap", ".db3"))
    sessions = []
    for k in range(count):
        original = originals[k % len(originals)]
        copy = folder / f"{k:02d}-{original.name}"
        os.symlink(original, copy)
        expected = original.with_name(original.stem + ".expected.json")
        if expected.exists():
            os.symlink(expected, copy.with_name(copy.stem + ".expected.json"))
        sessions.append(copy)
    return sessions


def run(sessions: list[Path], out: Path, use_ray: bool, address: str | None = None):
    job = FarmJob(str(DEFAULT_WEIGHTS), str(out), ReplayOptions(), Tolerances())
    started = time.perf_counter()
    outcomes = replay_sessions(sessions, job, ray_address=address, use_ray=use_ray)
    wall = time.perf_counter() - started
    failed = [o for o in outcomes if not o.passed]
    if failed:
        raise SystemExit(f"{len(failed)} sessions failed or changed, e.g. {failed[0].session}: {failed[0].error}")
    return wall, outcomes


def train_run(folder: Path, iterations: int, address: str | None) -> tuple[float, dict]:
    """Wall time and final weights of a short run of the default recipe, its beds made as ``address`` says
    (None: a worker process; "local" or a cluster's address: Ray tasks)."""
    from perception.train import TrainConfig, train
    from perception.weights import load_weights

    config = TrainConfig(iterations=iterations, checkpoint_every=iterations, validation_scenes=0)
    started = time.perf_counter()
    weights = train(config, folder, progress=False, ray_address=address)
    return time.perf_counter() - started, load_weights(weights)[0].state_dict()


def print_walls(title: str, walls: dict[str, float]) -> None:
    base = next(iter(walls.values()))
    print(title)
    for name, wall in walls.items():
        print(f"  {name:<28} {wall:7.1f} s  ({wall / base:.2f}x the one-process run)")


def start_cluster(workers: int) -> str:
    """A head with no CPUs of its own and ``workers`` one-CPU worker processes joining it, on this
    machine only. Ray's token authentication is turned off for them and for this process (a head may
    turn it on while its workers and drivers do not, and then refuse them)."""
    os.environ["RAY_AUTH_MODE"] = "disabled"
    ray = shutil.which("ray", path=str(Path(sys.executable).parent)) or "ray"
    address = f"127.0.0.1:{PORT}"
    subprocess.run([ray, "start", "--head", "--node-ip-address", "127.0.0.1", "--port", str(PORT), "--num-cpus", "0",
                    "--include-dashboard", "false"], check=True, capture_output=True)
    for _ in range(workers):
        subprocess.run([ray, "start", "--address", address, "--num-cpus", "1"], check=True, capture_output=True)
    return address


def stop_cluster() -> None:
    ray = shutil.which("ray", path=str(Path(sys.executable).parent)) or "ray"
    subprocess.run([ray, "stop", "--force"], capture_output=True)


def megabytes(paths) -> float:
    return sum(p.stat().st_size for p in paths if p.is_file()) / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--session-count", type=int, default=20)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--train-iterations", type=int, default=20, help="0: no training runs")
    parser.add_argument("--skip-cluster", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-scale-") as scratch:
        folder = Path(scratch)
        (folder / "in").mkdir()
        sessions = make_sessions(folder / "in", args.session_count)
        walls, train_walls, weights = {}, {}, {}
        walls["in this process"], outcomes = run(sessions, folder / "local", use_ray=False)
        walls["local Ray"], _ = run(sessions, folder / "ray", use_ray=True)
        places = {"in this process": None, "local Ray": "local"}
        try:
            if not args.skip_cluster:
                cluster = f"local cluster, {args.workers} workers"
                places[cluster] = start_cluster(args.workers)
                walls[cluster], _ = run(sessions, folder / "cluster", True, places[cluster])
            for name, place in places.items() if args.train_iterations else ():
                train_walls[name], weights[name] = train_run(folder / f"train-{len(weights)}", args.train_iterations,
                                                             place)
        finally:
            if not args.skip_cluster:
                stop_cluster()
        print_walls(f"{args.session_count} sessions replayed with --check, {os.cpu_count()} cores:", walls)
        seconds = np.array([o.seconds for o in outcomes])
        read = megabytes(s.resolve() for s in sessions) / len(sessions)
        written = megabytes((folder / "local").rglob("*")) / len(sessions)
        print(f"per session: {np.median(seconds):.1f} s median (quartiles {np.percentile(seconds, 25):.1f}-"
              f"{np.percentile(seconds, 75):.1f}), {read:.1f} MB read, {written:.1f} MB written")
        per_core_hour = 3600 / float(np.median(seconds))
        print(f"cost model: one core replays {per_core_hour:.0f} sessions an hour; a farm recording B beds a day "
              "(one session a bed) needs, to replay a day's sessions within an hour:")
        for beds in (100, 1000, 10000):
            cores = beds / per_core_hour
            print(f"  B = {beds:>5}: {cores:6.1f} cores, {int(np.ceil(cores / 8)):>3} machines of 8 cores, "
                  f"{beds * (read + written) / 1e3:.1f} GB moved")
        if train_walls:
            print_walls(f"training, {args.train_iterations} iterations of the default recipe, its beds made:",
                        train_walls)
            first = next(iter(weights.values()))
            same = all(all(torch.equal(first[key], other[key]) for key in first) for other in weights.values())
            print(f"  the weights are {'identical' if same else 'NOT identical'} in all {len(weights)} runs")


if __name__ == "__main__":
    main()
