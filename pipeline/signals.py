"""Stopping a run cleanly on SIGINT/SIGTERM: the loop ends after its current frame, outputs finalised."""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Any, Iterator

from capture.source import StopRequest


@contextmanager
def graceful_stop(signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[StopRequest]:
    """The first SIGINT/SIGTERM sets ``stop.requested`` so the loop ends after the current frame;
    a second one raises KeyboardInterrupt (for a source stuck in a blocking read). Signals the process
    ignores stay ignored; outside the main thread nothing is installed. Previous handlers come back
    on exit."""
    stop = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handle(signum: int, _frame: Any) -> None:
        if stop.requested:
            raise KeyboardInterrupt
        stop.requested, stop.signal = True, signal.Signals(signum).name

    previous = {sig: signal.signal(sig, handle) for sig in signals if signal.getsignal(sig) is not signal.SIG_IGN}
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
