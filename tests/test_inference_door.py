"""The robot's inference has a door of its own, and the editor's listener is bounded per client
address and per Engine.IO session (webapp/inference_door.py, webapp/server.py, webapp/socket_guard.py):

- the inference port answers infer, GET /api/brain, ping and health, and nothing else;
- one long-poll GET per Engine.IO session: a second one is 400 at once and closes the session, which
  wakes the first; a long-poll is answered within its deadline;
- one client address at its cap does not stop another;
- against a real `serve`: the long-poll flood (a handshake, then 200 concurrent long-polls on its
  session id, re-sent as they return) leaves inference and ping on the inference port answering
  200 throughout, ping on the editor's port too, and threads and descriptors come back after it.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import socket
import sys
import threading
import time
from pathlib import Path

import pytest

from brain_fixtures import brain_runs, promote_pointer, serve_a_copy
from hostile_clients import LongPollFlood, _dechunk, http_request, polling_handshake, process_counts, raw_request, wait_until
from test_server_hardening import OBS, Served, served  # noqa: F401 - the fixture

POLL = "/socket.io/?EIO=4&transport=polling"


def _infer_body() -> bytes:
    return json.dumps({"component": "fast_loop", "observation": OBS}).encode()


def test_the_inference_port_serves_the_robots_routes_and_nothing_else(tmp_path, tmp_path_factory):
    from hope_models.runtime.brain_service import BrainService
    from hope_models.settings import load_settings
    from webapp import create_app
    from webapp.auth import load_or_create_token
    from webapp.inference_door import open_inference_door

    home = tmp_path / "home"
    settings = load_settings(env={"HOPE_HOME": str(home), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": "",
                                  "HOPE_INFERENCE_PORT": "0"})
    promote_pointer(home, brain_runs(tmp_path_factory)["alpha30"])
    token = load_or_create_token(settings)
    auth = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}
    with BrainService(home) as brain:
        brain.check_now()
        app, _ = create_app(settings, token=token, brain=brain)
        door = open_inference_door(app, settings)
        door.start()
        try:
            port = door.port
            status, body = http_request(port, "POST", "/api/brain/infer", body=_infer_body(), headers=auth)
            assert status == 200 and len(json.loads(body)["action"]) == 2, body
            assert http_request(port, "POST", "/api/brain/infer", body=_infer_body(),
                                headers={"Content-Type": "application/json"})[0] == 401
            assert http_request(port, "GET", "/api/brain", headers=auth)[0] == 200
            assert http_request(port, "GET", "/api/brain")[0] == 401
            status, body = http_request(port, "GET", "/api/ping")
            assert status == 200 and json.loads(body)["api"] == "hope-trainer"
            assert http_request(port, "GET", "/api/health")[0] == 200
            for path in (POLL, "/", "/api/runs", "/api/brain/promote", "/api/brain/rollback", "/static/js/app.js"):
                status, body = http_request(port, "GET", path, headers=auth)
                assert status == 404 and b"inference port" in body, (path, status)
            assert http_request(port, "POST", "/api/brain/promote", body=b"{}", headers=auth)[0] == 404
            assert http_request(port, "GET", "/api/brain/infer", headers=auth)[0] == 405
            status, _ = http_request(port, "GET", "/api/ping", headers={"Upgrade": "websocket", "Connection": "Upgrade"})
            assert status == 400
            assert http_request(port, "GET", "/api/ping", headers={"Host": "evil.example"})[0] == 421
        finally:
            door.stop()
            app.extensions["hope"].close()
            app.extensions["hope"].registry.close()


def _waiting_get(port: int, sid: str, source: str = "127.0.0.1") -> socket.socket:
    """A long-poll GET sent and left waiting for its answer."""
    s = socket.create_connection(("127.0.0.1", port), timeout=10, source_address=(source, 0))
    s.sendall(f"GET {POLL}&sid={sid} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n".encode())
    return s


def _answer_within(sock: socket.socket, seconds: float) -> bytes:
    """What the server answered on `sock` within `seconds` (b"" if nothing)."""
    sock.settimeout(seconds)
    raw = b""
    try:
        while True:
            data = sock.recv(65536)
            if not data:
                break
            raw += data
    except (socket.timeout, ConnectionResetError):
        pass
    finally:
        sock.close()
    return raw


def test_a_session_has_one_long_poll_at_a_time_answered_within_its_deadline(served):
    s = served()
    sid = polling_handshake(s.port)
    first = _waiting_get(s.port, sid)
    time.sleep(0.5)  # the first GET is waiting on the session's queue
    started = time.monotonic()
    status, body = http_request(s.port, "GET", f"{POLL}&sid={sid}", timeout=5.0)
    assert status == 400, f"a second concurrent long-poll on one session got {status} (0: it was left waiting)"
    assert time.monotonic() - started < 2.0
    answer = _answer_within(first, 3.0)
    head, _, body = answer.partition(b"\r\n\r\n")
    body = _dechunk(body) if b"chunked" in head.lower() else body
    assert head.startswith(b"HTTP/1.1 200") and body == b"1", answer  # the CLOSE packet
    assert sid not in s.socketio.server.eio.sockets
    assert http_request(s.port, "GET", f"{POLL}&sid={sid}")[0] == 400
    # a long-poll with nothing to say is answered at its deadline (a NOOP), and the session lives on
    s.guard.poll_deadline_s = 1.0
    sid = polling_handshake(s.port)
    started = time.monotonic()
    status, body = http_request(s.port, "GET", f"{POLL}&sid={sid}", timeout=10.0)
    assert status == 200 and body == b"6" and time.monotonic() - started < 4.0, (status, body)
    assert sid in s.socketio.server.eio.sockets


def _handshake_from(port: int, source: str) -> str | None:
    s = socket.create_connection(("127.0.0.1", port), timeout=5, source_address=(source, 0))
    s.sendall(f"GET {POLL} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n".encode())
    head, _, body = _answer_within(s, 5.0).partition(b"\r\n\r\n")
    body = _dechunk(body) if b"chunked" in head.lower() else body
    raw = head
    return json.loads(body[1:])["sid"] if raw.startswith(b"HTTP/1.1 200") and body.startswith(b"0") else None


def test_one_client_address_at_its_cap_does_not_stop_another(served):
    from webapp.server import ConnectionLimits, HttpServer

    s = served(HOPE_MAX_CONNECTIONS="24", HOPE_MAX_CONNECTIONS_PER_CLIENT="12")
    s.server.stop()  # the same app again, on a server built from these settings
    s.server = HttpServer(s.app, "127.0.0.1", 0, ConnectionLimits.from_settings(s.settings))
    s.server.start()
    s.port = s.server.port
    # long enough that none of the held GETs is answered before the checks below, on a loaded machine
    s.guard.poll_deadline_s = 15.0
    # 127.0.0.2 holds one long-poll on each of 12 sessions (its cap): all legitimate Engine.IO, each
    # read and waiting in the app (one still being read counts as stalled, and a newcomer at the cap
    # may take its place: the eviction rule of webapp/server.py). A handshake or a GET is refused
    # while the previous handshake's connection is still being closed: that one tries again.
    held = []
    deadline = time.monotonic() + 30
    while len(held) < 12 and time.monotonic() < deadline:
        sid = _handshake_from(s.port, "127.0.0.2")
        if sid is None:
            time.sleep(0.05)
            continue
        while time.monotonic() < deadline:
            sock = _waiting_get(s.port, sid, source="127.0.0.2")
            answer = _answer_within(sock, 0.5)
            if not answer:  # waiting, as a long-poll does
                held.append(sock)
                break
            assert b" 503 " in answer.split(b"\r\n", 1)[0], answer[:200]
            sock.close()
            time.sleep(0.05)
    assert len(held) == 12
    assert wait_until(lambda: s.guard.waiting_polls() == 12, 10), s.guard.waiting_polls()
    assert s.server.connections_of("127.0.0.2") == 12
    status, body = http_request(s.port, "GET", "/api/ping", host="127.0.0.1")
    assert status == 200, f"127.0.0.1 got {status} while 127.0.0.2 held its connections: {body[:200]!r}"
    assert raw_request(s.port, "GET", "/api/ping", source="127.0.0.2") == 503
    sock = socket.create_connection(("127.0.0.1", s.port), source_address=("127.0.0.2", 0))
    sock.sendall(b"GET /api/ping HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    assert b"client address" in _answer_within(sock, 3.0)
    assert s.server.open_connections <= 12 + 1
    for _ in range(5):
        assert http_request(s.port, "GET", "/api/ping")[0] == 200
    for sock in held:
        sock.close()
    # the waiting GETs end at their deadline even though nobody reads them
    assert wait_until(lambda: s.server.open_connections == 0, 20), s.server.open_connections


def _serve_with_door(home):
    from daemon_fixtures import Proc
    from daemon_fixtures import REPO

    log = home.path / "serve.log"
    home.logs.append(log)
    proc = Proc("serve", [sys.executable, str(REPO / "run_trainer.py"), "serve", "--port", "0", "--no-worker"],
                home.env, log)

    def banner():
        assert proc.alive(), log.read_text(errors="replace")
        text = log.read_text(errors="replace")
        editor = re.search(r"Robot Editor: http://127\.0\.0\.1:(\d+)/  token: (\S+)", text)
        door = re.search(r"inference: http://127\.0\.0\.1:(\d+)/", text)
        return editor and door and (int(editor.group(1)), editor.group(2), int(door.group(1)))

    found = wait_until(banner, 30, step=0.2)
    assert found, log.read_text(errors="replace")
    return proc, found


@pytest.mark.slow
def test_a_real_serve_answers_inference_through_the_long_poll_flood(tmp_path, tmp_path_factory):
    from daemon_fixtures import Home

    # Engine.IO's ping threads outlive their session by one ping interval: 3 s lets the counts
    # come back within this test's budget without changing what is measured.
    home = Home(tmp_path / "home", extra_env={"HOPE_SOCKETIO_PING_INTERVAL_S": "3"})
    serve_a_copy(home.path, tmp_path_factory)
    proc, (port, token, door) = _serve_with_door(home)
    auth = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}
    try:
        assert wait_until(lambda: http_request(door, "POST", "/api/brain/infer", body=_infer_body(),
                                               headers=auth)[0] == 200, 20)
        for _ in range(20):  # the baseline is a server that has answered on both ports
            http_request(port, "GET", "/api/ping")
            http_request(door, "POST", "/api/brain/infer", body=_infer_body(), headers=auth)
        base_threads, base_fds = process_counts(proc.popen.pid)
        flood = LongPollFlood(port, concurrency=200, refresh_s=8.0, source="127.0.0.2").start()
        failures, probes = [], 0
        try:
            end = time.monotonic() + 15.0
            while time.monotonic() < end:
                for name, p, method, path, body, headers in (
                        ("infer", door, "POST", "/api/brain/infer", _infer_body(), auth),
                        ("door ping", door, "GET", "/api/ping", b"", None),
                        ("editor ping", port, "GET", "/api/ping", b"", None)):
                    status, answer = http_request(p, method, path, body=body, headers=headers, timeout=10.0)
                    probes += 1
                    if status != 200:
                        failures.append((name, status, answer[:120]))
                time.sleep(0.2)
        finally:
            flood.stop()
        attempts = sum(flood.statuses.values())
        assert attempts > 200 and flood.handshakes >= 1, (flood.statuses, flood.handshakes)
        assert not failures, f"{len(failures)} of {probes} probes failed under the flood: {failures[:5]}"

        def back():
            threads, fds = process_counts(proc.popen.pid)
            return threads <= base_threads + 8 and fds <= base_fds + 8

        # the attacker's last sessions end at the 10 s login deadline, their ping sleepers 3 s later
        assert wait_until(back, 25, step=0.5), (process_counts(proc.popen.pid), (base_threads, base_fds))
    finally:
        proc.popen.kill()  # nothing here checks a clean stop (test_cli_daemon does)
        proc.popen.wait(10)
        home.close()


def test_infer_asks_the_inference_port_by_default(tmp_path, tmp_path_factory):
    """`infer` reaches the robot's door even when the editor's port is full."""
    import subprocess

    from daemon_fixtures import REPO
    from webapp.server import ConnectionLimits, HttpServer

    held_threads = threading.Event()

    def full(environ, start_response):
        held_threads.wait(20)
        start_response("503 Service Unavailable", [("Content-Length", "0")])
        return [b""]

    s = Served(tmp_path / "s", HOPE_INFERENCE_PORT="0")
    editor = HttpServer(full, "127.0.0.1", 0, ConnectionLimits())  # an editor port that never answers
    editor.start()
    try:
        from hope_models.runtime.brain_service import BrainService
        from webapp.inference_door import open_inference_door

        promote_pointer(s.settings.home, brain_runs(tmp_path_factory)["alpha30"])
        with BrainService(s.settings.home) as brain:
            brain.check_now()
            s.app.extensions["hope"].brain = brain
            door = open_inference_door(s.app, s.settings)
            door.start()
            env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
            env.update(HOPE_HOME=str(s.settings.home), HOPE_HOST="127.0.0.1", HOPE_PORT=str(editor.port),
                       HOPE_INFERENCE_PORT=str(door.port))
            try:
                proc = subprocess.run([sys.executable, str(REPO / "run_trainer.py"), "infer", "--observation",
                                       json.dumps(OBS), "--json", "--timeout", "10"], cwd=REPO, env=env,
                                      capture_output=True, text=True, timeout=60)
            finally:
                door.stop()
        assert proc.returncode == 0, proc.stderr
        assert json.loads(proc.stdout)["via"] == "http"
    finally:
        held_threads.set()
        editor.stop()
        s.close()


def test_the_door_and_the_per_address_cap_are_settings(tmp_path):
    from hope_models.settings import SettingsError, load_settings
    from webapp.server import ConnectionLimits

    home = str(tmp_path / "home")
    defaults = load_settings(env={"HOPE_HOME": home})
    assert defaults.inference_port == 8766 and defaults.inference_port != defaults.port
    assert ConnectionLimits.from_settings(defaults).max_per_client == 32
    s = load_settings(env={"HOPE_HOME": home, "HOPE_INFERENCE_PORT": "0", "HOPE_MAX_CONNECTIONS_PER_CLIENT": "5"})
    assert s.inference_port == 0 and ConnectionLimits.from_settings(s).max_per_client == 5
    for var, value in (("HOPE_INFERENCE_PORT", "-1"), ("HOPE_MAX_CONNECTIONS_PER_CLIENT", "1"),
                       ("HOPE_INFERENCE_PORT", "eighty")):
        with pytest.raises(SettingsError, match=var):
            load_settings(env={"HOPE_HOME": home, var: value})


def _unix_request(path: str, request: bytes) -> bytes:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(10)
    s.connect(path)
    s.sendall(request)
    return _answer_within(s, 10.0)


def test_the_door_on_a_unix_socket(tmp_path):
    import stat
    import tempfile

    from webapp.inference_door import open_inference_door

    short = Path(tempfile.mkdtemp(prefix="hope-door-"))  # a Unix socket path is at most 107 bytes
    s = Served(tmp_path / "s", HOPE_INFERENCE_PORT="0", HOPE_INFERENCE_SOCKET=str(short / "inference.sock"))
    try:
        door = open_inference_door(s.app, s.settings)
        door.start()
        path = str(short / "inference.sock")
        assert door.socket == path and stat.S_IMODE(os.stat(path).st_mode) == 0o600
        answer = _unix_request(path, b"GET /api/ping HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n")
        assert answer.startswith(b"HTTP/1.1 200") and b"hope-trainer" in answer, answer
        body = _infer_body()
        answer = _unix_request(path, (f"POST /api/brain/infer HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n"
                                      f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n\r\n").encode()
                               + body)
        assert answer.startswith(b"HTTP/1.1 401"), answer
        answer = _unix_request(path, f"GET {POLL} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n".encode())
        assert answer.startswith(b"HTTP/1.1 404"), answer
        door.stop()
        assert not os.path.exists(path)
        stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        stale.bind(path)  # a socket file a killed process left behind: the next start replaces it
        stale.close()
        door = open_inference_door(s.app, s.settings)
        door.start()
        assert _unix_request(path, b"GET /api/health HTTP/1.1\r\nHost: localhost\r\n\r\n").startswith(b"HTTP/1.1 200")
        door.stop()
    finally:
        s.close()
        shutil.rmtree(short, ignore_errors=True)
