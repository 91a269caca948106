"""Many recorded sessions replayed as one job (``replay SESSIONS... [--ray [ADDRESS]]``): each session runs
the same chain as a single ``replay`` (pipeline/replay.py), in this process one after another, or as
one Ray task each (docs/DESIGN.md section 7: the same code on a laptop and on a cluster). A session that
fails is one failed row of the report, never the end of the run."""

from __future__ import annotations

import dataclasses
import glob
import json
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

SESSION_SUFFIXES = (".mcap", ".db3")


@dataclass(frozen=True)
class SessionOutcome:
    """One session's row of the report."""

    session: str
    caps: int | None
    """Caps of the session's last fused unit (None when it failed)."""
    changes: list[dict]
    """Caps lost, gained or changed beyond the tolerances (with ``--check``)."""
    seconds: float
    error: str | None
    """One line saying why the session failed, or None."""

    @property
    def passed(self) -> bool:
        return self.error is None and not self.changes


def expand_sessions(arguments: list[str]) -> list[Path]:
    """Session files from paths, folders (their .mcap and .db3 files, sorted) and glob patterns, each
    once, in the order given. Raises ValueError naming an argument that matches nothing."""
    sessions: list[Path] = []
    for argument in arguments:
        path = Path(argument)
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.suffix in SESSION_SUFFIXES and p.is_file())
        elif any(mark in argument for mark in "*?["):
            found = sorted(Path(p) for p in glob.glob(argument) if Path(p).suffix in SESSION_SUFFIXES)
        else:
            found = [path]
        if not found:
            raise ValueError(f"{argument} matches no session (.mcap or .db3)")
        sessions += [p for p in found if p not in sessions]
    return sessions


@dataclass(frozen=True)
class FarmJob:
    """What every session's replay needs: picklable, so a Ray worker can run it."""

    model: str
    out_dir: str
    options: object
    """pipeline.replay.ReplayOptions"""
    tolerances: object | None
    """pipeline.check.Tolerances, or None without --check."""
    threads: int = 1


def replay_session(job: FarmJob, session: str, index: int) -> SessionOutcome:
    """One session replayed into ``out_dir/<index>-<stem>/``; any failure becomes the row's one line."""
    import torch

    from perception.weights import load_weights
    from pipeline.replay import run_replay

    started = time.perf_counter()
    threads = torch.get_num_threads()
    torch.set_num_threads(job.threads)
    try:
        model, _ = load_weights(Path(job.model))
        out = Path(job.out_dir) / f"{index:03d}-{Path(session).stem}"
        out.mkdir(parents=True, exist_ok=True)
        result = run_replay(Path(session), model, out, None, job.options, job.tolerances, quiet=True)
        last = result.summary.detections[-1] if result.summary.detections else None
        changes = [dataclasses.asdict(d) for d in result.check.regressions] if result.check else []
        return SessionOutcome(session, last.caps if last else 0, changes, time.perf_counter() - started, None)
    except Exception as error:  # noqa: BLE001 - a failed session is a row, the run goes on
        line = str(error).splitlines()[0] if str(error) else type(error).__name__
        if not isinstance(error, (ValueError, OSError)):
            line = f"{type(error).__name__}: {line} ({traceback.extract_tb(error.__traceback__)[-1].name})"
        return SessionOutcome(session, None, [], time.perf_counter() - started, line)
    finally:
        torch.set_num_threads(threads)


def replay_sessions(sessions: list[Path], job: FarmJob, ray_address: str | None = None, use_ray: bool = False,
                    on_outcome=None) -> list[SessionOutcome]:
    """Every session's outcome, in the order given: in this process one after another, or with
    ``use_ray`` as Ray tasks (on the cluster at ``ray_address``, or a local Ray started here)."""
    items = [(job, str(session), index) for index, session in enumerate(sessions)]
    if not use_ray:
        outcomes = []
        for item in items:
            outcomes.append(replay_session(*item))
            if on_outcome is not None:
                on_outcome(outcomes[-1])
        return outcomes
    from common.distributed import ray_map

    return list(ray_map(replay_session, items, ray_address, cpus_per_task=job.threads, on_result=on_outcome))


def report_document(outcomes: list[SessionOutcome]) -> dict:
    return {"sessions": [dataclasses.asdict(o) for o in outcomes]}


def write_report(outcomes: list[SessionOutcome], path: Path) -> None:
    from common.files import write_atomically

    write_atomically(path, json.dumps(report_document(outcomes), indent=1))


def report_table(outcomes: list[SessionOutcome]) -> str:
    """One row per session: caps, changes, seconds, and the error when it failed."""
    width = max([len("session")] + [len(o.session) for o in outcomes])
    lines = [f"{'session':<{width}}  {'caps':>5}  {'changes':>7}  {'seconds':>7}  result"]
    for o in outcomes:
        result = "ok" if o.passed else ("FAILED: " + o.error if o.error else "changed")
        caps = "-" if o.caps is None else str(o.caps)
        lines.append(f"{o.session:<{width}}  {caps:>5}  {len(o.changes):>7}  {o.seconds:>7.1f}  {result}")
    failed, changed = sum(o.error is not None for o in outcomes), sum(bool(o.changes) for o in outcomes)
    lines.append(f"{len(outcomes)} sessions: {len(outcomes) - failed - changed} ok, {changed} changed, {failed} failed")
    return "\n".join(lines)
