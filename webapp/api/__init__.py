"""The JSON API blueprints: health, runs (+ metrics), training, brain, system, sim."""
from __future__ import annotations

from flask import Flask


def register(app: Flask) -> None:
    from webapp.api.brain import bp as brain_bp
    from webapp.api.health import bp as health_bp
    from webapp.api.runs import bp as runs_bp
    from webapp.api.sim import bp as sim_bp
    from webapp.api.system import bp as system_bp
    from webapp.api.training import bp as training_bp

    for bp in (health_bp, runs_bp, training_bp, brain_bp, system_bp, sim_bp):
        app.register_blueprint(bp)
