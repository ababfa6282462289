"""Logs that cannot fill the SD card: repeated lines folded into a count, log files rotated at a size.

    handler.addFilter(rate_limit())                        # every handler a process installs
    rotating_file_handler(path, settings)                  # $HOPE_HOME/logs/daemon.log
    rotate_if_over(path, settings)                         # before a child's output is appended
    PipeToLog(path, settings).start(proc.stdout)           # a child's whole output, rotated

The rate limit: a record's key is its logger, level and message template (the format string
before its arguments, so "session %s closed" from a thousand clients is one key). The first
`burst` records of a key in a `window_s` window pass; later ones in that window are counted and
dropped, and the first record of that key after the window carries the count: "... (and 523 more
like it in the last 60 s)". One filter object serves all the handlers of a process (the terminal
or journal and the file), and decides once per record, so they agree and nothing is counted
twice. A traceback of a real bug passes too, but a bug hit a thousand times a second writes
`burst` of them a minute, not a thousand.

Rotation: Python's RotatingFileHandler for what this process logs; for a file a child process
appends to (promote.log), the file is rotated before it is opened; and a child whose output must be
kept whole (serve's worker, with its job child and anything they print) writes into a pipe that a
thread reads line by line into a rotating handler. Foundation module: any layer may import it.
"""
from __future__ import annotations

import logging
import logging.handlers
import os
import threading
import time
from pathlib import Path
from typing import IO, Any

WINDOW_S = 60.0
BURST = 10
MAX_KEYS = 1024  # distinct templates remembered; the oldest windows are forgotten first
FILE_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
DEFAULT_MAX_MB = 10
DEFAULT_BACKUPS = 3
_DECIDED = "_hope_rate_limit"  # the record attribute holding the verdict for the other handlers


class RateLimitFilter(logging.Filter):
    """Passes the first `burst` records of a (logger, level, template) per `window_s`, counts the rest."""

    def __init__(self, window_s: float = WINDOW_S, burst: int = BURST, max_keys: int = MAX_KEYS,
                 clock=time.monotonic):
        super().__init__()
        self.window_s, self.burst, self.max_keys = float(window_s), int(burst), int(max_keys)
        self.clock = clock
        self._lock = threading.Lock()
        self._windows: dict[tuple, list] = {}  # key -> [window start, passed, dropped]

    def filter(self, record: logging.LogRecord) -> bool:
        verdict = record.__dict__.get(_DECIDED)
        if verdict is None:
            verdict = self._decide(record)
        return verdict

    def _decide(self, record: logging.LogRecord) -> bool:
        key = (record.name, record.levelno, str(record.msg))
        now = self.clock()
        with self._lock:
            window = self._windows.get(key)
            if window is None or now - window[0] >= self.window_s:
                dropped = window[2] if window is not None else 0
                if window is None and len(self._windows) >= self.max_keys:
                    self._forget(now)
                self._windows[key] = window = [now, 0, 0]
                if dropped:
                    # the same object goes to every handler: the count is appended once, here
                    record.msg = f"{record.msg} (and {dropped} more like it in the last {self.window_s:g} s)"
            if window[1] < self.burst:
                window[1] += 1
                verdict = True
            else:
                window[2] += 1
                verdict = False
        record.__dict__[_DECIDED] = verdict
        return verdict

    def _forget(self, now: float) -> None:
        expired = [k for k, w in self._windows.items() if now - w[0] >= self.window_s and not w[2]]
        for key in expired or sorted(self._windows, key=lambda k: self._windows[k][0])[: self.max_keys // 4]:
            del self._windows[key]


_PROCESS_FILTER: RateLimitFilter | None = None
_PROCESS_LOCK = threading.Lock()


def rate_limit() -> RateLimitFilter:
    """The process's one rate-limit filter, for every handler it installs."""
    global _PROCESS_FILTER
    with _PROCESS_LOCK:
        if _PROCESS_FILTER is None:
            _PROCESS_FILTER = RateLimitFilter()
        return _PROCESS_FILTER


def limits_of(settings: Any) -> tuple[int, int]:
    """(max bytes per file, backups) from the settings' log_max_mb and log_backups."""
    max_mb = int(getattr(settings, "log_max_mb", DEFAULT_MAX_MB))
    backups = int(getattr(settings, "log_backups", DEFAULT_BACKUPS))
    return max(1, max_mb) * 1024 * 1024, max(0, backups)


def _rotating(path: Path, max_bytes: int, backups: int) -> logging.handlers.RotatingFileHandler:
    path.parent.mkdir(parents=True, exist_ok=True)
    # backupCount 0 would never roll over: one backup at least, the cap counts it
    return logging.handlers.RotatingFileHandler(path, maxBytes=max_bytes, backupCount=max(1, backups),
                                                encoding="utf-8", delay=True)


def rotating_file_handler(path: Path, settings: Any, fmt: str = FILE_FORMAT) -> logging.Handler:
    """A handler appending to `path`, rotated at log_max_mb with log_backups kept, rate-limited."""
    max_bytes, backups = limits_of(settings)
    handler = _rotating(Path(path), max_bytes, backups)
    handler.setFormatter(logging.Formatter(fmt))
    handler.addFilter(rate_limit())
    return handler


def rotate_if_over(path: Path, settings: Any) -> None:
    """Rotate `path` (path.1, path.2, ...) when it is at or over log_max_mb: for a file a child
    process appends to, called before each child starts. Never raises."""
    max_bytes, backups = limits_of(settings)
    try:
        if Path(path).stat().st_size >= max_bytes:
            _rotate(Path(path), backups)
    except OSError:
        pass  # no file yet, or a race with another rotation: the next start tries again


def _rotate(path: Path, backups: int) -> None:
    """path -> path.1 -> ... -> path.<backups> (the oldest dropped), as RotatingFileHandler does."""
    backups = max(1, backups)
    for i in range(backups - 1, 0, -1):
        older = path.with_name(f"{path.name}.{i}")
        if older.exists():
            os.replace(older, path.with_name(f"{path.name}.{i + 1}"))
    os.replace(path, path.with_name(f"{path.name}.1"))


class PipeToLog:
    """A child's output (a pipe) copied into `path`, rotated like the other logs. Copied in chunks,
    not lines: a worker printing 200,000 lines costs serve ~0.1 s of CPU this way, 2.5 s through a
    logging handler. The thread ends when every writer has closed the pipe."""

    CHUNK = 64 * 1024

    def __init__(self, path: Path, settings: Any):
        self.max_bytes, self.backups = limits_of(settings)
        self.path = Path(path)
        self._thread: threading.Thread | None = None

    def start(self, pipe: IO[bytes]) -> "PipeToLog":
        self._thread = threading.Thread(target=self._copy, args=(pipe,), name=f"log-{self.path.name}",
                                        daemon=True)
        self._thread.start()
        return self

    def _copy(self, pipe: IO[bytes]) -> None:
        out, size = None, 0
        try:
            while data := os.read(pipe.fileno(), self.CHUNK):
                try:
                    if out is None or (size and size + len(data) > self.max_bytes):
                        out, size = self._reopen(out)
                    out.write(data)
                    size += len(data)
                except OSError:  # a full disk: this chunk is lost, but the child never blocks on its pipe
                    if out is not None:
                        out.close()
                    out = None
        except (OSError, ValueError):
            pass  # the pipe was closed under us: the child is gone
        finally:
            pipe.close()
            if out is not None:
                out.close()

    def _reopen(self, out):
        if out is not None:
            out.close()
            _rotate(self.path, self.backups)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        out = open(self.path, "ab", buffering=0)  # noqa: SIM115 - closed by _copy, reopened at each rotation
        return out, out.tell()

    def join(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)


__all__ = ["BURST", "PipeToLog", "RateLimitFilter", "WINDOW_S", "limits_of", "rate_limit", "rotate_if_over",
           "rotating_file_handler"]
