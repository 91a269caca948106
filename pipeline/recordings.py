"""The sessions of recordings/: made by the virtual camera over synthetic beds, run through the chain
with the shipped model, recorded with the detections they are expected to give.

    python -m pipeline.recordings [NAME ...] [--out recordings] [--model PATH]

makes the named recordings (default: all) and says, per recording, whether its expected detections
changed, so that a changed model or chain is a visible decision in the diff. A session whose caps stay
within the check's tolerances is kept as it was, session and expectations both.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.files import write_atomically

RECORDINGS_DIR = Path(__file__).resolve().parent.parent / "recordings"
START_NS = 1_767_225_600_000_000_000
"""Where every recording's capture clock starts (nanoseconds since the Unix epoch): a fixed, real instant,
so a remake writes the same timestamps."""


@dataclass(frozen=True)
class Recording:
    name: str
    what: str
    seed: int
    views: int = 1
    """Turntable views per turn (0: the fixed cameras of ``cameras``)."""
    cameras: int = 1
    """Fixed cameras around the bed (with views = 0)."""
    frames_per_camera: int = 1
    mushrooms: tuple[int, int] | None = None
    device_file: bool = False
    """A RealSense device file (.db3) played through the real driver, expected detections beside it."""

    @property
    def file(self) -> str:
        return f"{self.name}.db3" if self.device_file else f"{self.name}.mcap"


RECORDINGS = (
    Recording("single-view", "one fixed virtual D405 over bed 1, two frames, each fused alone", seed=1, views=0,
              frames_per_camera=2),
    Recording("turntable-12", "a 12-view turn of a virtual turntable over bed 2, one fused cloud", seed=2, views=12),
    Recording("two-cameras", "two fixed virtual cameras on opposite sides of bed 3, two synchronised sets", seed=3,
              views=0, cameras=2, frames_per_camera=2),
    Recording("dense-bed", "a 6-view turn over bed 4 packed with 40-45 touching caps and distractors", seed=4,
              views=6, mushrooms=(40, 45)),
    Recording("realsense-playback", "two frames of a fixed virtual camera over bed 5 as a RealSense device file, "
              "replayed through the RealSense driver", seed=5, views=0, frames_per_camera=2, device_file=True),
)


def fixed_camera_poses(cameras: int, radius: float = 0.2, height: float = 0.42) -> list[np.ndarray]:
    """Cameras evenly around the bed's centre, each looking at it from ``radius`` off and ``height`` up."""
    from common.geometry import look_at

    angles = 2 * np.pi * np.arange(cameras) / cameras
    return [look_at(np.array([radius * np.cos(a), radius * np.sin(a), height]), np.zeros(3),
                    up_hint=np.array([0.0, 0.0, 1.0])) for a in angles]


def recording_source(recording: Recording):
    """The virtual source of a recording and the number of cameras it interleaves."""
    from capture.source import Interleaved
    from capture.virtual import VirtualCameraConfig, VirtualSource
    from perception.synthetic.scene import SceneConfig, build_bed
    from pipeline.sources import VirtualBed, virtual_bed_source

    if recording.views:
        camera = VirtualCameraConfig(views=recording.views, start_ns=START_NS)
        setup = VirtualBed(seed=recording.seed, mushrooms=recording.mushrooms, camera=camera)
        return virtual_bed_source(setup)[0], 1
    config = SceneConfig(mushrooms=recording.mushrooms) if recording.mushrooms else SceneConfig()
    bed = build_bed(np.random.default_rng(recording.seed), config)
    sources = []
    for k, pose in enumerate(fixed_camera_poses(recording.cameras)):
        camera = VirtualCameraConfig(poses=(pose,) * recording.frames_per_camera, seed=recording.seed * 10 + k,
                                     sensor_id=f"cam{k}" if recording.cameras > 1 else "virtual", start_ns=START_NS)
        sources.append(VirtualSource(bed.vertices, bed.triangles, camera))
    return (Interleaved(sources) if len(sources) > 1 else sources[0]), len(sources)


def expected_path(recording_file: Path) -> Path:
    """Where a recording's expected detections lie as JSON (a list of detection documents, one per unit)."""
    return recording_file.with_name(recording_file.stem + ".expected.json")


def make_recording(recording: Recording, out_dir: Path, model) -> tuple[Path, list[dict]]:
    """Record ``recording`` into ``out_dir`` with its expected detections; returns the file and them."""
    from pipeline.runner import RunConfig
    from pipeline.chain import Outputs, run_chain

    target = out_dir / recording.file
    source, cameras = recording_source(recording)
    if recording.device_file:
        from capture.realsense import write_device_recording
        from pipeline.replay import run_replay

        with source:
            frames = list(source)
        write_device_recording(frames, target)
        with tempfile.TemporaryDirectory() as scratch:
            summary = run_replay(target, model, Path(scratch), None, quiet=True).summary
    else:
        summary = run_chain(source, model, RunConfig(), Outputs(record=target, name=recording.name, quiet=True),
                            sensors=cameras)
    documents = [detection.document for detection in summary.detections]
    write_atomically(expected_path(target), json.dumps(documents, indent=1) + "\n")
    return target, documents


def _caps_summary(documents: list[dict]) -> str:
    return " + ".join(str(len(d["mushrooms"])) for d in documents) or "none"


def main(argv: list[str] | None = None) -> int:
    from pipeline.check import compare
    from perception.weights import DEFAULT_WEIGHTS
    from perception.weights import load_weights

    names = [r.name for r in RECORDINGS]
    parser = argparse.ArgumentParser(prog="python -m pipeline.recordings", description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", choices=[[], *names], metavar="NAME", help=f"any of {', '.join(names)}")
    parser.add_argument("--out", type=Path, default=RECORDINGS_DIR)
    parser.add_argument("--model", type=Path, default=DEFAULT_WEIGHTS)
    args = parser.parse_args(argv)
    model, _ = load_weights(args.model)
    args.out.mkdir(parents=True, exist_ok=True)
    for recording in RECORDINGS:
        if args.names and recording.name not in args.names:
            continue
        session = args.out / recording.file
        sidecar = expected_path(session)
        previous = json.loads(sidecar.read_text()) if sidecar.is_file() and session.is_file() else None
        with tempfile.TemporaryDirectory(dir=args.out) as scratch:
            made, documents = make_recording(recording, Path(scratch), model)
            report = compare(previous, documents) if previous is not None else None
            if report is None or not report.passed:  # within the check's tolerances: keep the session as it was
                os.replace(made, session)
                os.replace(expected_path(made), sidecar)
        size = session.stat().st_size / 1e6
        if report is None:
            verdict = "new expected detections"
        else:
            verdict = "expected detections unchanged (the session is kept)" if report.passed else \
                "EXPECTED DETECTIONS CHANGED:\n" + report.table()
        print(f"{recording.file}: {size:.1f} MB, caps per unit {_caps_summary(documents)}; {verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
