"""Placeholder: being written."""
from __future__ import annotations

from flask import Blueprint

bp = Blueprint("workers", __name__, url_prefix="/api")
