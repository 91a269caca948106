"""A run of the chain with its outputs: the Rerun stream, the session MCAP, the detections JSON and
the console, opened together and finalised together (what demo, live, replay and detect share)."""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from capture.source import Source
from pipeline.runner import RunConfig, Runner, RunSummary
from pipeline.viewer_target import ViewerTarget


@dataclass(frozen=True)
class Outputs:
    """Where a run writes. Each file appears whole when the run ends (a temporary name, then renamed)."""

    record: Path | None = None
    """The session MCAP: frames (with ``record_frames``), fused clouds, caps."""
    record_frames: bool = True
    bed_id: str | None = None
    """The bed the session scans, recorded with its first frame."""
    viewer: ViewerTarget = ViewerTarget()
    """Where the Rerun stream goes (``pipeline.viewer``)."""
    name: str | None = None
    """The recording's name in the viewer (the session's)."""
    detections: Path | None = None
    quiet: bool = False
    publish_to: Any = None
    """A foxglove.Context a live server serves (``capture.mcap.writer.serve_session``): every channel of the
    session MCAP is published on it as it is written, with or without ``record``."""


def run_chain(source: Source, model, config: RunConfig, outputs: Outputs, sensors: int = 1,
              on_start: Callable[[str], None] | None = None,
              stop_requested: Callable[[], str | None] = lambda: None, overwrite: bool = True) -> RunSummary:
    """Run ``source`` through fusion and perception into the ``outputs``; raises what a stage raised,
    after every output is finalised."""
    from capture.mcap.writer import McapRecorder, SessionChannels
    from pipeline.sinks import ConsoleSink, JsonSink, McapSink, RerunSink
    from pipeline.viewer import viewer_stream

    with ExitStack() as stack:
        rec = stack.enter_context(viewer_stream(outputs.viewer, outputs.name))
        sinks = [ConsoleSink(outputs.quiet)]
        if rec is not None:
            sinks.append(RerunSink(rec))
        if outputs.record is not None:
            sinks.append(McapSink(McapRecorder(outputs.record, overwrite=overwrite, context=outputs.publish_to,
                                               bed_id=outputs.bed_id), frames=outputs.record_frames))
        elif outputs.publish_to is not None:
            sinks.append(McapSink(SessionChannels(outputs.publish_to, outputs.bed_id)))
        if outputs.detections is not None:
            sinks.append(JsonSink(outputs.detections))
        return Runner(source, model, config, sinks, sensors, on_start, stop_requested).run()
