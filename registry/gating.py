"""Gate a candidate and promote it when it passes: the one procedure behind `run_trainer.py promote`
(a child of the daemon's auto-promotion or of the webapp, or a person's command) and the gate a
worker child runs in-process right after its training (workers/warm_gate.py: torch already loaded).

    code, out = promote_candidate(settings, registry, PromoteRequest(run="r-..."))
    with promote_lock(home, wait=False) as mine: ...   # one gate at a time per $HOPE_HOME

1. the candidate: a completed run's newest complete checkpoint, or a checkpoint dir;
2. the gate (hope_models/promote/gate.py) runs in this process, with torch, against the promoted
   model of the component;
3. the candidate is recorded in the models table with its gate result (refused ones too), and
   promoted when it passed, or forced (never non-finite weights);
4. with settings.gate_reflex_after_serving, a fast_loop's reflex check in simulation runs after
   the candidate is served (a served model answers seconds after its run ends, instead of after
   the episodes): check_after_serving() rolls it back when it fails. What that costs in safety:
   a candidate worse than the promoted one is served for the check's duration. When the process
   dies during the check, the model stays served with the check owed (owed_checks: its row says
   the reflex deferred and has no "after_serving"); finish_owed_checks() runs it later
   (`promote --finish-checks`, which the daemon's auto-promotion starts when the lock is free).

Exit codes of the command: PROMOTED_EXIT (0), REFUSED_EXIT (1, refused or rolled back), USAGE_EXIT (2).
Torch-free at import: the gate's modules load lazily.
"""
from __future__ import annotations

import fcntl
import json
import logging
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from sqlalchemy import select

from hope_models.checkpoint_format import CONFIG_FILE, CheckpointError, read_json_object
from hope_models.components import COMPONENTS
from hope_models.json_finite import finite
from hope_models.promote.checks import DEFERRED
from hope_models.promoted import PointerError, checkpoint_version
from registry import promotion, runs
from registry.models import Model, Run

PROMOTED_EXIT, REFUSED_EXIT, USAGE_EXIT = 0, 1, 2
LOCK_FILE = "promote.lock"
PROMOTE_LOG = "promote.log"  # under $HOPE_HOME/logs: every gate's outcome, whoever ran it
log = logging.getLogger(__name__)


class UsageError(Exception):
    """Something about the request, not the candidate's quality (exit 2)."""


@dataclass(frozen=True)
class PromoteRequest:
    """What `promote` was asked (the command's argparse namespace has the same attributes)."""
    run: str | None = None
    checkpoint: str | None = None
    component: str | None = None
    force: bool = False
    by: str = "cli"
    auto: bool = False  # made by auto-promotion: a run that already has a candidate record is skipped
    threads: int = 1


@contextmanager
def promote_lock(home: Path, *, wait: bool = True) -> Iterator[bool]:
    """One gate at a time per $HOPE_HOME (a file lock: gates are CPU-heavy on a Pi). Yields whether
    it is held; with wait=False it yields False at once when another process holds it."""
    home.mkdir(parents=True, exist_ok=True)
    with open(home / LOCK_FILE, "a+") as fh:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BlockingIOError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def promote_lock_busy(home: Path) -> bool:
    """Another process is gating now (it holds the lock)."""
    if not (home / LOCK_FILE).exists():
        return False
    with promote_lock(home, wait=False) as mine:
        return not mine


def _run_data(run) -> str | None:
    """The dataset a registry run was submitted with (checked at the door: registry/run_request.py)."""
    data = run.config.get("data") if isinstance(run.config, dict) else None
    return data if isinstance(data, str) and data else None


def _candidate(s, args: Any) -> tuple[Path, str | None, str | None]:
    """(checkpoint dir, run id or None, the run's dataset or None) of the request."""
    from hope_models.promote.gate import GateError, resolve_candidate  # lazy: loads numpy

    if args.run:
        run = runs.get_run(s, args.run)
        if run.state != "completed":
            raise UsageError(f"run {run.id} is {run.state}; only a completed run is promoted "
                             "(or pass --checkpoint DIR to gate one of its checkpoints)")
        try:
            return resolve_candidate(run.run_dir), run.id, _run_data(run)
        except GateError as exc:
            raise UsageError(f"run {run.id}: {exc}") from None
    try:
        ckpt = resolve_candidate(args.checkpoint)
    except GateError as exc:
        raise UsageError(str(exc)) from None
    run_dir = str(ckpt.parent.parent)
    found = s.scalars(select(Run).where(Run.run_dir.in_([run_dir, str(Path(run_dir).resolve())]))).first()
    return ckpt, (found.id if found is not None else None), (_run_data(found) if found is not None else None)


def _component_and_version(ckpt: Path, expected: str | None) -> tuple[str, str]:
    """The checkpoint's component (from its config.json; `expected` if given) and its version."""
    try:
        component = read_json_object(ckpt / CONFIG_FILE).get("component")
    except (OSError, CheckpointError) as exc:
        raise UsageError(f"{ckpt / CONFIG_FILE}: not readable: {exc}") from None
    if not isinstance(component, str) or component not in COMPONENTS:
        raise UsageError(f"{ckpt / CONFIG_FILE}: component {component!r} is not one of {', '.join(COMPONENTS)}")
    if expected and expected != component:
        raise UsageError(f"{ckpt} holds a {component} checkpoint, not a {expected}")
    try:
        version, _sha = checkpoint_version(ckpt)
    except PointerError as exc:
        raise UsageError(str(exc)) from None
    return component, version


def _record_forced(s: Any, by: str, model: Any, reasons: list[str]) -> None:
    """A forced promotion is said out loud: a WARNING line, and a log event on the candidate's run
    (the models row holds forced and forced_by in its gate_result either way)."""
    message = (f"forced promotion by {by}: {model.component} {model.version} (model {model.id}) served past the "
               f"gate's refusal: {'; '.join(map(str, reasons)) or 'no reason given'}")
    log.warning("%s", message)
    if model.run_id is not None and s.get(Run, model.run_id) is not None:
        runs.add_event(s, model.run_id, "log", {"level": "warning", "message": message, "promotion": {
            "forced": True, "by": by, "model_id": model.id, "version": model.version, "component": model.component}})


def promote_candidate(settings: Any, registry: Any, args: Any) -> tuple[int, dict[str, Any]]:
    """The whole command minus printing: (exit code, output object). UsageError for exit 2."""
    from hope_models.promote.gate import GateError, gate_candidate  # lazy: loads numpy

    with registry.session(readonly=True) as s:
        try:
            ckpt, run_id, run_data = _candidate(s, args)
        except runs.RunError as exc:
            raise UsageError(str(exc)) from None
        if args.auto and run_id is not None:
            row = s.scalars(select(Model).where(Model.run_id == run_id)).first()
            if row is not None:
                return PROMOTED_EXIT, {"promoted": False, "model_id": row.id, "version": row.version,
                                       "component": row.component, "checkpoint": row.checkpoint_path,
                                       "run_id": run_id, "forced": False, "reasons": [], "metrics": {},
                                       "skipped": f"run {run_id} already has a candidate record (model {row.id})"}
        component, version = _component_and_version(ckpt, args.component)
        current = promotion.promoted(s, component)
        current_id = current.id if current is not None else None
        current_ckpt = current.checkpoint_path if current is not None else None
    base = {"component": component, "checkpoint": str(ckpt), "run_id": run_id, "version": version}
    if current is not None and current.version == version:
        return PROMOTED_EXIT, {"promoted": True, "model_id": current_id, **base, "forced": False,
                               "reasons": [f"{version} is already the promoted {component}"], "metrics": {},
                               "already": True}

    try:
        # A registry run's own dataset, not the one its checkpoint's config.json names (untrusted:
        # the gate follows those paths only inside the data roots).
        result = gate_candidate(ckpt, current_ckpt, data=run_data, settings=settings,
                                reflex_after_serving=bool(settings.gate_reflex_after_serving),
                                threads=max(1, int(args.threads)))
    except GateError as exc:
        raise UsageError(str(exc)) from None
    gate = result.to_json_obj()
    passed = result.passed
    reasons = list(gate["reasons"])
    finite = gate["metrics"].get("finite") is not False
    forced = bool(args.force and not passed and finite)
    if args.force and not finite:
        reasons.append("--force ignored: non-finite weights are never promoted")

    with registry.session() as s:
        now = promotion.promoted(s, component)
        if passed and (now.id if now is not None else None) != current_id:
            # Another promotion landed while this gate ran: the comparison is stale.
            passed = False
            reasons.insert(0, f"the promoted {component} changed while the gate ran (was model {current_id}, now "
                              f"{now.id if now is not None else 'none'}); run promote again")
            forced = bool(args.force)
        promote_it = passed or forced
        record = {"passed": result.passed, "promoted": promote_it, "forced": forced, "reasons": reasons,
                  "checks": gate["checks"], "mode": "auto" if args.auto else "manual",
                  "compared_with_model_id": current_id, **({"forced_by": args.by} if forced else {})}
        model = promotion.record_candidate(s, component=component, checkpoint_path=ckpt, version=version,
                                           run_id=run_id, metrics=gate["metrics"], gate_result=record)
        if promote_it:
            promotion.promote(s, settings, model.id)
        if forced:
            _record_forced(s, args.by, model, reasons)
        model_id = model.id
    out = {"promoted": promote_it, "model_id": model_id, **base, "forced": forced, "reasons": reasons,
           "metrics": gate["metrics"], "checks": gate["checks"]}
    reflex = gate["metrics"].get("reflex") or {}
    if promote_it and not forced and reflex.get("after_serving"):
        out.update(check_after_serving(settings, registry, model_id, ckpt, component, current_ckpt,
                                       str(reflex.get("task"))))
        if out["rolled_back"]:
            out["promoted"] = False
            out["reasons"] = [out["after_serving"]["detail"], *reasons]
            return REFUSED_EXIT, out
    return (PROMOTED_EXIT if promote_it else REFUSED_EXIT), out


def check_after_serving(settings: Any, registry: Any, model_id: int, ckpt: Path, component: str,
                        previous_ckpt: str | None, task: str, *, threads: int | None = None) -> dict[str, Any]:
    """The reflex check of model `model_id` (checkpoint `ckpt`), served now, against the model it replaced; when it
    fails and the model is still the promoted one, the previous model is served again (a rollback,
    recorded on the model's gate_result and as a warning on its run). {"after_serving": {...},
    "rolled_back": bool}."""
    from hope_models.promote.gate import GateError, reflex_verdict  # lazy: loads numpy, torch

    t0 = time.monotonic()
    try:
        verdict = reflex_verdict(ckpt, previous_ckpt, settings=settings, task=task, threads=threads)
        passed, checks, figures = verdict.passed, verdict.checks, verdict.metrics.get("reflex")
    except GateError as exc:
        passed, checks, figures = False, [{"check": "reflex", "status": "failed", "detail": str(exc)}], None
    detail = "; ".join(c["detail"] for c in checks if c["check"] == "reflex") or "reflex: not measured"
    after = {"passed": passed, "detail": detail, "checks": checks, "reflex": figures,
             "seconds": round(time.monotonic() - t0, 3)}
    rolled_back = False
    with registry.session() as s:
        model = s.get(Model, model_id)
        model.gate_result = finite({**(model.gate_result or {}), "after_serving": after})
        model.metrics = finite({**(model.metrics or {}), "reflex": figures})
        now = promotion.promoted(s, component)
        if not passed and now is not None and now.id == model_id:
            if now.previous_model_id is None:
                message = (f"{component} {model.version} (model {model_id}) failed its check after serving and "
                           f"stays served: nothing was promoted before it to roll back to: {detail}")
            else:
                try:
                    back = promotion.rollback(s, settings, component)
                except promotion.PromotionError as exc:  # nothing changed (a savepoint); the verdict is kept
                    message = (f"{component} {model.version} (model {model_id}) failed its check after serving and "
                               f"stays served: the rollback failed: {exc}: {detail}")
                else:
                    rolled_back = True
                    message = (f"{component} {model.version} (model {model_id}) rolled back to {back.version} "
                               f"(model {back.id}) {after['seconds']:.1f} s after it was served: {detail}")
            log.warning("%s", message)
            if model.run_id is not None and s.get(Run, model.run_id) is not None:
                runs.add_event(s, model.run_id, "log", {"level": "warning", "message": message})
    return {"after_serving": after, "rolled_back": rolled_back}


# -- a check interrupted after serving ---------------------------------------------------------------

def owes_check(model: Model) -> bool:
    """Whether `model` is served with its reflex check after serving owed: the gate deferred it, the
    promotion was not forced (a forced one never runs it), and no after_serving verdict was recorded
    (the process that served it died during the check: a SIGKILL, a power cut)."""
    gate = model.gate_result if isinstance(model.gate_result, dict) else {}
    checks = gate.get("checks")
    deferred = isinstance(checks, list) and any(
        isinstance(c, dict) and c.get("check") == "reflex" and c.get("status") == DEFERRED for c in checks)
    return model.promoted_at is not None and deferred and not gate.get("forced") and "after_serving" not in gate


def owed_checks(s: Any) -> list[Model]:
    """The promoted models whose reflex check after serving is owed (owes_check), oldest first."""
    served = s.scalars(select(Model).where(Model.promoted_at.is_not(None)).order_by(Model.id))
    return [m for m in served if owes_check(m)]


def finish_check(settings: Any, registry: Any, model_id: int, *, threads: int | None = None) -> dict[str, Any] | None:
    """Run the owed check of model `model_id` against the model it replaced (check_after_serving on
    `threads` torch threads: rolled back when it fails). The caller holds promote_lock: the row is read again under it, and
    None is returned when there is nothing to do any more (demoted meanwhile, or checked by another
    process)."""
    with registry.session(readonly=True) as s:
        model = s.get(Model, model_id)
        if model is None or not owes_check(model):
            return None
        previous = s.get(Model, model.previous_model_id) if model.previous_model_id is not None else None
        reflex = model.metrics.get("reflex") if isinstance(model.metrics, dict) else None
        task = str(reflex.get("task") or "reach") if isinstance(reflex, dict) else "reach"
        base = {"model_id": model.id, "component": model.component, "version": model.version,
                "run_id": model.run_id, "checkpoint": model.checkpoint_path}
        previous_ckpt = previous.checkpoint_path if previous is not None else None
    return {**base, **check_after_serving(settings, registry, model_id, Path(base["checkpoint"]), base["component"],
                                          previous_ckpt, task, threads=threads)}


def finish_owed_checks(settings: Any, registry: Any, threads: int = 1) -> tuple[int, dict[str, Any]]:
    """Every owed check finished (the caller holds promote_lock): (REFUSED_EXIT when one rolled its
    model back, else PROMOTED_EXIT, {"finished": [finish_check's outcomes], "rolled_back": bool}).
    A failed check with nothing to roll back to leaves its model served, as in promote_candidate."""
    with registry.session(readonly=True) as s:
        owed = [m.id for m in owed_checks(s)]
    finished = [out for out in (finish_check(settings, registry, i, threads=max(1, int(threads))) for i in owed)
                if out is not None]
    rolled_back = any(out["rolled_back"] for out in finished)
    return (REFUSED_EXIT if rolled_back else PROMOTED_EXIT), {"finished": finished, "rolled_back": rolled_back}


def describe_finished(entry: dict[str, Any], *, who: str = "auto-promote") -> tuple[str, str]:
    """(level, message) of one finished check (an entry of finish_owed_checks' "finished")."""
    what = f"{entry.get('component')} {entry.get('version')} (model {entry.get('model_id')})"
    after = entry.get("after_serving") or {}
    head = f"{who}: the reflex check of {what}, interrupted after it was served, ran now"
    if entry.get("rolled_back"):
        return "warning", f"{head}: failed, rolled back to the model it replaced: {after.get('detail')}"
    if not after.get("passed"):
        return "warning", f"{head}: failed; it stays served (nothing to roll back to): {after.get('detail')}"
    return "info", f"{head}: passed: {after.get('detail')}"


def describe_outcome(code: int | None, outcome: dict[str, Any] | None, problem: str | None = None, *,
                     who: str = "auto-promote") -> tuple[str, str]:
    """(level, message) of a finished gate for the run's log, said by `who`; `problem` says why there
    is no outcome (child_result.ChildResultError's message: the command and its exit code)."""
    if outcome is None:
        what = problem or f"the promote process exited with code {code} without a result"
        return "error", f"{who}: {what}; see $HOPE_HOME/logs/{PROMOTE_LOG}"
    what = f"{outcome.get('component')} {outcome.get('version')}"
    if outcome.get("skipped"):
        return "info", f"{who}: skipped: {outcome['skipped']}"
    if outcome.get("error"):
        return "error", f"{who}: could not gate: {outcome['error']}"
    reasons = "; ".join(str(r) for r in outcome.get("reasons") or [])
    after = outcome.get("after_serving") or {}
    if code == 0 and outcome.get("promoted"):
        return "info", f"{who}: promoted {what} (model {outcome.get('model_id')})" + (
            f"; {reasons}" if reasons else "") + (f"; after serving: {after['detail']}" if after.get("detail") else "")
    if code == 1 and outcome.get("rolled_back"):
        return "warning", (f"{who}: served {what} (model {outcome.get('model_id')}), then rolled it back: "
                           f"{reasons}")
    if code == 1:
        return "warning", f"{who}: the gate refused {what} (model {outcome.get('model_id')}): {reasons}"
    return "error", f"{who}: unexpected exit code {code}: {json.dumps(outcome)[:500]}"

__all__ = ["PROMOTED_EXIT", "REFUSED_EXIT", "USAGE_EXIT", "LOCK_FILE", "PROMOTE_LOG", "PromoteRequest",
           "UsageError", "check_after_serving", "describe_finished", "describe_outcome", "finish_check",
           "finish_owed_checks", "owed_checks", "owes_check", "promote_candidate", "promote_lock",
           "promote_lock_busy"]
