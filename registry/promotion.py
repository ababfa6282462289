"""Promotion records: candidates, the promoted model per component, rollback, the loop closure.

All functions take an open Session first (Registry.session(): one transaction) and leave
committing to it, like registry/runs.py. Torch-free: the gate that decides (hope_models/promote/
gate.py) runs in its own process (`run_trainer.py promote`); this module only records.

    m = record_candidate(s, component="fast_loop", checkpoint_path=..., version=..., run_id=...,
                         metrics={...}, gate_result={...})
    promote(s, settings, m.id)        # the old one demoted, this one promoted, pointer rewritten
    rollback(s, settings, "fast_loop")  # back to what was served before the current one

The models table is the history; the pointer file $HOPE_HOME/promoted/<component>.json is what
serving reads (hope_models.promoted). A pointer is written after the rows are flushed and
before the caller commits: if writing it fails, the changes are rolled back (a savepoint) and
PromotionError is raised, so the table never says "promoted" for a model the pointer does not name.
"""
from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from sqlalchemy import or_, select
from sqlalchemy.orm import Session

from hope_models.checkpoint_format import (
    CONFIG_FILE,
    MODEL_FILE,
    CheckpointError,
    NotACheckpoint,
    read_verified,
    version_name,
)
from hope_models.components import TOKENIZER
from hope_models.json_finite import finite
from hope_models.promoted import PointerError, read_pointer, write_pointer
from registry import runs
from registry.models import Model, Run, iso, utcnow

HISTORY_LIMIT = 20


class PromotionError(ValueError):
    """A promotion or rollback that cannot be done; the message names the model or component and why."""


def record_candidate(s: Session, *, component: str, checkpoint_path: str | Path, version: str,
                     run_id: str | None, metrics: dict[str, Any] | None,
                     gate_result: dict[str, Any] | None) -> Model:
    """A new candidate row (not promoted). The checkpoint path is stored absolute."""
    if not isinstance(component, str) or not component:
        raise PromotionError(f"component must be a non-empty string, got {component!r}")
    if not isinstance(version, str) or not version:
        raise PromotionError(f"version must be a non-empty string, got {version!r}")
    if run_id is not None and s.get(Run, run_id) is None:
        raise PromotionError(f"no run {run_id} (see `run_trainer.py status`)")
    model = Model(component=component, checkpoint_path=str(Path(checkpoint_path).resolve()), version=version,
                  run_id=run_id, metrics=finite(metrics), gate_result=finite(gate_result),
                  created_at=utcnow())
    s.add(model)
    s.flush()
    return model


def promoted(s: Session, component: str) -> Model | None:
    """The model of `component` being served, or None."""
    return s.scalars(select(Model).where(Model.component == component, Model.promoted_at.is_not(None))).first()


def history(s: Session, component: str, limit: int = HISTORY_LIMIT) -> list[Model]:
    """Every candidate of `component` (promoted, demoted, refused), newest first."""
    if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
        raise PromotionError(f"limit must be an integer >= 1, got {limit!r}")
    query = select(Model).where(Model.component == component).order_by(Model.created_at.desc(), Model.id.desc())
    return list(s.scalars(query.limit(limit)))


def pointer_obj(model: Model, sha256: str) -> dict[str, Any]:
    """The pointer file's contents for a promoted model."""
    return {"component": model.component, "checkpoint": model.checkpoint_path, "version": model.version,
            "sha256": sha256, "model_id": model.id, "run_id": model.run_id, "promoted_at": iso(model.promoted_at)}


def _check_checkpoint(model: Model) -> str:
    """The sha256 of the model's weights, after checking the dir is still a complete checkpoint
    holding the same weights that were gated."""
    ckpt = Path(model.checkpoint_path)
    if not ckpt.is_dir():
        raise PromotionError(f"model {model.id} ({model.version}): checkpoint {ckpt} no longer exists")
    try:  # each file hashed once: the manifest check gives the weights' sha256 the version is named by
        verified = read_verified(ckpt, keep=(CONFIG_FILE,))
    except NotACheckpoint as exc:
        raise PromotionError(f"model {model.id} ({model.version}): {ckpt} is not a complete checkpoint: "
                             f"{exc.reason}") from None
    except CheckpointError as exc:
        raise PromotionError(f"model {model.id}: {exc}") from None
    sha = verified.sha256[MODEL_FILE]
    try:  # the config is untrusted: any shape of it only loses the step in the name
        config = verified.json(CONFIG_FILE)
    except CheckpointError:
        config = None
    version = version_name(ckpt, sha, config)
    if model.version is not None and version != model.version:
        raise PromotionError(f"model {model.id}: {ckpt} now holds {version}, not the {model.version} that was "
                             "gated; gate it again")
    if model.version is None:  # a row from before revision 0002
        model.version = version
    return sha


def _switch(s: Session, settings: Any, old: Model | None, new: Model, *, set_previous: bool) -> Model:
    """Demote `old`, promote `new`, write the pointer; all or nothing (a savepoint)."""
    sha = _check_checkpoint(new)
    now = utcnow()
    savepoint = s.begin_nested()
    try:
        if old is not None:
            old.promoted_at = None
            old.demoted_at = now
            s.flush()  # the partial unique index allows one promoted row per component
        if set_previous:
            new.previous_model_id = old.id if old is not None else None
        new.promoted_at = now
        new.demoted_at = None
        s.flush()
        write_pointer(settings.home, new.component, pointer_obj(new, sha))
    except PointerError as exc:
        savepoint.rollback()
        raise PromotionError(f"{new.component}: the promotion of model {new.id} was rolled back: {exc}") from None
    except BaseException:
        savepoint.rollback()
        raise
    savepoint.commit()
    return new


def promote(s: Session, settings: Any, model_id: int) -> Model:
    """Serve model `model_id`: the current promoted model of its component is demoted and
    becomes this one's previous_model_id (what a rollback returns to); the pointer is rewritten.
    Promoting the model already served rewrites its pointer and changes nothing else."""
    model = s.get(Model, model_id)
    if model is None:
        raise PromotionError(f"no model {model_id}")
    current = promoted(s, model.component)
    if current is not None and current.id == model.id:
        sha = _check_checkpoint(model)
        try:
            write_pointer(settings.home, model.component, pointer_obj(model, sha))
        except PointerError as exc:
            raise PromotionError(str(exc)) from None
        return model
    return _switch(s, settings, current, model, set_previous=True)


def rollback(s: Session, settings: Any, component: str) -> Model:
    """Demote the promoted model of `component` and serve the one promoted before it again.
    Repeated rollbacks walk further back (each model keeps its own previous_model_id)."""
    current = promoted(s, component)
    if current is None:
        raise PromotionError(f"no {component} model is promoted; there is nothing to roll back")
    if current.previous_model_id is None:
        raise PromotionError(f"{component}: model {current.id} ({current.version}) was the first one promoted; "
                             "there is no previous model to roll back to")
    previous = s.get(Model, current.previous_model_id)
    if previous is None:
        raise PromotionError(f"{component}: the previous model {current.previous_model_id} is gone from the registry")
    return _switch(s, settings, current, previous, set_previous=False)


def sync_pointer(s: Session, settings: Any, component: str) -> dict[str, Any] | None:
    """Make the pointer file agree with the table (after a crash between writing the pointer and
    committing, or a pointer deleted by hand): rewrite it from the promoted row. Returns the
    pointer, or None when nothing is promoted (a stale pointer is then left alone and reported
    by the caller; removing what a BrainService serves is a decision for a person)."""
    model = promoted(s, component)
    if model is None:
        return None
    sha = _check_checkpoint(model)
    obj = pointer_obj(model, sha)
    try:
        if read_pointer(settings.home, component) != obj:
            write_pointer(settings.home, component, obj)
    except PointerError:
        write_pointer(settings.home, component, obj)  # a corrupt pointer is replaced
    return obj


def _aware(when: datetime | float | int) -> datetime:
    if isinstance(when, bool):
        raise PromotionError(f"when must be a datetime or epoch seconds, got {when!r}")
    if isinstance(when, (int, float)):
        return datetime.fromtimestamp(float(when), timezone.utc)
    if not isinstance(when, datetime):
        raise PromotionError(f"when must be a datetime or epoch seconds, got {when!r}")
    if when.tzinfo is None or when.utcoffset() is None:
        raise PromotionError(f"when={when!r} is naive; pass a timezone-aware time")
    return when.astimezone(timezone.utc)


def _model_for(s: Session, checkpoint_path_or_version: str | Path) -> Model | None:
    key = str(checkpoint_path_or_version)
    paths = {key}
    if "/" in key:
        paths.add(str(Path(key).resolve()))
    return s.scalars(select(Model).where(or_(Model.version == key, Model.checkpoint_path.in_(paths)))
                     .order_by(Model.promoted_at.is_(None), Model.id.desc())).first()


def record_loaded(s: Session, checkpoint_path_or_version: str | Path, when: datetime | float | int) -> Run | None:
    """A tokenizer loaded by BrainService: its codes are in every answer from then on, whoever asks,
    so its run's loop_closure_s is the time to being loaded (once per run; other components' is
    their first answer, record_first_inference). Returns the run when this call recorded it, else None."""
    at = _aware(when)
    model = _model_for(s, checkpoint_path_or_version)
    if model is None or model.run_id is None or model.component != TOKENIZER:
        return None
    run = s.get(Run, model.run_id)
    if run is None or run.loop_closure_s is not None or run.finished_at is None:
        return None
    run.loop_closure_s = round((at - run.finished_at).total_seconds(), 3)
    runs.add_event(s, run.id, "log", {"level": "info", "message": (
        f"{model.version} loaded by BrainService: loop closure {run.loop_closure_s:.1f} s after the run finished "
        "(its codes are in every answer from now on)")})
    return run


def record_first_inference(s: Session, checkpoint_path_or_version: str | Path,
                           when: datetime | float | int) -> Run | None:
    """The first inference answered by a model: set its run's first_inference_at and
    loop_closure_s = when - run.finished_at (seconds), once per run (later calls change nothing).

    Returns the run of the matching model (newest matching row), or None when no model matches
    or the model has no run (a checkpoint promoted by path from outside any run)."""
    at = _aware(when)
    model = _model_for(s, checkpoint_path_or_version)
    if model is None or model.run_id is None:
        return None
    run = s.get(Run, model.run_id)
    if run is None:
        return None
    if run.first_inference_at is not None:
        return run
    run.first_inference_at = at
    if run.finished_at is not None and run.loop_closure_s is None:  # a tokenizer's was set when it was loaded
        run.loop_closure_s = round((at - run.finished_at).total_seconds(), 3)
    runs.add_event(s, run.id, "log", {
        "level": "info",
        "message": (f"first inference on {model.version}"
                    + (f": loop closure {run.loop_closure_s:.1f} s after the run finished"
                       if run.loop_closure_s is not None else ""))})
    return run


__all__ = ["PromotionError", "record_candidate", "promote", "rollback", "promoted", "history", "sync_pointer",
           "record_loaded",
           "record_first_inference", "pointer_obj", "HISTORY_LIMIT"]
