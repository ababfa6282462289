"""`hope-trainer webapp`: the Robot Editor API and Socket.IO server on its own (hope-webapp.service).

    hope-trainer webapp [--host 127.0.0.1] [--port 8765] [--inference-port 8766]

Production runs the daemon and the worker as their own services; this process serves HTTP and
relays events. With HOPE_REDIS_URL set (production), Socket.IO uses Redis as its message queue,
so the events the daemon process emits reach this process's browsers. Without Redis it tails the
registry's run events itself (same host only; no system.stats, which only the daemon samples).

It hosts BrainService (the promoted models behind POST /api/brain/infer, hot-reloaded from
$HOPE_HOME/promoted/), so production's inference lives here, next to the Robot Editor, and answers
the robot on the inference port, in a child process of its own (webapp/door_process.py).

Under systemd (Type=notify) it sends READY=1 once the ports are bound and WATCHDOG=1 only while its
own GET /api/health answers on the inference port, so a wedged server is restarted. SIGTERM stops it cleanly.
"""
from __future__ import annotations

import argparse
import http.client
import logging
import signal
import sys
import threading
from typing import TYPE_CHECKING

from daemon.events import EventTailer, SocketIOSink
from daemon.sdnotify import SdNotifier
from hope_models.log_format import configure_logging, journal_prefix
from hope_models.malloc_arenas import limit_malloc_arenas
from hope_models.settings import SettingsError
from hope_trainer.commands.serve import add_listen_arguments, brain_summary, door_line, listen_settings
from hope_trainer.console import say
from webapp import create_app
from webapp.door_process import DoorProcess
from webapp.server import ConnectionLimits, HttpServer, ServerError

if TYPE_CHECKING:
    from registry.db import Registry

log = logging.getLogger("hope.webapp")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_listen_arguments(parser)
    parser.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"))


def health_ok(host: str, port: int, timeout: float = 5.0) -> bool:
    if host in ("0.0.0.0", "::", ""):
        host = "127.0.0.1"
    try:
        conn = http.client.HTTPConnection(host, port, timeout=timeout)
        try:
            conn.request("GET", "/api/health")
            return conn.getresponse().status == 200
        finally:
            conn.close()
    except OSError:
        return False


def _tail_events(registry: Registry, socketio, stop: threading.Event) -> None:
    """No Redis: push run events from the registry to this process's browsers."""
    tailer = EventTailer(registry, SocketIOSink(socketio))
    while not stop.is_set():
        try:
            tailer.poll()
        except Exception:  # noqa: BLE001 - the next poll retries; the events stay in the database
            log.exception("event tail failed; retrying")
        stop.wait(0.5)


def _start_logging(level: str) -> None:
    """Under systemd each line carries its journal priority (<3> err ...), elsewhere a timestamp."""
    configure_logging(getattr(logging, level.upper()))
    for noisy in ("werkzeug", "engineio", "socketio", "alembic"):
        logging.getLogger(noisy).setLevel(logging.WARNING)


def run(args: argparse.Namespace) -> int:
    from hope_models.runtime.brain_service import BrainService  # NumPy, no torch
    from registry.db import Registry, RegistryError  # lazy: loads sqlalchemy
    from webapp.auth import TokenError, load_or_create_token, token_path  # lazy: loads flask

    limit_malloc_arenas()  # a thread per connection, for days: hope_models/malloc_arenas.py
    _start_logging(args.log_level)
    notifier = SdNotifier()
    stop = threading.Event()
    try:
        settings = listen_settings(args)
        registry = Registry.open(settings, migrate=True)
    except (SettingsError, RegistryError, OSError) as exc:
        print(f"{journal_prefix()}error: {exc}", file=sys.stderr)
        return 2
    threads: list[threading.Thread] = []
    brain = BrainService(settings.home)
    try:
        token = load_or_create_token(settings)
        app, socketio = create_app(settings, token=token, registry=registry, message_queue=settings.redis_url,
                                   brain=brain)
        server = HttpServer(app, settings.host, settings.port, ConnectionLimits.from_settings(settings))
    except (TokenError, ServerError, ValueError) as exc:
        print(f"{journal_prefix()}error: {exc}", file=sys.stderr)
        registry.close()
        return 2
    try:
        door = DoorProcess(settings).start()  # the robot's door, in a process of its own
    except (ServerError, OSError) as exc:
        print(f"{journal_prefix()}error: {exc}", file=sys.stderr)
        server.stop()
        registry.close()
        return 2

    def on_signal(signum, _frame):
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        brain.start()  # loads what is promoted now, then watches the pointers
        server.start()
        if settings.redis_url:
            log.info("events from the daemon through Redis (Socket.IO message queue)")
        else:
            log.warning("no HOPE_REDIS_URL: relaying run events from the registry in this process "
                        "(production runs Redis; see docs/pi.md)")
            t = threading.Thread(target=_tail_events, args=(registry, socketio, stop), name="events", daemon=True)
            t.start()
            threads.append(t)
        say(f"Robot Editor: {server.url}  token in {token_path(settings)}")
        say(door_line(door))
        say(brain_summary(brain))
        notifier.ready(f"listening on {server.url}")
        ping_every = notifier.watchdog_s / 2 if notifier.watchdog_s else 5.0
        assert door.port is not None  # DoorProcess.start() set it from the child's ready message
        while not stop.wait(ping_every):
            # the robot's door: the editor's port may be full of a neighbour's requests, which a
            # restart would not cure but would cut the robot's inference
            if notifier.watchdog_s and health_ok(settings.host, door.port):
                notifier.watchdog()
        notifier.stopping("stopping")
        server.stop()
        door.stop()
        app.extensions["hope"].close()  # a promotion gate or sim reflex child still running
        for t in threads:
            t.join(2.0)
        return 0
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        brain.stop()
        registry.close()
