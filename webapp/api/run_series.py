"""Placeholder: being written."""
from __future__ import annotations

from flask import Blueprint

bp = Blueprint("run_series", __name__, url_prefix="/api")
