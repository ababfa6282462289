"""GET /api/health and GET /api/ping: open (no token).

/api/health, for systemd's watchdog, load balancers and the CLI: 200 {"status": "ok", ...} when
the registry answers a query; 503 {"status": "error", "error"} when it does not.

/api/ping, for the Continuon app's reachability check (its runDiagnostics sends no token):
200 {"status": "ok", "name": "HOPE Seed Trainer", "device_id": "hope-<16 hex>", "api": "hope-trainer"}.
It tells a caller that a trainer answers and which one it is, nothing more: device_id is a hash of
the machine id (or the host name) and the resolved $HOPE_HOME, salted for this purpose, so it is
stable across restarts, differs between two trainers on one host, and reveals neither input (the
app keeps it per host: robot_list_screen.dart reads device_id as a String).
"""
from __future__ import annotations

import hashlib
import socket
import time
from functools import lru_cache
from pathlib import Path

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


MACHINE_ID = Path("/etc/machine-id")
NAME = "HOPE Seed Trainer"


@lru_cache(maxsize=4)
def device_id(home: str) -> str:
    try:
        machine = MACHINE_ID.read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError):
        machine = ""
    seed = f"hope-trainer device id\0{machine or socket.gethostname()}\0{Path(home).resolve()}"
    return "hope-" + hashlib.sha256(seed.encode("utf-8", "surrogatepass")).hexdigest()[:16]


@bp.get("/ping")
@public
def ping():
    home = str(current_app.extensions["hope"].settings.home)
    return jsonify({"status": "ok", "name": NAME, "device_id": device_id(home), "api": "hope-trainer"})
