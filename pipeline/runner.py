"""The one chain behind demo, live, replay and detect on a session (docs/DESIGN.md section 5b).

A source thread reads frames into a bounded queue and hands each to the sinks that record it; fusion
takes frames as they arrive and emits a fused unit (a turn, a synchronised set of frames, a frame, or
a sliding window); perception runs on the newest unit in its own thread; sinks (Rerun, MCAP, detections
JSON, console) see every output. A live camera is never blocked: when fusion falls behind, the oldest
queued frame leaves the queue (it is already recorded) and is counted; when perception falls behind,
a waiting unit is replaced by the newer one and counted. A file source is read no faster than the
chain keeps up with, so nothing is dropped.
"""

from __future__ import annotations

import os
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

from capture.frames import DepthFrame
from capture.source import Source
from fusion.cloud import FusedCloud, FusionStage, UnitBuilder
from perception.grades import GradeTable
from perception.instances import ClusteringMethod
from perception.plan import PickConfig
from pipeline.perception_process import PerceptionProcess
from pipeline.process import hand_back_freed_memory


@dataclass(frozen=True)
class PerceptionStage:
    """The model that reads each fused unit and how its instances are clustered."""

    clustering: ClusteringMethod = "meanshift"
    """How the network's cap-centre votes are grouped into caps."""
    readings: int = 1
    """How many times the network reads each fused cloud, turned a further 360/N degrees about the
    vertical each time, its readings averaged: steadier caps for N network passes (one, so that a unit's
    caps come as its frames do; ``detect`` reads four times)."""


@dataclass(frozen=True)
class RunConfig:
    fusion: FusionStage = field(default_factory=FusionStage)
    perception: PerceptionStage = field(default_factory=PerceptionStage)
    plan: PickConfig = field(default_factory=PickConfig)
    grades: GradeTable = field(default_factory=GradeTable)
    queue_frames: int = 64
    """Frames that may wait for fusion; a live camera never waits for more room."""
    live: bool = False
    """A camera (drop the oldest waiting work when behind, and perceive in a process of its own so that
    fusion does not stall perception: ``pipeline.perception_process``) rather than a file (wait for the
    chain)."""
    max_units: int | None = None
    """Stop after this many fused units (turns of a turntable)."""
    duration_s: float | None = None
    """Stop capturing after this many seconds of wall clock (default: until the source ends)."""
    perception_threads: int | None = None
    """Torch threads while fusion runs beside perception (default: every core but one, which fusion
    keeps: both stages at full width on the same cores slow each other down more than they gain)."""


@dataclass(frozen=True)
class FusedUnit:
    """One fused cloud and where it came from, as the sinks see it."""

    index: int
    kind: str
    cloud: FusedCloud
    frames: int
    last_frame_index: int
    """Index of the unit's last frame on the ``frame`` timeline."""
    last_frame_ns: int
    """Capture time of the unit's last frame (log time of its outputs)."""
    last_arrival: float
    """``time.perf_counter()`` when the unit's last frame left the source."""
    fusion_seconds: float


@dataclass(frozen=True)
class Detection:
    """Perception's output on one unit, in the world frame, and how long it took."""

    unit: FusedUnit
    result: object
    """perception.detect.SceneResult, world frame."""
    document: dict
    """The detection document (perception.cap.Caps.to_document)."""
    perception_seconds: float
    latency_seconds: float
    """From the unit's last frame leaving the source to its detections."""


@dataclass(frozen=True)
class DetectionRecord:
    """What a run keeps of every unit it detected on: the document and the timings, not the clouds
    and per-point arrays (a day of turns would not fit in memory)."""

    unit: int
    document: dict
    caps: int
    fusion_seconds: float
    perception_seconds: float
    latency_seconds: float

    @staticmethod
    def of(detection: Detection) -> "DetectionRecord":
        return DetectionRecord(detection.unit.index, detection.document, len(detection.result.caps),
                               detection.unit.fusion_seconds, detection.perception_seconds,
                               detection.latency_seconds)


class Sink:
    """Consumes the chain's outputs; every method runs in the thread that made the output (capture
    in the source thread, fused in the fusion thread, detected in the perception thread)."""

    def captured(self, index: int, frame: DepthFrame) -> None:
        """Every frame the source delivered, dropped later or not."""

    def fused(self, unit: FusedUnit) -> None:
        """Every fused unit, handed to perception or not."""

    def detected(self, detection: Detection) -> None:
        """Every unit perception read."""

    def stats(self, name: str, value: float, frame: int, capture_ns: int) -> None:
        """A counter or latency at a point of the run (for plots over time)."""

    def failed(self, message: str, frame: int, capture_ns: int) -> None:
        """A unit fusion could not make, skipped (the run goes on)."""

    def close(self, ok: bool) -> None:
        """Finalise outputs; ``ok`` is False when the run ended by an error."""


@dataclass
class RunSummary:
    frames: int = 0
    dropped_frames: int = 0
    units: int = 0
    dropped_units: int = 0
    failed_units: int = 0
    """Units fusion could not make (views that do not overlap, a frame without depth), skipped."""
    last_failure: str | None = None
    detections: list[DetectionRecord] = field(default_factory=list)
    last_detection: Detection | None = None
    """The newest unit's whole detection (its cloud and per-point results)."""
    last_unit: FusedUnit | None = None
    stopped_by: str = "end"
    """end (the source ended), duration, turns, or a signal's name."""


_END = object()


class Runner:
    """Runs ``source`` through fusion and perception into ``sinks`` (see the module docstring)."""

    def __init__(self, source: Source, model, config: RunConfig, sinks: list[Sink],
                 sensors: int = 1, on_start: Callable[[str], None] | None = None,
                 stop_requested: Callable[[], str | None] = lambda: None):
        """``sensors``: how many cameras the source interleaves; ``on_start`` hears which fused unit
        the runner uses once the first frame has come; ``stop_requested`` returns the name of a stop
        (a signal) when the run should end early."""
        self.source, self.model, self.config, self.sinks = source, model, config, sinks
        self.sensors, self.on_start, self.stop_requested = sensors, on_start, stop_requested
        self.summary = RunSummary()
        self._frames: queue.Queue = queue.Queue(maxsize=config.queue_frames)
        self._halt = threading.Event()
        self._errors: list[BaseException] = []
        self._pending: FusedUnit | None = None
        self._detector: PerceptionProcess | None = None
        self._closed = False
        self._unit_ready = threading.Condition()
        self._lock = threading.Lock()

    # source thread -------------------------------------------------------------------------------
    def _capture(self) -> None:
        index, started = 0, time.monotonic()
        try:
            while not self._halt.is_set():
                if self.config.duration_s is not None and time.monotonic() - started >= self.config.duration_s:
                    self.summary.stopped_by = "duration"
                    break
                frame = self.source.read()
                if frame is None:
                    break
                arrival = time.perf_counter()
                for sink in self.sinks:
                    sink.captured(index, frame)
                self.summary.frames = index + 1
                self._enqueue((index, frame, arrival))
                index += 1
        except BaseException as error:  # noqa: BLE001 - handed to the main thread
            self._errors.append(error)
        finally:
            self._frames.put(_END)

    def _enqueue(self, item) -> None:
        if not self.config.live:
            while not self._halt.is_set():
                try:
                    self._frames.put(item, timeout=0.1)
                    return
                except queue.Full:
                    continue
            return
        while True:
            try:
                self._frames.put_nowait(item)
                return
            except queue.Full:
                try:
                    self._frames.get_nowait()
                    with self._lock:
                        self.summary.dropped_frames += 1
                except queue.Empty:
                    pass

    # perception thread ---------------------------------------------------------------------------
    def _offer(self, unit: FusedUnit) -> None:
        with self._unit_ready:
            if not self.config.live:
                self._unit_ready.wait_for(lambda: self._pending is None or self._errors)
            elif self._pending is not None:
                self.summary.dropped_units += 1
            self._pending = unit
            self._unit_ready.notify_all()

    def _perceive(self) -> None:
        from perception.detect import detect_points, transform_result
        from perception.instances import ClusterConfig
        from perception.plan import plan_of_result

        clustering = ClusterConfig(method=self.config.perception.clustering)
        try:
            while True:
                with self._unit_ready:
                    self._unit_ready.wait_for(lambda: self._pending is not None or self._closed)
                    unit, self._pending = self._pending, None
                    self._unit_ready.notify_all()
                if unit is None:
                    return
                started = time.perf_counter()
                cloud = unit.cloud
                readings = self.config.perception.readings
                found = (self._detector.detect(cloud.points, clustering, readings) if self._detector is not None
                         else detect_points(self.model, cloud.points, clustering, readings=readings))
                result = transform_result(found, cloud.T_world_bed, "world")
                document = {**result.caps.to_document("world", readings, self.config.grades,
                                                          self.config.plan.min_score),
                            "plan": plan_of_result(found, cloud.points, self.config.plan, cloud.T_world_bed),
                            "T_world_bed": cloud.T_world_bed.tolist()}
                now = time.perf_counter()
                detection = Detection(unit, result, document, now - started,
                                      now - unit.last_arrival)
                self.summary.detections.append(DetectionRecord.of(detection))
                self.summary.last_detection = detection
                for sink in self.sinks:
                    sink.detected(detection)
                for name, value in (("latency/perception_ms", 1000 * detection.perception_seconds),
                                    ("latency/last_frame_to_detections_ms", 1000 * detection.latency_seconds),
                                    ("counts/caps", len(result.caps)),
                                    ("counts/dropped_units", self.summary.dropped_units)):
                    self._stat(name, value, unit)
                hand_back_freed_memory()
        except BaseException as error:  # noqa: BLE001 - handed to the main thread
            self._errors.append(error)
            with self._unit_ready:
                self._unit_ready.notify_all()

    def _stat(self, name: str, value: float, unit: FusedUnit) -> None:
        for sink in self.sinks:
            sink.stats(name, value, unit.last_frame_index, unit.last_frame_ns)

    # fusion (calling thread) ---------------------------------------------------------------------
    def run(self) -> RunSummary:
        """Run until the source ends, a limit is reached, a stop is requested or a stage fails; sinks are
        closed in every case. Errors of any thread are raised here."""
        import torch

        capture = threading.Thread(target=self._capture, name="capture", daemon=True)
        perceive = threading.Thread(target=self._perceive, name="perception", daemon=True)
        ok = False
        threads = torch.get_num_threads()
        if self.config.fusion.recorded is None:
            torch.set_num_threads(self.config.perception_threads or max(1, min(threads, (os.cpu_count() or 2) - 1)))
        try:
            if self.config.live and self.config.fusion.recorded is None:  # inside: sinks close if it fails
                self._detector = PerceptionProcess(self.model, torch.get_num_threads())
            self.source.open()
            capture.start()
            perceive.start()
            self._fuse_frames()
            ok = not self._errors
        finally:
            self._halt.set()
            with self._unit_ready:
                self._closed = True
                self._unit_ready.notify_all()
            capture.join(timeout=10)
            perceive.join()
            if self._detector is not None:
                self._detector.close()
            torch.set_num_threads(threads)
            try:
                self.source.close()
            finally:
                for sink in self.sinks:
                    sink.close(ok and not self._errors)
        if self._errors:
            raise self._errors[0]
        return self.summary

    def _fuse_frames(self) -> None:
        builder: UnitBuilder | None = None
        recorded = self.config.fusion.recorded
        unit_frames, index, frame, arrival = 0, -1, None, time.perf_counter()
        while True:
            stop = self.stop_requested()
            if stop or self._errors:
                self.summary.stopped_by = stop or self.summary.stopped_by
                return
            try:
                item = self._frames.get(timeout=0.1)
            except queue.Empty:
                continue
            if item is _END:
                break
            index, frame, arrival = item
            if recorded is not None:
                continue
            if builder is None:
                builder = UnitBuilder(self.config.fusion, frame, self.sensors)
                if self.on_start is not None:
                    self.on_start(builder.describe())
            started = time.perf_counter()
            try:
                cloud = builder.add(frame)
            except ValueError as error:  # one unusable unit (no overlap, a frame without depth): the run goes on
                self._fail(str(error), index, frame)
                unit_frames = 0
                continue
            unit_frames += 1
            self._stat_frame("latency/fusion_per_frame_ms", 1000 * (time.perf_counter() - started), index, frame)
            self._stat_frame("counts/dropped_frames", self.summary.dropped_frames, index, frame)
            self._stat_frame("counts/queued_frames", self._frames.qsize(), index, frame)
            if cloud is not None:
                self._emit(cloud, builder.kind, unit_frames, index, frame, arrival, time.perf_counter() - started)
                unit_frames = 0
                if self.config.max_units is not None and self.summary.units >= self.config.max_units:
                    self.summary.stopped_by = "turns"
                    return
        if recorded is not None:
            for cloud in recorded:
                last = _frame_time(cloud, frame)
                self._emit(cloud, "recorded", len(cloud.frame_ids), index, last, arrival, 0.0)
            return
        if builder is not None and builder.pending and not self._errors:
            started = time.perf_counter()
            cloud = builder.flush()
            if cloud is not None:
                self._emit(cloud, builder.kind, unit_frames, index, frame, arrival, time.perf_counter() - started)

    def _fail(self, message: str, index: int, frame: DepthFrame) -> None:
        self.summary.failed_units += 1
        self.summary.last_failure = message
        for sink in self.sinks:
            sink.failed(message, index, frame.timestamp_ns)
        self._stat_frame("counts/failed_units", self.summary.failed_units, index, frame)

    def _stat_frame(self, name: str, value: float, index: int, frame: DepthFrame) -> None:
        for sink in self.sinks:
            sink.stats(name, value, index, frame.timestamp_ns)

    def _emit(self, cloud: FusedCloud, kind: str, frames: int, last_index: int, last: DepthFrame | int,
              arrival: float, seconds: float) -> None:
        last_ns = last if isinstance(last, int) else int(last.timestamp_ns)
        unit = FusedUnit(self.summary.units, kind, cloud, frames, last_index, last_ns, arrival, seconds)
        self.summary.units += 1
        self.summary.last_unit = unit
        for sink in self.sinks:
            sink.fused(unit)
        self._stat("latency/fusion_unit_ms", 1000 * seconds, unit)
        self._offer(unit)


def _frame_time(cloud: FusedCloud, fallback: DepthFrame | None) -> int:
    """Capture time of a recorded cloud's last frame (its id ``sensor@timestamp_ns``)."""
    if cloud.frame_ids:
        return int(cloud.frame_ids[-1].rsplit("@", 1)[1])
    return int(fallback.timestamp_ns) if fallback is not None else 0
