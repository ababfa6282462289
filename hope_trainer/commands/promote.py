"""`run_trainer.py promote (RUN | --checkpoint DIR) [--component C] [--force [--by cli|http]] [--auto] [--json]`.

Gates a candidate and promotes it when it passes (hope_models/promote/gate.py):

1. the candidate: RUN's newest complete checkpoint (the run must have completed), or DIR (a
   checkpoint dir or a run dir; its run is found in the registry by its run dir when it has one);
2. the gate runs here, with torch, against the model the registry says is promoted for the
   component (finite weights, validation loss on the candidate's validation split, the sim
   reflex for a reacher fast_loop); a candidate of a registry run is scored on that run's
   dataset as the registry holds it, a bare checkpoint on what its config.json names, followed
   only inside the data roots (config.json is untrusted: hope_models/promote/gate.py);
3. the candidate is recorded in the models table with its gate result and metrics (refused ones
   too: the history says why), and promoted when it passed, or with --force (recorded as forced,
   with who asked: `--by` cli or http; a WARNING line and a log event on its run; non-finite
   weights are never promoted, forced or not: a robot must not get NaN actions);
4. promotion rewrites $HOPE_HOME/promoted/<component>.json, which BrainService follows.

Output (--json, one line): {"promoted": bool, "model_id", "version", "component", "checkpoint",
"run_id", "forced", "reasons": [...], "metrics": {...}, "checks": [...]}; a usage error prints
{"promoted": false, "error": "..."}. Exit 0 promoted (or already the promoted one; with --auto also
when the run already has a candidate row: "skipped" says so), 1 refused by the gate, 2 usage.

--auto marks the record as made by the daemon's auto-promotion (daemon/autopromote.py). One
promote runs at a time per $HOPE_HOME (a file lock): gates are CPU-heavy on a Pi.
"""
from __future__ import annotations

import argparse
import fcntl
import json
import logging
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from daemon.cli.registry import CommandError, open_registry
from hope_models.checkpoint_format import CONFIG_FILE, CheckpointError, read_json_object
from hope_models.child_result import add_result_argument, write_result
from hope_models.components import COMPONENTS
from hope_models.promoted import PointerError, checkpoint_version

PROMOTED_EXIT, REFUSED_EXIT, USAGE_EXIT = 0, 1, 2
log = logging.getLogger(__name__)
LOCK_FILE = "promote.lock"


class UsageError(Exception):
    """Something about the request, not the candidate's quality (exit 2)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", nargs="?", metavar="RUN", help="a completed run id (see `run_trainer.py status`)")
    parser.add_argument("--checkpoint", metavar="DIR", help="a checkpoint dir or run dir instead of a run id")
    parser.add_argument("--component", choices=COMPONENTS, help="refuse unless the candidate is this component")
    parser.add_argument("--force", action="store_true",
                        help="promote even if the gate refuses (recorded as forced; never non-finite weights)")
    parser.add_argument("--by", choices=("cli", "http"), default="cli",
                        help="who asks (the webapp passes http): named in a forced promotion's record and log line")
    parser.add_argument("--auto", action="store_true",
                        help="called by the daemon's auto-promotion: skip a run that already has a candidate record")
    parser.add_argument("--threads", type=int, default=1, help="torch threads for the gate (default 1)")
    parser.add_argument("--json", action="store_true", help="print the outcome as one JSON object on stdout")
    add_result_argument(parser)


@contextmanager
def _promote_lock(home: Path) -> Iterator[None]:
    home.mkdir(parents=True, exist_ok=True)
    with open(home / LOCK_FILE, "a+") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def _emit(args: argparse.Namespace, out: dict[str, Any]) -> None:
    write_result(args.result_file, out)
    if args.json:
        print(json.dumps(out, allow_nan=False), flush=True)
        return
    if out.get("error"):
        return
    if out.get("skipped") or out.get("already"):
        print(out.get("skipped") or out["reasons"][0])
        return
    head = f"{out['component']} {out['version']}"
    if out["promoted"]:
        print(f"promoted {head} (model {out['model_id']}){' FORCED past the gate' if out.get('forced') else ''}")
    else:
        print(f"refused {head} (model {out['model_id']}): the gate said no")
    for check in out.get("checks", []):
        print(f"  {check['status']:7s} {check['check']}: {check['detail']}")
    for reason in out.get("reasons", []):
        if not any(reason == c["detail"] for c in out.get("checks", [])):
            print(f"  note    {reason}")


def _usage(args: argparse.Namespace, message: str) -> int:
    write_result(args.result_file, {"promoted": False, "error": message})
    if args.json:
        print(json.dumps({"promoted": False, "error": message}), flush=True)
    print(f"error: {message}", file=sys.stderr)
    return USAGE_EXIT


def _run_data(run) -> str | None:
    """The dataset a registry run was submitted with (checked at the door: registry/run_request.py)."""
    data = run.config.get("data") if isinstance(run.config, dict) else None
    return data if isinstance(data, str) and data else None


def _candidate(s, args: argparse.Namespace) -> tuple[Path, str | None, str | None]:
    """(checkpoint dir, run id or None, the run's dataset or None) of the request."""
    from sqlalchemy import select  # lazy: loads sqlalchemy

    from hope_models.promote.gate import GateError, resolve_candidate  # lazy: loads numpy
    from registry import runs  # lazy: loads sqlalchemy
    from registry.models import Run  # lazy: loads sqlalchemy

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
    from registry import runs  # lazy: loads sqlalchemy
    from registry.models import Run  # lazy: loads sqlalchemy

    message = (f"forced promotion by {by}: {model.component} {model.version} (model {model.id}) served past the "
               f"gate's refusal: {'; '.join(map(str, reasons)) or 'no reason given'}")
    log.warning("%s", message)
    if model.run_id is not None and s.get(Run, model.run_id) is not None:
        runs.add_event(s, model.run_id, "log", {"level": "warning", "message": message, "promotion": {
            "forced": True, "by": by, "model_id": model.id, "version": model.version, "component": model.component}})


def promote_candidate(settings: Any, registry: Any, args: argparse.Namespace) -> tuple[int, dict[str, Any]]:
    """The whole command minus printing: (exit code, output object). UsageError for exit 2."""
    from sqlalchemy import select  # lazy: loads sqlalchemy

    from hope_models.promote.gate import GateError, gate_candidate  # lazy: loads numpy
    from registry import promotion  # lazy: loads sqlalchemy
    from registry.models import Model  # lazy: loads sqlalchemy
    from registry.runs import RunError  # lazy: loads sqlalchemy

    with registry.session(readonly=True) as s:
        try:
            ckpt, run_id, run_data = _candidate(s, args)
        except RunError as exc:
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

    import torch  # lazy: loads torch

    torch.set_num_threads(max(1, int(args.threads)))
    try:
        # A registry run's own dataset, not the one its checkpoint's config.json names (untrusted:
        # the gate follows those paths only inside the data roots).
        result = gate_candidate(ckpt, current_ckpt, data=run_data, settings=settings)
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
    return (PROMOTED_EXIT if promote_it else REFUSED_EXIT), out


def run(args: argparse.Namespace) -> int:
    from registry.promotion import PromotionError  # lazy: loads sqlalchemy

    if bool(args.run) == bool(args.checkpoint):
        return _usage(args, "give either RUN or --checkpoint DIR (exactly one)")
    if args.threads < 1:
        return _usage(args, f"--threads {args.threads} must be >= 1")
    try:
        with open_registry() as (settings, registry):
            with _promote_lock(Path(settings.home)):
                code, out = promote_candidate(settings, registry, args)
    except (UsageError, CommandError, PromotionError) as exc:
        return _usage(args, str(exc))
    _emit(args, out)
    return code
