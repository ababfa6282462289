"""Lines for the person at the console (serve's and webapp's banner, the demo's progress), each
written whole.

Under PYTHONUNBUFFERED (systemd's journal, the tests, `python -u`) print() writes its text and its
newline in two writes, and a log line that another thread or a child writes to the same file
between them lands on the banner's line: a reader of "token: <token>" then takes the log's
timestamp for part of the token (seen in CI). One write per line cannot be split that way."""
from __future__ import annotations

import sys


def say(text: str = "") -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


__all__ = ["say"]
