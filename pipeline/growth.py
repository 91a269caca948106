"""One bed's sessions over the days read as scans for ``perception.track``, and what tracking them
gives written out: the track document (``track.json``) and a Rerun recording on a ``scan`` timeline."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from perception.grades import GradeTable
from perception.track import BedTracks, Scan, TrackConfig


class SessionError(ValueError):
    """A session that cannot be one of the bed's scans (one line)."""


def read_scans(paths: list[Path], bed_id: str) -> list[Scan]:
    """Each session's last fused cloud and its caps (world frame) at the time the session began, in time
    order; a SessionError names a session that is not of bed ``bed_id``, cannot be read, holds no caps,
    or began when another did."""
    from capture.mcap.reader import read_documents, read_fused_units, read_session_info
    from capture.source import SourceError
    from perception.cap import Caps

    scans, began = [], {}
    for path in paths:
        if not path.is_file():
            raise SessionError(f"{path} does not exist")
        try:
            info = read_session_info(path)
            units = read_fused_units(path)
            documents = read_documents(path)
        except SourceError as error:
            raise SessionError(str(error)) from None
        if not info or info.get("bed_id") is None:
            raise SessionError(f"{path} does not say which bed it scans: record it with --bed-id (live, record)")
        if info["bed_id"] != bed_id:
            raise SessionError(f"{path} scans bed {info['bed_id']!r}, not {bed_id!r}")
        if not units or not documents:
            raise SessionError(f"{path} holds no fused cloud with its caps: replay it first")
        started = int(info["started_ns"])
        if started in began:
            raise SessionError(f"{began[started]} and {path} began at the same moment: one scan given twice?")
        began[started] = path
        caps = Caps.from_document(documents[-1][1])
        scans.append(Scan(started / 1e9, units[-1].points.astype(np.float64), caps, path.name))
    return sorted(scans, key=lambda scan: scan.time_s)


def track_document(bed_id: str, scans: list[Scan], tracks: BedTracks, grades: GradeTable,
                   config: TrackConfig) -> dict:
    """What ``track.json`` holds: the scans (each one's day and pose in the first's frame), every cap
    with its sightings (scan, the id of its detection there, day, diameter, grade), growth and ready
    day, and the forecast count per grade."""
    days = [(scan.time_s - scans[0].time_s) / 86400.0 for scan in scans]
    caps = []
    for track in tracks.tracks:
        caps.append({"id": track.id, "present": track.present, "center": track.center.tolist(),
                     "growth_mm_per_day": track.growth_mm_per_day, "ready_day": track.ready_day,
                     "seen": [{"scan": int(s), "detection": int(c), "day": float(day), "diameter_mm": float(d),
                               "grade": grade}
                              for s, c, day, d, grade in zip(track.scans, track.caps, track.days, track.diameters_mm,
                                                             grades.grade_of(track.diameters_mm))]})
    return {"bed_id": bed_id, "units": "m", "frame": "first scan", "pick_mm": config.pick_mm,
            "grades": grades.to_document(),
            "scans": [{"session": scan.name, "time_s": scan.time_s, "day": day, "T_first_scan": T.tolist(),
                       "soil_overlap": overlap}
                      for scan, day, T, overlap in zip(scans, days, tracks.T_first_scan, tracks.soil_overlap)],
            "caps": caps, "forecast": tracks.forecast}


def write_track_rrd(path: Path, scans: list[Scan], tracks: BedTracks) -> None:
    """The bed scan by scan on the ``scan`` timeline, in the first scan's frame, each cap labelled with
    the id it keeps."""
    from pipeline.viewer import log_scan, viewer_stream
    from pipeline.viewer_target import ViewerTarget

    ids = {(s, c): track.id for track in tracks.tracks for s, c in zip(track.scans, track.caps)}
    with viewer_stream(ViewerTarget(path), "track") as rec:
        for index, (scan, T) in enumerate(zip(scans, tracks.T_first_scan)):
            log_scan(rec, index, scan.points, scan.caps.moved(T) if len(scan.caps) else scan.caps, T,
                     [ids[index, cap] for cap in range(len(scan.caps))])
