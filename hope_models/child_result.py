"""Reading a `hope-trainer ... --json` child's result: its last stdout line that is a JSON object.

Every command that reports prints its result as one JSON object on the last line; anything before
it (progress, frames, warnings of the libraries) is skipped. Used by whatever runs the CLI as a
child process (the sequential trainer, the daemon's auto-promoter, the webapp, the demo), so it
sits at the bottom of the package beside child_command.py, which builds those children's argv."""
from __future__ import annotations

import json
from typing import Any


def last_json_object(text: str) -> dict[str, Any] | None:
    """The last line of `text` that parses as a JSON object, or None."""
    for line in reversed(text.splitlines()):
        line = line.strip()
        if line.startswith("{"):
            try:
                obj = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(obj, dict):
                return obj
    return None
