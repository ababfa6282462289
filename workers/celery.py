"""The Celery app: one worker, one job at a time, each job in a fresh child process.

    celery -A workers.celery:app worker ...     (see workers/cli.py for the full command)
    app = create_celery(settings); app.send_task("hope.train_run", args=[run_id, attempt], queue="pi")

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
  goes back to the queue (see _stop_the_running_job and workers.job).

Importing this module builds `app` from the environment ($HOPE_HOME, HOPE_REDIS_URL) and does
nothing else: no connection, no files (the embedded broker's dir is made on first connect).
"""
from __future__ import annotations

import os
import signal
from pathlib import Path

from celery import Celery
from celery.signals import worker_init, worker_shutting_down

from hope_models.settings import Settings, load_settings, use_private_umask

TASK_TRAIN_RUN = "hope.train_run"
DEFAULT_QUEUE = "pi"
EMBEDDED_TRANSPORT = "workers.transport:Transport"
# Longer than the longest job: Redis redelivers an unacked message after this long. A real
# redelivery (Redis restarted, worker lost) is handled by the daemon from the registry instead.
VISIBILITY_TIMEOUT_S = 7 * 24 * 3600


def broker_path(settings: Settings) -> Path:
    return Path(settings.home) / "broker" / "broker.sqlite"


def broker_url(settings: Settings) -> str:
    """settings.redis_url, or the embedded SQLite broker file under $HOPE_HOME (an absolute
    path: 'sqlite:////abs/...')."""
    if settings.redis_url:
        return settings.redis_url
    return f"sqlite:///{broker_path(settings).resolve()}"


def celery_config(settings: Settings) -> dict:
    """The app's configuration as a plain dict (tests check it; nothing here connects)."""
    embedded = not settings.redis_url
    conf = dict(
        broker_url=broker_url(settings),
        # JSON in and out, everywhere; a pickled message is refused, not run.
        task_serializer="json",
        result_serializer="json",
        event_serializer="json",
        accept_content=["json"],
        result_accept_content=["json"],
        # State lives in the registry; Celery results are never read.
        result_backend=None,
        task_ignore_result=True,
        task_store_errors_even_if_ignored=False,
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
        # A Redis restart must not kill the training child: the worker reconnects (forever) and
        # the child keeps going; claim() in the registry stops any duplicate delivery.
        broker_connection_retry=True,
        broker_connection_retry_on_startup=True,
        broker_connection_max_retries=None,
        broker_channel_error_retry=True,
        worker_cancel_long_running_tasks_on_connection_loss=False,
        task_default_queue=DEFAULT_QUEUE,
        task_create_missing_queues=True,
        worker_hijack_root_logger=False,
        # Task/worker events would be broker traffic nobody consumes: run events go to the registry.
        worker_send_task_events=False,
        task_send_sent_event=False,
        enable_utc=True,
        timezone="UTC",
        include=["workers.tasks"],
    )
    if embedded:
        conf.update(
            broker_transport=EMBEDDED_TRANSPORT,
            broker_transport_options={"polling_interval": 0.1},
            # Remote control (celery inspect/control) needs fanout, which the SQL transport only
            # emulates inside one process: it would be one more queue polled for nothing.
            worker_enable_remote_control=False,
        )
    else:
        conf.update(broker_transport_options={"visibility_timeout": VISIBILITY_TIMEOUT_S})
    return conf


def create_celery(settings: Settings) -> Celery:
    """The Celery app for `settings` (the daemon builds one to send tasks; sending never
    imports torch). `app.hope_settings` is what the task body uses in the worker child."""
    conf = celery_config(settings)
    include = conf.pop("include")
    app = Celery("hope", include=include, set_as_current=False)
    app.conf.update(conf)
    app.hope_settings = settings
    return app


@worker_init.connect
def _private_files(**_kw) -> None:
    """A worker started as `celery -A workers.celery:app worker` (serve, tests, by hand) rather than
    through run_trainer.py: its job children write checkpoints, logs and the registry under
    $HOPE_HOME, which are its user's alone (they inherit the umask from this parent)."""
    use_private_umask()


@worker_shutting_down.connect
def _stop_the_running_job(**_kw) -> None:
    """The worker parent is stopping (SIGTERM, or Ctrl-C in a terminal, which the pool child
    ignores). A job may run for hours, so rather than wait for it, pass SIGTERM on to the child
    running it: the job checkpoints and goes back to the queue (workers.job), then the parent's
    warm shutdown completes. Idle children are left to the pool (a SIGTERM would make it log them
    as crashed). Under systemd with KillMode=control-group the child gets SIGTERM anyway; a second
    one changes nothing. Runs in the parent's signal handler: reads and kill() only."""
    from celery.worker import state as worker_state

    for request in list(worker_state.active_requests):
        pid = getattr(request, "worker_pid", None)
        if pid:
            try:
                os.kill(pid, signal.SIGTERM)
            except OSError:  # already gone
                pass


# The `celery -A workers.celery:app` entry point: settings from $HOPE_HOME / the environment.
app = create_celery(load_settings())
