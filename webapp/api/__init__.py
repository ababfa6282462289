"""The JSON API blueprints (health, runs); issue 6 adds brain, system, sim and training."""
from __future__ import annotations

from flask import Flask


def register(app: Flask) -> None:
    from webapp.api.health import bp as health_bp
    from webapp.api.runs import bp as runs_bp

    app.register_blueprint(health_bp)
    app.register_blueprint(runs_bp)
