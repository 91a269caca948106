"""The one owner of a run's Rerun stream: where it goes (file, viewer, web) and its timelines."""

from __future__ import annotations

from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Iterator

import numpy as np
import rerun as rr

from common.files import atomic_path

APPLICATION_ID = "mushroom-pose"
WEB_PORT = 9090
"""Where ``--serve`` serves the web viewer (the gRPC stream it reads has Rerun's own port)."""


@contextmanager
def rerun_stream(rrd: Path | None = None, spawn: bool = False, serve: bool = False,
                 blueprint: rr.BlueprintLike | None = None, name: str | None = None) -> Iterator[rr.RecordingStream | None]:
    """A recording stream saved to ``rrd`` and/or shown live, listed in the viewer as ``name``; None
    when nothing asked for one. ``serve`` serves the web viewer (for a headless machine at the bed).

    The .rrd is written to a temporary name and moved into place when the run ends, so an
    interrupted run never leaves a truncated file where the user expects a good one.
    """
    if rrd is None and not spawn and not serve:
        yield None
        return
    rec = rr.RecordingStream(APPLICATION_ID)
    if name:
        rec.send_recording_name(name)
    with nullcontext() if rrd is None else atomic_path(rrd) as tmp:
        if tmp is not None:
            rec.save(tmp, default_blueprint=blueprint)
        if spawn:
            rec.spawn(connect=rrd is None, default_blueprint=blueprint)
        if serve:
            _serve_web_viewer(rec, blueprint)
        try:
            yield rec
        except BaseException:
            rec.disconnect()
            raise
        rec.flush()
        rec.disconnect()


def _serve_web_viewer(rec: rr.RecordingStream, blueprint: rr.BlueprintLike | None) -> None:
    """Serve ``rec`` over gRPC and the web viewer that reads it, and print where to open it."""
    import sys
    from urllib.parse import quote

    uri = rec.serve_grpc(default_blueprint=blueprint)
    rr.serve_web_viewer(web_port=WEB_PORT, connect_to=uri, open_browser=False)
    print(f"Rerun web viewer: http://localhost:{WEB_PORT}/?url={quote(uri, safe='')} (the native viewer: "
          f"rerun {uri})", file=sys.stderr, flush=True)


HIDDEN_BY_DEFAULT = ("world/perception/existence", "world/perception/centers")
"""The network's per-point existence and collapsed centres: there to inspect, not to read the bed by."""


def default_blueprint(camera_ids: list[str] = (), T_world_bed: np.ndarray | None = None,
                      extent: float = 0.5, stats: bool = True,
                      hidden: tuple[str, ...] = HIDDEN_BY_DEFAULT) -> rr.BlueprintLike:
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
    hidden = [*hidden, *(f"world/camera/{cid}/depth" for cid in camera_ids)]
    bed = rrb.Spatial3DView(origin="world", name="bed", eye_controls=eye,
                            overrides={path: rrb.EntityBehavior(visible=False) for path in hidden})
    cameras = [rrb.Spatial2DView(origin=f"world/camera/{cid}", name=f"camera {cid}") for cid in camera_ids]
    plots = [rrb.TimeSeriesView(origin="stats/latency", name="latency per stage (ms)"),
             rrb.TimeSeriesView(origin="stats/counts", name="caps and dropped work")]
    if not stats and not cameras:
        return rrb.Blueprint(bed, collapse_panels=True)
    side = rrb.Vertical(*cameras[:2], *(plots if stats else ()))
    # following: a recording opens on its newest unit and caps, and a live run's view keeps up with it
    time = rrb.TimePanel(state="collapsed", timeline="frame", play_state="following")
    return rrb.Blueprint(rrb.Horizontal(bed, side, column_shares=[3, 2]), time, collapse_panels=True)


def set_frame(rec: rr.RecordingStream, frame: int, capture_ns: int | None = None) -> None:
    """Put what follows on the ``frame`` timeline and, when known, the ``capture`` timeline."""
    rec.set_time("frame", sequence=frame)
    if capture_ns is not None:
        rec.set_time("capture", timestamp=np.datetime64(int(capture_ns), "ns"))
