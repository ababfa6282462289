"""The embedded broker: kombu's SQLAlchemy transport on one SQLite file, polled fast.

With no Redis configured, Celery messages live in $HOPE_HOME/broker/broker.sqlite, so a first run
needs no server. Kombu's own `sqla` transport almost does it, but (kombu 5.7):
- it polls an empty queue once a second (Transport.polling_interval = 1.0), which adds up to a
  second between enqueue and the first step, and between one job and the next;
- it passes every broker transport option straight to sqlalchemy.create_engine, so setting
  {"polling_interval": 0.1} there (the documented virtual-transport option) raises TypeError
  ("Invalid argument(s) 'polling_interval' sent to create_engine()"), and so would a
  visibility_timeout;
- the SQLite file gets the default rollback journal and a 5 s lock timeout, while the worker
  takes a write lock (BEGIN IMMEDIATE) on every poll and the daemon writes when it dispatches;
- two processes opening a new broker file at once (serve starts the daemon and the worker
  together) race: both see no tables and one CREATE TABLE fails ("already exists"), or both
  insert the queue's row and one fails on the UNIQUE name (IntegrityError, which kombu does not
  catch), so the first send or the worker's start fails;
- a delivered message stays in the table for ever (marked invisible; an ack deletes nothing),
  so a service that runs for months would grow the file by one row per job.
This subclass fixes these without touching kombu's global state: options go to the virtual
transport only, the engine gets WAL + a 30 s busy timeout, the broker dir is created on first use
(not when the Celery app is built, so importing the app has no side effects), the tables are
created under an fcntl lock, a lost race for the queue row is retried, and delivered rows are
deleted when a message is taken. That is safe: kombu never reads an invisible row again (an
unacked message is restored from the consumer's memory by re-publishing its payload).

Celery selects it with broker_transport="registry.broker_transport:Transport" and a plain
"sqlite:////abs/path" broker URL (registry/broker.py), on the daemon's side (sending) and the
worker's (consuming) alike.
"""
from __future__ import annotations

import fcntl
import logging
import socket
import sys
import time
from pathlib import Path

from kombu.transport import sqlalchemy as kombu_sqla
from sqlalchemy import create_engine, event
from sqlalchemy.engine import make_url
from sqlalchemy.exc import IntegrityError, SQLAlchemyError

log = logging.getLogger(__name__)

POLLING_INTERVAL_S = 0.1  # an idle worker runs ~10 tiny SQLite transactions a second
BUSY_TIMEOUT_S = 30.0
DRAIN_SLICE_S = 0.25  # how often a waiting drain_events() looks at the worker's stop flags


def _on_connect(dbapi_connection, _record) -> None:
    cursor = dbapi_connection.cursor()
    try:
        # WAL: the daemon's INSERT of a message does not wait for the worker's poll to end.
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute(f"PRAGMA busy_timeout={int(BUSY_TIMEOUT_S * 1000)}")
        cursor.execute("PRAGMA synchronous=NORMAL")
    finally:
        cursor.close()


class Channel(kombu_sqla.Channel):
    def _engine_from_config(self):
        url = make_url(self.connection.client.hostname)
        if url.get_backend_name() != "sqlite" or not url.database or url.database == ":memory:":
            raise ValueError(f"the embedded broker needs a SQLite file URL (sqlite:////path), got {url}")
        path = Path(url.database)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OSError(f"cannot create the broker directory {path.parent}: {exc.strerror or exc}") from None
        engine = create_engine(url, connect_args={"timeout": BUSY_TIMEOUT_S})
        event.listen(engine, "connect", _on_connect)
        # kombu's _open runs create_all right after this; doing it here under a lock first
        # leaves it nothing to create.
        with open(path.with_name(path.name + ".lock"), "a+") as lock:
            fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
            kombu_sqla.metadata.create_all(engine)
        return engine

    def _get_or_create(self, queue):
        try:
            return super()._get_or_create(queue)
        except IntegrityError:  # another process inserted the queue's row between our SELECT and INSERT
            self.session.rollback()
            return super()._get_or_create(queue)

    def _get(self, queue):
        payload = super()._get(queue)  # raises Empty when there is none
        try:
            self.session.query(self.message_cls).filter(self.message_cls.visible == False).delete(  # noqa: E712
                synchronize_session=False)
            self.session.commit()
        except SQLAlchemyError as exc:  # housekeeping only: the message is delivered anyway
            self.session.rollback()
            log.warning("broker: could not delete delivered messages: %s", exc)
        return payload


class Transport(kombu_sqla.Transport):
    Channel = Channel
    # The virtual transport still honours transport_options["polling_interval"] when given.
    polling_interval = POLLING_INTERVAL_S

    def drain_events(self, connection, timeout=None):
        # Celery's loop for polling transports (synloop) asks for 2 s waits and looks at its stop
        # flag only between them, so a warm shutdown of an idle worker began up to 2 s late. Wait in
        # slices and give control back as soon as this process's worker was asked to stop.
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            left = DRAIN_SLICE_S if deadline is None else min(DRAIN_SLICE_S, deadline - time.monotonic())
            try:
                return super().drain_events(connection, timeout=max(left, 0.0))
            except socket.timeout:
                if _worker_stopping() or (deadline is not None and time.monotonic() >= deadline):
                    raise


def _worker_stopping() -> bool:
    """True in a Celery worker whose warm or cold shutdown has been asked for (its signal handlers
    set these flags); False anywhere else, without importing Celery's worker state."""
    state = sys.modules.get("celery.worker.state")
    return state is not None and bool(state.should_stop is not None or state.should_terminate is not None)
