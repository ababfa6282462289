"""The worker parent's heartbeat: who is connected, to which queues, doing what (the Workers page).

    hb = WorkerHeartbeat(settings, name="pi@raspberrypi", queues=["pi"])
    hb.start()      # on Celery's worker_ready (workers/celery.py): a daemon thread beats every
                    # settings.worker_heartbeat_s
    hb.stop()       # on worker_shutdown: the thread ends and the worker is marked stopped

Each beat says: name, host, pid, queues, when the worker started, and its current run. Where it goes
is decided at every beat by what this host has (report_mode):
- "db": the registry ($HOPE_HOME/hope.db) is on this host (the Pi's worker, `serve`'s worker): the
  beat writes the workers row itself (registry/workers.py);
- "redis": no registry here but a Redis URL (a worker on another machine, docs/scale-out.md): the
  beat is a "worker" report on hope:reports, which the daemon applies (daemon/remote.py);
- neither: nothing to report to yet (the registry is not created): said once in the log.
Deciding at every beat lets a worker started before the daemon's first migration appear once the
registry exists.

The current run is read from Celery's own bookkeeping in this process (celery.worker.state.
active_requests: the requests the pool is executing, with hope.train_run's run id as their first
argument). That is what this worker is actually running, whichever host holds the registry; the
runs table cannot say it (a run records its child's pid and host, not its worker's name, and two
workers on one host would be confused). registry/workers.py shows it with the run's live fields.

A database write never happens while the pool forks a child: a fork hook waits for the beat's
short transaction, so no child inherits an open SQLite connection (SQLite forbids using one across
fork, and its locks are per process). The parent never imports torch; this module imports only the
registry and Celery's worker state.
"""
from __future__ import annotations

import logging
import os
import socket
import threading
from datetime import datetime
from typing import TYPE_CHECKING, Any, Callable

from registry import workers
from registry.broker import TASK_TRAIN_RUN
from registry.db import Registry, db_path
from registry.models import utcnow
from registry.report_protocol import REPORTS_KEY, worker_report
from registry.workers import WorkerBeat

if TYPE_CHECKING:
    from hope_models.settings import Settings

log = logging.getLogger(__name__)

_fork_lock = threading.Lock()  # held by a beat's database write; a fork waits for it
_hooked = False


def _hook_fork() -> None:
    global _hooked
    if not _hooked:
        _hooked = True
        os.register_at_fork(before=_fork_lock.acquire, after_in_parent=_fork_lock.release,
                            after_in_child=_fork_lock.release)


def report_mode(settings: Settings) -> str | None:
    """"db" when the registry is on this host, else "redis" with a Redis URL, else None."""
    if db_path(settings).exists():
        return "db"
    return "redis" if settings.redis_url else None


def active_run_id() -> str | None:
    """The run id of the hope.train_run request this worker's pool executes now, if any."""
    from celery.worker import state  # lazy: loads celery


    for _ in range(3):  # the main thread may change the set while we copy it
        try:
            requests = list(state.active_requests)
            break
        except RuntimeError:
            continue
    else:
        return None
    for request in requests:
        if getattr(request, "name", None) != TASK_TRAIN_RUN:
            continue
        kwargs = request.kwargs or {}
        args = request.args or ()
        run_id = kwargs.get("run_id", args[0] if args else None)
        if isinstance(run_id, str) and run_id:
            return run_id
    return None


class WorkerHeartbeat:
    def __init__(self, settings: Settings, name: str, queues: list[str], *, interval_s: float | None = None,
                 pid: int | None = None, host: str | None = None, current: Callable[[], str | None] = active_run_id,
                 redis_client: Any = None):
        self.settings = settings
        self.name, self.queues = name, sorted(queues)
        self.interval_s = float(interval_s if interval_s is not None else settings.worker_heartbeat_s)
        self.pid = pid or os.getpid()
        self.host = host or socket.gethostname()
        self.started_at = utcnow()
        self._current = current
        self._redis = redis_client
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._failures = 0
        self._said: str | None = None
        self.beats = 0

    def start(self) -> None:
        _hook_fork()
        self._thread = threading.Thread(target=self._loop, name="hope-worker-heartbeat", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.is_set():
            self.safe_beat()
            self._stop.wait(self.interval_s)

    def stop(self, timeout: float = 5.0) -> None:
        """End the beats and say the worker stopped (best effort: a stop never waits long)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        try:
            self.beat(event="stopped")
        except Exception as exc:  # noqa: BLE001 - it turns offline after 3 intervals anyway
            log.warning("worker %s: could not record that it stopped: %s: %s", self.name, type(exc).__name__, exc)

    def snapshot(self, mode: str, at: datetime | None = None) -> WorkerBeat:
        try:
            current = self._current()
        except Exception:  # noqa: BLE001 - Celery's internals moved: report no run rather than no beat
            log.debug("worker %s: reading the active request failed", self.name, exc_info=True)
            current = None
        return WorkerBeat(name=self.name, host=self.host, pid=self.pid, queues=list(self.queues), report=mode,
                          heartbeat_s=self.interval_s, started_at=self.started_at, current_run_id=current,
                          at=at or utcnow())

    def safe_beat(self) -> None:
        try:
            mode = self.beat()
        except Exception as exc:  # noqa: BLE001 - a missed beat shows as offline, never kills the worker
            self._failures += 1
            if self._failures == 1 or self._failures % 60 == 0:
                log.warning("worker %s: heartbeat failed (%d in a row): %s: %s", self.name, self._failures,
                            type(exc).__name__, exc)
            return
        if self._failures:
            log.info("worker %s: heartbeat works again after %d failures", self.name, self._failures)
        self._failures = 0
        if mode != self._said:
            self._said = mode
            log.info("worker %s: heartbeat every %g s %s", self.name, self.interval_s,
                     {"db": "into the registry on this host", "redis": "through Redis (no registry on this host)",
                      None: "has nowhere to go yet: no registry here and no Redis URL"}[mode])

    def beat(self, event: str = "beat") -> str | None:
        mode = report_mode(self.settings)
        if mode == "db":
            self._beat_db(event)
        elif mode == "redis":
            self._beat_redis(event)
        self.beats += mode is not None
        return mode

    def _beat_db(self, event: str) -> None:
        with _fork_lock:
            registry = Registry.open(self.settings, migrate=False)
            try:
                with registry.session() as s:
                    if event == "stopped":
                        workers.mark_stopped(s, self.name, self.pid)
                    else:
                        workers.record_beat(s, self.snapshot("db"))
                        if self.beats % 720 == 0:
                            workers.prune(s)  # about hourly: rows of workers gone for a week
            finally:
                registry.close()

    def _beat_redis(self, event: str) -> None:
        if self._redis is None:
            import redis  # lazy: loads redis

            assert self.settings.redis_url is not None  # report_mode() says "redis" only with a URL
            self._redis = redis.Redis.from_url(self.settings.redis_url, socket_timeout=5, socket_connect_timeout=5)
        self._redis.rpush(REPORTS_KEY, worker_report(self.snapshot("redis"), event))


__all__ = ["WorkerHeartbeat", "active_run_id", "report_mode"]
