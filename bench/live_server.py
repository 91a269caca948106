"""Whether Foxglove clients cost a live run anything: ``live --camera virtual --serve-foxglove`` for
``--turns`` turns, once with no client, once with a client that reads everything and once with a client
that subscribes to every channel and never reads (its socket buffers stay full). Each run's frames
recorded, the largest gap between consecutive recorded frames (a frame lost at the source shows as a
gap of two frame periods), the frames and units dropped, the median time from a turn's last frame to
its caps, and the live process's wall time.

Usage: python bench/live_server.py [--turns 3] [--views 6]   (needs the websockets package)
"""

import sys
from pathlib import Path

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import argparse  # noqa: E402
import asyncio  # noqa: E402
import json  # noqa: E402
import re  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import websockets  # noqa: E402

from capture.mcap.reader import McapSource  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SUBPROTOCOL = "foxglove.sdk.v1"


async def client(url: str, reads: bool, stop: threading.Event) -> int:
    """Subscribe to each channel as advertised; with ``reads`` keep reading until the server goes,
    without, stop reading once the depth images are subscribed. The bytes received."""
    received = 0
    async with websockets.connect(url, subprotocols=[SUBPROTOCOL], max_queue=None if reads else 1,
                                  max_size=None) as connection:
        depth = False
        try:
            while reads or not depth:
                message = await connection.recv()
                received += len(message)
                if isinstance(message, str) and json.loads(message)["op"] == "advertise":
                    channels = json.loads(message)["channels"]
                    depth = depth or any(c["topic"].endswith("/depth") for c in channels)
                    await connection.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": c["id"], "channelId": c["id"]} for c in channels]}))
            while not stop.is_set():
                await asyncio.sleep(0.05)
        except websockets.ConnectionClosed:
            pass
    return received


def one_run(kind: str, turns: int, views: int, out: Path) -> dict:
    record = out / f"{kind}.mcap"
    command = [sys.executable, "-m", "pipeline.cli", "live", "--camera", "virtual", "--views", str(views),
               "--turns", str(turns), "--serve-foxglove", "127.0.0.1:0", "--record", str(record)]
    start = time.perf_counter()
    process = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    url = process.stdout.readline().split()[-1]
    stop = threading.Event()
    received, ended = 0, None
    if kind != "none":
        async def run_client():
            nonlocal received, ended
            task = asyncio.create_task(client(url, kind == "reading", stop))
            while process.poll() is None:
                await asyncio.sleep(0.05)
            ended = time.perf_counter()
            stop.set()
            received = await task

        asyncio.run(run_client())
    process.wait()
    ended = ended or time.perf_counter()
    stdout, stderr = process.communicate()
    seconds = ended - start
    latencies = [float(v) for v in re.findall(r"last frame to caps ([\d.]+) s", stderr)]
    summary = re.search(r"(\d+) frames and (\d+) units dropped", stdout)
    with McapSource(record) as session:
        stamps = np.array([frame.timestamp_ns for frame in session])
    return {"frames": len(stamps), "gap": float(np.diff(stamps).max() / (1e9 / 15)),
            "dropped": f"{summary[1]} frames, {summary[2]} units", "latency": statistics.median(latencies),
            "seconds": seconds, "received_mb": received / 1e6}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--turns", type=int, default=3)
    parser.add_argument("--views", type=int, default=6)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as out:
        print(f"{'client':<9} {'frames':>6} {'max gap':>8} {'dropped':>18} {'turn->caps':>10} {'wall':>7} "
              f"{'received':>9}")
        for kind in ("none", "reading", "stalled"):
            row = one_run(kind, args.turns, args.views, Path(out))
            print(f"{kind:<9} {row['frames']:>6} {row['gap']:>7.2f}T {row['dropped']:>18} {row['latency']:>9.2f}s "
                  f"{row['seconds']:>6.1f}s {row['received_mb']:>7.1f}MB", flush=True)
    print("T: one frame period (1/15 s); a gap of 2T or more is a frame lost at the source")


if __name__ == "__main__":
    main()
