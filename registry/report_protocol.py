"""The report/control protocol between a worker's job child and the daemon: what travels.

A job reports its run through a channel (workers/report.py opens it): "db", the registry itself
(registry/report_channel.py, RegistryChannel), for a worker on the registry's host; or "redis",
for a worker on another machine. The registry is SQLite in WAL mode, whose index lives in one
host's shared memory, so it cannot be shared over a network; the remote child reaches Redis
anyway (the Celery broker), so it reports there and the daemon applies its reports
(daemon/remote.py) with RegistryChannel: one set of rules for what a report does to a run,
whichever way it travelled. The daemon decides per queue and puts it in the task:
hope.train_run(run_id, attempt, report=...).

The Redis protocol (JSON only, keys under "hope:"):
    child -> daemon  RPUSH hope:reports  {"type": claim|heartbeat|event|control_request|finish,
                                          "run_id", "task_id", "attempt", "pid", "host", "time", ...}
    daemon -> child  SET hope:claim:<run_id>:<task_id>  {"ok": true, "run": RunSnapshot}
                                                        | {"ok": false, "status", "why"}   (TTL; a child
                                                          that gives up sets it itself, NX: withdrawn)
                     SET hope:control:<run_id>          ControlRow, every daemon tick   (TTL)
A remote Celery worker PARENT (not a job) beats through the same list (workers/heartbeat.py):
    RPUSH hope:reports  {"type": "worker", "event": "beat" | "stopped", "name", "host", "pid",
                         "queues": [queue...], "heartbeat_s", "started_at": epoch s, "time": epoch s,
                         "current_run_id": run id | null}
which the daemon writes to the workers table (registry/workers.py) with report "redis".
parse_report() is the shape a report must have (the daemon drops any other). Nothing here
imports torch.
"""
from __future__ import annotations

import json
import re
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from typing import Any

from hope_models.json_finite import finite
from registry.models import Run
from registry.run_states import HEARTBEAT_FIELDS
from registry.workers import WorkerBeat

REPORT_MODES = ("db", "redis")
REPORTS_KEY = "hope:reports"
REPORT_TYPES = ("claim", "heartbeat", "event", "control_request", "finish", "worker")
WORKER_EVENTS = ("beat", "stopped")
_QUEUE_RE = re.compile(r"[a-z0-9_-]{1,64}")
REQUESTS = ("shutdown", "thermal")
ANSWER_TTL_S = 300  # claim answers and control states expire: nothing is left behind in Redis
CONTROL_TTL_S = 300
ROW_FIELDS = frozenset(HEARTBEAT_FIELDS)


def claim_key(run_id: str, task_id: str) -> str:
    return f"hope:claim:{run_id}:{task_id}"


def control_key(run_id: str) -> str:
    return f"hope:control:{run_id}"


class ChannelError(RuntimeError):
    """A report could not be made or read. `transient`: worth trying again (a locked database,
    Redis unreachable); otherwise the request itself is wrong (e.g. an unknown event kind)."""

    def __init__(self, message: str, *, transient: bool = True):
        super().__init__(message)
        self.transient = transient


class StaleDelivery(Exception):
    """The task may not train: re-sent, requeued, cancelled, already claimed, or unanswered.
    `status` goes into the task's result ("stale", "missing", "no_answer")."""

    def __init__(self, status: str, why: str):
        super().__init__(why)
        self.status, self.why = status, why


@dataclass
class RunSnapshot:
    """What a job needs of its run row, taken at claim time (the remote child has no registry).
    vqvae_run is resolved by the registry's side: vqvae_dir, or vqvae_error saying why not."""

    id: str
    component: str
    config: dict[str, Any]
    total_steps: int
    run_dir: str
    attempt: int
    step: int = 0
    vqvae_dir: str | None = None
    vqvae_error: str | None = None

    def to_json_obj(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json_obj(cls, obj: Any) -> "RunSnapshot":
        try:
            snap = cls(**obj)
        except TypeError as exc:
            raise ChannelError(f"the daemon's claim answer has a malformed run: {exc}", transient=False) from None
        if not isinstance(snap.config, dict) or not isinstance(snap.total_steps, int):
            raise ChannelError(f"the daemon's claim answer for run {snap.id} has a malformed config or total_steps",
                               transient=False)
        return snap


@dataclass
class ControlRow:
    """The run row's control fields: what the job reads between steps."""

    state: str
    worker_pid: int | None = None
    worker_host: str | None = None
    desired_state: str = "run"
    throttle_level: int = 0
    requested_reason: str | None = None

    @classmethod
    def of(cls, run: Run | None) -> "ControlRow":
        if run is None:
            return cls(state="gone")
        return cls(run.state, run.worker_pid, run.worker_host, run.desired_state, run.throttle_level,
                   run.requested_reason)

    def owned_by(self, pid: int, host: str) -> bool:
        return self.state == "running" and self.worker_pid == pid and self.worker_host == host

    def describe(self) -> str:
        return "gone" if self.state == "gone" else f"{self.state}, worker pid {self.worker_pid} on {self.worker_host}"

    def to_json_obj(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json_obj(cls, obj: Any) -> "ControlRow":
        try:
            row = cls(**obj)
        except TypeError as exc:
            raise ChannelError(f"malformed control state: {exc}") from None
        if not isinstance(row.state, str) or not isinstance(row.throttle_level, int):
            raise ChannelError(f"malformed control state: {obj!r}")
        return row


def dumps(obj: Any) -> str:
    return json.dumps(finite(obj), allow_nan=False, default=str, separators=(",", ":"))



class BadReport(ValueError):
    """A report that does not follow the protocol; the message says which field."""


def _need(msg: dict, key: str, kind: type | tuple[type, ...], *, optional: bool = False) -> Any:
    value = msg.get(key)
    if value is None and optional:
        return None
    if not isinstance(value, kind) or isinstance(value, bool):
        name = kind.__name__ if isinstance(kind, type) else " or ".join(k.__name__ for k in kind)
        raise BadReport(f"{key!r} must be {name}, got {value!r}")
    return value


def parse_report(raw: bytes | str) -> dict[str, Any]:
    """The report as a dict, checked field by field (BadReport says what is wrong)."""
    try:
        msg = json.loads(raw)
    except (ValueError, UnicodeDecodeError) as exc:
        raise BadReport(f"not JSON ({exc})") from None
    if not isinstance(msg, dict):
        raise BadReport(f"not a JSON object but {type(msg).__name__}")
    if msg.get("type") not in REPORT_TYPES:
        raise BadReport(f"type {msg.get('type')!r} is not one of {', '.join(REPORT_TYPES)}")
    if msg["type"] == "worker":
        return _parse_worker(msg)
    for key, kind in (("run_id", str), ("task_id", str), ("host", str), ("attempt", int), ("pid", int),
                      ("time", (int, float))):
        _need(msg, key, kind)
    if not msg["run_id"] or not msg["host"] or msg["attempt"] < 1 or msg["pid"] < 1:
        raise BadReport("run_id and host must be non-empty, attempt and pid >= 1")
    row = _need(msg, "row", dict, optional=True)
    if row is not None and not set(row) <= ROW_FIELDS:
        raise BadReport(f"row fields {sorted(set(row) - ROW_FIELDS)} are not among {', '.join(sorted(ROW_FIELDS))}")
    if msg["type"] == "event":
        _need(msg, "kind", str)
        _need(msg, "payload", dict)
    elif msg["type"] == "control_request" and msg.get("request") not in REQUESTS:
        raise BadReport(f"request {msg.get('request')!r} is not one of {', '.join(REQUESTS)}")
    elif msg["type"] == "finish":
        _need(msg, "outcome", str)
        _need(msg, "message", str)
        _need(msg, "step", int, optional=True)
        _need(msg, "last_checkpoint", str, optional=True)
    return msg


def _parse_worker(msg: dict) -> dict[str, Any]:
    for key, kind in (("name", str), ("host", str), ("pid", int), ("queues", list), ("heartbeat_s", (int, float)),
                      ("started_at", (int, float)), ("time", (int, float))):
        _need(msg, key, kind)
    _need(msg, "current_run_id", str, optional=True)
    if msg.get("event") not in WORKER_EVENTS:
        raise BadReport(f"event {msg.get('event')!r} is not one of {', '.join(WORKER_EVENTS)}")
    if not 0 < len(msg["name"]) <= 255 or not 0 < len(msg["host"]) <= 255 or msg["pid"] < 1:
        raise BadReport("name and host must be 1..255 characters, pid >= 1")
    if not msg["queues"] or len(msg["queues"]) > 32 or not all(
            isinstance(q, str) and _QUEUE_RE.fullmatch(q) for q in msg["queues"]):
        raise BadReport(f"queues must be 1..32 names matching [a-z0-9_-]+, got {msg['queues']!r}")
    if not 0 < msg["heartbeat_s"] <= 3600:
        raise BadReport(f"heartbeat_s must be in (0, 3600], got {msg['heartbeat_s']!r}")
    if msg.get("current_run_id") is not None and not 0 < len(msg["current_run_id"]) <= 64:
        raise BadReport("current_run_id must be 1..64 characters")
    try:
        started = datetime.fromtimestamp(msg["started_at"], timezone.utc)
        at = datetime.fromtimestamp(msg["time"], timezone.utc)
    except (OverflowError, OSError, ValueError) as exc:
        raise BadReport(f"started_at / time are not times: {exc}") from None
    msg["beat"] = WorkerBeat(name=msg["name"], host=msg["host"], pid=msg["pid"], queues=list(msg["queues"]),
                             report="redis", heartbeat_s=float(msg["heartbeat_s"]), started_at=started,
                             current_run_id=msg.get("current_run_id"), at=at)
    return msg


def worker_report(beat: WorkerBeat, event: str = "beat") -> str:
    """The report a remote worker parent pushes (workers/heartbeat.py)."""
    return dumps({"type": "worker", "event": event, "name": beat.name, "host": beat.host, "pid": beat.pid,
                  "queues": list(beat.queues), "heartbeat_s": beat.heartbeat_s,
                  "started_at": beat.started_at.timestamp(), "time": beat.at.timestamp(),
                  "current_run_id": beat.current_run_id})


__all__ = ["ANSWER_TTL_S", "CONTROL_TTL_S", "BadReport", "ChannelError", "ControlRow", "REPORTS_KEY", "REPORT_MODES",
           "REPORT_TYPES", "REQUESTS", "ROW_FIELDS", "RunSnapshot", "StaleDelivery", "WORKER_EVENTS", "claim_key",
           "control_key", "dumps", "parse_report", "worker_report"]
