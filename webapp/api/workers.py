"""GET /api/workers: the Celery workers and their queues (the Robot Editor's Workers page).

    {"heartbeat_s": <this deployment's worker_heartbeat_s>,
     "workers": [{"name": "pi@raspberrypi", "host", "pid", "queues": [...], "report": "db" | "redis",
                  "started_at", "last_seen", "stopped_at", "heartbeat_s",
                  "state": "online" | "offline" | "stopped",
                  "current": {"run_id", "component", "state", "step", "total_steps"} | null}...],
     "queues": [{"name", "queued", "starting", "running", "paused", "workers_online"}...]}

Workers: online first, then by last_seen, newest first. A worker is "offline" when no beat came for
3 of its own intervals (its heartbeat_s), "stopped" once its warm shutdown said so. `current` is the
run its pool child executes (as the worker parent reported it), with the run's live fields, while
the worker is online. Queues: every queue that has a worker or a run, by name; the counts are runs
in each state, workers_online the online workers consuming it. Times are ISO-8601 UTC.

Every worker writes its own row (a local one) or has the daemon write it from its Redis reports
(a remote one: registry/workers.py, workers/heartbeat.py), so this reads the registry only, under
`serve` and the standalone webapp alike.
"""
from __future__ import annotations

from flask import Blueprint, current_app, jsonify

from webapp.api.validation import query_args

bp = Blueprint("workers", __name__, url_prefix="/api")


@bp.get("/workers")
def list_workers():
    from registry import workers  # lazy: loads sqlalchemy

    query_args()
    state = current_app.extensions["hope"]
    with state.registry.session(readonly=True) as s:
        rows = workers.list_workers(s)
        queues = workers.queue_summary(s, rows)
    return jsonify({"heartbeat_s": state.settings.worker_heartbeat_s, "workers": rows, "queues": queues})
