"""The product chain's speed and stamina (capture -> fusion -> perception -> sinks, pipeline/runner.py).

- realtime: turns of an 18-view virtual turntable (848x480, 15 fps) recorded to MCAP, then replayed at
  their recorded pace as ``replay --speed realtime`` does; prints frames dropped at the source and the
  latency from each turn's last frame to its detections (median, quartiles).
- max: the same session replayed as fast as the chain runs (``--speed max``), frames per second, against
  the batch chain (every frame read, then ``fuse`` on the turn, then ``detect_points``) in the same run.
- soak (``--soak-minutes M``): virtual turns streamed through the runner at the camera's pace
  (``--soak-speed``, 0: as fast as the chain runs), recorded to a scratch MCAP, for M minutes; prints
  RSS (this process and its children) every minute, the first and last 10 minutes' peaks, turns fused
  and detected, and frames recorded against frames captured.

Usage: python bench/pipeline.py [--turns 20] [--soak-minutes 0 [--soak-speed 1]] [--threads 2] [--readings N]
(--turns 0 runs the soak alone)
"""

import sys
from pathlib import Path

# the bench folder holds fusion.py and perception.py, which would shadow those packages
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from pipeline.process import let_idle_threads_sleep, reuse_freed_memory  # noqa: E402

let_idle_threads_sleep()  # as live and replay do, before torch and Open3D load

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from capture.mcap.reader import McapSource  # noqa: E402
from capture.mcap.writer import McapRecorder  # noqa: E402
from capture.source import Source  # noqa: E402
from perception.detect import LIVE_READINGS, detect_points  # noqa: E402
from perception.weights import DEFAULT_WEIGHTS  # noqa: E402
from perception.weights import load_weights  # noqa: E402
from capture.virtual import VirtualCameraConfig  # noqa: E402
from pipeline.sources import VirtualBed, virtual_bed_source  # noqa: E402

FPS = 15.0
VIEWS = 18


def turn_frames(seed: int, start_ns: int):
    """One 18-view turn over bed ``seed``, its clock starting at ``start_ns``."""
    camera = VirtualCameraConfig(views=VIEWS, fps=FPS, start_ns=start_ns)
    source, _ = virtual_bed_source(VirtualBed(seed=seed, camera=camera))
    with source:
        return list(source)


def record_session(path: Path, turns: int) -> None:
    """``turns`` consecutive turns (beds 100, 101, ...) in one MCAP."""
    frames, start = [], 0
    for turn in range(turns):
        frames += turn_frames(100 + turn, start)
        start = frames[-1].timestamp_ns + int(1e9 / FPS)
    with McapRecorder(path) as recorder:
        for frame in frames:
            recorder.write(frame)


def replay(session: Path, model, realtime: bool, out: Path, readings: int):
    from pipeline.replay import ReplayOptions, run_replay
    from pipeline.runner import PerceptionStage

    out.mkdir()
    started = time.perf_counter()
    options = ReplayOptions(speed="realtime" if realtime else "max", perception=PerceptionStage(readings=readings),
                            readings_as_recorded=False)
    result = run_replay(session, model, out, None, options, quiet=True)
    return result.summary, time.perf_counter() - started


def batch_chain(session: Path, model, readings: int) -> tuple[int, float]:
    """The chain as the demo ran it before the runner: read a whole turn, fuse it, detect."""
    from fusion.cloud import FusionConfig, fuse

    started = time.perf_counter()
    with McapSource(session) as source:
        frames = list(source)
    for turn in range(0, len(frames), VIEWS):
        cloud = fuse(frames[turn:turn + VIEWS], FusionConfig(angles="pose"))
        detect_points(model, cloud.points, readings=readings)
    return len(frames), time.perf_counter() - started


def rss_mb() -> float:
    """Resident memory of this process and its children (a live run perceives in a child), MB."""
    children = []
    for task in Path("/proc/self/task").iterdir():
        children += (task / "children").read_text().split()
    total = 0.0
    for pid in ["self", *children]:
        try:
            with open(f"/proc/{pid}/status") as status:
                total += next((int(line.split()[1]) for line in status if line.startswith("VmRSS:")), 0) / 1024
        except FileNotFoundError:  # a child that has just ended
            continue
    return total


class CyclingTurns(Source):
    """Virtual turns over a few beds, repeated with a clock that keeps running, until stopped."""

    def __init__(self, beds: int = 3):
        self.turns = [turn_frames(200 + bed, 0) for bed in range(beds)]
        self.stop = threading.Event()
        self.count = 0

    def read(self):
        if self.stop.is_set():
            return None
        turn = self.turns[(self.count // VIEWS) % len(self.turns)]
        frame = dataclasses.replace(turn[self.count % VIEWS], timestamp_ns=int(self.count * 1e9 / FPS))
        self.count += 1
        return frame


def soak(model, minutes: float, speed: float, folder: Path, readings: int) -> None:
    from capture.source import Paced
    from pipeline.runner import PerceptionStage, RunConfig, Runner
    from pipeline.sinks import McapSink

    source = CyclingTurns()
    recorder = McapRecorder(folder / "soak.mcap", chunk_size=4 << 20)
    runner = Runner(Paced(source, speed) if speed > 0 else source, model,
                    RunConfig(perception=PerceptionStage(readings=readings), live=True), [McapSink(recorder)])
    samples: list[tuple[float, float]] = []
    started = time.monotonic()

    def watch() -> None:
        while not source.stop.is_set():
            elapsed = time.monotonic() - started
            samples.append((elapsed, rss_mb()))
            if int(elapsed) % 60 < 5 and elapsed > 5:
                print(f"  {elapsed / 60:5.1f} min  RSS {samples[-1][1]:7.1f} MB  frames {source.count}  "
                      f"turns detected {len(runner.summary.detections)}", flush=True)
            if elapsed >= 60 * minutes:
                source.stop.set()
            time.sleep(5)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    summary = runner.run()
    watcher.join()
    with McapSource(folder / "soak.mcap") as recorded:
        frames_recorded = sum(1 for _ in recorded)
    (folder / "soak.mcap").unlink()
    times, rss = np.array([t for t, _ in samples]), np.array([r for _, r in samples])
    first = rss[times <= 600].max()
    last = rss[times >= times.max() - 600].max()
    print(f"soak at {'max speed' if speed <= 0 else f'{speed:g}x the camera pace'}: {times.max() / 60:.1f} min, {summary.frames} frames captured, {frames_recorded} recorded, "
          f"{summary.units} turns fused, {len(summary.detections)} detected, {summary.dropped_frames} frames and "
          f"{summary.dropped_units} turns dropped before fusion/perception")
    print(f"peak RSS: first 10 min {first:.1f} MB, last 10 min {last:.1f} MB (ratio {last / first:.3f})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--turns", type=int, default=20)
    parser.add_argument("--model", type=Path, default=DEFAULT_WEIGHTS)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--soak-minutes", type=float, default=0.0)
    parser.add_argument("--soak-speed", type=float, default=1.0)
    parser.add_argument("--readings", type=int, default=LIVE_READINGS,
                        help=f"readings per fused turn (default {LIVE_READINGS}, as the runner reads)")
    args = parser.parse_args()
    reuse_freed_memory()
    torch.set_num_threads(args.threads)
    model, _ = load_weights(args.model)
    with tempfile.TemporaryDirectory(prefix="bench-pipeline-") as scratch:
        folder = Path(scratch)
        if args.turns == 0:
            soak(model, args.soak_minutes, args.soak_speed, folder, args.readings)
            return
        session = folder / "session.mcap"
        record_session(session, args.turns)
        print(f"session: {args.turns} turns of {VIEWS} views, 848x480 at {FPS:g} fps, "
              f"{session.stat().st_size / 1e6:.1f} MB")
        summary, wall = replay(session, model, realtime=True, out=folder / "realtime", readings=args.readings)
        latency = np.array([d.latency_seconds for d in summary.detections])
        perception = np.array([d.perception_seconds for d in summary.detections])
        fusion = np.array([d.fusion_seconds for d in summary.detections])
        print(f"realtime: {summary.frames} frames in {wall:.1f} s, {summary.dropped_frames} dropped at the source, "
              f"{summary.dropped_units} turns dropped before perception, {len(latency)} of {args.turns} turns "
              f"detected")
        print(f"  last frame to detections: median {np.median(latency):.2f} s (quartiles "
              f"{np.percentile(latency, 25):.2f}-{np.percentile(latency, 75):.2f}); of which the turn's last fusion "
              f"step {np.median(fusion):.2f} s and perception {np.median(perception):.2f} s (medians)")
        summary, wall = replay(session, model, realtime=False, out=folder / "max", readings=args.readings)
        count, batch_wall = batch_chain(session, model, args.readings)
        print(f"max speed: runner {summary.frames / wall:.1f} frames/s ({wall:.1f} s), batch chain "
              f"{count / batch_wall:.1f} frames/s ({batch_wall:.1f} s): the runner takes "
              f"{wall / batch_wall:.2f}x the batch chain's time")
        print(f"peak RSS so far {rss_mb():.0f} MB (current)")
        if args.soak_minutes > 0:
            soak(model, args.soak_minutes, args.soak_speed, folder, args.readings)


if __name__ == "__main__":
    main()
