"""POST /api/training/sequential: queue a chain of runs, like `run_trainer.py sequential`.

    {"components": "vqvae,fast_loop,mid_loop" | ["vqvae", "fast_loop"], "data": "ds", "steps": 2000,
     "queue"?, "priority"?, "max_attempts"?, "vqvae_dir" | "vqvae_run"?, <TrainConfig overrides>?}
    -> 201 {"sequence_id", "runs": [Run.to_json_obj(), ...]}

One run per component, in order, sharing a sequence id; each starts after the previous one
completed (daemon.dispatch.create_sequence). The fields are checked by the same code as the CLI
and POST /api/runs (registry.run_request), with `data` / `vqvae_dir` confined to $HOPE_HOME and the
configured data_roots (relative paths are taken from $HOPE_HOME/datasets); then, before any run
exists, each member's model_config and memory estimate against the dataset (run_request.preflight:
a chain shares one model_config, so it must suit every member). 429 when the queue has no room for
the chain's members under max_queued_runs (queued or starting runs of that queue).
"""
from __future__ import annotations

from pathlib import Path

from flask import Blueprint, current_app, jsonify

from hope_models.components.chain import SequenceError, parse_sequence
from hope_models.paths import data_roots
from registry.run_request import CONFIG_FIELDS, REQUEST_KEYS, RunRequestError, build_request, queue_sequence
from webapp.api.validation import json_body
from webapp.errors import ApiError

bp = Blueprint("training", __name__, url_prefix="/api/training")

MAX_COMPONENTS = 8


def _components(value) -> str:
    if isinstance(value, list):
        if not value or len(value) > MAX_COMPONENTS or not all(isinstance(v, str) and v.strip() for v in value):
            raise ApiError(f"components: expected 1 to {MAX_COMPONENTS} component names, e.g. "
                           "[\"vqvae\", \"fast_loop\"]", 400)
        return ",".join(v.strip() for v in value)
    if isinstance(value, str) and value.strip() and len(value) <= 256:
        return value
    raise ApiError("components: expected a list of component names or a comma-separated string, e.g. "
                   "\"vqvae,fast_loop,mid_loop\"", 400)


@bp.post("/sequential")
def sequential():
    from registry import runs  # lazy: loads sqlalchemy

    state = current_app.extensions["hope"]
    settings = state.settings
    keys = (REQUEST_KEYS - {"component"}) | {"components"} | set(CONFIG_FIELDS)
    body = json_body(allowed=keys, required=("components", "data"))
    try:
        names = parse_sequence(_components(body["components"]))
    except SequenceError as exc:
        raise ApiError(str(exc).replace("--sequential", "components"), 400) from None
    main = {k: body[k] for k in REQUEST_KEYS - {"component"} if k in body}
    overrides = {k: body[k] for k in CONFIG_FIELDS if k in body}
    try:
        # the fields every member shares, checked as `sequential` checks them
        req = build_request(component=names[0], **main, overrides=overrides, base=Path(settings.datasets_dir),
                            allowed_roots=data_roots(settings))
        sequence_id, members = queue_sequence(state.registry, settings, names, req)
        out = {"sequence_id": sequence_id, "runs": members}
    except (RunRequestError, runs.RunError) as exc:  # 429 when the queue is full (QueueFullError)
        raise ApiError(str(exc), getattr(exc, "status", 400), getattr(exc, "retry_after_s", None)) from None
    state.wake_daemon()
    response = jsonify(out)
    response.status_code = 201
    return response
