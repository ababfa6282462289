"""What a Socket.IO client may send, and how its mistakes are logged: one WARNING line, never a
traceback, and a session that sent something this server never takes is closed at once.

    install(socketio, guard)      # in create_app, after SocketGuard

Our clients (the Robot Editor, the Continuon app) send one CONNECT with the token and then only
Engine.IO pongs; every event flows from the server. So:

- Binary data is refused before python-socketio collects it. A BINARY_EVENT / BINARY_ACK packet
  (Socket.IO types 5 and 6) declares how many attachments follow (up to 10 digits), and
  python-socketio appends every later message of the session to that packet until the count is
  reached, holding them all in memory. Such a packet, or any Engine.IO binary message, closes the
  session (and cuts its WebSocket's TCP connection, so nothing more is read from it).
- Engine.IO buffers at most `MAX_MESSAGE_BYTES` per polling POST and per WebSocket message
  (python-engineio's default is 1 MB, and its WebSocket transport buffers a message of any size
  before it compares it with that).
- A malformed packet is the client's error, not ours. python-engineio 4.15 logs, with a full
  traceback at ERROR, every polling body it cannot decode ("post request handler error") and every
  Socket.IO packet python-socketio cannot decode ("message handler error"); a WebSocket message it
  cannot decode escapes to Werkzeug, which logs "Error on request" with a traceback; and its
  "log once" errors (an unknown session id, a bad transport) are ERROR too. Each becomes one
  WARNING line naming the client's address, the session and what was wrong. An exception in our
  own handlers still logs its traceback.

Logged client lines use fixed templates, so the rate limit on every handler
(`hope_models/log_limits.py`) folds a flood of them into one line with a count.
"""
from __future__ import annotations

import logging
import threading
from typing import Any
from urllib.parse import parse_qs

import simple_websocket
from socketio import packet as sio_packet

from webapp.socket_guard import SocketGuard, cut_websocket
from webapp.strikes import strike

log = logging.getLogger(__name__)

# What the app's clients send is a CONNECT packet with the token (well under 1 KiB) and pongs; a
# polling POST may carry several, and a future event with a small JSON body still fits.
MAX_MESSAGE_BYTES = 64 * 1024
# What python-engineio's decoding raises on bad input (binascii.Error, UnicodeDecodeError and
# JSONDecodeError are ValueErrors; KeyError is a JSONP body without its `d` field; RecursionError
# is JSON nested a thousand deep).
DECODE_ERRORS = (ValueError, KeyError, IndexError, TypeError, RecursionError)
ENGINEIO_LOGGERS = ("engineio.server", "socketio.server")
_ACCEPTED_TYPES = (sio_packet.CONNECT, sio_packet.DISCONNECT, sio_packet.EVENT, sio_packet.ACK)


class ClientPacketError(ValueError):
    """A Socket.IO packet this server refuses; the message says what was wrong with it."""


def _shape_problem(pkt: sio_packet.Packet) -> str | None:
    if pkt.packet_type not in _ACCEPTED_TYPES:
        return f"a Socket.IO packet of type {pkt.packet_type!r}, which clients do not send"
    if pkt.packet_type == sio_packet.CONNECT and not (pkt.data is None or isinstance(pkt.data, dict)):
        return "a CONNECT packet whose auth is not an object"
    if pkt.packet_type == sio_packet.EVENT and not (
            isinstance(pkt.data, list) and pkt.data and isinstance(pkt.data[0], str)):
        return "an EVENT packet that is not a list starting with the event's name"
    if pkt.packet_type == sio_packet.ACK and (pkt.id is None or not isinstance(pkt.data, list)):
        return "an ACK packet without an id or a list of arguments"
    return None


class CheckedPacket(sio_packet.Packet):
    """python-socketio's packet, refusing what this server never takes while decoding it, before
    `_handle_eio_message` acts on it (it stores a binary packet to collect its attachments)."""

    def decode(self, encoded_packet):
        if not isinstance(encoded_packet, str):
            raise ClientPacketError("a binary message (this server takes no binary data)")
        kind = encoded_packet[:1]
        if kind in (str(sio_packet.BINARY_EVENT), str(sio_packet.BINARY_ACK)):
            name = "event" if kind == str(sio_packet.BINARY_EVENT) else "ack"
            raise ClientPacketError(f"a binary Socket.IO {name} (this server takes no binary data)")
        try:
            attachments = super().decode(encoded_packet)
        except DECODE_ERRORS as exc:
            raise ClientPacketError(f"a malformed Socket.IO packet ({_short(exc)})") from None
        problem = _shape_problem(self)
        if problem is not None:
            raise ClientPacketError(problem)
        return attachments


def _short(exc: BaseException, limit: int = 120) -> str:
    kind = type(exc)
    name = kind.__name__ if kind.__module__ == "builtins" else f"{kind.__module__}.{kind.__qualname__}"
    text = f"{name}: {exc}"
    return text if len(text) <= limit else text[:limit] + "..."


def client_of(environ: dict | None) -> str:
    """The client's address as the server saw it (never a forwarded header)."""
    if not environ:
        return "an unknown client"
    return f"{environ.get('REMOTE_ADDR', '?')}:{environ.get('REMOTE_PORT', '?')}"


class _Current(threading.local):
    """The Engine.IO request this thread is handling, for the log filter's lines."""

    environ: dict | None = None
    sid: str | None = None


class ClientErrorFilter(logging.Filter):
    """On python-engineio's logger: its client-caused errors become one WARNING line each."""

    def __init__(self, current: _Current):
        super().__init__()
        self.current = current

    def filter(self, record: logging.LogRecord) -> bool:
        if record.funcName == "_log_error_once" and record.levelno > logging.WARNING:
            # an unknown session id (a client after our restart), a bad transport or upgrade
            _as_warning(record, "Engine.IO request from %s refused: %s",
                        (client_of(self.current.environ), record.getMessage().split(" (further")[0]))
        elif record.msg == "post request handler error" and record.exc_info:
            exc = record.exc_info[1]
            if isinstance(exc, DECODE_ERRORS):
                _as_warning(record, "bad Engine.IO POST from %s (session %s): %s",
                            (client_of(self.current.environ), self.current.sid, _short(exc)))
        return True


_CURRENT = _Current()
_FILTER = ClientErrorFilter(_CURRENT)


def _as_warning(record: logging.LogRecord, msg: str, args: tuple) -> None:
    record.levelno, record.levelname = logging.WARNING, "WARNING"
    record.msg, record.args = msg, args
    record.exc_info = record.exc_text = record.stack_info = None


def quiet_loggers() -> dict[str, logging.Logger]:
    """The loggers handed to python-socketio and python-engineio. Given a logger (rather than
    False) they add no StreamHandler of their own, which printed each error a second time; their
    per-packet INFO lines stay off unless a level was set."""
    loggers = {}
    for name in ENGINEIO_LOGGERS:
        logger = logging.getLogger(name)
        if logger.level == logging.NOTSET:
            logger.setLevel(logging.WARNING)
        loggers[name] = logger
    return loggers


def install(socketio: Any, guard: SocketGuard) -> None:
    """Refuse binary data and malformed packets on this Flask-SocketIO server, log each as one line."""
    from engineio.async_drivers._websocket_wsgi import SimpleWebSocketWSGI  # lazy: loads engineio

    sio = socketio.server
    eio = sio.eio
    if not hasattr(sio, "packet_class") or "message" not in eio.handlers:
        raise RuntimeError("python-socketio changed: webapp/socket_packets.py must be revisited")
    sio.packet_class = CheckedPacket
    eio.max_http_buffer_size = MAX_MESSAGE_BYTES
    if eio._async.get("websocket") is SimpleWebSocketWSGI:  # a copy: the dict is the module's
        eio._async = {**eio._async, "websocket": _bounded_websocket_class(SimpleWebSocketWSGI)}
    if _FILTER not in eio.logger.filters:  # once: the logger is the process's, apps come and go
        eio.logger.addFilter(_FILTER)
    _wrap_message_handler(sio, eio, guard)
    _wrap_handle_request(sio, eio, _CURRENT, guard)


WAIT_STEP_S = 1.0


def _bounded_websocket_class(base: type) -> type:
    class BoundedWebSocket(base):
        def __init__(self, handler, server, **kwargs):
            # simple-websocket stops reading a message past this size (and closes) instead of
            # buffering it whole for Engine.IO to measure afterwards
            super().__init__(handler, server, max_message_size=MAX_MESSAGE_BYTES, **kwargs)

        def close(self):
            try:
                super().close()
            except OSError:  # cut_websocket shut the socket under Engine.IO's writer thread
                pass

        def wait(self):
            # simple-websocket (1.1) ends its reader on a message past max_message_size by waking
            # receive() before it marks the socket closed: a receive() that wakes in between waits
            # on its event for ever, holding the connection and its thread. Look again every second.
            while True:
                try:
                    data = self.ws.receive(timeout=WAIT_STEP_S)
                except simple_websocket.ConnectionClosed:
                    return None
                if data is not None or not self.ws.connected:
                    return data

    return BoundedWebSocket


def _wrap_message_handler(sio: Any, eio: Any, guard: Any) -> None:
    inner = eio.handlers["message"]

    def on_message(eio_sid, data):
        # Engine.IO runs each message on a thread of its own, so a session's later messages may
        # still arrive after one of them closed it: those are dropped without a word.
        if eio_sid not in eio.sockets or eio_sid not in sio.environ:
            return None
        try:
            if not isinstance(data, str):
                raise ClientPacketError("a binary message (this server takes no binary data)")
            if not data:  # python-socketio would not decode it and act on an empty EVENT
                raise ClientPacketError("an empty Socket.IO packet")
            return inner(eio_sid, data)
        except ClientPacketError as exc:
            if eio_sid not in eio.sockets:
                return None
            log.warning("Socket.IO session %s from %s closed: it sent %s", eio_sid,
                        client_of(sio.environ.get(eio_sid)), exc)
            strike(sio.environ.get(eio_sid), str(exc))
            guard.close_session(eio_sid, sio.environ.get(eio_sid))
            return None
        except KeyError:
            if eio_sid in sio.environ:
                raise  # the session is there: a bug of ours, with its traceback
            return None  # it was closed while python-socketio handled this message

    eio.on("message", on_message)


def _wrap_handle_request(sio: Any, eio: Any, current: _Current, guard: Any) -> None:
    inner = eio.handle_request

    def handle_request(environ, start_response):
        sid = parse_qs(environ.get("QUERY_STRING", "")).get("sid", [None])[0]
        current.environ, current.sid = environ, sid

        def answer(status, headers, exc_info=None):
            if status.startswith("400"):  # a packet, session or transport Engine.IO could not take
                strike(environ, f"an Engine.IO {environ.get('REQUEST_METHOD')} refused {status[:3]}")
            return start_response(status, headers, exc_info)

        try:
            return inner(environ, answer)
        except DECODE_ERRORS as exc:
            if environ.get("HTTP_UPGRADE", "").lower() != "websocket":
                raise  # not a client's packet: ours to fix, with its traceback
            # a WebSocket message Engine.IO could not decode ends its read loop with this error
            sid = sid or next((s for s, env in list(sio.environ.items()) if env is environ), None)
            log.warning("Engine.IO WebSocket from %s (session %s) closed: it sent a malformed packet (%s)",
                        client_of(environ), sid or "already closed", _short(exc))
            strike(environ, "a malformed Engine.IO WebSocket packet")
            if sid is not None:
                guard.close_session(sid, sio.environ.get(sid))
            cut_websocket(environ)
            raise ConnectionError("closed after a malformed packet") from None  # Werkzeug: dropped, no log
        finally:
            current.environ = current.sid = None

    eio.handle_request = handle_request


__all__ = ["CheckedPacket", "ClientPacketError", "MAX_MESSAGE_BYTES", "client_of", "install", "quiet_loggers"]
