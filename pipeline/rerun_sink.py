"""The one owner of a run's Rerun stream: where it goes (file, viewer, web) and its timelines."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np
import rerun as rr

APPLICATION_ID = "mushroom-pose"


@contextmanager
def rerun_stream(rrd: Path | None = None, spawn: bool = False, serve: bool = False,
                 blueprint: rr.BlueprintLike | None = None) -> Iterator[rr.RecordingStream | None]:
    """A recording stream saved to ``rrd`` and/or shown live; None when nothing asked for one.

    The .rrd is written to a temporary name and moved into place when the run ends, so an
    interrupted run never leaves a truncated file where the user expects a good one.
    """
    if rrd is None and not spawn and not serve:
        yield None
        return
    rec = rr.RecordingStream(APPLICATION_ID)
    tmp = None
    if rrd is not None:
        rrd = Path(rrd)
        tmp = rrd.with_name(rrd.name + ".partial")
        rec.save(tmp, default_blueprint=blueprint)
    if spawn:
        rec.spawn(connect=rrd is None, default_blueprint=blueprint)
    if serve:
        rec.serve_grpc(default_blueprint=blueprint)
    try:
        yield rec
    except BaseException:
        rec.disconnect()
        if tmp is not None:
            tmp.unlink(missing_ok=True)
        raise
    rec.flush()
    rec.disconnect()
    if tmp is not None:
        tmp.replace(rrd)


def default_blueprint(camera_ids: list[str] = ()) -> rr.BlueprintLike:
    """3D view of the world, each camera's depth (and colour) in 2D, and per-stage latency over time."""
    import rerun.blueprint as rrb

    cameras = [rrb.Spatial2DView(origin=f"world/camera/{cid}", name=f"camera {cid}") for cid in camera_ids]
    side = [*cameras, rrb.TimeSeriesView(origin="stats", name="latency and counts")]
    return rrb.Blueprint(rrb.Horizontal(rrb.Spatial3DView(origin="world", name="bed"), rrb.Vertical(*side),
                                        column_shares=[3, 2]), collapse_panels=True)


def set_frame(rec: rr.RecordingStream, frame: int, capture_ns: int | None = None) -> None:
    """Put what follows on the ``frame`` timeline and, when known, the ``capture`` timeline."""
    rec.set_time("frame", sequence=frame)
    if capture_ns is not None:
        rec.set_time("capture", timestamp=np.datetime64(int(capture_ns), "ns"))
