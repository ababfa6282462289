"""GET /api/health: open (no token), for systemd's watchdog, load balancers and the CLI.

200 {"status": "ok", ...} when the registry answers a query; 503 {"status": "error", "error"}
when it does not.
"""
from __future__ import annotations

import time

from flask import Blueprint, current_app, jsonify
from sqlalchemy import text

from webapp.auth import public

bp = Blueprint("health", __name__, url_prefix="/api")


@bp.get("/health")
@public
def health():
    state = current_app.extensions["hope"]
    try:
        with state.registry.session(readonly=True) as s:
            s.execute(text("SELECT 1 FROM runs LIMIT 1"))
    except Exception as exc:  # noqa: BLE001 - any registry failure is "unhealthy", with its reason
        response = jsonify({"status": "error", "error": f"registry {state.registry.path}: {exc}"})
        response.status_code = 503
        return response
    return jsonify({"status": "ok", "uptime_s": round(time.monotonic() - state.started, 1),
                    "embedded_daemon": state.daemon is not None})
