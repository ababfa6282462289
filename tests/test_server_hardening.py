"""The webapp's server under a hostile neighbour on the same machine (no token needed for any of it):

- Socket.IO polling sessions closed by a bad POST (`6`, `0`, `2probe`, `9zzz`, an oversized payload)
  answer at once and leave no thread behind (python-engineio's close() used to wait for ever);
- deadlines: request headers, request bodies, the drain after an answer, the Socket.IO login;
- a cap on connections with a clear 503, where stalled requests make room for new clients;
- new unauthenticated Socket.IO sessions are limited in number and rate;
- a Host allowlist on every route and on the Socket.IO handshake (DNS rebinding), origins tied to it;
- the whole pattern set against a real `serve`: afterwards threads and descriptors come back to the
  baseline and health and inference answer in under 100 ms.
"""
from __future__ import annotations

import json
import socket
import threading
import time
from pathlib import Path

import pytest

from brain_fixtures import serve_a_copy
from hostile_clients import (BAD_POLL_BODIES, HostileRound, SocketIOClient, bad_poll_pair, fd_kinds, half_header_socket,
                             http_request, polling_handshake, process_counts, silent_websocket, wait_until)

OBS = [0.1, -0.2, 0.3, 0.0, 0.5, -0.4]  # brain_fixtures' fast_loop reads 6 observation values


def _settings(tmp_path, **env):
    from hope_models.settings import load_settings

    return load_settings(env={"HOPE_HOME": str(tmp_path / "home"), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": "",
                              **env})


class Served:
    """create_app on the real (guarded) HTTP server in this process."""

    def __init__(self, tmp_path, *, limits=None, socket_auth_timeout_s: float = 10.0, **env):
        from webapp import create_app
        from webapp.auth import load_or_create_token
        from webapp.server import HttpServer

        self.settings = _settings(tmp_path, **env)
        self.token = load_or_create_token(self.settings)
        self.app, self.socketio = create_app(self.settings, token=self.token,
                                             socket_auth_timeout_s=socket_auth_timeout_s)
        self.guard = self.app.extensions["hope"].socket_guard
        self.server = HttpServer(self.app, "127.0.0.1", 0, limits)
        self.server.start()
        self.port = self.server.port

    def close(self):
        self.server.stop()
        self.app.extensions["hope"].close()
        self.app.extensions["hope"].registry.close()


@pytest.fixture
def served(tmp_path):
    made = []

    def make(cls=None, **kwargs):
        s = (cls or Served)(tmp_path / f"s{len(made)}", **kwargs)
        made.append(s)
        return s

    yield make
    for s in made:
        s.close()


def _closed_by_server(sock: socket.socket, within: float) -> bool:
    """True when the server hangs up on `sock` within `within` seconds (EOF or reset)."""
    sock.settimeout(within)
    try:
        while True:
            data = sock.recv(65536)
            if not data:
                return True
    except (ConnectionResetError, BrokenPipeError):
        return True
    except socket.timeout:
        return False
    finally:
        sock.close()


# -- Engine.IO: closing a polling session never waits for the client ---------------------------------


def test_bad_polling_posts_are_answered_and_leave_no_thread(served):
    s = served()
    s.guard._rate = s.guard._burst = 1000.0  # this test is about close(), not the session rate limit
    s.server.strikes.to_ban = 0  # nor the ban an address earns by its bad packets (test_strikes.py)
    before = threading.active_count()
    for body in BAD_POLL_BODIES:
        for _ in range(6):
            started = time.monotonic()
            status = bad_poll_pair(s.port, body, timeout=3.0)
            assert status == 400, f"POST {body[:10]!r}: got {status} (0: no answer, the thread is stuck)"
            assert time.monotonic() - started < 2.0
    # only Engine.IO's ping sleepers (25 s) may still be there; no request thread is parked
    assert wait_until(lambda: s.server.open_connections == 0, 2)
    assert not s.socketio.server.eio.sockets, "closed sessions must be dropped at once"
    assert threading.active_count() - before <= len(BAD_POLL_BODIES) * 6 + 2


# -- deadlines ------------------------------------------------------------------------------------


def test_half_sent_headers_are_cut_at_the_header_deadline(served):
    from webapp.server import ConnectionLimits

    s = served(limits=ConnectionLimits(header_timeout_s=0.5))
    sock = half_header_socket(s.port)
    started = time.monotonic()
    assert _closed_by_server(sock, within=5.0)
    assert time.monotonic() - started < 2.0
    assert wait_until(lambda: s.server.open_connections == 0, 2)
    # a one-byte-at-a-time request line is cut too: the deadline is for all the headers, not per read
    sock = socket.create_connection(("127.0.0.1", s.port))
    started = time.monotonic()
    cut = False
    for ch in b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Drip: " + b"a" * 40:
        try:
            sock.send(bytes([ch]))
        except OSError:
            cut = True
            break
        time.sleep(0.1)
        if time.monotonic() - started > 3.0:
            break
    assert cut or _closed_by_server(sock, within=0.5), "a dripping client kept its connection past the deadline"
    assert time.monotonic() - started < 3.0


def test_a_body_that_never_arrives_is_cut_at_the_body_deadline(served):
    from webapp.server import ConnectionLimits

    s = served(limits=ConnectionLimits(body_timeout_s=0.5))
    sock = socket.create_connection(("127.0.0.1", s.port))
    sock.sendall(f"POST /api/brain/infer HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {s.token}\r\n"
                 "Content-Type: application/json\r\nContent-Length: 1000\r\n\r\n{\"obs".encode())
    started = time.monotonic()
    assert _closed_by_server(sock, within=5.0)
    assert time.monotonic() - started < 2.5
    assert wait_until(lambda: s.server.open_connections == 0, 2)


def _send_body_paced(port: int, token: str, total: int, chunk: int, every_s: float, give_up_s: float):
    """POST a multipart body of `total` bytes to the handoff route, `chunk` bytes every `every_s`.
    Returns (the status line or None when cut, seconds sent)."""
    boundary = "pacedboundary"
    head = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"manifest\"\r\n\r\n").encode()
    tail = f"\r\n--{boundary}--\r\n".encode()
    body = head + b"x" * (total - len(head) - len(tail)) + tail
    sock = socket.create_connection(("127.0.0.1", port))
    sock.sendall((f"POST /api/training/episode_handoff HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                  f"authorization: Bearer {token}\r\nContent-Type: multipart/form-data; boundary={boundary}\r\n"
                  f"Content-Length: {len(body)}\r\n\r\n").encode())
    started = time.monotonic()
    try:
        for i in range(0, len(body), chunk):
            sock.sendall(body[i:i + chunk])
            time.sleep(every_s)
            if time.monotonic() - started > give_up_s:
                break
        sock.settimeout(5)
        reply = sock.recv(4096)
    except (ConnectionResetError, BrokenPipeError, socket.timeout):
        reply = b""
    finally:
        sock.close()
    return (reply.split(b"\r\n", 1)[0].decode() if reply else None), time.monotonic() - started


def test_a_body_that_keeps_arriving_earns_its_time_and_a_trickle_does_not(served):
    from webapp.server import ConnectionLimits

    s = served(limits=ConnectionLimits(body_timeout_s=0.5, min_body_rate=64 << 10))
    # 400 kB at ~200 kB/s takes ~2 s, four times body_timeout_s: read to the end and answered
    status, took = _send_body_paced(s.port, s.token, 400_000, 20_000, 0.1, give_up_s=10)
    assert took > 1.5
    assert status is not None and status.startswith("HTTP/1.1 4"), status  # the view read it: a bad manifest
    # 100 bytes every 0.1 s earns nothing past the deadline
    status, took = _send_body_paced(s.port, s.token, 400_000, 100, 0.1, give_up_s=5)
    assert status is None, f"a trickling body was answered {status} instead of being cut"
    assert took < 4.0


def test_the_unread_rest_of_a_refused_body_is_not_waited_for(served):
    # the answer goes out before the body was read; the server then drains for 2 s at most
    s = served()
    sock = socket.create_connection(("127.0.0.1", s.port))
    sock.sendall(b"POST /api/runs HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                 b"Content-Length: 100000\r\n\r\n{")
    sock.settimeout(5)
    head = sock.recv(4096)
    assert head.startswith(b"HTTP/1.1 401")
    started = time.monotonic()
    assert _closed_by_server(sock, within=6.0)
    assert time.monotonic() - started < 4.0


def test_a_socket_io_session_must_log_in_before_its_deadline(served):
    # 1.5 s: a deadline a loaded CI box can open a session within (at 0.5 s the WebSocket's own
    # handshake, two test workers and chromium beside it, sometimes took longer)
    s = served(socket_auth_timeout_s=1.5)
    silent = silent_websocket(s.port)
    assert silent is not None
    refused = SocketIOClient(s.port, "not-the-token-at-all")
    assert not refused.connected and "unauthorized" in refused.connect_reply
    good = SocketIOClient(s.port, s.token)
    assert good.connected, good.connect_reply
    started = time.monotonic()
    assert _closed_by_server(silent, within=5.0)
    assert time.monotonic() - started < 3.0
    with pytest.raises(ConnectionError):
        refused.pump(3.0)  # a refused CONNECT does not keep the session either
    good.pump(4.5)  # the logged-in client stays, past three deadlines
    assert good.ws.connected
    assert wait_until(lambda: len(s.socketio.server.eio.sockets) == 1, 3)
    good.close()


def test_new_sessions_waiting_to_log_in_are_limited(served):
    s = served()
    s.guard.max_pending = 5
    s.guard._rate, s.guard._burst, s.guard._tokens = 0.001, 1000.0, 1000.0
    sids = [polling_handshake(s.port) for _ in range(8)]
    assert all(sids[:5]) and not any(sids[5:])
    status, body = http_request(s.port, "GET", "/socket.io/?EIO=4&transport=polling")
    assert status == 401 and b"waiting to log in" in body
    assert len(s.socketio.server.eio.sockets) == 5
    # and a rate: the burst is spent, the next handshakes are refused with the reason
    s.guard.max_pending, s.guard._tokens, s.guard._burst = 1000, 2.0, 2.0
    results = [polling_handshake(s.port) for _ in range(4)]
    assert sum(1 for r in results if r) == 2
    status, body = http_request(s.port, "GET", "/socket.io/?EIO=4&transport=polling")
    assert status == 401 and b"new Socket.IO sessions a second" in body


# -- the connection cap -----------------------------------------------------------------------------


def test_connections_over_the_cap_get_503_and_stalled_requests_make_room():
    from webapp.server import ConnectionLimits, HttpServer

    release = threading.Event()
    inside: list[int] = []  # requests the app is serving (their headers read)

    def app(environ, start_response):
        if environ["PATH_INFO"] == "/hold":
            inside.append(1)
            release.wait(10)
        start_response("200 OK", [("Content-Type", "application/json"), ("Content-Length", "2")])
        return [b"{}"]

    server = HttpServer(app, "127.0.0.1", 0, ConnectionLimits(max_connections=8))
    server.start()
    try:
        # stalled headers: a newcomer at the cap evicts the oldest of them and is served
        stalled = [half_header_socket(server.port) for _ in range(8)]
        assert wait_until(lambda: server.open_connections == 8, 2)
        assert http_request(server.port, "GET", "/ok") == (200, b"{}")
        assert _closed_by_server(stalled[0], within=2.0), "the oldest stalled request was not evicted"
        for sock in stalled[1:]:
            sock.close()
        assert wait_until(lambda: server.open_connections == 0, 3)
        # requests being served are never evicted: the newcomer is refused, with a reason
        holders = [threading.Thread(target=http_request, args=(server.port, "GET", "/hold"), kwargs={"timeout": 15})
                   for _ in range(8)]
        for t in holders:
            t.start()
        # all eight in the app, not merely accepted: one still sending its headers is a stalled
        # request to the server, which a newcomer at the cap may evict
        assert wait_until(lambda: len(inside) == 8 and server.open_connections == 8, 5)
        status, body = http_request(server.port, "GET", "/ok")
        assert status == 503
        assert "limit" in json.loads(body)["error"]
        assert server.refused_connections == 1
        release.set()
        for t in holders:
            t.join(15)
        assert http_request(server.port, "GET", "/ok") == (200, b"{}")
    finally:
        release.set()
        server.stop()


# -- the Host allowlist -----------------------------------------------------------------------------


def _concrete(rule) -> str:
    path = rule.rule
    for arg in rule.arguments:
        path = path.replace(f"<{arg}>", "x").replace(f"<path:{arg}>", "x")
        for conv in ("int", "string", "path"):
            path = path.replace(f"<{conv}:{arg}>", "1" if conv == "int" else "x")
    return path


def test_a_foreign_host_is_refused_on_every_route_and_the_socket_handshake(tmp_path):
    from webapp import create_app

    settings = _settings(tmp_path, HOPE_ALLOWED_HOSTS="robot.lan, 192.168.7.20")
    app, _sio = create_app(settings, token="t" * 32)
    client = app.test_client()
    auth = {"Authorization": "Bearer " + "t" * 32}
    paths = sorted({_concrete(r) for r in app.url_map.iter_rules()} | {"/socket.io/", "/no/such/page"})
    assert any(p.startswith("/api/") for p in paths) and "/" in paths
    for path in paths:
        for method in ("GET", "POST"):
            for host in ("evil.example", "evil.example:8765", "127.0.0.1.evil.example", "localhost.evil.example",
                         "10.9.8.7"):
                r = client.open(path + ("?EIO=4&transport=polling" if "socket.io" in path else ""), method=method,
                                headers={"Host": host, **auth})
                assert r.status_code == 421, (method, path, host, r.status_code)
                assert "allowed_hosts" in r.get_json()["error"]
    r = client.get("/api/health", headers={"Host": ""})
    assert r.status_code == 400
    for host in ("localhost", "localhost:8765", "127.0.0.1:1", "[::1]:8765", "robot.lan", "ROBOT.LAN:80",
                 "192.168.7.20:8765", "editor.localhost"):
        r = client.get("/api/health", headers={"Host": host})
        assert r.status_code == 200, host
    # the Socket.IO handshake from a browser: the Origin must be this allowed host:port
    ok = client.get("/socket.io/?EIO=4&transport=polling",
                    headers={"Host": "robot.lan:8765", "Origin": "http://robot.lan:8765"})
    assert ok.status_code == 200
    for origin in ("http://evil.example", "http://robot.lan:9999", "null", "file://"):
        r = client.get("/socket.io/?EIO=4&transport=polling", headers={"Host": "robot.lan:8765", "Origin": origin})
        assert r.status_code == 400, origin
    app.extensions["hope"].close()
    app.extensions["hope"].registry.close()


def test_the_real_server_refuses_a_foreign_host_and_websocket(served):
    s = served()
    status, body = http_request(s.port, "GET", "/api/health", headers={"Host": "evil.example"})
    assert status == 421 and b"allowed_hosts" in body
    status, _ = http_request(s.port, "GET", "/socket.io/?EIO=4&transport=polling", headers={"Host": "evil.example"})
    assert status == 421
    sock = socket.create_connection(("127.0.0.1", s.port), timeout=5)
    sock.sendall(b"GET /socket.io/?EIO=4&transport=websocket HTTP/1.1\r\nHost: evil.example\r\nUpgrade: websocket\r\n"
                 b"Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                 b"Sec-WebSocket-Version: 13\r\n\r\n")
    assert sock.recv(4096).startswith(b"HTTP/1.1 421")
    sock.close()


# -- the whole pattern set against a real serve ---------------------------------------------------------


# The registry's descriptors are a bounded cache, not a baseline: SQLAlchemy keeps up to 5 pooled
# connections per engine and opens up to 10 more under load (each one the database and its WAL),
# and SQLite's unix VFS keeps a closed connection's database file open, for reuse, while another
# connection of the process holds a lock on it. How many there are depends on how many requests
# overlapped, which a contended CPU decides; a leak of connections grows past any bound.
REGISTRY_FDS_MAX = 64


def _registry_fds(kinds: dict[str, int]) -> int:
    return sum(n for kind, n in kinds.items() if kind.startswith("hope.db"))


def _timed(fn) -> float:
    started = time.perf_counter()
    fn()
    return time.perf_counter() - started


@pytest.mark.slow
def test_a_real_serve_comes_back_to_its_baseline_after_the_hostile_patterns(tmp_path, tmp_path_factory):
    from daemon_fixtures import Home
    from test_cli_daemon import Serve

    # Engine.IO keeps each session's ping thread asleep for a ping interval after the session is gone
    # (25 s by default), so threads come back to the baseline only after one; 3 s here spares the two
    # waits below ~45 s without changing what is measured (the editor still answers every ping).
    # Every pattern comes from this test's one address and must reach the app (what they leave behind
    # is the point), so that address is never refused for its protocol errors (test_strikes.py).
    home = Home(tmp_path / "home", extra_env={"HOPE_SOCKETIO_PING_INTERVAL_S": "3", "HOPE_STRIKES_TO_BAN": "0"})
    serve_a_copy(home.path, tmp_path_factory)
    serve = Serve(home)
    try:
        port = int(serve.url.rstrip("/").rsplit(":", 1)[1])
        pid = serve.proc.pid
        auth = {"Authorization": f"Bearer {serve.token}", "Content-Type": "application/json"}
        infer_body = json.dumps({"component": "fast_loop", "observation": OBS}).encode()

        def health():
            assert http_request(port, "GET", "/api/health")[0] == 200

        def infer():
            status, body = http_request(port, "POST", "/api/brain/infer", body=infer_body, headers=auth)
            assert status == 200, body
            assert len(json.loads(body)["action"]) == 2

        assert wait_until(lambda: http_request(port, "POST", "/api/brain/infer", body=infer_body,
                                               headers=auth)[0] == 200, 20)
        # The baseline is a server that has seen this load once; its registry's descriptors are held
        # to their bound instead (REGISTRY_FDS_MAX). A leak would grow again with the measured round.
        editor = SocketIOClient(port, serve.token)
        assert editor.connected
        burst = [threading.Thread(target=lambda: [health() or infer() for _ in range(5)]) for _ in range(12)]
        for t in burst:
            t.start()
        for t in burst:
            t.join(30)
        first = process_counts(pid)
        HostileRound(port, pairs_per_body=60, half_headers=50, silent_websockets=100).run().release()
        assert wait_until(lambda: editor.pump(0.2) is not None and process_counts(pid)[0] <= first[0] + 5, 40,
                          step=0.3)
        base_threads, base_fds = process_counts(pid)
        base_kinds = fd_kinds(pid)
        base_others = base_fds - _registry_fds(base_kinds)

        attack = HostileRound(port, pairs_per_body=300, half_headers=50, silent_websockets=100).run()
        # every bad POST was answered (400) or its handshake refused (-1: the session limits); none hung (0)
        assert 0 not in attack.statuses, attack.statuses
        assert sum(attack.statuses.values()) == 300 * len(BAD_POLL_BODIES)
        assert len(attack.held) + attack.refused == 150
        editor.pump(0.5)  # the logged-in editor is still connected through all of it
        attack.release()

        def back_to_baseline():
            editor.pump(0.2)  # answers the server's pings meanwhile, as a browser does
            threads, fds = process_counts(pid)
            registry = _registry_fds(fd_kinds(pid))
            return threads <= base_threads + 10 and fds - registry <= base_others + 10 and registry <= REGISTRY_FDS_MAX

        ended = time.monotonic()
        assert wait_until(back_to_baseline, 30, step=0.5), (
            f"threads/fds {process_counts(pid)} vs baseline {(base_threads, base_fds)} 30 s after the attack; "
            f"descriptors {fd_kinds(pid)} vs {base_kinds}")
        assert time.monotonic() - ended <= 30
        health_s = sorted(_timed(health) for _ in range(5))[2]
        infer_s = sorted(_timed(infer) for _ in range(5))[2]
        assert health_s < 0.1 and infer_s < 0.1, (health_s, infer_s)
        editor.pump(0.2)
        editor.close()
    finally:
        serve.proc.kill()  # nothing here checks a clean stop (test_cli_daemon does); SIGTERM waits ~5 s
        home.close()


def test_the_socket_io_ping_interval_is_a_setting(served):
    # production keeps Engine.IO's 25 s; the real-serve test above shortens it through the environment
    assert served().socketio.server.eio.ping_interval == 25
    assert served(HOPE_SOCKETIO_PING_INTERVAL_S="3").socketio.server.eio.ping_interval == 3


def test_a_login_the_server_is_slow_to_check_is_not_cut_at_the_deadline(served):
    # Under load the thread that checks a CONNECT may start seconds after it arrived; the client
    # logged in in time, so it must not be cut for the server's slowness (a soak under attack once
    # dropped two editors that way).
    s = served(socket_auth_timeout_s=1.0)
    eio = s.socketio.server.eio
    inner = eio.handlers["message"]

    def slow_check(sid, data, *args):
        if isinstance(data, str) and data.startswith("0"):
            time.sleep(2.0)
        return inner(sid, data, *args)

    eio.on("message", slow_check)
    good = SocketIOClient(s.port, s.token)
    assert good.connected, good.connect_reply
    good.pump(2.5)  # past the deadline, twice
    assert good.ws.connected
    refused = SocketIOClient(s.port, "not-the-token-at-all")
    assert not refused.connected and "unauthorized" in refused.connect_reply
    with pytest.raises(ConnectionError):
        refused.pump(3.0)  # checked and refused after its deadline: closed at once
    good.close()


def test_one_address_holds_only_a_share_of_the_sessions_waiting_to_log_in(served):
    s = served()
    s.guard._rate, s.guard._burst, s.guard._tokens = 0.001, 1000.0, 1000.0
    share = s.guard.max_pending_per_client
    assert 1 <= share < s.guard.max_pending
    from hostile_clients import raw_request

    neighbour = [polling_handshake(s.port, source="127.0.0.2") for _ in range(share + 3)]
    assert all(neighbour[:share]) and not any(neighbour[share:])
    status, body = http_request(s.port, "GET", "/socket.io/?EIO=4&transport=polling", source="127.0.0.2")
    assert status == 401 and b"127.0.0.2 has" in body and b"one client address" in body, body
    assert raw_request(s.port, "GET", "/socket.io/?EIO=4&transport=polling") == 200  # the editor's address
    editor = SocketIOClient(s.port, s.token)
    assert editor.connected, editor.connect_reply
    editor.close()
