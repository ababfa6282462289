"""The Celery broker both sides use: the task name, where the broker is, and the message rules.

    app = celery_app(settings); app.send_task(TASK_TRAIN_RUN, args=[run_id, attempt], queue="pi")

The daemon sends `hope.train_run` by name and the worker (workers/celery.py) serves it; neither
imports the other, so what they must agree on lives here: the broker URL (settings.redis_url, or
the embedded SQLite broker under $HOPE_HOME with its transport, registry/broker_transport.py),
JSON only (a broker message must not be able to run code), no result backend (the state of every
run lives in the registry, not in Celery results), and the default queue. How a worker runs a
task (one child per job, acks late, ...) is the worker's own business: workers/celery.py.

Building an app connects to nothing and creates no file (the embedded broker's dir is made on
first connect), and imports no torch.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from hope_models.settings import Settings

TASK_TRAIN_RUN = "hope.train_run"
DEFAULT_QUEUE = "pi"
EMBEDDED_TRANSPORT = "registry.broker_transport:Transport"
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


def celery_config(settings: Settings) -> dict[str, Any]:
    """What sender and worker must agree on, as a plain dict (nothing here connects)."""
    conf: dict[str, Any] = dict(
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
        # A Redis restart must not kill the training child: both sides reconnect (forever);
        # claim() in the registry stops any duplicate delivery.
        broker_connection_retry=True,
        broker_connection_retry_on_startup=True,
        broker_connection_max_retries=None,
        broker_channel_error_retry=True,
        task_default_queue=DEFAULT_QUEUE,
        task_create_missing_queues=True,
        # Task events would be broker traffic nobody consumes: run events go to the registry.
        task_send_sent_event=False,
        enable_utc=True,
        timezone="UTC",
    )
    if settings.redis_url:
        conf.update(broker_transport_options={"visibility_timeout": VISIBILITY_TIMEOUT_S})
    else:
        conf.update(broker_transport=EMBEDDED_TRANSPORT, broker_transport_options={"polling_interval": 0.1})
    return conf


def celery_app(settings: Settings, **conf: Any):
    """A Celery app on the broker of `settings` with celery_config(settings) updated by `conf`
    (the worker adds how it runs tasks). `app.hope_settings` is `settings`."""
    from celery import Celery  # lazy: loads celery

    include = conf.pop("include", ())
    app = Celery("hope", include=list(include), set_as_current=False)
    app.conf.update({**celery_config(settings), **conf})
    app.hope_settings = settings
    return app


__all__ = ["DEFAULT_QUEUE", "EMBEDDED_TRANSPORT", "TASK_TRAIN_RUN", "VISIBILITY_TIMEOUT_S", "broker_path",
           "broker_url", "celery_app", "celery_config"]
