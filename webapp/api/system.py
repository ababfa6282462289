"""GET /api/system: the host and the queue at a glance (the Robot Editor's System page).

    {"stats": <daemon.monitor sample: memory, CPU, temperature, firmware flags, sources>,
     "throttle": {"level": 0|1|2|null, "source": "daemon" | "runs" | null},
     "queue": {"counts": {state: n}, "starting": [run summary], "running": [run summary],
               "queued": [run summary, dispatch order], "paused": [run summary]},
     "process": {"pid", "rss_mb"}}

GET /api/system/history[?seconds=N]: the host over time (the System page's chart). N is an
integer from 1 to 86400 (default 3600; anything else is a 400 naming `seconds`).

    {"interval_s": <seconds between samples>, "source": "daemon" | "registry",
     "samples": [{"time": ISO-8601 UTC, "mem_percent", "mem_used_mb", "mem_available_mb",
                  "mem_total_mb", "temp_c", "cpu_percent", "throttle_level"}...]}   oldest first

Under `serve` the daemon's one-hour ring answers ("daemon"; a longer span reads the registry and
adds the samples the daemon has not written yet); the standalone webapp reads the registry, which
the daemon fills in batches about every 30 s and prunes to 24 h (daemon/system_history.py). The
live `system.stats` Socket.IO event carries the same field names and "time", so a browser appends
it to the chart it loaded here.

Under `serve` the daemon runs in this process: its last sample and its throttle level are the ones
it acts on. The standalone webapp (systemd, the daemon in another process) samples the host itself
with the same SystemMonitor, and reads the level the daemon wrote on the running runs (no running
run: unknown, null).
"""
from __future__ import annotations

import os
import threading

from flask import Blueprint, current_app, jsonify
from sqlalchemy import func, select

from registry import system_samples
from registry.models import Run
from webapp.api.validation import query_args, query_int

bp = Blueprint("system", __name__, url_prefix="/api")

LIST_LIMIT = 20
HISTORY_DEFAULT_S = 3600
HISTORY_MAX_S = 86400
_monitor_lock = threading.Lock()


def _summary(run) -> dict:
    return {"id": run.id, "component": run.component, "queue": run.queue, "state": run.state,
            "step": run.step, "total_steps": run.total_steps, "priority": run.priority,
            "pause_reason": run.pause_reason, "sequence_id": run.sequence_id, "waiting": run.waiting_text()}


def queue_summary(session) -> dict:
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
            from daemon.monitor import SystemMonitor  # lazy: loads psutil

            state.monitor = SystemMonitor(state.settings)
        return state.monitor.sample(), None, None


@bp.get("/system")
def system():
    import psutil  # lazy: loads psutil


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


@bp.get("/system/history")
def system_history():
    query_args("seconds")
    seconds = query_int("seconds", default=HISTORY_DEFAULT_S, minimum=1, maximum=HISTORY_MAX_S)
    state = current_app.extensions["hope"]
    history = getattr(state.daemon, "history", None)
    if history is not None and seconds <= history.window_s:
        return jsonify({"interval_s": history.interval_s, "source": "daemon", "samples": history.samples(seconds)})
    with state.registry.session(readonly=True) as s:
        samples = system_samples.recent_samples(s, seconds)
    if history is not None:  # what the daemon in this process has not written yet
        last = samples[-1]["time"] if samples else None
        last_at = system_samples.as_time(last) if last else None
        samples += [x for x in history.unflushed() if last_at is None or system_samples.as_time(x["time"]) > last_at]
    interval = history.interval_s if history is not None else state.settings.system_sample_s
    return jsonify({"interval_s": interval, "source": "registry", "samples": samples})
