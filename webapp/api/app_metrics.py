"""The Continuon app's learning screens: loss and curiosity charts, progress, benchmarks.

    GET /api/training/metrics[?limit=N]     (N: 1..5000, default 200)
        -> {"success": true,
            "loss_history": [{"timestamp": ISO 8601, "value": float, "label": "fast_loop · run r-... · step 400"}],
            "curiosity_history": [...same shape, one point per completed mid_loop run...],
            "surprise_history": [...same shape, in nats...],
            "surprise": float | null, "curiosity": float | null,
            "surprise_source": {"run_id", "step", "n_codes", "code_groups", "finished_at"} | null,
            "runs": [{"id", "component", "state", "step", "total_steps"}]}
    GET /api/learning/progress
        -> {"total_steps": int, "total_episodes": int, "learning_updates": int,
            "avg_parameter_change": float | null, "parameter_change": {component: float},
            "learning_rate": float | null, "learning_rate_run": str | null,
            "is_stable": bool, "stability_notes": [str]}
    GET /api/training/benchmarks[?limit=N]  (N: 1..500, default 50)
        -> {"success": true, "benchmarks": [{"id": "gate-12", "timestamp": ISO 8601, "score": float,
            "model_version": str, "details": {"model_id": "12", "component", "score_kind", "higher_is_better",
            "passed", "promoted", "reasons", ...}}]}   newest first

What each number is (webapp/api/app_measures.py and docs/app.md say it exactly):
- loss_history: the training loss of the latest run (or the latest chain's runs) from their
  metrics.jsonl, evenly thinned to at most `limit` points with the first and the newest kept;
- surprise: the latest completed mid_loop run's validation cross-entropy, in nats per predicted
  code, on the dataset's held-out validation episodes (summary.val.loss of its result.json);
  curiosity: surprise / ln(number of codes an observation can take), 0 = fully predictable, 1 = no
  better than chance.
  Both null until a mid_loop has completed with a validation split: never a made-up 0;
  surprise_history and curiosity_history hold only the runs finished after the app's last
  POST /api/learning/reset (registry/learning.reset);
- total_steps: optimizer steps of every run in the registry; total_episodes: the distinct
  episodes in the ingest manifests of the inbox and of the datasets runs trained on;
  learning_updates: models ever promoted; avg_parameter_change: the mean over components of the
  relative L2 change of the served weights against the ones they replaced (null with nothing to
  compare); learning_rate: the newest logged lr of the newest run that has started; is_stable:
  no recent run stopped on a non-finite loss, gradient or weights;
- benchmarks: one per gated candidate (the models table): for a sim fast_loop the gate's reflex
  mean return (score_kind "reflex_mean_return", higher is better), else its validation loss
  ("val_loss", lower is better); a candidate the gate could measure neither for is left out.
"""
from __future__ import annotations

from datetime import datetime
from typing import Any

from flask import Blueprint, current_app, jsonify
from sqlalchemy import select

from hope_models.components import ACTOR
from registry import learning
from registry.models import Model
from webapp.api import app_measures as measures
from webapp.api.validation import query_args, query_int

bp = Blueprint("app_metrics", __name__, url_prefix="/api")

METRICS_DEFAULT, METRICS_MAX = 200, 5000
VALIDATIONS_MAX = 200  # mid_loop runs read for the curiosity chart (one result.json each)
BENCH_DEFAULT, BENCH_MAX = 50, 500


def _state():
    return current_app.extensions["hope"]


def _series(validations: list[dict], key: str, limit: int) -> list[dict]:
    points = [measures.point(v["finished_at"], v[key], f"mid_loop · run {v['run_id']} · step {v['step']}")
              for v in validations if v[key] is not None and v["finished_at"]]
    return measures.thin(points, limit)


@bp.get("/training/metrics")
def training_metrics():
    query_args("limit")
    limit = query_int("limit", default=METRICS_DEFAULT, minimum=1, maximum=METRICS_MAX)
    with _state().registry.session(readonly=True) as s:
        runs = measures.latest_runs(s)
        run_rows = [{"id": r.id, "component": r.component, "state": r.state, "step": r.step,
                     "total_steps": r.total_steps} for r in runs]
        loss = [p for run in runs for p in measures.loss_points(run)]
        validations = measures.mid_loop_validations(s, min(limit, VALIDATIONS_MAX))
        reset_at = learning.reset_at(s)
    last = validations[-1] if validations else None
    # The charts start at the app's last reset (registry/learning.reset); the current figure stays the
    # newest one measured, which a reset does not make untrue.
    if reset_at is not None:
        validations = [v for v in validations if v["finished_at"] and datetime.fromisoformat(v["finished_at"]) > reset_at]
    return jsonify({
        "success": True,
        "loss_history": measures.thin(loss, limit),
        "curiosity_history": _series(validations, "curiosity", limit),
        "surprise_history": _series(validations, "surprise", limit),
        "surprise": last["surprise"] if last else None,
        "curiosity": last["curiosity"] if last else None,
        "surprise_source": None if last is None else {k: last[k] for k in ("run_id", "step", "n_codes", "code_groups", "finished_at")},
        "runs": run_rows,
    })


@bp.get("/learning/progress")
def learning_progress():
    query_args()
    state = _state()
    with state.registry.session(readonly=True) as s:
        newest = measures.newest_started(s)
        rec = measures.last_metric(newest) if newest is not None else None
        changes = measures.parameter_changes(s)
        stable, notes = measures.stability(s, newest)
        out = {"total_steps": measures.total_steps(s),
               "total_episodes": measures.total_episodes(s, state.settings.inbox_dir),
               "learning_updates": measures.learning_updates(s)}
        newest_id = newest.id if newest is not None else None
    lr = measures.finite_number((rec or {}).get("lr"))
    out.update({
        "avg_parameter_change": sum(changes.values()) / len(changes) if changes else None,
        "parameter_change": changes,
        "learning_rate": lr,
        "learning_rate_run": newest_id if lr is not None else None,
        "is_stable": stable,
        "stability_notes": notes,
    })
    return jsonify(out)


def benchmark(model) -> dict[str, Any] | None:
    """A gated candidate as a benchmark entry, or None when the gate measured no score for it."""
    metrics = model.metrics if isinstance(model.metrics, dict) else {}
    gate = model.gate_result if isinstance(model.gate_result, dict) else {}
    recorded_reflex = metrics.get("reflex")
    reflex = recorded_reflex if isinstance(recorded_reflex, dict) else {}
    ret = measures.finite_number(reflex.get("candidate_mean_return"))
    val = measures.finite_number(metrics.get("candidate_val_loss"))
    if model.component == ACTOR and ret is not None:
        score, kind, higher = ret, "reflex_mean_return", True
    elif val is not None:
        score, kind, higher = val, "val_loss", False
    else:
        return None
    details = {"model_id": str(model.id), "component": model.component, "score_kind": kind,
               "higher_is_better": higher, "passed": gate.get("passed"), "promoted": gate.get("promoted"),
               "forced": gate.get("forced"), "reasons": gate.get("reasons") or [],
               "candidate_val_loss": val,
               "promoted_val_loss": measures.finite_number(metrics.get("promoted_val_loss")),
               "reflex": reflex or None, "run_id": model.run_id}
    return {"id": f"gate-{model.id}", "timestamp": model.created_at.isoformat(), "score": score,
            "model_version": model.version or f"model {model.id}", "details": details}


@bp.get("/training/benchmarks")
def training_benchmarks():
    query_args("limit")
    limit = query_int("limit", default=BENCH_DEFAULT, minimum=1, maximum=BENCH_MAX)
    out = []
    with _state().registry.session(readonly=True) as s:
        for model in s.scalars(select(Model).order_by(Model.created_at.desc(), Model.id.desc())):
            entry = benchmark(model)
            if entry is not None:
                out.append(entry)
                if len(out) >= limit:
                    break
    return jsonify({"success": True, "benchmarks": out})
