"""Episodes: upload of packages, the inbox, tags (the Robot Editor's Episodes page and the app's /api/v1/data calls)."""
from __future__ import annotations

from flask import Blueprint

bp = Blueprint("episodes", __name__)
