"""The app's learning calls: /api/learning/status|pause|resume and /api/training/status.

    GET  /api/learning/status   -> {"enabled", "running", "is_paused", "paused", "current_phase",
                                    "last_update_time", "phase", "phase_detail", "new_episodes", ...}
    POST /api/learning/pause    -> 200 {"success": true, "paused": true, "paused_runs", "paused_now"}
    POST /api/learning/resume   -> 200 {"success": true, "paused": false, "resumed_runs"}
    POST /api/learning/reset    -> 200 {"success": true, "reset_at", "forgot_watermark": {component: n},
                                        "forgot_last_auto_run": sequence id | null, "paused"}
    GET  /api/training/status   -> {"status": <the same object as /api/learning/status>}

The Continuon app (brain_client.dart getLearningStatus / pauseLearning / resumeLearning,
learning_metrics.dart SlowLoopStatus.fromJson) reads these keys. `enabled` is settings.auto_train,
`running` whether a run trains now on a local queue, `current_phase` the continuous-learning phase
(daemon/continuous.py; "waiting for data (N more)" says how many episodes are missing). pause and
resume take an empty body (the app posts none) and are idempotent; what they do is
registry/learning.py's: pause holds the daemon's local queues and pauses the runs training there,
resume resumes exactly those. reset (brain_client.dart resetLearning: an empty POST, success read
from the answer) forgets what continuous learning counted, never what it made: the watermark (the
next auto chain counts every trainable inbox episode as new again), the record of the last auto run,
and the surprise history the app charts (GET /api/training/metrics lists only Mid Loop runs
finished after it); runs, checkpoints, models and inbox episodes stay, a pause stays, a run training
now goes on (registry/learning.reset). It takes the token like every call that changes state, and
is idempotent. The state lives in the registry, so a daemon in another process
obeys it and it survives restarts.
"""
from __future__ import annotations

from flask import Blueprint, current_app, jsonify

from webapp.api.validation import no_body, query_args

bp = Blueprint("learning", __name__)


def _state():
    return current_app.extensions["hope"]


def _status() -> dict:
    from registry import learning  # lazy: loads sqlalchemy

    state = _state()
    with state.registry.session(readonly=True) as s:
        return learning.status(s, state.settings)


@bp.get("/api/learning/status")
def learning_status():
    query_args()
    return jsonify(_status())


@bp.get("/api/training/status")
def training_status():
    query_args()
    return jsonify({"status": _status()})


def _apply(action: str):
    """One of registry/learning.py's pause, resume, reset, then the daemon woken so it acts on it
    at once rather than at its next tick."""
    from registry import learning  # lazy: loads sqlalchemy

    no_body()
    state = _state()
    with state.registry.session() as s:
        out = getattr(learning, action)(s)
    state.wake_daemon()
    return jsonify({"success": True, **out})


@bp.post("/api/learning/pause")
def pause():
    return _apply("pause")


@bp.post("/api/learning/resume")
def resume():
    return _apply("resume")


@bp.post("/api/learning/reset")
def reset():
    return _apply("reset")
