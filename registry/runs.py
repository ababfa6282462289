"""Every change to a run, by who asks for it: create and read (CLI, API), control from outside
(cancel / pause / resume), dispatch (the daemon), the worker child's claim / heartbeat / finish,
and recovery of a run whose child died.

The states and the one function that moves a run between them are registry/run_states.py; its
names are re-exported here, so `runs` is the one module callers need.

All functions take an open Session first (Registry.session(): one transaction, BEGIN IMMEDIATE)
and leave committing to it. Invalid requests raise RunError naming the run and the field.

`starting` is a run whose task was sent to its queue but that no worker child has claimed yet:
nothing trains it, so it is not `running` (with no worker on the queue it would stay that way),
and a cancel or pause of it is done at once. Only claim() makes it running. Its task message,
if a worker takes it later, is refused by claim() (the run is no longer starting, or the task id
is not its current one), so such a worker never trains it.

Control from outside (CLI, webapp, daemon) flows through desired_state / throttle_level on the
row; the worker child reads them between steps and reports back through finish().
"""
from __future__ import annotations

import re
from typing import Any, Iterable, cast

from sqlalchemy import CursorResult, select, update
from sqlalchemy.orm import Session

from hope_models.components import COMPONENTS
from hope_models.json_finite import finite
from registry.models import Run, new_run_id, utcnow
from registry.run_states import (
    ACTIVE,
    ALLOWED,
    CONTROL_ACTIONS,
    DESIRED_STATES,
    EVENT_KINDS,
    HEARTBEAT_FIELDS,
    OUTCOMES,
    PAUSE_REASONS,
    SHUTDOWN_MESSAGE,
    STATES,
    TERMINAL,
    RunError,
    add_event,
    events_after,
    json_dict,
    log_event,
    not_found,
    run_events,
    transition,
)

_QUEUE_RE = re.compile(r"[a-z0-9_-]+")


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


# --- create and read ----------------------------------------------------------------------

def create_run(
    s: Session,
    *,
    component: str,
    config: dict[str, Any],
    total_steps: int,
    run_dir: str,
    queue: str = "pi",
    priority: int = 0,
    max_attempts: int = 3,
    sequence_id: str | None = None,
    sequence_index: int | None = None,
    run_id: str | None = None,
    dataset_fingerprint: str | None = None,
) -> Run:
    rid = run_id or new_run_id()
    if component not in COMPONENTS:
        raise RunError(f"run {rid}: component {component!r} is not one of {', '.join(COMPONENTS)}")
    json_dict(config, f"run {rid}: config")
    if not _is_int(total_steps) or total_steps < 1:
        raise RunError(f"run {rid}: total_steps must be an integer >= 1, got {total_steps!r}")
    if not isinstance(queue, str) or not _QUEUE_RE.fullmatch(queue):
        raise RunError(f"run {rid}: queue {queue!r} must match [a-z0-9_-]+")
    if not _is_int(priority):
        raise RunError(f"run {rid}: priority must be an integer, got {priority!r}")
    if not _is_int(max_attempts) or max_attempts < 1:
        raise RunError(f"run {rid}: max_attempts must be an integer >= 1, got {max_attempts!r}")
    if not run_dir or not isinstance(run_dir, str):
        raise RunError(f"run {rid}: run_dir must be a non-empty path string, got {run_dir!r}")
    if (sequence_id is None) != (sequence_index is None):
        raise RunError(f"run {rid}: sequence_id and sequence_index go together (got {sequence_id!r}, {sequence_index!r})")
    if sequence_index is not None and (not _is_int(sequence_index) or sequence_index < 0):
        raise RunError(f"run {rid}: sequence_index must be an integer >= 0, got {sequence_index!r}")
    if s.get(Run, rid) is not None:
        raise RunError(f"run {rid} already exists")
    now = utcnow()
    run = Run(
        id=rid,
        component=component,
        config=config,
        dataset_fingerprint=dataset_fingerprint,
        queue=queue,
        priority=priority,
        sequence_id=sequence_id,
        sequence_index=sequence_index,
        state="queued",
        desired_state="run",
        throttle_level=0,
        step=0,
        total_steps=total_steps,
        attempt=1,
        max_attempts=max_attempts,
        run_dir=run_dir,
        created_at=now,
        queued_at=now,
        updated_at=now,
    )
    s.add(run)
    s.flush()
    add_event(s, rid, "state", {"state": "queued", "from": None, "reason": "created", "message": None})
    return run


def get_run(s: Session, run_id: str) -> Run:
    run = s.get(Run, run_id)
    if run is None:
        raise RunError(not_found(run_id))
    return run


def list_runs(s: Session, states: Iterable[str] | None = None, limit: int | None = None) -> list[Run]:
    """Runs, newest first."""
    query = select(Run)
    if states is not None:
        states = list(states)
        unknown = [st for st in states if st not in STATES]
        if unknown:
            raise RunError(f"unknown state(s) {', '.join(map(repr, unknown))} (states: {', '.join(STATES)})")
        query = query.where(Run.state.in_(states))
    query = query.order_by(Run.created_at.desc(), Run.id.desc())
    if limit is not None:
        query = query.limit(limit)
    return list(s.scalars(query))


def sequence_runs(s: Session, sequence_id: str) -> list[Run]:
    return list(s.scalars(select(Run).where(Run.sequence_id == sequence_id).order_by(Run.sequence_index)))


def to_json(s: Session, items: Iterable[Run]) -> list[dict[str, Any]]:
    """Run.to_json_obj() of each run, where a queued run that its queue holds back also says why
    in `waiting`: the run ahead of it (one run per queue at a time), which may itself be waiting
    for a worker. What status, the API and the Robot Editor show."""
    items = list(items)
    queues = {r.queue for r in items if r.state == "queued"}
    holders: dict[str, Run] = {}
    if queues:
        for held in s.scalars(select(Run).where(Run.queue.in_(queues), Run.state.in_(ACTIVE)).order_by(Run.id)):
            holders.setdefault(held.queue, held)
    out = []
    for run in items:
        obj = run.to_json_obj()
        ahead = holders.get(run.queue) if run.state == "queued" else None
        if ahead is not None:
            doing = "waiting for a worker" if ahead.state == "starting" else "running"
            obj["waiting"] = f"behind run {ahead.id}, {doing} on queue '{run.queue}' (one run per queue at a time)"
        out.append(obj)
    return out


# --- control from outside (CLI, webapp) ------------------------------------------------------

def request_control(s: Session, run_id: str, action: str) -> Run:
    """cancel | pause | resume. Done at once when no child runs the job; a running job is asked
    through desired_state and stops at its next control poll (the worker reports via finish())."""
    if action not in CONTROL_ACTIONS:
        raise RunError(f"run {run_id}: action {action!r} is not one of {', '.join(CONTROL_ACTIONS)}")
    run = get_run(s, run_id)
    state = run.state
    if state in TERMINAL:
        raise RunError(f"run {run_id} is {state}; nothing to {action}")
    if action == "cancel":
        if state == "running":
            if run.desired_state != "cancel":
                run.desired_state, run.requested_reason = "cancel", "user"
                run.updated_at = utcnow()
            log_event(s, run, "cancel requested by user; the job stops at its next step")
        else:  # queued, starting, paused, interrupted: no child trains it, so it ends now
            transition(s, run, "cancelled", reason="user", message="cancelled by user")
            if state == "starting":
                log_event(s, run, f"cancel requested by user; cancelled before a worker took it (task {run.celery_task_id} "
                             "is refused if a worker picks it up later)")
            else:
                log_event(s, run, "cancel requested by user; cancelled")
            _cancel_followers(s, run)
    elif action == "pause":
        if state in ("queued", "starting"):
            transition(s, run, "paused", reason="user")
            log_event(s, run, "pause requested by user; paused before it started")
        elif state == "running":
            if run.desired_state == "cancel":
                raise RunError(f"run {run_id}: a cancel is already requested; it cannot be paused")
            run.desired_state, run.requested_reason = "pause", "user"
            run.updated_at = utcnow()
            log_event(s, run, "pause requested by user; the job checkpoints and stops at its next step")
        elif state == "paused":
            log_event(s, run, f"pause requested by user; already paused ({run.pause_reason})")
        else:  # interrupted: transient, the daemon requeues it in the same transaction
            raise RunError(f"run {run_id} is interrupted and about to be requeued; pause it once it is queued")
    else:  # resume
        if state == "paused":
            transition(s, run, "queued", reason="user", message=f"resumed by user (was paused: {run.pause_reason})")
            log_event(s, run, "resume requested by user; queued")
        elif state == "running":
            if run.desired_state == "cancel":
                raise RunError(f"run {run_id}: a cancel is already requested; it cannot be resumed")
            if run.desired_state == "pause":
                run.desired_state, run.requested_reason = "run", None
                run.updated_at = utcnow()
                log_event(s, run, "resume requested by user; the pending pause is withdrawn")
            else:
                log_event(s, run, "resume requested by user; already running")
        else:  # queued, starting, interrupted: it will run
            log_event(s, run, f"resume requested by user; already {state}")
    return run


# --- dispatch (daemon) ----------------------------------------------------------------------

def _predecessor(s: Session, run: Run) -> Run | None:
    assert run.sequence_index is not None  # called only for a chain member past the first
    return s.scalars(
        select(Run).where(Run.sequence_id == run.sequence_id, Run.sequence_index == run.sequence_index - 1)
    ).first()


def _cancel_followers(s: Session, run: Run) -> None:
    """The later members of `run`'s chain can never start once it is cancelled: end them now, so
    the user sees the whole chain cancelled at once (not when its queue next frees up)."""
    if run.sequence_id is None:
        return
    for later in sequence_runs(s, run.sequence_id):
        if (later.sequence_index or 0) > (run.sequence_index or 0) and later.state not in TERMINAL | ACTIVE:
            transition(s, later, "cancelled", reason="sequence",
                       message=f"previous run {run.id} in sequence {run.sequence_id} ended cancelled")


def next_dispatchable(s: Session, queue: str) -> Run | None:
    """The run to start next on `queue`, or None (one already runs there, or nothing is ready).

    Highest priority first, then oldest queued_at. A chain member waits for its predecessor to
    complete; if the predecessor ended failed/cancelled (or is gone) the member is cancelled.
    """
    if s.scalars(select(Run.id).where(Run.queue == queue, Run.state.in_(ACTIVE)).limit(1)).first() is not None:
        return None
    while True:
        candidates = s.scalars(
            select(Run)
            .where(Run.queue == queue, Run.state == "queued")
            .order_by(Run.priority.desc(), Run.queued_at, Run.created_at, Run.id)
        ).all()
        cancelled_one = False
        for run in candidates:
            if not run.sequence_index:  # not in a chain, or its first member
                return run
            prev = _predecessor(s, run)
            if prev is not None and prev.state == "completed":
                return run
            if prev is None or prev.state in ("failed", "cancelled"):
                why = (
                    f"previous run {prev.id} in sequence {run.sequence_id} ended {prev.state}"
                    if prev is not None
                    else f"previous member #{run.sequence_index - 1} of sequence {run.sequence_id} does not exist"
                )
                transition(s, run, "cancelled", reason="sequence", message=why)
                cancelled_one = True
                break  # cancelling may unblock or cancel later members: scan again
            # predecessor still queued/running/paused/interrupted: wait, consider the next one
        if not cancelled_one:
            return None


def mark_dispatched(s: Session, run: Run, task_id: str, *, throttle_level: int = 0) -> Run:
    """queued -> starting as its task is sent; the worker child makes it running with claim().
    heartbeat_at is when the task was last sent (reconcile re-sends it after claim_timeout_s),
    dispatched_at when this attempt was first sent (what `waiting` counts from)."""
    transition(s, run, "starting", reason="dispatched",
               message=f"waiting for a worker on queue '{run.queue}' (task {task_id}, attempt {run.attempt})")
    now = utcnow()
    run.celery_task_id = task_id
    run.dispatched_at = now
    run.heartbeat_at = now
    run.worker_pid = None
    run.worker_host = None
    run.started_at = None
    run.throttle_level = throttle_level
    return run


def request_shutdown(s: Session, run: Run) -> Run:
    """The service is stopping: ask the running job to checkpoint and stop; finish() then puts it
    back to queued (attempt unchanged) instead of paused, so the next start resumes it."""
    if run.state != "running":
        raise RunError(f"run {run.id} is {run.state}; only a running run is stopped for shutdown")
    run.desired_state, run.requested_reason = "pause", "shutdown"
    run.updated_at = utcnow()
    log_event(s, run, "service stopping; the job checkpoints and is requeued")
    return run


def resend(s: Session, run: Run, task_id: str) -> Run:
    """A starting run that no child claimed: record the new task id (same attempt). The old
    task, if it ever arrives, no longer matches celery_task_id, so claim() refuses it."""
    if run.state != "starting":
        raise RunError(f"run {run.id}: only a starting (sent, unclaimed) run can be re-sent (state {run.state})")
    old = run.celery_task_id
    run.celery_task_id = task_id
    run.heartbeat_at = utcnow()
    run.updated_at = run.heartbeat_at
    log_event(s, run, f"task {old} was not picked up; re-sent as task {task_id} (attempt {run.attempt})", "warning")
    return run


# --- the worker child ---------------------------------------------------------------------

def claim(s: Session, run_id: str, task_id: str, attempt: int, host: str, pid: int) -> Run | None:
    """starting -> running: record this child as the one training the run. None if the task is
    stale (re-sent, requeued, paused, cancelled, or already claimed): then it must not train."""
    now = utcnow()
    # One guarded UPDATE, so of two deliveries racing for the run exactly one wins.
    # An UPDATE statement's result is a CursorResult (it has rowcount); Session.execute is typed Result.
    result = cast(CursorResult[Any], s.execute(
        update(Run)
        .where(
            Run.id == run_id,
            Run.celery_task_id == task_id,
            Run.attempt == attempt,
            Run.state == "starting",
            Run.worker_pid.is_(None),
        )
        .values(worker_pid=pid, worker_host=host, started_at=now, heartbeat_at=now, updated_at=now)
        .execution_options(synchronize_session=False)
    ))
    if result.rowcount != 1:
        return None
    run = s.scalars(select(Run).where(Run.id == run_id).execution_options(populate_existing=True)).one()
    waited = (now - run.dispatched_at).total_seconds() if run.dispatched_at is not None else None
    transition(s, run, "running", reason="claimed",
               message=f"pid {pid} on {host}" + (f" after {waited:.1f} s waiting" if waited is not None else ""))
    log_event(s, run, f"claimed by pid {pid} on {host} (task {task_id}, attempt {attempt})")
    return run


def heartbeat(s: Session, run_id: str, pid: int, **progress: Any) -> bool:
    """The child is alive (+ optional step/loss/steps_per_s/last_checkpoint). False when the run
    is no longer this child's (then the child should stop)."""
    unknown = set(progress) - set(HEARTBEAT_FIELDS)
    if unknown:
        raise RunError(f"run {run_id}: heartbeat fields {sorted(unknown)} are not among {', '.join(HEARTBEAT_FIELDS)}")
    now = utcnow()
    values = {k: v for k, v in finite(progress).items() if v is not None}
    result = cast(CursorResult[Any], s.execute(  # an UPDATE's result: a CursorResult, with rowcount
        update(Run)
        .where(Run.id == run_id, Run.worker_pid == pid, Run.state == "running")
        .values(heartbeat_at=now, updated_at=now, **values)
        .execution_options(synchronize_session=False)
    ))
    return result.rowcount == 1


def finish(
    s: Session,
    run_id: str,
    pid: int,
    outcome: str,
    message: str,
    *,
    step: int | None,
    last_checkpoint: str | None,
) -> Run | None:
    """Record the trainer's outcome. None (nothing written) if the run is no longer this
    child's: a stale child must not overwrite the state the daemon has moved on to."""
    if outcome not in OUTCOMES:
        raise RunError(f"run {run_id}: outcome {outcome!r} is not one of {', '.join(OUTCOMES)}")
    run = s.scalars(select(Run).where(Run.id == run_id).execution_options(populate_existing=True)).first()
    if run is None:
        raise RunError(not_found(run_id))
    if run.state != "running" or run.worker_pid != pid:
        return None
    if step is not None:
        run.step = step
    if last_checkpoint is not None:
        run.last_checkpoint = last_checkpoint
    requested = run.requested_reason
    if outcome in ("completed", "failed", "cancelled"):
        transition(s, run, outcome, reason="trainer", message=message or None)
    elif outcome in ("paused_memory", "paused_disk"):
        transition(s, run, "paused", reason=outcome.removeprefix("paused_"), message=message)
    elif requested == "shutdown":  # paused_user because the service is stopping
        transition(s, run, "queued", reason="shutdown", message=SHUTDOWN_MESSAGE)
    else:
        reason = requested or ("thermal" if run.throttle_level >= 2 else "user")
        transition(s, run, "paused", reason=reason, message=message)
    return run


# --- recovery (daemon) ----------------------------------------------------------------------

def mark_interrupted(s: Session, run: Run, why: str) -> Run:
    """A running run whose child is gone: interrupted, then at once queued for another attempt
    (it resumes from its last checkpoint), or failed when the attempts are used up."""
    transition(s, run, "interrupted", reason="lost", message=why)
    if run.attempt >= run.max_attempts:
        transition(s, run, "failed", reason="attempts", message=f"gave up after {run.attempt} attempts: {why}")
    else:
        run.attempt += 1
        transition(s, run, "queued", reason="retry", message=f"attempt {run.attempt} of {run.max_attempts} after: {why}")
    return run


__all__ = [
    # the state machine (registry/run_states.py)
    "ACTIVE", "ALLOWED", "CONTROL_ACTIONS", "DESIRED_STATES", "EVENT_KINDS", "HEARTBEAT_FIELDS", "OUTCOMES",
    "PAUSE_REASONS", "SHUTDOWN_MESSAGE", "STATES", "TERMINAL", "RunError", "add_event", "events_after", "run_events",
    "transition",
    # the changes
    "claim", "create_run", "finish", "get_run", "heartbeat", "list_runs", "mark_dispatched", "mark_interrupted",
    "next_dispatchable", "request_control", "request_shutdown", "resend", "sequence_runs", "to_json",
]
