"""CORS for the API on the Robot Editor's port: which other web origins' pages may call /api/.

A web build of the Continuon app is served from its own origin (its host, or a dev server's
`http://<laptop>:<port>`), so a browser lets it read the trainer's answers only when they say so,
and asks first (a preflight) before any call that sends `authorization` or a JSON body. The
setting `cors_origins` (config.toml, or HOPE_CORS_ORIGINS, comma-separated; checked and spelled
like an Origin header by hope_models/settings.check_origin) lists the origins allowed; it is empty
by default, and then this middleware is not installed at all: no answer carries a CORS header.

For a request to /api/... whose Origin is listed:
- a preflight (OPTIONS with Access-Control-Request-Method) is answered here, 204, with
  Access-Control-Allow-Origin (that origin, never `*`), -Allow-Methods (GET, POST, HEAD),
  -Allow-Headers (Authorization, Content-Type), -Max-Age and Vary: Origin. It never reaches the
  app: no token is asked for (a browser sends none with a preflight), and no view runs, so a
  preflight can change nothing;
- any other request goes to the app as usual (the token, the Host rule, every check), and its
  answer gains Access-Control-Allow-Origin: <that origin> and Vary: Origin.
An Origin that is not listed gets no CORS header, and its preflight is refused (403, a JSON
message naming the setting): the browser then does not send the call. Requests without an Origin
(the phone app, curl, the robot) and the Robot Editor's own same-origin calls are untouched, so a
listed origin adds a reader and takes nothing away. No credentials mode: the API's credential is
the bearer token a page sends itself, never a cookie.

Only /api/ is covered: Socket.IO (/socket.io/) keeps its own origin rule (webapp/hosts.py:
the page's own host:port), and the pages are the editor's. The inference door (webapp/inference_door.py)
is not for browsers: it is not wrapped, so a preflight there gets 405 without CORS headers.

Installed inside the Host allowlist (webapp/__init__.py): a foreign Host is refused before this.
"""
from __future__ import annotations

import json
from typing import Callable, Iterable

API_PREFIX = "/api/"
ALLOW_METHODS = "GET, POST, HEAD"
ALLOW_HEADERS = "Authorization, Content-Type"
MAX_AGE_S = 600  # browsers cap it anyway (Chrome at 7200 s); a changed setting is seen within 10 minutes


def _vary(headers: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """headers with Origin in Vary (added to an existing Vary, never a second header)."""
    out, done = [], False
    for name, value in headers:
        if name.lower() == "vary":
            parts = [p.strip() for p in value.split(",") if p.strip()]
            if "origin" not in {p.lower() for p in parts}:
                value = ", ".join([*parts, "Origin"])
            done = True
        out.append((name, value))
    return out if done else [*out, ("Vary", "Origin")]


class Cors:
    """WSGI middleware: the rules of the module doc for the origins in `origins`."""

    def __init__(self, app: Callable, origins: Iterable[str]):
        self.app = app
        self.origins = frozenset(origins)

    def __call__(self, environ, start_response):
        if not str(environ.get("PATH_INFO", "")).startswith(API_PREFIX):
            return self.app(environ, start_response)
        origin = environ.get("HTTP_ORIGIN")
        listed = origin is not None and origin.lower() in self.origins
        preflight = environ.get("REQUEST_METHOD") == "OPTIONS" and "HTTP_ACCESS_CONTROL_REQUEST_METHOD" in environ
        if preflight and origin is not None:
            return self._preflight(origin, listed, start_response)
        if not listed:
            return self.app(environ, start_response)

        def with_cors(status, headers, exc_info=None):
            headers = [(k, v) for k, v in headers if not k.lower().startswith("access-control-")]
            return start_response(status, _vary([*headers, ("Access-Control-Allow-Origin", origin)]), exc_info)

        return self.app(environ, with_cors)

    @staticmethod
    def _preflight(origin: str, listed: bool, start_response):
        if not listed:
            body = json.dumps({"error": f"origin {origin[:200]!r} may not call this API from a browser; if it is "
                               "your web build of the app, add it to cors_origins in $HOPE_HOME/config.toml "
                               "(or HOPE_CORS_ORIGINS)"}).encode()
            start_response("403 Forbidden", [("Content-Type", "application/json"),
                                              ("Content-Length", str(len(body))), ("Vary", "Origin")])
            return [body]
        start_response("204 No Content", [("Access-Control-Allow-Origin", origin),
                                          ("Access-Control-Allow-Methods", ALLOW_METHODS),
                                          ("Access-Control-Allow-Headers", ALLOW_HEADERS),
                                          ("Access-Control-Max-Age", str(MAX_AGE_S)), ("Vary", "Origin"),
                                          ("Content-Length", "0")])
        return []


def install(wsgi_app: Callable, origins: Iterable[str]) -> Callable:
    """`wsgi_app` wrapped by Cors, or `wsgi_app` itself when no origin is listed (the default)."""
    origins = list(origins)
    return Cors(wsgi_app, origins) if origins else wsgi_app


__all__ = ["ALLOW_HEADERS", "ALLOW_METHODS", "Cors", "MAX_AGE_S", "install"]
