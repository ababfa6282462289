"""The robot's door: its calls on a listener of their own, which the Robot Editor's side cannot fill.

    door = open_inference_door(app, settings)   # settings.inference_port (8766), + inference_socket
    door.start() ... door.stop()

The Robot Editor's listener (webapp/server.py) serves browsers, the phone app and Socket.IO, whose
long-polls and WebSockets hold a thread each for as long as a client likes; a neighbour without a
token can hold many of them. The robot's control loop must never wait behind that, so its calls
are answered here, by the same Flask app (the same BrainService, token and Host rule), on another
port with its own threads and its own connection cap:

    POST /api/brain/infer   the token, as on the editor's port
    GET  /api/brain         the token
    GET  /api/ping, /api/health   open, so a robot can check it reaches this door

Everything else is 404 here (no Socket.IO, no editor pages, no uploads) and a WebSocket upgrade is
refused, so every request on this door is answered in milliseconds and nothing can park on it.
The editor's port keeps /api/brain/* too: the Robot Editor's Inference page calls it there.
The door is not for browsers: it has no CORS (cors_origins applies to the editor's port only,
webapp/cors.py), so a browser's preflight here gets 405 without Access-Control-* headers and a
page of another origin can neither call it with the token nor read its answers.
With `inference_socket` set, the same door also listens on that Unix socket (0600, under $HOPE_HOME
when relative): a robot runtime on this machine then needs no TCP port at all.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

from webapp.hosts import HostAllowlist, HostPolicy
from webapp.server import ConnectionLimits, HttpServer, ServerError

if TYPE_CHECKING:
    from hope_models.settings import Settings
    from registry.db import Registry

DOOR_ROUTES = {
    "/api/brain/infer": ("POST",),
    "/api/brain": ("GET", "HEAD"),
    "/api/ping": ("GET", "HEAD"),
    "/api/health": ("GET", "HEAD"),
}
DOOR_KEY = "hope.door"


def _answer(start_response, status: str, message: str, extra: tuple = ()):
    body = json.dumps({"error": message}).encode()
    start_response(status, [("Content-Type", "application/json"), ("Content-Length", str(len(body))),
                            *extra])
    return [body]


def door_app(app):
    """WSGI: only the robot's routes of `app` (the Flask app of create_app), everything else 404."""
    def robots_routes_only(environ, start_response):
        path = environ.get("PATH_INFO", "")
        methods = DOOR_ROUTES.get(path)
        if methods is None:
            return _answer(start_response, "404 Not Found",
                           f"{path[:200]} is not served on the inference port (only "
                           f"{', '.join(sorted(DOOR_ROUTES))}); the Robot Editor is on the main port")
        if environ.get("HTTP_UPGRADE"):
            return _answer(start_response, "400 Bad Request", "no protocol upgrades on the inference port",
                           (("Connection", "close"),))
        if environ.get("REQUEST_METHOD") not in methods:
            return _answer(start_response, "405 Method Not Allowed", f"{path} takes {', '.join(methods)}",
                           (("Allow", ", ".join(methods)),))
        environ[DOOR_KEY] = "inference"
        return app(environ, start_response)

    return robots_routes_only


def create_door_app(settings: Settings, *, token: str, registry: Registry, brain):
    """The app of the door's own process (webapp/door_process.py): the robot's routes only, under the
    same rules as create_app's (the Host rule, the token, JSON errors, the body limit), without
    Socket.IO or the editor's blueprints (~17 MB less to import), wrapped by door_app()."""
    from flask import Flask  # lazy: loads flask

    from webapp import MAX_BODY_BYTES, HopeState, auth, errors, wire_brain  # lazy: loads flask
    from webapp.api import brain as brain_api  # lazy: loads flask
    from webapp.api import health  # lazy: loads flask, sqlalchemy
    from webapp.json_provider import FiniteJSONProvider  # lazy: loads flask

    app = Flask("webapp-door")
    app.config.update(JSON_SORT_KEYS=False, MAX_CONTENT_LENGTH=MAX_BODY_BYTES)
    app.json = FiniteJSONProvider(app)
    app.json.sort_keys = False
    app.extensions["hope"] = HopeState(settings=settings, registry=registry, token=token, brain=brain)
    errors.install(app)
    auth.install(app, None)
    app.register_blueprint(health.bp)
    app.register_blueprint(brain_api.bp)
    wire_brain(brain, None, registry)  # first inferences recorded (the loop closure); no browsers here
    # Flask's documented middleware hook; its stubs declare wsgi_app a method, so mypy refuses the assignment.
    app.wsgi_app = HostAllowlist(app.wsgi_app, HostPolicy.from_settings(settings))  # type: ignore[method-assign]
    return app


def door_limits(settings: Settings) -> ConnectionLimits:
    """The editor's caps, on separate threads; no WebSocket phase (no upgrades here)."""
    limits = ConnectionLimits.from_settings(settings)
    return ConnectionLimits(max_connections=limits.max_connections, max_per_client=limits.max_per_client,
                            websockets=False)


def socket_path(settings: Settings) -> Path | None:
    """The Unix socket the door also listens on (inference_socket; relative = under $HOPE_HOME), or None."""
    name = getattr(settings, "inference_socket", "") or ""
    return Path(settings.home) / name if name else None


class InferenceDoor:
    """The door's listeners: the TCP port, and the Unix socket when one is set."""

    def __init__(self, servers: list[HttpServer]):
        self.servers = servers
        self.port = servers[0].port
        self.url = servers[0].url
        self.socket = servers[1].unix_path if len(servers) > 1 else None

    def start(self) -> None:
        for server in self.servers:
            server.start()

    def stop(self) -> None:
        for server in self.servers:
            server.stop()


def open_inference_door(app, settings: Settings, host: str | None = None) -> InferenceDoor:
    """Bind the door (ServerError when its port or socket cannot be had); the caller starts and stops it."""
    wsgi, limits = door_app(app), door_limits(settings)
    servers = [HttpServer(wsgi, settings.host if host is None else host, settings.inference_port, limits,
                          name="inference", port_hint="--inference-port or HOPE_INFERENCE_PORT; 0 = any free port")]
    path = socket_path(settings)
    if path is not None:
        if len(str(path).encode()) > 107:  # sun_path: 108 bytes with the terminating NUL
            servers[0].stop()
            raise ServerError(f"inference_socket: {path} is longer than a Unix socket path may be (107 bytes); "
                              "set a shorter one (HOPE_INFERENCE_SOCKET)")
        try:
            servers.append(HttpServer(wsgi, f"unix://{path}", 0, limits, name="inference-socket",
                                      port_hint="inference_socket or HOPE_INFERENCE_SOCKET"))
        except Exception:
            servers[0].stop()
            raise
    return InferenceDoor(servers)


__all__ = ["DOOR_ROUTES", "InferenceDoor", "create_door_app", "door_app", "open_inference_door", "socket_path"]
