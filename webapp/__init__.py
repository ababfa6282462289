"""The webapp: Flask + Flask-SocketIO for the Robot Editor (REST API, live events).

    app, socketio = create_app(settings, token=load_or_create_token(settings))

Two ways it runs:
- embedded (`run_trainer.py serve`): the daemon runs in this process and pushes events straight
  into this SocketIO (daemon.events.SocketIOSink); `daemon=` lets the API wake it at once;
- production (`run_trainer.py webapp`, systemd): `message_queue=settings.redis_url`, so events the
  daemon process emits through Redis reach this process's browsers.
`brain=` is the BrainService this process hosts (hope_models.runtime.brain_service: NumPy, no
torch) or None; create_app wires its callbacks: a swap is pushed to browsers as `brain.reloaded`
{component, version, checkpoint}, and the first inference on a version records the loop-closure
time of the run that produced it (registry.promotion.record_first_inference). The caller starts and
stops it. Whatever needs torch (the promotion gate, the sim reflex) runs as a `run_trainer.py`
child (webapp/commands.py). Never imports torch (tests/test_api.py checks it).
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import TYPE_CHECKING, Any

from hope_models.components import TOKENIZER
from webapp import cors
from webapp.commands import ChildProcesses
from webapp.hosts import HostAllowlist, HostPolicy
from webapp.socket_guard import SocketGuard

if TYPE_CHECKING:
    from hope_models.settings import Settings

log = logging.getLogger(__name__)


@dataclass
class HopeState:
    """What the views need, kept in app.extensions["hope"]."""

    settings: Any
    registry: Any
    token: str
    daemon: Any = None
    brain: Any = None  # BrainService | None
    children: Any = None  # webapp.commands.ChildProcesses: promote / eval-reflex children
    reflex_jobs: Any = None  # webapp.api.sim.ReflexJobs
    monitor: Any = None  # daemon.monitor.SystemMonitor, made on the first GET /api/system without a daemon
    socket_guard: Any = None  # webapp.socket_guard.SocketGuard: Socket.IO sessions must log in in time
    started: float = field(default_factory=time.monotonic)

    def close(self) -> None:
        """Stop the children this app started (a running promotion gate or sim reflex)."""
        if self.children is not None:
            self.children.close()
        if self.socket_guard is not None:
            self.socket_guard.close()

    def wake_daemon(self) -> None:
        """Ask an embedded daemon to look at the queue now rather than at its next tick."""
        wake = getattr(self.daemon, "wake", None)
        if callable(wake):
            wake()


RELOADED_EVENT = "brain.reloaded"
MAX_BODY_BYTES = 1 << 20  # 1 MiB: an observation of 4096 floats is ~100 kB of JSON


def create_app(settings: Settings, *, token: str, daemon: Any = None, registry: Any = None,
               message_queue: str | None = None, brain: Any = None,
               socket_auth_timeout_s: float = 10.0):
    """(Flask app, SocketIO). `registry` defaults to Registry.open(settings) (migrated)."""
    from flask import Flask  # lazy: loads flask
    from flask_socketio import SocketIO  # lazy: loads flask_socketio

    from webapp import auth, errors, socket_packets  # lazy: loads flask, socketio
    from webapp.api import register  # lazy: loads flask
    from webapp.api.sim import ReflexJobs  # lazy: loads flask
    from webapp.json_provider import FiniteJSONProvider  # lazy: loads flask

    if not isinstance(token, str) or len(token) < auth.MIN_TOKEN_CHARS:
        raise ValueError(f"create_app: the token must be a string of at least {auth.MIN_TOKEN_CHARS} characters")
    if registry is None:
        from registry.db import Registry  # lazy: loads sqlalchemy

        registry = Registry.open(settings)
    app = Flask("webapp")
    app.config.update(JSON_SORT_KEYS=False, MAX_CONTENT_LENGTH=MAX_BODY_BYTES)
    app.json = FiniteJSONProvider(app)  # no NaN/Infinity in any answer: webapp/json_provider.py
    app.json.sort_keys = False
    children = ChildProcesses(settings)
    app.extensions["hope"] = HopeState(settings=settings, registry=registry, token=token, daemon=daemon,
                                       brain=brain, children=children, reflex_jobs=ReflexJobs(children))
    hosts = HostPolicy.from_settings(settings)
    # threading mode: no eventlet/gevent monkey-patching; WebSocket through simple-websocket.
    # Browser origins follow the Host rule (webapp/hosts.py), never X-Forwarded-* headers.
    loggers = socket_packets.quiet_loggers()
    socketio = SocketIO(app, async_mode="threading", message_queue=message_queue,
                        logger=loggers["socketio.server"], engineio_logger=loggers["engineio.server"],
                        max_http_buffer_size=socket_packets.MAX_MESSAGE_BYTES,
                        cors_allowed_origins=hosts.origin_allowed,
                        ping_interval=settings.socketio_ping_interval_s)
    app.extensions["hope"].socket_guard = SocketGuard(socketio, auth_timeout_s=socket_auth_timeout_s)
    # no binary data, bounded messages, a client's bad packet one WARNING line (socket_packets.py)
    socket_packets.install(socketio, app.extensions["hope"].socket_guard)
    app.extensions["hope"].reflex_jobs.socketio = socketio  # sim.frame events of the reflex jobs
    errors.install(app)  # first: the body size is checked before the token
    auth.install(app, socketio)
    register(app)
    if brain is not None:
        wire_brain(brain, socketio, registry)

    from webapp.pages import bp as pages_bp  # lazy: loads flask

    app.register_blueprint(pages_bp)  # the Robot Editor: "/" and its pages (webapp/pages.py)
    # Outermost, around Socket.IO's middleware too: no route or handshake answers a foreign Host.
    # Inside it, CORS for the origins in cors_origins (none by default: not installed), so a listed
    # origin's preflight is answered before the token check and before any view (webapp/cors.py).
    # Flask's documented middleware hook; its stubs declare wsgi_app a method, so mypy refuses the assignment.
    app.wsgi_app = HostAllowlist(  # type: ignore[method-assign]
        cors.install(app.extensions["hope"].socket_guard.middleware(app.wsgi_app), settings.cors_origins), hosts)

    return app, socketio


def _chain(previous: Any, fn):
    """fn, then whatever callback the caller had set (so wiring never drops one)."""
    if not callable(previous):
        return fn

    def both(*args):
        fn(*args)
        previous(*args)

    return both


def wire_brain(brain: Any, socketio: Any, registry: Any) -> None:
    """BrainService callbacks -> Socket.IO and the registry. They run on BrainService's threads;
    a failure is logged, never raised into a request or the watcher."""
    from registry.models import iso  # lazy: loads sqlalchemy

    def on_swap(component, version, checkpoint=None, *_rest):
        try:
            if socketio is not None:  # None: the inference door's process, which has no browsers
                socketio.emit(RELOADED_EVENT, {"component": component, "version": version,
                                               "checkpoint": None if checkpoint is None else str(checkpoint)})
        except Exception:  # noqa: BLE001 - a browser push must not disturb the swap
            log.exception("could not push %s", RELOADED_EVENT)
        log.info("brain: %s now serves %s", component, version)
        if checkpoint is not None and component == TOKENIZER:  # its loop closes when it is loaded (record_loaded)
            threading.Thread(target=loaded, args=(str(checkpoint), datetime.now(timezone.utc)), name="loop-closure",
                             daemon=True).start()

    def loaded(checkpoint, when):
        from registry.promotion import record_loaded  # lazy: loads sqlalchemy

        try:
            with registry.session() as s:
                run = record_loaded(s, checkpoint, when)
                if run is not None:
                    log.info("loop closed: run %s (%s) loaded %.1f s after it finished", run.id, run.component,
                             run.loop_closure_s)
        except Exception:  # noqa: BLE001 - the model is served; only the record failed
            log.exception("could not record the loading of %s", checkpoint)

    def record(component, version, checkpoint, when):
        from registry.promotion import record_first_inference  # lazy: loads sqlalchemy

        try:
            with registry.session() as s:
                run = record_first_inference(s, str(checkpoint), when)
                if run is not None and run.loop_closure_s is not None:
                    log.info("loop closed: run %s (%s) finished %s, first inference on %s at %s: %.1f s",
                             run.id, component, iso(run.finished_at), version, iso(when), run.loop_closure_s)
        except Exception:  # noqa: BLE001 - the inference itself succeeded; only the record failed
            log.exception("could not record the first inference on %s %s", component, version)

    def on_first_inference(component, version, checkpoint, when, *_rest):
        # Called on the request's thread: the registry write (which may wait for the database
        # lock while a job writes) happens beside it, so that first answer is not delayed.
        threading.Thread(target=record, args=(component, version, checkpoint, when), name="loop-closure",
                         daemon=True).start()

    def on_error(component, message, *_rest):
        log.warning("brain: %s: %s (the previous model keeps serving)", component, message)

    brain.on_swap = _chain(getattr(brain, "on_swap", None), on_swap)
    brain.on_first_inference = _chain(getattr(brain, "on_first_inference", None), on_first_inference)
    brain.on_error = _chain(getattr(brain, "on_error", None), on_error)


__all__ = ["HopeState", "MAX_BODY_BYTES", "RELOADED_EVENT", "create_app", "wire_brain"]
