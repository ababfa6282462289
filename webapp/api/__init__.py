"""The JSON API blueprints: health, runs (+ metrics), training, brain, system, sim, and the Continuon
app's calls (handoff, episodes, learning, app_models, app_metrics)."""
from __future__ import annotations

from importlib import import_module

from flask import Flask

BLUEPRINTS = ("health", "runs", "training", "brain", "system", "sim", "handoff", "episodes", "learning",
              "app_models", "app_metrics")


def register(app: Flask) -> None:
    for name in BLUEPRINTS:
        app.register_blueprint(import_module(f"webapp.api.{name}").bp)
