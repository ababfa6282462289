"""Run and system events to the Robot Editor.

The worker child writes run_events rows to SQLite (the source of truth; Flask-SocketIO's message
queue works only with Redis, and the child should not care where browsers are). The daemon tails
that table (`EventTailer.poll()`: rows with id > the last one pushed) and pushes each row to an
`EventSink` under its Socket.IO name:

    progress            -> run.progress      {run_id, step, total, loss, steps_per_s, eta_s, rss_mb, ...}
    state               -> run.state         {run_id, state, from, reason, message}
    log, checkpoint     -> run.log           {run_id, kind, ...payload}
    throttle            -> system.throttle   {run_id, level, ...}
    (metric rows stay in the database: the API serves them; progress already carries the loss)

and the monitor's sample as `system.stats` every few seconds (service.py decides when).

Sinks: `SocketIOSink` (the webapp's SocketIO in this process: `serve`), `RedisEmitterSink`
(a write-only Flask-SocketIO emitter on the Redis message queue: production, where the webapp is
another process), `NullSink`, `ListSink` (tests). A sink that fails is logged and skipped: the
events are in the database, and a browser reloading the page reads them from there.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Any, Protocol

log = logging.getLogger(__name__)

EVENT_NAMES = {
    "progress": "run.progress",
    "state": "run.state",
    "log": "run.log",
    "checkpoint": "run.log",
    "throttle": "system.throttle",
}
STATS_EVENT = "system.stats"
THROTTLE_EVENT = "system.throttle"


class EventSink(Protocol):
    def emit(self, event: str, data: dict[str, Any]) -> None:
        ...


class NullSink:
    def emit(self, event: str, data: dict[str, Any]) -> None:
        pass


class ListSink:
    """Keeps every (event, data) pushed; thread-safe, for tests."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.events: list[tuple[str, dict[str, Any]]] = []

    def emit(self, event: str, data: dict[str, Any]) -> None:
        with self._lock:
            self.events.append((event, data))

    def of(self, event: str) -> list[dict[str, Any]]:
        with self._lock:
            return [d for e, d in self.events if e == event]

    def names(self) -> list[str]:
        with self._lock:
            return [e for e, _ in self.events]


class SocketIOSink:
    """The webapp's flask_socketio.SocketIO in this process (embedded `serve` mode)."""

    def __init__(self, socketio: Any, namespace: str = "/"):
        self.socketio = socketio
        self.namespace = namespace

    def emit(self, event: str, data: dict[str, Any]) -> None:
        self.socketio.emit(event, data, namespace=self.namespace)


class RedisEmitterSink:
    """A write-only Flask-SocketIO emitter through Redis: the webapp process (started with the
    same message_queue) relays to its browsers. Production mode."""

    def __init__(self, redis_url: str, namespace: str = "/", channel: str = "flask-socketio"):
        import socketio as python_socketio  # lazy: loads socketio
        from flask_socketio import SocketIO  # no app: an external-process emitter

        if not redis_url or not redis_url.startswith(("redis://", "rediss://")):
            raise ValueError(f"redis_url {redis_url!r}: the Socket.IO message queue needs a redis:// URL")
        self.redis_url = redis_url
        self.namespace = namespace
        # Our own manager, for two reasons: timeouts, so an unreachable Redis cannot stall a daemon
        # tick for minutes, and a logger that says "cannot publish" once a minute, not per event.
        manager = python_socketio.RedisManager(
            redis_url, channel=channel, write_only=True, logger=_quiet_logger(),
            redis_options={"socket_connect_timeout": 2.0, "socket_timeout": 5.0})
        self.socketio = SocketIO(message_queue=redis_url, client_manager=manager, channel=channel)

    def emit(self, event: str, data: dict[str, Any]) -> None:
        self.socketio.emit(event, data, namespace=self.namespace)


class _OncePerInterval(logging.Filter):
    """Lets a repeated message through once per `interval_s` (with a count of the ones held back)."""

    def __init__(self, interval_s: float = 60.0):
        super().__init__()
        self.interval_s = interval_s
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        key = str(record.msg)[:60]
        now = time.monotonic()
        last = self._last.get(key)
        if last is not None and now - last < self.interval_s:
            self._held[key] = self._held.get(key, 0) + 1
            return False
        self._last[key] = now
        held = self._held.pop(key, 0)
        if held:
            record.msg = f"{record.msg} ({held} more like it in the last {self.interval_s:g} s)"
        return True


def _quiet_logger() -> logging.Logger:
    logger = logging.getLogger("daemon.events.redis")
    if not any(isinstance(f, _OncePerInterval) for f in logger.filters):
        logger.addFilter(_OncePerInterval())
    return logger


def event_for(row: Any) -> tuple[str, dict[str, Any]] | None:
    """(Socket.IO event name, data) for a RunEvent row, or None for kinds not pushed."""
    name = EVENT_NAMES.get(row.kind)
    if name is None:
        return None
    payload = row.payload if isinstance(row.payload, dict) else {"value": row.payload}
    data = dict(payload)
    if name == "run.log":
        data.setdefault("kind", row.kind)
    data["run_id"] = row.run_id
    data["event_id"] = row.id
    time: Any = getattr(row, "time", None)
    data.setdefault("time", time.isoformat() if hasattr(time, "isoformat") else time)
    return name, data


class EventTailer:
    """Pushes run_events rows newer than the last one seen. Starts at the newest row (a restarted
    daemon does not replay history to browsers; it is all in the database), unless `after_id`."""

    def __init__(self, registry: Any, sink: EventSink, *, after_id: int | None = None, batch: int = 500):
        self.registry = registry
        self.sink = sink
        self.batch = batch
        self.last_id = self._newest_id() if after_id is None else int(after_id)
        self.pushed = 0
        self._sink_failed = False

    def _newest_id(self) -> int:
        from sqlalchemy import func, select  # lazy: loads sqlalchemy

        from registry.models import RunEvent  # lazy: loads sqlalchemy

        with self.registry.session(readonly=True) as s:
            return int(s.scalar(select(func.max(RunEvent.id))) or 0)

    def push(self, event: str, data: dict[str, Any]) -> bool:
        try:
            self.sink.emit(event, data)
        except Exception as exc:  # noqa: BLE001 - a browser relay must never stop the daemon
            if not self._sink_failed:
                log.warning("event sink %s failed (%s: %s); events stay in the database",
                            type(self.sink).__name__, type(exc).__name__, exc)
            self._sink_failed = True
            return False
        if self._sink_failed:
            log.info("event sink %s works again", type(self.sink).__name__)
            self._sink_failed = False
        return True

    def poll(self) -> int:
        """Push every new row (in batches); returns how many were pushed."""
        from registry import runs  # lazy: loads sqlalchemy

        count = 0
        while True:
            with self.registry.session(readonly=True) as s:
                rows = runs.events_after(s, self.last_id, limit=self.batch)
                items = [(row.id, event_for(row)) for row in rows]
            for row_id, item in items:
                self.last_id = max(self.last_id, row_id)
                if item is not None and self.push(*item):
                    count += 1
            if len(items) < self.batch:
                break
        self.pushed += count
        return count


__all__ = ["EVENT_NAMES", "EventSink", "EventTailer", "ListSink", "NullSink", "RedisEmitterSink",
           "STATS_EVENT", "SocketIOSink", "THROTTLE_EVENT", "event_for"]
