"""Continuous learning's shared state: one registry row (models.LearningState) the daemon and the
webapp both read and write, so it survives restarts and two processes agree on it.

    learning.pause(s)                  # the app's pause: hold the local queues, pause what trains
    learning.resume(s)                 # the reverse: resume exactly the runs that pause paused
    learning.is_paused(s)              # dispatch asks this every tick (daemon/dispatch.py)
    learning.record_decision(s, ...)   # the daemon's phase, written when it changes
    learning.record_auto_run(s, ...)   # an auto chain was queued: why, and for which episodes
    learning.reset(s)                  # the app's reset: forget the watermark, start the surprise history
    learning.status(s, settings)       # what GET /api/learning/status answers

The app's pause means the robot stops learning: nothing is dispatched on the daemon's local queues
(runs queued by hand wait too), and every active run there is paused as `pause` does (a control
request with reason user: a running job checkpoints and stops at its next step, a starting one is
paused at once). Those run ids are kept, so resume resumes them and no other (a run someone paused
by hand before stays paused). Both are idempotent. Which queues are local is what the daemon
wrote at its start; before any daemon has started, every queue counts.

The app's reset forgets what continuous learning has counted, never what it made: the watermark
(so the next auto chain counts every trainable inbox episode as new) and the record of the last auto
run go, `reset_at` says when, and the app's surprise history (GET /api/training/metrics) starts
after it. Runs, their checkpoints and events, the models and the inbox are untouched, a pause stays
as it is, and a run training now goes on. Idempotent: a second reset forgets nothing more.
The daemon keys its cached watermark on last_auto_sequence_id, so clearing it makes the daemon read
the (now empty) watermark again on its next tick.

The phase is the daemon's last decision (daemon/continuous.py), except that a pause and a run
training now are read fresh here, so the answer never lags a tick behind them.
"""
from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any, Iterable

from sqlalchemy import select
from sqlalchemy.orm import Session

from registry import runs
from registry.models import LearningState, Run, iso, utcnow

ROW_ID = 1
HOST_PAUSES = ("thermal", "memory", "disk")  # the reasons the daemon pauses a run for (the host's)
# the `waiting` of the first run in line on a local queue while learning is paused
PAUSE_HOLD = "held: learning is paused from the app (POST /api/learning/resume releases it)"


def read(s: Session) -> LearningState | None:
    return s.get(LearningState, ROW_ID)


def row(s: Session) -> LearningState:
    """The row, created on first use (needs a read-write session)."""
    state = s.get(LearningState, ROW_ID)
    if state is None:
        state = LearningState(id=ROW_ID, paused=False, phase="idle", updated_at=utcnow())
        s.add(state)
        s.flush()
    return state


def is_paused(s: Session) -> bool:
    state = read(s)
    return bool(state is not None and state.paused)


def set_local_queues(s: Session, queues: Iterable[str]) -> None:
    state = row(s)
    queues = sorted(set(queues))
    if state.local_queues != queues:
        state.local_queues = queues


def local_queues(s: Session) -> list[str] | None:
    """The daemon's local queues, or None (no daemon started yet: every queue counts)."""
    state = read(s)
    return list(state.local_queues) if state is not None and state.local_queues else None


def _on_queues(query, queues: list[str] | None):
    return query if queues is None else query.where(Run.queue.in_(queues))


def active_runs(s: Session, queues: list[str] | None) -> list[Run]:
    return list(s.scalars(_on_queues(select(Run).where(Run.state.in_(runs.ACTIVE)), queues)
                          .order_by(Run.created_at)))


# -- pause / resume (the app) ----------------------------------------------------------------

def hold_active(s: Session, queues: list[str] | None = None) -> list[str]:
    """While paused: pause every active run on the local queues that is not asked to stop yet
    (a run a worker claimed after the pause, say); returns the ids it paused now."""
    state = row(s)
    if not state.paused:
        return []
    if queues is None:
        queues = local_queues(s)
    done = []
    for run in active_runs(s, queues):
        if run.state == "running" and run.desired_state != "run":
            continue  # already asked to pause (or to cancel, which a pause cannot override)
        runs.request_control(s, run.id, "pause")
        runs.log_event(s, run, "paused because learning was paused from the app")
        done.append(run.id)
    if done:
        state.paused_runs = sorted(set(state.paused_runs or []) | set(done))
    return done


def pause(s: Session) -> dict[str, Any]:
    """The app's pause (idempotent): hold the local queues and pause what trains there."""
    state = row(s)
    if not state.paused:
        state.paused, state.paused_at, state.paused_runs = True, utcnow(), []
    paused_now = hold_active(s)
    return {"paused": True, "paused_at": iso(state.paused_at), "paused_runs": list(state.paused_runs or []),
            "paused_now": paused_now}


def resume(s: Session) -> dict[str, Any]:
    """The app's resume (idempotent): release the queues and resume the runs the pause paused
    that are still paused by it (or still only asked to pause)."""
    state = row(s)
    resumed = []
    for run_id in state.paused_runs or []:
        run = s.get(Run, run_id)
        if run is None:
            continue
        user_paused = run.state == "paused" and run.pause_reason == "user"
        pending = run.state == "running" and run.desired_state == "pause" and run.requested_reason == "user"
        if user_paused or pending:
            runs.request_control(s, run_id, "resume")
            resumed.append(run_id)
    for held in s.scalars(select(Run).where(Run.state == "queued", Run.error_message == PAUSE_HOLD)):
        held.error_message = None  # its `waiting` said the pause held it
    was_paused = state.paused
    state.paused, state.paused_at, state.paused_runs = False, None, None
    return {"paused": False, "was_paused": was_paused, "resumed_runs": resumed}


# -- the daemon's decision and the auto runs --------------------------------------------------

def record_decision(s: Session, phase: str, detail: str | None, decision: dict[str, Any] | None = None, *,
                    min_interval_s: float = 15.0, now: datetime | None = None) -> bool:
    """Write the daemon's decision when it changed: at once for a new phase, at most every
    min_interval_s when only its detail moved (a temperature, a free-memory figure)."""
    state = row(s)
    now = now or utcnow()
    if state.phase == phase and state.phase_detail == detail:
        return False
    if state.phase == phase and state.phase_at is not None and \
            now - state.phase_at < timedelta(seconds=min_interval_s):
        return False
    state.phase, state.phase_detail, state.decision, state.phase_at = phase, detail, decision, now
    return True


def watermark(s: Session) -> dict[str, set[str]]:
    """Per component, the inbox episodes its last auto run was queued for."""
    state = read(s)
    marks = (state.watermark if state is not None else None) or {}
    return {component: set(ids) for component, ids in marks.items()}


def record_auto_run(s: Session, sequence_id: str, reason: str, episodes: dict[str, Iterable[str]],
                    now: datetime | None = None) -> None:
    """An auto chain was queued for `episodes` (per component, the trainable inbox episodes it
    trains on): they are no longer new for those components."""
    state = row(s)
    marks = dict(state.watermark or {})
    marks.update({component: sorted(ids) for component, ids in episodes.items()})
    state.watermark = marks
    state.last_auto_sequence_id, state.last_auto_reason = sequence_id, reason
    state.last_auto_at = now or utcnow()


def reset(s: Session, now: datetime | None = None) -> dict[str, Any]:
    """The app's reset (the module doc): what it forgot, and when."""
    state = row(s)
    marks = state.watermark or {}
    forgot = {component: len(ids) for component, ids in marks.items()}
    last = state.last_auto_sequence_id
    state.watermark = None
    state.last_auto_sequence_id = state.last_auto_at = state.last_auto_reason = None
    state.reset_at = now or utcnow()
    return {"reset_at": iso(state.reset_at), "forgot_watermark": forgot, "forgot_last_auto_run": last,
            "paused": bool(state.paused)}


def reset_at(s: Session) -> datetime | None:
    state = read(s)
    return state.reset_at if state is not None else None


# -- what the app reads -------------------------------------------------------------------------

def current_phase(s: Session) -> tuple[str, str | None, Run | None]:
    """(phase, detail, the active run): a pause and a run training now read fresh, else the
    daemon's last decision."""
    state = read(s)
    if state is not None and state.paused:
        held = len(state.paused_runs or [])
        return "paused", f"paused from the app; {held} run(s) paused by it, the local queues held", None
    active = active_runs(s, local_queues(s))
    if active:
        run = next((r for r in active if r.state == "running"), active[0])
        return f"training {run.component}", f"run {run.id} step {run.step}/{run.total_steps}", run
    if state is None:
        return "idle", None, None
    return state.phase, state.phase_detail, None


def status(s: Session, settings: Any) -> dict[str, Any]:
    state = read(s)
    phase, detail, active = current_phase(s)
    decision = (state.decision if state is not None else None) or {}
    shown = phase
    if phase == "waiting for data" and decision.get("more_needed") is not None:
        shown = f"waiting for data ({decision['more_needed']} more)"
    times = [t for t in (state.phase_at if state else None, state.paused_at if state else None,
                         active.updated_at if active is not None else None) if t is not None]
    paused = bool(state is not None and state.paused)
    return {
        "enabled": bool(settings.auto_train),
        "running": active is not None and active.state == "running",
        "is_paused": paused,
        "paused": paused,
        "current_phase": shown,
        "phase": phase,
        "phase_detail": detail,
        "last_update_time": iso(max(times) if times else utcnow()),
        "active_run": active.id if active is not None else None,
        "new_episodes": decision.get("new_episodes"),
        "min_new_episodes": int(settings.auto_train_min_new_episodes),
        "components": list(settings.auto_train_components),
        "next_components": decision.get("next_components"),
        "inbox": str(settings.inbox_dir),
        "paused_runs": list(state.paused_runs or []) if state is not None else [],
        "reset_at": iso(state.reset_at) if state is not None else None,
        "last_auto_run": None if state is None or state.last_auto_sequence_id is None else {
            "sequence_id": state.last_auto_sequence_id, "at": iso(state.last_auto_at),
            "reason": state.last_auto_reason},
    }


__all__ = ["HOST_PAUSES", "PAUSE_HOLD", "active_runs", "current_phase", "hold_active", "is_paused", "local_queues", "pause",
           "read", "record_auto_run", "record_decision", "reset", "reset_at", "resume", "row", "set_local_queues",
           "status", "watermark"]
