"""Runs over HTTP (bearer token): list, create, read, and cancel / pause / resume.

    GET  /api/runs[?state=queued,running][&limit=50]  -> {"runs": [Run.to_json_obj(), ...]} newest first
    POST /api/runs  {"component", "data", "steps", ...}  -> 201 {"run": {...}}
    GET  /api/runs/<id>                                -> {"run": {...}}
    POST /api/runs/<id>/cancel|pause|resume            -> {"run": {...}}

POST /api/runs takes the fields of `run_trainer.py enqueue` (daemon/run_request.py: component,
data, steps, queue, priority, max_attempts, vqvae_dir | vqvae_run and the TrainConfig overrides
such as seed, batch_size, lr, threads, checkpoint_every_steps, model_config). `data` is a path
inside $HOPE_HOME (relative paths are taken from $HOPE_HOME/datasets) or one of the configured
data_roots. Errors: 400 bad input (the message names the field), 404 unknown run, 409 a control
request the run's state refuses.
"""
from __future__ import annotations

from pathlib import Path

from flask import Blueprint, current_app, jsonify, request

from webapp.errors import ApiError

bp = Blueprint("runs", __name__, url_prefix="/api/runs")
MAX_LIMIT = 1000


def _state():
    return current_app.extensions["hope"]


def _json_body() -> dict:
    body = request.get_json(silent=True)
    if body is None:
        raise ApiError("the request body must be JSON (Content-Type: application/json)", 400)
    if not isinstance(body, dict):
        raise ApiError("the request body must be a JSON object", 400)
    return body


def _get(s, run_id: str):
    from daemon.models import Run

    run = s.get(Run, run_id)
    if run is None:
        raise ApiError(f"no run {run_id}", 404)
    return run


@bp.get("")
def list_runs():
    from daemon import runs

    states = None
    if request.args.get("state"):
        states = [x.strip() for x in request.args["state"].split(",") if x.strip()]
        unknown = [x for x in states if x not in runs.STATES]
        if unknown:
            raise ApiError(f"state: unknown {', '.join(unknown)} (states: {', '.join(runs.STATES)})", 400)
    limit = None
    if request.args.get("limit"):
        try:
            limit = int(request.args["limit"])
        except ValueError:
            raise ApiError(f"limit: {request.args['limit']!r} is not an integer", 400) from None
        if not 1 <= limit <= MAX_LIMIT:
            raise ApiError(f"limit: must be between 1 and {MAX_LIMIT}", 400)
    with _state().registry.session(readonly=True) as s:
        items = [r.to_json_obj() for r in runs.list_runs(s, states=states, limit=limit)]
    return jsonify({"runs": items})


@bp.post("")
def create_run():
    from daemon.run_request import RunRequestError, request_from_json, submit

    state = _state()
    settings = state.settings
    roots = [Path(settings.home)] + [Path(r) for r in settings.data_roots]
    try:
        req = request_from_json(_json_body(), allowed_roots=roots, base=Path(settings.datasets_dir))
        with state.registry.session() as s:
            obj = submit(s, settings, req).to_json_obj()
    except RunRequestError as exc:
        raise ApiError(str(exc), 400) from None
    state.wake_daemon()
    response = jsonify({"run": obj})
    response.status_code = 201
    response.headers["Location"] = f"/api/runs/{obj['id']}"
    return response


@bp.get("/<run_id>")
def get_run(run_id: str):
    with _state().registry.session(readonly=True) as s:
        return jsonify({"run": _get(s, run_id).to_json_obj()})


def _control(run_id: str, action: str):
    from daemon import runs

    state = _state()
    with state.registry.session() as s:
        _get(s, run_id)
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
