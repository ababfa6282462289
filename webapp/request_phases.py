"""A request's phases after its headers, as webapp/server.py's connection table sees them.

    environ["wsgi.input"] = BodyReader(raw, conn, environ, limits)   # the body: its deadline moves
    app = bounded_drain(app, drain_s)                                # after the answer: the drain

The server gives a connection a deadline per phase (webapp/server.py's module doc). The body's
moves on as bytes arrive (a large upload arriving at a walking pace earns its time, a trickle is
cut), and ends when the declared body is read; after the answer, only Werkzeug's drain of unread
request bytes is left, which would read until EOF, so it gets `drain_s` and no more.
"""
from __future__ import annotations

import time
from typing import Any

CONN_KEY = "hope.connection"  # the WSGI environ key of the request's connection (server.py's _Connection)


def has_body(environ) -> bool:
    if environ.get("HTTP_TRANSFER_ENCODING", "").lower() == "chunked":
        return True
    try:
        return int(environ.get("CONTENT_LENGTH") or 0) > 0
    except ValueError:
        return False


_PIECE = 64 << 10


class BodyReader:
    """wsgi.input that moves the connection's body deadline on as bytes arrive (at min_body_rate)
    and ends it once the declared body is read."""

    def __init__(self, raw, conn: Any, environ, limits: Any):
        self._raw = raw
        self._conn = conn
        self._start = time.monotonic()
        self._timeout_s = limits.body_timeout_s
        self._rate = max(1, limits.min_body_rate)
        self._received = 0
        try:
            self._left = int(environ.get("CONTENT_LENGTH") or -1)
        except ValueError:
            self._left = -1

    def _consumed(self, data: bytes) -> bytes:
        self._received += len(data)
        if self._left >= 0:
            self._left -= len(data)
        if self._conn.phase == "body":
            if not data or self._left == 0:
                self._conn.enter("app", None)
            else:
                self._conn.deadline = self._start + self._timeout_s + self._received / self._rate
        return data

    def read(self, size: int | None = -1):
        # In pieces, so the deadline moves on while a large read is still filling: one blocking
        # read of megabytes would otherwise be cut at body_timeout_s however fast it arrives.
        if size is not None and 0 <= size <= _PIECE:
            return self._consumed(self._raw.read(size))
        parts = []
        want = None if size is None or size < 0 else size
        while want is None or want > 0:
            piece = self._consumed(self._raw.read(_PIECE if want is None else min(_PIECE, want)))
            if not piece:
                break
            parts.append(piece)
            if want is not None:
                want -= len(piece)
        return b"".join(parts)

    def readinto(self, buffer) -> int:
        # werkzeug's LimitedStream reads through readinto when the stream has one: a short read
        # (at most a piece) is allowed, and keeps the deadline moving
        data = self.read(min(len(buffer), _PIECE))
        buffer[:len(data)] = data
        return len(data)

    def readline(self, *args):
        return self._consumed(self._raw.readline(*args))

    def readlines(self, *args):
        return [self._consumed(line) for line in self._raw.readlines(*args)]

    def __iter__(self):
        return iter(self.readline, b"")

    def __getattr__(self, name):
        return getattr(self._raw, name)


class _AnswerSent:
    """The app's response iterable; once it is exhausted, the connection only has Werkzeug's drain
    of unread request bytes left, which reads until EOF: give that `drain_s` and no more."""

    def __init__(self, iterable, conn: Any, drain_s: float):
        self._iterable, self._conn, self._drain_s = iterable, conn, drain_s

    def __iter__(self):
        yield from self._iterable
        if self._conn is not None and self._conn.phase != "websocket":
            self._conn.enter("drain", time.monotonic() + self._drain_s)

    def close(self):
        close = getattr(self._iterable, "close", None)
        if close is not None:
            close()


def bounded_drain(app, drain_s: float):
    def guarded(environ, start_response):
        return _AnswerSent(app(environ, start_response), environ.get(CONN_KEY), drain_s)

    return guarded


__all__ = ["BodyReader", "CONN_KEY", "bounded_drain", "has_body"]
