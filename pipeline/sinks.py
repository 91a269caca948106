"""Where a run's outputs go: Rerun, the session MCAP, the detections JSON and the console."""

from __future__ import annotations

import json
import sys
import threading
from pathlib import Path

import numpy as np

from capture.frames import DepthFrame
from common.files import write_atomically
from perception.cap import CAP_COLOR
from pipeline.runner import Detection, FusedUnit, Sink

class RerunSink(Sink):
    """Frames under each camera's entity, the fused cloud, the caps in 3D and over each camera's image,
    and the run's statistics over the frame and capture timelines (``pipeline.viewer``); the blueprint
    goes with the first fused unit, when the bed frame is known."""

    def __init__(self, rec):
        self.rec = rec
        self._views: dict[str, DepthFrame] = {}
        self._static_cameras: set[str] = set()
        self._framed = False

    def _time(self, frame: int, capture_ns: int) -> None:
        from pipeline.viewer import set_frame

        set_frame(self.rec, frame, capture_ns)

    def captured(self, index: int, frame: DepthFrame) -> None:
        from pipeline.viewer import log_frame

        self._time(index, frame.timestamp_ns)
        log_frame(self.rec, frame, pinhole=frame.sensor_id not in self._static_cameras)
        self._static_cameras.add(frame.sensor_id)
        self._views[frame.sensor_id] = frame

    def fused(self, unit: FusedUnit) -> None:
        from pipeline.viewer import log_fused_cloud, send_blueprint

        if not self._framed:
            self._framed = True
            send_blueprint(self.rec, sorted(self._views), unit.cloud.T_world_bed, unit.cloud.points)
        self._time(unit.last_frame_index, unit.last_frame_ns)
        log_fused_cloud(self.rec, unit.cloud)

    def detected(self, detection: Detection) -> None:
        from pipeline.viewer import log_caps_in_image, log_detection

        unit = detection.unit
        self._time(unit.last_frame_index, unit.last_frame_ns)
        log_detection(self.rec, detection.result, unit.cloud.world_points, plan=detection.document.get("plan"))
        for frame in list(self._views.values()):
            if frame.T_world_camera is not None:
                log_caps_in_image(self.rec, frame, detection.result.caps)

    def stats(self, name: str, value: float, frame: int, capture_ns: int) -> None:
        from pipeline.viewer import log_stat

        self._time(frame, capture_ns)
        log_stat(self.rec, name, value)


class McapSink(Sink):
    """The session's channels (an MCAP file, a live server, or both): every captured frame (with
    ``frames``), each fused cloud coloured, its T_world_bed on /fusion/tf and in a unit record, the caps
    and the pick plan each as a SceneUpdate and as JSON."""

    def __init__(self, recorder, frames: bool = True):
        self.recorder, self.frames = recorder, frames
        self._lock = threading.Lock()

    def captured(self, index: int, frame: DepthFrame) -> None:
        if self.frames:
            with self._lock:
                if not self.recorder.frames:
                    self._announce_clouds(frame.timestamp_ns)
                self.recorder.write(frame)

    def _announce_clouds(self, log_time_ns: int) -> None:
        """Empty clouds on the fused-cloud and cap-outline topics at the first frame: a viewer that
        meets a topic before its first message knows no frame for it (Rerun flags the 3D view), so
        both say "world" from the start. Readers skip empty clouds."""
        from capture.mcap.schema import CAP_OUTLINES_TOPIC, FUSED_CLOUD_TOPIC

        for topic in (FUSED_CLOUD_TOPIC, CAP_OUTLINES_TOPIC):
            self.recorder.write_point_cloud(topic, np.zeros((0, 3), np.float32), log_time_ns, "world",
                                            colors=np.zeros((0, 3), np.uint8))

    def fused(self, unit: FusedUnit) -> None:
        from capture.mcap.schema import BED_TRANSFORM_TOPIC, FUSED_CLOUD_TOPIC, UNIT_TOPIC

        t = unit.last_frame_ns
        with self._lock:
            self.recorder.write_transform("world", "bed", unit.cloud.T_world_bed, t, BED_TRANSFORM_TOPIC)
            self.recorder.write_point_cloud(FUSED_CLOUD_TOPIC, unit.cloud.world_points, t, "world",
                                            colors=unit.cloud.display_colors)
            self.recorder.write_json(UNIT_TOPIC, {"index": unit.index, "kind": unit.kind,
                                                  "T_world_bed": unit.cloud.T_world_bed.ravel().tolist(),
                                                  "frame_ids": list(unit.cloud.frame_ids)}, t)

    def detected(self, detection: Detection) -> None:
        from capture.mcap.schema import CAPS_TOPIC, CAP_OUTLINES_TOPIC, DETECTIONS_TOPIC, PLAN_JSON_TOPIC, PLAN_TOPIC

        t = detection.unit.last_frame_ns
        document = {**detection.document, "unit": detection.unit.index}
        outlines = cap_outlines(detection.result.caps)
        plan = detection.document.get("plan")
        with self._lock:
            self.recorder.write_scene_update(CAPS_TOPIC, caps_scene_update(detection, t), t)
            self.recorder.write_point_cloud(CAP_OUTLINES_TOPIC, outlines, t, "world",
                                            colors=np.tile(np.uint8(CAP_COLOR), (len(outlines), 1)))
            if plan is not None:
                self.recorder.write_scene_update(PLAN_TOPIC, plan_scene_update(plan, t), t)
                self.recorder.write_json(PLAN_JSON_TOPIC, {**plan, "unit": detection.unit.index}, t)
            self.recorder.write_json(DETECTIONS_TOPIC, document, t)

    def close(self, ok: bool) -> None:
        """Finalise the file; one that got no frame to copy is discarded (an earlier file of its name stays)."""
        with self._lock:
            self.recorder.close(discard=self.frames and not self.recorder.frames)


def cap_outlines(caps) -> np.ndarray:
    """The caps as wire domes in one (N, 3) array, for viewers that draw point clouds but no
    SceneUpdate from an MCAP (Rerun)."""
    from perception.cap import cap_wireframe

    return cap_wireframe(caps.centers, caps.rotations, caps.scales).reshape(-1, 3).astype(np.float32)


def caps_scene_update(detection: Detection, log_time_ns: int):
    """The caps as Foxglove draws them: an ellipsoid, its box and a label with id and diameter each."""
    from foxglove.messages import (Color, CubePrimitive, Pose, Quaternion, SceneEntity, SceneEntityDeletion,
                                   SceneEntityDeletionType, SceneUpdate, SpherePrimitive, TextPrimitive,
                                   Timestamp, Vector3)
    from scipy.spatial.transform import Rotation

    caps = detection.result.caps
    stamp = Timestamp(log_time_ns // 1_000_000_000, log_time_ns % 1_000_000_000)
    r, g, b = (channel / 255 for channel in CAP_COLOR)
    quaternions = Rotation.from_matrix(caps.rotations).as_quat() if len(caps) else np.zeros((0, 4))
    entities = []
    for k, (center, rotation, scales, q) in enumerate(zip(caps.centers, caps.rotations, caps.scales, quaternions)):
        orientation = Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])
        box_center = center + rotation[:, 2] * scales[2] / 2
        top = center + rotation[:, 2] * (scales[2] + 0.006)
        entities.append(SceneEntity(
            timestamp=stamp, frame_id="world", id=f"cap-{k}",
            spheres=[SpherePrimitive(pose=Pose(position=Vector3(x=center[0], y=center[1], z=center[2]),
                                               orientation=orientation),
                                     size=Vector3(x=2 * scales[0], y=2 * scales[1], z=2 * scales[2]),
                                     color=Color(r=r, g=g, b=b, a=0.55))],
            cubes=[CubePrimitive(pose=Pose(position=Vector3(x=box_center[0], y=box_center[1], z=box_center[2]),
                                           orientation=orientation),
                                 size=Vector3(x=2 * scales[0], y=2 * scales[1], z=scales[2]),
                                 color=Color(r=r, g=g, b=b, a=0.15))],
            texts=[TextPrimitive(pose=Pose(position=Vector3(x=top[0], y=top[1], z=top[2]),
                                           orientation=Quaternion(w=1.0)),
                                 billboard=True, font_size=14.0, scale_invariant=True,
                                 color=Color(r=1.0, g=1.0, b=1.0, a=1.0),
                                 text=f"#{k} {2000 * scales[:2].mean():.0f} mm")]))
    return SceneUpdate(deletions=[SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletionType.All)],
                       entities=entities)


def plan_scene_update(plan: dict, log_time_ns: int):
    """A pick plan (in the world frame) as Foxglove draws it: one arrow per cap from its grasp point
    along its approach, coloured and labelled as in Rerun (``perception.plan.plan_marks``)."""
    from foxglove.messages import (ArrowPrimitive, Color, Pose, Quaternion, SceneEntity, SceneEntityDeletion,
                                   SceneEntityDeletionType, SceneUpdate, TextPrimitive, Timestamp, Vector3)

    from perception.plan import APPROACH_ARROW, PLAN_COLORS, plan_marks

    stamp = Timestamp(log_time_ns // 1_000_000_000, log_time_ns % 1_000_000_000)
    caps = plan["caps"]
    grasps = np.array([cap["grasp"] for cap in caps]).reshape(-1, 3)
    approaches = np.array([cap["approach"] for cap in caps]).reshape(-1, 3)
    # a Foxglove arrow points along its pose's +x: the shortest rotation taking +x onto each approach,
    # (x, y, z, w) = (+x cross a, 1 + +x . a) normalised (approaches point away from the bed, never along -x)
    quaternions = np.stack([np.zeros(len(caps)), -approaches[:, 2], approaches[:, 1], 1 + approaches[:, 0]], 1)
    quaternions /= np.linalg.norm(quaternions, axis=1, keepdims=True)
    entities = []
    for cap, grasp, approach, q, (kind, label) in zip(caps, grasps, approaches, quaternions, plan_marks(plan)):
        r, g, b = (channel / 255 for channel in PLAN_COLORS[kind])
        tip = grasp + approach * (APPROACH_ARROW + 0.004)
        entities.append(SceneEntity(
            timestamp=stamp, frame_id="world", id=f"pick-{cap['id']}",
            arrows=[ArrowPrimitive(pose=Pose(position=Vector3(x=grasp[0], y=grasp[1], z=grasp[2]),
                                             orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])),
                                   shaft_length=0.75 * APPROACH_ARROW, shaft_diameter=0.0024,
                                   head_length=0.25 * APPROACH_ARROW, head_diameter=0.006,
                                   color=Color(r=r, g=g, b=b, a=1.0))],
            texts=[TextPrimitive(pose=Pose(position=Vector3(x=tip[0], y=tip[1], z=tip[2]),
                                           orientation=Quaternion(w=1.0)),
                                 billboard=True, font_size=14.0, scale_invariant=True,
                                 color=Color(r=r, g=g, b=b, a=1.0), text=label)] if label else []))
    return SceneUpdate(deletions=[SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletionType.All)],
                       entities=entities)


class JsonSink(Sink):
    """The newest unit's detections, written whole after every unit (a stop keeps the last one)."""

    def __init__(self, path: Path):
        self.path = path
        self.written = False

    def detected(self, detection: Detection) -> None:
        write_atomically(self.path, json.dumps(detection.document, indent=1))
        self.written = True


class ConsoleSink(Sink):
    """One line per fused unit on stderr: frames, caps, and the time each stage took; one per unit
    fusion could not make, even when quiet."""

    def __init__(self, quiet: bool = False):
        self.quiet = quiet

    def failed(self, message: str, frame: int, capture_ns: int) -> None:
        print(f"warning: the unit ending at frame {frame} is skipped: {message}", file=sys.stderr, flush=True)

    def detected(self, detection: Detection) -> None:
        if self.quiet:
            return
        unit = detection.unit
        print(f"{unit.kind} {unit.index + 1}: {unit.frames} frames, {len(unit.cloud)} points, "
              f"{len(detection.result.caps)} caps (fusion {unit.fusion_seconds:.2f} s, perception "
              f"{detection.perception_seconds:.2f} s, last frame to caps {detection.latency_seconds:.2f} s)",
              file=sys.stderr, flush=True)
