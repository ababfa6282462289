"""The webapp: Flask + Flask-SocketIO for the Robot Editor (REST API, live events).

    app, socketio = create_app(settings, token=load_or_create_token(settings))

Two ways it runs:
- embedded (`run_trainer.py serve`): the daemon runs in this process and pushes events straight
  into this SocketIO (daemon.events.SocketIOSink); `daemon=` lets the API wake it at once;
- production (`run_trainer.py webapp`, systemd): `message_queue=settings.redis_url`, so events the
  daemon process emits through Redis reach this process's browsers.
Never imports torch (issue 6's BrainService loads models lazily in its own module).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

log = logging.getLogger(__name__)


@dataclass
class HopeState:
    """What the views need, kept in app.extensions["hope"]."""

    settings: Any
    registry: Any
    token: str
    daemon: Any = None
    started: float = field(default_factory=time.monotonic)

    def wake_daemon(self) -> None:
        """Ask an embedded daemon to look at the queue now rather than at its next tick."""
        wake = getattr(self.daemon, "wake", None)
        if callable(wake):
            wake()


def create_app(settings, *, token: str, daemon: Any = None, registry: Any = None,
               message_queue: str | None = None):
    """(Flask app, SocketIO). `registry` defaults to Registry.open(settings) (migrated)."""
    from flask import Flask
    from flask_socketio import SocketIO

    from webapp import auth, errors
    from webapp.api import register

    if not isinstance(token, str) or len(token) < auth.MIN_TOKEN_CHARS:
        raise ValueError(f"create_app: the token must be a string of at least {auth.MIN_TOKEN_CHARS} characters")
    if registry is None:
        from daemon.db import Registry

        registry = Registry.open(settings)
    app = Flask("webapp")
    app.config.update(JSON_SORT_KEYS=False, MAX_CONTENT_LENGTH=1 << 20)
    app.json.sort_keys = False
    app.extensions["hope"] = HopeState(settings=settings, registry=registry, token=token, daemon=daemon)
    # threading mode: no eventlet/gevent monkey-patching; WebSocket through simple-websocket.
    socketio = SocketIO(app, async_mode="threading", message_queue=message_queue, logger=False,
                        engineio_logger=False)
    errors.install(app)
    auth.install(app, socketio)
    register(app)

    @app.get("/")
    def index():
        # Placeholder until the Robot Editor pages (issue 6): say where the API is.
        return ("HOPE Seed Trainer\n\nAPI (Authorization: Bearer <token from $HOPE_HOME/token>):\n"
                "  GET /api/health (open)\n  GET|POST /api/runs\n  GET /api/runs/<id>\n"
                "  POST /api/runs/<id>/cancel|pause|resume\nSocket.IO events: run.state, run.progress, "
                "run.log, system.stats, system.throttle\n", 200, {"Content-Type": "text/plain; charset=utf-8"})

    return app, socketio


__all__ = ["HopeState", "create_app"]
