"""Work spread over Ray tasks (docs/DESIGN.md section 7): the same code on one machine (a local Ray) and on a
cluster (its address). Ray is an optional extra (``pip install -e '.[ray]'``); nothing imports it until
a command is asked to use it."""

from __future__ import annotations

from typing import Any, Callable, Iterator


class RayUnavailable(RuntimeError):
    """Ray could not be started or reached (one line: where, and Ray's reason)."""


def _probe(address: str | None, seconds: float = 5.0) -> None:
    """A RayUnavailable at once when nothing listens at a ``host:port`` address (Ray itself would keep
    retrying for minutes)."""
    import socket

    host, _, port = (address or "").rpartition(":")
    if not host or not port.isdigit() or "://" in address:
        return
    try:
        socket.create_connection((host, int(port)), timeout=seconds).close()
    except OSError as error:
        raise RayUnavailable(f"cannot reach the Ray cluster at {address}: {error.strerror or error}") from None


def require_ray() -> Any:
    """The ray module, or a one-line ValueError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise ValueError("--ray needs Ray: pip install -e '.[ray]'") from None
    return ray


def ray_map(function: Callable, items: list[tuple], address: str | None = None, cpus_per_task: float = 1,
            in_flight: int | None = None, on_result: Callable | None = None, shared: tuple = ()) -> Iterator[Any]:
    """``function(*shared, *item)`` for every item as Ray tasks (``shared``, e.g. a model, is put in
    Ray's object store once, not sent with every task), yielded in the items' order (with at most
    ``in_flight`` tasks submitted ahead, so results stream through a bounded window); Ray is started
    here (locally, or joining ``address``) when it is not running, and stopped at the end."""
    ray = require_ray()
    started_here = not ray.is_initialized()
    if started_here:
        _probe(address)
        try:
            ray.init(address=address, include_dashboard=False, log_to_driver=False)
        except Exception as error:  # noqa: BLE001 - Ray raises many kinds; all mean the same here
            reason = (str(error).strip().splitlines() or [type(error).__name__])[0]
            where = f"the Ray cluster at {address}" if address else "a local Ray"
            raise RayUnavailable(f"cannot start or reach {where}: {reason}") from None
    try:
        task = ray.remote(num_cpus=cpus_per_task)(function)
        refs = [ray.put(value) for value in shared]
        window = in_flight or max(2, 2 * int(ray.available_resources().get("CPU", 1) / cpus_per_task))
        pending = [task.remote(*refs, *item) for item in items[:window]]
        for index in range(len(items)):
            result = ray.get(pending[index])
            pending[index] = None  # the result leaves the window: only ``window`` are held at once
            if index + window < len(items):
                pending.append(task.remote(*refs, *items[index + window]))
            if on_result is not None:
                on_result(result)
            yield result
    finally:
        if started_here:
            ray.shutdown()
