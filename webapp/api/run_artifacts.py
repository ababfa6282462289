"""Placeholder: being written."""
from __future__ import annotations

from flask import Blueprint

bp = Blueprint("run_artifacts", __name__, url_prefix="/api")
