"""GET /api/system: the host and the queue at a glance (the Robot Editor's System page).

    {"stats": <daemon.monitor sample: memory, CPU, temperature, firmware flags, sources>,
     "throttle": {"level": 0|1|2|null, "source": "daemon" | "runs" | null},
     "queue": {"counts": {state: n}, "starting": [run summary], "running": [run summary],
               "queued": [run summary, dispatch order], "paused": [run summary]},
     "process": {"pid", "rss_mb"}}

Under `serve` the daemon runs in this process: its last sample and its throttle level are the ones
it acts on. The standalone webapp (systemd, the daemon in another process) samples the host itself
with the same SystemMonitor, and reads the level the daemon wrote on the running runs (no running
run: unknown, null).
"""
from __future__ import annotations

import threading

from flask import Blueprint, current_app, jsonify
from sqlalchemy import func, select

bp = Blueprint("system", __name__, url_prefix="/api")

LIST_LIMIT = 20
_monitor_lock = threading.Lock()


def _summary(run) -> dict:
    return {"id": run.id, "component": run.component, "queue": run.queue, "state": run.state,
            "step": run.step, "total_steps": run.total_steps, "priority": run.priority,
            "pause_reason": run.pause_reason, "sequence_id": run.sequence_id, "waiting": run.waiting_text()}


def queue_summary(session) -> dict:
    from registry.models import Run

    counts = dict(session.execute(select(Run.state, func.count()).group_by(Run.state)).all())

    def of(state: str, order):
        return [_summary(r) for r in session.scalars(select(Run).where(Run.state == state).order_by(*order)
                                                     .limit(LIST_LIMIT))]

    return {"counts": counts,
            # sent, but no worker has taken them yet (e.g. none serves their queue)
            "starting": of("starting", (Run.dispatched_at,)),
            "running": of("running", (Run.started_at,)),
            # the order the dispatcher takes them in (registry.runs.next_dispatchable)
            "queued": of("queued", (Run.priority.desc(), Run.created_at, Run.id)),
            "paused": of("paused", (Run.updated_at.desc(),))}


def _sample(state) -> tuple[dict, int | None, str | None]:
    daemon = state.daemon
    sample = getattr(daemon, "last_sample", None)
    policy = getattr(daemon, "policy", None)
    if sample is not None and policy is not None:
        return sample, policy.level, "daemon"
    with _monitor_lock:
        if state.monitor is None:
            from daemon.monitor import SystemMonitor

            state.monitor = SystemMonitor(state.settings)
        return state.monitor.sample(), None, None


@bp.get("/system")
def system():
    import os

    import psutil

    from registry.models import Run

    state = current_app.extensions["hope"]
    sample, level, source = _sample(state)
    with state.registry.session(readonly=True) as s:
        queue = queue_summary(s)
        if source is None:
            levels = list(s.scalars(select(Run.throttle_level).where(Run.state == "running")))
            if levels:
                level, source = max(levels), "runs"
    rss = psutil.Process(os.getpid()).memory_info().rss
    return jsonify({"stats": sample, "throttle": {"level": level, "source": source}, "queue": queue,
                    "process": {"pid": os.getpid(), "rss_mb": round(rss / 2**20, 1)}})
