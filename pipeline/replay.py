"""``mushroom-pose replay``: a recorded session through the chain again, at a desk, and ``--check``
against the detections the session recorded."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from fusion.cloud import FusionStage
from perception.grades import GradeTable
from pipeline.check import CheckReport, Tolerances, compare
from pipeline.runner import PerceptionStage, RunSummary


class ReplayError(ValueError):
    """A session that cannot be replayed (one line)."""


@dataclass(frozen=True)
class ReplayOptions:
    """How a session is replayed: its own flags of ``mushroom-pose replay``, and the fusion and
    perception stages as ``live`` runs them."""

    from_stage: Literal["capture", "fusion"] = "capture"
    """capture: fuse the recorded frames again; fusion: detect on the recorded fused clouds."""
    speed: Literal["max", "realtime"] = "max"
    """max: as fast as the chain runs; realtime: at the recorded frame rate, as a camera delivers them."""
    fusion: FusionStage = field(default_factory=FusionStage)
    perception: PerceptionStage = field(default_factory=PerceptionStage)
    readings_as_recorded: bool = True
    """Read each unit as often as the session's recorded detections say (once when they do not say)
    rather than ``perception.readings`` times, so that a replay reads as the run did."""
    grades: GradeTable = field(default_factory=GradeTable)
    """The table each cap's grade comes from."""

    @property
    def realtime(self) -> bool:
        return self.speed == "realtime"


@dataclass(frozen=True)
class ReplayResult:
    summary: RunSummary
    frames_lost: bool
    """The session was cut short (no MCAP footer): replayed up to its last whole frame."""
    check: CheckReport | None


def read_expected(path: Path) -> list[dict]:
    """Detection documents from a JSON file: a list of them (one per fused unit) or a single one."""
    import json

    try:
        documents = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ReplayError(f"{path} is not readable JSON: {error}") from None
    if isinstance(documents, dict):
        documents = [documents]
    if not isinstance(documents, list) or not all(isinstance(d, dict) and isinstance(d.get("mushrooms"), list)
                                                  for d in documents):
        raise ReplayError(f"{path} holds no detection documents ({{\"mushrooms\": [...]}} or a list of them)")
    from perception.cap import Caps

    for unit, document in enumerate(documents):
        try:
            Caps.from_document(document)
        except ValueError as error:
            raise ReplayError(f"{path}, unit {unit}: {error}") from None
    return documents


def recorded_readings(session: Path, expected: list[dict] | None) -> int:
    """How many turned readings the session's detections (``expected``, else ``expected_documents``) were
    made with: their documents' ``readings``, 1 when they do not say; so that a replay reads as the run did."""
    from perception.detect import MAX_READINGS

    documents = expected
    if documents is None:
        try:
            documents = expected_documents(session)
        except ReplayError:  # none recorded (or none readable): a replay that checks nothing reads once
            documents = []
    said = [document.get("readings", 1) if isinstance(document, dict) else None for document in documents]
    if not all(type(n) is int and 1 <= n <= MAX_READINGS for n in said) or len({*said}) > 1:
        counts = ", ".join(sorted({repr(n) for n in said}))
        raise ReplayError(f"{session}: its detections do not say one number of readings ({counts}); give --readings")
    return said[0] if said else 1


def expected_documents(session: Path) -> list[dict]:
    """The detection documents a recording carries: its /perception/mushrooms_json messages, or, for a
    device file or a session without them, ``<session stem>.expected.json`` beside it (a list)."""
    from capture.mcap.reader import read_documents
    from capture.source import SourceError

    sidecar = session.with_name(session.stem + ".expected.json")
    if session.suffix == ".mcap":
        try:
            documents = [document for _, document in read_documents(session)]
        except SourceError:
            documents = []
        if documents:
            return documents
    if sidecar.is_file():
        return read_expected(sidecar)
    raise ReplayError(f"{session} records no detections (/perception/mushrooms_json) and has no {sidecar.name} "
                      "beside it: nothing to check against")


def run_replay(session: Path, model, out_dir: Path, viewer=None, options: ReplayOptions = ReplayOptions(),
               check: Tolerances | None = None, quiet: bool = False, stop_requested=lambda: None,
               on_start=None, expected: list[dict] | None = None) -> ReplayResult:
    """Replay ``session`` (an MCAP session, or a RealSense device file through the driver) into
    ``out_dir`` (replay.mcap: the session's frames with the new fusion and perception topics;
    detections.json: the last unit's caps) and the ``pipeline.viewer_target.ViewerTarget`` ``viewer`` (None:
    no viewer); with ``check``, compare every unit's caps with
    ``expected``, by default those the session recorded."""
    from capture.mcap.reader import McapSource, TruncatedRecordingWarning, read_fused_units, read_session_info
    from capture.source import Paced, SourceError
    from fusion.cloud import FusedCloud
    from pipeline.chain import Outputs, run_chain
    from pipeline.runner import RunConfig
    from pipeline.viewer_target import ViewerTarget

    if check is not None and expected is None:
        expected = expected_documents(session)
    if session.suffix == ".db3":
        if options.from_stage == "fusion":
            raise ReplayError(f"{session} is a RealSense device file: it holds frames only, replay it from capture")
        from capture.realsense import RealSenseConfig, RealSenseSource

        source, sensor_ids, caught = RealSenseSource(RealSenseConfig(playback=session)), ["camera"], []
    else:
        source = McapSource(session)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", TruncatedRecordingWarning)
            try:
                source.open()
            except SourceError as error:
                raise ReplayError(str(error)) from None
        sensor_ids = source.sensor_ids
    truncated = any(issubclass(w.category, TruncatedRecordingWarning) for w in caught)
    recorded = None
    if options.from_stage == "fusion":
        try:
            units = read_fused_units(session)
        except SourceError as error:
            raise ReplayError(str(error)) from None
        if not units:
            raise ReplayError(f"{session} holds no fused clouds (/fusion/cloud with /fusion/unit): replay it from "
                              "--from-stage capture")
        recorded = tuple(FusedCloud.from_world(u.points, u.T_world_bed, u.frame_ids) for u in units)
    perception = options.perception
    if options.readings_as_recorded:
        perception = replace(perception, readings=recorded_readings(session, expected))
    # a checked replay stops after as many units as it is checked against, as the run it replays stopped:
    # a live run records the frames that came while its last unit was detected, and fuses none of them
    config = RunConfig(fusion=replace(options.fusion, recorded=recorded), perception=perception,
                       grades=options.grades, live=options.realtime,
                       max_units=len(expected) if check is not None else None)
    info = None
    if session.suffix == ".mcap":
        try:
            info = read_session_info(session)
        except SourceError:  # a session cut short: its frames replay all the same
            pass
    outputs = Outputs(record=out_dir / "replay.mcap", viewer=viewer or ViewerTarget(),
                      name=f"replay of {session.name}", detections=out_dir / "detections.json", quiet=quiet,
                      bed_id=(info or {}).get("bed_id"))
    frames = Paced(source) if options.realtime else source
    try:
        summary = run_chain(frames, model, config, outputs, sensors=max(1, len(sensor_ids)),
                            on_start=on_start, stop_requested=stop_requested)
    except (SourceError, ValueError) as error:
        raise ReplayError(str(error)) from None
    if summary.frames == 0:
        raise ReplayError(f"{session} holds no readable depth frame")
    report = None
    if expected is not None:
        report = compare(expected, [d.document for d in summary.detections], check)
    return ReplayResult(summary, truncated, report)
