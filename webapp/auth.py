"""The webapp's bearer token: where it lives, how requests prove they have it.

One random token per deployment in `$HOPE_HOME/token` (mode 0600), created on the first start
and printed by `serve`. HTTP requests send `Authorization: Bearer <token>`; Socket.IO clients send
it as `auth={"token": ...}` (or `?token=` on the connection URL, for clients that cannot set auth).

Default deny: every route under /api/ needs the token unless its view is marked `@public`
(/api/health, and /api/ping, which the Continuon app calls without one). Comparisons are constant-time.
"""
from __future__ import annotations

import hmac
import os
import secrets
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from flask import Flask, current_app, jsonify, request

from webapp.socket_guard import mark_authorized

if TYPE_CHECKING:
    from hope_models.settings import Settings

TOKEN_FILENAME = "token"
TOKEN_BYTES = 32  # 256 bits, urlsafe base64 (43 characters)
MIN_TOKEN_CHARS = 16
PUBLIC_ATTR = "hope_public"  # set on a view by public()


class TokenError(RuntimeError):
    """The token file cannot be used (unreadable, too permissive, empty); the message names the file."""


def token_path(settings: Settings) -> Path:
    return Path(settings.home) / TOKEN_FILENAME


def read_token(path: Path) -> str:
    try:
        st = path.stat()
        text = path.read_text(encoding="utf-8").strip()
    except OSError as exc:
        raise TokenError(f"{path}: cannot read the webapp token: {exc.strerror or exc}") from None
    if st.st_mode & 0o077:
        raise TokenError(f"{path}: the token file is readable by others (mode {st.st_mode & 0o777:o}); "
                         f"chmod 600 {path}")
    if len(text) < MIN_TOKEN_CHARS:
        raise TokenError(f"{path}: the token is shorter than {MIN_TOKEN_CHARS} characters; delete the file "
                         "to have a new one made")
    return text


def load_or_create_token(settings: Settings) -> str:
    """The deployment's token, created (0600, exclusively: two starts at once agree) if missing."""
    return load_or_create_secret(token_path(settings))


def load_or_create_secret(path: Path) -> str:
    """The token in `path` (read_token's checks), a new random one written 0600 first if missing."""
    path.parent.mkdir(parents=True, exist_ok=True)
    token = secrets.token_urlsafe(TOKEN_BYTES)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return read_token(path)
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        fh.write(token + "\n")
        fh.flush()
        os.fsync(fh.fileno())
    return token


def tokens_match(given: Any, expected: str) -> bool:
    if not isinstance(given, str) or not given:
        return False
    return hmac.compare_digest(given.encode("utf-8"), expected.encode("utf-8"))


def bearer_token() -> str | None:
    """The token of the current HTTP request's Authorization header, if it is a Bearer one."""
    header = request.headers.get("Authorization", "")
    scheme, _, value = header.partition(" ")
    if scheme.lower() != "bearer":
        return None
    return value.strip() or None


def _expected() -> str:
    return current_app.extensions["hope"].token


def unauthorized(message: str):
    response = jsonify({"error": message})
    response.status_code = 401
    response.headers["WWW-Authenticate"] = 'Bearer realm="hope-trainer"'
    return response


def check_request():
    """None when the request carries the token, else the 401 response."""
    given = bearer_token()
    if given is None:
        return unauthorized("missing bearer token: send 'Authorization: Bearer <token>' "
                            "(the token is in $HOPE_HOME/token)")
    if not tokens_match(given, _expected()):
        return unauthorized("invalid bearer token")
    return None


def public(view: Callable) -> Callable:
    """Mark a view as open (no token), e.g. the health check."""
    setattr(view, PUBLIC_ATTR, True)
    return view


def install(app: Flask, socketio) -> None:
    """Default-deny on /api/ and the Socket.IO connect check (none without `socketio`: the door)."""

    @app.before_request
    def _api_needs_token():
        if not request.path.startswith("/api/"):
            return None
        view = app.view_functions.get(request.endpoint) if request.endpoint else None
        if view is not None and getattr(view, PUBLIC_ATTR, False):
            return None
        return check_request()

    if socketio is None:
        return
    # '*': every namespace. A namespace that registers its own connect handler must call
    # socket_authorized(auth) itself: python-socketio prefers the specific handler over this one.
    # flask_socketio's, not the builtin ConnectionRefusedError: only its message reaches the client
    from flask_socketio import ConnectionRefusedError as SocketRefused

    @socketio.on("connect", namespace="*")
    def _socket_connect(auth=None):
        if not socket_authorized(auth):
            raise SocketRefused("unauthorized: connect with auth={'token': <token>} (the token is in $HOPE_HOME/token)")
        mark_authorized(request.environ)  # the session may stay past its login deadline (socket_guard.py)


def socket_authorized(auth: Any) -> bool:
    """Token from the Socket.IO auth payload, the ?token= query or an Authorization header."""
    given = None
    if isinstance(auth, dict):
        given = auth.get("token")
    if given is None:
        given = request.args.get("token")
    if given is None:
        given = bearer_token()
    return tokens_match(given, _expected())
