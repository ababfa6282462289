"""The app's model calls: /api/v1/models and /api/v1/models/activate."""
from __future__ import annotations

from flask import Blueprint

bp = Blueprint("app_models", __name__)
