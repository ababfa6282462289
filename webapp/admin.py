"""The second credential a forced promotion over HTTP needs.

The app's bearer token travels in clear on the LAN and sits in the phone app, so it cannot be what
lets a client serve a model the promotion gate refused. `POST /api/brain/promote` with
`force: true` is refused (403) unless the setting allow_http_force is on (off by default) and the
request carries `X-Hope-Admin: <the token in $HOPE_HOME/admin_token>` (0600; made on the first
such request when missing: read it on the robot). On the robot, `hope-trainer promote --force`
can always force. Comparisons are constant-time.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from flask import request

from webapp.auth import TokenError, load_or_create_secret, tokens_match

if TYPE_CHECKING:
    from hope_models.settings import Settings

ADMIN_TOKEN_FILENAME = "admin_token"
ADMIN_HEADER = "X-Hope-Admin"


def admin_token_path(settings: Settings) -> Path:
    return Path(settings.home) / ADMIN_TOKEN_FILENAME


def force_refusal(settings: Settings) -> str | None:
    """Why the current request may not force a promotion (the 403's message), or None."""
    if not settings.allow_http_force:
        return ("force: forcing a promotion past the gate over HTTP is off (setting allow_http_force); run "
                "`hope-trainer promote --force` on the robot, or turn allow_http_force on and send the admin "
                f"token in the {ADMIN_HEADER} header")
    try:
        expected = load_or_create_secret(admin_token_path(settings))
    except TokenError as exc:
        return f"force: the admin token cannot be used: {exc}"
    given = request.headers.get(ADMIN_HEADER)
    if given is None:
        return (f"force: needs the admin token in the {ADMIN_HEADER} header (it is in "
                f"$HOPE_HOME/{ADMIN_TOKEN_FILENAME} on the robot)")
    if not tokens_match(given.strip(), expected):
        return f"force: the {ADMIN_HEADER} header does not hold the admin token"
    return None


__all__ = ["ADMIN_HEADER", "ADMIN_TOKEN_FILENAME", "admin_token_path", "force_refusal"]
