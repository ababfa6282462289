"""HOPE Seed Trainer command line: a thin dispatcher over hope_models, registry, daemon, workers and webapp.

    hope-trainer COMMAND [options]      (the same as `python -m hope_trainer` and, in a checkout,
                                         `python run_trainer.py`)

Each sub-command lives in its own module with `add_arguments(parser)` and `run(args) -> int`;
modules are imported only when their command runs, so `status` never pays for torch.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from hope_models.omp_wait import passive_waits
from hope_models.settings import use_private_umask
from hope_trainer import __version__

PROG = "hope-trainer"

# command name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "validate": ("hope_models.cli.validate", "check RLDS episodes (train or cloud profile)"),
    "ingest": ("hope_models.cli.ingest", "copy episodes into a canonical dataset dir"),
    "export": ("hope_models.cli.export", "write cloud upload files: the Pi runtime's package or ContinuonCloud's .npz"),
    "dataset": ("hope_models.cli.dataset", "build the feature spec and cache of a dataset and summarise it"),
    "train": ("hope_models.cli.train", "train one component (or a sequence) in the foreground, resumable"),
    "sim-demos": ("hope_models.cli.sim_demos", "record expert demonstrations in the dm_control reacher as RLDS"),
    "imagine": ("hope_models.cli.imagine", "produce imagined rollouts by offline search, stored as RLDS"),
    "eval-reflex": ("hope_models.cli.eval_reflex", "run a fast_loop in closed loop in the reacher and score it"),
    "demo": ("hope_trainer.commands.demo",
             "the whole loop through the services: sim demos, chain training, gate, serve, reflex"),
    # the service side: none of these imports torch in its own process (training runs in job children)
    "serve": ("hope_trainer.commands.serve",
              "all-in-one: daemon + webapp + a worker child (first run, no Redis needed)"),
    "daemon": ("daemon.cli.daemon", "the supervisor service: dispatch, monitors, recovery, events (systemd)"),
    "worker": ("workers.cli", "the Celery worker that trains one queued run at a time (-Q queue)"),
    "webapp": ("hope_trainer.commands.webapp", "the Robot Editor API and Socket.IO server (systemd; events via Redis)"),
    "enqueue": ("daemon.cli.enqueue", "queue a training run for the daemon (works with the daemon down)"),
    "sequential": ("daemon.cli.sequential", "queue a chain of runs, e.g. vqvae,fast_loop,mid_loop, one after another"),
    "status": ("daemon.cli.status", "list runs from the registry (--json for scripts)"),
    "watch": ("daemon.cli.watch", "follow a run with a progress bar until it ends"),
    "cancel": ("daemon.cli.cancel", "cancel a run (a running job checkpoints first)"),
    "pause": ("daemon.cli.pause", "pause a run (a running job checkpoints and stops)"),
    "resume": ("daemon.cli.resume", "queue a paused run again; it resumes from its checkpoint"),
    # promotion: promote gates with torch in its own process; rollback is torch-free
    "promote": ("hope_trainer.commands.promote", "gate a completed run's checkpoint and promote it if it passes"),
    "rollback": ("daemon.cli.rollback", "serve the previously promoted model of a component again"),
    "infer": ("hope_trainer.commands.infer",
              "one tick of the promoted model: action, version, latency (serve, or --local)"),
    "doctor": ("hope_trainer.commands.doctor", "what is wrong on this machine: one line per check, each with its fix"),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The full parser, or (when `command` is known) one whose only detailed sub-command is that
    one, so running `status` never imports what `train` needs."""
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module_name)
        if command is None or name == command:
            importlib.import_module(module_name).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:

    # Before anything is written: $HOPE_HOME (registry, broker, token, runs, logs) is for this user
    # only, and the processes this one starts (worker, job children, gate) inherit the umask.
    use_private_umask()
    passive_waits()  # before any torch: the jobs, gates and evaluations this command runs or starts
    argv = sys.argv[1:] if argv is None else argv
    command = argv[0] if argv and argv[0] in COMMANDS else None
    args = build_parser(command).parse_args(argv)
    module = importlib.import_module(args._module)
    try:
        return int(module.run(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


__all__ = ["COMMANDS", "PROG", "build_parser", "main"]
