"""`run_trainer.py status [RUN] [--all] [--json]`: the runs in the registry.

Without RUN: every run that has not ended plus the most recent ones (`--all`: every run), newest
first. `--json` prints {"runs": [Run.to_json_obj(), ...]} (runs.to_json). Reads the database only,
so it works whether the daemon is up or not.

A `starting` run was sent to its queue but no worker has taken it yet; under the table (and in
`waiting` in the JSON) it says since when it waits for a worker on which queue, and a queued run
held behind it says so too.

CLOSURE is the run's loop-closure time: from the run completing to the first inference BrainService
answered with its weights (promotion gate and hot reload included; recorded by the webapp that hosts
BrainService). "-" until that happened.
"""
from __future__ import annotations

import argparse
import math
from datetime import datetime
from typing import Any

from daemon.cli.registry import open_registry, print_json, run_command

RECENT = 20  # ended runs shown without --all


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", nargs="?", metavar="RUN", help="one run id (default: active and recent runs)")
    parser.add_argument("--all", action="store_true", help=f"every run, not just active ones and the last {RECENT}")
    parser.add_argument("--json", action="store_true", help='print {"runs": [...]} on stdout')


def state_text(run: dict[str, Any]) -> str:
    state = run["state"]
    if state == "paused" and run.get("pause_reason"):
        return f"paused({run['pause_reason']})"
    if state == "running" and run.get("desired_state") not in (None, "run"):
        return f"running->{run['desired_state']}"
    return state


def age_text(iso_time: str | None, now: datetime | None = None) -> str:
    if not iso_time:
        return "-"
    then = datetime.fromisoformat(iso_time)
    now = now or datetime.now(then.tzinfo)
    s = max(0, int((now - then).total_seconds()))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m"
    if s < 86400:
        return f"{s // 3600}h{s % 3600 // 60:02d}m"
    return f"{s // 86400}d{s % 86400 // 3600:02d}h"


def _num(v: Any, fmt: str) -> str:
    return "-" if not isinstance(v, (int, float)) or not math.isfinite(v) else format(v, fmt)


def closure_text(seconds: Any) -> str:
    """Loop-closure seconds, short: 8.4s, 12m05s, 3h20m."""
    if not isinstance(seconds, (int, float)) or not math.isfinite(seconds):
        return "-"
    if seconds < 60:
        return f"{seconds:.1f}s"
    s = int(seconds)
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{s % 3600 // 60:02d}m"


def format_table(runs: list[dict[str, Any]]) -> str:
    if not runs:
        return "no runs (queue one with: run_trainer.py enqueue --component fast_loop --data DS)"
    header = ("RUN", "COMPONENT", "QUEUE", "STATE", "STEP", "LOSS", "STEPS/S", "ATTEMPT", "AGE", "CLOSURE")
    rows = [header]
    for r in runs:
        rows.append((r["id"], r["component"], r["queue"], state_text(r), f"{r['step']}/{r['total_steps']}",
                     _num(r.get("loss"), ".4g"), _num(r.get("steps_per_s"), ".1f"),
                     f"{r['attempt']}/{r['max_attempts']}", age_text(r.get("created_at")),
                     closure_text(r.get("loop_closure_s"))))
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip() for row in rows]
    for r in runs:  # why a run failed or was cancelled, or what it waits for, under the table
        if r["state"] in ("failed", "cancelled") and r.get("error"):
            lines.append(f"{r['id']}: {r['error']}")
        elif r.get("waiting"):
            lines.append(f"{r['id']}: {r['waiting']}")
    return "\n".join(lines)


def collect(session, run_id: str | None, all_runs: bool) -> list[dict[str, Any]]:
    from registry import runs  # lazy: loads sqlalchemy

    if run_id:
        return runs.to_json(session, [runs.get_run(session, run_id)])
    if all_runs:
        return runs.to_json(session, runs.list_runs(session))
    live = [s for s in runs.STATES if s not in runs.TERMINAL]
    chosen = {r.id: r for r in runs.list_runs(session, states=live)}
    for r in runs.list_runs(session, limit=RECENT):
        chosen.setdefault(r.id, r)
    ordered = sorted(chosen.values(), key=lambda r: (r.created_at, r.id), reverse=True)
    return runs.to_json(session, ordered)


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        with open_registry() as (_settings, registry):
            with registry.session(readonly=True) as s:
                items = collect(s, args.run, args.all)
        if args.json:
            print_json({"runs": items})
        else:
            print(format_table(items))
        return 0

    return run_command(body)
