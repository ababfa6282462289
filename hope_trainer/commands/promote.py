"""`run_trainer.py promote (RUN | --checkpoint DIR) [--component C] [--force [--by cli|http]] [--auto] [--json]`,
`run_trainer.py promote --finish-checks [--json]`.

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
4. promotion rewrites $HOPE_HOME/promoted/<component>.json, which BrainService follows;
5. a sim reacher fast_loop's reflex check runs after it is served (gate_reflex_after_serving, on
   by default) and serves the previous model again when it fails: exit 1, "rolled_back": true,
   "after_serving": {passed, detail, checks, reflex, seconds}.

The procedure is registry/gating.py's; the worker child that trained a run runs it in-process
(workers/warm_gate.py), so auto-promotion spawns this command only for runs no worker gated.

Output (--json, one line): {"promoted": bool, "model_id", "version", "component", "checkpoint",
"run_id", "forced", "reasons": [...], "metrics": {...}, "checks": [...]}; a usage error prints
{"promoted": false, "error": "..."}. Exit 0 promoted (or already the promoted one; with --auto also
when the run already has a candidate row: "skipped" says so), 1 refused by the gate, 2 usage.

--auto marks the record as made by the daemon's auto-promotion (daemon/autopromote.py). One
promote runs at a time per $HOPE_HOME (a file lock): gates are CPU-heavy on a Pi.

--finish-checks finishes the reflex checks after serving that a dead process left owed (step 5
interrupted by a SIGKILL or a power cut: the model is served, its row says the check is deferred
and holds no "after_serving"): each runs now against the model its row replaced, which is served
again when it fails (registry/gating.py finish_owed_checks). It is promote's own last step, so it
is a flag of promote, under the same lock (a row is read again once the lock is held: another
process may have finished it meanwhile). The daemon's auto-promotion starts it by itself.
Output: {"finished": [{"model_id", "component", "version", "run_id", "checkpoint", "after_serving",
"rolled_back"}...], "rolled_back": bool}. Exit 0 every check passed or none was owed (also a failed
one with nothing to roll back to: it stays served, as in step 5), 1 one was rolled back, 2 usage.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from daemon.cli.registry import CommandError, open_registry
from hope_models.child_result import add_result_argument, write_result
from hope_models.components import COMPONENTS
from registry.gating import (
    USAGE_EXIT,
    UsageError,
    describe_finished,
    finish_owed_checks,
    promote_candidate,
    promote_lock,
)
from registry.promotion import PromotionError


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
    parser.add_argument("--finish-checks", action="store_true",
                        help="run the reflex checks after serving that a dead process left owed (no RUN: "
                             "every served model that owes one), rolling back those that fail")
    parser.add_argument("--threads", type=int, default=1, help="torch threads for the gate (default 1)")
    parser.add_argument("--json", action="store_true", help="print the outcome as one JSON object on stdout")
    add_result_argument(parser)


def _emit(args: argparse.Namespace, out: dict[str, Any]) -> None:
    write_result(args.result_file, out)
    if args.json:
        print(json.dumps(out, allow_nan=False), flush=True)
        return
    if out.get("error"):
        return
    if "finished" in out:
        for entry in out["finished"]:
            print(describe_finished(entry, who="promote --finish-checks")[1])
        if not out["finished"]:
            print("no reflex check after serving is owed")
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


def _finish_checks(args: argparse.Namespace) -> int:
    given = [flag for flag, on in (("RUN", args.run), ("--checkpoint", args.checkpoint), ("--component", args.component),
                                   ("--force", args.force), ("--auto", args.auto)) if on]
    if given:
        return _usage(args, f"--finish-checks takes no {', '.join(given)}: it finishes every owed check")
    try:
        with open_registry() as (settings, registry):
            with promote_lock(Path(settings.home)):
                code, out = finish_owed_checks(settings, registry, threads=args.threads)
    except (CommandError, PromotionError) as exc:
        return _usage(args, str(exc))
    _emit(args, out)
    return code


def run(args: argparse.Namespace) -> int:
    if args.threads < 1:
        return _usage(args, f"--threads {args.threads} must be >= 1")
    if args.finish_checks:
        return _finish_checks(args)
    if bool(args.run) == bool(args.checkpoint):
        return _usage(args, "give either RUN or --checkpoint DIR (exactly one), or --finish-checks")
    try:
        with open_registry() as (settings, registry):
            with promote_lock(Path(settings.home)):
                code, out = promote_candidate(settings, registry, args)
    except (UsageError, CommandError, PromotionError) as exc:
        return _usage(args, str(exc))
    _emit(args, out)
    return code
