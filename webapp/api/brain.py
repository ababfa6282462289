"""The inference runtime over HTTP: what is served, inference, promotion and rollback.

    GET  /api/brain[?history=10]
         -> {"brain": "running" | "not running in this process",
             "components": {name: {"serving": BrainService.status()[name] | null,
                                   "promoted": Model | null, "pointer": pointer file | null,
                                   "pointer_error": str | null, "history": [Model, ...]}}}
    POST /api/brain/infer     {"component": "fast_loop" | "mid_loop" | "vqvae", "observation": [floats],
                               "session"?: str, "reset"?: bool, "action"?: [floats], "frame"?: image}
         -> {"action": [floats] | null, "model_version": str, "latency_ms": float, "session": str | null,
             "code": [ints] | null, "prediction": {"0.5s": [floats], ...} | null, "surprise": float | null,
             "surprise_by_horizon": {"0.5s": float | null, ...} | null, "mid_tick": int | null,
             "mid_grid_point": int | null, "versions": {"vqvae": str | null, "fast_loop": ..., "mid_loop": ...}}
            One request is one control tick of the session; every served component that reads the
            observation's layout answers (hope_models/components/mid_loop/serving.py: `code`, the Mid Loop's
            grid points, `prediction` in raw units and `surprise` in nats, defined in
            docs/training.md "Surprise at inference"). `component` is the one the caller needs:
            503 while it is not promoted (an action needs the fast_loop; a prediction the mid_loop).
            `action`: the action the robot actually took on the previous tick (the Mid Loop's
            input; by default the fast_loop's previous answer).
            `frame`: the camera frame, for a served model that reads the camera (status:
            "frame_shape"): a base64 JPEG/PNG or a data:image/...;base64 URL (any size, resized to the
            model's), {"encoding": "jpeg"|"png", "data": base64}, {"encoding": "raw", "shape": [H, W, 3],
            "data": base64 of H*W*3 RGB bytes} at the model's size, or [H][W][3] integer lists
            (hope_models/runtime/brain_frame.py). The whole body stays within the 1 MiB limit of
            every request (413 beyond): a camera frame or a 640x480 JPEG (~60 kB) fits, a phone
            photo of several MB does not (downscale it first).
            400 an observation value that is not a number, not finite or beyond +-1e6
                (brain_service.MAX_ABS_OBSERVATION; the message gives the range); a frame that is not
                an image, truncated, declares more than 16 MP, or a raw array of another size; no
                frame for a model that reads the camera; a frame when no served model reads one
            500 the served model computed NaN/Inf from a valid observation (its fault, logged; the
                session's recurrent state is left as it was before the tick)
    POST /api/brain/promote   {"run_id": "r-..." | "checkpoint": "<dir under $HOPE_HOME or a data root>",
                               "component"?: str, "force"?: bool}
         -> 200 {"promoted": true, "model_id", "version", "reasons", "metrics", "serving"}
            409 {"error": "refused by the gate: ...", "promoted": false, ...}
            403 force without the admin credential (webapp/admin.py: the setting allow_http_force,
                off by default, and the X-Hope-Admin header); nothing is gated or served
    POST /api/brain/rollback  {"component": "fast_loop"}
         -> 200 {"model": Model, "version", "serving"}; 409 when there is nothing to roll back to

Promotion runs `run_trainer.py promote ... --json` as a child process: the gate computes validation
loss with torch, which this process never imports (webapp/commands.py). One promotion at a time.
Rollback needs no torch and runs here (registry.promotion). After either, the response waits briefly
(SERVE_WAIT_S) for BrainService to load the new pointer, so "serving" says which version now answers.
"""
from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

from flask import Blueprint, current_app, jsonify, request

from hope_models.components import COMPONENTS
from hope_models.paths import data_roots
from hope_models.promoted import PointerError, read_pointer
from registry.run_request import RunRequestError, resolve_path
from webapp.admin import force_refusal
from webapp.api.validation import get_bool, get_numbers, get_str, json_body, query_int
from webapp.errors import ApiError

log = logging.getLogger(__name__)

bp = Blueprint("brain", __name__, url_prefix="/api/brain")

MAX_OBSERVATION = 4096
MAX_SESSION = 128
MAX_RUN_ID = 64
PROMOTE_TIMEOUT_S = 900.0  # the gate: validation batches, and for a sim fast_loop a few reflex episodes
SERVE_WAIT_S = 3.0  # BrainService notices a pointer within 1 s, then loads and warms the model
_promote_lock = threading.Lock()


def _state():
    return current_app.extensions["hope"]


def _components() -> tuple[str, ...]:
    return tuple(COMPONENTS)


def _brain_status(brain) -> dict:
    if brain is None:
        return {}
    try:
        return brain.status()
    except Exception:  # noqa: BLE001 - GET /api/brain still reports the registry and the pointers
        log.exception("BrainService.status() failed")
        return {}


def serving_version(brain, component: str) -> str | None:
    return (_brain_status(brain).get(component) or {}).get("version")


def wait_serving(brain, component: str, version: str | None, timeout_s: float = SERVE_WAIT_S) -> str | None:
    """The version BrainService serves for `component`, once it is `version` or after timeout_s."""
    if brain is None or component not in _brain_status(brain):
        return None
    deadline = time.monotonic() + timeout_s
    current = serving_version(brain, component)
    while current != version and time.monotonic() < deadline:
        time.sleep(0.05)
        current = serving_version(brain, component)
    return current


@bp.get("")
def status():
    from registry import promotion  # lazy: loads sqlalchemy

    limit = query_int("history", default=10, minimum=0, maximum=100)
    state = _state()
    served = _brain_status(state.brain)
    out = {}
    with state.registry.session(readonly=True) as s:
        for component in _components():
            promoted = promotion.promoted(s, component)
            try:
                pointer, pointer_error = read_pointer(state.settings.home, component), None
            except PointerError as exc:
                pointer, pointer_error = None, str(exc)
            out[component] = {
                "serving": served.get(component),
                "promoted": promoted.to_json_obj() if promoted is not None else None,
                "pointer": pointer,
                "pointer_error": pointer_error,
                "history": [m.to_json_obj() for m in promotion.history(s, component, limit)] if limit else [],
            }
    return jsonify({"brain": "running" if state.brain is not None else "not running in this process",
                    "components": out})


@bp.post("/infer")
def infer():
    from hope_models.runtime.brain_service import BrainError  # lazy: loads numpy

    body = json_body(allowed=("component", "observation", "session", "reset", "action", "frame"),
                     required=("component", "observation"))
    component = get_str(body, "component", max_len=64)
    observation = get_numbers(body, "observation", max_len=MAX_OBSERVATION)
    session = get_str(body, "session", max_len=MAX_SESSION)
    reset = get_bool(body, "reset")
    action = get_numbers(body, "action", max_len=MAX_OBSERVATION) if body.get("action") is not None else None
    brain = _state().brain
    if brain is None:
        raise ApiError("inference is not available: BrainService is not running in this process "
                       "(start the webapp with `run_trainer.py serve` or `run_trainer.py webapp`)", 503)
    try:
        # the frame's form is brain_frame's to check (its messages name what is wrong with the image)
        return jsonify(brain.infer(component, observation, session=session, reset=reset, action=action,
                                   frame=body.get("frame")))
    except BrainError as exc:
        raise ApiError(str(exc), int(getattr(exc, "status", 400))) from None


def _checkpoint_arg(value: str) -> str:
    settings = _state().settings
    try:
        path = resolve_path("checkpoint", value, base=Path(settings.home), allowed_roots=data_roots(settings))
    except RunRequestError as exc:
        raise ApiError(str(exc), 400) from None
    if not Path(path).is_dir():
        raise ApiError(f"checkpoint: {path} is not a directory (a checkpoints/<step> dir or a run dir)", 400)
    return path


@bp.post("/promote")
def promote():
    from registry.models import Run  # lazy: loads sqlalchemy

    body = json_body(allowed=("run_id", "checkpoint", "component", "force"))
    run_id = get_str(body, "run_id", max_len=MAX_RUN_ID)
    checkpoint = get_str(body, "checkpoint")
    component = get_str(body, "component", choices=_components())
    force = get_bool(body, "force")
    if (run_id is None) == (checkpoint is None):
        raise ApiError("give run_id (a completed run) or checkpoint (a checkpoint dir), not both and not neither", 400)
    state = _state()
    if force:
        refusal = force_refusal(state.settings)
        if refusal is not None:
            log.warning("forced promotion over HTTP refused (from %s): %s", request.remote_addr, refusal)
            raise ApiError(refusal, 403)
    if run_id is not None:
        with state.registry.session(readonly=True) as s:
            if s.get(Run, run_id) is None:
                raise ApiError(f"run_id: no run {run_id} (see GET /api/runs)", 404)
        args = ["promote", run_id]
    else:
        args = ["promote", "--checkpoint", _checkpoint_arg(checkpoint)]
    if component is not None:
        args += ["--component", component]
    if force:
        args += ["--force", "--by", "http"]
    args.append("--json")
    if not _promote_lock.acquire(blocking=False):
        raise ApiError("a promotion is already running; try again when it has finished", 409)
    try:
        res = state.children.run(args, timeout_s=PROMOTE_TIMEOUT_S)
    finally:
        _promote_lock.release()
    if res.timed_out:
        raise ApiError(f"the promotion gate did not finish within {PROMOTE_TIMEOUT_S:.0f} s", 504)
    if res.code is None:  # killed: the webapp is stopping
        raise ApiError(f"the promotion was stopped before it finished: {res.error()}", 503)
    if res.output is None:  # it ended without writing its result: say so, never answer an empty success
        raise ApiError(f"the promotion gate gave no result: {res.error()}", 500)
    out = dict(res.output)
    if res.code == 0:  # promoted now, or it already was the promoted one ("already": true)
        if out.get("forced"):
            log.warning("forced promotion over HTTP (from %s, admin token): %s %s (model %s) served past the "
                        "gate's refusal: %s", request.remote_addr, out.get("component"), out.get("version"),
                        out.get("model_id"), "; ".join(map(str, out.get("reasons") or [])))
        comp = component or out.get("component") or _component_of(out)
        out["serving"] = wait_serving(state.brain, comp, out.get("version")) if comp else None
        return jsonify(out)
    if res.code == 1:
        reasons = out.get("reasons") or []
        message = "refused by the gate: " + ("; ".join(map(str, reasons)) if reasons else res.error())
        response = jsonify({**out, "error": message, "promoted": False})
        response.status_code = 409
        return response
    if res.code == 2:
        raise ApiError(res.error(), 400)
    log.error("promote %s failed (exit %s): %s", " ".join(args), res.code, res.stderr[-2000:])
    raise ApiError(f"promote failed (exit {res.code}): {res.error()}", 500)


def _component_of(out: dict) -> str | None:
    from registry.models import Model  # lazy: loads sqlalchemy

    model_id = out.get("model_id")
    if not isinstance(model_id, int):
        return None
    with _state().registry.session(readonly=True) as s:
        model = s.get(Model, model_id)
        return model.component if model is not None else None


@bp.post("/rollback")
def rollback():
    from registry import promotion  # lazy: loads sqlalchemy

    body = json_body(allowed=("component",), required=("component",))
    component = get_str(body, "component", choices=_components())
    state = _state()
    try:
        with state.registry.session() as s:
            model = promotion.rollback(s, state.settings, component)
            out = {"model": model.to_json_obj(), "version": model.version}
    except promotion.PromotionError as exc:
        raise ApiError(str(exc), 409) from None
    out["serving"] = wait_serving(state.brain, component, out["version"])
    return jsonify(out)
