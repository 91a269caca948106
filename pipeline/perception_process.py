"""Perception in a process of its own, for a chain that must keep up with a camera.

Fusion's Open3D calls (bilateral filter, ICP) hold Python's interpreter lock while they run, so a
perception thread beside them waits for the lock between its torch operations: on 2 cores the same
turn took 0.61 s in a thread against 0.41 s in a process (0.35 s alone). A process costs its start
(torch imported, the model sent over: a few seconds, before the source starts), which is why
only live runs use one.
"""

from __future__ import annotations

import multiprocessing
import signal
import threading

import numpy as np


class PerceptionProcessError(RuntimeError):
    """The perception process ended without answering."""


def _serve(connection, model, threads: int) -> None:
    """The child's loop: (points, clustering config, readings) in, SceneResult (or the exception) out, until None."""
    import torch

    from perception.detect import detect_points
    from pipeline.process import hand_back_freed_memory, reuse_freed_memory

    reuse_freed_memory()
    torch.set_num_threads(threads)
    # a first pass on a flat patch folds the model and sizes the buffers before the first unit comes
    grid = np.stack(np.meshgrid(np.arange(0.0, 0.2, 0.003), np.arange(0.0, 0.2, 0.003)), -1).reshape(-1, 2)
    detect_points(model, np.column_stack([grid, np.zeros(len(grid))]))
    connection.send(True)  # ready: what arrives from now on is answered at once
    while True:
        try:
            request = connection.recv()
        except EOFError:
            return
        if request is None:
            return
        points, clustering, readings = request
        try:
            answer = (True, detect_points(model, points, clustering, readings=readings))
        except Exception as error:  # noqa: BLE001 - raised again in the parent
            answer = (False, error)
        connection.send(answer)
        del answer
        hand_back_freed_memory()


class PerceptionProcess:
    """``detect_points`` run by a child process that holds its own copy of the model."""

    def __init__(self, model, threads: int):
        context = multiprocessing.get_context("spawn")  # fork would copy the parent's threads' locks
        self._connection, child = context.Pipe()
        self._process = context.Process(target=_serve, args=(child, model, threads), name="perception", daemon=True)
        # the child starts with Ctrl-C ignored (an ignored signal stays ignored across exec): the
        # parent alone handles it and then closes the child
        in_main = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if in_main else None
        try:
            self._process.start()
        finally:
            if in_main:
                signal.signal(signal.SIGINT, previous)
        child.close()
        # a live source starts once perception is ready, so that no early unit waits for the start
        try:
            self._connection.recv()
        except EOFError:
            self._process.join(timeout=1)
            raise PerceptionProcessError(f"the perception process did not start (exit code "
                                         f"{self._process.exitcode})") from None

    def detect(self, points: np.ndarray, clustering, readings: int):
        """The caps in ``points`` (bed frame), as ``detect_points`` finds them."""
        try:
            self._connection.send((np.ascontiguousarray(points), clustering, readings))
            ok, value = self._connection.recv()
        except (EOFError, BrokenPipeError, ConnectionResetError):
            self._process.join(timeout=1)
            raise PerceptionProcessError(f"the perception process ended (exit code {self._process.exitcode})") from None
        if not ok:
            raise value
        return value

    def close(self) -> None:
        """Ask the child to end, and make sure it has."""
        try:
            self._connection.send(None)
        except (BrokenPipeError, OSError):
            pass
        self._process.join(timeout=5)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()
        self._connection.close()
