"""POST /api/training/episode_handoff: the Continuon app hands an episode and its media to the trainer."""
from __future__ import annotations

from flask import Blueprint

bp = Blueprint("handoff", __name__)
