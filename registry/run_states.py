"""The run state machine: the states, the moves allowed between them, transition() (the one
function that changes a run's state) and the event log every change writes.

    queued -> starting -> running -> completed | failed | cancelled
    starting -> queued (the send failed, or shutdown) | cancelled | paused (user): at once, no child
    running -> paused (user | thermal | memory) -> queued -> starting ...
    running -> interrupted (its worker died) -> queued (attempt + 1) | failed (attempts used up)
    running -> queued (shutdown; attempt unchanged)

Every state change writes a `state` RunEvent {"state", "from", "reason", "message"}, so the event
log is a complete timeline of each run. Who moves a run, and when, is registry/runs.py. Functions
take an open Session first and leave committing to it.
"""
from __future__ import annotations

import json
from typing import Any, Iterable

from sqlalchemy import select
from sqlalchemy.orm import Session

from hope_models.json_finite import finite
from registry.models import Run, RunEvent, utcnow

STATES = ("queued", "starting", "running", "paused", "completed", "failed", "cancelled", "interrupted")
TERMINAL = {"completed", "failed", "cancelled"}
# What holds its queue: the daemon starts one run per queue at a time. A starting run holds it
# too: with no worker on the queue nothing could train the next one either, and once a worker
# comes it takes the messages in order. The run's `waiting` text says why the queue stands still.
ACTIVE = {"starting", "running"}
ALLOWED: dict[str, set[str]] = {
    "queued": {"starting", "cancelled", "paused"},
    "starting": {"running", "queued", "cancelled", "paused"},
    "running": {"paused", "completed", "failed", "cancelled", "interrupted", "queued"},
    "paused": {"queued", "cancelled"},
    # + cancelled: request_control cancels an interrupted run at once (no child trains it).
    "interrupted": {"queued", "failed", "cancelled"},
    "completed": set(),
    "failed": set(),
    "cancelled": set(),
}
EVENT_KINDS = ("progress", "log", "state", "throttle", "checkpoint", "metric")
PAUSE_REASONS = ("user", "thermal", "memory", "shutdown", "disk")
DESIRED_STATES = ("run", "pause", "cancel")
CONTROL_ACTIONS = ("cancel", "pause", "resume")
# Trainer outcomes (hope_models.train.contract.OUTCOME_EXIT_CODES) that finish() accepts.
OUTCOMES = ("completed", "failed", "cancelled", "paused_memory", "paused_user", "paused_disk")
HEARTBEAT_FIELDS = ("step", "loss", "steps_per_s", "last_checkpoint")
SHUTDOWN_MESSAGE = "stopped by shutdown; resumes on next start"


class RunError(ValueError):
    """A run request that cannot be done; the message names the run id and the field."""


def not_found(run_id: str) -> str:
    """RunError's message for a run id the registry does not hold."""
    return f"no run {run_id} (see `run_trainer.py status`)"


def json_dict(value: Any, what: str) -> dict[str, Any]:
    """`value` if it is a JSON object that serialises strictly; RunError naming `what` otherwise."""
    if not isinstance(value, dict):
        raise RunError(f"{what} must be a JSON object, got {type(value).__name__}")
    try:
        json.dumps(value, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise RunError(f"{what} is not JSON-serialisable: {exc}") from None
    return value


# --- events -------------------------------------------------------------------------------

def add_event(s: Session, run_id: str, kind: str, payload: dict[str, Any]) -> RunEvent:
    if kind not in EVENT_KINDS:
        raise RunError(f"run {run_id}: event kind {kind!r} is not one of {', '.join(EVENT_KINDS)}")
    payload = json_dict(finite(payload), f"run {run_id}: {kind} event payload")
    if s.get(Run, run_id) is None:
        raise RunError(not_found(run_id))
    event = RunEvent(run_id=run_id, kind=kind, payload=payload, time=utcnow())
    s.add(event)
    s.flush()  # assigns the id
    return event


def events_after(s: Session, last_id: int, limit: int = 500) -> list[RunEvent]:
    """Events of every run with id > last_id, oldest first (the daemon's tail of the log)."""
    return list(s.scalars(select(RunEvent).where(RunEvent.id > last_id).order_by(RunEvent.id).limit(limit)))


def run_events(s: Session, run_id: str, kinds: Iterable[str] | None = None, after_id: int = 0) -> list[RunEvent]:
    query = select(RunEvent).where(RunEvent.run_id == run_id, RunEvent.id > after_id)
    if kinds is not None:
        query = query.where(RunEvent.kind.in_(list(kinds)))
    return list(s.scalars(query.order_by(RunEvent.id)))


def log_event(s: Session, run: Run, message: str, level: str = "info") -> None:
    add_event(s, run.id, "log", {"level": level, "message": message})


# --- the state machine --------------------------------------------------------------------

def transition(s: Session, run: Run, new: str, *, reason: str | None = None, message: str | None = None) -> Run:
    """Move `run` to state `new` (validated against ALLOWED) and record a state event.

    Entering queued or leaving starting/running for any other state clears what belonged to the
    last attempt's child (worker pid/host, desired state and its reason, throttle level): a
    request has been served once the child has stopped, and a requeued run starts clean.
    """
    old = run.state
    if new not in STATES:
        raise RunError(f"run {run.id}: unknown state {new!r} (states: {', '.join(STATES)})")
    if new not in ALLOWED.get(old, set()):
        raise RunError(f"run {run.id}: cannot go from {old} to {new}")
    if new == "paused" and reason not in PAUSE_REASONS:
        raise RunError(f"run {run.id}: pause reason {reason!r} is not one of {', '.join(PAUSE_REASONS)}")
    now = utcnow()
    run.state = new
    run.updated_at = now
    if old in ACTIVE and new not in ACTIVE:
        run.worker_pid = None
        run.worker_host = None
        run.desired_state = "run"
        run.requested_reason = None
        run.throttle_level = 0
    if new == "paused":
        run.pause_reason = reason
    elif old == "paused":
        run.pause_reason = None
    if new == "queued":
        # queued_at orders the line. A run the system knocked out (shutdown, lost worker, thermal
        # or memory pause) keeps its place; a user's resume re-enters at the back.
        if run.queued_at is None or (old == "paused" and reason == "user"):
            run.queued_at = now
        run.desired_state = "run"
        run.requested_reason = None
    if old == "queued" and new != "queued":
        run.error_message = None  # the daemon's hold reason (Run.waiting_text) was the queued run's
    if new in TERMINAL:
        run.finished_at = now
        if new in ("failed", "cancelled") and message:
            run.error_message = message
    add_event(s, run.id, "state", {"state": new, "from": old, "reason": reason, "message": message})
    return run


__all__ = ["ACTIVE", "ALLOWED", "CONTROL_ACTIONS", "DESIRED_STATES", "EVENT_KINDS", "HEARTBEAT_FIELDS", "OUTCOMES",
           "PAUSE_REASONS", "SHUTDOWN_MESSAGE", "STATES", "TERMINAL", "RunError", "add_event", "events_after",
           "json_dict", "log_event", "not_found", "run_events", "transition"]
