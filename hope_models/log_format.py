"""How every process writes its log lines to stderr: plain lines on a terminal or into a file,
journald-native lines when stderr is the journal.

    configure_logging(logging.INFO)      # the daemon, the webapp, the Celery worker (and its job child)
    console_formatter()                  # serve's terminal handler
    journal_prefix(logging.ERROR)        # "<3>" for a print() that is an error, "" off the journal

Under a systemd unit, stderr is a stream socket to journald, and systemd sets JOURNAL_STREAM to
"<st_dev>:<st_ino>" of that stream (systemd.exec(5), "$JOURNAL_STREAM"). A child whose stderr was
redirected (serve's worker.log, a captured child) inherits the variable, so it counts only when it
matches stderr's own device and inode, as the documentation asks. Then a line starts with "<N>",
the syslog priority journald files it under (sd-daemon.h: SD_ERR "<3>", SD_WARNING "<4>",
SD_INFO "<6>", SD_DEBUG "<7>"), so `journalctl -p err` finds the errors, and it has no timestamp of
its own: journald stamps every entry. journald reads each line as one entry, so every line of a
multi-line record (a traceback) carries the prefix. Anywhere else the format stays as it was:
"12:00:00 ERROR daemon: message". Foundation module: any layer may import it.
"""
from __future__ import annotations

import logging
import os
import sys
from collections.abc import Mapping
from typing import IO

from hope_models.log_limits import rate_limit

PLAIN_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
JOURNAL_FORMAT = "%(name)s: %(message)s"


def stderr_is_journal(stream: IO | None = None, environ: Mapping[str, str] | None = None) -> bool:
    """True when `stream` (default sys.stderr) is the journal stream systemd connected."""
    value = (os.environ if environ is None else environ).get("JOURNAL_STREAM", "")
    dev, sep, ino = value.partition(":")
    if not sep or not dev.isdigit() or not ino.isdigit():
        return False
    stream = sys.stderr if stream is None else stream
    try:
        st = os.fstat(stream.fileno())
    except (AttributeError, OSError, ValueError):  # no fd (a test's capture), or closed
        return False
    return (st.st_dev, st.st_ino) == (int(dev), int(ino))


def syslog_priority(levelno: int) -> int:
    """The syslog priority of a logging level (CRITICAL 2, ERROR 3, WARNING 4, INFO 6, DEBUG 7)."""
    if levelno >= logging.CRITICAL:
        return 2
    if levelno >= logging.ERROR:
        return 3
    if levelno >= logging.WARNING:
        return 4
    return 6 if levelno >= logging.INFO else 7


class JournalFormatter(logging.Formatter):
    """`<N>name: message`, each line of the record prefixed (journald splits entries at newlines)."""

    def __init__(self) -> None:
        super().__init__(JOURNAL_FORMAT)

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{syslog_priority(record.levelno)}>"
        return "\n".join(prefix + line for line in super().format(record).split("\n"))


def console_formatter(datefmt: str | None = None, stream: IO | None = None) -> logging.Formatter:
    """The formatter for a handler writing to `stream` (default sys.stderr)."""
    return JournalFormatter() if stderr_is_journal(stream) else logging.Formatter(PLAIN_FORMAT, datefmt)


def journal_prefix(levelno: int = logging.ERROR, stream: IO | None = None) -> str:
    """For a line printed rather than logged (a configuration error before logging is set up):
    its priority prefix on the journal, nothing elsewhere."""
    return f"<{syslog_priority(levelno)}>" if stderr_is_journal(stream) else ""


def configure_logging(level: int | str = logging.INFO, stream: IO | None = None) -> logging.Handler | None:
    """Like logging.basicConfig(level=..., stream=stderr): a handler on the root logger with the
    console format, unless the root logger has handlers already (then nothing changes, as with
    basicConfig, so a test's capture or an embedding program keeps its own), rate-limited like every
    handler (hope_models/log_limits.py). Returns the handler."""
    root = logging.getLogger()
    if root.handlers:
        return None
    stream = sys.stderr if stream is None else stream
    handler = logging.StreamHandler(stream)
    handler.setFormatter(console_formatter(stream=stream))
    handler.addFilter(rate_limit())  # a flood of one line is folded into a count (log_limits.py)
    root.addHandler(handler)
    root.setLevel(level)
    return handler
