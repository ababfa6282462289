"""Socket.IO sessions that cannot pin a server thread: no waiting on a client, a deadline to log in.

Two holes in python-engineio (4.15) as Flask-SocketIO runs it in threading mode, closed here:

1. `engineio.Server.disconnect()` closes a session with `Socket.close(wait=True)`, which queues a
   CLOSE packet and then `queue.join()`s until the client fetches it. A long-polling client fetches
   packets only with its next GET, so when the disconnect happens inside that client's own POST
   (any bad packet: `6`, `0`, `2probe`, an oversized payload all raise and disconnect), the POST's
   thread waits for a GET that never comes: one thread and one socket lost per request, for ever,
   without a token. We close without waiting: the session is dropped at once, and a client that
   polls again gets "invalid session" and reconnects, as after any server restart.
2. An Engine.IO session needs no token: authentication is the Socket.IO CONNECT packet. A client
   that opens a WebSocket (or polling session) and never sends CONNECT, or sends a refused one,
   would hold it open while answering pings. Every session must be authorised within
   `auth_timeout_s` or it is closed; one whose CONNECT arrived in time is not cut while the server
   is still checking it (a loaded server may start that check seconds late), up to CHECK_LIMIT_S.
3. Each new session starts a ping thread that sleeps `ping_interval` (25 s) before it notices its
   session is gone, so handshakes alone (no token) could pile up thousands of threads. New sessions
   are therefore limited: at most `max_pending` waiting to log in at once (a quarter of them from
   any one client address, so a neighbour's handshakes leave room for the editor's), and no more than
   `sessions_per_s` (with a burst) started; beyond that the handshake is refused (401 with a
   message) and a real client retries, as it does after any refused connection.
4. A long-polling GET waits for packets up to ping_interval + ping_timeout (45 s), and any number of
   them may wait on one session, so one handshake and a few hundred GETs held every thread of the
   server. Here a session has at most one long-poll GET at a time, as the Engine.IO protocol says:
   a second one while the first waits is answered 400 at once and closes the session (which wakes
   the first). A long-poll is answered within `poll_deadline_s` (a NOOP packet when nothing came;
   the client simply polls again), and a closed session wakes every GET still waiting on it.

Closing a WebSocket session from the server only sends a close frame: simple-websocket then waits
for the client's answer (a silent client never gives one) until the socket's idle timeout. A session
closed for not logging in therefore also has its TCP connection cut (`middleware` remembers the
sockets of WebSocket requests, including upgrades of polling sessions, by session id).

The authorised flag lives in the session's WSGI environ (the connect handler sees the same dict:
`mark_authorized`), so nothing here needs python-socketio's internals beyond the Engine.IO
`connect`/`disconnect` handlers it registers.
"""
from __future__ import annotations

import logging
import socket
import threading
import time
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qs

from webapp.strikes import strike

log = logging.getLogger(__name__)

AUTHORIZED_KEY = "hope.socket_authorized"
DEFAULT_AUTH_TIMEOUT_S = 10.0
MAX_PENDING = 64
SESSIONS_PER_S = 20.0
SESSIONS_BURST = 60
CHECK_LIMIT_S = 60.0  # a login check that takes longer than this is not waited for
POLL_DEADLINE_S = 15.0  # well under Engine.IO's 45 s; a browser polls again at once


def _bounded_poll_socket_class(base: type, guard: "SocketGuard") -> type:
    from engineio import packet  # lazy: loads engineio

    class BoundedPollSocket(base):
        def poll(self):
            if self.upgraded:  # the WebSocket's writer thread: no HTTP answer waits on it
                return super().poll()
            empty = self.server.get_queue_empty_exception()
            try:
                first = self.queue.get(timeout=guard.poll_deadline_s)
                self.queue.task_done()
            except empty:
                return [packet.Packet(packet.NOOP)]  # the answer's deadline; the session lives on
            packets = []
            pkt = first
            while True:
                if pkt is None:  # closed: leave the marker for every other GET waiting here
                    self.queue.put(None)
                    return packets
                packets.append(pkt)
                try:
                    pkt = self.queue.get(block=False)
                    self.queue.task_done()
                except empty:
                    return packets

        def receive(self, pkt):
            # here, on the thread that read it: Engine.IO hands the message itself to a thread of
            # its own, which a loaded server may start seconds later
            if pkt.packet_type == packet.MESSAGE and isinstance(pkt.data, str) and pkt.data[:1] == "0":
                guard.login_arrived(self.sid)
            return super().receive(pkt)

    return BoundedPollSocket


def _non_waiting_engineio_class(base: type) -> type:
    class NonWaitingEngineIOServer(base):
        def disconnect(self, sid=None):
            targets = [sid] if sid is not None else list(self.sockets)
            for target in targets:
                socket = self.sockets.get(target)
                if socket is not None:
                    socket.close(wait=False, reason=self.reason.SERVER_DISCONNECT)
                self.sockets.pop(target, None)

    return NonWaitingEngineIOServer


def _polling_get_sid(environ: dict) -> str | None:
    """The session id of a long-polling GET (not a WebSocket upgrade), else None."""
    if environ.get("REQUEST_METHOD") != "GET" or environ.get("HTTP_UPGRADE"):
        return None
    query = parse_qs(environ.get("QUERY_STRING", ""))
    if query.get("transport", [None])[0] != "polling":
        return None
    return query.get("sid", [None])[0]


def _second_poll_refused(start_response):
    body = b'{"error": "a second long-poll GET on a session whose GET is still waiting; the session is closed"}'
    start_response("400 Bad Request", [("Content-Type", "application/json"), ("Content-Length", str(len(body)))])
    return [body]


@dataclass
class _Pending:
    """A session waiting to log in."""

    deadline: float
    environ: dict
    client: str  # the address it came from: one address may hold only a share of the places
    checking_since: float | None = None  # its CONNECT arrived and the server is checking it
    checked: bool = False

    def checking(self, now: float) -> bool:
        return self.checking_since is not None and now - self.checking_since < CHECK_LIMIT_S


def cut_websocket(environ: dict | None) -> None:
    """Shut the TCP connection of a WebSocket request: its reader thread wakes with EOF and stops
    reading (and buffering); the handler ends. Anything but a WebSocket request is left alone."""
    if not environ or environ.get("HTTP_UPGRADE", "").lower() != "websocket":
        return
    sock = environ.get("werkzeug.socket")
    if sock is None:  # no socket to shut (what the AttributeError below used to swallow)
        return
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except (OSError, AttributeError):
        pass


def mark_authorized(environ: dict) -> None:
    """Called by the Socket.IO connect handler once the token checked out."""
    environ[AUTHORIZED_KEY] = True


class SocketGuard:
    def __init__(self, socketio: Any, auth_timeout_s: float = DEFAULT_AUTH_TIMEOUT_S, *,
                 max_pending: int = MAX_PENDING, sessions_per_s: float = SESSIONS_PER_S,
                 sessions_burst: int = SESSIONS_BURST, poll_deadline_s: float = POLL_DEADLINE_S):
        import engineio  # lazy: loads engineio

        eio = socketio.server.eio
        if type(eio) is not engineio.Server:  # a new python-socketio may build it differently: look again
            raise RuntimeError(f"unexpected Engine.IO server class {type(eio).__name__}; "
                               "webapp/socket_guard.py must be revisited")
        eio.__class__ = _non_waiting_engineio_class(engineio.Server)
        self.eio = eio
        from engineio.socket import Socket  # lazy: loads engineio

        self.poll_deadline_s = float(poll_deadline_s)
        self._socket_class = _bounded_poll_socket_class(Socket, self)
        self._polling: dict[str, dict] = {}  # session id -> environ of its waiting long-poll GET
        self.second_polls = 0
        self.auth_timeout_s = float(auth_timeout_s)
        self._pending: dict[str, _Pending] = {}
        self._websockets: dict[str, dict] = {}  # session id -> environ of its WebSocket request
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._closed = False
        self.max_pending = int(max_pending)
        self.max_pending_per_client = max(1, self.max_pending // 4)
        self._rate, self._burst = float(sessions_per_s), float(sessions_burst)
        self._tokens, self._refilled = self._burst, time.monotonic()
        self.refused = 0
        inner_connect = eio.handlers.get("connect")
        inner_message = eio.handlers.get("message")
        inner_disconnect = eio.handlers.get("disconnect")

        def on_connect(eio_sid, environ, *args):
            with self._lock:
                client = str(environ.get("REMOTE_ADDR", ""))
                refusal = self._admit(client)
                if refusal is None:
                    self._pending[eio_sid] = _Pending(time.monotonic() + self.auth_timeout_s, environ, client)
                    self._ensure_reaper()
            if refusal is not None:
                return refusal  # engineio drops the session before its ping thread starts
            session = eio.sockets.get(eio_sid)
            if session is not None and type(session) is Socket:
                session.__class__ = self._socket_class  # before its first poll (in this same request)
            return inner_connect(eio_sid, environ, *args) if inner_connect else None

        def on_disconnect(eio_sid, *args):
            with self._lock:
                self._pending.pop(eio_sid, None)
            return inner_disconnect(eio_sid, *args) if inner_disconnect else None

        def on_message(eio_sid, data, *args):
            try:
                return inner_message(eio_sid, data, *args)
            finally:
                if isinstance(data, str) and data[:1] == "0":  # a Socket.IO CONNECT, answered
                    self.login_checked(eio_sid)

        eio.on("connect", on_connect)
        eio.on("disconnect", on_disconnect)
        eio.on("message", on_message)

    def middleware(self, app):
        """WSGI: remember which TCP connection carries each session's WebSocket while it is open."""
        def remember_websockets(environ, start_response):
            polling_sid = _polling_get_sid(environ)
            if polling_sid is not None:
                return self._one_poll_per_session(app, polling_sid, environ, start_response)
            if environ.get("HTTP_UPGRADE", "").lower() != "websocket":
                return app(environ, start_response)
            sid = parse_qs(environ.get("QUERY_STRING", "")).get("sid", [None])[0]
            if sid is None:
                return app(environ, start_response)  # a new session: its connect environ is this one
            with self._lock:
                self._websockets[sid] = environ
            try:
                return app(environ, start_response)  # returns when the WebSocket has ended
            finally:
                with self._lock:
                    if self._websockets.get(sid) is environ:
                        del self._websockets[sid]

        return remember_websockets

    def _one_poll_per_session(self, app, sid: str, environ, start_response):
        with self._lock:
            waiting = self._polling.get(sid)
            if waiting is None:
                self._polling[sid] = environ
        if waiting is not None:
            self.second_polls += 1
            strike(environ, "a second long-poll GET on one Engine.IO session")
            if self.second_polls in (1, 10, 100) or self.second_polls % 1000 == 0:
                log.warning("closed a Socket.IO session that sent a second long-poll GET while one waited "
                            "(%d so far)", self.second_polls)
            try:
                self.eio.disconnect(sid)  # the waiting GET gets the CLOSE packet
            except Exception:  # noqa: BLE001 - the session may have gone meanwhile
                log.debug("closing %s failed", sid, exc_info=True)
            return _second_poll_refused(start_response)
        try:
            return app(environ, start_response)  # threading mode: returns once the poll is answered
        finally:
            with self._lock:
                if self._polling.get(sid) is environ:
                    del self._polling[sid]

    def waiting_polls(self) -> int:
        """Long-poll GETs waiting in the app now (one per session at most)."""
        with self._lock:
            return len(self._polling)

    def close_session(self, sid: str, environ: dict | None) -> None:
        """Drop an Engine.IO session now and cut the TCP connections of its WebSocket (`environ`, the
        session's own request, and an upgraded polling session's WebSocket request): closing a
        WebSocket from the server only sends a close frame, which a silent client never answers."""
        with self._lock:
            upgraded = self._websockets.get(sid)
        try:
            self.eio.disconnect(sid)
        except Exception:  # noqa: BLE001 - the session may have gone meanwhile
            log.debug("closing %s failed", sid, exc_info=True)
        cut_websocket(environ)
        cut_websocket(upgraded)

    def login_arrived(self, sid: str) -> None:
        """The session's first Socket.IO CONNECT came. Checking it is the server's part, which under
        load may take longer than the deadline: the session is not cut for the server's own
        slowness while its check runs (up to CHECK_LIMIT_S). Only the first CONNECT counts, so
        CONNECTs sent again and again do not keep a session alive."""
        with self._lock:
            entry = self._pending.get(sid)
            if entry is not None and entry.checking_since is None and not entry.checked:
                entry.checking_since = time.monotonic()

    def login_checked(self, sid: str) -> None:
        """The server has answered that CONNECT: authorised (the reaper lets it go), or refused (it
        is closed at its deadline, or at once when that has passed)."""
        with self._lock:
            entry = self._pending.get(sid)
            if entry is not None and entry.checking_since is not None:
                entry.checking_since, entry.checked = None, True

    def _admit(self, client: str = "") -> str | None:
        """None when a new session may start, else why not (under self._lock)."""
        now = time.monotonic()
        self._tokens = min(self._burst, self._tokens + (now - self._refilled) * self._rate)
        self._refilled = now
        mine = sum(1 for entry in self._pending.values() if entry.client == client)
        if len(self._pending) >= self.max_pending:
            why = f"{len(self._pending)} Socket.IO sessions are waiting to log in, the limit"
        elif mine >= self.max_pending_per_client:
            # one address may not take every place: a neighbour's handshakes leave room for the editor's
            why = f"{client} has {mine} Socket.IO sessions waiting to log in, the limit for one client address"
        elif self._tokens < 1.0:
            why = f"more than {self._rate:g} new Socket.IO sessions a second"
        else:
            self._tokens -= 1.0
            return None
        self.refused += 1
        if self.refused in (1, 10, 100) or self.refused % 1000 == 0:
            log.warning("refused a Socket.IO session: %s (%d refused so far)", why, self.refused)
        return f"{why}; try again in a few seconds"

    @property
    def pending(self) -> int:
        with self._lock:
            return len(self._pending)

    def _ensure_reaper(self) -> None:
        # A thread only while sessions wait to log in: an idle webapp (and each test app) has none.
        if self._thread is None and not self._closed:
            self._thread = threading.Thread(target=self._reap, name="socket-auth-deadline", daemon=True)
            self._thread.start()

    def _reap(self) -> None:
        while True:
            time.sleep(min(0.5, self.auth_timeout_s / 4))
            now = time.monotonic()
            expired = []
            with self._lock:
                for sid, entry in list(self._pending.items()):
                    if entry.environ.get(AUTHORIZED_KEY):
                        del self._pending[sid]
                    elif now >= entry.deadline and not entry.checking(now):
                        del self._pending[sid]
                        expired.append((sid, entry.environ))
                if not self._pending or self._closed:
                    self._thread = None
                    stop = True
                else:
                    stop = False
            for sid, environ in expired:
                log.info("socket.io session %s did not log in within %.0f s; closed", sid, self.auth_timeout_s)
                self.close_session(sid, environ)
            if stop:
                return

    def close(self) -> None:
        with self._lock:
            self._closed = True


__all__ = ["AUTHORIZED_KEY", "SocketGuard", "cut_websocket", "mark_authorized"]
