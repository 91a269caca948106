"""``mushroom-pose demo``: the whole chain with no hardware and no download.

A virtual D405 on a virtual turntable circles a synthetic bed; the runner records every frame to MCAP,
shows it in Rerun, fuses the turn (encoder prior refined by ICP, merged depth) and the shipped model
finds the caps. Because the bed is synthetic, the demo also scores its detections against the truth.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

OUTPUT_NAMES = ("session.mcap", "detections.json", "demo.rrd")


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


def run_demo(out_dir: Path, model, seed: int = 0, views: int = 18, rrd: bool = True, viewer=None,
             progress: bool = True) -> DemoResult:
    """Run the chain into ``out_dir``: session.mcap, detections.json and (``rrd``) demo.rrd appear
    together when the run succeeds; an interrupted or failed run leaves the folder as it was. A
    ``pipeline.viewer_target.ViewerTarget`` also shows the run in a viewer (its ``rrd`` is demo.rrd's)."""
    staging = Path(tempfile.mkdtemp(prefix=".demo-", dir=out_dir))
    try:
        result = _run(staging, model, seed, views, rrd, viewer, progress)
        for name in OUTPUT_NAMES:
            if (staging / name).exists():
                os.replace(staging / name, out_dir / name)
        return DemoResult(out_dir / "detections.json", out_dir / "session.mcap",
                          out_dir / "demo.rrd" if rrd else None, *result)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _run(folder: Path, model, seed: int, views: int, rrd: bool, viewer, progress: bool) -> tuple:
    from fusion.cloud import FusionConfig
    from fusion.turntable import Rig
    from perception.cap import Caps
    from perception.evaluate import evaluate
    from fusion.cloud import FusionStage
    from pipeline.runner import RunConfig
    from pipeline.chain import Outputs, run_chain
    from capture.virtual import VirtualCameraConfig
    from pipeline.sources import VirtualBed, virtual_bed_source
    from pipeline.viewer_target import ViewerTarget

    start = time.perf_counter()
    camera = VirtualCameraConfig(views=views, start_ns=time.time_ns())
    source, bed = virtual_bed_source(VirtualBed(seed=seed, camera=camera))
    scene_s = time.perf_counter() - start
    config = RunConfig(fusion=FusionStage(FusionConfig(angles="encoder"), Rig(source.turntable)))
    viewer = replace(viewer or ViewerTarget(), rrd=folder / "demo.rrd" if rrd else None)
    outputs = Outputs(record=folder / "session.mcap", viewer=viewer, name=f"demo bed {seed}",
                      detections=folder / "detections.json", quiet=not progress)
    start = time.perf_counter()
    summary = run_chain(source, model, config, outputs)
    if not summary.detections:
        raise ValueError("the turn produced no fused cloud")
    detection = summary.last_detection
    score = evaluate([detection.result.caps], [Caps(bed.centers, bed.rotations, bed.scales)])
    seconds = {"scene": scene_s, "capture and fusion": time.perf_counter() - start - detection.perception_seconds,
               "perception": detection.perception_seconds}
    return len(detection.result.caps), len(bed.centers), score.ap25, score.ap50, score.angle_deg, seconds
