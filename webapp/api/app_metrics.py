"""The app's metrics calls: /api/training/metrics, /api/training/benchmarks, /api/learning/progress."""
from __future__ import annotations

from flask import Blueprint

bp = Blueprint("app_metrics", __name__)
