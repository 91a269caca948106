"""One way to get frames from anything: the ``Source`` interface, its configs, and discovery.

Modelled on LeRobot's camera drivers: a config dataclass per kind, a small abstract class with
open / read / close (and iteration, and ``with``); ``capture.cameras`` registers the kinds and finds
what is attached.
RealSense, OAK, the virtual camera and MCAP replay all yield the same ``DepthFrame``.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import Iterator

from capture.frames import DepthFrame


class SourceError(RuntimeError):
    """A source could not be opened or stopped delivering (unplugged camera, unreadable file)."""


@dataclass
class StopRequest:
    """A request to end a loop after its current frame, with the signal that asked for it: set by
    ``pipeline.signals.graceful_stop``; recording and run loops check ``requested``."""

    requested: bool = False
    signal: str | None = None


class Source(abc.ABC):
    """Frames in time order. ``read()`` returns None once the stream has ended."""

    def open(self) -> None:
        """Acquire the device or file; called by ``with`` and by the first ``read``."""

    @abc.abstractmethod
    def read(self) -> DepthFrame | None:
        ...

    def close(self) -> None:
        """Release the device or file; safe to call twice."""

    @property
    def turntable(self):
        """The ``common.geometry.Turntable`` the frames are taken on when the source's own set-up says
        it (a virtual camera); None for a real camera, whose rig comes from ``calibrate``."""
        return None

    def __iter__(self) -> Iterator[DepthFrame]:
        while (frame := self.read()) is not None:
            yield frame

    def __enter__(self) -> "Source":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass(frozen=True)
class CameraInfo:
    """One attached camera, as ``mushroom-pose cameras`` lists it."""

    kind: str
    serial: str
    name: str


class Paced(Source):
    """Another source's frames, delivered no sooner than their timestamps allow: frame k comes
    (t_k - t_0) / ``speed`` seconds after the first, as a camera would deliver it."""

    def __init__(self, source: Source, speed: float = 1.0):
        if speed <= 0:
            raise ValueError(f"speed must be positive, got {speed}")
        self.source, self.speed = source, speed
        self._start: tuple[float, int] | None = None

    def open(self) -> None:
        self.source.open()

    @property
    def turntable(self):
        return self.source.turntable

    def read(self) -> DepthFrame | None:
        import time

        frame = self.source.read()
        if frame is None:
            return None
        if self._start is None:
            self._start = (time.monotonic(), frame.timestamp_ns)
        due = self._start[0] + (frame.timestamp_ns - self._start[1]) / 1e9 / self.speed
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        return frame

    def close(self) -> None:
        self.source.close()


class Interleaved(Source):
    """Several cameras as one source: one frame of each in turn (a synchronised set), ending when
    any of them ends."""

    def __init__(self, sources: list[Source]):
        if not sources:
            raise ValueError("no sources to interleave")
        self.sources = sources
        self._next = 0

    def open(self) -> None:
        for source in self.sources:
            source.open()

    def read(self) -> DepthFrame | None:
        frame = self.sources[self._next].read()
        self._next = (self._next + 1) % len(self.sources)
        return frame

    def close(self) -> None:
        for source in self.sources:
            source.close()
