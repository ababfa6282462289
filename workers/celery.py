"""The Celery app: one worker, one job at a time, each job in a fresh child process.

    celery -A workers.celery:app worker ...     (see workers/cli.py for the full command)

The broker, the task name and the JSON-only rule are shared with the daemon, which sends the task
by name without importing this package: registry/broker.py. What is here is how the worker runs it.

Celery is only the delivery mechanism. The state of every run lives in the registry (SQLite):
the task carries a run id and an attempt number, the child claims the run there (a stale or
duplicate delivery is refused by claim()), trains, and records the outcome there. Hence:
- no result backend (task_ignore_result): nothing reads Celery results;
- acks late and a killed child's message is not redelivered (task_reject_on_worker_lost=False):
  the daemon sees the dead child in the registry and requeues the run to resume from its
  checkpoint, so a redelivery would only be a second, racing attempt;
- JSON only, never pickle (a broker message must not be able to run code);
- prefetch 1, concurrency 1, a new child per task (its memory, torch included, goes back to
  the OS when it exits; the parent never imports torch);
- stopping the worker does not wait for a job that may run for hours: the job checkpoints and
  goes back to the queue (see _stop_the_running_job and workers.job);
- the parent beats (workers/heartbeat.py) from worker_ready to worker_shutdown: name, queues,
  current run, for the Workers page; Celery's own heartbeat/gossip stay off (workers/cli.py).

Importing this module builds `app` from the environment ($HOPE_HOME, HOPE_REDIS_URL) and does
nothing else: no connection, no files (the embedded broker's dir is made on first connect).
"""
from __future__ import annotations

import logging
import os
import signal

from celery.signals import setup_logging, worker_init, worker_ready, worker_shutdown, worker_shutting_down
from celery.utils.log import get_multiprocessing_logger
from celery.worker import state as worker_state

from hope_models.log_format import configure_logging
from hope_models.omp_wait import passive_waits
from hope_models.settings import Settings, load_settings, use_private_umask
from registry.broker import celery_app


def worker_config(settings: Settings) -> dict:
    """How this worker runs tasks, on top of the broker rules it shares with the daemon
    (registry/broker.py)."""
    conf = dict(
        # Ack when the task returns; a dead child's message is acked, not requeued (see above).
        task_acks_late=True,
        task_reject_on_worker_lost=False,
        task_acks_on_failure_or_timeout=True,
        worker_prefetch_multiplier=1,
        worker_concurrency=1,
        worker_max_tasks_per_child=1,
        # After a child dies, billiard waits this long for a result nobody reads (results are
        # ignored) before the next message is taken: the default 10 s only delays recovery.
        worker_lost_wait=1.0,
        worker_pool="prefork",
        # A lost broker connection must not kill the training child: the worker reconnects and
        # the child keeps going.
        worker_cancel_long_running_tasks_on_connection_loss=False,
        worker_hijack_root_logger=False,
        # Worker events would be broker traffic nobody consumes: run events go to the registry.
        worker_send_task_events=False,
        include=["workers.tasks"],
    )
    if not settings.redis_url:
        # Remote control (celery inspect/control) needs fanout, which the SQL transport only
        # emulates inside one process: it would be one more queue polled for nothing.
        conf.update(worker_enable_remote_control=False)
    return conf


def create_celery(settings: Settings):
    """The worker's Celery app for `settings`. `app.hope_settings` is what the task body uses in
    the worker child."""
    return celery_app(settings, **worker_config(settings))


@worker_init.connect
def _private_files(**_kw) -> None:
    """A worker started as `celery -A workers.celery:app worker` (serve, tests, by hand) rather than
    through run_trainer.py: its job children write checkpoints, logs and the registry under
    $HOPE_HOME, which are its user's alone (they inherit the umask from this parent). Likewise
    OpenMP's passive waits (hope_models/omp_wait.py): the children load torch, this parent never."""
    use_private_umask()
    passive_waits()


@setup_logging.connect
def _log_like_the_other_services(loglevel=None, **_kw) -> None:
    """Celery's own handler would stamp every line with its own time and leave journald to file it
    all as "info". With a receiver on this signal Celery configures no logging at all; the root
    logger gets the daemon's and the webapp's format instead (hope_models/log_format.py: under
    systemd, `<N>` priority prefixes and no timestamp), at --loglevel. The job runs in a forked pool
    child, which inherits this handler, so its lines are formatted the same way."""
    handler = configure_logging(loglevel or "INFO")
    mp_logger = get_multiprocessing_logger()  # billiard's pool logger does not propagate
    if handler is not None and mp_logger is not None and not mp_logger.handlers:
        # as Celery would: its errors (a pool child that died) on the same stream, nothing below
        mp_logger.addHandler(handler)
        mp_logger.setLevel(logging.ERROR)


@worker_shutting_down.connect
def _stop_the_running_job(**_kw) -> None:
    """The worker parent is stopping (SIGTERM, or Ctrl-C in a terminal, which the pool child
    ignores). A job may run for hours, so rather than wait for it, pass SIGTERM on to the child
    running it: the job checkpoints and goes back to the queue (workers.job), then the parent's
    warm shutdown completes. Idle children are left to the pool (a SIGTERM would make it log them
    as crashed). Under systemd with KillMode=control-group the child gets SIGTERM anyway; a second
    one changes nothing. Runs in the parent's signal handler: reads and kill() only."""
    for request in list(worker_state.active_requests):
        pid = getattr(request, "worker_pid", None)
        if pid:
            try:
                os.kill(pid, signal.SIGTERM)
            except OSError:  # already gone
                pass


_heartbeat = None  # this parent's workers.heartbeat.WorkerHeartbeat, between ready and shutdown


@worker_ready.connect
def _start_heartbeat(sender=None, **_kw) -> None:
    """The worker consumes now: beat from a daemon thread of this (parent) process. `sender` is
    Celery's consumer: its node name and the queues it consumes."""
    global _heartbeat
    from workers.heartbeat import WorkerHeartbeat  # lazy: loads sqlalchemy

    settings = getattr(sender.app, "hope_settings", None) or load_settings()
    queues = sorted(sender.app.amqp.queues.consume_from or sender.app.amqp.queues)
    _heartbeat = WorkerHeartbeat(settings, sender.hostname, queues)
    _heartbeat.start()


@worker_shutdown.connect
def _stop_heartbeat(**_kw) -> None:
    """Warm shutdown done (sent in the parent only): the last beat says "stopped"."""
    global _heartbeat
    if _heartbeat is not None:
        _heartbeat.stop()
        _heartbeat = None


# The `celery -A workers.celery:app` entry point: settings from $HOPE_HOME / the environment.
app = create_celery(load_settings())
