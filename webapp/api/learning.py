"""The app's learning calls: /api/learning/status|pause|resume and /api/training/status."""
from __future__ import annotations

from flask import Blueprint

bp = Blueprint("learning", __name__)
