"""Dispatch: start the next queued run on each queue when nothing runs there.

Per queue, at most one run is active, `starting` or `running` (registry: next_dispatchable
refuses otherwise), highest priority first, then first queued; a chain member waits for its
predecessor. A run is marked `starting` (with a fresh task id) and committed BEFORE its Celery
message is sent, so the worker child's claim() always finds the row it expects; only that claim
makes it `running`. If the send fails the run goes back to queued. A message that is sent but
never picked up (no worker serves the queue, or it was lost) leaves the run starting, which says
it waits for a worker on its queue; reconcile.py re-sends it after claim_timeout_s. The queue
holds its next run meanwhile (nothing could train it either, and a worker that comes takes the
messages in order); a cancel or pause of the starting run is done at once and frees the queue. A
duplicate or stale delivery never trains: claim() refuses a task id that is not the run's
current one, and any run that is no longer starting.

Local queues (the ones whose worker runs on this host, default just "pi") follow this host's
throttle level: no new run starts at level 2 (hot), a thermal-paused run is requeued once the
level is back to 0, and a memory-paused run is requeued once the host has its memory budget free
again (not sooner than memory_retry_s after it paused, and not again when the last automatic
requeue got no step further: a job that hits its own limit at once must not spin; it then waits
for a user's resume). Runs paused on other hosts' queues wait for a user's resume.
A local run does not start while the free space under $HOPE_HOME is below its floor, and a
disk-paused run is requeued once it is above again (disk_guard.py); the run says so in `waiting`.
Nor while learning is paused from the app (registry/learning.py): every local queue is held, runs
queued by hand included, and the first run in line says so in `waiting` until the resume.

How the job reports its run travels in the task: hope.train_run(run_id, attempt, report=...).
A local queue's worker shares this host and writes the registry ("db"). Any other queue's worker
may be on another machine, where the registry (SQLite WAL) cannot reach, so its job reports
through Redis and daemon/remote.py applies the reports ("redis"). That needs Redis; with the
embedded broker (no redis_url) every worker necessarily runs on this host (the broker is a
SQLite file here), so every queue reports "db". `serve` runs the worker itself: all "db".

The daemon reaches the worker only through the broker, by the task's name: the Celery app it
sends with is registry/broker.py's (no worker code, no torch).
"""
from __future__ import annotations

import logging
import uuid
from dataclasses import dataclass
from datetime import timedelta
from typing import Any, Callable, Iterable

from sqlalchemy import select

from daemon.disk_guard import DiskGuard
from registry import learning, runs
from registry.broker import TASK_TRAIN_RUN, celery_app
from registry.models import Run, utcnow

log = logging.getLogger(__name__)


@dataclass
class Dispatched:
    run_id: str
    queue: str
    task_id: str
    attempt: int


class Dispatcher:
    def __init__(self, registry: Any, settings: Any, *, celery_app: Any = None,
                 local_queues: Iterable[str] = ("pi",), memory_retry_s: float = 60.0,
                 remote_reports: bool = False, send: Callable[[str, int, str, str], None] | None = None):
        self.registry = registry
        self.settings = settings
        self.local_queues = set(local_queues)
        # Runs on other queues report through Redis (see the module docstring).
        self.remote_reports = bool(remote_reports and settings.redis_url)
        self.memory_retry_s = float(memory_retry_s)
        self._app = celery_app
        self._send = send  # tests may replace the broker; None = Celery send_task
        self.disk = DiskGuard(registry, settings)  # the free-space floor (daemon/disk_guard.py)

    # -- sending ---------------------------------------------------------------------------

    @property
    def app(self) -> Any:
        if self._app is None:

            self._app = celery_app(self.settings)
        return self._app

    def report_mode(self, queue: str) -> str:
        """How a job on `queue` reports its run: "db" (the registry, this host) or "redis"."""
        return "redis" if self.remote_reports and queue not in self.local_queues else "db"

    def send(self, run_id: str, attempt: int, queue: str, task_id: str) -> None:
        if self._send is not None:
            self._send(run_id, attempt, queue, task_id)
            return

        self.app.send_task(TASK_TRAIN_RUN, args=[run_id, attempt], kwargs={"report": self.report_mode(queue)},
                           queue=queue, task_id=task_id)

    # -- dispatch --------------------------------------------------------------------------

    def waiting_queues(self) -> list[str]:
        """Queues with a queued run and no running one (a cheap read; most ticks end here)."""
        with self.registry.session(readonly=True) as s:
            queued = set(s.scalars(select(Run.queue).where(Run.state == "queued").distinct()))
            busy = set(s.scalars(select(Run.queue).where(Run.state.in_(runs.ACTIVE)).distinct()))
        return sorted(queued - busy)

    def dispatch(self, throttle_level: int = 0) -> list[Dispatched]:
        """Start the next run on every idle queue; returns what was sent."""
        sent: list[Dispatched] = []
        queues = self.waiting_queues()
        held = bool(queues) and self._learning_paused()
        for queue in queues:
            local = queue in self.local_queues
            if local and held:
                self._hold_for_pause(queue)
                continue
            if local and throttle_level >= 2:
                continue  # too hot to start anything here; the run waits queued
            d = self._dispatch_one(queue, throttle_level if local else 0, local)
            if d is not None:
                sent.append(d)
        return sent

    def _learning_paused(self) -> bool:
        with self.registry.session(readonly=True) as s:
            return learning.is_paused(s)

    def _hold_for_pause(self, queue: str) -> None:
        with self.registry.session() as s:
            run = runs.next_dispatchable(s, queue)
            if run is not None:
                self.disk.hold(s, run, learning.PAUSE_HOLD)

    def _dispatch_one(self, queue: str, level: int, local: bool = True) -> Dispatched | None:
        task_id = str(uuid.uuid4())
        with self.registry.session() as s:
            run = runs.next_dispatchable(s, queue)
            if run is None:
                return None
            why = self.disk.refusal(s, run) if local else None  # a remote job writes its own disk
            if why is not None:
                self.disk.hold(s, run, why)  # stays queued, first in line, saying why
                return None
            runs.mark_dispatched(s, run, task_id, throttle_level=level)
            d = Dispatched(run.id, queue, task_id, run.attempt)
        try:
            self.send(d.run_id, d.attempt, queue, task_id)
        except Exception as exc:  # noqa: BLE001 - broker down, bad URL: keep the run queued
            self._unsend(d, exc)
            return None
        log.info("dispatched %s (attempt %d) to queue %s as task %s, reporting via %s", d.run_id, d.attempt, queue,
                 task_id, self.report_mode(queue))
        return d

    def _unsend(self, d: Dispatched, exc: BaseException) -> None:
        why = f"could not send task {d.task_id} to queue {d.queue}: {type(exc).__name__}: {exc}"
        log.warning("run %s: %s; it stays queued", d.run_id, why)
        with self.registry.session() as s:
            run = runs.get_run(s, d.run_id)
            # Only if nothing happened to it since (a very fast child could have claimed it
            # from a send that raised after all; then it is really running).
            if run.state == "starting" and run.celery_task_id == d.task_id:
                runs.transition(s, run, "queued", reason="send_failed", message=why)
                run.celery_task_id = None

    def resend(self, run_id: str) -> str | None:
        """A starting run that no child claimed in time: same attempt, new task id."""
        task_id = str(uuid.uuid4())
        with self.registry.session() as s:
            run = runs.get_run(s, run_id)
            if run.state != "starting":
                return None
            runs.resend(s, run, task_id)
            attempt, queue = run.attempt, run.queue
        try:
            self.send(run_id, attempt, queue, task_id)
        except Exception as exc:  # noqa: BLE001
            self._unsend(Dispatched(run_id, queue, task_id, attempt), exc)
            return None
        log.warning("run %s: not claimed in time (is a worker serving queue %s?); re-sent as task %s", run_id,
                    queue, task_id)
        return task_id

    # -- paused runs that the daemon paused --------------------------------------------------

    def requeue_paused(self, throttle_level: int, mem_available_mb: float | None) -> list[str]:
        """Thermal-paused runs once the level is 0; memory-paused ones once their budget is free."""
        with self.registry.session(readonly=True) as s:
            paused = s.scalars(select(Run).where(Run.state == "paused", Run.queue.in_(self.local_queues),
                                                 Run.pause_reason.in_(("thermal", "memory", "disk")))).all()
            candidates, stuck = [], []
            for r in paused:
                if not self._ready(r, throttle_level, mem_available_mb, s):
                    continue
                if r.pause_reason == "memory":
                    requeued_at, said = self._memory_marks(s, r)
                    if requeued_at and requeued_at[-1] >= r.step:  # see _say_stuck
                        if r.step not in said:
                            stuck.append(r.id)
                        continue
                candidates.append(r.id)
        for run_id in stuck:
            with self.registry.session() as s:
                self._say_stuck(s, runs.get_run(s, run_id))
        requeued = []
        for run_id in candidates:
            with self.registry.session() as s:
                run = runs.get_run(s, run_id)
                if run.state != "paused" or not self._ready(run, throttle_level, mem_available_mb, s):
                    continue
                if run.pause_reason == "thermal":
                    msg = "cooled down (throttle level 0); resumes from its last checkpoint"
                elif run.pause_reason == "disk":
                    msg = "disk space is back above the floor; resumes from its last checkpoint"
                else:
                    msg = (f"{mem_available_mb:.0f} MB available again (budget {self._budget_mb(run):.0f} MB); "
                           "resumes from its last checkpoint")
                    runs.add_event(s, run.id, "log", {"level": "info", "message": msg,
                                                      "memory_requeue_step": run.step})
                runs.transition(s, run, "queued", reason=run.pause_reason, message=msg)
                requeued.append(run_id)
                log.info("run %s requeued: %s", run_id, msg)
        return requeued

    @staticmethod
    def _memory_marks(s: Any, run: Run) -> tuple[list[int], list[int]]:
        logs = [e.payload or {} for e in runs.run_events(s, run.id, kinds=["log"])]
        return ([p["memory_requeue_step"] for p in logs if "memory_requeue_step" in p],
                [p["memory_requeue_stopped"] for p in logs if "memory_requeue_stopped" in p])

    def _say_stuck(self, s: Any, run: Run) -> None:
        """A memory-paused run whose last automatic requeue got no step further reaches its own
        limit at once: requeueing it again would only spin. It waits for a user's resume (with a
        larger memory_budget_mb, or less else running on the host); said once in its log."""
        requeued_at, said = self._memory_marks(s, run)
        if run.state != "paused" or not requeued_at or requeued_at[-1] < run.step or run.step in said:
            return
        runs.add_event(s, run.id, "log", {
            "level": "warning", "memory_requeue_stopped": run.step,
            "message": f"paused for memory again at step {run.step} without progress since the last automatic "
                       "resume; not resuming it automatically (resume it yourself, e.g. with a larger memory budget)"})

    def _budget_mb(self, run: Run) -> float:
        return float((run.config or {}).get("memory_budget_mb") or self.settings.memory_budget_mb)

    def _ready(self, run: Run, level: int, mem_available_mb: float | None, s: Any) -> bool:
        if run.pause_reason == "thermal":
            return level == 0
        if run.pause_reason == "disk":  # the dispatch floor is checked again when it starts
            return self.disk.refusal(s, run) is None
        if run.pause_reason == "memory":
            paused_for = utcnow() - (run.updated_at or utcnow())
            return (mem_available_mb is not None and mem_available_mb >= self._budget_mb(run)
                    and paused_for >= timedelta(seconds=self.memory_retry_s))
        return False


__all__ = ["Dispatched", "Dispatcher"]
