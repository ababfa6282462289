"""The Continuon app's model calls: the models a robot has, and switching the one it serves.

    GET  /api/v1/models
         -> {"success": true, "models": [{"id": "12", "name": "fast_loop · run r-... step 2000 (serving,
             promoted 2026-11-23 21:05)", "backend": "numpy" | "torch", "component", "version",
             "active": bool, "status": "serving" | "promoted before" | "refused by the gate" | "candidate",
             "activatable": bool, "why_not": str | null, "run_id", "created_at", "promoted_at",
             "demoted_at", "metrics", "gate": {...} | null}, ...]}
    POST /api/v1/models/activate  {"model_id": "12"}
         -> 200 {"success": true, "id", "component", "version", "serving", "model": Model}
            400 a body that is not {"model_id": "<string>"}; 404 no model with that id;
            409 a version the gate refused, or one never promoted, or whose checkpoint is gone

The list is, per component (vqvae, fast_loop, mid_loop), the promoted model first and then the
component's other candidates newest first (registry/promotion.history: the rows the promotion gate
recorded, refused ones included, so the app shows why a version is not served). `id` is the
registry's model row id as a string, because the app's Dart code passes it on as a String.
`backend` says what runs the weights when they are served: BrainService runs each component in
hope_models/runtime/brain_service.RUNTIMES with NumPy in this process (today all three); one
outside it would be a torch checkpoint only the trainer and the gate load.

Activation follows the rule of `promote` and `rollback` (registry/promotion.py): a version that was
promoted before (served now, demoted, or rolled away from) is served again without a new gate,
through promotion.promote, which checks that the checkpoint still holds the weights that were
gated; a version the gate refused is never forced from the app (409 with the gate's reasons:
`run_trainer.py promote --force` is a person's decision), and a candidate that was never promoted
must go through the gate again (POST /api/brain/promote). There is no second promotion path here.
"""
from __future__ import annotations

import re
from typing import Any

from flask import Blueprint, current_app, jsonify

from hope_models.components import COMPONENTS
from webapp.api.brain import wait_serving
from webapp.api.validation import get_str, json_body, query_args, query_int
from webapp.errors import ApiError

bp = Blueprint("app_models", __name__, url_prefix="/api/v1/models")

HISTORY_DEFAULT = 20
HISTORY_MAX = 200
MAX_ID = 32
_ID = re.compile(r"[0-9]{1,18}")


def _state():
    return current_app.extensions["hope"]


def backend_of(component: str) -> str:
    """What runs a component's weights when they are served (see the module doc)."""
    from hope_models.runtime.brain_service import RUNTIMES  # lazy: loads numpy

    return "numpy" if component in RUNTIMES else "torch"


def _minute(value) -> str | None:
    return f"{value:%Y-%m-%d %H:%M}" if value is not None else None


def _run_and_step(model) -> tuple[str, str]:
    """(run name, step) from the version "<run>@<step>:<sha12>"; the run id when the version is absent."""
    version = model.version or ""
    head = version.rsplit(":", 1)[0]
    run, _, step = head.rpartition("@")
    if not run:
        return model.run_id or f"model {model.id}", "?"
    return run, step


def status_of(model) -> tuple[str, str | None]:
    """(status, why it cannot be activated or None)."""
    gate = model.gate_result if isinstance(model.gate_result, dict) else {}
    if model.promoted_at is not None:
        return "serving", None
    if model.demoted_at is not None or gate.get("promoted") is True:
        return "promoted before", None
    if gate.get("passed") is False:
        reasons = [str(r) for r in gate.get("reasons") or []]
        return "refused by the gate", "refused by the gate: " + ("; ".join(reasons) if reasons else "no reason recorded")
    return "candidate", ("never promoted: gate it again (POST /api/brain/promote with its checkpoint, or "
                         "`run_trainer.py promote --checkpoint DIR`)")


def model_json(model) -> dict[str, Any]:
    """One entry of the app's model list."""
    status, why_not = status_of(model)
    run, step = _run_and_step(model)
    when = {"serving": f"serving, promoted {_minute(model.promoted_at)}",
            "promoted before": f"promoted before, demoted {_minute(model.demoted_at) or '?'}",
            "refused by the gate": f"refused by the gate {_minute(model.created_at)}",
            "candidate": f"candidate {_minute(model.created_at)}"}[status]
    gate = model.gate_result if isinstance(model.gate_result, dict) else None
    return {
        "id": str(model.id),
        "name": f"{model.component} · run {run} step {step} ({when})",
        "backend": backend_of(model.component),
        "component": model.component,
        "version": model.version,
        "active": model.promoted_at is not None,
        "status": status,
        "activatable": why_not is None,
        "why_not": why_not,
        "run_id": model.run_id,
        "created_at": model.created_at.isoformat() if model.created_at else None,
        "promoted_at": model.promoted_at.isoformat() if model.promoted_at else None,
        "demoted_at": model.demoted_at.isoformat() if model.demoted_at else None,
        "metrics": model.metrics if isinstance(model.metrics, dict) else None,
        "gate": None if gate is None else {k: gate.get(k) for k in ("passed", "promoted", "forced", "reasons", "mode")},
    }


@bp.get("")
def list_models():
    from registry import promotion  # lazy: loads sqlalchemy

    query_args("history")
    limit = query_int("history", default=HISTORY_DEFAULT, minimum=1, maximum=HISTORY_MAX)
    out = []
    with _state().registry.session(readonly=True) as s:
        for component in COMPONENTS:
            current = promotion.promoted(s, component)
            rows = [m for m in promotion.history(s, component, limit) if current is None or m.id != current.id]
            out.extend(model_json(m) for m in ([current] if current is not None else []) + rows)
    return jsonify({"success": True, "models": out})


def _model_id(body: dict) -> str:
    value = body.get("model_id")
    if not isinstance(value, str):
        raise ApiError("model_id: expected the model's id as a string (an \"id\" of GET /api/v1/models)", 400)
    text = get_str(body, "model_id", max_len=MAX_ID)  # empty, too long, lone surrogates: 400
    assert text is not None  # a string (checked above): get_str returns it, not the default
    return text.strip()


@bp.post("/activate")
def activate():
    from registry import promotion  # lazy: loads sqlalchemy
    from registry.models import Model  # lazy: loads sqlalchemy

    model_id = _model_id(json_body(allowed=("model_id",), required=("model_id",)))
    state = _state()
    with state.registry.session() as s:
        model = s.get(Model, int(model_id)) if _ID.fullmatch(model_id) else None
        if model is None:
            raise ApiError(f"model_id: no model {model_id!r} (see GET /api/v1/models)", 404)
        status, why_not = status_of(model)
        if why_not is not None:
            gate = model.gate_result if isinstance(model.gate_result, dict) else {}
            response = jsonify({"success": False, "error": f"model {model_id} ({model.version}): {why_not}",
                                "status": status, "reasons": gate.get("reasons") or []})
            response.status_code = 409
            return response
        try:
            promotion.promote(s, state.settings, model.id)
        except promotion.PromotionError as exc:
            raise ApiError(str(exc), 409) from None
        out = {"success": True, "id": str(model.id), "component": model.component, "version": model.version,
               "was": status, "model": model.to_json_obj()}
    out["serving"] = wait_serving(state.brain, out["component"], out["version"])
    return jsonify(out)
