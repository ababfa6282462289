"""`run_trainer.py cancel|pause|resume RUN [--json]`: ask for a change of a run's state.

The request goes into the registry (runs.request_control): a queued, starting (sent to its queue,
not yet taken by a worker) or paused run changes at once; a running one gets its desired state set, and the job's training loop, which polls it between
steps, checkpoints and stops (cancel keeps the checkpoints). So these work whether the daemon is up
or not. A request that makes no sense (cancelling a completed run) exits 2 with the reason.
`--json` prints {"run": Run.to_json_obj()} after the request.
"""
from __future__ import annotations

import argparse
from typing import Callable

from daemon.cli.registry import open_registry, print_json, run_command

WHAT = {
    "cancel": "stop the run for good (a running job checkpoints first; checkpoints are kept)",
    "pause": "pause the run (a running job checkpoints and stops; `resume` queues it again)",
    "resume": "queue a paused run again (it resumes from its last checkpoint)",
}


def describe(action: str, run: dict) -> str:
    state = run["state"]
    if state == "running" and run.get("desired_state") != "run":
        return (f"{run['id']}: {action} requested; the job stops at its next step "
                f"(state running -> {run['desired_state']})")
    if state == "paused":
        return f"{run['id']}: paused ({run.get('pause_reason') or 'user'})"
    return f"{run['id']}: {state}"


def make(action: str) -> tuple[Callable, Callable]:
    """(add_arguments, run) of the command for one action."""
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        parser.description = f"{action}: {WHAT[action]}"
        parser.add_argument("run", metavar="RUN", help="the run id (see `run_trainer.py status`)")
        parser.add_argument("--json", action="store_true", help='print {"run": {...}} on stdout')

    def run(args: argparse.Namespace) -> int:
        from registry import runs  # lazy: loads sqlalchemy

        def body() -> int:
            with open_registry() as (_settings, registry):
                with registry.session() as s:
                    obj = runs.request_control(s, args.run, action).to_json_obj()
            if args.json:
                print_json({"run": obj})
            else:
                print(describe(action, obj))
            return 0

        return run_command(body)

    return add_arguments, run
