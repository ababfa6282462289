"""What the Continuon app's learning screens show, measured from the registry and the runs' files.

Each number is read from something the trainer wrote, never made up; a quantity nothing has
measured yet is None (the API answers null), never a 0 that looks like a measurement.

- loss history: the `loss` of each metric record in metrics.jsonl (hope_models/train/metrics.py:
  one record per log_every optimizer steps, the steps a resume trained again counted once) of the
  latest training: the newest run that has started and, when it belongs to a chain, every started
  run of that chain in chain order. Each point is labelled "<component> · run <id> · step <n>".
- surprise: the latest completed mid_loop run's validation cross-entropy, in nats per predicted
  observation code (the sum over the VQ-VAE's code groups): the Mid Loop predicts the VQ-VAE codes
  of the next steps, and at the end of a completed
  job the trainer measures its mean cross-entropy on the held-out validation episodes (the episode
  split of val_fraction, hope_models/train/validation.py), written to the run's result.json as
  summary.val.loss (the promotion gate computes the same number the same way).
- curiosity: surprise / (groups x ln(n_codes)), the log of the number of codes an observation can
  take (groups codebooks of n_codes each, from the Mid Loop checkpoint's config.json): 0 = the next
  codes are fully predictable, 1 = no better than a uniform guess (above 1: worse than a guess). curiosity_history: one point per completed mid_loop
  run, at the time it finished.
- parameter change: ||w_new - w_old||_2 / ||w_old||_2 over all the tensors the two checkpoints
  share (same name and shape), from the safetensors files with NumPy, between a component's
  promoted model and the one it replaced (its previous_model_id); cached by the version pair.
- total_episodes: the distinct episodes (by content hash) in the ingest manifests of the inbox
  dataset and of every dataset a run trained on; a dataset without an ingest manifest (episode
  files used in place) is not counted.
- is_stable: none of the last STABLE_WINDOW finished runs stopped on a non-finite loss, gradient
  or weights, and the newest logged loss of the latest run is finite.
"""
from __future__ import annotations

import json
import logging
import math
import os
import re
import threading
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from sqlalchemy import func, or_, select

from hope_models.checkpoint_format import CONFIG_FILE, VQVAE_REF, CheckpointError, read_json_object
from hope_models.components import PREDICTOR
from registry.models import Model, Run

log = logging.getLogger(__name__)

RESULT_FILE = "result.json"
MAX_RESULT_BYTES = 1 << 20


def held_out_figures(run_dir: str | Path) -> dict[str, Any] | None:
    """A finished run's validation figures (result.json summary.val: the component's held-out
    metrics and, for vqvae and mid_loop, their baselines), or None."""
    try:
        result = read_json_object(Path(run_dir) / RESULT_FILE, max_bytes=MAX_RESULT_BYTES)
    except (OSError, CheckpointError):
        return None
    summary = result.get("summary")
    val = summary.get("val") if isinstance(summary, dict) else None
    return {k: v for k, v in val.items() if finite_number(v) is not None} if isinstance(val, dict) else None
MAX_MANIFEST_BYTES = 16 << 20  # ~50k episodes; a bigger JSON would cost the Pi more memory than the count is worth
TAIL_BYTES = 64 << 10
STABLE_WINDOW = 5
NON_FINITE = re.compile(r"loss is (nan|-?inf)|gradient norm is (nan|-?inf)|non-finite", re.IGNORECASE)
_change_cache: dict[tuple[str, str], float | None] = {}
_manifest_cache: dict[str, tuple[tuple[int, int], frozenset[str]]] = {}
_lock = threading.Lock()
CACHE_MAX = 64


def finite_number(value: Any) -> float | None:
    """A finite float of an int or float (not a bool), else None."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _iso(wall_time: float) -> str:
    return datetime.fromtimestamp(wall_time, timezone.utc).isoformat()


def point(when: str, value: float, label: str) -> dict[str, Any]:
    return {"timestamp": when, "value": value, "label": label}


def thin(points: list, limit: int) -> list:
    """At most `limit` points, evenly spaced over the series; the first and the newest kept."""
    n = len(points)
    if n <= limit:
        return points
    if limit == 1:
        return points[-1:]
    return [points[round(i * (n - 1) / (limit - 1))] for i in range(limit)]


# -- the loss history of the latest training ----------------------------------------------------

def newest_started(s) -> Run | None:
    return s.scalars(select(Run).where(Run.started_at.is_not(None))
                     .order_by(Run.started_at.desc(), Run.created_at.desc())).first()


def latest_runs(s) -> list[Run]:
    """The newest run that has started, or its whole chain (the started members, in order)."""
    newest = newest_started(s)
    if newest is None:
        return []
    if newest.sequence_id is None:
        return [newest]
    return list(s.scalars(select(Run).where(Run.sequence_id == newest.sequence_id, Run.started_at.is_not(None))
                          .order_by(Run.sequence_index, Run.created_at)))


def loss_points(run: Run) -> list[dict[str, Any]]:
    from hope_models.train.metrics import read_metrics  # lazy: loads mcap

    out = []
    for rec in read_metrics(Path(run.run_dir)):
        loss, wall, step = finite_number(rec.get("loss")), finite_number(rec.get("wall_time")), rec.get("step")
        if rec.get("type") == "metric" and loss is not None and wall is not None and isinstance(step, int):
            out.append(point(_iso(wall), loss, f"{run.component} · run {run.id} · step {step}"))
    return out


def last_metric(run: Run) -> dict[str, Any] | None:
    """The newest metric record of a run, from the tail of its metrics.jsonl (not the whole file)."""
    path = Path(run.run_dir) / "metrics.jsonl"
    try:
        with open(path, "rb") as f:
            size = f.seek(0, os.SEEK_END)
            start = max(0, size - TAIL_BYTES)
            f.seek(start)
            lines = f.read().split(b"\n")
    except OSError:
        return None
    for line in reversed(lines[1:] if start else lines):  # a read from the middle starts mid-line
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        if isinstance(rec, dict) and rec.get("type") == "metric":
            return rec
    return None


# -- surprise and curiosity: the Mid Loop's validation cross-entropy -----------------------------

def _code_space(run: Run) -> tuple[int, int] | None:
    """(n_codes per group, groups) of the VQ-VAE the run's Mid Loop reads."""
    ckpt = run.last_checkpoint
    try:
        if not ckpt:  # a run the registry lost the checkpoint of: result.json names it
            ckpt = read_json_object(Path(run.run_dir) / RESULT_FILE, max_bytes=MAX_RESULT_BYTES).get("checkpoint")
        if not isinstance(ckpt, str):
            return None
        obj = read_json_object(Path(ckpt) / CONFIG_FILE)
    except (OSError, CheckpointError):
        return None
    cfg, vq = obj.get("model_config"), obj.get(VQVAE_REF)
    n = cfg.get("n_codes") if isinstance(cfg, dict) else None
    vq_cfg = vq.get("model_config") if isinstance(vq, dict) else None
    groups = vq_cfg.get("groups", 1) if isinstance(vq_cfg, dict) else 1  # 1: saved before groups existed
    if (not isinstance(n, int) or isinstance(n, bool) or not isinstance(groups, int) or isinstance(groups, bool)
            or n < 2 or groups < 1):
        return None
    return n, groups


def mid_loop_validations(s, limit: int) -> list[dict[str, Any]]:
    """The validation cross-entropy of the newest `limit` completed mid_loop runs, oldest first:
    [{"run_id", "finished_at", "step", "surprise", "n_codes", "code_groups", "curiosity"}]."""
    rows = s.scalars(select(Run).where(Run.component == PREDICTOR, Run.state == "completed")
                     .order_by(Run.finished_at.desc(), Run.created_at.desc()).limit(limit))
    out = []
    for run in rows:
        val = held_out_figures(run.run_dir)
        loss = finite_number(val.get("loss")) if val else None
        if loss is None:
            continue  # no validation split (too few episodes): nothing was measured
        space = _code_space(run)
        n, groups = space if space else (None, None)
        when = run.finished_at or run.updated_at
        out.append({"run_id": run.id, "finished_at": when.isoformat() if when else None, "step": run.step,
                    "surprise": loss, "n_codes": n, "code_groups": groups,
                    "curiosity": loss / (space[1] * math.log(space[0])) if space else None})
    return out[::-1]


# -- progress -------------------------------------------------------------------------------------

def total_steps(s) -> int:
    return int(s.scalar(select(func.coalesce(func.sum(Run.step), 0))) or 0)


def learning_updates(s) -> int:
    """Models that were ever served: promoted now, or promoted and later demoted."""
    return int(s.scalar(select(func.count(Model.id)).where(
        or_(Model.promoted_at.is_not(None), Model.demoted_at.is_not(None)))) or 0)


def _manifest_hashes(dataset: Path) -> frozenset[str]:
    path = dataset / "manifest.json"
    try:
        st = path.stat()
    except OSError:
        return frozenset()
    key = str(path)
    with _lock:
        hit = _manifest_cache.get(key)
    if hit is not None and hit[0] == (st.st_mtime_ns, st.st_size):
        return hit[1]
    try:
        manifest = read_json_object(path, max_bytes=MAX_MANIFEST_BYTES)
    except (OSError, CheckpointError) as exc:  # logged once per version of the file (it is cached below)
        log.warning("total_episodes: %s is not counted: %s", dataset, exc)
        manifest = {}
    episodes = manifest.get("episodes") if manifest.get("format") == "hope-rlds-dataset" else None
    hashes = frozenset(str(e.get("content_sha256")) for e in episodes if isinstance(e, dict)
                       and e.get("content_sha256")) if isinstance(episodes, list) else frozenset()
    with _lock:
        if len(_manifest_cache) >= CACHE_MAX:
            _manifest_cache.clear()
        _manifest_cache[key] = ((st.st_mtime_ns, st.st_size), hashes)
    return hashes


def total_episodes(s, inbox: Path) -> int:
    datasets = {str(inbox)}
    for config in s.scalars(select(Run.config)):
        data = config.get("data") if isinstance(config, dict) else None
        if isinstance(data, str) and data:
            datasets.add(data)
    seen: set[str] = set()
    for d in sorted(datasets):
        seen |= _manifest_hashes(Path(d))
    return len(seen)


def relative_change(old_ckpt: str, new_ckpt: str) -> float | None:
    """||new - old|| / ||old|| over the tensors both hold with the same shape (NumPy, one tensor
    at a time); None when they share none or the old weights are all zero."""
    from safetensors import safe_open  # lazy: loads safetensors

    num = den = 0.0
    shared = 0
    with safe_open(str(Path(old_ckpt) / "model.safetensors"), framework="numpy") as old, \
            safe_open(str(Path(new_ckpt) / "model.safetensors"), framework="numpy") as new:
        names = set(new.keys())
        for name in old.keys():
            if name not in names:
                continue
            a, b = old.get_tensor(name), new.get_tensor(name)
            if a.shape != b.shape or a.dtype.kind != "f":
                continue
            a64, b64 = a.astype("float64"), b.astype("float64")
            num += float(((b64 - a64) ** 2).sum())
            den += float((a64 ** 2).sum())
            shared += 1
    if not shared or den <= 0.0:
        return None
    value = math.sqrt(num) / math.sqrt(den)
    return value if math.isfinite(value) else None


def parameter_changes(s) -> dict[str, float]:
    """Per component with a promoted model that replaced another: its relative weight change."""
    out = {}
    for new in s.scalars(select(Model).where(Model.promoted_at.is_not(None), Model.previous_model_id.is_not(None))):
        old = s.get(Model, new.previous_model_id)
        if old is None:
            continue
        key = (f"{old.version}|{old.checkpoint_path}", f"{new.version}|{new.checkpoint_path}")
        with _lock:
            cached = key in _change_cache
            value = _change_cache.get(key)
        if not cached:
            try:
                value = relative_change(old.checkpoint_path, new.checkpoint_path)
            except (OSError, ValueError, RuntimeError) as exc:  # a checkpoint gone or damaged: not measured, not cached
                log.warning("parameter change of %s: not measured: %s", new.component, exc)
                continue
            with _lock:
                if len(_change_cache) >= CACHE_MAX:
                    _change_cache.clear()
                _change_cache[key] = value
        if value is not None:
            out[new.component] = value
    return out


def stability(s, latest: Run | None) -> tuple[bool, list[str]]:
    """(stable, why not): see the module doc."""
    why = []
    finished = s.scalars(select(Run).where(Run.state.in_(("completed", "failed")))
                         .order_by(Run.finished_at.desc(), Run.created_at.desc()).limit(STABLE_WINDOW))
    for run in finished:
        if run.state == "failed" and NON_FINITE.search(run.error_message or ""):
            why.append(f"run {run.id} ({run.component}) stopped: {run.error_message}")
    if latest is not None:
        rec = last_metric(latest)
        if rec is not None and "loss" in rec and finite_number(rec.get("loss")) is None:
            why.append(f"run {latest.id}: its newest logged loss (step {rec.get('step')}) is not finite")
    return not why, why
