"""Capture speed: virtual depth camera frames per second at 848x480, MCAP write and replay rates, and
the size of a 10 s recording (150 frames at 15 fps). Target: the virtual camera at >= 15 fps.
Usage: python bench/capture.py [--frames 150] [--out DIR]
"""

import sys
from pathlib import Path

# bench/capture.py would shadow the capture package: take this folder off the import path
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import argparse  # noqa: E402
import resource  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from capture.mcap.reader import McapSource  # noqa: E402
from capture.mcap.writer import McapRecorder  # noqa: E402
from capture.virtual import sense_view  # noqa: E402
from capture.virtual import VirtualCameraConfig  # noqa: E402
from pipeline.sources import VirtualBed, virtual_bed_source  # noqa: E402
from pipeline.process import reuse_freed_memory  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    reuse_freed_memory()
    source, _ = virtual_bed_source(VirtualBed(camera=VirtualCameraConfig(views=args.frames)))
    frames, render_s = [], []
    with source:
        while True:
            start = time.perf_counter()
            frame = source.read()
            if frame is None:
                break
            render_s.append(time.perf_counter() - start)
            frames.append(frame)
        steady = np.median(render_s[1:])
        print(f"virtual camera 848x480: median {1000 * steady:.1f} ms/frame = {1 / steady:.1f} fps "
              f"(first frame with scene build {1000 * render_s[0]:.0f} ms); target >= 15 fps")
        cast_s, sensor_s = [], []
        for index in range(0, len(source), max(1, len(source) // 20)):
            T_world_camera, _ = source.config.pose(index)
            start = time.perf_counter()
            render = source._scene.render(source.config.intrinsics, T_world_camera)
            middle = time.perf_counter()
            sense_view(render, source.config, index)
            cast_s.append(middle - start)
            sensor_s.append(time.perf_counter() - middle)
        print(f"  of which rendering (Open3D rays and cast_rays, incidence) {1000 * np.median(cast_s):.1f} ms, "
              f"sensor model and frame {1000 * np.median(sensor_s):.1f} ms")
    out_dir = args.out or Path(tempfile.mkdtemp())
    for compression in ("zstd", "lz4", None):
        path = out_dir / f"session-{compression or 'none'}.mcap"
        start = time.perf_counter()
        with McapRecorder(path, compression, overwrite=True) as recorder:
            for frame in frames:
                recorder.write(frame)
        write_s = time.perf_counter() - start
        start = time.perf_counter()
        with McapSource(path) as replay:
            count = sum(1 for _ in replay)
        read_s = time.perf_counter() - start
        size = path.stat().st_size
        seconds = len(frames) / 15.0
        print(f"MCAP {compression or 'none':<5}: {len(frames)} frames ({seconds:.0f} s at 15 fps) {size / 1e6:6.1f} MB "
              f"= {size / 1e6 / seconds:5.2f} MB/s of recording; write {len(frames) / write_s:6.1f} fps, "
              f"replay {count / read_s:6.1f} fps")
    print(f"peak RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
