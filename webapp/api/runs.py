"""Runs over HTTP (bearer token): list, create, read, and cancel / pause / resume.

    GET  /api/runs[?state=queued,running][&limit=50]  -> {"runs": [Run.to_json_obj(), ...]} newest first
    POST /api/runs  {"component", "data", "steps", ...}  -> 201 {"run": {...}}
    GET  /api/runs/<id>                                -> {"run": {..., "validation": held-out figures or null}}
    POST /api/runs/<id>/cancel|pause|resume            -> {"run": {...}}
    GET  /api/runs/<id>/metrics[?after=STEP][&limit=N][&events=1]
         -> {"run_id", "records": [...], "next_after": STEP | null, "more": bool}

POST /api/runs takes the fields of `run_trainer.py enqueue` (registry/run_request.py: component,
data, steps, queue, priority, max_attempts, vqvae_dir | vqvae_run and the TrainConfig overrides
such as seed, batch_size, lr, threads, checkpoint_every_steps, model_config). `data` is a path
inside $HOPE_HOME (relative paths are taken from $HOPE_HOME/datasets) or one of the configured
data_roots. Before the run exists, `data` must hold usable episodes and the model_config (with
batch_size) must fit the component, the data and the memory budget (memory_budget_mb may lower
the deployment's HOPE_MEMORY_BUDGET_MB, never raise it): daemon/run_request.preflight. Errors:
400 bad input (the message names the field), 404 unknown run, 409 a control request the run's
state refuses, 429 the queue already holds max_queued_runs runs waiting to start (queued or
starting; registry/run_request.check_queue_room).

A run's `state` is one of registry.runs.STATES; `starting` is a run sent to its queue that no worker
has taken yet, and its `waiting` says since when it waits for a worker on which queue (a queued
run held behind it says that in its own `waiting`; null otherwise). cancel and pause of a
starting run are done at once, like a queued one.

Metrics are the rows of the run's metrics.jsonl (docs/training.md): metric records {"type":
"metric", "step", "wall_time", "loss", ...} with step > `after`, in step order, at most `limit`
(default 1000, at most 5000), with the steps a resume trained again counted once. `events=1` adds
the event records (checkpoint, resume, throttle, ...) in the same step range. A client pages with
after=next_after while "more" is true; it is how the Robot Editor rebuilds a loss chart after a
page reload, before the live `run.progress` events take over.
"""
from __future__ import annotations

from pathlib import Path

from flask import Blueprint, current_app, jsonify, request

from hope_models.paths import data_roots
from registry.run_request import RunRequestError, queue_run, request_from_json
from webapp.api.validation import json_body, no_body, query_args, query_int
from webapp.errors import ApiError

bp = Blueprint("runs", __name__, url_prefix="/api/runs")
MAX_LIMIT = 1000
METRICS_DEFAULT = 1000
METRICS_MAX = 5000


def _state():
    return current_app.extensions["hope"]


def run_or_404(s, run_id: str):
    """The registry's Run row of run_id (inside session s); 404 for an unknown run."""
    from registry.models import Run  # lazy: loads sqlalchemy

    run = s.get(Run, run_id)
    if run is None:
        raise ApiError(f"no run {run_id}", 404)
    return run


def run_dir_of(run_id: str) -> str:
    """The run dir of run_id; 404 for an unknown run."""
    with _state().registry.session(readonly=True) as s:
        return run_or_404(s, run_id).run_dir


@bp.get("")
def list_runs():
    from registry import runs  # lazy: loads sqlalchemy

    query_args("state", "limit")
    states = None
    if request.args.get("state"):
        states = [x.strip() for x in request.args["state"].split(",") if x.strip()]
        unknown = [x for x in states if x not in runs.STATES]
        if unknown:
            raise ApiError(f"state: unknown {', '.join(unknown)} (states: {', '.join(runs.STATES)})", 400)
    limit = query_int("limit", default=None, minimum=1, maximum=MAX_LIMIT)
    with _state().registry.session(readonly=True) as s:
        items = runs.to_json(s, runs.list_runs(s, states=states, limit=limit))
    return jsonify({"runs": items})


@bp.post("")
def create_run():
    state = _state()
    settings = state.settings
    try:
        req = request_from_json(json_body(), allowed_roots=data_roots(settings), base=Path(settings.datasets_dir))
        obj = queue_run(state.registry, settings, req)
    except RunRequestError as exc:  # 429 when the queue is full (QueueFullError)
        raise ApiError(str(exc), exc.status, getattr(exc, "retry_after_s", None)) from None
    state.wake_daemon()
    response = jsonify({"run": obj})
    response.status_code = 201
    response.headers["Location"] = f"/api/runs/{obj['id']}"
    return response


@bp.get("/<run_id>")
def get_run(run_id: str):
    from registry import runs  # lazy: loads sqlalchemy
    from webapp.api.app_measures import held_out_figures  # lazy: loads sqlalchemy

    query_args()
    with _state().registry.session(readonly=True) as s:
        obj = runs.to_json(s, [run_or_404(s, run_id)])[0]
    # the held-out figures the gate judges (with the baselines), once the run has finished
    obj["validation"] = held_out_figures(obj["run_dir"]) if obj.get("run_dir") else None
    return jsonify({"run": obj})


@bp.get("/<run_id>/metrics")
def metrics(run_id: str):
    from hope_models.train.metrics import read_metrics  # lazy: loads mcap

    query_args("after", "limit", "events")
    after = query_int("after", default=None, minimum=0)
    limit = query_int("limit", default=METRICS_DEFAULT, minimum=1, maximum=METRICS_MAX)
    events = request.args.get("events", "0")
    if events not in ("0", "1", "true", "false"):
        raise ApiError(f"events: {events[:20]!r} is not 0 or 1", 400)
    run_dir = run_dir_of(run_id)
    floor = -1 if after is None else after
    with_events = events in ("1", "true")
    rows = []
    for step, record in _stepped(read_metrics(Path(run_dir))):
        if step > floor and (record.get("type") == "metric" or (with_events and record.get("type") == "event")):
            rows.append((step, record))
            if len(rows) > limit:
                break
    page = rows[:limit]
    if len(rows) > limit and page[0][0] != rows[limit][0]:
        # never split one step's records across pages: the next page starts after next_after
        page = [r for r in page if r[0] != rows[limit][0]]
    return jsonify({"run_id": run_id, "records": [r for _, r in page],
                     "next_after": page[-1][0] if page else after, "more": len(rows) > limit})


def _stepped(records: list[dict]):
    """(step, record) in file order, steps ascending: an event counts at the step it names in its
    payload, else at the step of the metric record before it (a run's steps only go up once
    read_metrics dropped what a resume repeated)."""
    last = 0
    for record in records:
        step = record.get("step")
        if record.get("type") == "metric" and isinstance(step, int):
            last = step
            yield step, record
        elif record.get("type") == "event":
            payload = record.get("payload")
            named = payload.get("step") if isinstance(payload, dict) else None
            yield (named if isinstance(named, int) and named >= last else last), record


def _control(run_id: str, action: str):
    from registry import runs  # lazy: loads sqlalchemy

    no_body()
    state = _state()
    with state.registry.session() as s:
        run_or_404(s, run_id)
        try:
            obj = runs.request_control(s, run_id, action).to_json_obj()
        except runs.RunError as exc:
            raise ApiError(str(exc), 409) from None
    state.wake_daemon()
    return jsonify({"run": obj})


@bp.post("/<run_id>/cancel")
def cancel(run_id: str):
    return _control(run_id, "cancel")


@bp.post("/<run_id>/pause")
def pause(run_id: str):
    return _control(run_id, "pause")


@bp.post("/<run_id>/resume")
def resume(run_id: str):
    return _control(run_id, "resume")
