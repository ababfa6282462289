"""HOPE Seed Trainer as a tool: the `hope-trainer` command (`python -m hope_trainer`) and the
commands that compose every layer below it (serve, demo, infer, the webapp launcher).

This is the top layer: it may import hope_models, registry, daemon, workers and webapp; no layer
below imports it (children are started by module name, see hope_models/child_command.py).
"""
from __future__ import annotations

from importlib import metadata

DISTRIBUTION = "hope-seed-trainer"  # pyproject.toml [project] name


def _version() -> str:
    try:
        return metadata.version(DISTRIBUTION)
    except metadata.PackageNotFoundError:
        # a plain checkout that was never pip-installed (PYTHONPATH or cwd only)
        return "0+unknown"


__version__ = _version()
