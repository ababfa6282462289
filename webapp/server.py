"""The HTTP server for the webapp: Werkzeug's threaded WSGI server, bounded, in a background thread.

Flask-SocketIO's threading mode runs on it (WebSocket through simple-websocket). Werkzeug's server
gives every connection a thread and waits on it as long as the client likes, so a neighbour that
opens sockets and sends nothing (or half a request line) would take a thread each until the
process runs out of threads or descriptors. Here every connection lives under limits:

    accept --(cap reached, or this client address's cap?)-- yes --> "503 too many connections", closed
       |
       v  one thread per connection (as Werkzeug)
    headers  -- all of the request line and headers within `header_timeout_s`
       |
    body     -- the declared body read within `body_timeout_s` (or until the answer starts), plus one
       |        second for every `min_body_rate` bytes received: a large upload that keeps arriving
       |        at a walking pace (64 KiB/s) earns its time, a trickle is cut at body_timeout_s
       |
    app      -- no deadline: a long-poll GET waits for events, a view runs
       |        every socket read/write may stall at most `io_timeout_s`
    drain    -- after the answer, unread request bytes are discarded for `drain_timeout_s` at most
       |        (at the cap, the oldest connection still sending its request is dropped for a newcomer)
    websocket-- reads and writes may stall at most `ws_idle_timeout_s` (Engine.IO pings every 25 s);
                logging in within a deadline is Socket.IO's part (webapp/socket_guard.py)

A deadline is enforced by a reaper thread that shuts the socket down, which wakes the handler's
blocked read with EOF. We bind first and serve in a thread (rather than socketio.run(), which blocks
and cannot be stopped from outside) so that `serve` can stop it in order with the daemon and the
worker, and so port 0 (tests) reports the port it got.
"""
from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import socket
import stat
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from werkzeug.serving import ThreadedWSGIServer, WSGIRequestHandler, select_address_family

from webapp.request_phases import CONN_KEY, BodyReader, bounded_drain, has_body
from webapp.strikes import STRIKE_KEY, Strikes

if TYPE_CHECKING:
    from _typeshed.wsgi import WSGIApplication

    from hope_models.settings import Settings

log = logging.getLogger(__name__)


class ServerError(RuntimeError):
    """The server cannot start (the port is taken, the address is not local); the message says which."""


@dataclass(frozen=True)
class ConnectionLimits:
    max_connections: int = 200
    # one address's share: a neighbour holding long requests cannot take every connection (0 = no cap)
    max_per_client: int = 32
    header_timeout_s: float = 10.0
    body_timeout_s: float = 30.0
    io_timeout_s: float = 30.0
    ws_idle_timeout_s: float = 60.0  # > Engine.IO ping interval + ping timeout (25 + 20 s)
    drain_timeout_s: float = 2.0  # after the answer: reading what is left of an unread request body
    min_body_rate: int = 64 << 10  # bytes/s a body must average to be given time past body_timeout_s
    websockets: bool = True  # False: an Upgrade request is an ordinary one, under the ordinary deadlines
    strikes_to_ban: int = 20  # webapp/strikes.py; 0 = an address is never refused for its protocol errors

    @classmethod
    def from_settings(cls, settings: Settings) -> "ConnectionLimits":
        return cls(max_connections=int(getattr(settings, "max_connections", cls.max_connections)),
                   max_per_client=int(getattr(settings, "max_connections_per_client", cls.max_per_client)),
                   strikes_to_ban=int(getattr(settings, "strikes_to_ban", cls.strikes_to_ban)))


class _Connection:
    __slots__ = ("sock", "client", "phase", "deadline", "opened", "evicted")

    def __init__(self, sock, client: str, deadline: float):
        self.sock = sock
        self.client = client
        self.phase = "headers"
        self.deadline: float | None = deadline
        self.opened = time.monotonic()
        self.evicted = False

    def cut(self) -> None:
        try:
            self.sock.shutdown(socket.SHUT_RDWR)  # wakes the handler's blocked read with EOF
        except OSError:
            pass

    def enter(self, phase: str, deadline: float | None) -> None:
        self.phase, self.deadline = phase, deadline


# At the cap, a stalled request may be evicted for a new connection; the evicted ones take a moment
# to leave, so the count may pass the cap by this much before newcomers are refused outright.
EVICTION_SLACK = 32


def _client_key(client_address) -> str:
    """The address a connection counts against (an IPv4-mapped IPv6 address as its IPv4 one)."""
    host = client_address[0] if isinstance(client_address, tuple) and client_address else "local"
    return host[7:] if isinstance(host, str) and host.startswith("::ffff:") else str(host)


def http_url(host: str, port: int | None) -> str:
    """The URL a client on this machine uses for a listener bound to host:port (any-address -> loopback)."""
    if host in ("0.0.0.0", "::", ""):
        host = "127.0.0.1"
    if ":" in host:
        host = f"[{host}]"
    return f"http://{host}:{port}/"


def _refusal(why: str) -> bytes:
    body = json.dumps({"error": f"{why}; try again shortly"}).encode()
    head = ("HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\nRetry-After: 2\r\n"
            f"Connection: close\r\nContent-Length: {len(body)}\r\n\r\n").encode()
    return head + body


class GuardedRequestHandler(WSGIRequestHandler):
    """Werkzeug's handler with the socket timeout, and each request's connection put in its phase."""

    def setup(self):
        self.timeout = self.server.limits.io_timeout_s  # StreamRequestHandler applies it to the socket
        super().setup()

    def make_environ(self):
        environ = super().make_environ()
        conn = self.server.connection_of(self.connection)
        environ[CONN_KEY] = conn
        limits = self.server.limits
        if conn is not None:
            client, strikes = conn.client, self.server.strikes
            environ[STRIKE_KEY] = lambda why: strikes.strike(client, why)
            if limits.websockets and environ.get("HTTP_UPGRADE", "").lower() == "websocket":
                conn.enter("websocket", None)
                self.connection.settimeout(limits.ws_idle_timeout_s)
            elif has_body(environ):
                conn.enter("body", time.monotonic() + limits.body_timeout_s)
                environ["wsgi.input"] = BodyReader(environ["wsgi.input"], conn, environ, limits)
            else:
                conn.enter("app", None)
        return environ

    def log_error(self, format, *args):  # noqa: A002 - http.server's signature
        # "Request timed out" and friends from clients we cut off are not the service's errors.
        log.debug("http: " + format, *args)


class GuardedServer(ThreadedWSGIServer):
    """Werkzeug's threaded server under the limits: the connection cap (evicting a stalled request
    first), and a reaper thread that cuts a connection past its phase's deadline."""

    def __init__(self, host: str, port: int, app: WSGIApplication, *, limits: ConnectionLimits, **kwargs: Any):
        self.limits = limits
        self._conns: dict[int, _Connection] = {}
        self._conns_lock = threading.Lock()
        self.refused = 0
        self.strikes = Strikes(to_ban=limits.strikes_to_ban)  # addresses refused at accept for a while
        super().__init__(host, port, app, handler=GuardedRequestHandler, **kwargs)  # (calls server_close once)
        self._reaper_stop = threading.Event()
        self._reaper = threading.Thread(target=self._reap, name="http-deadlines", daemon=True)
        self._reaper.start()

    def connection_of(self, sock) -> _Connection | None:
        with self._conns_lock:
            return self._conns.get(id(sock))

    @property
    def open_connections(self) -> int:
        with self._conns_lock:
            return len(self._conns)

    def connections_of(self, client: str) -> int:
        with self._conns_lock:
            return sum(1 for c in self._conns.values() if c.client == client)

    def _admit(self, client: str) -> tuple[str | None, _Connection | None]:
        """(why a newcomer from `client` is refused, or None; the stalled connection to evict for it),
        under the lock. A client still sending its request after others have been served is the
        one to drop (slow-header floods), not the newcomer: the oldest such, from the same address
        when that address is at its own cap."""
        limits = self.limits
        ban = self.strikes.banned(client)
        if ban:
            return f"{client} kept sending requests no client sends; refused for {ban:.0f} s more", None
        mine = [c for c in self._conns.values() if c.client == client]  # a scan of at most max_connections + slack
        if limits.max_per_client and len(mine) >= limits.max_per_client:
            why = f"{client} has {len(mine)} connections open, the limit for one client address"
            pool, cap = mine, limits.max_per_client
        elif len(self._conns) >= limits.max_connections:
            why = f"the server has {limits.max_connections} connections open, its limit"
            pool, cap = list(self._conns.values()), limits.max_connections
        else:
            return None, None
        if len(pool) >= cap + EVICTION_SLACK:
            return why, None  # the evicted ones have not left yet
        stalled = [c for c in pool if c.phase in ("headers", "body") and not c.evicted]
        if not stalled:
            return why, None
        victim = min(stalled, key=lambda c: c.opened)
        victim.evicted = True
        return None, victim

    def process_request(self, request, client_address):
        client = _client_key(client_address)
        with self._conns_lock:
            why, victim = self._admit(client)
            if why is None:
                self._conns[id(request)] = _Connection(request, client,
                                                       time.monotonic() + self.limits.header_timeout_s)
        if victim is not None:
            victim.cut()
        if why is not None:
            self.refused += 1
            self._refuse(request, why)
            return
        try:
            super().process_request(request, client_address)
        except Exception:  # e.g. "can't start new thread": the connection must not stay counted
            self._forget(request)
            self.shutdown_request(request)
            raise

    def process_request_thread(self, request, client_address):
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._forget(request)

    def _forget(self, request) -> None:
        with self._conns_lock:
            self._conns.pop(id(request), None)

    def _refuse(self, request, why: str) -> None:
        # On the accepting thread: never block it. Read what the client already sent (so closing
        # does not reset the connection before it sees the answer), say why, close.
        try:
            request.setblocking(False)
            try:
                request.recv(65536)
            except OSError:
                pass
            request.send(_refusal(why))
        except OSError:
            pass
        if self.refused in (1, 10, 100) or self.refused % 1000 == 0:
            log.warning("refused a connection: %s (%d refused so far)", why, self.refused)
        self.shutdown_request(request)

    def _reap(self) -> None:
        while not self._reaper_stop.wait(0.25):
            now = time.monotonic()
            with self._conns_lock:
                late = [c for c in self._conns.values() if c.deadline is not None and now >= c.deadline]
            for conn in late:
                conn.deadline = None
                log.debug("http: closing a connection that overran its %s deadline", conn.phase)
                conn.cut()

    def server_close(self):
        stop = getattr(self, "_reaper_stop", None)
        if stop is not None:
            stop.set()
        super().server_close()


def _bind_unix(sock, path: str) -> None:
    """Bind a Unix socket at `path`, 0600: one a dead process left is replaced, a live one is not."""
    if os.path.exists(path):
        if not stat.S_ISSOCK(os.lstat(path).st_mode):
            raise OSError(errno.EEXIST, f"{path} exists and is not a socket")
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            probe.connect(path)
            raise OSError(errno.EADDRINUSE, "another process listens there")
        except (ConnectionRefusedError, FileNotFoundError):
            os.unlink(path)  # a stale socket file
        finally:
            probe.close()
    old = os.umask(0o177)
    try:
        sock.bind(path)
    finally:
        os.umask(old)


class HttpServer:
    def __init__(self, app, host: str, port: int, limits: ConnectionLimits | None = None, *,
                 name: str = "webapp", port_hint: str = "--port or HOPE_PORT"):
        # Werkzeug logs every request at INFO; keep the service logs about the service.
        logging.getLogger("werkzeug").setLevel(logging.WARNING)
        self.limits = limits or ConnectionLimits()
        # Bind here (werkzeug would print its own message and sys.exit on a taken port).
        family = select_address_family(host, port)
        unix_path = host[len("unix://"):] if host.startswith("unix://") else None
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            if unix_path is not None:
                _bind_unix(sock, unix_path)
                bound_port = 0
            else:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                sock.bind((host, port))
                bound_port = sock.getsockname()[1]
            sock.listen(128)
            self._server = GuardedServer(host, bound_port, bounded_drain(app, self.limits.drain_timeout_s),
                                         fd=sock.fileno(), limits=self.limits)
        except OSError as exc:
            where = host if unix_path is not None else f"{host}:{port}"
            raise ServerError(f"{name}: cannot listen on {where}: {exc.strerror or exc} "
                              f"(set another {'path' if unix_path is not None else 'port'} with {port_hint})") from None
        finally:
            sock.close()  # the server holds its own duplicate of the descriptor
        self.host = host
        self.port = bound_port
        self.name = name
        self.unix_path = unix_path
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        if self.unix_path is not None:
            return f"unix://{self.unix_path}"
        return http_url(self.host, self.port)

    @property
    def open_connections(self) -> int:
        return self._server.open_connections

    def connections_of(self, client: str) -> int:
        """Open connections from one client address (what its cap counts)."""
        return self._server.connections_of(client)

    @property
    def refused_connections(self) -> int:
        return self._server.refused

    @property
    def strikes(self) -> Strikes:
        return self._server.strikes

    def start(self) -> None:
        self._thread = threading.Thread(target=self._server.serve_forever, name=f"http-{self.name}", daemon=True)
        self._thread.start()
        log.info("%s listening on %s (at most %d connections, %d per client address)", self.name, self.url,
                 self.limits.max_connections, self.limits.max_per_client)

    def stop(self, timeout: float = 5.0) -> None:
        if self._thread is not None:  # shutdown() waits for serve_forever, which never ran otherwise
            self._server.shutdown()
        self._server.server_close()
        if self.unix_path is not None:
            with contextlib.suppress(OSError):
                os.unlink(self.unix_path)
        if self._thread is not None:
            self._thread.join(timeout)


__all__ = ["ConnectionLimits", "HttpServer", "ServerError"]
