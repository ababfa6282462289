"""Opening the registry for one CLI command, with the errors a user can act on.

Every daemon-side command (enqueue, status, watch, cancel, ...) reads the same settings and opens
the same `$HOPE_HOME/hope.db`, migrating it when needed (cheap when it is at head), so the command
works whether the daemon is up or not. Problems become `CommandError` (exit 2, one line on stderr;
a full queue exits 75).
"""
from __future__ import annotations

import json
import sys
from contextlib import contextmanager
from typing import Any, Iterator

from hope_models.settings import SettingsError, load_settings
from registry.run_request import RunRequestError

USAGE_EXIT = 2


class CommandError(Exception):
    """A usage or state problem to report in one line (exit code 2)."""


@contextmanager
def open_registry(*, migrate: bool = True) -> Iterator[tuple[Any, Any]]:
    """(settings, Registry) for the duration of a command."""
    from registry.db import Registry, RegistryError  # lazy: loads sqlalchemy

    try:
        settings = load_settings()
        registry = Registry.open(settings, migrate=migrate)
    except (SettingsError, RegistryError, OSError) as exc:
        raise CommandError(str(exc)) from None
    try:
        yield settings, registry
    finally:
        registry.close()


def run_command(body) -> int:
    """Call `body()` and turn the errors users cause into a message and exit code 2 (75 for a full
    queue: nothing wrong with the request, try again later)."""
    from registry.runs import RunError  # lazy: loads sqlalchemy

    try:
        return int(body() or 0)
    except (CommandError, RunError, RunRequestError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return getattr(exc, "exit_code", USAGE_EXIT)  # a full queue: 75, try again later


def print_json(obj: Any) -> None:
    print(json.dumps(obj, sort_keys=False), flush=True)
