"""`run_trainer.py worker`: run the Celery worker that trains one queued run at a time.

    run_trainer.py worker [-Q pi] [--hostname NAME] [--loglevel info]

It replaces itself (exec) with

    python -m celery -A workers.celery:app worker --pool=prefork --concurrency=1
        --max-tasks-per-child=1 --prefetch-multiplier=1 -Q <queue> -n <queue>@%h
        --without-gossip --without-mingle --without-heartbeat --loglevel=<level>

so systemd (hope-worker.service) supervises the Celery parent directly. Gossip, mingle and the
worker heartbeat are broadcast/event traffic only Celery's monitoring tools read, and the
embedded SQL broker cannot fan out at all; task events (-E) are off for the same reason: run
progress goes to the registry. Nothing here imports Celery or torch.
"""
from __future__ import annotations

import argparse
import os
import re
import sys
from collections.abc import Mapping
from typing import TYPE_CHECKING

from hope_models.child_command import module_argv
from hope_models.log_format import journal_prefix
from hope_models.settings import SettingsError, load_settings

if TYPE_CHECKING:
    from hope_models.settings import Settings

QUEUE_RE = re.compile(r"[a-z0-9_-]+")
LOGLEVELS = ("debug", "info", "warning", "error", "critical")


def worker_command(settings: Settings | None = None, queue: str = "pi", *, hostname: str | None = None,
                   loglevel: str = "info", python: str | None = None) -> list[str]:
    """The worker's argv (python first). Run it with worker_env(settings) so it reads the same
    HOPE_HOME (and Redis URL) as the caller; `settings` is accepted for that symmetry."""
    if not isinstance(queue, str) or not QUEUE_RE.fullmatch(queue):
        raise ValueError(f"queue {queue!r} must match [a-z0-9_-]+ (e.g. pi, gpu)")
    if loglevel.lower() not in LOGLEVELS:
        raise ValueError(f"loglevel {loglevel!r} is not one of {', '.join(LOGLEVELS)}")
    return module_argv("celery", "-A", "workers.celery:app", "worker",
                       "--pool=prefork", "--concurrency=1", "--max-tasks-per-child=1", "--prefetch-multiplier=1",
                       "-Q", queue, "-n", hostname or f"{queue}@%h",
                       "--without-gossip", "--without-mingle", "--without-heartbeat",
                       f"--loglevel={loglevel.lower()}", python=python)


def worker_env(settings: Settings, base: Mapping[str, str] | None = None) -> dict[str, str]:
    """The environment for the worker process: `base` (default os.environ) with HOPE_HOME and,
    when set, HOPE_REDIS_URL taken from `settings`, so the worker uses the caller's state dir
    and broker even when those came from code rather than the environment."""
    env = dict(os.environ if base is None else base)
    env["HOPE_HOME"] = str(settings.home)
    if settings.redis_url:
        env["HOPE_REDIS_URL"] = settings.redis_url
    else:
        env.pop("HOPE_REDIS_URL", None)
    return env


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-Q", "--queue", default="pi",
                        help="the queue this worker serves, one run at a time (default pi; e.g. gpu on a desktop)")
    parser.add_argument("-n", "--hostname", default=None, metavar="NAME",
                        help="the worker's node name (default <queue>@<host>)")
    parser.add_argument("--loglevel", default="info", choices=LOGLEVELS)


def run(args: argparse.Namespace) -> int:
    try:
        settings = load_settings()
        cmd = worker_command(settings, args.queue, hostname=args.hostname, loglevel=args.loglevel)
    except (SettingsError, ValueError) as exc:
        print(f"{journal_prefix()}error: {exc}", file=sys.stderr)
        return 2
    broker = "redis (HOPE_REDIS_URL)" if settings.redis_url else f"embedded ({settings.home / 'broker'})"
    print(f"worker: queue {args.queue}, broker {broker}, state {settings.home}", file=sys.stderr, flush=True)
    os.execve(cmd[0], cmd, worker_env(settings))
    return 0  # not reached
