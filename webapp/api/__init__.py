"""The JSON API blueprints: health, runs (+ metrics, series, provenance, artifacts), training, brain,
system, workers, sim, and the Continuon app's calls (handoff, episodes, learning, app_models, app_metrics,
ownership, training_queue)."""
from __future__ import annotations

from importlib import import_module

from flask import Flask

BLUEPRINTS = ("health", "runs", "run_series", "run_artifacts", "training", "brain", "system", "workers", "sim",
              "handoff", "episodes", "learning", "app_models", "app_metrics", "ownership", "training_queue")


def register(app: Flask) -> None:
    for name in BLUEPRINTS:
        app.register_blueprint(import_module(f"webapp.api.{name}").bp)
