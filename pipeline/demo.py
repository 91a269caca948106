"""``mushroom-pose demo``: the whole chain with no hardware and no download.

A virtual D405 on a virtual turntable circles a synthetic bed; every frame is recorded to MCAP and shown
in Rerun; the turn is fused (encoder prior refined by ICP, merged depth) and the shipped model finds the caps.
Because the bed is synthetic, the demo also scores its detections against the truth.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path


@dataclass(frozen=True)
class DemoResult:
    detections: Path
    recording: Path
    rrd: Path | None
    caps_found: int
    caps_true: int
    ap25: float
    ap50: float
    angle_deg: float
    seconds: dict[str, float]


def run_demo(out_dir: Path, model, seed: int = 0, views: int = 18, rrd: bool = True, spawn: bool = False,
             progress: bool = True) -> DemoResult:
    """Run the chain into ``out_dir``: session.mcap, detections.json and (``rrd``) demo.rrd appear
    together when the run succeeds; an interrupted or failed run leaves the folder as it was."""
    staging = Path(tempfile.mkdtemp(prefix=".demo-", dir=out_dir))
    try:
        result = _run(staging, model, seed, views, rrd, spawn, progress)
        moved = {}
        for name in ("session.mcap", "detections.json", "demo.rrd"):
            if (staging / name).exists():
                os.replace(staging / name, out_dir / name)
                moved[name] = out_dir / name
        return replace(result, detections=moved["detections.json"], recording=moved["session.mcap"],
                       rrd=moved.get("demo.rrd"))
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _run(folder: Path, model, seed: int, views: int, rrd: bool, spawn: bool, progress: bool) -> DemoResult:
    from tqdm import tqdm

    from capture.frames import log_rerun as log_frame
    from capture.mcap_io import DETECTIONS_TOPIC, FUSED_CLOUD_TOPIC, McapRecorder
    from fusion.cloud import Fuser, FusionConfig, log_rerun as log_fused
    from fusion.turntable import Rig
    from perception.cap import detections_json
    from perception.detect import detect_points, log_rerun as log_detections, transform_result
    from perception.evaluate import SceneCaps, evaluate
    from pipeline.rerun_sink import default_blueprint, rerun_stream, set_frame
    from pipeline.sources import VirtualBedRig, virtual_bed_source

    seconds: dict[str, float] = {}
    start = time.perf_counter()
    source, bed = virtual_bed_source(VirtualBedRig(seed=seed, views=views))
    fuser = Fuser(FusionConfig(angles="encoder"), Rig(source.config.turntable))
    recording = folder / "session.mcap"
    detections_path = folder / "detections.json"
    rrd = folder / "demo.rrd" if rrd else None
    fused = None
    with rerun_stream(rrd, spawn=spawn, blueprint=default_blueprint([source.config.sensor_id])) as rec, \
            McapRecorder(recording, overwrite=True) as recorder, source:
        seconds["scene"] = time.perf_counter() - start
        render_s = fuse_s = 0.0
        for index in tqdm(range(len(source)), desc="turntable", unit="view", disable=not progress):
            tick = time.perf_counter()
            frame = source.read()
            render_s += time.perf_counter() - tick
            recorder.write(frame)
            if rec is not None:
                set_frame(rec, index, frame.timestamp_ns)
                log_frame(rec, frame)
            tick = time.perf_counter()
            completed = fuser.add(frame)
            fused = completed if completed is not None else fused
            fuse_s += time.perf_counter() - tick
        if fused is None:
            fused = fuser.flush()
        seconds["render"], seconds["fusion"] = render_s, fuse_s
        tick = time.perf_counter()
        result = transform_result(detect_points(model, fused.points), fused.T_world_bed, "world")
        seconds["perception"] = time.perf_counter() - tick
        log_time = frame.timestamp_ns
        recorder.write_point_cloud(FUSED_CLOUD_TOPIC, fused.world_points, log_time)
        document = json.loads(detections_json(result.mushrooms, "world"))
        recorder.write_json(DETECTIONS_TOPIC, document, log_time)
        if rec is not None:
            log_fused(rec, fused)
            log_detections(rec, result, fused.world_points)
    detections_path.write_text(json.dumps(document, indent=1))
    score = evaluate([SceneCaps(result.fit.centers, result.fit.rotations, result.fit.scales, result.fit.scores)],
                     [SceneCaps(bed.centers, bed.rotations, bed.scales)])
    return DemoResult(detections_path, recording, rrd, len(result.mushrooms), len(bed.centers), score.ap25,
                      score.ap50, score.angle_deg, seconds)
