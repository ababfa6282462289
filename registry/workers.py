"""The Celery workers, as their beats left them (table workers): what the Workers page shows.

    record_beat(session, WorkerBeat(...))        # insert or refresh the worker's row (a restarted
                                                 # worker, a new pid, starts a new life on the same name)
    mark_stopped(session, name, pid, at=None)    # its warm shutdown: stopped, no current run
    list_workers(session, now=None)              # [worker_json...]: online first, then last_seen desc
    queue_summary(session, workers)              # [{"name", "queued", "starting", "running", "paused",
                                                 #   "workers_online"}...] for every queue with a worker or a run
    prune(session, keep_s=KEEP_S, now=None)      # rows not seen for a week go

A worker parent beats every `heartbeat_s` (workers/heartbeat.py): a local one ("db") writes its row
here itself, a remote one ("redis") through Redis, applied by the daemon (daemon/remote.py). Its
state is read from the row: "stopped" once it said so, "offline" when no beat came for
OFFLINE_BEATS intervals (killed, its host gone, the network down), else "online". Its current job
is the run its pool child executes as the parent sees it (current_run_id), shown with the run's
live fields from the runs table while the worker is online.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import delete, func, select

from registry.models import Run, Worker, iso, utcnow

OFFLINE_BEATS = 3
KEEP_S = 7 * 24 * 3600
QUEUE_STATES = ("queued", "starting", "running", "paused")


@dataclass
class WorkerBeat:
    """One beat of a worker parent (also the payload of a remote "worker" report)."""

    name: str
    host: str
    pid: int
    queues: list[str]
    report: str
    heartbeat_s: float
    started_at: datetime
    current_run_id: str | None = None
    at: datetime = field(default_factory=utcnow)


def record_beat(session, beat: WorkerBeat) -> Worker:
    row = session.get(Worker, beat.name)
    if row is None:
        row = Worker(name=beat.name)
        session.add(row)
    row.host, row.pid, row.queues, row.report = beat.host, int(beat.pid), list(beat.queues), beat.report
    row.heartbeat_s, row.started_at, row.last_seen = float(beat.heartbeat_s), beat.started_at, beat.at
    row.current_run_id = beat.current_run_id
    row.stopped_at = None  # beating again: a restart under the same name
    return row


def mark_stopped(session, name: str, pid: int, at: datetime | None = None) -> bool:
    """The worker `name` with this `pid` stopped; False when the row is another process's (a newer
    worker took the name) or unknown."""
    row = session.get(Worker, name)
    if row is None or row.pid != int(pid):
        return False
    row.stopped_at = row.last_seen = at or utcnow()
    row.current_run_id = None
    return True


def worker_state(row: Worker, now: datetime) -> str:
    if row.stopped_at is not None:
        return "stopped"
    if now - row.last_seen > timedelta(seconds=OFFLINE_BEATS * row.heartbeat_s):
        return "offline"
    return "online"


def _current(session, row: Worker, state: str) -> dict[str, Any] | None:
    if state != "online" or not row.current_run_id:
        return None
    run = session.get(Run, row.current_run_id)
    if run is None:
        return None
    return {"run_id": run.id, "component": run.component, "state": run.state, "step": run.step,
            "total_steps": run.total_steps}


def worker_json(session, row: Worker, now: datetime) -> dict[str, Any]:
    state = worker_state(row, now)
    return {"name": row.name, "host": row.host, "pid": row.pid, "queues": list(row.queues or []),
            "report": row.report, "started_at": iso(row.started_at), "last_seen": iso(row.last_seen),
            "stopped_at": iso(row.stopped_at), "heartbeat_s": row.heartbeat_s, "state": state,
            "current": _current(session, row, state)}


def list_workers(session, now: datetime | None = None) -> list[dict[str, Any]]:
    now = now or utcnow()
    recent = now - timedelta(seconds=KEEP_S)  # a worker gone for a week is history (prune() removes it)
    rows = session.scalars(select(Worker).where(Worker.last_seen >= recent)
                           .order_by(Worker.last_seen.desc(), Worker.name)).all()
    out = [worker_json(session, r, now) for r in rows]
    return sorted(out, key=lambda w: w["state"] != "online")  # stable: last_seen desc within each group


def queue_summary(session, workers: list[dict[str, Any]]) -> list[dict[str, Any]]:
    counts: dict[str, dict[str, Any]] = {}

    def of(name: str) -> dict[str, Any]:
        return counts.setdefault(name, {"name": name, **{s: 0 for s in QUEUE_STATES}, "workers_online": 0})

    for queue, state, n in session.execute(select(Run.queue, Run.state, func.count()).group_by(Run.queue, Run.state)):
        entry = of(queue)
        if state in QUEUE_STATES:
            entry[state] = n
    for w in workers:
        for queue in w["queues"]:
            of(queue)["workers_online"] += w["state"] == "online"
    return [counts[k] for k in sorted(counts)]


def prune(session, keep_s: float = KEEP_S, now: datetime | None = None) -> int:
    before = (now or utcnow()) - timedelta(seconds=float(keep_s))
    return session.execute(delete(Worker).where(Worker.last_seen < before)).rowcount or 0


__all__ = ["KEEP_S", "OFFLINE_BEATS", "QUEUE_STATES", "WorkerBeat", "list_workers", "mark_stopped",
           "prune", "queue_summary", "record_beat", "worker_state", "worker_json"]
