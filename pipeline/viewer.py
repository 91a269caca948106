"""Everything the Rerun viewer shows, in one place: the stream to where a run's ``ViewerTarget``
says (a .rrd, a spawned viewer, a served web viewer), the entity paths, the blueprint, and one logging
function per thing shown (camera frames, the fused cloud, the caps and the pick plan, synthetic beds,
run and training statistics). Commands get the --rrd, --spawn and --serve flags from
``pipeline.commands.common``."""

from __future__ import annotations

import sys
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Iterator

import numpy as np
import rerun as rr

from common.files import atomic_path
from perception.cap import CAP_COLOR
from pipeline.viewer_target import ViewerTarget

APPLICATION_ID = "mushroom-pose"
WEB_PORT = 9090
"""Where ``--serve`` serves the web viewer."""
GRPC_PORT = 9876
"""Where ``--serve`` serves the stream the web viewer reads (Rerun's own default)."""
SPAWN_PORT = 9876
"""Where a ``--spawn``-ed viewer listens (Rerun's own default)."""

WORLD = "world"
"""The world frame; every 3D entity lies under it."""
FUSED_CLOUD = f"{WORLD}/fusion/cloud"
PERCEPTION = f"{WORLD}/perception"
"""The network's per-point existence (``existence``), collapsed centres (``centers``), the caps
(``mushrooms``: boxes, ellipsoids, labels) and the pick plan (``plan``)."""
SYNTHETIC = f"{WORLD}/synthetic"
"""A synthetic bed: its points by label and its true caps."""
TRACK = f"{WORLD}/track"
"""``track``: one bed's scans in the first scan's frame (``cloud``), its caps with the ids they keep
(``mushrooms``), over the ``scan`` timeline."""
STATS = "stats"
"""Time series: the runner's ``latency/<stage>`` and ``counts/<what>``, training's ``loss/<term>`` and
``val/<metric>``."""
HIDDEN_BY_DEFAULT = (f"{PERCEPTION}/existence", f"{PERCEPTION}/centers")
"""The network's per-point existence and collapsed centres: there to inspect, not to read the bed by."""

TRUE_CAP_COLOR = (230, 60, 40)
"""A synthetic bed's true caps."""


def camera_entity(sensor_id: str) -> str:
    """A camera's pose and pinhole; its ``depth``, ``color`` and ``caps`` (the rims it sees) below it."""
    return f"{WORLD}/camera/{sensor_id}"


@contextmanager
def viewer_stream(target: ViewerTarget, name: str | None = None) -> Iterator[rr.RecordingStream | None]:
    """A recording stream to every place ``target`` names at once, listed in the viewer as ``name``;
    None when nothing asked for one. The blueprint is sent once, by ``send_blueprint``, when the bed
    frame is known. With ``target.hold``, a served stream stays up after the run until Ctrl-C.

    The .rrd is written to a temporary name and moved into place when the run ends, so an
    interrupted run never leaves a truncated file where the user expects a good one.
    """
    if not target.wanted:
        yield None
        return
    rec = rr.RecordingStream(APPLICATION_ID)
    with nullcontext() if target.rrd is None else atomic_path(target.rrd) as tmp:
        sinks = [] if tmp is None else [rr.FileSink(tmp)]
        if target.spawn:
            rr.spawn(port=SPAWN_PORT, connect=False, recording=rec)
            sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{SPAWN_PORT}/proxy"))
        if target.serve:
            sinks.append(rr.GrpcServerSink(port=GRPC_PORT))
        rec.set_sinks(*sinks)  # each of save, spawn and serve_grpc alone would replace the others
        if name:
            rec.send_recording_name(name)
        if target.serve:
            _serve_web_viewer(f"rerun+http://127.0.0.1:{GRPC_PORT}/proxy")
        try:
            yield rec
        except BaseException:
            rec.disconnect()
            raise
        rec.flush()
        if target.serve and target.hold:
            _serve_until_interrupted()
        rec.disconnect()


def _serve_web_viewer(uri: str) -> None:
    """Serve the web viewer that reads the stream at ``uri``, and print where to open it."""
    from urllib.parse import quote

    rr.serve_web_viewer(web_port=WEB_PORT, connect_to=uri, open_browser=False)
    print(f"Rerun web viewer: http://localhost:{WEB_PORT}/?url={quote(uri, safe='')} (the native viewer: "
          f"rerun {uri})", file=sys.stderr, flush=True)


def _serve_until_interrupted() -> None:
    """Keep the served stream up after a command's work is done, as Rerun's own scripts do, until
    SIGINT or SIGTERM (whatever handled them during the run, such as a graceful stop, is set aside)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return
    done = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: done.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    print("the run is done; serving the Rerun web viewer until Ctrl-C", file=sys.stderr, flush=True)
    try:
        while not done.wait(1.0):
            pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def blueprint(camera_ids: list[str] = (), T_world_bed: np.ndarray | None = None, extent: float = 0.5,
              stats: bool = True, hidden: tuple[str, ...] = HIDDEN_BY_DEFAULT) -> rr.BlueprintLike:
    """The bed in 3D, filling its view from above and in front (known once the bed frame is, from
    ``T_world_bed`` and the bed's ``extent`` in metres); each camera's depth with the caps over it;
    with ``stats``, per-stage latency and the counts (caps, dropped work) over time. The ``hidden``
    entities start switched off."""
    import rerun.blueprint as rrb

    eye = None
    if T_world_bed is not None:
        T = np.asarray(T_world_bed, np.float64)
        target = T[:3, 3]
        position = target + T[:3, :3] @ np.array([0.0, -0.7, 1.0]) * extent
        eye = rrb.EyeControls3D(position=position, look_target=target, eye_up=T[:3, 2])
    # each depth image would also show in 3D as a cloud of its own, over the fused one
    hidden = [*hidden, *(f"{camera_entity(cid)}/depth" for cid in camera_ids)]
    bed = rrb.Spatial3DView(origin=WORLD, name="bed", eye_controls=eye,
                            overrides={path: rrb.EntityBehavior(visible=False) for path in hidden})
    cameras = [rrb.Spatial2DView(origin=camera_entity(cid), name=f"camera {cid}") for cid in camera_ids]
    plots = [rrb.TimeSeriesView(origin=f"{STATS}/latency", name="latency per stage (ms)"),
             rrb.TimeSeriesView(origin=f"{STATS}/counts", name="caps and dropped work")]
    if not stats and not cameras:
        return rrb.Blueprint(bed, collapse_panels=True)
    side = rrb.Vertical(*cameras[:2], *(plots if stats else ()))
    # following: a recording opens on its newest unit and caps, and a live run's view keeps up with it
    time_panel = rrb.TimePanel(state="collapsed", timeline="frame", play_state="following")
    return rrb.Blueprint(rrb.Horizontal(bed, side, column_shares=[3, 2]), time_panel, collapse_panels=True)


def send_blueprint(rec: rr.RecordingStream, camera_ids: list[str] = (), T_world_bed: np.ndarray | None = None,
                   points: np.ndarray | None = None, stats: bool = True,
                   hidden: tuple[str, ...] = HIDDEN_BY_DEFAULT) -> None:
    """The run's one blueprint (``blueprint``), its view fitted to the bed's ``points`` (bed frame)."""
    extent = float(np.ptp(points[:, :2], axis=0).max()) if points is not None and len(points) else 0.5
    rec.send_blueprint(blueprint(camera_ids, T_world_bed, extent, stats, hidden))


def set_frame(rec: rr.RecordingStream, frame: int, capture_ns: int | None = None) -> None:
    """Put what follows on the ``frame`` timeline and, when known, the ``capture`` timeline."""
    rec.set_time("frame", sequence=frame)
    if capture_ns is not None:
        rec.set_time("capture", timestamp=np.datetime64(int(capture_ns), "ns"))


def log_frame(rec: rr.RecordingStream, frame, pinhole: bool = True) -> None:
    """A ``capture.frames.DepthFrame`` under ``camera_entity``: its pose, depth image and colour, and with
    ``pinhole`` its intrinsics, logged as static (a camera's intrinsics do not change in a run)."""
    entity = camera_entity(frame.sensor_id)
    if frame.T_world_camera is not None:
        rec.log(entity, rr.Transform3D(translation=frame.T_world_camera[:3, 3], mat3x3=frame.T_world_camera[:3, :3]))
    if pinhole:
        rec.log(entity, rr.Pinhole(image_from_camera=frame.intrinsics.matrix,
                                   resolution=[frame.intrinsics.width, frame.intrinsics.height],
                                   camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.05), static=True)
    rec.log(f"{entity}/depth", rr.DepthImage(frame.depth, meter=1.0 / frame.depth_scale, colormap="turbo"))
    if frame.color is not None:
        rec.log(f"{entity}/color", rr.Image(frame.color))


def log_fused_cloud(rec: rr.RecordingStream, fused, radius: float = 0.0008) -> None:
    """A ``fusion.cloud.FusedCloud`` in world coordinates, in its colours, or by height above the bed
    when it has none."""
    rec.log(FUSED_CLOUD, rr.Points3D(fused.world_points, colors=fused.display_colors, radii=radius))


def log_detection(rec: rr.RecordingStream, result, points: np.ndarray, plan: dict | None = None) -> None:
    """A ``perception.detect.SceneResult`` over its cloud's ``points`` (same frame): existence on the
    points, the collapsed centres, the caps labelled with their ids and sizes, and the pick ``plan``
    (the detection document's) as approach arrows."""
    heat = np.clip(result.point_existence, 0, 1)[:, None]
    colors = (255 * (heat * np.array([0.95, 0.25, 0.15]) + (1 - heat) * np.array([0.45, 0.4, 0.35]))).astype(np.uint8)
    rec.log(f"{PERCEPTION}/existence", rr.Points3D(points, colors=colors, radii=0.0012))
    cap_voxels = result.voxels.existence > 0.5
    rec.log(f"{PERCEPTION}/centers", rr.Points3D(result.voxels.centers[cap_voxels], radii=0.0008,
                                                 colors=(40, 120, 240)))
    caps = result.caps
    log_caps(rec, f"{PERCEPTION}/mushrooms", caps.centers, caps.rotations, caps.scales,
             labels=[f"#{k} {2000 * radius:.0f} mm" for k, radius in enumerate(caps.radii)])
    if plan is not None:
        log_plan(rec, plan)


def log_caps(rec: rr.RecordingStream, entity: str, centers: np.ndarray, rotations: np.ndarray,
             scales: np.ndarray, labels: list[str] | None = None, color=CAP_COLOR) -> None:
    """Each cap as its box ([-s_x, s_x] x [-s_y, s_y] x [0, s_z]), its half-ellipsoid's full ellipsoid,
    both in ``color``, and one label per cap just above its top."""
    from scipy.spatial.transform import Rotation

    if len(centers) == 0:
        for part in ("boxes", "ellipsoids", "labels"):
            rec.log(f"{entity}/{part}", rr.Clear(recursive=False))
        return
    quaternions = Rotation.from_matrix(rotations).as_quat()
    box_centers = centers + rotations[:, :, 2] * (scales[:, 2:3] / 2)
    half = scales * np.array([1.0, 1.0, 0.5])
    rec.log(f"{entity}/boxes", rr.Boxes3D(centers=box_centers, half_sizes=half, quaternions=quaternions,
                                          colors=color, radii=0.0004))
    rec.log(f"{entity}/ellipsoids", rr.Ellipsoids3D(centers=centers, half_sizes=scales, quaternions=quaternions,
                                                    colors=color, line_radii=0.0003))
    if labels is not None:
        tops = centers + rotations[:, :, 2] * (scales[:, 2:3] + 0.004)
        rec.log(f"{entity}/labels", rr.Points3D(tops, labels=labels, radii=0.0001, colors=color,
                                                show_labels=True))


def log_plan(rec: rr.RecordingStream, plan: dict) -> None:
    """The pick plan (a detection document's ``"plan"``, in the caps' frame): one arrow per cap from its
    grasp point along its approach, labelled with its place in the order or why it waits."""
    from perception.plan import APPROACH_ARROW, PLAN_COLORS, plan_marks

    entity, caps = f"{PERCEPTION}/plan", plan["caps"]
    if not caps:
        rec.log(entity, rr.Clear(recursive=False))
        return
    marks = plan_marks(plan)
    rec.log(entity, rr.Arrows3D(origins=[cap["grasp"] for cap in caps],
                                vectors=APPROACH_ARROW * np.array([cap["approach"] for cap in caps]),
                                colors=[PLAN_COLORS[kind] for kind, _ in marks], labels=[label for _, label in marks],
                                radii=0.0012, show_labels=True))


def log_caps_in_image(rec: rr.RecordingStream, frame, caps) -> None:
    """The rims of ``caps`` (world frame) as ``frame``'s camera sees them, over its depth image."""
    from perception.cap import cap_wireframe

    entity = f"{camera_entity(frame.sensor_id)}/caps"
    if len(caps.centers) == 0:
        rec.log(entity, rr.Clear(recursive=False))
        return
    samples, intrinsics = 48, frame.intrinsics
    rims = cap_wireframe(caps.centers, caps.rotations, caps.scales, samples)[:, :samples].reshape(-1, 3)
    T = np.linalg.inv(np.asarray(frame.T_world_camera, np.float64))
    camera = rims @ T[:3, :3].T + T[:3, 3]
    depth = np.maximum(camera[:, 2], 1e-6)
    pixels = np.stack([intrinsics.fx * camera[:, 0] / depth + intrinsics.cx,
                       intrinsics.fy * camera[:, 1] / depth + intrinsics.cy], 1).reshape(len(caps.centers), -1, 2)
    in_front = (camera[:, 2] > 0).reshape(len(caps.centers), -1).all(1)
    closed = np.concatenate([pixels, pixels[:, :1]], axis=1)
    rec.log(entity, rr.LineStrips2D(closed[in_front], colors=CAP_COLOR, radii=1.5))


def log_scene(rec: rr.RecordingStream, scene) -> None:
    """A ``perception.synthetic.scene.SyntheticScene``: its points coloured by label, its true caps."""
    from perception.synthetic.dataset import label_colors

    rec.log(f"{SYNTHETIC}/points", rr.Points3D(scene.points, colors=label_colors(scene), radii=0.0015))
    log_caps(rec, f"{SYNTHETIC}/mushrooms", scene.centers, scene.rotations, scene.scales,
             labels=[f"{2000 * r:.0f} mm" for r in scene.radii], color=TRUE_CAP_COLOR)


def log_scan(rec: rr.RecordingStream, index: int, points: np.ndarray, caps, T_first_scan: np.ndarray,
             ids: list[int]) -> None:
    """Scan ``index`` of a tracked bed on the ``scan`` timeline: its cloud moved into the first scan's
    frame by ``T_first_scan``, its caps (already there) labelled with the ids they keep."""
    from fusion.cloud import height_colors

    rec.set_time("scan", sequence=index)
    aligned = points @ T_first_scan[:3, :3].T + T_first_scan[:3, 3]
    ground = np.percentile(aligned[:, 2], 10) if len(aligned) else 0.0
    rec.log(f"{TRACK}/cloud", rr.Points3D(aligned, colors=height_colors(aligned[:, 2] - ground), radii=0.0008))
    log_caps(rec, f"{TRACK}/mushrooms", caps.centers, caps.rotations, caps.scales,
             labels=[f"#{cap_id} {2000 * radius:.0f} mm" for cap_id, radius in zip(ids, caps.radii)])


def log_stat(rec: rr.RecordingStream, name: str, value: float) -> None:
    """One value of the time series ``stats/<name>``."""
    rec.log(f"{STATS}/{name}", rr.Scalars(float(value)))


ABANDONED_STREAMS: list = []
"""Rerun streams whose file writer failed: kept referenced, since Rerun waits for ever on the dead
writer when such a stream is dropped; the command line ends the process without dropping them."""


class TrainingLog:
    """A training session's losses and validation metrics over the ``iteration`` timeline, saved to
    ``path`` (``perception.train.train``'s ``metrics_log``)."""

    def __init__(self, path: Path):
        self.rec = rr.RecordingStream(f"{APPLICATION_ID}-train")
        self.rec.save(path)

    def losses(self, iteration: int, losses: dict[str, float]) -> None:
        self.rec.set_time("iteration", sequence=iteration)
        for name, value in losses.items():
            log_stat(self.rec, f"loss/{name}", value)

    def validation(self, iteration: int, metrics: dict[str, float]) -> None:
        self.rec.set_time("iteration", sequence=iteration)
        for name, value in metrics.items():
            log_stat(self.rec, f"val/{name}", value)

    def close(self) -> None:
        try:
            self.rec.flush(timeout_sec=10)
        except RuntimeError:  # its file writer died (a full disk): dropping the stream would wait on it
            ABANDONED_STREAMS.append(self.rec)
